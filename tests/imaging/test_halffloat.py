"""float16 conversions through OpenCV give NumPy's bits (the merged images' storage)."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.imaging.halffloat import to_float16, to_float32


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    view = np.uint16 if a.dtype == np.float16 else np.uint32
    return a.dtype == b.dtype and a.shape == b.shape and bool(
        ((a.view(view) == b.view(view)) | (np.isnan(a) & np.isnan(b))).all())


@pytest.fixture(scope="module")
def values() -> np.ndarray:
    """Radiance-like float32 over 24 decades, both signs, with the special values in the first row."""
    rng = np.random.default_rng(7)
    x = (10.0 ** rng.uniform(-12, 12, (64, 96, 3))).astype(np.float32)
    x *= rng.choice([-1, 1], x.shape).astype(np.float32)
    x[0, :4] = [[np.nan, np.inf, -np.inf], [0.0, -0.0, 65504.0], [65520.0, 1e-8, 6e-8], [3e-5, 2.0**-24, 2.0**-14]]
    return x


@pytest.mark.parametrize("factor", [2.0**-30, 2.0**-3, 1.0, 2.0**10])
def test_to_float16_and_back_match_numpy_bit_for_bit(values, factor):
    ref16 = np.empty(values.shape, np.float16)
    with np.errstate(over="ignore"):
        np.multiply(values, np.float32(factor), out=ref16, casting="unsafe")
    got16 = to_float16(values, factor)
    assert _same_bits(got16, ref16)
    assert _same_bits(to_float32(got16, 1.0 / factor), ref16.astype(np.float32) * np.float32(1.0 / factor))


@pytest.mark.parametrize("shape", [(0, 3), (5,), (7, 1), (3, 4, 2, 3)])
def test_any_shape_and_layout(shape):
    x = np.arange(int(np.prod(shape)), dtype=np.float32).reshape(shape) * np.float32(0.37)
    assert _same_bits(to_float16(x), x.astype(np.float16))
    strided = np.asfortranarray(x.astype(np.float16))
    assert _same_bits(to_float32(strided, 4.0), strided.astype(np.float32) * np.float32(4.0))


def test_other_dtypes_go_through_numpy():
    x = np.linspace(-3, 3, 24, dtype=np.float32).reshape(2, 4, 3)
    assert to_float32(x) is x  # nothing to convert
    assert _same_bits(to_float32(x, 0.5), x * np.float32(0.5))
    assert _same_bits(to_float32(x.astype(np.float64), 2.0), x * np.float32(2.0))
