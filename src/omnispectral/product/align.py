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

from dataclasses import dataclass

import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE, register_with_fallback


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
    import json

    key = json.dumps([model_a.to_dict(), model_b.to_dict()], sort_keys=True)
    if key not in _MAPS_CACHE:
        _MAPS_CACHE.clear()
        _MAPS_CACHE[key] = b_onto_a_maps(model_a, model_b)
    return _MAPS_CACHE[key]


def warp_b_onto_a(image_b: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """B's image on A's grid (linear interpolation) and the mask of A's pixels that B sees."""
    import cv2

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
