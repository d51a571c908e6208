"""One POC offset per direction: camera B registered to camera A through the shared geometry (paper Sec. 4.3).

The paper (Hirai et al. 2018, Sec. 4.3) registers camera B's image to camera A's, the reference, by the
displacement at the peak of the Phase Only Correlation

.. math:: R(u, v) = \\frac{F(u, v)\\,\\overline{G}(u, v)}{\\lvert F(u, v)\\,\\overline{G}(u, v) \\rvert}
          \\qquad \\text{(Eq. (3))}.

Camera B differs from camera A by its filter, a small mounting misalignment and a baseline.  The rig
description (or a calibration) predicts where each of A's pixels falls on B's sensor for a scene at
infinity (:mod:`omnispectral.product.pairgeometry`); POC then measures what that prediction misses:

1. B's image is resampled onto A's pixel grid through ``A.pixel_to_world → B.world_to_pixel`` (one
   ``cv2.remap``, linear) — the images then differ by a residual shift ``d`` only;
2. :func:`~omnispectral.imaging.registration.register_with_fallback` on (A, warped B), over the centred
   rectangle B sees entirely (:func:`common_crop`), gives ``d`` in A's pixels (``warped_B(x) ≈ A(x - d)``)
   and a confidence; below ``min_confidence`` (a texture-less sky) the calibrated offset (zero) is used and
   the result says so;
3. ``d`` is carried to B's sensor with the local Jacobian ``J`` of the A → B pixel map at the image
   centre: the **offset** ``J d`` is the vector to add to B's predicted sensor coordinates, which is what
   the mosaic engine takes (``B_px(ray) + offset``).

One offset per direction also absorbs the parallax of the direction's dominant near surfaces; the
per-pixel parallax (:mod:`omnispectral.product.direction_parallax`) goes beyond it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE, register_with_fallback
from omnispectral.product.pairgeometry import cached_maps, offset_jacobian, warp_b_onto_a

__all__ = ["DEFAULT_MAX_OFFSET_PX", "DirectionAlignment", "align_direction", "common_crop"]


@dataclass(frozen=True)
class DirectionAlignment:
    """Camera B's offset for one direction and how it was obtained."""

    direction: int
    offset_px: tuple[float, float]
    measured_px: tuple[float, float]
    confidence: float
    used_fallback: bool

    def to_dict(self) -> dict:
        """The alignment as a JSON object (kept with the direction's merged images; offsets in px components)."""
        return {"direction": self.direction, "offset_dx_px": self.offset_px[0], "offset_dy_px": self.offset_px[1],
                "measured_dx_px": self.measured_px[0], "measured_dy_px": self.measured_px[1],
                "confidence": self.confidence, "used_fallback": self.used_fallback}


def common_crop(seen: np.ndarray, step: int = 4) -> tuple[slice, slice]:
    """A centred rectangle of A's image that B sees entirely (shrunk from the borders in ``step`` px moves).

    Parameters
    ----------
    seen
        ``(H, W)`` boolean mask of A's pixels that B sees (:func:`~omnispectral.product.pairgeometry.warp_b_onto_a`).
    step
        How far a side moves in per step (px).

    Returns
    -------
    tuple of slice
        ``(rows, columns)`` of the rectangle; empty slices when none of at least 32 × 32 px exists.
    """
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

    Parameters
    ----------
    direction
        The direction's index (kept in the result).
    image_a, image_b
        The direction's merged images of camera A and camera B ``(H, W, C)``.
    model_a, model_b
        Camera A's and camera B's models (B: the rig file's or the calibrated one).
    pan_deg, tilt_deg
        The head's direction (degrees).
    min_confidence
        Smallest POC confidence that counts as a measurement.
    calibrated_offset_px
        The offset (B's sensor px) used when the measurement fails.
    max_offset_px
        Largest distance (px) of the measured offset from the calibrated one.

    Returns
    -------
    DirectionAlignment
        The offset to add to B's predicted sensor coordinates (px), the shift measured on A's grid (px),
        the POC confidence and whether the fallback was used.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3), Fig. 6 (camera B registered to camera A, the reference,
       by the POC displacement; ``--registration paper``).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003 (the sub-pixel
       band-limited POC of :func:`~omnispectral.imaging.registration.phase_correlate`).
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
