from __future__ import annotations

import colour
import numpy as np
import pytest

from omnispectral.spectral.colour import signal_to_XYZ
from omnispectral.spectral.library import load_illuminant, load_reflectances
from omnispectral.spectral.metrics import colour_differences, nrmse, spectral_angle_deg

WL = np.arange(400.0, 701.0, 5.0)


def test_nrmse_definition():
    a = np.ones(61)
    b = np.ones(61) * 7.0  # same shape, other scale -> 0
    assert nrmse(a, b) == pytest.approx(0.0)
    c = np.zeros(61)
    c[0] = 1.0
    # unit vectors: ||1/sqrt(61) - e0||^2 = 2 - 2/sqrt(61)
    assert nrmse(a, c) == pytest.approx(np.sqrt((2 - 2 / np.sqrt(61)) / 61))


def test_spectral_angle():
    x = np.zeros(61)
    x[0] = 1
    y = np.zeros(61)
    y[1] = 1
    assert spectral_angle_deg(x, y) == pytest.approx(90.0)
    assert spectral_angle_deg(x, 3 * x) == pytest.approx(0.0, abs=1e-6)


def test_XYZ_matches_colour_science_integration():
    cc = load_reflectances("colorchecker")
    d65 = load_illuminant("D65")
    shape = colour.SpectralShape(400, 700, 5)
    spd = d65.resample(WL).values[0]
    refl = cc.resample(WL).values
    ours = signal_to_XYZ(refl * spd, spd, WL)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    illum = colour.SDS_ILLUMINANTS["D65"].copy().align(shape)
    for i, name in enumerate(cc.names):
        sd = colour.SpectralDistribution(refl[i], WL, name=name)
        ref = colour.sd_to_XYZ(sd, cmfs, illum, method="Integration")
        np.testing.assert_allclose(ours[i], ref, rtol=1e-6, atol=1e-6)


def test_delta_e_matches_colour_science_pipeline():
    rng = np.random.default_rng(3)
    spd = load_illuminant("D65").resample(WL).values[0]
    true = load_reflectances("colorchecker").resample(WL).values * spd
    est = true * (1 + 0.05 * rng.standard_normal(true.shape))
    de = colour_differences(est, true, spd, WL)
    white = colour.XYZ_to_xy(signal_to_XYZ(spd, spd, WL))
    lab1 = colour.XYZ_to_Lab(signal_to_XYZ(true, spd, WL) / 100, white)
    lab2 = colour.XYZ_to_Lab(signal_to_XYZ(est, spd, WL) / 100, white)
    np.testing.assert_allclose(de["delta_e_ab"], np.linalg.norm(lab1 - lab2, axis=-1), rtol=1e-9)
    np.testing.assert_allclose(de["delta_e_2000"], colour.delta_E(lab1, lab2, method="CIE 2000"), rtol=1e-9)
    # white of a perfect diffuser has L* = 100
    assert colour.XYZ_to_Lab(signal_to_XYZ(spd, spd, WL) / 100, white)[0] == pytest.approx(100.0)
