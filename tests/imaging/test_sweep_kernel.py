"""The parallax sweep's compiled bookkeeping against its NumPy version, bit for bit."""

import numpy as np
import pytest

from omnispectral.imaging import parallax
from omnispectral.imaging.parallax import _SWEEP_STATE, _sweep_level_numpy, _sweep_state, sweep_inverse_depth
from omnispectral.imaging.sweep_kernel import compiled_sweep

pytestmark = pytest.mark.skipif(compiled_sweep() is None, reason="Numba not installed")

STATE = tuple(_SWEEP_STATE)


def test_level_updates_are_the_numpy_bits_over_a_whole_sweep():
    """Twelve levels of scores with ties, NaN and flat stretches: every state array equal after each level."""
    rng = np.random.default_rng(3)
    h, w = 37, 53
    own = rng.choice([0.0, 0.05, 0.1, 0.2], size=(h, w)).astype(np.float32)
    lo, hi = (own - 0.08).astype(np.float32), (own + 0.08).astype(np.float32)
    levels = np.linspace(-0.1, 0.3, 12)
    dw = float(levels[1] - levels[0])
    k_zero = int(np.argmin(np.abs(levels)))
    ours, numpys = _sweep_state(h, w), _sweep_state(h, w)
    kernel = compiled_sweep().level_update
    for k, wk in enumerate(levels):
        raw = np.round(rng.uniform(0.0, 1.0, (h, w)), 1).astype(np.float32)  # ties between levels
        raw[rng.random((h, w)) < 0.03] = np.nan
        raw[:5, :5] = 0.5  # a flat stretch: every level a peak
        score = np.maximum(raw, np.roll(raw, 1, axis=1))
        for update, st in ((kernel, ours), (_sweep_level_numpy, numpys)):
            update(k, wk, dw / 2, k == k_zero, raw, score, lo, hi, own, *(getattr(st, n) for n in STATE))
        for name in STATE:
            np.testing.assert_array_equal(getattr(ours, name), getattr(numpys, name), err_msg=f"{name}, level {k}")
    assert np.isfinite(ours.best).mean() > 0.5 and (ours.rival > -np.inf).any()  # the test exercised the state


@pytest.mark.parametrize("second_order", [False, True])
def test_sweep_gives_the_numpy_versions_depths(monkeypatch, second_order):
    """A textured wall with a near square, B moved along a slanted epipolar field: the whole sweep (moved
    positions and bookkeeping compiled) gives the NumPy version's inverse depth and confidence."""
    rng = np.random.default_rng(7)
    h, w = 96, 128
    a = rng.uniform(0.2, 1.0, (h, w, 3)).astype(np.float32)
    a = (a + np.roll(a, 1, axis=0) + np.roll(a, 1, axis=1)) / 3  # some correlation between neighbours
    inv_depth = np.full((h, w), 0.05, np.float32)
    inv_depth[30:60, 40:80] = 0.5
    field = np.zeros((h, w, 4 if second_order else 2), np.float64)
    field[..., 0], field[..., 1] = 8.0, 1.5
    if second_order:
        field[..., 2] = 0.4
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    import cv2
    b = cv2.remap(a, xx - 8.0 * inv_depth, yy - 1.5 * inv_depth, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    ny, nx = 6, 8
    y_px, x_px = np.linspace(8, h - 8, ny), np.linspace(8, w - 8, nx)
    w_blocks = np.full((ny, nx), 0.05, np.float32)
    w_blocks[2:4, 3:5] = 0.5
    measured = np.ones((ny, nx), bool)
    compiled = sweep_inverse_depth(a, b, field, w_blocks, measured, y_px, x_px)
    monkeypatch.setattr(parallax, "compiled_sweep", lambda: None)
    plain = sweep_inverse_depth(a, b, field, w_blocks, measured, y_px, x_px)
    for got, want in zip(compiled, plain, strict=True):
        np.testing.assert_array_equal(got, want)
    assert abs(float(np.median(compiled[0][35:55, 45:75])) - 0.5) < 0.05  # the square found
