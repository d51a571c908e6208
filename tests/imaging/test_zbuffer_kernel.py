"""The compiled occlusion z-buffer against its NumPy version."""

import numpy as np
import pytest

from omnispectral.imaging import blockpoc
from omnispectral.imaging.blockpoc import occlusion_zbuffer
from omnispectral.imaging.zbuffer_kernel import compiled_zbuffer

pytestmark = pytest.mark.skipif(compiled_zbuffer() is None, reason="Numba not installed")


def _cases(seed):
    """Near squares over a far wall (float64 and float32 displacements), with targets on .5 ties, beyond the
    image and non-finite, NaN nearness; and a nearness that is NaN everywhere."""
    rng = np.random.default_rng(seed)
    h, w = 61, 83
    inv_depth = np.full((h, w), 0.02)
    for _ in range(4):
        y, x, s = rng.integers(0, h - 10), rng.integers(0, w - 10), rng.integers(3, 10)
        inv_depth[y:y + s, x:x + s] = rng.uniform(0.2, 1.0)
    dx, dy = inv_depth * 12.0, inv_depth * -3.0
    dx[rng.random((h, w)) < 0.05] = 0.5  # round-half-even ties
    dx[0, :5] = [np.nan, np.inf, -np.inf, 1e30, -1e30]
    nearness = inv_depth * 12.4
    nearness[rng.random((h, w)) < 0.02] = np.nan
    return [(dx, dy, nearness), (dx.astype(np.float32), dy.astype(np.float32), nearness),
            (dx, dy, np.full((h, w), np.nan))]


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast")  # the NumPy version casts NaN
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_zbuffer_is_the_numpy_result(monkeypatch, seed):
    """The same occluded pixels as the NumPy version; the near squares hide part of the wall."""
    cases = _cases(seed)
    compiled = [occlusion_zbuffer(*case, 0.5) for case in cases]
    monkeypatch.setattr(blockpoc, "compiled_zbuffer", lambda: None)
    plain = [occlusion_zbuffer(*case, 0.5) for case in cases]
    for got, want in zip(compiled, plain, strict=True):
        np.testing.assert_array_equal(got, want)
    assert plain[0].any() and not plain[0].all() and not plain[2].any()
