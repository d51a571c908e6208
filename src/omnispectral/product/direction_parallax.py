"""Camera B's per-pixel parallax against camera A for one direction, on top of the calibrated rig model.

Beyond the paper: Hirai et al. (2018, Sec. 4.3) register B to A by one POC offset per direction (Eq. (3);
:mod:`omnispectral.product.align`), which leaves near objects misaligned (their Sec. 7: content within a
metre of the cameras shows colour artifacts).  Here B's image is resampled onto A's grid for points at
infinity with the calibrated mounting (:mod:`omnispectral.product.pairgeometry`), and

1. every pixel's inverse depth ``w`` (1/m) is measured along its epipolar line
   (:func:`omnispectral.imaging.parallax.parallax_map`: content of A's pixel ``p`` lies at
   ``p + w e(p) + w² h(p)/2`` in the warped B image, ``e``, ``h`` from
   :func:`~omnispectral.product.pairgeometry.cached_epipolar_field`), with a level ground
   :func:`ground_inverse_depth` as the prior below the horizon when its height is known;
2. on the pixels found at infinity (parallax below :data:`FAR_PARALLAX_PX`) POC measures what the rig model
   still misses there, the direction's offset at infinity ``d`` (:func:`far_offset`, at most
   :data:`MAX_FAR_OFFSET_DEG`);
3. the parallax is taken relative to the model shifted by ``d``: ``w' = max(w − (d·e)/|e|², 0)`` where
   ``w > 0``, and ``J d`` (``J`` the A → B Jacobian, :func:`~omnispectral.product.pairgeometry.offset_jacobian`)
   is B's offset on its sensor (:func:`parallax_direction`).

Each direction's blocks that sit off the model *across* the epipolar lines, where no depth moves content,
say the calibration does not fit the session (:func:`off_model_warnings`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from omnispectral.imaging.binning import CALIBRATION_ANALYSIS_PX, analysis_factor, bin_image
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.parallax import PARALLAX_ANALYSIS_PX, parallax_map
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE, phase_correlate
from omnispectral.product.pairgeometry import (
    baseline_m,
    cached_epipolar_field,
    cached_maps,
    offset_jacobian,
    warp_b_onto_a,
)

__all__ = ["FAR_OFFSET_MIN_STD_PX", "FAR_PARALLAX_PX", "MAX_FAR_OFFSET_DEG", "OFF_MODEL_MIN_BLOCKS",
           "OFF_MODEL_WARNING_DEG", "DirectionParallax", "far_offset", "ground_inverse_depth", "off_model_warnings",
           "parallax_direction", "rays_below_horizon"]


def rays_below_horizon(model_a: CameraModel, pan_deg: float, tilt_deg: float):
    """``f(pixels) →`` the sine of the angle below the horizon of A's rays at ``pixels`` ``(..., 2)`` (negative
    above it): what a level ground's inverse depth is proportional to
    (:func:`omnispectral.imaging.parallax.level_ground_prior`)."""

    def down(pixels):
        rays, _ = model_a.pixel_to_world(pixels, pan_deg, tilt_deg)
        return np.nan_to_num(-rays[..., 1]).astype(np.float64)

    return down


def ground_inverse_depth(model_a: CameraModel, pan_deg: float, tilt_deg: float, height_m: float | None):
    """``f(pixels) → 1/m`` of a level ground ``height_m`` below the head (0 above the horizon), or None.

    Parameters
    ----------
    model_a
        Camera A's model.
    pan_deg, tilt_deg
        The head's direction (degrees).
    height_m
        The ground's depth below the head (m); ``None`` or 0: no ground known.

    Returns
    -------
    callable or None
        ``inv_depth(pixels)``: float32 inverse depth (1/m) of the ground seen at A's pixels ``(..., 2)``.
    """
    if not height_m:
        return None
    down = rays_below_horizon(model_a, pan_deg, tilt_deg)

    def inv_depth(pixels):
        return (np.maximum(down(pixels), 0.0) / height_m).astype(np.float32)

    return inv_depth


#: Pixels whose parallax is below this (px) take part in the per-direction offset at infinity.
FAR_PARALLAX_PX = 0.25
#: The per-direction offset at infinity is applied only when the rig model states no uncertainty at
#: infinity or one above this (px): POC on a direction's far pixels measures a few hundredths of a pixel at
#: best, and where the far mask holds near content the parallax left at 0 (ground beside a horizon)
#: it is biased by that content's parallax (17:00 seed 0: 0.38 px in the direction holding the sun,
#: against a chessboard model good to 0.01 px).  A session-fitted model is known to ~0.4 px along the
#: lines, so its directions keep the offset.
FAR_OFFSET_MIN_STD_PX = 0.05
#: Largest per-direction offset at infinity accepted on top of the rig calibration, as an angle (1 px of
#: the 256-px sensor): the rig model's yaw rests on the scene's farthest content and can miss by ~0.15°,
#: which is 3.5 px at full scale (a 1-px cap there left the direction holding the sun 3 px off).
MAX_FAR_OFFSET_DEG = 0.37


@dataclass(frozen=True)
class DirectionParallax:
    """One direction's registration of B: offset at infinity (B's sensor px) on top of the rig model, and
    the per-pixel parallax on A's grid."""

    offset_px: tuple[float, float]
    far_offset_a_px: tuple[float, float]
    far_confidence: float
    parallax: object
    #: degrees per pixel of the grid the parallax was analysed on (binned for large sensors)
    analysis_deg_per_px: float = 0.0

    def stats(self) -> dict:
        """The parallax's statistics with the offset at infinity (px) and the median across the lines in degrees."""
        st = self.parallax.stats()
        across = st.get("median_across_px")
        return {**st, "median_across_deg": None if across is None else across * self.analysis_deg_per_px,
                "far_offset_px": list(self.offset_px), "far_offset_measured_a_px": list(self.far_offset_a_px),
                "far_confidence": self.far_confidence}


#: A direction whose reliable blocks sit, in the median, farther than this (degrees) off the rig model
#: *across* the epipolar lines disagrees with the model: no depth moves content that way.
OFF_MODEL_WARNING_DEG = 0.3
#: ... judged on at least this many blocks.
OFF_MODEL_MIN_BLOCKS = 8


def off_model_warnings(direction_stats: list[dict]) -> list[str]:
    """Warnings for the directions whose reliable blocks mostly sit off the rig model across the epipolar
    lines (``median_across_deg`` beyond :data:`OFF_MODEL_WARNING_DEG` on at least
    :data:`OFF_MODEL_MIN_BLOCKS` blocks): camera B moved since the calibration was made, or the file is
    another rig's.

    Parameters
    ----------
    direction_stats
        Each direction's parallax statistics (:meth:`DirectionParallax.stats` with ``direction``).

    Returns
    -------
    list of str
        One warning per such direction.
    """
    bad = [d for d in direction_stats if (d.get("n_across_blocks") or 0) >= OFF_MODEL_MIN_BLOCKS
           and d.get("median_across_deg") is not None and d["median_across_deg"] > OFF_MODEL_WARNING_DEG]
    return [f"direction {d['direction']}: camera B's {d['n_across_blocks']} reliable blocks sit "
            f"{d['median_across_deg']:.2f}° off the rig model across the epipolar lines (median; bound "
            f"{OFF_MODEL_WARNING_DEG}°, no depth explains it): the rig calibration does not fit this session "
            "(camera B moved, or another rig's file?)" for d in bad]


def far_offset(image_a: np.ndarray, warped_b: np.ndarray, far: np.ndarray,
               min_confidence: float = DEFAULT_MIN_CONFIDENCE, *,
               max_offset_px: float) -> tuple[tuple[float, float], float]:
    """POC shift (A's pixels) of B against A on the direction's far content only (sky, distant land, the
    sun): what the rig model still misses at infinity in this direction; (0, 0) when not measurable.
    Large images are measured binned to about 1024 px (POC's sub-pixel precision, ~0.02 px, is then
    ~0.04 full pixels).

    Parameters
    ----------
    image_a
        Camera A's image ``(H, W, C)``.
    warped_b
        Camera B's image on A's grid (:func:`~omnispectral.product.pairgeometry.warp_b_onto_a`).
    far
        ``(H, W)`` boolean mask of A's pixels at infinity.
    min_confidence
        Smallest POC confidence that counts as a measurement.
    max_offset_px
        Largest accepted shift (A's px).

    Returns
    -------
    tuple
        ``((dx_px, dy_px), confidence)``: the shift on A's grid, ``(0, 0)`` when under 5 % of the pixels are far,
        the confidence is low or the shift too large.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3) (the POC displacement of camera B against camera A, here
       measured on the far content only).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003.
    """

    if far.mean() < 0.05:
        return (0.0, 0.0), 0.0
    f = analysis_factor(far.shape[1], far.shape[0], CALIBRATION_ANALYSIS_PX)
    valid = bin_image(far.astype(np.float32), f) > 0.999
    reg = phase_correlate(bin_image(image_a, f), bin_image(warped_b, f), reference_valid=valid, moving_valid=valid)
    d = (float(reg.dx) * f, float(reg.dy) * f)
    if reg.confidence < min_confidence or np.hypot(*d) > max_offset_px or not np.isfinite(d).all():
        return (0.0, 0.0), float(reg.confidence)
    return d, float(reg.confidence)


def parallax_direction(image_a: np.ndarray, image_b: np.ndarray, model_a: CameraModel, model_b: CameraModel,
                       pan_deg: float = 0.0, tilt_deg: float = 0.0,
                       ground_height_m: float | None = None, apply_far_offset: bool = True) -> DirectionParallax:
    """Camera B against A for one direction, B's model being the calibrated one (:mod:`.rigfile`):

    1. per-pixel parallax (:func:`omnispectral.imaging.parallax.parallax_map`) against the rig model;
    2. on the pixels it finds at infinity, the direction's residual offset (:func:`far_offset`): the rig
       model is fitted on all directions and leaves a few hundredths of a degree, which matter next to the
       HDR sun; an offset measured on far content only cannot absorb near parallax (the paper's one
       offset per direction does);
    3. the parallax relative to the shifted model: content at ``p`` was found at ``p + w e`` and B now
       starts from ``p + d``, so ``w' = w − (d·e)/|e|²`` (clamped at 0; ``d`` is at most a pixel, its
       part across the line is what the offset corrects).

    With ``apply_far_offset=False`` (a rig model more certain than the offset's measurement,
    :data:`FAR_OFFSET_MIN_STD_PX`) the offset is measured and reported but not applied.

    Parameters
    ----------
    image_a, image_b
        The direction's merged images of camera A and camera B ``(H, W, C)``.
    model_a, model_b
        Camera A's and camera B's models (B: the calibrated one).
    pan_deg, tilt_deg
        The head's direction (degrees).
    ground_height_m
        The ground's depth below the head (m), the parallax's prior below the horizon; ``None``: none.
    apply_far_offset
        Apply the measured offset at infinity (step 3).

    Returns
    -------
    DirectionParallax
        The offset at infinity on B's sensor (px; ``(0, 0)`` when not applied), the measured shift on A's grid
        (px), its confidence, the per-pixel parallax and the analysis grid's degrees per pixel.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3), Fig. 6 (registration of camera B to camera A by POC);
       Sec. 7 (colour artifacts of close-range objects from occlusion and parallax, which the per-pixel
       parallax addresses).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003.
    """

    maps = cached_maps(model_a, model_b)
    field = cached_epipolar_field(model_a, model_b)
    c = baseline_m(model_b)
    ground = ground_inverse_depth(model_a, pan_deg, tilt_deg, ground_height_m)
    warped, seen = warp_b_onto_a(image_b, maps)
    first = parallax_map(image_a, warped, seen, model_a, c, field, ground_inv_depth=ground,
                         ground_down=None if ground is not None else rays_below_horizon(model_a, pan_deg, tilt_deg))
    far = seen & (np.abs(first.inv_depth_per_m) * np.hypot(field[..., 0], field[..., 1]) < FAR_PARALLAX_PX)
    d, conf = far_offset(image_a, warped, far, max_offset_px=MAX_FAR_OFFSET_DEG * model_a.width / model_a.hfov_deg)
    deg_per_px = model_a.hfov_deg / model_a.width * analysis_factor(model_a.width, model_a.height,
                                                                    PARALLAX_ANALYSIS_PX)
    if d == (0.0, 0.0) or not apply_far_offset:
        return DirectionParallax((0.0, 0.0), d, conf, first, deg_per_px)
    e2 = np.maximum(np.sum(field[..., :2] ** 2, axis=-1), 1e-12)
    near = first.inv_depth_per_m > 0
    inv_depth = np.where(near, np.maximum(first.inv_depth_per_m - (d[0] * field[..., 0] + d[1] * field[..., 1]) / e2,
                                          0.0), 0.0).astype(np.float32)
    second = replace(first, inv_depth_per_m=inv_depth)
    off = offset_jacobian(model_a, model_b, 0.0, 0.0) @ np.array(d)
    return DirectionParallax((float(off[0]), float(off[1])), d, conf, second, deg_per_px)
