from __future__ import annotations

import numpy as np
import pytest

from omnispectral.spectral.noise import CMV2000, SensorNoiseModel, measure_patches


def test_cmv2000_constants():
    assert CMV2000.max_dn == 4095
    assert CMV2000.gain_e_per_dn == pytest.approx(13500 / 4095)


def test_sampled_mean_and_variance_follow_the_model():
    rng = np.random.default_rng(0)
    for mu_e in (50.0, 2000.0, 10000.0):
        dn = CMV2000.sample_dn(np.full(200_000, mu_e), rng)
        assert dn.mean() == pytest.approx(mu_e / CMV2000.gain_e_per_dn, rel=0.01)
        assert dn.var() == pytest.approx(float(CMV2000.variance_dn2(dn.mean())), rel=0.03)


def test_saturation_clips_to_max_code():
    dn = CMV2000.sample_dn(np.full(1000, 30000.0), np.random.default_rng(1))
    assert np.all(dn == 4095)


def test_patch_means_noise_free_and_noisy():
    signal = np.array([[1.0, 2.0, 3.0, 0.5, 0.6, 0.7], [0.1, 0.2, 0.3, 0.05, 0.06, 0.07]])
    cams = np.array([0, 0, 0, 1, 1, 1])
    clean, var0 = measure_patches(signal, cams, None)
    np.testing.assert_array_equal(clean, signal)
    assert np.all(var0 == 0)
    # repeated patch measurements scatter as predicted by the returned variance
    rng = np.random.default_rng(2)
    draws = np.array([measure_patches(signal, cams, CMV2000, rng, patch_px=8)[0] for _ in range(400)])
    _, var = measure_patches(signal, cams, CMV2000, rng, patch_px=8)
    np.testing.assert_allclose(draws.mean(0), signal, rtol=0.01)
    np.testing.assert_allclose(draws.var(0), var, rtol=0.25)


def test_invalid_model_rejected():
    with pytest.raises(ValueError):
        SensorNoiseModel(full_well_e=-1)
