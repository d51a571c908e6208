"""Per-pixel channel tests one channel at a time against NumPy's reductions over the last axis."""

import numpy as np
import pytest

from omnispectral.imaging.channels import all_channels, any_channel, finite_pixels


@pytest.mark.parametrize("shape", [(7, 5, 3), (4, 6), (2, 3, 4, 6), (5, 0)])
def test_channel_reductions_are_numpys(shape):
    rng = np.random.default_rng(sum(shape))
    x = rng.normal(size=shape).astype(np.float32)
    if x.size:
        x.flat[rng.choice(x.size, size=max(1, x.size // 5), replace=False)] = rng.choice([np.nan, np.inf, -np.inf])
    mask = x > 0.3
    np.testing.assert_array_equal(any_channel(mask), mask.any(axis=-1))
    np.testing.assert_array_equal(all_channels(mask), mask.all(axis=-1))
    np.testing.assert_array_equal(finite_pixels(x), np.isfinite(x).all(axis=-1))
    assert any_channel(mask).shape == all_channels(mask).shape == shape[:-1]
