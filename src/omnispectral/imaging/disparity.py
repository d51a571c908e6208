"""Per-pixel parallax of camera B against camera A along the rig's epipolar lines (beyond the paper).

Camera B sits ``c`` (the baseline, metres, head frame) from camera A, whose optical centre is the
head's rotation centre.  Once B's image is resampled onto A's pixel grid for points at infinity
(:func:`omnispectral.product.align.warp_b_onto_a` with B's calibrated mounting), a point of A's pixel
``p`` at distance ``Z`` appears in the warped B image at ``π_A(r_A(p) − c/Z)``: it moves along the
epipolar line through ``p`` by an amount set by one unknown per pixel, the **inverse depth**
``w = 1/Z`` (1/m; 0 at infinity).  :func:`epipolar_field` gives that line's direction and its
pixels per unit of ``w``; :func:`parallax_map` measures ``w`` at every pixel:

1. block-wise POC (:func:`block_disparity`, at the end of this module) between A and the
   warped B; each reliable block's disparity is projected on the epipolar direction (the
   perpendicular part, which no depth explains, must be small: otherwise the block is rejected);
2. blocks without a reliable measurement take the inverse depth of reliable neighbours
   (normalised convolution over 5 × 5 blocks), else of the ground plane when one is known
   (rays below the horizon), else 0 (sky);
3. every pixel sweeps the inverse depths spanned by its 5 × 5 neighbouring blocks (every 0.25 px of
   parallax) and keeps the one whose warped-B neighbourhood matches A best (:class:`LocalLinearScore`:
   how well B's channels are a linear function of A's over 11 × 11 px, which the different filters of
   the two cameras allow; parabolic sub-step refinement; shiftable windows: a pixel takes the depth of
   its own surface, never a blend of two); a pixel whose match is not distinctive takes its distinctive
   neighbours' depth, and one left at infinity whose B colour plainly misfits A takes its surface's
   depth by colour (:func:`settle_by_colour`);
4. pixels of A that B cannot see because a nearer surface hides them (z-buffer forward warp) are
   flagged as occluded: the mosaic takes B's bands there from other directions.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.registration import (
    DEFAULT_BAND_LIMIT,
    DEFAULT_FIT_RADIUS,
    DEFAULT_PREPROCESS,
    DEFAULT_UPSAMPLE,
    DEFAULT_WINDOW,
    MIN_SIZE_PX,
    _apply_window,
    _check_options,
    _check_pair,
    _fade_saturated,
    _poc_shift,
    _prepare,
    as_gray,
    preprocess_image,
)

#: Block size (px) of the POC measurement for a sensor of 256 px; scaled with the sensor (32..64 px):
#: below 32 px the band-limited POC peak fit no longer resolves sub-pixel shifts (measured: 16 and 24 px
#: blocks return 0 and 0.12 px for a 0.6 px shift; 32 px blocks 0.59 px).
BLOCK_PX_PER_256 = 32
#: A block measures parallax when its structure measures shifts along the epipolar line at least this
#: well (``eᵀJe / |e|²`` with the normalised structure tensor J: 0 for an edge parallel to the line).
MIN_ALONG_WEIGHT = 0.3
#: Refinement passes of :func:`refine_block_shifts`.
REFINE_PASSES = 3
_REMAP_ROWS = 32000
#: Largest last-pass correction (px) of a block that counts as converged.
CONVERGED_PX = 0.05
#: Largest part of a block's disparity perpendicular to its epipolar line (px) that is still accepted.
MAX_PERPENDICULAR_PX = 0.75
#: Window (px) of the per-pixel choice of depth.
NCC_WINDOW_PX = 11
#: Parallax step (px) between the levels of the per-pixel sweep, and the most levels per direction.
SWEEP_STEP_PX = 0.25
SWEEP_MAX_LEVELS = 48
#: A pixel is occluded when a surface nearer by more than this parallax (px) lands on the same place in B.
OCCLUSION_TOL_PX = 1.0
#: Long side (px) at which the per-pixel parallax is analysed (larger images are binned), and the rig
#: calibration's block measurements.
PARALLAX_ANALYSIS_PX = 512
CALIBRATION_ANALYSIS_PX = 1024
#: Smallest normalised correlation that counts as a match in the sweep (noise alone reaches ~0.3 on 11 px windows).
SWEEP_MIN_NCC = 0.5
#: Correlation by which a finite depth must beat infinity (and any other level far from it) in the sweep.
SWEEP_ZERO_MARGIN = 0.03
#: Steps searched beyond the range of a pixel's neighbouring blocks.
SWEEP_MARGIN_STEPS = 4
#: Neighbourhood (blocks) whose range of estimates a pixel searches: a near object narrower than a block
#: (a post at 1.5 m) is measured mixed with its background by every block that holds it.
SWEEP_RANGE_BLOCKS = 5
#: An unsure pixel left at infinity takes its neighbours' depth only when B's colour at infinity misfits
#: A's pixel by more than this (relative, :func:`settle_by_colour`): an unrelated surface, not the spectral
#: variety one linear map between the cameras leaves (a few per cent).
COLOUR_MISFIT_MIN = 0.3
#: Two pixels are taken for one surface when their colours in A differ by at most this fraction of
#: their summed magnitudes (shading within a surface moves both brightness and colour a little).
SAME_SURFACE_COLOUR = 0.1
#: Share of a block's pixels B must see for the block to be measured.
MIN_BLOCK_SEEN = 0.95
#: Minimum POC peak height of a block measurement.
PARALLAX_MIN_CONFIDENCE = 0.3
#: Inverse depth change (1/m) used for the finite difference of the epipolar field.
_DW_PER_M = 0.01


def analysis_factor(width: int, height: int, target_px: int) -> int:
    """Integer binning that brings an image's long side to about ``target_px`` (1 for small images)."""
    return max(1, round(max(width, height) / target_px))


def bin_image(image: np.ndarray, factor: int) -> np.ndarray:
    """``factor × factor`` box average (area integration: a binned pixel is the mean of the pixels it covers)."""
    if factor == 1:
        return np.asarray(image, np.float32)
    h, w = image.shape[:2]
    return cv2.resize(np.asarray(image, np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def binned_to_full_px(x, factor: int):
    """Pixel coordinates of a binned image → full-resolution coordinates (pixel centres at integers)."""
    return (np.asarray(x, np.float64) + 0.5) * factor - 0.5


def block_size_for(width: int, height: int) -> int:
    """POC block side for an image: 32 px per 256 px of the longer side, even, 32..64 px."""
    side = BLOCK_PX_PER_256 * max(width, height) / 256.0
    return int(np.clip(2 * round(side / 2), 32, 64))


def refine_block_shifts(a: np.ndarray, b: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, dx: np.ndarray,
                        dy: np.ndarray, block: int, passes: int = REFINE_PASSES,
                        edge_normal: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-pixel block shifts without the window's pull: each pass resamples the moving image's block at
    the current estimate (bicubic) and adds the POC residual, which is then a small fraction of a pixel.

    A fixed window on content that moves pulls a windowed POC estimate towards zero by ~15 % of the
    shift (0.32 px measured for a 0.4 px shift on 32 px blocks); resampling at the estimate makes the
    remaining shift, and so the pull, shrink geometrically (the same idea as
    :func:`~omnispectral.imaging.registration.phase_correlate`'s refinement, batched over blocks).
    ``a``, ``b``: preprocessed (H, W) float32; ``y_px, x_px``: block centres; ``dx, dy``: (ny, nx) start.
    ``edge_normal`` (ny, nx, 2): for blocks that measure one direction only (an edge), the unit normal of
    the edge, NaN for two-directional blocks; convergence is then judged across the edge only (along it
    the shift is not observable and wanders from pass to pass).
    Returns refined ``dx, dy`` and the last pass's peak heights (0 where the refinement did not converge).
    """
    half = (block - 1) / 2.0
    off = (np.arange(block) - half).astype(np.float32)
    y0 = np.rint(y_px - half).astype(int)
    x0 = np.rint(x_px - half).astype(int)
    view_a = np.lib.stride_tricks.sliding_window_view(a, (block, block))
    ref = _apply_window(view_a[np.repeat(y0, x0.size), np.tile(x0, y0.size)], DEFAULT_WINDOW)
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
            rx, ry, c = _poc_shift(ref[sl], _apply_window(mov, DEFAULT_WINDOW), DEFAULT_BAND_LIMIT,
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
    """Refined block shifts and what they can be trusted for.

    ``textured``: the block has detail beyond a smooth gradient (a shifted ramp or a smooth sky
    gradient is the same ramp plus a constant: POC then reports 0 with a high peak);
    ``two_d``: the detail has two directions (corners, texture), so both components are measured;
    otherwise only the component along ``normal`` (across the block's edge) is (the aperture problem).
    ``tensor``: the block's structure tensor ``(jxx, jxy, jyy)`` divided by its trace, the relative
    information of a shift in each direction (``dᵀ J d``), for weighting residuals.
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
    """Per block: textured, two-directional, the unit normal of its dominant edge and the normalised
    structure tensor ``(jxx, jxy, jyy) / trace`` (structure tensor
    of the high-passed image, image minus its Gaussian blur σ = 1.5 px; noise level from the median
    high-pass energy of the whole image)."""
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

    A block is reliable when its POC peak is high, its refinement converged, it has texture, and it agrees
    with its confident neighbours in what it measures (:func:`edge_aware_outliers`; with ``edge_aware``
    False, in both components against the median of all neighbours, as :func:`block_disparity` judges)."""
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
    """Blocks whose shift across their edge is more than ``tol_px`` from the median of their confident 3 × 3
    neighbours (themselves included) that measure that component: two-directional blocks, or edge blocks
    whose normal is within 45° of theirs.  (:func:`measure_blocks` applies it to edge blocks only.)

    An edge block measures the shift across its edge only; along the edge its POC shift is arbitrary (the
    aperture problem).  Comparing whole vectors, as :func:`block_disparity`'s ``outlier`` does, rejects
    every block of a thin near object lying along the epipolar lines' normal -- a post whose long edges cut
    the lines, measured by a row of edge blocks with equal shifts across and scattered shifts along it --
    and lets flat blocks' noise set the median.
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


def epipolar_field(model_a: CameraModel, baseline_m: np.ndarray, pixels: np.ndarray | None = None,
                   second_order: bool = False) -> np.ndarray:
    """A-pixel displacement per unit inverse depth (px · m), ``(..., 2)``, at ``pixels`` (default: every pixel).

    ``baseline_m``: camera B's optical centre relative to A's in the world frame at pan = tilt = 0.
    The content of A's pixel ``p`` at inverse depth ``w`` lies at ``p + w · e(p)`` (to first order) in
    B's image resampled onto A's grid for points at infinity.  With ``second_order`` the result is
    ``(..., 4)``: ``e`` and the second derivative ``h`` (``p + w e + w² h / 2``; at 1 m on the small rig
    the first-order position is 0.2 px off, the second-order one 0.002 px).
    """
    if pixels is None:
        v, u = np.mgrid[0:model_a.height, 0:model_a.width]
        pixels = np.stack([u, v], axis=-1).astype(np.float64)
    rays, _ = model_a.pixel_to_world(pixels, 0.0, 0.0)
    c = np.asarray(baseline_m, np.float64)
    plus, _ = model_a.world_to_pixel(rays - _DW_PER_M * c, 0.0, 0.0, margin_px=None)
    minus, _ = model_a.world_to_pixel(rays + _DW_PER_M * c, 0.0, 0.0, margin_px=None)
    e = (plus - minus) / (2 * _DW_PER_M)
    if not second_order:
        return e
    h_step = 0.1  # 1/m: the second difference needs a larger step than the first to rise above rounding
    p2, _ = model_a.world_to_pixel(rays - h_step * c, 0.0, 0.0, margin_px=None)
    m2, _ = model_a.world_to_pixel(rays + h_step * c, 0.0, 0.0, margin_px=None)
    centre, _ = model_a.world_to_pixel(rays, 0.0, 0.0, margin_px=None)
    return np.concatenate([e, (p2 - 2 * centre + m2) / h_step**2], axis=-1)


def shifted_positions(model_a: CameraModel, baseline_m: np.ndarray, pixels: np.ndarray,
                      inv_depth_per_m: np.ndarray) -> np.ndarray:
    """Exact position in the warped B image of A's ``pixels`` at inverse depth ``w``: ``π_A(r_A(p) − w c)``."""
    rays, _ = model_a.pixel_to_world(pixels, 0.0, 0.0)
    shifted = rays - np.asarray(inv_depth_per_m, np.float64)[..., None] * np.asarray(baseline_m, np.float64)
    out, _ = model_a.world_to_pixel(shifted, 0.0, 0.0, margin_px=None)
    return out


@dataclass(frozen=True)
class BlockParallax:
    """Block-grid inverse depth: centres ``(y_px, x_px)``, ``inv_depth_per_m`` and what was measured."""

    y_px: np.ndarray
    x_px: np.ndarray
    inv_depth_per_m: np.ndarray
    measured: np.ndarray
    confidence: np.ndarray
    perpendicular_px: np.ndarray
    #: the shift no depth explains (px, J-norm), on reliable blocks with structure across the epipolar lines
    #: (``pᵀJp / |e|² ≥ 0.3``, ``p ⟂ e``), whatever its size; NaN elsewhere.  Edges parallel to the lines
    #: count with their whole measured shift (no depth moves them).  Says whether the rig model fits
    #: this direction at all
    across_px: np.ndarray | None = None


def block_parallax(gray_a: np.ndarray, warped_b: np.ndarray, seen: np.ndarray, field: np.ndarray, *,
                   block: int, min_confidence: float = PARALLAX_MIN_CONFIDENCE,
                   max_perpendicular_px: float = MAX_PERPENDICULAR_PX) -> BlockParallax:
    """Step 1 of the module docstring: reliable blocks' inverse depth along their epipolar lines."""
    bs = measure_blocks(gray_a, warped_b, block, min_confidence)
    y_px, x_px, dx, dy = bs.y_px, bs.x_px, bs.dx, bs.dy
    iy = np.clip(np.rint(y_px).astype(int), 0, gray_a.shape[0] - 1)
    ix = np.clip(np.rint(x_px).astype(int), 0, gray_a.shape[1] - 1)
    e = field[iy[:, None], ix[None, :], :2]
    e_len = np.linalg.norm(e, axis=-1)
    # the structure tensor J says which components of the shift the block measures: the inverse depth is
    # the J-weighted projection on the epipolar direction, the rest (which no depth explains) must be small
    jxx, jxy, jyy = bs.tensor[..., 0], bs.tensor[..., 1], bs.tensor[..., 2]
    ex, ey = e[..., 0], e[..., 1]
    eje = ex * (jxx * ex + jxy * ey) + ey * (jxy * ex + jyy * ey)
    ejd = ex * (jxx * dx + jxy * dy) + ey * (jxy * dx + jyy * dy)
    w = ejd / np.maximum(eje, 1e-12)
    rx, ry = dx - w * ex, dy - w * ey
    perp = np.sqrt(np.maximum(rx * (jxx * rx + jxy * ry) + ry * (jxy * rx + jyy * ry), 0.0))
    along_weight = eje / np.maximum(e_len**2, 1e-12)
    inside = _blocks_seen(seen, y_px, x_px, block)
    usable = bs.reliable & inside & (e_len > 1e-6)
    measured = usable & (along_weight >= MIN_ALONG_WEIGHT) & (perp <= max_perpendicular_px)
    across_weight = (ey * (jxx * ey - jxy * ex) - ex * (jxy * ey - jyy * ex)) / np.maximum(e_len**2, 1e-12)
    # an edge (nearly) parallel to the line: a depth would have to be absurd to explain its shift, so all of it
    # is across (the J-projection above would "explain" it with w → ∞)
    whole = np.sqrt(np.maximum(dx * (jxx * dx + jxy * dy) + dy * (jxy * dx + jyy * dy), 0.0))
    across = np.where(usable & (across_weight >= MIN_ALONG_WEIGHT),
                      np.where(along_weight >= MIN_ALONG_WEIGHT, perp, whole), np.nan)
    w = np.where(measured, w, 0.0)
    return BlockParallax(y_px, x_px, w.astype(np.float32), measured, bs.confidence.astype(np.float32),
                         perp.astype(np.float32), across.astype(np.float32))


def _blocks_seen(seen: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, block: int) -> np.ndarray:
    """Blocks lying (nearly) wholly where the warped B image has data: at least :data:`MIN_BLOCK_SEEN` of
    their pixels (a block along A's frame edge that B misses by a row still measures its content)."""
    integral = cv2.integral(seen.astype(np.uint8))
    y0 = np.clip(np.rint(y_px - (block - 1) / 2).astype(int), 0, seen.shape[0] - block)
    x0 = np.clip(np.rint(x_px - (block - 1) / 2).astype(int), 0, seen.shape[1] - block)
    a, b = y0[:, None], x0[None, :]
    total = integral[a + block, b + block] - integral[a, b + block] - integral[a + block, b] + integral[a, b]
    return total >= MIN_BLOCK_SEEN * block * block


def fill_blocks(bp: BlockParallax, ground_inv_depth: np.ndarray | None = None, radius: int = 2) -> np.ndarray:
    """Step 2: inverse depth for every block: measured, else the (lower) median of the measured blocks
    within ``radius`` blocks, else the ground plane, else 0.  A median is one neighbour's surface; a mean
    of a near chart's blocks and one of the background beside it is neither (08:00 seed 5, chart at
    1.5 m: five chart blocks and one far block gave a surface 0.9 px behind the chart)."""
    w = np.where(bp.measured, bp.inv_depth_per_m, np.nan).astype(np.float64)
    stack = neighbourhood_stack(w, radius)
    has = np.isfinite(stack).any(axis=0)
    neighbours = np.full(w.shape, np.nan)
    if has.any():
        neighbours[has] = np.nanpercentile(stack[:, has], 50, axis=0, method="lower")
    out = np.where(bp.measured, w, neighbours)
    if ground_inv_depth is not None:
        out = np.where(np.isnan(out), ground_inv_depth, out)
    # nothing is beyond infinity: a negative inverse depth is measurement noise (or the rig model's residual,
    # which the per-direction offset at infinity takes up)
    return np.maximum(np.nan_to_num(out, nan=0.0), 0.0).astype(np.float32)


def matching_feature(gray: np.ndarray) -> np.ndarray:
    """Gradient magnitude of the square-rooted luminance: the cameras see the scene through different
    filters, so a patch can be brighter than its neighbour in A and darker in B, but its edges are
    where they are in both; correlating edge strength is immune to such contrast reversals."""
    s = np.sqrt(np.maximum(gray, 0)).astype(np.float32)
    gx = cv2.Sobel(s, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(s, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def local_ncc(a: np.ndarray, b: np.ndarray, window: int = NCC_WINDOW_PX) -> np.ndarray:
    """Normalised cross-correlation of ``a`` and ``b`` over a ``window`` box around each pixel (0 where flat)."""
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
    Correlating gradient magnitudes instead (this module's first version) doubles the frequency of a
    row of patches, so that a chart at 5 m matched itself 2 px off.
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
        """``image`` ``(H, W, C)`` float32 minus its local mean: the window statistics are then formed from
        small numbers, which float32 holds without cancellation next to the HDR sun (a window's covariances
        change only by the small variation of the local mean across it)."""
        return (image - _blur3(image, self.k)).astype(np.float32, copy=False)

    def prepare_b(self, image_b: np.ndarray) -> np.ndarray:
        """B's image as the score expects it: scaled like A and centred, once, before the levels move it."""
        return self.centred(as_channels(image_b) * np.float32(self.scale))

    def __call__(self, moved_b: np.ndarray) -> np.ndarray:
        """The score of B (:meth:`prepare_b`-ed, then moved) against A at every pixel, ``(H, W)`` float32.
        B's channels are filtered together (one box filter call per statistic for up to four channels)."""
        b = moved_b if moved_b.ndim == 3 else moved_b[..., None]
        if b.shape[-1] > 4:  # OpenCV filters at most four channels at once
            return np.mean([self(b[..., k]) for k in range(b.shape[-1])], axis=0).astype(np.float32)
        b = np.ascontiguousarray(b)
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
    """An image as ``(H, W, C)`` float32 with no NaN or infinity."""
    img = np.asarray(image, dtype=np.float32)
    return np.nan_to_num(img if img.ndim == 3 else img[..., None], nan=0.0, posinf=0.0, neginf=0.0)


def sweep_inverse_depth(ga: np.ndarray, gb: np.ndarray, field: np.ndarray, w_blocks: np.ndarray,
                        measured: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, step_px: float = SWEEP_STEP_PX,
                        max_levels: int = SWEEP_MAX_LEVELS,
                        window: int = NCC_WINDOW_PX) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: per-pixel inverse depth by a sweep along the epipolar lines (plane sweep, Collins 1996).

    Inverse depths ``w_k`` every ``step_px`` of parallax span the range of the block estimates; at each
    level B's resampled image is moved by ``w_k · e(p)`` and compared with A (:class:`LocalLinearScore`
    over a ``window``; :func:`local_ncc` for one-channel inputs); each pixel keeps the best level within
    the range of its 5 × 5 neighbouring blocks (± 4 steps: a block larger than an object mixes it with its
    background), refined
    by a parabola through the
    neighbouring levels.  Where nothing correlates (best correlation below :data:`SWEEP_MIN_NCC`: flat
    areas, noise) or no neighbouring block was measured, the pixel keeps its own block's value.  A prior
    must be beaten by a margin (:data:`SWEEP_ZERO_MARGIN`): infinity where the blocks around see infinity,
    else the block's value.  A pixel whose best match is not distinctive (another local maximum of the
    score comes within the margin: inside a uniform patch a few pixels wide, whose windows hold only
    edges along the line), or that matched nothing, takes the median depth of its distinctive neighbours
    (:func:`fill_from_neighbours`; choosing them by colour was tried and did not help at 3-px patches).
    Returns the inverse depth and the correlation reached (0 where ambiguous), both ``(H, W)`` float32.
    """
    h, w = ga.shape[:2]
    by = np.clip(np.rint(np.interp(np.arange(h), y_px, np.arange(y_px.size))).astype(int), 0, y_px.size - 1)
    bx = np.clip(np.rint(np.interp(np.arange(w), x_px, np.arange(x_px.size))).astype(int), 0, x_px.size - 1)
    e_len = np.linalg.norm(field[..., :2], axis=-1)
    valid = e_len[np.isfinite(e_len) & (e_len > 0)]
    if valid.size == 0:
        return w_blocks[by[:, None], bx[None, :]].astype(np.float32), np.zeros((h, w), np.float32)
    dw = step_px / float(np.median(valid))
    # blocks larger than an object measure a mixture of its depth and its background's: search beyond
    lo_b = ndimage.minimum_filter(w_blocks, size=SWEEP_RANGE_BLOCKS, mode="nearest") - SWEEP_MARGIN_STEPS * dw
    hi_b = ndimage.maximum_filter(w_blocks, size=SWEEP_RANGE_BLOCKS, mode="nearest") + SWEEP_MARGIN_STEPS * dw
    lo, hi = lo_b[by[:, None], bx[None, :]], hi_b[by[:, None], bx[None, :]]
    own = w_blocks[by[:, None], bx[None, :]]
    w_lo, w_hi = float(lo_b.min()), float(hi_b.max())
    n = int(np.ceil((w_hi - w_lo) / dw)) + 1
    if n > max_levels:
        dw = (w_hi - w_lo) / (max_levels - 1)
        n = max_levels
    levels = w_lo + dw * np.arange(n)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    fx, fy = field[..., 0].astype(np.float32), field[..., 1].astype(np.float32)
    # second order along the line when the field carries it (a near object's line curves: 0.2 px at 1 m)
    hx, hy = ((0.5 * field[..., 2]).astype(np.float32), (0.5 * field[..., 3]).astype(np.float32)) \
        if field.shape[-1] == 4 else (np.float32(0), np.float32(0))
    # shiftable windows (Bobick & Intille 1999): a pixel takes the best of all windows that contain it,
    # so near a depth edge it can use a window lying wholly on its own surface
    shift_kernel = np.ones((window, window), np.uint8)
    # several channels: the local linear score; one: normalised cross-correlation
    ga_raw, gb_raw = (ga, gb) if ga.ndim == 3 else (None, None)
    if ga.ndim == 3:
        score_of = LocalLinearScore(ga, window)
        gb = score_of.prepare_b(gb)
    else:
        def score_of(moved):
            return local_ncc(ga, moved, window)
    best = np.full((h, w), -np.inf, np.float32)
    best_raw = np.full((h, w), np.nan, np.float32)
    best_k = np.zeros((h, w), np.int32)
    left = np.full((h, w), np.nan, np.float32)
    right = np.full((h, w), np.nan, np.float32)
    prev = np.full((h, w), np.nan, np.float32)
    k_zero = int(np.argmin(np.abs(levels)))
    score_zero = np.full((h, w), -np.inf, np.float32)
    score_own = np.full((h, w), -np.inf, np.float32)
    rival = np.full((h, w), -np.inf, np.float32)
    top1 = np.full((h, w), -np.inf, np.float32)
    prev_sel = prev2_sel = np.full((h, w), -np.inf, np.float32)
    for k, wk in enumerate(levels):
        wk2 = np.float32(wk * wk)
        moved = cv2.remap(gb, xx + np.float32(wk) * fx + wk2 * hx, yy + np.float32(wk) * fy + wk2 * hy,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        raw = score_of(moved)
        score = cv2.dilate(raw, shift_kernel)
        # the sub-step parabola uses the centred window's scores (the same window at every level)
        right = np.where(best_k == k - 1, raw, right)
        if k == k_zero:
            score_zero = score
        at_own = np.abs(wk - own) <= dw / 2
        score_own = np.where(at_own, np.maximum(score_own, score), score_own)
        score_sel = np.where((wk >= lo) & (wk <= hi), score + np.where(at_own, 0.01, 0.0), -np.inf).astype(np.float32)
        better = score_sel > best
        # the two highest local maxima of the score over the levels: a match is distinctive when the best
        # beats every other peak by a margin (a broad peak's shoulders are not rivals; a flat curve, whose
        # every level is a peak, is ambiguous).  Level k - 1 is judged once level k is known.
        if k >= 1:
            top1, rival = _add_peak(top1, rival, np.where((prev_sel >= prev2_sel) & (prev_sel >= score_sel),
                                                          prev_sel, -np.inf))
        prev2_sel, prev_sel = prev_sel, score_sel
        left = np.where(better, prev, left)
        right = np.where(better, np.nan, right)
        best = np.where(better, score_sel, best)
        best_raw = np.where(better, raw, best_raw)
        best_k = np.where(better, k, best_k)
        prev = raw
    top1, rival = _add_peak(top1, rival, np.where(prev_sel >= prev2_sel, prev_sel, -np.inf))  # the last level
    # keep the block's value where nothing nearby was measured or the best match is not a real match
    near = ndimage.maximum_filter(measured.astype(np.uint8), size=3, mode="nearest")
    measured_near = near[by[:, None], bx[None, :]]
    flat = ~np.isfinite(best) | (best - 0.01 < SWEEP_MIN_NCC) | (measured_near == 0)
    centre = best - np.where(np.abs(levels[best_k] - own) <= dw / 2, 0.01, 0.0)
    den = left - 2 * best_raw + right
    peak = (best_raw >= left) & (best_raw >= right)
    curved = np.isfinite(den) & (den < -1e-6) & peak
    frac = np.where(curved, 0.5 * (left - right) / np.where(curved, den, -1.0), 0.0)
    out = levels[best_k] + np.clip(np.nan_to_num(frac), -0.5, 0.5) * dw
    out = np.where(flat, own, out)
    # a prior the pixel's own match must beat by a margin: infinity where the blocks around see (nearly)
    # infinity, else the block's value.  Smooth content (the sun's halo) correlates almost as well at
    # neighbouring levels and would otherwise wander by a fraction of a pixel; the inside of a small
    # uniform patch matches almost as well at several levels (a row of patches matches itself moved along
    # the row) and would take any of them
    zero_ok = (np.abs(levels[k_zero]) <= dw) & (lo <= 0) & (hi >= 0) & (np.abs(own) <= 2 * dw)
    prior = np.where(zero_ok, 0.0, own)
    score_prior = np.where(zero_ok, score_zero, score_own)
    at_prior = centre - score_prior < SWEEP_ZERO_MARGIN
    out = np.where(at_prior, prior, out).astype(np.float32)
    # a pixel whose match other levels reach almost as well (or that matched nothing) takes the depth of
    # its distinctive neighbours, unless it sits at infinity among blocks that see infinity
    unsure = flat | (best - rival < SWEEP_ZERO_MARGIN)
    ambiguous = unsure & ~(at_prior & zero_ok)
    out = fill_from_neighbours(out, ambiguous, ~ambiguous)
    # an unsure pixel left at infinity (its prior, or its neighbours' depth) may belong to a near object
    # whose windows saw only its edges along the line (the end of a post against the sky): it takes the
    # depth of its surface when B's colour there fits A's pixel and B's colour at infinity plainly does not.
    # Pixels that took a near neighbour's depth are left alone: inside a chart's 3-px patches one linear map
    # between the cameras misfits saturated colours, and a search would trade a patch for its neighbour
    at_infinity = unsure & (np.abs(out) * e_len < SWEEP_STEP_PX * 2)
    if ga_raw is not None and at_infinity.any():
        out = settle_by_colour(ga_raw, gb_raw, field, out, at_infinity, ~unsure, window)
    return cv2.medianBlur(out, 3), np.clip(np.where(ambiguous, 0.0, centre), 0.0, 1.0).astype(np.float32)


def moved_by_parallax(image: np.ndarray, field: np.ndarray, inv_depth: np.ndarray) -> np.ndarray:
    """``image`` (B on A's grid) sampled at ``p + w(p) e(p)`` (with the field's second order when it has
    one): what B saw at A's pixel ``p`` for the per-pixel inverse depth ``w``."""
    h, w = inv_depth.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    mx, my = _parallax_positions(xx, yy, field, inv_depth.astype(np.float32))
    return cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).reshape(image.shape)


def _parallax_positions(x: np.ndarray, y: np.ndarray, field: np.ndarray, inv_depth: np.ndarray):
    """``p + w e(p) (+ w²/2 · second order)``: where B saw the content of A's pixels ``(x, y)`` (float32);
    ``field`` is the epipolar field at those pixels."""
    mx = x + inv_depth * field[..., 0]
    my = y + inv_depth * field[..., 1]
    if field.shape[-1] == 4:
        mx += 0.5 * inv_depth * inv_depth * field[..., 2]
        my += 0.5 * inv_depth * inv_depth * field[..., 3]
    return mx.astype(np.float32, copy=False), my.astype(np.float32, copy=False)


def colour_map_a_to_b(a: np.ndarray, b: np.ndarray, sample: np.ndarray, max_samples: int = 20000) -> np.ndarray:
    """The direction's linear map ``M`` (``C_B × C_A``) with ``B ≈ M A`` over the ``sample`` pixels, fitted in
    relative terms (each pixel divided by its brightness in A, so that the HDR sun does not outweigh the
    rest): the cameras see through different filters, and over a direction one linear map predicts B's
    channels from A's to within the materials' spectral variety."""
    idx = np.flatnonzero(sample.ravel())
    if idx.size > max_samples:
        idx = idx[np.linspace(0, idx.size - 1, max_samples).astype(np.int64)]
    xa = a.reshape(-1, a.shape[-1])[idx].astype(np.float64)
    xb = b.reshape(-1, b.shape[-1])[idx].astype(np.float64)
    norm = np.linalg.norm(xa, axis=1)
    ok = norm > 0
    if ok.sum() < 4 * a.shape[-1]:
        return np.full((b.shape[-1], a.shape[-1]), np.nan)
    m, *_ = np.linalg.lstsq(xa[ok] / norm[ok, None], xb[ok] / norm[ok, None], rcond=None)
    return m.T


def _colour_residual(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Relative misfit ``|B − M A| / (|M A| + |B|)`` per pixel (0: B is what A predicts; 1: unrelated)."""
    pred = a @ m.T.astype(np.float32)
    num = np.linalg.norm(b - pred, axis=-1)
    den = np.linalg.norm(pred, axis=-1) + np.linalg.norm(b, axis=-1)
    return np.where(den > 0, num / np.maximum(den, 1e-30), 0.0).astype(np.float32)


def settle_by_colour(ga_raw: np.ndarray, gb_raw: np.ndarray, field: np.ndarray, current: np.ndarray,
                     todo: np.ndarray, reliable: np.ndarray, window: int = NCC_WINDOW_PX,
                     passes: int = 16) -> np.ndarray:
    """Where ``todo`` and B's colour at the current parallax plainly misfits A's pixel, take the depth of the
    pixel's surface: the median depth of the reliable pixels within a ``window`` whose colour in A is the
    pixel's (:data:`SAME_SURFACE_COLOUR`) and whose B colour fits -- their nearest or their median depth,
    whichever B's colour fits better -- if B's colour at that parallax fits the pixel (misfit halved).

    A pixel whose windows cannot tell its depth (the end of a post against the sky: an edge along the
    line) is still one surface, and B must show that surface's colour there.  The misfit is measured
    with one linear map from A's channels to B's (:func:`colour_map_a_to_b`, fitted on the ``reliable``
    pixels at their parallax) and must exceed :data:`COLOUR_MISFIT_MIN` and three times the reliable
    pixels' typical misfit.  Repeated up to ``passes`` times, switched pixels serving as reliable ones,
    so that the depth reaches into an object from its measured part.  A pixel with no such neighbour keeps
    its depth: searching the line for the best colour fit was tried (session 6) and gave far buildings and
    sky 20-30 px of parallax where one linear map between the cameras misfits their colours everywhere
    (a brick wall's repeated texture fits somewhere along any line).
    """
    a = as_channels(ga_raw)
    b = as_channels(gb_raw)
    out = current.astype(np.float32).copy()
    seen = moved_by_parallax(b, field, out)
    m = colour_map_a_to_b(a, seen, reliable & np.isfinite(out))
    if not np.isfinite(m).all():
        return out
    r_cur = _colour_residual(a, seen, m)
    typical = float(np.median(r_cur[reliable])) if reliable.any() else 0.0
    misfit = r_cur > max(COLOUR_MISFIT_MIN, 3 * typical)
    todo = todo & misfit
    known = reliable | ~misfit  # pixels whose colour fits at their depth vote for their surface
    h, w = out.shape
    half = window // 2
    for _ in range(passes):
        ys, xs = np.nonzero(todo)
        if ys.size == 0:
            break
        ap = a[ys, xs]
        votes = np.full((ys.size, window * window), np.nan, np.float32)
        for k, (dy, dx) in enumerate((dy, dx) for dy in range(-half, half + 1) for dx in range(-half, half + 1)):
            yq, xq = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            aq = a[yq, xq]
            same = (np.linalg.norm(ap - aq, axis=1)
                    <= SAME_SURFACE_COLOUR * (np.linalg.norm(ap, axis=1) + np.linalg.norm(aq, axis=1)))
            votes[:, k] = np.where(known[yq, xq] & same, out[yq, xq], np.nan)
        has = np.isfinite(votes).any(axis=1)
        if not has.any():
            break
        ys, xs, votes = ys[has], xs[has], votes[has]
        # the nearest and the median depth of the pixel's surface around it (a uniform object's pixels that
        # fit at the far depth too would outvote its measured part): the one at which B's colour fits best
        ap = a[ys, xs][None]
        cands = [np.nanmax(votes, axis=1).astype(np.float32), np.nanmedian(votes, axis=1).astype(np.float32)]
        fits = [_colour_residual(ap, _sample_moved(b, field, ys, xs, c)[None], m)[0] for c in cands]
        near_better = fits[0] <= fits[1]
        cand = np.where(near_better, cands[0], cands[1])
        r_cand = np.where(near_better, fits[0], fits[1])
        switch = r_cand < 0.5 * r_cur[ys, xs]
        if not switch.any():
            break
        ys, xs = ys[switch], xs[switch]
        out[ys, xs] = cand[switch]
        r_cur[ys, xs] = r_cand[switch]
        known[ys, xs] = True
        todo[ys, xs] = False
    return out


def _sample_moved(image: np.ndarray, field: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                  inv_depth: np.ndarray) -> np.ndarray:
    """:func:`moved_by_parallax` at the pixels ``(ys, xs)`` only, ``(n, C)``."""
    mx, my = _parallax_positions(xs.astype(np.float32), ys.astype(np.float32), field[ys, xs],
                                 inv_depth.astype(np.float32))
    out = cv2.remap(image, mx[None], my[None], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(xs.size, image.shape[-1])


def _add_peak(top1: np.ndarray, top2: np.ndarray, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Streaming update of the highest and second-highest local maxima (``-inf`` where none is new)."""
    top2 = np.where(peak > top1, np.maximum(top2, top1), np.maximum(top2, peak))
    return np.maximum(top1, peak), top2


def neighbourhood_stack(values: np.ndarray, radius: int) -> np.ndarray:
    """``((2r + 1)², H, W)``: every value of each pixel's ``(2r + 1)²`` neighbourhood (NaN beyond the border;
    NaN values stay NaN, so ``np.nan*`` reductions over axis 0 see only the known neighbours)."""
    h, w = values.shape
    padded = np.pad(values, radius, mode="constant", constant_values=np.nan)
    return np.stack([padded[dy:dy + h, dx:dx + w] for dy in range(2 * radius + 1) for dx in range(2 * radius + 1)])


def fill_from_neighbours(values: np.ndarray, fill: np.ndarray, sources: np.ndarray, radius: int = 2,
                         passes: int = 3) -> np.ndarray:
    """Replace the ``fill`` pixels by the median of the ``sources`` pixels within ``radius`` (repeated
    ``passes`` times, filled pixels serving as sources of the next pass, so that holes up to
    ``2 · radius · passes`` pixels wide close from their rims); pixels with none in reach keep their value."""
    out = values.astype(np.float32).copy()
    known = sources & ~fill
    todo = fill.copy()
    for _ in range(passes):
        if not todo.any() or not known.any():
            break
        stack = neighbourhood_stack(np.where(known, out, np.nan), radius)[:, todo]
        has = np.isfinite(stack).any(axis=0)
        if not has.any():
            break
        idx = np.flatnonzero(todo.ravel())[has]
        out.ravel()[idx] = np.nanmedian(stack[:, has], axis=0)
        known.ravel()[idx] = True
        todo.ravel()[idx] = False
    return out


@dataclass(frozen=True)
class Parallax:
    """Per-pixel result on A's grid: inverse depth (1/m), confidence (the correlation of A with B moved by
    that parallax, 0..1; 0 where flat) and occlusion."""

    inv_depth_per_m: np.ndarray
    confidence: np.ndarray
    occluded: np.ndarray
    blocks: BlockParallax

    def stats(self) -> dict:
        w = self.blocks.inv_depth_per_m[self.blocks.measured]
        across = self.blocks.across_px
        across = across[np.isfinite(across)] if across is not None else np.zeros(0)
        return {"n_blocks": int(self.blocks.measured.size), "n_measured": int(self.blocks.measured.sum()),
                "n_across_blocks": int(across.size),
                # in the analysis grid's px (binned for large sensors: see parallax_direction's degrees)
                "median_across_px": float(np.median(across)) if across.size else None,
                "occluded_fraction": float(self.occluded.mean()),
                "nearest_m": float(1.0 / w.max()) if w.size and w.max() > 0 else None,
                "median_perpendicular_px": float(np.median(np.abs(self.blocks.perpendicular_px[self.blocks.measured])))
                if w.size else None}


def parallax_map(image_a: np.ndarray, warped_b: np.ndarray, seen: np.ndarray, model_a: CameraModel,
                 baseline_m: np.ndarray, field: np.ndarray, *, block: int | None = None,
                 ground_inv_depth=None, min_confidence: float = PARALLAX_MIN_CONFIDENCE,
                 target_px: int = PARALLAX_ANALYSIS_PX) -> Parallax:
    """Steps 1-4 of the module docstring for one direction.

    ``image_a`` and ``warped_b`` are A's image and B's resampled onto A's grid (both (H, W, C) radiance);
    ``field`` is :func:`epipolar_field` at every pixel; ``ground_inv_depth(pixels)`` optionally gives
    the ground plane's inverse depth at A's pixels (0 above the horizon).  Images larger than about
    ``target_px`` are analysed binned (inverse depth does not depend on the pixel size; the sweep costs
    ~50 remaps per pixel), and the result is brought back to every pixel (nearest: never a blend of
    two surfaces) where the occlusion is evaluated.
    """
    f = analysis_factor(image_a.shape[1], image_a.shape[0], target_px)
    if f > 1:
        h, w = image_a.shape[:2]
        small_field = bin_image(field, f) / f
        small_seen = bin_image(seen.astype(np.float32), f) > 0.999
        ground_small = None
        if ground_inv_depth is not None:
            def ground_small(pixels):
                return ground_inv_depth(binned_to_full_px(pixels, f))
        low = parallax_map(bin_image(image_a, f), bin_image(warped_b, f), small_seen, model_a, baseline_m,
                           small_field, block=block, ground_inv_depth=ground_small,
                           min_confidence=min_confidence, target_px=10**9)
        rows = np.clip(np.arange(h) // f, 0, low.inv_depth_per_m.shape[0] - 1)
        cols = np.clip(np.arange(w) // f, 0, low.inv_depth_per_m.shape[1] - 1)
        inv_depth = low.inv_depth_per_m[rows[:, None], cols[None, :]]
        confidence = low.confidence[rows[:, None], cols[None, :]]
        return Parallax(inv_depth, confidence, _occluded(inv_depth, field), low.blocks)
    h, w = image_a.shape[:2]
    block = block or block_size_for(w, h)
    gray_a, gray_b = as_gray(image_a), as_gray(warped_b)
    bp = block_parallax(gray_a, gray_b, seen, field, block=block, min_confidence=min_confidence)
    ga, gb = as_channels(image_a), as_channels(warped_b)
    ground = None
    if ground_inv_depth is not None:
        gy, gx = np.meshgrid(bp.y_px, bp.x_px, indexing="ij")
        ground = ground_inv_depth(np.stack([gx, gy], axis=-1))
    wb = fill_blocks(bp, ground)
    inv_depth, confidence = sweep_inverse_depth(ga, gb, field, wb, bp.measured, bp.y_px, bp.x_px)
    inv_depth = np.maximum(inv_depth, 0.0)
    return Parallax(inv_depth.astype(np.float32), confidence.astype(np.float32), _occluded(inv_depth, field), bp)


def _occluded(inv_depth: np.ndarray, field: np.ndarray, e_len: np.ndarray | None = None) -> np.ndarray:
    """Step 4: pixels hidden from B by a nearer surface (z-buffer of the forward warp, nearness in px along
    the epipolar line); ``e_len``: the field's length, when the caller has it."""
    if e_len is None:
        e_len = np.hypot(field[..., 0], field[..., 1]).astype(np.float32)
    return _occlusion_zbuffer(inv_depth * field[..., 0], inv_depth * field[..., 1], inv_depth * e_len,
                              OCCLUSION_TOL_PX)


# ------------------------------------------------------------------------------ block disparity
#: Block-wise default: smaller blocks have fewer frequencies, so noise peaks are higher
#: (measured on 32 px blocks of pure sensor noise: 99th percentile 0.30, maximum 0.34).
DEFAULT_BLOCK_MIN_CONFIDENCE = 0.35
_BLOCK_CHUNK = 4096


@dataclass(frozen=True)
class DisparityMap:
    """Block-wise POC disparity of ``moving`` (camera B) relative to ``reference`` (camera A).

    Grid arrays are ``(ny, nx)`` with block centres at ``y_px[i], x_px[j]`` (pixel coordinates of
    the reference).  ``unreliable`` marks blocks with low confidence, a left-right inconsistency
    or an outlier against their neighbours; ``occluded`` is ``(H, W)``: reference pixels hidden in
    the moving image by a nearer surface (z-buffer forward warp of the block disparities).
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
        """Bilinear ``dx, dy, confidence`` and nearest-block ``unreliable`` at every reference pixel, ``(H, W)``."""
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


def _occlusion_zbuffer(dx_px: np.ndarray, dy_px: np.ndarray, nearness: np.ndarray, tol_px: float) -> np.ndarray:
    """Reference pixels whose target ``p + d(p)`` in the moving image is taken by a nearer pixel (z-buffer).

    A pixel is hidden only by one at least ``tol_px`` nearer, so only pixels more than ``tol_px`` nearer
    than the farthest can hide anything and only those are scattered into the buffer: the same result,
    at the cost of the near pixels only (most of a panorama is far)."""
    h, w = dx_px.shape
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
    through one batched ``rfft2`` per chunk, the band-limited POC and the vectorised peak fit of
    :func:`phase_correlate`; a second pass re-pairs every block with the moving block displaced by
    its rounded first-pass disparity.  Disparities follow the module convention (content at ``p`` in the
    reference is at ``p + d`` in the moving image) and include ``offset``; they must stay below
    about ``block / 3`` around ``offset`` for the first pass to find them.

    Masks on the block grid (``unreliable`` is their union, plus blocks that leave the image):

    - ``low_confidence``: peak height below ``min_confidence`` (flat regions, mixed motions);
    - ``inconsistent``: left-right check -- the disparity at ``p`` and the one found where ``p``
      lands, ``p + d(p)``, differ by more than ``consistency_tol_px`` (depth edges);
    - ``outlier``: more than ``outlier_tol_px`` from the 3 x 3 median of the neighbouring blocks.

    ``occluded`` (full resolution): reference pixels hidden in the moving image by a nearer
    surface -- a z-buffer forward warp of the nearest-block disparities, where nearness is the
    distance of the disparity from ``far_offset`` (default: the median disparity of reliable
    blocks, i.e. the background).  This is the paper's occlusion problem around close objects.
    """
    _check_options(window, band_limit, upsample, preprocess, fit_radius)
    ref, mov = _check_pair(reference, moving)
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
    a, sat_a = _prepare(ref, "reference", preprocess, saturation)
    b, sat_b = _prepare(mov, "moving", preprocess, saturation)
    if sat_a is not None:
        a = _fade_saturated(a, sat_a)
    if sat_b is not None:
        b = _fade_saturated(b, sat_b)

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
        blocks_a = _apply_window(view_a[org_y[sel], org_x[sel]], window)
        blocks_b = _apply_window(view_b[mov_y[sel], mov_x[sel]], window)
        dx[sel], dy[sel], conf[sel] = _poc_shift(blocks_a, blocks_b, band_limit, upsample, fit_radius)
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
    occluded = _occlusion_zbuffer(dx_px, dy_px, nearness, occlusion_tol_px)
    return DisparityMap(x_px=x_px, y_px=y_px, dx=dx, dy=dy, confidence=conf, unreliable=unreliable,
                        low_confidence=low, inconsistent=inconsistent, outlier=outlier, occluded=occluded,
                        block=int(block), step=int(step), shape=(int(shape[0]), int(shape[1])), offset=offset,
                        extras={"far_offset": far, "min_confidence": float(min_confidence)})
