"""Local similarity of two images taken through different filters (the matching cost of camera B's parallax).

Camera A and camera B see the scene through different filters, so a patch can be brighter than its
neighbour in A and darker in B.  Measured over a small window (``NCC_WINDOW_PX``) around each pixel:

- :class:`LocalLinearScore`: the multiple correlation coefficient of the regression of each of B's
  channels on A's channels within the window,

  .. math::  R_c = \\sqrt{c_c^{\\mathsf T}\\, \\Sigma_{AA}^{-1}\\, c_c \\,/\\, \\sigma^2_{B_c}},

  averaged over B's channels (0..1; the local linear model of the guided filter, He et al. 2013, used
  for cross-spectral matching as in Heo et al. 2011);
- :func:`local_ncc`: the normalised cross-correlation of one-channel images (the one-channel case of
  the score, up to its sign);
- :func:`matching_feature`: gradient magnitude of the square-rooted luminance, the feature the parallax
  sweep correlated before the local linear score replaced it.

References
----------
K. He, J. Sun, X. Tang, "Guided image filtering", IEEE TPAMI 35(6), 1397-1409, 2013.
Y. S. Heo, K. M. Lee, S. U. Lee, "Robust stereo matching using adaptive normalized cross-correlation",
IEEE TPAMI 33(4), 807-822, 2011.
"""

from __future__ import annotations

import cv2
import numpy as np

from omnispectral.imaging.similarity_kernel import compiled_score

__all__ = ["NCC_WINDOW_PX", "LocalLinearScore", "as_channels", "local_ncc", "matching_feature"]

#: Window (px) of the local similarity (and of the parallax sweep's per-pixel choice of depth).
NCC_WINDOW_PX = 11


def matching_feature(gray: np.ndarray) -> np.ndarray:
    """Gradient magnitude of the square-rooted luminance, ``|∇ sqrt(max(gray, 0))|`` (3 × 3 Sobel).

    The cameras see the scene through different filters, so a patch can be brighter than its neighbour in
    A and darker in B, but its edges are where they are in both; correlating edge strength is immune to
    such contrast reversals.  (The parallax sweep's first matching feature; :class:`LocalLinearScore`
    replaced it.)

    Parameters
    ----------
    gray
        ``(H, W)`` luminance.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 gradient magnitude (Sobel units of the square-rooted image).
    """
    s = np.sqrt(np.maximum(gray, 0)).astype(np.float32)
    gx = cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def local_ncc(a: np.ndarray, b: np.ndarray, window: int = NCC_WINDOW_PX) -> np.ndarray:
    """Normalised cross-correlation of ``a`` and ``b`` over a ``window`` box around each pixel (0 where flat).

    .. math::  \\mathrm{NCC} = \\frac{\\overline{ab} - \\bar a \\bar b}
               {\\sqrt{(\\overline{a^2} - \\bar a^2)(\\overline{b^2} - \\bar b^2)}}

    with box means over the window.

    Parameters
    ----------
    a, b
        ``(H, W)`` float32 images (same shape).
    window
        Side of the box (px).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 in ``[-1, 1]``; 0 where either window is flat (variance product below
        ``1e-6`` of ``a``'s mean variance).
    """
    k = (window, window)
    ma, mb = cv2.blur(a, k), cv2.blur(b, k)
    va = cv2.blur(a * a, k) - ma * ma
    vb = cv2.blur(b * b, k) - mb * mb
    cov = cv2.blur(a * b, k) - ma * mb
    den = np.sqrt(np.maximum(va, 0) * np.maximum(vb, 0))
    floor = np.float32(1e-6) * max(float(np.mean(np.maximum(va, 0))), 1e-12)
    return np.where(den > floor, cov / np.maximum(den, 1e-30), 0.0).astype(np.float32)


class LocalLinearScore:
    """How well B's channels are a linear function of A's channels within a window around each pixel.

    The cameras see the scene through different filters: within a small window, which holds a few
    materials, each of B's channels is close to a linear combination of A's three (a patch brighter than
    its neighbour in A can be darker in B, and a regression takes that in its stride), but only when the
    two images are aligned.  The score is the multiple correlation coefficient of that regression,
    ``R_c = sqrt(c_cᵀ Σ_AA⁻¹ c_c / σ²_Bc)`` with the window's covariance ``Σ_AA`` of A's channels and
    ``c_c`` of A's channels with B's channel ``c``, averaged over B's channels: 0..1, 1 for an exact
    linear relation, scale-free like a normalised cross-correlation (the one-channel case is |NCC|).
    The same local linear model underlies the guided filter (He et al. 2013); using it to match images
    taken through different filters is in the spirit of cross-spectral stereo (Heo et al. 2011).
    Correlating gradient magnitudes instead (:func:`matching_feature`, the parallax sweep's first
    version) doubles the frequency of a row of patches, so that a chart at 5 m matched itself 2 px off.

    Parameters
    ----------
    image_a
        Camera A's image, ``(H, W, C)`` or ``(H, W)`` (radiance, any scale: it is normalised by its median).
    window
        Side of the box window (px).
    ridge
        Ridge added to ``Σ_AA``, relative to its trace (keeps collinear or flat windows solvable).

    Notes
    -----
    Call :meth:`prepare_b` once on B's image, move the result (e.g. along the epipolar lines), then call
    the instance on it: ``score = LocalLinearScore(a); b0 = score.prepare_b(b); r = score(moved(b0))``.
    """

    def __init__(self, image_a: np.ndarray, window: int = NCC_WINDOW_PX, ridge: float = 1e-3):
        a = as_channels(image_a)
        self.k = (window, window)
        self.scale = 1.0 / max(float(np.median(np.abs(a))), 1e-30)  # numbers near 1 (HDR radiance in DN/s)
        a = self.centred(a * np.float32(self.scale))
        self.a = [np.ascontiguousarray(a[..., i]) for i in range(a.shape[-1])]
        n = len(self.a)
        mean = [cv2.blur(x, self.k) for x in self.a]
        cov = np.empty((*a.shape[:2], n, n), np.float32)
        for i in range(n):
            for j in range(i, n):
                cov[..., i, j] = cov[..., j, i] = cv2.blur(self.a[i] * self.a[j], self.k) - mean[i] * mean[j]
        trace = np.maximum(np.trace(cov, axis1=-2, axis2=-1), 0.0)
        # a ridge: windows where A's channels are (nearly) collinear or flat stay solvable
        cov += (ridge * trace + 1e-12)[..., None, None] * np.eye(n, dtype=np.float32)
        inv = _inverse_3x3(cov) if n == 3 else np.linalg.inv(cov.astype(np.float64)).astype(np.float32)
        self.mean_a = mean
        # the quadratic form cᵀ Σ⁻¹ c over the upper triangle, off-diagonal terms doubled
        self.form = [(i, j, np.ascontiguousarray(inv[..., i, j] * np.float32(1 if i == j else 2)))
                     for i in range(n) for j in range(i, n)]
        self.var_floor = np.float32(1e-6 * max(float(np.mean(trace)) / n, 1e-24))

    def centred(self, image: np.ndarray) -> np.ndarray:
        """``image`` minus its local (box) mean.

        The window statistics are then formed from small numbers, which float32 holds without cancellation
        next to the HDR sun (a window's covariances change only by the small variation of the local mean
        across it).

        Parameters
        ----------
        image
            ``(H, W, C)`` float32.

        Returns
        -------
        numpy.ndarray
            ``(H, W, C)`` float32.
        """
        return (image - _blur3(image, self.k)).astype(np.float32, copy=False)

    def prepare_b(self, image_b: np.ndarray) -> np.ndarray:
        """B's image as the score expects it: scaled like A and centred, once, before the levels move it.

        Parameters
        ----------
        image_b
            Camera B's image on A's grid, ``(H, W, C)`` or ``(H, W)``.

        Returns
        -------
        numpy.ndarray
            ``(H, W, C)`` float32.
        """
        return self.centred(as_channels(image_b) * np.float32(self.scale))

    def __call__(self, moved_b: np.ndarray) -> np.ndarray:
        """The score of B (:meth:`prepare_b`-ed, then moved) against A at every pixel.

        B's channels are filtered together (one box filter call per statistic for up to four channels).

        Parameters
        ----------
        moved_b
            ``(H, W, C)`` or ``(H, W)`` float32, the output of :meth:`prepare_b` resampled as wanted.

        Returns
        -------
        numpy.ndarray
            ``(H, W)`` float32 in ``[0, 1]`` (0 where B's window is flat).
        """
        b = moved_b if moved_b.ndim == 3 else moved_b[..., None]
        if b.shape[-1] > 4:  # OpenCV filters at most four channels at once
            return np.mean([self(b[..., k]) for k in range(b.shape[-1])], axis=0).astype(np.float32)
        b = np.ascontiguousarray(b)
        kernels = compiled_score() if len(self.a) == 3 and b.shape[-1] == 3 else None
        if kernels is not None:
            return self._compiled(kernels, b)
        mb = _blur3(b, self.k)
        var_b = _blur3(b * b, self.k) - mb * mb
        cross = [_blur3(self.a[i][..., None] * b, self.k) - self.mean_a[i][..., None] * mb for i in range(len(self.a))]
        explained = np.zeros_like(var_b)
        for i, j, coef in self.form:
            explained += coef[..., None] * cross[i] * cross[j]
        ok = var_b > self.var_floor
        r = np.where(ok, np.sqrt(np.clip(explained / np.where(ok, var_b, 1.0), 0.0, 1.0)), 0.0)
        # the mean over B's channels, summed in order as np.mean does for so few (a strided reduction over the
        # last axis costs a third of the score)
        total = r[..., 0].copy()
        for c in range(1, r.shape[-1]):
            total += r[..., c]
        return (total / np.float32(r.shape[-1])).astype(np.float32)

    def _compiled(self, kernels, b: np.ndarray) -> np.ndarray:
        """:meth:`__call__` for three channels on each side: the same operations, fused between the box filters
        (:mod:`omnispectral.imaging.similarity_kernel`)."""
        products = [np.empty_like(b) for _ in range(4)]
        kernels.window_products(*self.a, b, *products)
        mb = _blur3(b, self.k)
        bb, ab0, ab1, ab2 = (_blur3(x, self.k) for x in products)
        out = np.empty(b.shape[:2], np.float32)
        kernels.score_from_moments(mb, bb, ab0, ab1, ab2, *self.mean_a, *(coef for _, _, coef in self.form),
                                   self.var_floor, out)
        return out


def _blur3(x: np.ndarray, k: tuple[int, int]) -> np.ndarray:
    """Box filter of ``(H, W, C)`` keeping the channel axis (OpenCV drops it for one channel)."""
    return cv2.blur(x, k).reshape(x.shape)


def _inverse_3x3(m: np.ndarray) -> np.ndarray:
    """Inverses of symmetric 3 × 3 matrices ``(..., 3, 3)`` by their adjugate (float32; a batched LAPACK
    inverse costs ten times as much at this size)."""
    a, b, c = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    d, e, f = m[..., 1, 1], m[..., 1, 2], m[..., 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * c00 + b * c01 + c * c02
    inv_det = np.where(det != 0, 1.0 / np.where(det != 0, det, 1.0), 0.0).astype(np.float32)
    out = np.empty(m.shape, np.float32)
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = c00 * inv_det, c01 * inv_det, c02 * inv_det
    out[..., 1, 1], out[..., 1, 2] = (a * f - c * c) * inv_det, (b * c - a * e) * inv_det
    out[..., 2, 2] = (a * d - b * b) * inv_det
    out[..., 1, 0], out[..., 2, 0], out[..., 2, 1] = out[..., 0, 1], out[..., 0, 2], out[..., 1, 2]
    return out


def as_channels(image: np.ndarray) -> np.ndarray:
    """An image as ``(H, W, C)`` float32 with no NaN or infinity.

    Parameters
    ----------
    image
        ``(H, W)`` or ``(H, W, C)`` image.

    Returns
    -------
    numpy.ndarray
        ``(H, W, C)`` float32 (``C = 1`` for a 2-D input); NaN and ±infinity replaced by 0.
    """
    img = np.asarray(image, dtype=np.float32)
    return np.nan_to_num(img if img.ndim == 3 else img[..., None], nan=0.0, posinf=0.0, neginf=0.0)
