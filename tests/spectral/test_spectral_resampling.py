"""One spectral resampling (``resample_spectra``, its matrix form ``resample_matrix``) and one colour module."""

from __future__ import annotations

import colour
import numpy as np
import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.colour import cmfs_on_grid, spectra_to_linear_srgb, spectra_to_xyz, xyz_to_linear_srgb
from omnispectral.spectral.curves import SpectralSet, resample_matrix, resample_spectra

SRC = np.array([400.0, 410.0, 425.0, 440.0, 470.0, 500.0, 560.0, 600.0, 650.0, 700.0])
DST = np.arange(400.0, 700.0 + 1e-9, 7.0)


def _spectra(shape=(4, 3)):
    return np.random.default_rng(0).uniform(0.0, 2.0, (*shape, SRC.size))


def test_resample_spectra_is_np_interp_bit_for_bit():
    v = _spectra()
    out = resample_spectra(v, SRC, DST)
    assert out.shape == (4, 3, DST.size) and out.dtype == np.float64
    for idx in np.ndindex(4, 3):
        np.testing.assert_array_equal(out[idx], np.interp(DST, SRC, v[idx]))
    # colour-science's linear interpolator is np.interp too
    np.testing.assert_array_equal(out[0, 0], colour.LinearInterpolator(SRC, v[0, 0])(DST))


def test_the_matrix_form_is_the_same_interpolation():
    v = _spectra((50,))
    np.testing.assert_allclose(v @ resample_matrix(SRC, DST).T, resample_spectra(v, SRC, DST), rtol=1e-14, atol=0)


def test_outside_the_source_range():
    v = _spectra((2,))
    wide = np.array([390.0, 400.0, 550.0, 710.0])
    with pytest.raises(ConfigurationError, match="does not cover"):
        resample_spectra(v, SRC, wide)
    with pytest.raises(ConfigurationError, match="does not cover"):
        resample_matrix(SRC, wide)
    edge = resample_spectra(v, SRC, wide, outside="edge")
    np.testing.assert_array_equal(edge[:, 0], v[:, 0])
    np.testing.assert_array_equal(edge[:, -1], v[:, -1])
    zero = resample_spectra(v, SRC, wide, outside=0.0)
    assert np.all(zero[:, [0, -1]] == 0.0) and np.array_equal(zero[:, 1:3], edge[:, 1:3])
    with pytest.raises(ConfigurationError, match="outside"):
        resample_spectra(v, SRC, DST, outside="extrapolate")
    with pytest.raises(ConfigurationError, match="strictly increasing"):
        resample_spectra(v, SRC[::-1], DST)
    with pytest.raises(ConfigurationError, match="do not match"):
        resample_spectra(v[:, :-1], SRC, DST)


def test_spectral_set_linear_resampling_calls_it():
    s = SpectralSet(SRC, _spectra((3,)), ["a", "b", "c"], "signal", "test")
    np.testing.assert_array_equal(s.resample(DST).values, resample_spectra(s.values, SRC, DST))


def test_xyz_keeps_float64_and_srgb_is_float32():
    wl = np.arange(400.0, 700.0 + 1e-9, 5.0)
    s64 = np.random.default_rng(1).uniform(0.0, 1.0, (5, wl.size))
    xyz64 = spectra_to_xyz(s64, wl)
    assert xyz64.dtype == np.float64
    np.testing.assert_allclose(xyz64, s64 @ (cmfs_on_grid(wl).T * 5.0), rtol=1e-12)
    xyz32 = spectra_to_xyz(s64.astype(np.float32), wl)
    assert xyz32.dtype == np.float32
    rgb = spectra_to_linear_srgb(s64, wl)
    assert rgb.dtype == np.float32
    np.testing.assert_array_equal(rgb, xyz_to_linear_srgb(xyz32))  # computed from the float32 spectra
    with pytest.raises(ConfigurationError, match="do not match"):
        spectra_to_xyz(s64[:, :-1], wl)
