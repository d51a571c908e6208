"""Per-pixel parallax of camera B against camera A along the rig's epipolar lines (beyond the paper).

Camera B sits ``c`` (the baseline, metres, head frame) from camera A, whose optical centre is the
head's rotation centre.  Once B's image is resampled onto A's pixel grid for points at infinity
(:func:`omnispectral.product.pairgeometry.warp_b_onto_a` with B's calibrated mounting), a point of A's pixel
``p`` at distance ``Z`` appears in the warped B image at

.. math::  p' = \\pi_A\\big(r_A(p) - w\\, c\\big) \\approx p + w\\, e(p) + \\tfrac{1}{2} w^2 h(p),
           \\qquad w = 1/Z,

it moves along the epipolar line through ``p`` by an amount set by one unknown per pixel, the
**inverse depth** ``w`` (1/m; 0 at infinity).  :func:`epipolar_field` gives that line's direction and
its pixels per unit of ``w`` (``e``, px · m, and optionally ``h``); :func:`parallax_map` measures ``w``
at every pixel:

1. block-wise POC (:func:`omnispectral.imaging.blockpoc.measure_blocks`) between A and the warped B;
   each reliable block's disparity is projected on the epipolar direction (the perpendicular part,
   which no depth explains, must be small: otherwise the block is rejected): :func:`block_parallax`;
2. blocks without a reliable measurement take the inverse depth of reliable neighbours (the median
   over 5 × 5 blocks), else of the ground plane (rays below the horizon: its height given, or fitted to the
   direction's measured blocks that look down, :func:`level_ground_prior`), else 0 (sky): :func:`fill_blocks`;
3. every pixel sweeps the inverse depths spanned by its 5 × 5 neighbouring blocks (every 0.25 px of
   parallax; its prior is interpolated between the blocks around it unless they differ by a depth step,
   :func:`block_prior`) and keeps the one whose warped-B neighbourhood matches A best
   (:class:`~omnispectral.imaging.similarity.LocalLinearScore`: how well B's channels are a linear
   function of A's over 11 × 11 px, which the different filters of the two cameras allow; parabolic
   sub-step refinement; shiftable windows: a pixel takes the depth of its own surface, never a blend of
   two); a pixel whose match is not distinctive takes its distinctive neighbours' depth, and one left
   at infinity whose B colour plainly misfits A takes its surface's depth by colour
   (:func:`settle_by_colour`): :func:`sweep_inverse_depth`;
4. a binned analysis is brought to full resolution by cells (:func:`upsampled_by_colour`), then pixels where
   B's colour misfits A's try the depths of the cells around them and, on edges across the line, parallaxes
   within a binned pixel of their own (:func:`settled_at_steps`);
5. pixels of A that B cannot see because a nearer surface hides them (z-buffer forward warp,
   :func:`omnispectral.imaging.blockpoc.occlusion_zbuffer`), and those where B plainly shows another surface
   than the one A sees (a near object outside A's frame in front of a flat background:
   :func:`sees_another_surface`), are flagged as occluded: the mosaic takes B's bands there from other
   directions.

References
----------
R. T. Collins, "A space-sweep approach to true multi-image matching", CVPR 1996 (plane sweep).
A. F. Bobick, S. S. Intille, "Large occlusion stereo", IJCV 33(3), 181-200, 1999 (shiftable windows).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import cv2
import numpy as np
from scipy import ndimage

from omnispectral.imaging.binning import analysis_factor, bin_image, binned_to_full_px
from omnispectral.imaging.blockpoc import block_size_for, measure_blocks, occlusion_zbuffer
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.registration import as_gray
from omnispectral.imaging.similarity import NCC_WINDOW_PX, LocalLinearScore, as_channels, local_ncc
from omnispectral.imaging.sweep_kernel import compiled_sweep

__all__ = ["COLOUR_MISFIT_MIN", "DEPTH_STEP_PX", "EDGE_MAX_FIT", "EDGE_MIN_MISFIT", "EDGE_MIN_RELATIVE_GRADIENT",
           "EDGE_SEARCH_COST_PER_PX", "EDGE_SEARCH_PX", "EDGE_SEARCH_STEP_PX", "GROUND_HEIGHT_PERCENTILE",
           "GROUND_MIN_BLOCKS",
           "GROUND_MIN_DEPRESSION_DEG", "MAX_PERPENDICULAR_PX", "MIN_ALONG_WEIGHT", "MIN_BLOCK_SEEN",
           "NEAREST_OBJECT_M", "OCCLUSION_HIDDEN", "OCCLUSION_OTHER_SURFACE", "OCCLUSION_TOL_PX",
           "OTHER_SURFACE_MISFIT", "OTHER_SURFACE_RADIUS", "PARALLAX_ANALYSIS_PX", "PARALLAX_MIN_CONFIDENCE",
           "SAME_SURFACE_COLOUR", "SETTLE_MIN_MISFIT", "SMOOTH_PRIOR_MAX_SPAN_PX", "STEP_SETTLE_GAIN",
           "SWEEP_MARGIN_STEPS", "SWEEP_MAX_LEVELS", "SWEEP_MIN_NCC", "SWEEP_RANGE_BLOCKS",
           "SWEEP_STEP_PX", "SWEEP_ZERO_MARGIN", "UPSAMPLE_DISTANCE_COST", "BlockParallax", "Parallax",
           "block_parallax", "block_prior", "colour_map_a_to_b", "could_be_shadowed", "epipolar_field", "fill_blocks",
           "fill_from_neighbours", "level_ground_prior", "moved_by_parallax", "neighbourhood_stack", "parallax_map",
           "sees_another_surface", "settle_by_colour", "settled_at_steps", "shifted_positions",
           "step_cell_pixels", "sweep_inverse_depth", "upsampled_by_colour"]

#: A block measures parallax when its structure measures shifts along the epipolar line at least this
#: well (``eᵀJe / |e|²`` with the normalised structure tensor J: 0 for an edge parallel to the line).
MIN_ALONG_WEIGHT = 0.3
#: Largest part of a block's disparity perpendicular to its epipolar line (px) that is still accepted.
MAX_PERPENDICULAR_PX = 0.75
#: Largest parallax spread (px of the analysed grid) of four neighbouring blocks over which the sweep's prior
#: is interpolated between them (:func:`block_prior`); beyond it they are a depth step and each pixel takes
#: its nearest block's value.
SMOOTH_PRIOR_MAX_SPAN_PX = 1.5
#: Parallax step (px) between the levels of the per-pixel sweep, and the most levels per direction.
SWEEP_STEP_PX = 0.25
SWEEP_MAX_LEVELS = 48
#: A pixel is occluded when a surface nearer by more than this parallax (px) lands on the same place in B.
OCCLUSION_TOL_PX = 1.0
#: Long side (px) at which the per-pixel parallax is analysed (larger images are binned).
PARALLAX_ANALYSIS_PX = 512
#: Smallest normalised correlation that counts as a match in the sweep (noise alone reaches ~0.3 on 11 px windows).
SWEEP_MIN_NCC = 0.5
#: Correlation by which a finite depth must beat infinity (and any other level far from it) in the sweep, at
#: full resolution (an analysis binned f times uses it / f: :func:`parallax_map`).
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
#: :func:`sees_another_surface`: radius of the neighbourhood whose reliable pixels of the pixel's colour in A
#: tell B's colour of that surface, as a fraction of the image's width (24 px of a 512-px analysis grid), and
#: the step (px) at which it is sampled; the fewest such pixels; how far apart (relative) their B colours may
#: be; how far (relative) B's colour at the pixel must be from theirs.
OTHER_SURFACE_RADIUS = 24 / 512
OTHER_SURFACE_STEP_PX = 3
OTHER_SURFACE_MIN_VOTES = 4
OTHER_SURFACE_MAX_SPREAD = 0.1
OTHER_SURFACE_MISFIT = 0.3
#: :func:`could_be_shadowed`: the nearest an object outside A's frame is taken to stand (m).
NEAREST_OBJECT_M = 1.0
#: Occlusion codes of :meth:`Parallax.occlusion_code`: B's view of the pixel hidden by a nearer surface (its
#: bands count only where no direction sees the surface), or B showing another surface there (not used).
OCCLUSION_HIDDEN = 1.0
OCCLUSION_OTHER_SURFACE = 2.0
#: :func:`upsampled_by_colour`: parallax span (full-resolution px) over 3 × 3 binned cells that makes a depth step,
#: and the cost per binned cell of distance added to the colour distance (ties go to the nearest cell).
DEPTH_STEP_PX = 0.5
UPSAMPLE_DISTANCE_COST = 0.02
#: :func:`settled_at_steps`: a pixel whose B colour misfits A's by more than ``SETTLE_MIN_MISFIT`` (relative,
#: :func:`_colour_residual`) tries other depths and switches to one at which the misfit is below ``STEP_SETTLE_GAIN``
#: times its own.  Beside a depth step it tries its 3 × 3 binned cells' values; on an edge of A across the
#: epipolar line (A's brightness changing along the line by at least ``EDGE_MIN_RELATIVE_GRADIENT`` of itself
#: per pixel) with a misfit above ``EDGE_MIN_MISFIT``, parallaxes within ``EDGE_SEARCH_PX`` of its own
#: (full-resolution px: a binned pixel, about what a binned sweep cannot tell from infinity) every
#: ``EDGE_SEARCH_STEP_PX``, each px away costing ``EDGE_SEARCH_COST_PER_PX`` of misfit (the nearest of equal
#: fits), and only when the fit reached is below ``EDGE_MAX_FIT`` (a chart's patch never takes its neighbour's
#: depth because one linear map misfits its saturated colour).
STEP_SETTLE_GAIN = 0.7
SETTLE_MIN_MISFIT = 0.05
EDGE_MIN_RELATIVE_GRADIENT = 0.1
EDGE_MIN_MISFIT = 0.1
EDGE_SEARCH_PX = 4.0
EDGE_SEARCH_STEP_PX = 0.5
EDGE_SEARCH_COST_PER_PX = 0.02
EDGE_MAX_FIT = 0.1
#: :func:`level_ground_prior`: blocks looking at least this far below the horizon (degrees) tell the ground's
#: depth below the head; at least this many measured ones are needed; the percentile of their heights taken
#: (objects standing on the ground are nearer than it along the same ray: their heights fall below the ground's).
GROUND_MIN_DEPRESSION_DEG = 5.0
GROUND_MIN_BLOCKS = 5
GROUND_HEIGHT_PERCENTILE = 75.0
#: Longest row of positions handed to ``cv2.remap`` at once (its maps must be narrower than 32767).
_REMAP_ROW = 4096
#: Inverse depth change (1/m) used for the finite difference of the epipolar field.
_DW_PER_M = 0.01
#: The eight neighbours of a pixel (row and column steps).
_NEIGHBOURS_DY = np.array([-1, -1, -1, 0, 0, 1, 1, 1])
_NEIGHBOURS_DX = np.array([-1, 0, 1, -1, 1, -1, 0, 1])


def epipolar_field(model_a: CameraModel, baseline_m: np.ndarray, pixels: np.ndarray | None = None,
                   second_order: bool = False) -> np.ndarray:
    """A-pixel displacement per unit inverse depth (px · m) at ``pixels`` (default: every pixel).

    The content of A's pixel ``p`` at inverse depth ``w`` lies at ``p + w · e(p)`` (to first order) in
    B's image resampled onto A's grid for points at infinity; ``e`` is the central difference of
    ``π_A(r_A(p) ∓ δw · c)`` (``δw = 0.01`` 1/m).  With ``second_order`` the second derivative ``h`` is
    added (``p + w e + w² h / 2``; at 1 m on the small rig the first-order position is 0.2 px off, the
    second-order one 0.002 px).

    Parameters
    ----------
    model_a
        Camera A's model (pan = tilt = 0).
    baseline_m
        Camera B's optical centre relative to A's in the world frame at pan = tilt = 0 (m), ``(3,)``.
    pixels
        ``(..., 2)`` pixel positions ``(x, y)`` of A; default: every pixel, ``(H, W, 2)``.
    second_order
        Also return the second derivative.

    Returns
    -------
    numpy.ndarray
        ``(..., 2)`` ``e`` (px · m), or ``(..., 4)`` ``(e, h)`` (``h`` in px · m²) with ``second_order``.
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
    """Exact position in the warped B image of A's ``pixels`` at inverse depth ``w``: ``π_A(r_A(p) − w c)``.

    Parameters
    ----------
    model_a
        Camera A's model (pan = tilt = 0).
    baseline_m
        Camera B's optical centre relative to A's (m), ``(3,)``.
    pixels
        ``(..., 2)`` pixel positions ``(x, y)`` of A.
    inv_depth_per_m
        Inverse depth ``w`` (1/m), broadcastable to ``pixels.shape[:-1]``.

    Returns
    -------
    numpy.ndarray
        ``(..., 2)`` positions (px of A's grid).
    """
    rays, _ = model_a.pixel_to_world(pixels, 0.0, 0.0)
    shifted = rays - np.asarray(inv_depth_per_m, np.float64)[..., None] * np.asarray(baseline_m, np.float64)
    out, _ = model_a.world_to_pixel(shifted, 0.0, 0.0, margin_px=None)
    return out


@dataclass(frozen=True)
class BlockParallax:
    """Block-grid inverse depth (:func:`block_parallax`): centres, inverse depth and what was measured.

    Attributes
    ----------
    y_px, x_px : numpy.ndarray
        Block centres (px), ``(ny,)`` and ``(nx,)``.
    inv_depth_per_m : numpy.ndarray
        ``(ny, nx)`` float32 inverse depth (1/m; 0 where not measured).
    measured : numpy.ndarray
        ``(ny, nx)`` boolean, blocks whose inverse depth was measured.
    confidence : numpy.ndarray
        ``(ny, nx)`` float32 POC peak height of the block measurement.
    perpendicular_px : numpy.ndarray
        ``(ny, nx)`` float32, the J-norm (px) of the part of the block's shift that no depth explains.
    across_px : numpy.ndarray or None
        ``(ny, nx)`` float32, the shift no depth explains (px, J-norm) on reliable blocks with structure
        across the epipolar lines, NaN elsewhere: whether the rig model fits this direction at all.
    """

    y_px: np.ndarray
    x_px: np.ndarray
    inv_depth_per_m: np.ndarray
    measured: np.ndarray
    confidence: np.ndarray
    perpendicular_px: np.ndarray
    #: the shift no depth explains (px, J-norm), on reliable blocks with structure across the epipolar lines
    #: (``pᵀJp / |e|² ≥ 0.3``, ``p ⟂ e``), whatever its size; NaN elsewhere.  Edges (nearly) parallel to the
    #: lines count with their whole measured shift unless a parallax within the sweep's reach (up to
    #: ``SWEEP_MAX_LEVELS · SWEEP_STEP_PX``) explains it.  Says whether the rig model fits
    #: this direction at all
    across_px: np.ndarray | None = None


def block_parallax(gray_a: np.ndarray, warped_b: np.ndarray, seen: np.ndarray, field: np.ndarray, *,
                   block: int, min_confidence: float = PARALLAX_MIN_CONFIDENCE,
                   max_perpendicular_px: float = MAX_PERPENDICULAR_PX) -> BlockParallax:
    """Step 1 of the module docstring: reliable blocks' inverse depth along their epipolar lines.

    The blocks' shifts (:func:`~omnispectral.imaging.blockpoc.measure_blocks`) are projected on the
    epipolar direction ``e`` with the block's normalised structure tensor ``J``:
    ``w = eᵀJd / eᵀJe``; the rest ``d − w e`` (which no depth explains) must be small.

    Parameters
    ----------
    gray_a, warped_b
        ``(H, W)`` grey images of camera A and of camera B resampled onto A's grid.
    seen
        ``(H, W)`` boolean, where the warped B image has data.
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` at every pixel (px · m).
    block
        Block side (px).
    min_confidence
        Smallest POC peak height of a reliable block.
    max_perpendicular_px
        Largest accepted part of a block's shift perpendicular to its epipolar line (px).

    Returns
    -------
    BlockParallax
    """
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
    # an edge (nearly) parallel to the line: all of its shift is across unless a depth the sweep could reach
    # explains it (a near post 20° off the line, 6 px of parallax, moves its edge 2 px across); beyond that
    # the J-projection above would "explain" any shift with w → ∞
    whole = np.sqrt(np.maximum(dx * (jxx * dx + jxy * dy) + dy * (jxy * dx + jyy * dy), 0.0))
    parallax_px = w * e_len
    reachable = (parallax_px >= -SWEEP_STEP_PX) & (parallax_px <= SWEEP_MAX_LEVELS * SWEEP_STEP_PX)
    across = np.where(usable & (across_weight >= MIN_ALONG_WEIGHT),
                      np.where((along_weight >= MIN_ALONG_WEIGHT) | reachable, perp, whole), np.nan)
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
    """Step 2: inverse depth for every block.

    Measured, else the (lower) median of the measured blocks within ``radius`` blocks, else the ground
    plane, else 0.  A median is one neighbour's surface; a mean of a near chart's blocks and one of the
    background beside it is neither (08:00 seed 5, chart at 1.5 m: five chart blocks and one far block
    gave a surface 0.9 px behind the chart).  Negative values are clamped to 0 (nothing is beyond
    infinity).

    Parameters
    ----------
    bp
        The block measurements.
    ground_inv_depth
        Optional ``(ny, nx)`` inverse depth (1/m) of the ground plane at the block centres (0 above the
        horizon).
    radius
        Neighbourhood radius (blocks).

    Returns
    -------
    numpy.ndarray
        ``(ny, nx)`` float32 inverse depth (1/m), ``>= 0``.
    """
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


def level_ground_prior(bp: BlockParallax, down: np.ndarray) -> np.ndarray | None:
    """Step 2's ground plane when its height is not known: fitted to the direction's own measured blocks.

    A level ground ``h`` below the head is seen along a ray that points ``sin δ = down`` below the horizon
    at inverse depth ``w = down / h``; each measured block below the horizon gives ``h = down / w``.  Things
    standing on the ground (posts, walls, the chart) are nearer along their rays, so their heights fall
    short of the ground's: the :data:`GROUND_HEIGHT_PERCENTILE` th percentile is taken.  Without a ground
    prior a uniform stretch of ground between two edges (a shadow on a plate 2.5 m away, 29 px of parallax at
    full scale) keeps infinity, and B's edge lands that far from A's.

    Parameters
    ----------
    bp
        The block measurements.
    down
        ``(ny, nx)`` sine of each block centre's ray below the horizon (``≤ 0`` above it).

    Returns
    -------
    numpy.ndarray or None
        ``(ny, nx)`` float32 inverse depth (1/m) of the fitted ground (0 above the horizon), or ``None`` when
        fewer than :data:`GROUND_MIN_BLOCKS` measured blocks look down.
    """
    down = np.asarray(down, np.float64)
    use = bp.measured & (down >= np.sin(np.radians(GROUND_MIN_DEPRESSION_DEG))) & (bp.inv_depth_per_m > 0)
    if use.sum() < GROUND_MIN_BLOCKS:
        return None
    height_m = float(np.percentile(down[use] / bp.inv_depth_per_m[use], GROUND_HEIGHT_PERCENTILE))
    return (np.maximum(down, 0.0) / height_m).astype(np.float32)


def block_prior(w_blocks: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, h: int, w: int,
                max_span: float) -> np.ndarray:
    """``(H, W)`` float32 per-pixel prior from the block values: bilinear between the four block centres around a
    pixel where their values span at most ``max_span`` (a smooth surface: inverse depth is affine in the ray on
    a plane, so a slanted ground's blocks step by a pixel or two of parallax that no pixel between them has),
    else the nearest block's value (a depth step: a blend would be neither surface).

    Parameters
    ----------
    w_blocks
        ``(ny, nx)`` inverse depth of every block (1/m, :func:`fill_blocks`).
    y_px, x_px
        Block centres (px), increasing.
    h, w
        The image's size (px).
    max_span
        Largest spread of the four values (1/m) that is interpolated.
    """
    def axis(centres: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        pos = np.interp(np.arange(n), centres, np.arange(centres.size))
        i0 = np.clip(np.floor(pos).astype(int), 0, max(centres.size - 2, 0))
        i1 = np.minimum(i0 + 1, centres.size - 1)
        return i0, i1, np.clip(pos - i0, 0.0, 1.0).astype(np.float32)

    y0, y1, fy = axis(y_px, h)
    x0, x1, fx = axis(x_px, w)
    wb = w_blocks.astype(np.float32)
    c00, c01 = wb[y0[:, None], x0[None, :]], wb[y0[:, None], x1[None, :]]
    c10, c11 = wb[y1[:, None], x0[None, :]], wb[y1[:, None], x1[None, :]]
    fy, fx = fy[:, None], fx[None, :]
    smooth = (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy
    span = np.maximum(np.maximum(c00, c01), np.maximum(c10, c11)) - np.minimum(np.minimum(c00, c01),
                                                                             np.minimum(c10, c11))
    by = np.where(fy < 0.5, y0[:, None], y1[:, None])
    bx = np.where(fx < 0.5, x0[None, :], x1[None, :])
    return np.where(span <= max_span, smooth, wb[by, bx]).astype(np.float32)


def sweep_inverse_depth(ga: np.ndarray, gb: np.ndarray, field: np.ndarray, w_blocks: np.ndarray,
                        measured: np.ndarray, y_px: np.ndarray, x_px: np.ndarray, step_px: float = SWEEP_STEP_PX,
                        max_levels: int = SWEEP_MAX_LEVELS, window: int = NCC_WINDOW_PX,
                        zero_margin: float = SWEEP_ZERO_MARGIN) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: per-pixel inverse depth by a sweep along the epipolar lines (plane sweep, Collins 1996).

    Inverse depths ``w_k`` every ``step_px`` of parallax span the range of the block estimates; at each
    level B's resampled image is moved by ``w_k · e(p)`` and compared with A
    (:class:`~omnispectral.imaging.similarity.LocalLinearScore` over a ``window``;
    :func:`~omnispectral.imaging.similarity.local_ncc` for one-channel inputs); each pixel keeps the best
    level within the range of its 5 × 5 neighbouring blocks (± 4 steps: a block larger than an object
    mixes it with its background), refined by a parabola through the neighbouring levels.  Where nothing
    correlates (best correlation below :data:`SWEEP_MIN_NCC`: flat areas, noise) or no neighbouring block
    was measured, the pixel keeps the blocks' value at its place (:func:`block_prior`: interpolated between
    the four blocks around it on a smooth surface, whose blocks on a slanted ground step by 2 px of parallax at
    full scale; the nearest block's across a depth step).  A prior must be beaten by a margin
    (``zero_margin``, :data:`SWEEP_ZERO_MARGIN` at full resolution): infinity where the blocks around see
    infinity, else the blocks' value.
    A pixel whose best match is not distinctive (another local maximum of the score comes within the
    margin: inside a uniform patch a few pixels wide, whose windows hold only edges along the line), or
    that matched nothing, takes the median depth of its distinctive neighbours
    (:func:`fill_from_neighbours`; choosing them by colour was tried and did not help at 3-px patches).

    Parameters
    ----------
    ga, gb
        Camera A's image and camera B's resampled onto A's grid, ``(H, W, C)`` (local linear score) or
        ``(H, W)`` (normalised cross-correlation).
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` (px · m; second order used when present).
    w_blocks
        ``(ny, nx)`` inverse depth of every block (1/m, :func:`fill_blocks`).
    measured
        ``(ny, nx)`` boolean, blocks whose inverse depth was measured.
    y_px, x_px
        Block centres (px).
    step_px
        Parallax step (px) between levels (at the median field length).
    max_levels
        Most levels.
    window
        Side (px) of the matching window.
    zero_margin
        Score by which a level must beat the prior, and the best level any other peak, to be taken.

    Returns
    -------
    inv_depth : numpy.ndarray
        ``(H, W)`` float32 inverse depth (1/m), 3 × 3 median filtered.
    confidence : numpy.ndarray
        ``(H, W)`` float32 correlation reached, 0..1 (0 where ambiguous).
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
    own = block_prior(w_blocks, y_px, x_px, h, w, SMOOTH_PRIOR_MAX_SPAN_PX / float(np.median(valid)))
    w_lo, w_hi = float(lo_b.min()), float(hi_b.max())
    n = int(np.ceil((w_hi - w_lo) / dw)) + 1
    if n > max_levels:
        dw = (w_hi - w_lo) / (max_levels - 1)
        n = max_levels
    levels = w_lo + dw * np.arange(n)
    fx, fy = field[..., 0].astype(np.float32), field[..., 1].astype(np.float32)
    # second order along the line when the field carries it (a near object's line curves: 0.2 px at 1 m)
    hx, hy = ((0.5 * field[..., 2]).astype(np.float32), (0.5 * field[..., 3]).astype(np.float32)) \
        if field.shape[-1] == 4 else (np.zeros((h, w), np.float32), np.zeros((h, w), np.float32))
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
    k_zero = int(np.argmin(np.abs(levels)))
    st = _sweep_state(h, w)
    kernels = compiled_sweep()
    map_x, map_y = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) if kernels is None else (None, None)
    update = kernels.level_update if kernels is not None else _sweep_level_numpy
    state = [getattr(st, name) for name in _SWEEP_STATE]
    for k, wk in enumerate(levels):
        wk2 = np.float32(wk * wk)
        if kernels is not None:
            kernels.moved_positions(np.float32(wk), wk2, fx, fy, hx, hy, map_x, map_y)
        else:
            map_x, map_y = xx + np.float32(wk) * fx + wk2 * hx, yy + np.float32(wk) * fy + wk2 * hy
        moved = cv2.remap(gb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        raw = np.asarray(score_of(moved), np.float32)
        score = cv2.dilate(raw, shift_kernel)
        update(k, wk, dw / 2, k == k_zero, raw, score, lo, hi, own, *state)
    best, best_raw, best_k, left, right = st.best, st.best_raw, st.best_k, st.left, st.right
    score_zero, score_own, top1, rival, prev_sel, prev2_sel = (st.score_zero, st.score_own, st.top1, st.rival,
                                                               st.prev_sel, st.prev2_sel)
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
    at_prior = centre - score_prior < zero_margin
    out = np.where(at_prior, prior, out).astype(np.float32)
    # a pixel whose match other levels reach almost as well (or that matched nothing) takes the depth of
    # its distinctive neighbours, unless it sits at infinity among blocks that see infinity
    unsure = flat | (best - rival < zero_margin)
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


#: The sweep's running per-pixel state, in the order the level updates take it, with its value before the first
#: level (float32; ``best_k`` int32).
_SWEEP_STATE = {"best": -np.inf, "best_raw": np.nan, "best_k": 0, "left": np.nan, "right": np.nan, "prev": np.nan,
                "score_zero": -np.inf, "score_own": -np.inf, "top1": -np.inf, "rival": -np.inf, "prev_sel": -np.inf,
                "prev2_sel": -np.inf}


def _sweep_state(h: int, w: int) -> SimpleNamespace:
    """The sweep's running per-pixel state before its first level (:func:`sweep_inverse_depth`)."""
    return SimpleNamespace(**{name: np.full((h, w), value, np.int32 if name == "best_k" else np.float32)
                              for name, value in _SWEEP_STATE.items()})


def _sweep_level_numpy(k, wk, half_dw, at_zero, raw, score, lo, hi, own, best, best_raw, best_k, left, right,
                       prev, score_zero, score_own, top1, rival, prev_sel, prev2_sel) -> None:
    """One level of :func:`sweep_inverse_depth`'s bookkeeping, in place: the best level so far (a level counts
    within the pixel's range ``[lo, hi]``, at its block's own depth with a 0.01 bonus), the centred scores on
    both sides of it (for the parabola), the scores at infinity and at the block's depth, and the two highest
    local maxima of the score curve (level ``k - 1`` is judged once level ``k`` is known).  The compiled
    kernel (:mod:`omnispectral.imaging.sweep_kernel`) does the same operations in one pass."""
    np.copyto(right, raw, where=best_k == k - 1)
    if at_zero:
        np.copyto(score_zero, score)
    at_own = np.abs(wk - own) <= half_dw
    np.copyto(score_own, np.maximum(score_own, score), where=at_own)
    score_sel = np.where((wk >= lo) & (wk <= hi), score + np.where(at_own, 0.01, 0.0), -np.inf).astype(np.float32)
    better = score_sel > best
    if k >= 1:
        t1, t2 = _add_peak(top1, rival, np.where((prev_sel >= prev2_sel) & (prev_sel >= score_sel), prev_sel,
                                                 -np.inf))
        np.copyto(top1, t1)
        np.copyto(rival, t2)
    np.copyto(prev2_sel, prev_sel)
    np.copyto(prev_sel, score_sel)
    np.copyto(left, prev, where=better)
    np.copyto(right, np.float32(np.nan), where=better)
    np.copyto(best, score_sel, where=better)
    np.copyto(best_raw, raw, where=better)
    np.copyto(best_k, k, where=better)
    np.copyto(prev, raw)


def moved_by_parallax(image: np.ndarray, field: np.ndarray, inv_depth: np.ndarray) -> np.ndarray:
    """What B saw at A's pixel ``p`` for the per-pixel inverse depth ``w``.

    ``image`` (B on A's grid) sampled bilinearly at ``p + w(p) e(p)`` (``+ w² h / 2`` when the field
    carries the second order).

    Parameters
    ----------
    image
        ``(H, W)`` or ``(H, W, C)`` float32, camera B's image resampled onto A's grid.
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` (px · m).
    inv_depth
        ``(H, W)`` inverse depth (1/m).

    Returns
    -------
    numpy.ndarray
        Same shape as ``image``.
    """
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
    """The direction's linear map ``M`` (``C_B × C_A``) with ``B ≈ M A`` over the ``sample`` pixels.

    Fitted by least squares in relative terms (each pixel divided by its brightness in A, so that the HDR
    sun does not outweigh the rest): the cameras see through different filters, and over a direction one
    linear map predicts B's channels from A's to within the materials' spectral variety.

    Parameters
    ----------
    a, b
        ``(H, W, C_A)`` and ``(H, W, C_B)`` images of camera A and (moved) camera B.
    sample
        ``(H, W)`` boolean, the pixels to fit on.
    max_samples
        At most this many pixels (evenly spaced among the sample) enter the fit.

    Returns
    -------
    numpy.ndarray
        ``(C_B, C_A)`` float64; all NaN when fewer than ``4 C_A`` usable pixels.
    """
    idx = _evenly_spaced(np.flatnonzero(sample.ravel()), max_samples)
    xa = a.reshape(-1, a.shape[-1])[idx].astype(np.float64)
    xb = b.reshape(-1, b.shape[-1])[idx].astype(np.float64)
    norm = np.linalg.norm(xa, axis=1)
    ok = norm > 0
    if ok.sum() < 4 * a.shape[-1]:
        return np.full((b.shape[-1], a.shape[-1]), np.nan)
    m, *_ = np.linalg.lstsq(xa[ok] / norm[ok, None], xb[ok] / norm[ok, None], rcond=None)
    return m.T


def _evenly_spaced(idx: np.ndarray, max_n: int) -> np.ndarray:
    """At most ``max_n`` of ``idx``, evenly spaced (all of them when there are fewer)."""
    return idx[np.linspace(0, idx.size - 1, max_n).astype(np.int64)] if idx.size > max_n else idx


def _colour_residual(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Relative misfit ``|B − M A| / (|M A| + |B|)`` per pixel (0: B is what A predicts; 1: unrelated)."""
    pred = a @ m.T.astype(np.float32)
    d = b - pred
    num = np.sqrt(np.einsum("...c,...c->...", d, d))
    den = np.sqrt(np.einsum("...c,...c->...", pred, pred)) + np.sqrt(np.einsum("...c,...c->...", b, b))
    return np.where(den > 0, num / np.maximum(den, 1e-30), 0.0).astype(np.float32)


def settle_by_colour(ga_raw: np.ndarray, gb_raw: np.ndarray, field: np.ndarray, current: np.ndarray,
                     todo: np.ndarray, reliable: np.ndarray, window: int = NCC_WINDOW_PX,
                     passes: int = 16) -> np.ndarray:
    """Give pixels whose B colour plainly misfits A's the depth of their surface.

    Where ``todo`` and B's colour at the current parallax plainly misfits A's pixel, take the median
    depth of the reliable pixels within a ``window`` whose colour in A is the pixel's
    (:data:`SAME_SURFACE_COLOUR`) and whose B colour fits -- their nearest or their median depth,
    whichever B's colour fits better -- if B's colour at that parallax fits the pixel (misfit halved).

    A pixel whose windows cannot tell its depth (the end of a post against the sky: an edge along the
    line) is still one surface, and B must show that surface's colour there.  The misfit is measured
    with one linear map from A's channels to B's (:func:`colour_map_a_to_b`, fitted on the ``reliable``
    pixels at their parallax) and must exceed :data:`COLOUR_MISFIT_MIN` and three times the reliable
    pixels' typical misfit.  Repeated up to ``passes`` times, switched pixels serving as reliable ones,
    so that the depth reaches into an object from its measured part.  A pixel with no such neighbour keeps
    its depth: searching the line for the best colour fit was tried and gave far buildings and
    sky 20-30 px of parallax where one linear map between the cameras misfits their colours everywhere
    (a brick wall's repeated texture fits somewhere along any line).

    Parameters
    ----------
    ga_raw, gb_raw
        ``(H, W, C)`` images of camera A and of camera B resampled onto A's grid.
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` (px · m).
    current
        ``(H, W)`` current inverse depth (1/m).
    todo
        ``(H, W)`` boolean, the pixels that may change.
    reliable
        ``(H, W)`` boolean, pixels whose depth is trusted.
    window
        Side (px) of the neighbourhood that votes.
    passes
        Most repetitions.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 inverse depth (1/m).
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
    a_norm = np.linalg.norm(a, axis=-1)
    for _ in range(passes):
        ys, xs = np.nonzero(todo)
        if ys.size == 0:
            break
        ap, ap_norm = a[ys, xs], a_norm[ys, xs]
        votes = np.full((ys.size, window * window), np.nan, np.float32)
        for k, (dy, dx) in enumerate((dy, dx) for dy in range(-half, half + 1) for dx in range(-half, half + 1)):
            yq, xq = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            same = _same_colour(ap, a[yq, xq], ap_norm, a_norm[yq, xq])
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


def _same_colour(p: np.ndarray, q: np.ndarray, p_norm: np.ndarray, q_norm: np.ndarray) -> np.ndarray:
    """Whether colours ``p`` and ``q`` ``(..., C)`` (with their norms) are one surface's
    (:data:`SAME_SURFACE_COLOUR`)."""
    d = p - q
    return np.einsum("...c,...c->...", d, d) <= (SAME_SURFACE_COLOUR * (p_norm + q_norm)) ** 2


def _b_edges_without_a(a: np.ndarray, a_norm: np.ndarray, unit_b: np.ndarray, unit_norm: np.ndarray,
                       usable: np.ndarray) -> np.ndarray:
    """Pixels beside a change of B's colour (relative to A's brightness) where A's colour does not change."""
    h, w = usable.shape
    out = np.zeros((h, w), bool)
    for sl_p, sl_q in (((slice(None), slice(0, w - 1)), (slice(None), slice(1, w))),
                       ((slice(0, h - 1), slice(None)), (slice(1, h), slice(None)))):
        same_b = _same_colour(unit_b[sl_p], unit_b[sl_q], unit_norm[sl_p], unit_norm[sl_q])
        step = usable[sl_p] & usable[sl_q] & ~same_b & _same_colour(a[sl_p], a[sl_q], a_norm[sl_p], a_norm[sl_q])
        out[sl_p] |= step
        out[sl_q] |= step
    return out


def could_be_shadowed(inv_depth: np.ndarray, field: np.ndarray) -> np.ndarray:
    """Pixels where B can see a nearer surface than the one A sees: a surface whose parallax exceeds the pixel's
    by at least its distance from it (at 2ⁿ px, by half of that), or within the largest parallax of the frame's
    border (an object outside A's frame).

    Elsewhere B sees A's surface or nothing at all, so a B colour that differs from what A's colour leads one to
    expect is the surface's own (a metameric patch only B tells apart), never another surface.

    Parameters
    ----------
    inv_depth
        ``(H, W)`` inverse depth (1/m).
    field
        ``(H, W, 2+)`` :func:`epipolar_field` (px · m).

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` boolean.
    """
    e_len = np.nan_to_num(np.hypot(field[..., 0], field[..., 1]))
    parallax_px = (np.nan_to_num(inv_depth) * e_len).astype(np.float32)
    h, w = parallax_px.shape
    out = np.zeros((h, w), bool)
    reach = int(np.ceil(parallax_px.max())) if parallax_px.size else 0
    level = 1
    while level <= 2 * reach:
        disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * level + 1, 2 * level + 1))
        out |= cv2.dilate(parallax_px, disk) - parallax_px >= level / 2
        level *= 2
    # an object outside A's frame as near as NEAREST_OBJECT_M
    border = max(reach, int(np.ceil(e_len.max() / NEAREST_OBJECT_M)) if e_len.size else 0)
    if border >= 1:
        out[:border], out[-border:], out[:, :border], out[:, -border:] = True, True, True, True
    return out



def sees_another_surface(ga_raw: np.ndarray, gb_raw: np.ndarray, field: np.ndarray, inv_depth: np.ndarray,
                         reliable: np.ndarray, radius: float = OTHER_SURFACE_RADIUS,
                         step: int = OTHER_SURFACE_STEP_PX, grow_passes: int = 128) -> np.ndarray:
    """Pixels where camera B, at the pixel's parallax, shows another surface than the one A sees there.

    A near object that A's frame does not show (or shows at a wrong depth) can stand in front of the
    background in B's view (only within its parallax of it: :func:`could_be_shadowed`, which keeps a
    metameric patch that only B tells apart): no z-buffer of A's depths flags it, and a flat background
    matches B equally badly at every depth, so the sweep keeps an unsure depth and B's bands there are the
    object's.  The surface tells: the reliable pixels (distinctive matches) of the pixel's colour in A within
    ``radius`` (a fraction of the image's width: the same angle on any sensor) show B's colour of that surface
    (per unit of A's brightness); where they agree among themselves (spread below
    :data:`OTHER_SURFACE_MAX_SPREAD`) and B's colour at the pixel is plainly another (relative misfit above
    :data:`OTHER_SURFACE_MISFIT`), B sees something else.  Tested where B's colour changes while A's does not
    (the edge of such a patch), then grown over the unreliable pixels of the same colour in A whose B colour
    misfits the surface's too (up to ``grow_passes`` px).

    Parameters
    ----------
    ga_raw, gb_raw
        ``(H, W, C)`` images of camera A and of camera B resampled onto A's grid.
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` (px · m).
    inv_depth
        ``(H, W)`` inverse depth (1/m) of every pixel.
    reliable
        ``(H, W)`` boolean, pixels whose depth was measured distinctively.
    radius, step
        Neighbourhood radius (fraction of the image's width, at least two steps) and sampling step (px).
    grow_passes
        Most growing passes.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` boolean.
    """
    a = as_channels(ga_raw)  # finite float32, as is B moved by the parallax
    seen = moved_by_parallax(as_channels(gb_raw), field, inv_depth.astype(np.float32))
    bright = a.sum(axis=-1)
    usable = bright > 0
    unit = np.where(usable[..., None], seen / np.where(usable, bright, 1.0)[..., None], 0.0).astype(np.float32)
    a_norm = np.sqrt(np.einsum("...c,...c->...", a, a))
    u_norm = np.sqrt(np.einsum("...c,...c->...", unit, unit))
    refs = reliable & usable
    todo = ~reliable & usable & could_be_shadowed(inv_depth, field)
    h, w = todo.shape
    out = np.zeros((h, w), bool)
    ys, xs = np.nonzero(todo & _b_edges_without_a(a, a_norm, unit, u_norm, usable))
    if ys.size == 0 or not refs.any():
        return out
    ap, ap_norm = a[ys, xs], a_norm[ys, xs]
    reach = max(2 * step, round(radius * w / step) * step)
    # edge-padded copies, so that a neighbour's index needs no clipping
    pad = [np.pad(x, ((reach, reach), (reach, reach)) + ((0, 0),) * (x.ndim - 2), mode="edge")
           for x in (refs, a, a_norm, unit, u_norm)]
    s1 = np.zeros((ys.size, unit.shape[-1]))
    s2 = np.zeros(ys.size)
    n = np.zeros(ys.size)
    for dy in range(-reach, reach + 1, step):
        for dx in range(-reach, reach + 1, step):
            yq, xq = ys + (dy + reach), xs + (dx + reach)
            same = pad[0][yq, xq] & _same_colour(ap, pad[1][yq, xq], ap_norm, pad[2][yq, xq])
            s1 += np.where(same[:, None], pad[3][yq, xq], 0.0)
            s2 += np.where(same, pad[4][yq, xq] ** 2, 0.0)
            n += same
    has = n >= OTHER_SURFACE_MIN_VOTES
    mean = s1[has] / n[has, None]
    norm = np.maximum(np.linalg.norm(mean, axis=1), 1e-30)
    spread = np.sqrt(np.maximum(s2[has] / n[has] - (mean * mean).sum(axis=1), 0.0)) / norm
    up = unit[ys[has], xs[has]]
    misfit = np.linalg.norm(up - mean, axis=1) / (np.linalg.norm(up, axis=1) + norm)
    flag = (misfit > OTHER_SURFACE_MISFIT) & (spread < OTHER_SURFACE_MAX_SPREAD)
    fy, fx = ys[has][flag], xs[has][flag]
    out[fy, fx] = True
    # the surface's B colour travels with the flagged pixels: a neighbour of A's same colour joins them
    # where its own B colour misfits that surface's too (never where B shows the surface).  Flat indices of
    # a grid padded by one pixel (never a candidate), so that a neighbour is an index step away
    wp = w + 2

    def padded(x):
        return np.pad(x, ((1, 1), (1, 1)) + ((0, 0),) * (x.ndim - 2)).reshape(-1, *x.shape[2:])

    a_f, an_f, u_f, un_f, todo_f = padded(a), padded(a_norm), padded(unit), padded(u_norm), padded(todo)
    out_f = padded(out)
    expected = np.zeros_like(u_f)
    e_norm = np.zeros_like(un_f)
    frontier = (fy + 1) * wp + (fx + 1)
    expected[frontier], e_norm[frontier] = mean[flag], norm[flag]
    steps = _NEIGHBOURS_DY * wp + _NEIGHBOURS_DX
    for _ in range(grow_passes):
        # the unflagged unreliable neighbours of the pixels flagged last pass
        cand = np.unique((frontier[:, None] + steps[None, :]).ravel())
        cand = cand[todo_f[cand] & ~out_f[cand]]
        if cand.size == 0:
            break
        add = np.zeros(cand.size, bool)
        carried = np.zeros((cand.size, unit.shape[-1]), np.float32)
        carried_norm = np.zeros(cand.size, np.float32)
        uc, ucn, ac, acn = u_f[cand], un_f[cand], a_f[cand], an_f[cand]
        for step_q in steps:
            q = cand + step_q
            eq, eqn = expected[q], e_norm[q]
            d = uc - eq
            joins = out_f[q] & ~add & _same_colour(ac, a_f[q], acn, an_f[q]) \
                & (np.einsum("nc,nc->n", d, d) > (OTHER_SURFACE_MISFIT * (ucn + eqn)) ** 2)
            carried[joins], carried_norm[joins] = eq[joins], eqn[joins]
            add |= joins
        if not add.any():
            break
        frontier = cand[add]
        out_f[frontier] = True
        expected[frontier], e_norm[frontier] = carried[add], carried_norm[add]
    return out_f.reshape(h + 2, wp)[1:-1, 1:-1].copy()


def _sample_moved(image: np.ndarray, field: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                  inv_depth: np.ndarray) -> np.ndarray:
    """:func:`moved_by_parallax` at the pixels ``(ys, xs)`` only, ``(n, C)``.  The positions go to OpenCV as
    rows of :data:`_REMAP_ROW` (its maps hold fewer than 32767 columns), the last one padded."""
    mx, my = _parallax_positions(xs.astype(np.float32), ys.astype(np.float32), field[ys, xs],
                                 inv_depth.astype(np.float32))
    n = xs.size
    rows = max(1, -(-n // _REMAP_ROW))
    width = min(n, _REMAP_ROW) if n else 1
    pad = rows * width - n
    mx = np.concatenate([mx.ravel(), np.zeros(pad, np.float32)]).reshape(rows, width)
    my = np.concatenate([my.ravel(), np.zeros(pad, np.float32)]).reshape(rows, width)
    out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(rows * width, -1)[:n].reshape(n, image.shape[-1])


def _add_peak(top1: np.ndarray, top2: np.ndarray, peak: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Streaming update of the highest and second-highest local maxima (``-inf`` where none is new)."""
    top2 = np.where(peak > top1, np.maximum(top2, top1), np.maximum(top2, peak))
    return np.maximum(top1, peak), top2


def neighbourhood_stack(values: np.ndarray, radius: int) -> np.ndarray:
    """Every value of each pixel's ``(2r + 1)²`` neighbourhood.

    NaN beyond the border; NaN values stay NaN, so ``np.nan*`` reductions over axis 0 see only the known
    neighbours.

    Parameters
    ----------
    values
        ``(H, W)`` float array.
    radius
        ``r``, the neighbourhood radius (px or blocks).

    Returns
    -------
    numpy.ndarray
        ``((2r + 1)², H, W)``.
    """
    h, w = values.shape
    padded = np.pad(values, radius, mode="constant", constant_values=np.nan)
    return np.stack([padded[dy:dy + h, dx:dx + w] for dy in range(2 * radius + 1) for dx in range(2 * radius + 1)])


def fill_from_neighbours(values: np.ndarray, fill: np.ndarray, sources: np.ndarray, radius: int = 2,
                         passes: int = 3) -> np.ndarray:
    """Replace the ``fill`` pixels by the median of the ``sources`` pixels within ``radius``.

    Repeated ``passes`` times, filled pixels serving as sources of the next pass, so that holes up to
    ``2 · radius · passes`` pixels wide close from their rims; pixels with none in reach keep their value.

    Parameters
    ----------
    values
        ``(H, W)`` values.
    fill
        ``(H, W)`` boolean, the pixels to replace.
    sources
        ``(H, W)`` boolean, the pixels that may vote (``fill`` pixels never do in the first pass).
    radius
        Neighbourhood radius (px).
    passes
        Most passes.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32.
    """
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
    """Per-pixel result on A's grid (:func:`parallax_map`).

    Attributes
    ----------
    inv_depth_per_m : numpy.ndarray
        ``(H, W)`` float32 inverse depth (1/m; 0 at infinity).
    confidence : numpy.ndarray
        ``(H, W)`` float32, the correlation of A with B moved by that parallax, 0..1 (0 where flat or
        ambiguous).
    occluded : numpy.ndarray
        ``(H, W)`` boolean, A's pixels hidden from B by a nearer surface, or where B shows another surface
        than A's (:func:`sees_another_surface`).
    blocks : BlockParallax
        The block measurements (on the analysis grid, binned for large sensors).
    other_surface : numpy.ndarray or None
        ``(H, W)`` boolean, the part of ``occluded`` where B shows another surface (on this grid).
    """

    inv_depth_per_m: np.ndarray
    confidence: np.ndarray
    occluded: np.ndarray
    blocks: BlockParallax
    other_surface: np.ndarray | None = None

    def occlusion_code(self) -> np.ndarray:
        """``(H, W)`` float32 per pixel: 0 seen by B, :data:`OCCLUSION_HIDDEN` hidden from B by a nearer
        surface, :data:`OCCLUSION_OTHER_SURFACE` B shows another surface (the third layer of the stored
        parallax records)."""
        code = self.occluded.astype(np.float32) * np.float32(OCCLUSION_HIDDEN)
        if self.other_surface is not None:
            code[self.other_surface] = OCCLUSION_OTHER_SURFACE
        return code

    def stats(self) -> dict:
        """Summary numbers for reports.

        Returns
        -------
        dict
            ``n_blocks``, ``n_measured``, ``n_across_blocks``, ``median_across_px`` (px of the analysis grid),
            ``occluded_fraction``, ``nearest_m`` (m) and ``median_perpendicular_px``; ``None`` where nothing
            was measured.
        """
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
                 target_px: int = PARALLAX_ANALYSIS_PX, ground_down=None,
                 zero_margin: float = SWEEP_ZERO_MARGIN) -> Parallax:
    """Steps 1-5 of the module docstring for one direction.

    Images larger than about ``target_px`` are analysed binned (inverse depth does not depend on the pixel
    size; the sweep costs ~50 remaps per pixel), and the result is brought back to every pixel (each takes
    one binned cell's values, never a blend of two surfaces: its own cell, or beside a depth step the
    neighbouring cell of its colour in A, :func:`upsampled_by_colour`) where the occlusion is evaluated.

    Parameters
    ----------
    image_a, warped_b
        Camera A's image and camera B's resampled onto A's grid, both ``(H, W, C)`` radiance.
    seen
        ``(H, W)`` boolean, where the warped B image has data.
    model_a
        Camera A's model (not used by the computation, which takes ``field``; kept for callers).
    baseline_m
        Camera B's optical centre relative to A's (m), ``(3,)`` (likewise not used).
    field
        ``(H, W, 2)`` or ``(H, W, 4)`` :func:`epipolar_field` at every pixel (px · m).
    block
        Block side (px) of the POC measurement (default :func:`~omnispectral.imaging.blockpoc.block_size_for`).
    ground_inv_depth
        Optional callable ``ground_inv_depth(pixels)`` giving the ground plane's inverse depth (1/m) at A's
        pixels ``(..., 2)`` (0 above the horizon).
    min_confidence
        Smallest POC peak height of a block measurement.
    target_px
        Long side (px) of the analysis grid.
    ground_down
        Optional callable ``ground_down(pixels)``: the sine of the angle below the horizon of A's rays at
        ``pixels`` ``(..., 2)``.  Without ``ground_inv_depth``, a level ground of unknown height is then fitted
        to the measured blocks (:func:`level_ground_prior`).
    zero_margin
        The sweep's margin (:func:`sweep_inverse_depth`) at full resolution; an analysis binned ``f`` times
        uses ``zero_margin / f``.  Binning averages an edge's shift away: a building 20 m off (3.6 px of
        parallax at full scale, 0.9 px on the 4×-binned grid) matches its true depth better than infinity
        by only 0.025 in the median there, under the full-resolution margin (docs/benchmarks.md, Processing).

    Returns
    -------
    Parallax
    """
    f = analysis_factor(image_a.shape[1], image_a.shape[0], target_px)
    if f > 1:
        h, w = image_a.shape[:2]
        small_field = bin_image(field, f) / f
        small_seen = bin_image(seen.astype(np.float32), f) > 0.999
        ground_small = down_small = None
        if ground_inv_depth is not None:
            def ground_small(pixels):
                return ground_inv_depth(binned_to_full_px(pixels, f))
        if ground_down is not None:
            def down_small(pixels):
                return ground_down(binned_to_full_px(pixels, f))
        binned_a = bin_image(image_a, f)
        low = parallax_map(binned_a, bin_image(warped_b, f), small_seen, model_a, baseline_m,
                           small_field, block=block, ground_inv_depth=ground_small,
                           min_confidence=min_confidence, target_px=10**9, ground_down=down_small,
                           zero_margin=zero_margin / f)
        inv_depth, confidence, other = upsampled_by_colour(
            image_a, binned_a, low.inv_depth_per_m, small_field, f, [low.inv_depth_per_m, low.confidence,
                                                                     low.other_surface])
        inv_depth = settled_at_steps(image_a, warped_b, field, inv_depth, low.inv_depth_per_m, small_field, f,
                                     (confidence > 0) & seen)
        return Parallax(inv_depth, confidence, _occluded(inv_depth, field) | other, low.blocks, other)
    h, w = image_a.shape[:2]
    block = block or block_size_for(w, h)
    gray_a, gray_b = as_gray(image_a), as_gray(warped_b)
    bp = block_parallax(gray_a, gray_b, seen, field, block=block, min_confidence=min_confidence)
    ga, gb = as_channels(image_a), as_channels(warped_b)
    ground = None
    gy, gx = np.meshgrid(bp.y_px, bp.x_px, indexing="ij")
    if ground_inv_depth is not None:
        ground = ground_inv_depth(np.stack([gx, gy], axis=-1))
    elif ground_down is not None:
        ground = level_ground_prior(bp, ground_down(np.stack([gx, gy], axis=-1)))
    wb = fill_blocks(bp, ground)
    inv_depth, confidence = sweep_inverse_depth(ga, gb, field, wb, bp.measured, bp.y_px, bp.x_px,
                                                zero_margin=zero_margin)
    inv_depth = np.maximum(inv_depth, 0.0)
    other = sees_another_surface(ga, gb, field, inv_depth, confidence > 0)
    return Parallax(inv_depth.astype(np.float32), confidence.astype(np.float32), _occluded(inv_depth, field) | other,
                    bp, other)


def upsampled_by_colour(image_a: np.ndarray, binned_a: np.ndarray, inv_depth: np.ndarray, binned_field: np.ndarray,
                        factor: int, layers: list[np.ndarray], step_px: float = DEPTH_STEP_PX) -> list[np.ndarray]:
    """Per-pixel values on A's full grid from the binned analysis grid: each pixel takes one cell's values.

    Its own cell, except beside a depth step: there a pixel takes, of its cell and the eight around it, the
    one whose colour in A (binned) is nearest its own (relative distance, ties to the nearest cell), so that a
    far building's silhouette against the sky follows A's edge at full resolution instead of the binned
    grid's staircase (a discrete joint bilateral upsampling, Kopf et al., SIGGRAPH 2007).  A cell is beside a
    step when the parallax over its 3 × 3 cells spans more than ``step_px`` full-resolution px.

    Parameters
    ----------
    image_a, binned_a
        ``(H, W, C)`` camera A's image and its ``factor`` binning.
    inv_depth
        ``(h, w)`` inverse depth (1/m) on the binned grid.
    binned_field
        ``(h, w, 2+)`` the epipolar field on the binned grid (binned px · m).
    factor
        The binning factor.
    layers
        ``(h, w)`` arrays on the binned grid (inverse depth, confidence, …).
    step_px
        Parallax span (full-resolution px) that makes a depth step.

    Returns
    -------
    list of numpy.ndarray
        ``(H, W)`` per layer.
    """
    h, w = image_a.shape[:2]
    hb, wb = inv_depth.shape
    out = [_repeat_to(x, factor, h, w) for x in layers]
    step = step_cell_pixels(inv_depth, binned_field, factor, h, w, step_px)
    if step is None:
        return out
    ys, xs, cy, cx = step
    a = as_channels(image_a[ys, xs][None])[0]
    ab = as_channels(binned_a)
    ab_norm = np.sqrt(np.einsum("...c,...c->...", ab, ab))
    a_norm = np.sqrt(np.einsum("nc,nc->n", a, a))
    # the pixel's offset from its cell's centre (binned px), to break ties towards the nearest cell
    oy = ((ys - cy * factor + 0.5) / factor - 0.5).astype(np.float32)
    ox = ((xs - cx * factor + 0.5) / factor - 0.5).astype(np.float32)
    best = np.full(ys.size, np.inf, np.float32)
    best_r, best_c = cy.copy(), cx.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            qr, qc = np.clip(cy + dy, 0, hb - 1), np.clip(cx + dx, 0, wb - 1)
            d = a - ab[qr, qc]
            cost = np.sqrt(np.einsum("nc,nc->n", d, d)) / np.maximum(a_norm + ab_norm[qr, qc], np.float32(1e-30)) \
                + np.float32(UPSAMPLE_DISTANCE_COST) * np.hypot(oy - np.float32(dy), ox - np.float32(dx))
            better = cost < best
            best = np.where(better, cost, best)
            best_r, best_c = np.where(better, qr, best_r), np.where(better, qc, best_c)
    for full, low in zip(out, layers, strict=True):
        full[ys, xs] = low[best_r, best_c]
    return out


def step_cell_pixels(inv_depth: np.ndarray, binned_field: np.ndarray, factor: int, h: int, w: int,
                     step_px: float = DEPTH_STEP_PX) -> tuple[np.ndarray, ...] | None:
    """The full-resolution pixels of the binned cells beside a depth step (:func:`upsampled_by_colour`): rows,
    columns and their cells' rows and columns ``(n,)`` each, or ``None`` when there is no step."""
    parallax_px = (np.nan_to_num(inv_depth * np.hypot(binned_field[..., 0], binned_field[..., 1])) * factor
                   ).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    step_cells = (cv2.dilate(parallax_px, kernel) - cv2.erode(parallax_px, kernel)) > step_px
    if not step_cells.any():
        return None
    sy, sx = np.nonzero(step_cells)
    iy, ix = np.divmod(np.arange(factor * factor), factor)
    ys, xs = (sy[:, None] * factor + iy[None, :]).ravel(), (sx[:, None] * factor + ix[None, :]).ravel()
    cy, cx = np.repeat(sy, factor * factor), np.repeat(sx, factor * factor)
    inside = (ys < h) & (xs < w)
    return ys[inside], xs[inside], cy[inside], cx[inside]


def settled_at_steps(image_a: np.ndarray, warped_b: np.ndarray, field: np.ndarray, inv_depth: np.ndarray,
                     binned_inv_depth: np.ndarray, binned_field: np.ndarray, factor: int, reliable: np.ndarray,
                     gain: float = STEP_SETTLE_GAIN) -> np.ndarray:
    """Full-resolution inverse depth of a binned analysis corrected where camera B's colour misfits A's.

    The binned grid's depth reaches the full grid by cells (:func:`upsampled_by_colour`), and where it is wrong
    by a pixel or two B shows the other side of an edge there: a strip narrower than a cell (a plate's shadow
    beside its edge) has no cell of its colour, and far content whose parallax is under a binned pixel (a
    building 40 m off: 1.8 px at full scale, 0.45 binned px) is left at infinity by the binned sweep, its
    silhouette's B edge 1.8 px from A's.  Each pixel whose B colour at its parallax misfits the colour A's
    pixel predicts (one linear map between the cameras, :func:`colour_map_a_to_b`, fitted on ``reliable``
    pixels; :data:`SETTLE_MIN_MISFIT`) tries

    1. beside a depth step, the values of its binned cell and the eight around it;
    2. on an edge of A across the epipolar line, parallaxes within :data:`EDGE_SEARCH_PX` of its own (the
       nearest of equal fits, and only a fit below :data:`EDGE_MAX_FIT`),

    and takes the best when its misfit is below ``gain`` times the current one.  At full scale (2026-11-28,
    docs/benchmarks.md, Processing) this took camera B's band NRMSE within 2 px of depth edges from 0.172
    to 0.131.  An unbinned analysis, whose sweep is at full resolution already, does not use it: there the
    search along the line moved a ColorChecker's 3-px patches onto their neighbours' depths.

    Parameters
    ----------
    image_a, warped_b
        ``(H, W, C)`` camera A's image and camera B's resampled onto A's grid.
    field
        ``(H, W, 2+)`` :func:`epipolar_field` (px · m).
    inv_depth
        ``(H, W)`` inverse depth (1/m) upsampled from the binned grid.
    binned_inv_depth, binned_field
        The binned grid's inverse depth and epipolar field (binned px · m).
    factor
        The binning factor.
    reliable
        ``(H, W)`` boolean, pixels whose depth is trusted (the colour map's sample).
    gain
        Largest ratio of the new misfit to the current one that switches.

    Returns
    -------
    numpy.ndarray
        ``(H, W)`` float32 inverse depth (1/m).
    """
    h, w = inv_depth.shape
    out = inv_depth.astype(np.float32, copy=True)
    # NaN (B's frame edge) stays: its misfit is NaN and never switches
    a, b = (x[..., None] if x.ndim == 2 else x for x in (np.asarray(image_a, np.float32),
                                                         np.asarray(warped_b, np.float32)))
    m = _colour_map_at(a, b, field, out, reliable)
    if not np.isfinite(m).all():
        return out
    step = step_cell_pixels(binned_inv_depth, binned_field, factor, h, w)
    if step is not None:
        _settle_among_cells(a, b, field, out, m, binned_inv_depth, step, gain)
    _settle_along_line(a, b, field, out, m, gain)
    return out


def _colour_map_at(a: np.ndarray, b: np.ndarray, field: np.ndarray, inv_depth: np.ndarray,
                   reliable: np.ndarray, max_samples: int = 20000) -> np.ndarray:
    """:func:`colour_map_a_to_b` fitted on (at most ``max_samples`` of) the ``reliable`` pixels, B moved by their
    parallax."""
    sy, sx = np.divmod(_evenly_spaced(np.flatnonzero(reliable.ravel()), max_samples), inv_depth.shape[1])
    sa, sb = a[sy, sx][:, None], _sample_moved(b, field, sy, sx, inv_depth[sy, sx])[:, None]
    return colour_map_a_to_b(sa, sb, (np.isfinite(sa).all(axis=-1) & np.isfinite(sb).all(axis=-1)))


def _settle_among_cells(a: np.ndarray, b: np.ndarray, field: np.ndarray, out: np.ndarray, m: np.ndarray,
                        binned_inv_depth: np.ndarray, step: tuple[np.ndarray, ...], gain: float) -> None:
    """:func:`settled_at_steps`' first part, in place: the step pixels whose B colour misfits A's try their
    3 × 3 cells' values (each only where it differs from the pixel's own)."""
    ys, xs, cy, cx = step
    current = out[ys, xs]
    misfit0 = _colour_residual(a[ys, xs][None], _sample_moved(b, field, ys, xs, current)[None], m)[0]
    todo = misfit0 > SETTLE_MIN_MISFIT
    ys, xs, cy, cx, current, misfit0 = ys[todo], xs[todo], cy[todo], cx[todo], current[todo], misfit0[todo]
    ap = a[ys, xs][None]
    e_len = np.hypot(field[ys, xs, 0], field[ys, xs, 1])
    hb, wb = binned_inv_depth.shape
    best, best_w = misfit0.copy(), current.copy()
    for dy, dx in ((dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)):
        cand = binned_inv_depth[np.clip(cy + dy, 0, hb - 1), np.clip(cx + dx, 0, wb - 1)].astype(np.float32)
        differs = np.flatnonzero(np.abs(cand - current) * e_len > 0.1)  # > 0.1 px of parallax apart
        r = _colour_residual(ap[:, differs], _sample_moved(b, field, ys[differs], xs[differs], cand[differs])[None],
                             m)[0]
        better = r < best[differs]
        best[differs[better]], best_w[differs[better]] = r[better], cand[differs[better]]
    switch = best < gain * misfit0
    out[ys[switch], xs[switch]] = best_w[switch]


def _settle_along_line(a: np.ndarray, b: np.ndarray, field: np.ndarray, out: np.ndarray, m: np.ndarray,
                       gain: float) -> None:
    """:func:`settled_at_steps`' second part, in place: pixels on an edge of A across the epipolar line whose B
    colour misfits try parallaxes within :data:`EDGE_SEARCH_PX` of their own, every half pixel (nearest first)."""
    gray = a.sum(axis=-1)
    centred = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gx = cv2.filter2D(gray, -1, centred, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.filter2D(gray, -1, centred.T, borderType=cv2.BORDER_REPLICATE)
    fx, fy = field[..., 0], field[..., 1]
    e_len = np.sqrt(fx * fx + fy * fy)
    along = np.abs(gx * fx + gy * fy)
    edge = (along > np.float32(EDGE_MIN_RELATIVE_GRADIENT) * gray * e_len) & (e_len > 0)
    edge = cv2.dilate(edge.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    ys, xs = np.nonzero(edge)
    if ys.size == 0:
        return
    ap = a[ys, xs][None]
    current = out[ys, xs]
    misfit0 = _colour_residual(ap, _sample_moved(b, field, ys, xs, current)[None], m)[0]
    todo = misfit0 > EDGE_MIN_MISFIT
    ys, xs, ap, current, misfit0 = ys[todo], xs[todo], ap[:, todo], current[todo], misfit0[todo]
    if ys.size == 0:
        return
    w_per_px = 1.0 / e_len[ys, xs]
    n = round(EDGE_SEARCH_PX / EDGE_SEARCH_STEP_PX)
    best, best_cost, best_w = misfit0.copy(), misfit0.copy(), current.copy()
    for k in sorted(range(-n, n + 1), key=abs)[1:]:
        cand = np.maximum(current + np.float32(k * EDGE_SEARCH_STEP_PX) * w_per_px, 0.0).astype(np.float32)
        r = _colour_residual(ap, _sample_moved(b, field, ys, xs, cand)[None], m)[0]
        cost = r + np.float32(EDGE_SEARCH_COST_PER_PX * abs(k) * EDGE_SEARCH_STEP_PX)
        better = cost < best_cost
        best, best_cost, best_w = np.where(better, r, best), np.where(better, cost, best_cost), \
            np.where(better, cand, best_w)
    switch = (best < gain * misfit0) & (best < EDGE_MAX_FIT)
    out[ys[switch], xs[switch]] = best_w[switch]


def _repeat_to(x: np.ndarray, factor: int, h: int, w: int) -> np.ndarray:
    """Each cell of ``x`` repeated over its ``factor × factor`` pixels, cut or edge-extended to ``(h, w)``."""
    up = np.repeat(np.repeat(x, factor, axis=0), factor, axis=1)[:h, :w]
    if up.shape != (h, w):
        up = np.pad(up, ((0, h - up.shape[0]), (0, w - up.shape[1])), mode="edge")
    return np.ascontiguousarray(up)


def _occluded(inv_depth: np.ndarray, field: np.ndarray, e_len: np.ndarray | None = None) -> np.ndarray:
    """Step 5: pixels hidden from B by a nearer surface (z-buffer of the forward warp, nearness in px along
    the epipolar line); ``e_len``: the field's length, when the caller has it."""
    if e_len is None:
        e_len = np.hypot(field[..., 0], field[..., 1]).astype(np.float32)
    return occlusion_zbuffer(inv_depth * field[..., 0], inv_depth * field[..., 1], inv_depth * e_len,
                              OCCLUSION_TOL_PX)
