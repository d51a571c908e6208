"""Blending of overlapping directions: the paper's linear blending and optional multi-band blending.

Linear blending (paper Sec. 4.5: "the overlapping regions between the neighboring images are
blended linearly"; feathering in Szeliski, "Image alignment and stitching: a tutorial", 2006,
Sec. 6.3.2).  Each source pixel gets the weight

    ``w(u, v) = (1 - |2 (u + 1/2) / W - 1|) · (1 - |2 (v + 1/2) / H - 1|)``,

a tent in each sensor axis: 1 at the image centre, falling linearly to 0 at the image border
(``u = -1/2`` and ``u = W - 1/2`` with pixel centres at integers).  The output is
``Σ w_i x_i / Σ w_i``, a convex combination per pixel: where the overlapping sources agree, the
panorama has their value exactly (up to float rounding), so radiometry is kept.  Weights reach
zero at the border, so seams are continuous.

Multi-band blending (Burt & Adelson, "A multiresolution spline with application to image mosaics",
ACM TOG 2(4), 1983; as in Brown & Lowe, IJCV 74(1), 2007, Sec. 7): every source is split into
Laplacian-pyramid bands; band ``k`` is blended with the Gaussian-pyramid level ``k`` of a seam
mask (each pixel to the source with the largest feathering weight), so low frequencies mix over
wide regions and fine detail switches sharply at the seam.  Outside its coverage a source is
filled with the linear blend, so identical overlaps still give identical values (all pyramids
agree) and no dark halo leaks in from uncovered areas.  It runs per output tile on a halo of
``4 · 2^levels`` pixels, in linear radiance; negative ringing is clipped to 0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from omnispectral.choices import BLEND_NAMES, DEFAULT_MULTIBAND_LEVELS, method_from
from omnispectral.mosaic.kernels import compiled_kernels

__all__ = ["BLENDS", "CONSISTENCY_TOL", "DEFAULT_MULTIBAND_LEVELS", "PAIR_RATIO", "Blend", "LinearBlend",
           "blend_method", "collapse", "feather_weight", "gaussian_pyramid", "laplacian_pyramid", "multiband_blend",
           "multiband_halo_px", "reject_inconsistent", "seam_masks", "settle_pairs"]


def feather_weight(u: np.ndarray, v: np.ndarray, width: int, height: int) -> np.ndarray:
    """Linear-blending weight (module docstring) of sensor positions; 0 outside the image and for NaN.

    float32 arithmetic for float32 positions (the engine's maps), float64 otherwise.
    """
    ft = np.float32 if np.result_type(u, v) == np.float32 else np.float64
    kernels = compiled_kernels()
    if ft is np.float32 and kernels is not None and np.shape(u) == np.shape(v) and np.ndim(u) == 2:
        out = np.empty(np.shape(u), np.float32)
        kernels.feather(u, v, ft(2.0 / width), ft(2.0 / height), out)
        return out
    one, half = ft(1.0), ft(0.5)
    with np.errstate(invalid="ignore"):
        wu = one - np.abs(ft(2.0 / width) * (u + half) - one)
        wv = one - np.abs(ft(2.0 / height) * (v + half) - one)
        w = np.clip(wu, 0.0, 1.0) * np.clip(wv, 0.0, 1.0)
    return np.nan_to_num(w, nan=0.0).astype(np.float32, copy=False)


class LinearBlend:
    """Accumulates ``Σ w x`` and ``Σ w`` over sources for an ``(h, w)`` tile with ``n_bands`` bands.

    The sums run in a compiled loop (Numba) when available: the same float32 products and sums as
    the NumPy expressions (bit for bit), without NumPy's slow broadcast over a 3-long last axis.

    Parameters
    ----------
    shape : tuple of int
        The tile's ``(h, w)`` in output pixels.
    n_bands : int
        Bands of the output (e.g. 6: camera A's three, then camera B's).

    Attributes
    ----------
    numerator : numpy.ndarray
        ``(h, w, n_bands)`` float32, ``Σ w x`` (in the sources' radiance units).
    denominator : dict
        ``Σ w`` per group of bands that the sources added together: tuple of band indices → ``(h, w)`` float32
        (each camera's sources carry their own weights).
    shape : tuple of int
        ``(h, w)``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.5 (the overlapping regions are blended linearly), Fig. 8.
    .. [2] R. Szeliski, "Image alignment and stitching: a tutorial", 2006, Sec. 6.3.2 (feathering).
    """

    def __init__(self, shape: tuple[int, int], n_bands: int):
        self.numerator = np.zeros((*shape, n_bands), np.float32)
        self.denominator = {}
        self.shape = shape

    def add(self, bands: tuple[int, ...], row0: int, col0: int, values: np.ndarray, weight: np.ndarray) -> None:
        """Add a source's values ``(h_s, w_s, len(bands))`` and weights ``(h_s, w_s)`` at ``(row0, col0)``."""
        den = self.denominator.setdefault(bands, np.zeros(self.shape, np.float32))
        kernels = compiled_kernels()
        if kernels is not None and values.dtype == np.float32 and weight.dtype == np.float32 \
                and 0 <= row0 and row0 + weight.shape[0] <= self.shape[0] \
                and 0 <= col0 and col0 + weight.shape[1] <= self.shape[1]:
            kernels.accumulate(self.numerator, den, row0, col0, bands[0], values, weight)
            return
        rows = slice(row0, row0 + weight.shape[0])
        cols = slice(col0, col0 + weight.shape[1])
        b = slice(bands[0], bands[-1] + 1)
        self.numerator[rows, cols, b] += weight[..., None] * values
        den[rows, cols] += weight

    def result(self, fill: float = np.nan) -> np.ndarray:
        """``Σ w x / Σ w``; ``fill`` where no source covers a pixel."""
        out = np.full(self.numerator.shape, fill, np.float32)
        kernels = compiled_kernels()
        for bands, den in self.denominator.items():
            if kernels is not None:
                kernels.divide(self.numerator, den, bands[0], len(bands), out)
                continue
            b = slice(bands[0], bands[-1] + 1)
            covered = den > 0
            out[covered, b] = self.numerator[covered, b] / den[covered, None]
        return out


#: Relative difference (sum over the camera's bands) beyond which two sources see different surfaces.
CONSISTENCY_TOL = 0.1


def reject_inconsistent(values: list[np.ndarray], weights: list[np.ndarray], offsets: list[tuple[int, int]],
                        shape: tuple[int, int], tol: float = CONSISTENCY_TOL,
                        expected: np.ndarray | None = None) -> list[np.ndarray]:
    """Weights with the sources that disagree with the majority set to 0, pixel by pixel.

    ``values[i]`` ``(h_i, w_i, c)`` and ``weights[i]`` ``(h_i, w_i)`` lie at ``offsets[i]`` (row, col) of
    an ``shape`` tile; all see the same bands.  Where three or more sources cover a pixel (each with at
    least 10⁻³ of the largest weight there: an occluded view does not vote), the reference is the median
    of their band sums, and a source more than ``tol`` (relative) from it is dropped there: a pixel takes
    its value from the views that agree and does not average two surfaces (one direction's registration
    putting the background where the others see a chart patch).  The median is not weighted: the wrong
    view can be the most confident one (a chart's corner matched on its background with NCC 0.92 while
    two of three right views sit at their image's edge).  Two disagreeing sources are left as they are:
    nothing among them says which is right, unless camera A's ``expected (h, w)`` band sum for these sources is
    given: then two that see two surfaces are settled by it (:func:`settle_pairs`, on what the median vote
    left), and of two that differ less, one whose values step across an edge that A and the other view do not
    show is dropped (:func:`edge_beside_flat`).  Returns new weight arrays, same shapes as ``weights``.
    """
    n = len(values)
    if n < (3 if expected is None else 2):
        return [np.asarray(w) for w in weights]
    s, wt = _vote_arrays(values, weights, offsets, shape)
    disagree = _median_disagreement(s, wt, tol) if n >= 3 else None
    if expected is not None:
        kept = wt if disagree is None else np.where(disagree, np.float32(0.0), wt)
        for settle in (_pair_disagreement, edge_beside_flat):
            pairs = settle(s, kept, expected)
            if pairs is not None:
                disagree = pairs if disagree is None else disagree | pairs
                kept = np.where(pairs, np.float32(0.0), kept)
    return [np.asarray(x) for x in weights] if disagree is None else _without(weights, offsets, disagree)


def _median_disagreement(s: np.ndarray, wt: np.ndarray, tol: float) -> np.ndarray | None:
    """``(n, h, w)`` the votes more than ``tol`` from the median where three or more vote
    (:func:`reject_inconsistent`), None where none is."""
    disagree = np.zeros(s.shape, bool)
    kernels = compiled_kernels()
    if kernels is not None:  # the same median and comparisons in one pass
        return disagree if kernels.disagreeing(s, wt, np.float32(tol), disagree) else None
    voting = (wt > np.float32(1e-3) * wt.max(axis=0, keepdims=True)) & np.isfinite(s)
    several = voting.sum(axis=0) >= 3
    if not several.any():
        return None
    with np.errstate(all="ignore"):
        ref = np.nanmedian(np.where(voting, s, np.nan)[:, several], axis=0)
    disagree[:, several] = np.abs(s[:, several] - ref) > np.float32(tol) * np.abs(ref)
    return disagree


#: Two views of a pixel whose band sums differ by more than this factor see two surfaces, not one surface at two
#: sampling phases (:func:`settle_pairs`).
PAIR_RATIO = 2.0


def settle_pairs(values: list[np.ndarray], weights: list[np.ndarray], offsets: list[tuple[int, int]],
                 shape: tuple[int, int], expected: np.ndarray) -> list[np.ndarray]:
    """Weights with, where exactly two sources vote at a pixel and see two surfaces, the one farther from
    ``expected`` set to 0.

    Two disagreeing sources do not outvote each other in the median vote.  When their band sums differ by more
    than :data:`PAIR_RATIO` they do not sample one surface at two phases but two surfaces: one direction's
    camera B sees the surface camera A sees, the other sees a near object in front of it (a post beside the low
    sun hides the sky from B's viewpoint in one direction; that view's B was 1/140 of the other's, and their
    blend read the sky 26 % dark).  ``expected (h, w)`` is the band sum A's bands predict for these sources
    (the prior's linear predictor), NaN where unknown; the source whose ``|log(sum / expected)|`` is larger by
    more than ``log PAIR_RATIO`` is dropped (the prediction can be twice off for a saturated colour: a blue
    post's two views, itself and the ground behind it, are then left to their blend).  Voters as in
    :func:`reject_inconsistent`; a pixel with another count of voters, or an unknown expectation, is left as
    it is.  Returns new weight arrays, same shapes as ``weights``; :func:`reject_inconsistent` applies it with
    its ``expected``."""
    if len(values) < 2:
        return [np.asarray(w) for w in weights]
    dropped = _pair_disagreement(*_vote_arrays(values, weights, offsets, shape), expected)
    return [np.asarray(x) for x in weights] if dropped is None else _without(weights, offsets, dropped)


def _two_voters(s: np.ndarray, wt: np.ndarray, expected: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixels where exactly two sources vote (as in :func:`reject_inconsistent`) and ``expected`` is known:
    ``(rows, cols, voting (n, k), votes (n, k))``, the votes NaN where a source does not vote."""
    with np.errstate(invalid="ignore"):
        voting = (wt > np.float32(1e-3) * wt.max(axis=0, keepdims=True)) & (s > 0)
        ys, xs = np.nonzero((voting.sum(axis=0) == 2) & (np.asarray(expected) > 0))
    at = voting[:, ys, xs]
    return ys, xs, at, np.where(at, s[:, ys, xs], np.float32(np.nan))


def _at_pixels(shape: tuple[int, ...], ys: np.ndarray, xs: np.ndarray, drop: np.ndarray) -> np.ndarray | None:
    """``(n, h, w)`` bool, ``drop (n, k)`` at pixels ``ys, xs``; None where nothing is dropped."""
    if not drop.any():
        return None
    out = np.zeros(shape, bool)
    out[:, ys, xs] = drop
    return out


def _pair_disagreement(s: np.ndarray, wt: np.ndarray, expected: np.ndarray) -> np.ndarray | None:
    """``(n, h, w)`` the sources :func:`settle_pairs` drops, None where none is."""
    ys, xs, voting, votes = _two_voters(s, wt, expected)
    if ys.size == 0:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        apart = np.nanmax(votes, axis=0) > np.float32(PAIR_RATIO) * np.nanmin(votes, axis=0)
        if not apart.any():
            return None
        exp = np.asarray(expected, np.float32)[ys, xs]
        distance = np.where(voting & apart, np.abs(np.log(votes / exp)), -np.inf)
    nearer = np.where(np.isfinite(distance), distance, np.inf).min(axis=0, keepdims=True)
    # dropped only when A's expectation is decisive: the farther source at least PAIR_RATIO farther (a saturated
    # colour's expectation can be twice off, and a blend of the two is then the safer value)
    return _at_pixels(s.shape, ys, xs, np.isfinite(distance) & (distance > nearer + np.float32(np.log(PAIR_RATIO))))


#: Two views of a pixel this far apart (band sums) whose one changes by more than :data:`EDGE_STEP` to a
#: 4-neighbour where the other changes by less than :data:`FLAT_STEP` and A's expectation by less than
#: :data:`A_FLAT_STEP`: the first one's sample reached across an edge that is not there
#: (:func:`edge_beside_flat`; A's expectation, a linear prediction, moves up to 16 % between neighbours of a
#: smooth blue sky).
EDGE_PAIR_RATIO = 1.15
EDGE_STEP = 1.5
FLAT_STEP = 1.1
A_FLAT_STEP = 1.25


def edge_beside_flat(s: np.ndarray, wt: np.ndarray, expected: np.ndarray) -> np.ndarray | None:
    """``(n, h, w)`` the sources to drop where exactly two vote, their band sums ``s (n, h, w)`` differ by more
    than :data:`EDGE_PAIR_RATIO`, and one of them steps by more than :data:`EDGE_STEP` to one of its
    4-neighbours while the other steps by less than :data:`FLAT_STEP` to every one, and A's ``expected (h, w)``
    band sum by less than :data:`A_FLAT_STEP`; None where there are none.

    A view whose interpolation kernel reaches across an edge in its own frame (another surface in front of the
    one A sees, half a pixel beyond the sample: the post by the low sun, in one of two B views of the sky
    beside it) reads a blend of the two surfaces, 20–30 % off, where A and the other view see one flat
    surface: too little apart for :data:`PAIR_RATIO`, and the blend of the two views kept a third of that error
    over 16 rows.  The step shows in the view's own values beside the pixel, which its neighbours' samples
    carry across the edge.  Voters as in :func:`reject_inconsistent`."""
    ys, xs, voting, votes = _two_voters(s, wt, expected)
    if ys.size == 0:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):
        apart = np.nanmax(votes, axis=0) > np.float32(EDGE_PAIR_RATIO) * np.nanmin(votes, axis=0)
    ys, xs, voting = ys[apart], xs[apart], voting[:, apart]
    if ys.size == 0:
        return None
    n, h, w = s.shape
    exp = np.asarray(expected, np.float32)
    steps = np.zeros((n, ys.size))
    step_a = np.zeros(ys.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        here = np.where(voting, np.log(s[:, ys, xs].astype(np.float64)), np.nan)
        a_here = np.log(exp[ys, xs].astype(np.float64))
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            yy, xx = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            # the view's own value beside the pixel, voting there or not (dropped beside the edge it reached)
            there = np.log(s[:, yy, xx].astype(np.float64))
            steps = np.fmax(steps, np.abs(there - here))
            a_there = exp[yy, xx].astype(np.float64)
            step_a = np.fmax(step_a, np.where(a_there > 0, np.abs(np.log(a_there) - a_here), np.nan))
    voters = np.isfinite(here)
    steps = np.where(voters, steps, 0.0)
    other = np.where(voters, steps.sum(axis=0) - steps, np.inf)  # the other voter's step (two voters)
    drop = voters & (steps > np.log(EDGE_STEP)) & (other < np.log(FLAT_STEP)) & (step_a < np.log(A_FLAT_STEP))
    return _at_pixels(s.shape, ys, xs, drop)


def _vote_arrays(values: list[np.ndarray], weights: list[np.ndarray], offsets: list[tuple[int, int]],
                 shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """``(n, h, w)`` band sums (NaN where a source has no weight) and weights (0 where its sum is not finite)
    of the sources on the ``shape`` tile."""
    n, (h, w) = len(values), shape
    s = np.full((n, h, w), np.nan, np.float32)
    wt = np.zeros((n, h, w), np.float32)
    for i, (v, wi, (r, c)) in enumerate(zip(values, weights, offsets, strict=True)):
        # the band sum as element-wise additions (NumPy's reduction over a 3-long last axis is ~5x slower; the
        # same float32 additions in the same order); it is finite exactly where every band is
        total = v[..., 0].copy()
        for k in range(1, v.shape[-1]):
            total += v[..., k]
        s[i, r:r + wi.shape[0], c:c + wi.shape[1]] = np.where(wi > 0, total, np.nan)
        wt[i, r:r + wi.shape[0], c:c + wi.shape[1]] = np.where(np.isfinite(total), wi, 0.0)
    return s, wt


def _without(weights: list[np.ndarray], offsets: list[tuple[int, int]], dropped: np.ndarray) -> list[np.ndarray]:
    """The ``weights`` with 0 where ``dropped (n, h, w)`` (tile coordinates) says so."""
    out = []
    for i, (wi, (r, c)) in enumerate(zip(weights, offsets, strict=True)):
        d = dropped[i, r:r + wi.shape[0], c:c + wi.shape[1]]
        out.append(np.where(d, 0.0, wi).astype(np.float32))
    return out


# ------------------------------------------------------------------------------------------ multi-band
def _down(img: np.ndarray) -> np.ndarray:
    return cv2.pyrDown(img, borderType=cv2.BORDER_REFLECT101)


def _up(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    return cv2.pyrUp(img, dstsize=(shape[1], shape[0]), borderType=cv2.BORDER_REFLECT101)


def gaussian_pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    pyr = [img]
    for _ in range(levels):
        pyr.append(_down(pyr[-1]))
    return pyr


def laplacian_pyramid(img: np.ndarray, levels: int) -> list[np.ndarray]:
    g = gaussian_pyramid(img, levels)
    return [g[k] - _up(g[k + 1], g[k].shape[:2]) for k in range(levels)] + [g[levels]]


def collapse(pyr: list[np.ndarray]) -> np.ndarray:
    img = pyr[-1]
    for band in reversed(pyr[:-1]):
        img = band + _up(img, band.shape[:2])
    return img


def seam_masks(weights: list[np.ndarray]) -> list[np.ndarray]:
    """Each pixel to the source with the largest weight (first on ties); float32 0/1 masks."""
    stack = np.stack(weights)
    best = np.argmax(stack, axis=0)
    covered = stack.max(axis=0) > 0
    return [((best == i) & covered).astype(np.float32) for i in range(len(weights))]


def multiband_blend(values: list[np.ndarray], weights: list[np.ndarray], levels: int = DEFAULT_MULTIBAND_LEVELS,
                    fill: float = np.nan) -> np.ndarray:
    """Multi-band blend (module docstring) of sources ``values[i]`` (h, w, c) with feathering ``weights[i]``."""
    h, w, c = values[0].shape
    den = np.sum(weights, axis=0)
    covered = den > 0
    linear = np.zeros((h, w, c), np.float32)
    for x, wt in zip(values, weights, strict=True):
        linear += wt[..., None] * x
    linear[covered] /= den[covered, None]
    masks = seam_masks(weights)
    acc = None
    mask_sum = None
    for x, wt, m in zip(values, weights, masks, strict=True):
        filled = np.where((wt > 0)[..., None], x, linear).astype(np.float32)
        lp = laplacian_pyramid(filled, levels)
        gp = gaussian_pyramid(m, levels)
        if acc is None:
            acc = [g[..., None] * lap for g, lap in zip(gp, lp, strict=True)]
            mask_sum = gp
        else:
            for k in range(levels + 1):
                acc[k] += gp[k][..., None] * lp[k]
                mask_sum[k] = mask_sum[k] + gp[k]
    lin_pyr = laplacian_pyramid(linear, levels)
    bands = []
    for k in range(levels + 1):
        s = mask_sum[k]
        ok = s > 1e-6
        band = lin_pyr[k].copy()
        band[ok] = acc[k][ok] / s[ok, None]
        bands.append(band)
    out = np.maximum(collapse(bands), 0.0)
    out[~covered] = fill
    return out.astype(np.float32)


def multiband_halo_px(levels: int) -> int:
    """Halo around a tile for ``levels`` pyramid levels (5-tap kernels: support ≈ 4 · 2^levels)."""
    return 4 * 2 ** levels


def _no_halo_px(levels: int) -> int:
    """Linear blending needs no pixels beyond the tile."""
    return 0


@dataclass(frozen=True)
class Blend:
    """What a blending method (module docstring) asks of the tile renderer.

    Attributes
    ----------
    halo_px
        ``halo_px(levels) -> px``: pixels around a tile the method needs (``levels``: multi-band levels).
    uses_levels
        Whether the method has pyramid levels (recorded in the panorama's metadata only then).
    quality_layer
        Whether the method also blends the registration-quality layer (confidence, occlusion) of camera B.
    """

    halo_px: Callable[[int], int]
    uses_levels: bool
    quality_layer: bool


#: The blending methods by name (the valid names are its keys, :data:`~omnispectral.choices.BLEND_NAMES` in that
#: order; the tile renderers of :mod:`omnispectral.mosaic.tile` are keyed alike): ``linear`` (the paper's) and
#: ``multiband``.
BLENDS: dict[str, Blend] = dict(zip(BLEND_NAMES, (
    Blend(_no_halo_px, uses_levels=False, quality_layer=True),  # linear
    Blend(multiband_halo_px, uses_levels=True, quality_layer=False),  # multiband
), strict=True))


def blend_method(name: str) -> Blend:
    """The :class:`Blend` called ``name``.

    Parameters
    ----------
    name
        A key of :data:`BLENDS`.

    Returns
    -------
    Blend
        The method's entry.

    Raises
    ------
    ConfigurationError
        For an unknown name (the message lists the valid ones).
    """
    return method_from(BLENDS, name, "blend")
