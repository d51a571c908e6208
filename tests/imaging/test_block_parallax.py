"""Block parallax (imaging.parallax.block_parallax): the shift across the epipolar lines that no depth explains,
which the session check (product.direction_parallax.off_model_warnings) reads as "the rig model does not fit"."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omnispectral.imaging.parallax import SWEEP_MAX_LEVELS, SWEEP_STEP_PX, block_parallax

H, W = 128, 256


def _bars(theta_deg: float, shift_xy: tuple[float, float], spacing: float = 37.0, width: float = 4.0):
    """Grey A with bright bars at ``theta_deg`` from vertical on a flat ground, and B with A's content moved by
    ``shift_xy`` (px)."""
    yy, xx = np.mgrid[0:H + 64, 0:W + 64].astype(np.float64)
    t = np.radians(theta_deg)
    coord = (xx * np.cos(t) - yy * np.sin(t)) % spacing
    img = cv2.GaussianBlur((0.3 + 0.6 * np.clip(1 - np.abs(coord - spacing / 2) / width, 0, 1)).astype(np.float32),
                           (0, 0), 0.7)
    moved = cv2.warpAffine(img, np.float32([[1, 0, shift_xy[0]], [0, 1, shift_xy[1]]]), (W + 64, H + 64),
                           flags=cv2.INTER_CUBIC)
    return img[32:32 + H, 32:32 + W], moved[32:32 + H, 32:32 + W]


@pytest.mark.parametrize(("theta_deg", "shift_xy", "low", "high"), [
    (20.0, (0.0, 5.0), 0.0, 0.1),    # a near post 20° off the lines, 5 px of parallax: a depth explains it
    (20.0, (0.0, -5.0), 1.5, 2.0),   # the same moved the other way: beyond infinity, nothing explains it
    (5.0, (2.0, 0.0), 1.5, 2.1),     # lines 5° off the edges, B moved 2 px across them: the rig moved
])
def test_edges_near_the_lines_count_across_only_what_no_reachable_depth_explains(theta_deg, shift_xy, low, high):
    """Vertical epipolar lines (9 px per 1/m of inverse depth, as in the small preset's tilted views). Bars whose
    edges lie within 33° of the lines (too near to measure depth by the J-projection) used to count their
    whole shift as across: the near chart stand of every small-preset session read 0.55–1.0° off the model in
    two directions and `process` warned that the rig calibration did not fit (with the right calibration).
    A shift that a parallax within the sweep's reach explains now counts only its unexplained rest; a
    shift no such parallax explains still counts whole (the 2° knocked camera of tests/product/
    test_rig_chessboard.py)."""
    a, b = _bars(theta_deg, shift_xy)
    field = np.zeros((H, W, 2), np.float32)
    field[..., 1] = 9.0
    across = block_parallax(a, b, np.ones((H, W), bool), field, block=32).across_px
    measured = across[np.isfinite(across)]
    assert measured.size > 50
    assert low <= float(np.median(measured)) <= high
    assert 5.0 < SWEEP_MAX_LEVELS * SWEEP_STEP_PX  # the first case's parallax is within the sweep's reach
