from __future__ import annotations

import numpy as np
import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.prior import SpectralPrior
from omnispectral.spectral.system import MultibandSystem, six_band_system
from omnispectral.spectral.wiener import WienerEstimator, wiener_matrix

WL = np.arange(400.0, 701.0, 5.0)


def smooth_spectra(rng, k, n=61):
    """Positive smooth spectra: sums of broad Gaussians."""
    wl = np.linspace(0, 1, n)
    out = np.zeros((k, n))
    for _ in range(4):
        c = rng.uniform(0, 1, (k, 1))
        w = rng.uniform(0.1, 0.4, (k, 1))
        out += rng.uniform(0.1, 1, (k, 1)) * np.exp(-0.5 * ((wl - c) / w) ** 2)
    return out + 0.05


def prior_from(signals, illuminants=("x",)):
    k = signals.shape[0] // len(illuminants)
    return SpectralPrior(WL, signals, ("test",), tuple(illuminants), k)


def test_wiener_matrix_closed_form_scalar():
    # n = m = 1: W = c r / (r^2 c + s2)
    assert wiener_matrix(np.array([[2.0]]), np.array([[3.0]]), 0.5)[0, 0] == pytest.approx(3 * 2 / (4 * 3 + 0.5))


def test_wiener_matrix_equals_explicit_formula():
    rng = np.random.default_rng(0)
    R = rng.uniform(0, 1, (6, 61))
    X = rng.standard_normal((200, 61))
    C = X.T @ X / 200
    W = wiener_matrix(R, C, 0.1)
    np.testing.assert_allclose(W, C @ R.T @ np.linalg.inv(R @ C @ R.T + 0.1 * np.eye(6)), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("normalized", [False, True])
def test_exact_when_prior_is_test_set_and_noise_zero(normalized):
    rng = np.random.default_rng(1)
    system = six_band_system()
    # prior spans a space the six bands can resolve: 6 spectra (rank <= 6 after normalisation)
    spectra = smooth_spectra(rng, 6)
    est = WienerEstimator.fit(system, prior_from(spectra), 0.0, normalized=normalized)
    out = est.estimate(system.response(spectra), dtype=np.float64)
    np.testing.assert_allclose(out, spectra, rtol=1e-6, atol=1e-8)


def test_normalized_form_is_exposure_equivariant_and_linear():
    rng = np.random.default_rng(2)
    system = six_band_system()
    est = WienerEstimator.fit(system, prior_from(smooth_spectra(rng, 300)), 1e-4, normalized=True)
    rho = system.response(smooth_spectra(rng, 5))
    a = est.estimate(rho, dtype=np.float64)
    np.testing.assert_allclose(est.estimate(1e4 * rho, dtype=np.float64), 1e4 * a, rtol=1e-9)
    M, b = est.linear_map()
    np.testing.assert_allclose(rho @ M.T + b, a, rtol=1e-9)
    assert np.all(b == 0)


def test_posterior_covariance_matches_monte_carlo():
    """Absolute form with a true Gaussian prior: the empirical error variance equals diag(C - WRC)."""
    rng = np.random.default_rng(4)
    system = six_band_system()
    basis = smooth_spectra(rng, 10)
    coeff = rng.standard_normal((20000, 10))
    signals = 1.0 + coeff @ basis * 0.1
    sigma2 = 1e-3
    est = WienerEstimator.fit(system, prior_from(signals), sigma2, normalized=False)
    truth = 1.0 + rng.standard_normal((4000, 10)) @ basis * 0.1
    rho = system.response(truth) + rng.normal(0, np.sqrt(sigma2), (4000, 6))
    err = est.estimate(rho, dtype=np.float64) - truth
    predicted = est.posterior_std(rho[:1], dtype=np.float64)[0] ** 2
    np.testing.assert_allclose(err.var(axis=0), predicted, rtol=0.12)


def test_per_pixel_noise_zero_equals_constant_path_and_image_shapes():
    rng = np.random.default_rng(5)
    system = six_band_system()
    est = WienerEstimator.fit(system, prior_from(smooth_spectra(rng, 200)), 1e-3)
    img = system.response(smooth_spectra(rng, 12)).reshape(3, 4, 6)
    a = est.estimate(img, dtype=np.float64, chunk_pixels=5)
    b = est.estimate(img, noise_variance=0.0, dtype=np.float64, chunk_pixels=7)
    assert a.shape == (3, 4, 61)
    np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(est.posterior_std(img, noise_variance=0.0, dtype=np.float64),
                               est.posterior_std(img, dtype=np.float64), rtol=1e-6)


def test_signal_dependent_noise_raises_uncertainty_and_shrinks_to_prior():
    rng = np.random.default_rng(6)
    system = six_band_system()
    est = WienerEstimator.fit(system, prior_from(smooth_spectra(rng, 300)), 1e-5, normalized=False)
    rho = system.response(smooth_spectra(rng, 3))
    quiet = est.posterior_std(rho, noise_variance=1e-8, dtype=np.float64)
    loud = est.posterior_std(rho, noise_variance=1e6, dtype=np.float64)
    assert np.all(loud.mean(-1) > quiet.mean(-1))
    # infinite noise: the estimate is the prior mean
    np.testing.assert_allclose(est.estimate(rho, noise_variance=1e12, dtype=np.float64),
                               np.broadcast_to(est.mean, (3, 61)), rtol=1e-4)


def test_nonnegative_clips():
    rng = np.random.default_rng(7)
    system = six_band_system()
    est = WienerEstimator.fit(system, prior_from(smooth_spectra(rng, 300)), 1e-6)
    rho = system.response(np.eye(61)[::10] * 50 + 1e-3)  # spiky spectra the prior cannot represent
    assert est.estimate(rho).min() < 0
    assert est.estimate(rho, nonnegative=True).min() >= 0


def test_mixture_with_one_component_equals_pooled_and_picks_right_light():
    rng = np.random.default_rng(8)
    system = six_band_system()
    refl = smooth_spectra(rng, 200) / 2
    warm = np.linspace(0.2, 1.8, 61)
    cold = warm[::-1].copy()
    signals = np.vstack([refl * warm, refl * cold])
    prior = prior_from(signals, ("warm", "cold"))
    mix = WienerEstimator.fit(system, prior, 1e-5, mixture=True)
    pooled = WienerEstimator.fit(system, prior, 1e-5, mixture=False)
    assert mix.n_components == 2 and pooled.n_components == 1
    np.testing.assert_allclose(mix.covariance, pooled.covariances[0], rtol=1e-6, atol=1e-12)
    test = smooth_spectra(rng, 50) / 2
    post_warm = mix.component_posterior(system.response(test * warm), dtype=np.float64)
    post_cold = mix.component_posterior(system.response(test * cold), dtype=np.float64)
    assert post_warm[:, 0].mean() > 0.8 and post_cold[:, 1].mean() > 0.8
    single = WienerEstimator.fit(system, prior_from(signals[:200]), 1e-5, mixture=True)
    pooled_single = WienerEstimator.fit(system, prior_from(signals[:200]), 1e-5)
    rho = system.response(test * warm)
    np.testing.assert_allclose(single.estimate(rho, dtype=np.float64), pooled_single.estimate(rho, dtype=np.float64),
                               rtol=1e-6)
    with pytest.raises(ConfigurationError):
        mix.linear_map()
    M, _ = mix.linear_map(np.array([1.0, 0.0]))
    np.testing.assert_allclose(M, mix._component_map(0)[0])


def test_band_count_mismatch_is_clear():
    rng = np.random.default_rng(9)
    system = six_band_system()
    est = WienerEstimator.fit(system, prior_from(smooth_spectra(rng, 50)), 1e-3)
    with pytest.raises(ConfigurationError, match="3 bands; the estimator expects 6"):
        est.estimate(np.ones((4, 3)))


def test_custom_system_dataclass():
    s = MultibandSystem(WL, np.ones((1, 61)), ("mono",), np.zeros(1, int), "mono")
    assert s.matrix.sum() == pytest.approx(61 * 5.0)
