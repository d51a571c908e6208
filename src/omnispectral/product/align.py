"""Registration of camera B to camera A for one head direction (paper Sec. 4.3), through the shared geometry.

Camera B differs from camera A by its filter, a small mounting misalignment and a baseline.  The rig
description (or a calibration) predicts where each of A's pixels falls on B's sensor for a scene at
infinity; POC then measures what that prediction misses:

1. B's image is resampled onto A's pixel grid through ``A.pixel_to_world → B.world_to_pixel`` (one
   ``cv2.remap``, linear) — the images then differ by a residual shift ``d`` only;
2. :func:`~omnispectral.imaging.registration.register_with_fallback` on (A, warped B) gives ``d`` in
   A's pixels (``warped_B(x) ≈ A(x - d)``) and a confidence; below ``min_confidence`` (a
   texture-less sky) the calibrated offset (zero) is used and the result says so;
3. ``d`` is carried to B's sensor with the local Jacobian of the A → B pixel map at the image
   centre: the **offset** is the vector to add to B's predicted sensor coordinates, which is what the
   mosaic engine takes (``B_px(ray) + offset``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import cv2
import numpy as np

from omnispectral.imaging.disparity import (
    CALIBRATION_ANALYSIS_PX,
    PARALLAX_ANALYSIS_PX,
    analysis_factor,
    bin_image,
    epipolar_field,
    parallax_map,
)
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE, phase_correlate, register_with_fallback


@dataclass(frozen=True)
class DirectionAlignment:
    """Camera B's offset for one direction and how it was obtained."""

    direction: int
    offset_px: tuple[float, float]
    measured_px: tuple[float, float]
    confidence: float
    used_fallback: bool

    def to_dict(self) -> dict:
        return {"direction": self.direction, "offset_dx_px": self.offset_px[0], "offset_dy_px": self.offset_px[1],
                "measured_dx_px": self.measured_px[0], "measured_dy_px": self.measured_px[1],
                "confidence": self.confidence, "used_fallback": self.used_fallback}


def baseline_m(model_b: CameraModel) -> np.ndarray:
    """B's optical centre relative to A's in the world frame at pan = tilt = 0, metres."""
    return model_b.camera_center_mm(0.0, 0.0) / 1000.0


def b_onto_a_maps(model_a: CameraModel, model_b: CameraModel, pan_deg: float = 0.0, tilt_deg: float = 0.0,
                  step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """For each of A's pixels (every ``step``), where the same ray at infinity lands on B's sensor (float32 maps).

    Both cameras turn with the head, so for points at infinity the map does not depend on the head's
    pan and tilt (the head rotation cancels): compute it once per rig (:func:`cached_maps`).
    """
    v, u = np.mgrid[0:model_a.height:step, 0:model_a.width:step]
    rays, ok = model_a.pixel_to_world(np.stack([u, v], axis=-1).astype(np.float64), pan_deg, tilt_deg)
    px, ok_b = model_b.world_to_pixel(np.nan_to_num(rays), pan_deg, tilt_deg, margin_px=None)
    px = np.where((ok & ok_b)[..., None], px, -1e6)
    return px[..., 0].astype(np.float32), px[..., 1].astype(np.float32)


_MAPS_CACHE: dict = {}


def cached_maps(model_a: CameraModel, model_b: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """:func:`b_onto_a_maps` at pan = tilt = 0, computed once per pair of camera models in this process."""

    key = json.dumps([model_a.to_dict(), model_b.to_dict()], sort_keys=True)
    value = _MAPS_CACHE.get(key)  # thread-safe without a lock: at worst two threads compute it
    if value is None:
        value = b_onto_a_maps(model_a, model_b)
        _MAPS_CACHE.clear()
        _MAPS_CACHE[key] = value
    return value


def warp_b_onto_a(image_b: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """B's image on A's grid (linear interpolation) and the mask of A's pixels that B sees."""

    mx, my = maps
    img = np.asarray(image_b, np.float32)
    warped = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    h, w = img.shape[:2]
    seen = (mx >= 0) & (my >= 0) & (mx <= w - 1) & (my <= h - 1)
    return warped, seen


def offset_jacobian(model_a: CameraModel, model_b: CameraModel, pan_deg: float, tilt_deg: float,
                    delta_px: float = 1.0) -> np.ndarray:
    """2 × 2 derivative of B's sensor position with respect to A's at A's image centre (finite differences)."""
    c = np.array([[model_a.cx, model_a.cy], [model_a.cx + delta_px, model_a.cy], [model_a.cx, model_a.cy + delta_px]])
    rays, _ = model_a.pixel_to_world(c, pan_deg, tilt_deg)
    px, _ = model_b.world_to_pixel(rays, pan_deg, tilt_deg, margin_px=None)
    return np.stack([(px[1] - px[0]) / delta_px, (px[2] - px[0]) / delta_px], axis=1)


def common_crop(seen: np.ndarray, step: int = 4) -> tuple[slice, slice]:
    """A centred rectangle of A's image that B sees entirely (shrunk from the borders in ``step`` px moves)."""
    h, w = seen.shape
    top, bottom, left, right = 0, h, 0, w
    while bottom - top >= 32 and right - left >= 32:
        rect = seen[top:bottom, left:right]
        if rect.all():
            return slice(top, bottom), slice(left, right)
        # move in the side(s) with unseen pixels; all sides when the holes are inside
        sides = [rect[:step].all(), rect[-step:].all(), rect[:, :step].all(), rect[:, -step:].all()]
        if all(sides):
            sides = [False] * 4
        top += 0 if sides[0] else step
        bottom -= 0 if sides[1] else step
        left += 0 if sides[2] else step
        right -= 0 if sides[3] else step
    return slice(0, 0), slice(0, 0)


#: A measured offset farther than this from the calibrated one is taken for a false peak and the calibrated
#: offset is used.  It is deliberately generous: like the paper, one offset per direction also absorbs the
#: parallax of the direction's dominant near surfaces (the ground 1.5 m away moves ~30 px between cameras
#: 60 mm apart at the paper's resolution); rejecting it leaves near objects misaligned between the cameras
#: (measured on the simulated demo: ColorChecker ΔE*ab 1.1 with per-direction offsets, 45 with a 2 px bound).
#: Depth-aware (per-block) registration of near objects is not done yet.
DEFAULT_MAX_OFFSET_PX = 64.0


def align_direction(direction: int, image_a: np.ndarray, image_b: np.ndarray, model_a: CameraModel,
                    model_b: CameraModel, pan_deg: float, tilt_deg: float,
                    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
                    calibrated_offset_px: tuple[float, float] = (0.0, 0.0),
                    max_offset_px: float = DEFAULT_MAX_OFFSET_PX) -> DirectionAlignment:
    """Camera B's sensor offset for one direction (module docstring); images are merged radiance (H, W, C).

    Falls back to ``calibrated_offset_px`` when the POC confidence is below ``min_confidence`` or the
    measured offset lies more than ``max_offset_px`` from the calibrated one.
    """
    warped, seen = warp_b_onto_a(image_b, cached_maps(model_a, model_b))
    rows, cols = common_crop(seen)
    if rows.stop - rows.start < 32:
        return DirectionAlignment(direction, calibrated_offset_px, (float("nan"), float("nan")), 0.0, True)
    reg = register_with_fallback(np.asarray(image_a, np.float32)[rows, cols], warped[rows, cols], (0.0, 0.0),
                                 min_confidence=min_confidence)
    measured = (float(reg.measured_dx), float(reg.measured_dy))
    if reg.used_fallback:
        return DirectionAlignment(direction, calibrated_offset_px, measured, float(reg.confidence), True)
    jac = offset_jacobian(model_a, model_b, pan_deg, tilt_deg)
    off = jac @ np.array([reg.dx, reg.dy])
    if np.hypot(off[0] - calibrated_offset_px[0], off[1] - calibrated_offset_px[1]) > max_offset_px:
        return DirectionAlignment(direction, calibrated_offset_px, measured, float(reg.confidence), True)
    return DirectionAlignment(direction, (float(off[0]), float(off[1])), measured, float(reg.confidence), False)


# ------------------------------------------------------------------------------------------ per-pixel parallax
_FIELD_CACHE: dict = {}


def cached_epipolar_field(model_a: CameraModel, model_b: CameraModel) -> np.ndarray:
    """:func:`~omnispectral.imaging.disparity.epipolar_field` of A's every pixel, once per pair of models."""


    key = json.dumps([model_a.to_dict(), model_b.to_dict()], sort_keys=True)
    value = _FIELD_CACHE.get(key)
    if value is None:
        # pixels beyond the lens model have no ray: no parallax there
        value = np.nan_to_num(epipolar_field(model_a, baseline_m(model_b), second_order=True)).astype(np.float32)
        _FIELD_CACHE.clear()
        _FIELD_CACHE[key] = value
    return value


def ground_inverse_depth(model_a: CameraModel, pan_deg: float, tilt_deg: float, height_m: float | None):
    """``f(pixels) → 1/m`` of a level ground ``height_m`` below the head (0 above the horizon), or None."""
    if not height_m:
        return None

    def inv_depth(pixels):
        rays, _ = model_a.pixel_to_world(pixels, pan_deg, tilt_deg)
        return np.nan_to_num(np.maximum(-rays[..., 1], 0.0) / height_m).astype(np.float32)

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
    another rig's.  ``direction_stats``: each direction's parallax statistics."""
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
    ~0.04 full pixels)."""

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
    """Camera B against A for one direction, B's model being the calibrated one (``product.rigcal``):

    1. per-pixel parallax (:func:`omnispectral.imaging.disparity.parallax_map`) against the rig model;
    2. on the pixels it finds at infinity, the direction's residual offset (:func:`far_offset`): the rig
       model is fitted on all directions and leaves a few hundredths of a degree, which matter next to the
       HDR sun; an offset measured on far content only cannot absorb near parallax (the paper's one
       offset per direction does);
    3. the parallax relative to the shifted model: content at ``p`` was found at ``p + w e`` and B now
       starts from ``p + d``, so ``w' = w − (d·e)/|e|²`` (clamped at 0; ``d`` is at most a pixel, its
       part across the line is what the offset corrects).

    With ``apply_far_offset=False`` (a rig model more certain than the offset's measurement,
    :data:`FAR_OFFSET_MIN_STD_PX`) the offset is measured and reported but not applied.
    """

    maps = cached_maps(model_a, model_b)
    field = cached_epipolar_field(model_a, model_b)
    c = baseline_m(model_b)
    ground = ground_inverse_depth(model_a, pan_deg, tilt_deg, ground_height_m)
    warped, seen = warp_b_onto_a(image_b, maps)
    first = parallax_map(image_a, warped, seen, model_a, c, field, ground_inv_depth=ground)
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
