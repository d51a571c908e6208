"""Block-wise phase-only correlation: a dense (block-grid) disparity of camera B against camera A.

Every ``block × block`` window of the reference image (camera A), every ``step`` pixels, is registered
with the window of the moving image (camera B) at the same place by band-limited phase-only correlation
(POC; paper Sec. 4.3, Eq. (3), with Takita et al.'s band limitation and peak model; see
:mod:`omnispectral.imaging.registration`).  For blocks ``f``, ``g`` of A and B with DFTs ``F``, ``G``,

.. math::  R(k) = \\frac{G(k)\\,\\overline{F}(k)}{|G(k)\\,\\overline{F}(k)|}, \\quad |k_i| \\le K_i,
           \\qquad r = \\mathrm{IDFT}_M(R) \\approx \\alpha\\, D_{L_0}(n_0 - \\delta_0)\\, D_{L_1}(n_1 - \\delta_1),

the peak position ``δ`` (rescaled from the ``M``-point grid to pixels) is the block's disparity and the
peak height ``α`` its confidence (1 for identical structure, about ``1/sqrt(L0 L1)`` for unrelated
blocks).  All blocks go through one batched FFT (:func:`~omnispectral.imaging.registration.poc_shift`).

- :func:`block_disparity`: two passes (the second re-pairs every block with the moving block displaced
  by its rounded first-pass disparity), then a left-right consistency check, an outlier test against
  the 3 × 3 median and a z-buffer occlusion mask (:func:`occlusion_zbuffer`): the paper's named open
  problem, near objects and occlusion.  Result: :class:`DisparityMap`.
- :func:`refine_block_shifts`: sub-pixel block shifts without the window's pull (each pass resamples the
  moving block at the current estimate and adds the POC residual).
- :func:`block_structure`, :func:`measure_blocks`, :func:`edge_aware_outliers`: refined shifts and
  what each block can be trusted for (texture, one or two measured directions -- the aperture problem --
  and agreement with its neighbours): :class:`BlockShifts`, the input of the rig calibration
  (:mod:`omnispectral.product.rigmeasure`) and of camera B's parallax (:mod:`omnispectral.imaging.parallax`).

Disparities follow the registration convention: content at ``p`` in the reference is at ``p + d`` in the
moving image (``x`` = column, ``y`` = row, pixels).

References
----------
C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
Cybernetics and Society, 163-165, 1975.
K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration based on
phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.registration import (
    DEFAULT_BAND_LIMIT,
    DEFAULT_FIT_RADIUS,
    DEFAULT_PREPROCESS,
    DEFAULT_UPSAMPLE,
    DEFAULT_WINDOW,
    MIN_SIZE_PX,
    apply_window,
    check_image_pair,
    check_poc_options,
    fade_saturated,
    poc_shift,
    prepare_for_poc,
    preprocess_image,
)
from omnispectral.imaging.zbuffer_kernel import compiled_zbuffer

__all__ = ["BLOCK_PX_PER_256", "CONVERGED_PX", "DEFAULT_BLOCK_MIN_CONFIDENCE", "REFINE_PASSES", "BlockShifts",
           "DisparityMap", "block_disparity", "block_size_for", "block_structure", "edge_aware_outliers",
           "measure_blocks", "occlusion_zbuffer", "refine_block_shifts"]

#: Block-wise default: smaller blocks have fewer frequencies, so noise peaks are higher
#: (measured on 32 px blocks of pure sensor noise: 99th percentile 0.30, maximum 0.34).
DEFAULT_BLOCK_MIN_CONFIDENCE = 0.35
_BLOCK_CHUNK = 4096
#: Block size (px) of the POC measurement for a sensor of 256 px; scaled with the sensor (32..64 px):
#: below 32 px the band-limited POC peak fit no longer resolves sub-pixel shifts (measured: 16 and 24 px
#: blocks return 0 and 0.12 px for a 0.6 px shift; 32 px blocks 0.59 px).
BLOCK_PX_PER_256 = 32
#: Refinement passes of :func:`refine_block_shifts`.
REFINE_PASSES = 3
_REMAP_ROWS = 32000
#: Largest last-pass correction (px) of a block that counts as converged.
CONVERGED_PX = 0.05


@dataclass(frozen=True)
class DisparityMap:
    """Block-wise POC disparity of ``moving`` (camera B) relative to ``reference`` (camera A).

    Grid arrays are ``(ny, nx)`` with block centres at ``y_px[i], x_px[j]`` (pixel coordinates of
    the reference).  ``unreliable`` marks blocks with low confidence, a left-right inconsistency
    or an outlier against their neighbours; ``occluded`` is ``(H, W)``: reference pixels hidden in
    the moving image by a nearer surface (z-buffer forward warp of the block disparities).

    Attributes
    ----------
    x_px, y_px : numpy.ndarray
        Block centres (px of the reference), ``(nx,)`` and ``(ny,)``.
    dx, dy : numpy.ndarray
        ``(ny, nx)`` float32 disparity (px; content at ``p`` in the reference is at ``p + d`` in the
        moving image), ``offset`` included.
    confidence : numpy.ndarray
        ``(ny, nx)`` float32 fitted POC peak height of the last pass.
    unreliable, low_confidence, inconsistent, outlier : numpy.ndarray
        ``(ny, nx)`` boolean masks (see :func:`block_disparity`); ``unreliable`` is their union, plus
        blocks whose displaced moving block left the image.
    occluded : numpy.ndarray
        ``(H, W)`` boolean, reference pixels hidden in the moving image by a nearer surface.
    block, step : int
        Block side and grid step (px).
    shape : tuple of int
        ``(H, W)`` of the reference.
    offset : tuple of float
        The ``(dx, dy)`` (px) around which the blocks were measured.
    extras : dict
        ``far_offset`` (the background disparity used for the occlusion) and ``min_confidence``.
    """

    x_px: np.ndarray
    y_px: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    confidence: np.ndarray
    unreliable: np.ndarray
    low_confidence: np.ndarray
    inconsistent: np.ndarray
    outlier: np.ndarray
    occluded: np.ndarray
    block: int
    step: int
    shape: tuple[int, int]
    offset: tuple[float, float] = (0.0, 0.0)
    extras: dict = field(default_factory=dict)

    def to_full_resolution(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The block grid at every reference pixel.

        Returns
        -------
        dx, dy, confidence : numpy.ndarray
            ``(H, W)`` float32, bilinear between block centres (edges held constant).
        unreliable : numpy.ndarray
            ``(H, W)`` boolean, of the nearest block.
        """
        return (_grid_to_pixels(self.dx, self.x_px, self.y_px, self.shape),
                _grid_to_pixels(self.dy, self.x_px, self.y_px, self.shape),
                _grid_to_pixels(self.confidence, self.x_px, self.y_px, self.shape),
                _grid_to_pixels(self.unreliable, self.x_px, self.y_px, self.shape, nearest=True))


def _block_origins(n: int, block: int, step: int) -> np.ndarray:
    starts = np.arange(0, n - block + 1, step)
    if starts[-1] != n - block:
        starts = np.append(starts, n - block)
    return starts


def _grid_to_pixels(values: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, shape: tuple[int, int],
                    nearest: bool = False) -> np.ndarray:
    """Values on the block-centre grid → every pixel (bilinear, or nearest block), edges held constant."""

    fy = np.interp(np.arange(shape[0]), y_px, np.arange(y_px.size))
    fx = np.interp(np.arange(shape[1]), x_px, np.arange(x_px.size))
    if nearest:
        return values[np.rint(fy).astype(int)[:, None], np.rint(fx).astype(int)[None, :]]
    coords = np.stack(np.meshgrid(fy, fx, indexing="ij"))
    return ndimage.map_coordinates(values.astype(np.float32), coords, order=1, mode="nearest")


def _sample_grid(values: np.ndarray, x_px: np.ndarray, y_px: np.ndarray, xq: np.ndarray, yq: np.ndarray) -> np.ndarray:
    """Bilinear sample of a block-centre grid at pixel positions ``(xq, yq)``."""

    fy = np.interp(yq, y_px, np.arange(y_px.size))
    fx = np.interp(xq, x_px, np.arange(x_px.size))
    return ndimage.map_coordinates(values, np.stack([fy, fx]), order=1, mode="nearest")


def occlusion_zbuffer(dx_px: np.ndarray, dy_px: np.ndarray, nearness: np.ndarray, tol_px: float) -> np.ndarray:
    """Reference pixels whose target ``p + d(p)`` in the moving image is taken by a nearer pixel (z-buffer).

    Every pixel is forward-warped to ``round(p + d(p))``; a pixel is occluded when another pixel that
    lands on the same target is nearer by more than ``tol_px``.  Only pixels more than ``tol_px`` nearer
    than the farthest can hide anything and only those are scattered into the buffer: the same result,
    at the cost of the near pixels only (most of a panorama is far).

    Parameters
    ----------
    dx_px, dy_px
        ``(H, W)`` displacement (px) of each reference pixel's content in the moving image.
    nearness
        ``(H, W)`` nearness in the units of ``tol_px`` (e.g. parallax in px from the background); larger
        is nearer; non-finite values never occlude.
    tol_px
        Nearness margin (px) one pixel must have over another to hide it.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` boolean, ``True`` for hidden reference pixels (targets outside the image are never
        occluded).  Compiled (:mod:`omnispectral.imaging.zbuffer_kernel`) where Numba is installed: the same
        result.
    """
    h, w = dx_px.shape
    kernel = compiled_zbuffer()
    if kernel is not None:
        out = np.empty((h, w), bool)
        kernel(dx_px, dy_px, np.asarray(nearness, dtype=np.float64), float(tol_px), out)
        return out
    tx = np.rint(np.arange(w, dtype=np.float64)[None, :] + dx_px).astype(np.int64)
    ty = np.rint(np.arange(h, dtype=np.float64)[:, None] + dy_px).astype(np.int64)
    inside = (tx >= 0) & (tx < w) & (ty >= 0) & (ty < h)
    key = np.where(inside, ty * w + tx, 0)
    near = np.asarray(nearness, dtype=np.float64)
    finite = np.isfinite(near)
    occluders = inside & finite & (near > (float(near[finite].min()) if finite.any() else 0.0) + tol_px)
    top = np.full(h * w, -np.inf, dtype=np.float64)
    np.maximum.at(top, key[occluders], near[occluders])
    occluded = inside & (near < top[key] - tol_px)
    return occluded


def block_disparity(reference, moving, *, block: int = 32, step: int | None = None,
                    offset: tuple[float, float] = (0.0, 0.0), far_offset: tuple[float, float] | None = None,
                    window: str = DEFAULT_WINDOW, band_limit: float = DEFAULT_BAND_LIMIT,
                    upsample: float = DEFAULT_UPSAMPLE, preprocess: str = DEFAULT_PREPROCESS,
                    saturation: float | str | None = None, fit_radius: int = DEFAULT_FIT_RADIUS,
                    min_confidence: float = DEFAULT_BLOCK_MIN_CONFIDENCE, consistency_tol_px: float = 1.0,
                    outlier_tol_px: float = 1.0, occlusion_tol_px: float = 0.5) -> DisparityMap:
    """Dense (block-grid) disparity of ``moving`` (camera B) against ``reference`` (camera A) by block-wise POC.

    Each ``block x block`` window of the reference, every ``step`` pixels, is registered with the
    window of the moving image at the same place moved by the rounded ``offset`` (e.g. the rig's
    calibrated offset, so that blocks measure only the parallax of near objects).  All blocks go
    through one batched ``rfft2`` per chunk, the band-limited POC (Eq. (3),
    :func:`~omnispectral.imaging.registration.band_limited_poc`) and the vectorised peak fit of
    :func:`~omnispectral.imaging.registration.phase_correlate`; a second pass re-pairs every block with
    the moving block displaced by its rounded first-pass disparity.  Disparities follow the registration
    convention (content at ``p`` in the reference is at ``p + d`` in the moving image) and include
    ``offset``; they must stay below about ``block / 3`` around ``offset`` for the first pass to find them.

    Masks on the block grid (``unreliable`` is their union, plus blocks that leave the image):

    - ``low_confidence``: peak height below ``min_confidence`` (flat regions, mixed motions);
    - ``inconsistent``: left-right check -- the disparity at ``p`` and the one found where ``p``
      lands, ``p + d(p)``, differ by more than ``consistency_tol_px`` (depth edges);
    - ``outlier``: more than ``outlier_tol_px`` from the 3 x 3 median of the neighbouring blocks.

    ``occluded`` (full resolution): reference pixels hidden in the moving image by a nearer
    surface -- a z-buffer forward warp of the nearest-block disparities (:func:`occlusion_zbuffer`),
    where nearness is the distance of the disparity from ``far_offset`` (default: the median disparity of
    reliable blocks, i.e. the background).  This is the paper's occlusion problem around close objects.

    Parameters
    ----------
    reference, moving
        Same-size ``(H, W)`` or ``(H, W, C)`` arrays of any real dtype (channels are averaged): camera A's
        image and camera B's.
    block
        Block side (px, at least :data:`~omnispectral.imaging.registration.MIN_SIZE_PX`, at most the image).
    step
        Grid step (px; default ``block // 2``).  The last block of each axis ends at the image edge.
    offset
        ``(dx, dy)`` (px) around which the blocks are measured.
    far_offset
        ``(dx, dy)`` (px) of the background for the occlusion mask (default: median of reliable blocks).
    window, band_limit, upsample, preprocess, saturation, fit_radius
        As for :func:`~omnispectral.imaging.registration.phase_correlate`.
    min_confidence
        Peak height below which a block is ``low_confidence``.
    consistency_tol_px, outlier_tol_px
        Tolerances (px) of the left-right check and of the 3 x 3 median test.
    occlusion_tol_px
        Nearness margin (px) of the occlusion z-buffer.

    Returns
    -------
    DisparityMap
        The block grid, disparities, confidences and masks.

    Raises
    ------
    ConfigurationError
        For invalid options, images of different sizes, or a block or step that does not fit.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3) (POC registration of camera B to camera A), Fig. 6;
       Sec. 7 (occlusions around close-range objects, the open problem the masks flag).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003 (band-limited POC
       and its peak model).
    """
    check_poc_options(window, band_limit, upsample, preprocess, fit_radius)
    ref, mov = check_image_pair(reference, moving)
    step = block // 2 if step is None else step
    h, w = ref.shape[:2]
    if int(block) != block or block < MIN_SIZE_PX:
        raise ConfigurationError(f"block must be an integer >= {MIN_SIZE_PX} px, got {block}")
    if block > min(h, w):
        raise ConfigurationError(f"block {block} px is larger than the image ({h}x{w})")
    if int(step) != step or step < 1:
        raise ConfigurationError(f"step must be a positive integer, got {step}")
    off = np.asarray(offset, dtype=np.float64)
    if off.shape != (2,) or not np.isfinite(off).all():
        raise ConfigurationError(f"offset must be two finite numbers (dx, dy), got {offset!r}")
    a, sat_a = prepare_for_poc(ref, "reference", preprocess, saturation)
    b, sat_b = prepare_for_poc(mov, "moving", preprocess, saturation)
    if sat_a is not None:
        a = fade_saturated(a, sat_a)
    if sat_b is not None:
        b = fade_saturated(b, sat_b)

    ys, xs = _block_origins(h, block, step), _block_origins(w, block, step)
    ny, nx = ys.size, xs.size
    org_y = np.repeat(ys, nx)
    org_x = np.tile(xs, ny)
    view_a = np.lib.stride_tricks.sliding_window_view(a, (block, block))
    view_b = np.lib.stride_tricks.sliding_window_view(b, (block, block))
    # Pass 1 pairs each block with the moving block displaced by the rounded offset; pass 2 with the
    # one displaced by the rounded pass-1 disparity, so the residual is below half a pixel and the
    # window (fixed while the content moves) no longer pulls large disparities towards zero.
    guess_x = np.full(ny * nx, float(round(off[0])))
    guess_y = np.full(ny * nx, float(round(off[1])))
    for _ in range(2):
        mov_y = np.clip(org_y + np.rint(guess_y).astype(np.int64), 0, h - block)
        mov_x = np.clip(org_x + np.rint(guess_x).astype(np.int64), 0, w - block)
        res_x, res_y, conf = _block_pass(view_a, view_b, org_y, org_x, mov_y, mov_x, window, band_limit, upsample,
                                         fit_radius)
        guess_x = (mov_x - org_x) + res_x
        guess_y = (mov_y - org_y) + res_y
    clipped = ((mov_y - org_y) != np.rint(guess_y - res_y)) | ((mov_x - org_x) != np.rint(guess_x - res_x))
    clipped |= (org_y + np.rint(guess_y) < 0) | (org_y + np.rint(guess_y) > h - block)
    clipped |= (org_x + np.rint(guess_x) < 0) | (org_x + np.rint(guess_x) > w - block)
    dx = guess_x.reshape(ny, nx).astype(np.float32)
    dy = guess_y.reshape(ny, nx).astype(np.float32)
    conf = conf.reshape(ny, nx).astype(np.float32)
    clipped = clipped.reshape(ny, nx)
    x_px = xs + (block - 1) / 2.0
    y_px = ys + (block - 1) / 2.0
    return _finish_disparity(dx, dy, conf, clipped, x_px, y_px, (h, w), block, step, (float(off[0]), float(off[1])),
                             far_offset, min_confidence, consistency_tol_px, outlier_tol_px, occlusion_tol_px)


def _block_pass(view_a, view_b, org_y, org_x, mov_y, mov_x, window, band_limit, upsample, fit_radius):
    """POC of reference blocks at ``(org_y, org_x)`` against moving blocks at ``(mov_y, mov_x)``, in chunks."""
    n = org_y.size
    dx, dy, conf = np.empty(n), np.empty(n), np.empty(n)
    for start in range(0, n, _BLOCK_CHUNK):
        sel = slice(start, start + _BLOCK_CHUNK)
        blocks_a = apply_window(view_a[org_y[sel], org_x[sel]], window)
        blocks_b = apply_window(view_b[mov_y[sel], mov_x[sel]], window)
        dx[sel], dy[sel], conf[sel] = poc_shift(blocks_a, blocks_b, band_limit, upsample, fit_radius)
    return dx, dy, conf


def _finish_disparity(dx, dy, conf, clipped, x_px, y_px, shape, block, step, offset, far_offset, min_confidence,
                      consistency_tol_px, outlier_tol_px, occlusion_tol_px) -> DisparityMap:
    low = conf < min_confidence
    gy, gx = np.meshgrid(y_px, x_px, indexing="ij")
    dx_back = _sample_grid(dx, x_px, y_px, (gx + dx).ravel(), (gy + dy).ravel()).reshape(dx.shape)
    dy_back = _sample_grid(dy, x_px, y_px, (gx + dx).ravel(), (gy + dy).ravel()).reshape(dy.shape)
    inconsistent = np.hypot(dx - dx_back, dy - dy_back) > consistency_tol_px
    med_x = ndimage.median_filter(dx, size=3, mode="nearest")
    med_y = ndimage.median_filter(dy, size=3, mode="nearest")
    outlier = np.hypot(dx - med_x, dy - med_y) > outlier_tol_px
    unreliable = low | inconsistent | outlier | clipped
    if far_offset is None:
        good = ~unreliable
        far = (float(np.median(dx[good])), float(np.median(dy[good]))) if good.any() else offset
    else:
        far = (float(far_offset[0]), float(far_offset[1]))
    dx_px = _grid_to_pixels(dx, x_px, y_px, shape, nearest=True)
    dy_px = _grid_to_pixels(dy, x_px, y_px, shape, nearest=True)
    nearness = np.hypot(dx_px - far[0], dy_px - far[1])
    occluded = occlusion_zbuffer(dx_px, dy_px, nearness, occlusion_tol_px)
    return DisparityMap(x_px=x_px, y_px=y_px, dx=dx, dy=dy, confidence=conf, unreliable=unreliable,
                        low_confidence=low, inconsistent=inconsistent, outlier=outlier, occluded=occluded,
                        block=int(block), step=int(step), shape=(int(shape[0]), int(shape[1])), offset=offset,
                        extras={"far_offset": far, "min_confidence": float(min_confidence)})


# ----------------------------------------------------------------- refined block shifts
def block_size_for(width: int, height: int) -> int:
    """POC block side for an image: :data:`BLOCK_PX_PER_256` px per 256 px of the longer side, even, 32..64 px.

    Parameters
    ----------
    width, height
        Image size (px).

    Returns
    -------
    int
        Block side (px).
    """
    side = BLOCK_PX_PER_256 * max(width, height) / 256.0
    return int(np.clip(2 * round(side / 2), 32, 64))


def refine_block_shifts(a: np.ndarray, b: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, dx: np.ndarray,
                        dy: np.ndarray, block: int, passes: int = REFINE_PASSES,
                        edge_normal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel block shifts without the window's pull.

    Each pass resamples the moving image's block at the current estimate (bicubic) and adds the POC
    residual, which is then a small fraction of a pixel.  A fixed window on content that moves pulls a
    windowed POC estimate towards zero by ~15 % of the shift (0.32 px measured for a 0.4 px shift on 32 px
    blocks); resampling at the estimate makes the remaining shift, and so the pull, shrink geometrically
    (the same idea as :func:`~omnispectral.imaging.registration.phase_correlate`'s refinement, batched
    over blocks).

    Parameters
    ----------
    a, b
        Pre-processed ``(H, W)`` float32 reference and moving images
        (:func:`~omnispectral.imaging.registration.preprocess_image`).
    y_px, x_px
        Block centres (px), ``(ny,)`` and ``(nx,)``.
    dx, dy
        ``(ny, nx)`` starting shifts (px, registration convention).
    block
        Block side (px).
    passes
        Number of passes.
    edge_normal
        Optional ``(ny, nx, 2)``: for blocks that measure one direction only (an edge), the unit normal of
        the edge, NaN for two-directional blocks; convergence is then judged across the edge only (along
        it the shift is not observable and wanders from pass to pass).

    Returns
    -------
    dx, dy : numpy.ndarray
        ``(ny, nx)`` float64 refined shifts (px).
    confidence : numpy.ndarray
        ``(ny, nx)`` last pass's peak heights, 0 where the refinement did not converge (last correction
        above :data:`CONVERGED_PX`).
    """
    half = (block - 1) / 2.0
    off = (np.arange(block) - half).astype(np.float32)
    y0 = np.rint(y_px - half).astype(int)
    x0 = np.rint(x_px - half).astype(int)
    view_a = np.lib.stride_tricks.sliding_window_view(a, (block, block))
    ref = apply_window(view_a[np.repeat(y0, x0.size), np.tile(x0, y0.size)], DEFAULT_WINDOW)
    cx = np.tile(x_px, y_px.size).astype(np.float32)
    cy = np.repeat(y_px, x_px.size).astype(np.float32)
    ddx, ddy = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
    conf = np.zeros(ddx.size)
    last = np.zeros(ddx.size)
    per = max(1, _REMAP_ROWS // block)
    if edge_normal is not None:
        normal_x, normal_y = edge_normal[..., 0].ravel(), edge_normal[..., 1].ravel()
    for _ in range(passes):
        for s0 in range(0, ddx.size, per):
            sl = slice(s0, s0 + per)
            mx = (cx[sl] + ddx[sl].astype(np.float32))[:, None, None] + off[None, None, :]
            my = (cy[sl] + ddy[sl].astype(np.float32))[:, None, None] + off[None, :, None]
            mx, my = np.broadcast_arrays(mx, my)
            n = mx.shape[0]
            mov = cv2.remap(b, np.ascontiguousarray(mx.reshape(n * block, block)),
                            np.ascontiguousarray(my.reshape(n * block, block)), cv2.INTER_CUBIC,
                            borderMode=cv2.BORDER_REFLECT).reshape(n, block, block)
            rx, ry, c = poc_shift(ref[sl], apply_window(mov, DEFAULT_WINDOW), DEFAULT_BAND_LIMIT,
                                   DEFAULT_UPSAMPLE, DEFAULT_FIT_RADIUS)
            ok = np.isfinite(rx) & np.isfinite(ry) & (np.abs(rx) < 1.0) & (np.abs(ry) < 1.0)
            ddx[sl] += np.where(ok, rx, 0.0)
            ddy[sl] += np.where(ok, ry, 0.0)
            conf[sl] = np.where(ok, c, 0.0)
            step = np.hypot(rx, ry)
            if edge_normal is not None:
                nx_, ny_ = normal_x[sl], normal_y[sl]
                step = np.where(np.isfinite(nx_), np.abs(np.nan_to_num(nx_) * rx + np.nan_to_num(ny_) * ry), step)
            last[sl] = np.where(ok, step, np.inf)
    # a block whose last correction is not small has not converged (flat or ambiguous content)
    conf = np.where(last <= CONVERGED_PX, conf, 0.0)
    return ddx.reshape(dx.shape), ddy.reshape(dy.shape), conf.reshape(dx.shape)


@dataclass(frozen=True)
class BlockShifts:
    """Refined block shifts and what they can be trusted for (:func:`measure_blocks`).

    Attributes
    ----------
    y_px, x_px : numpy.ndarray
        Block centres (px), ``(ny,)`` and ``(nx,)``.
    dx, dy : numpy.ndarray
        ``(ny, nx)`` refined shifts (px; content at ``p`` in A is at ``p + d`` in B).
    confidence : numpy.ndarray
        ``(ny, nx)`` peak height of the last refinement pass (0: not converged).
    reliable : numpy.ndarray
        ``(ny, nx)`` boolean: confident, converged, textured and no outlier.
    two_d : numpy.ndarray
        ``(ny, nx)`` boolean, reliable blocks whose detail has two directions (corners, texture), so both
        components are measured; otherwise only the component along ``normal`` (across the block's edge)
        is (the aperture problem).
    normal : numpy.ndarray
        ``(ny, nx, 2)`` unit normal of the block's dominant edge.
    tensor : numpy.ndarray
        ``(ny, nx, 3)``: the block's structure tensor ``(jxx, jxy, jyy)`` divided by its trace, the
        relative information of a shift in each direction (``dᵀ J d``), for weighting residuals (``n nᵀ``
        for one-directional blocks).

    Notes
    -----
    A block is ``textured`` when it has detail beyond a smooth gradient (a shifted ramp or a smooth sky
    gradient is the same ramp plus a constant: POC then reports 0 with a high peak).
    """

    y_px: np.ndarray
    x_px: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    confidence: np.ndarray
    reliable: np.ndarray
    two_d: np.ndarray
    normal: np.ndarray
    tensor: np.ndarray


def block_structure(a: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, block: int,
                    min_snr: float = 9.0, min_ratio: float = 0.3) -> tuple[np.ndarray, ...]:
    """Per block: textured, two-directional, the unit normal of its dominant edge and the normalised structure tensor.

    The structure tensor is that of the high-passed image (image minus its Gaussian blur, σ = 1.5 px),
    averaged over each block; the noise level is the median high-pass energy of the whole image.

    Parameters
    ----------
    a
        Pre-processed ``(H, W)`` float32 image.
    y_px, x_px
        Block centres (px), ``(ny,)`` and ``(nx,)``.
    block
        Block side (px).
    min_snr
        A block is textured when its high-pass energy is at least this multiple of the noise level.
    min_ratio
        A textured block is two-directional when the smaller eigenvalue of its tensor is at least this
        fraction of the larger.

    Returns
    -------
    textured, two_d : numpy.ndarray
        ``(ny, nx)`` boolean.
    normal : numpy.ndarray
        ``(ny, nx, 2)`` unit normal ``(cos θ, sin θ)`` of the dominant edge.
    tensor : numpy.ndarray
        ``(ny, nx, 3)`` ``(jxx, jxy, jyy) / trace`` for two-directional blocks; ``n nᵀ`` of the edge
        normal otherwise (an edge's POC shift along the edge is not noisy but biased -- the window pulls
        it to zero -- so only the component across the edge is kept).
    """
    hp = a - cv2.GaussianBlur(a, (0, 0), 1.5)
    gx = cv2.Sobel(hp, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(hp, cv2.CV_32F, 0, 1, ksize=3) / 8
    half = (block - 1) / 2.0
    y0 = np.rint(y_px - half).astype(int)
    x0 = np.rint(x_px - half).astype(int)

    def block_mean(x):
        ii = cv2.integral(x.astype(np.float64))
        a_, b_ = y0[:, None], x0[None, :]
        return (ii[a_ + block, b_ + block] - ii[a_, b_ + block] - ii[a_ + block, b_] + ii[a_, b_]) / block**2

    jxx, jyy, jxy = block_mean(gx * gx), block_mean(gy * gy), block_mean(gx * gy)
    energy = block_mean(hp * hp)
    noise = float(np.median(hp * hp))
    floor = max(noise, 1e-8 * float(np.mean(a)) ** 2)
    tr, det = jxx + jyy, jxx * jyy - jxy * jxy
    disc = np.sqrt(np.maximum(tr * tr / 4 - det, 0))
    lmax, lmin = tr / 2 + disc, tr / 2 - disc
    textured = energy >= min_snr * floor
    two_d = textured & (lmin >= min_ratio * np.maximum(lmax, 1e-30))
    angle = 0.5 * np.arctan2(2 * jxy, jxx - jyy)
    normal = np.stack([np.cos(angle), np.sin(angle)], axis=-1)
    tensor = np.stack([jxx, jxy, jyy], axis=-1) / np.maximum(tr, 1e-30)[..., None]
    # an edge's POC shift along the edge is not noisy but biased (the window pulls it to zero): keep only
    # the component across the edge, n nᵀ, rather than a small weight on a wrong number
    edge = np.stack([normal[..., 0] ** 2, normal[..., 0] * normal[..., 1], normal[..., 1] ** 2], axis=-1)
    tensor = np.where(two_d[..., None], tensor, edge)
    return textured, two_d, normal, tensor


def measure_blocks(gray_a: np.ndarray, gray_b: np.ndarray, block: int, min_confidence: float, *,
                   edge_aware: bool = True) -> BlockShifts:
    """Block grid, refined shifts (content at ``p`` in A is at ``p + d`` in B) and what they can be trusted for.

    :func:`block_disparity` (step ``block // 2``), :func:`block_structure` and
    :func:`refine_block_shifts` on the square-rooted images.  A block is reliable when its POC peak is
    high, its refinement converged, it has texture, and it agrees with its confident neighbours in what
    it measures (:func:`edge_aware_outliers`; with ``edge_aware`` False, in both components against the
    median of all neighbours, as :func:`block_disparity` judges).

    Parameters
    ----------
    gray_a, gray_b
        ``(H, W)`` grey images of camera A and of camera B resampled onto A's grid.
    block
        Block side (px).
    min_confidence
        Smallest peak height (of the first measurement and of the refinement) of a reliable block.
    edge_aware
        Judge one-directional (edge) blocks on their component across the edge only.

    Returns
    -------
    BlockShifts
        Block centres, refined shifts ``dx``, ``dy`` (px), confidences (peak heights), and the ``reliable`` and
        two-directional masks, edge normals and structure tensors (``(ny, nx)`` grids).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3) (POC registration of camera B to camera A).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003 (band-limited POC
       and its peak model).
    """
    dm = block_disparity(gray_a, gray_b, block=block, step=block // 2, min_confidence=min_confidence)
    a = preprocess_image(gray_a, "sqrt")
    b = preprocess_image(gray_b, "sqrt")
    textured, two_d, normal, tensor = block_structure(a, dm.y_px, dm.x_px, block)
    edge_normal = np.where(two_d[..., None], np.nan, normal) if edge_aware else None
    dx, dy, conf = refine_block_shifts(a, b, dm.y_px, dm.x_px, dm.dx, dm.dy, block, edge_normal=edge_normal)
    moved = np.hypot(dx - dm.dx, dy - dm.dy)
    if edge_aware:  # an edge block's shift along its edge is not observable: judge the part across it
        moved = np.where(two_d, moved, np.abs(normal[..., 0] * (dx - dm.dx) + normal[..., 1] * (dy - dm.dy)))
    moved = moved < 1.0
    confident = ~dm.low_confidence & moved & (conf >= min_confidence) & textured
    # two-directional blocks keep the whole-vector test (a chart's corner blocks straddling the chart and
    # its background measure the chart 0.3-0.5 px off and would hold its pixels there as a prior)
    outlier = np.where(two_d, dm.outlier, edge_aware_outliers(dx, dy, confident, two_d, normal)) \
        if edge_aware else dm.outlier
    reliable = confident & ~outlier
    return BlockShifts(dm.y_px, dm.x_px, dx, dy, conf, reliable, two_d & reliable, normal, tensor)


#: Cosine above which a neighbour's edge normal counts as the same direction (within 45°).
_SAME_NORMAL_COS = 0.7


def edge_aware_outliers(dx: np.ndarray, dy: np.ndarray, confident: np.ndarray, two_d: np.ndarray,
                        normal: np.ndarray, tol_px: float = 1.0) -> np.ndarray:
    """Blocks whose shift across their edge is far from that of their confident neighbours.

    A block is an outlier when its shift along its normal is more than ``tol_px`` from the median of its
    confident 3 × 3 neighbours (itself included) that measure that component: two-directional blocks,
    or edge blocks whose normal is within 45° of its own.  (:func:`measure_blocks` applies it to edge
    blocks only.)

    An edge block measures the shift across its edge only; along the edge its POC shift is arbitrary (the
    aperture problem).  Comparing whole vectors, as :func:`block_disparity`'s ``outlier`` does, rejects
    every block of a thin near object lying along the epipolar lines' normal -- a post whose long edges cut
    the lines, measured by a row of edge blocks with equal shifts across and scattered shifts along it --
    and lets flat blocks' noise set the median.

    Parameters
    ----------
    dx, dy
        ``(ny, nx)`` block shifts (px).
    confident
        ``(ny, nx)`` boolean, blocks whose measurement may vote.
    two_d
        ``(ny, nx)`` boolean, two-directional blocks.
    normal
        ``(ny, nx, 2)`` unit edge normals.
    tol_px
        Largest accepted distance (px) from the neighbours' median.

    Returns
    -------
    numpy.ndarray
        ``(ny, nx)`` boolean (``False`` where no neighbour measures the component).
    """
    ny, nx = dx.shape
    pad = ((1, 1), (1, 1))
    px_, py_ = np.pad(dx.astype(np.float64), pad), np.pad(dy.astype(np.float64), pad)
    pc, p2 = np.pad(confident, pad), np.pad(two_d, pad)
    pnx, pny = np.pad(normal[..., 0], pad), np.pad(normal[..., 1], pad)
    ux, uy = normal[..., 0], normal[..., 1]
    vals = np.full((9, ny, nx), np.nan)
    for k, (oy, ox) in enumerate((oy, ox) for oy in range(3) for ox in range(3)):
        sl = (slice(oy, oy + ny), slice(ox, ox + nx))
        usable = pc[sl] & (p2[sl] | (np.abs(pnx[sl] * ux + pny[sl] * uy) >= _SAME_NORMAL_COS))
        vals[k] = np.where(usable, px_[sl] * ux + py_[sl] * uy, np.nan)
    counted = np.isfinite(vals).any(axis=0)
    med = np.nanmedian(np.where(counted[None], vals, 0.0), axis=0)
    return counted & (np.abs(dx * ux + dy * uy - med) > tol_px)
