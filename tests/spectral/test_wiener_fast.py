"""The fast stacked estimator equals the one-component-at-a-time reference."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from omnispectral.spectral.prior import build_prior
from omnispectral.spectral.system import six_band_system
from omnispectral.spectral.wiener import WienerEstimator, apply_linear_map
from omnispectral.threads import kernel_threads, single_threaded_blas

TOL = 1e-6  # relative to each pixel's largest value
#: The float32 mixture estimate sums 60 products per value in single precision, in the order of the host's sgemm
#: kernel: 1.04e-6 on an AMD EPYC host (AVX-512), 6.2e-7 on an Intel one; 32 float32 roundings of the peak.
TOL_FLOAT32 = 32 * float(np.finfo(np.float32).eps)


def peak_relative_error(fast: np.ndarray, ref: np.ndarray) -> float:
    fast = np.asarray(fast, np.float64).reshape(-1, fast.shape[-1])
    ref = np.asarray(ref, np.float64).reshape(-1, ref.shape[-1])
    return float((np.abs(fast - ref).max(axis=1) / np.abs(ref).max(axis=1)).max())


@pytest.fixture(scope="module")
def setup():
    system = six_band_system()
    prior = build_prior()
    rng = np.random.default_rng(17)
    n = 1500
    random = rng.uniform(0.01, 1.0, (n, 6)).astype(np.float32)
    # realistic: the prior's colour signals (nine lights x reflectances) at brightness spanning 1e4, plus noise
    pick = rng.choice(len(prior.signals), n)
    clean = system.response(prior.signals[pick] * np.geomspace(0.01, 100, n)[:, None])
    realistic = (clean * (1 + 0.01 * rng.standard_normal(clean.shape))).astype(np.float32)
    return system, prior, {"random": random, "realistic": realistic}


@pytest.fixture(scope="module", params=[True, False], ids=["normalized", "absolute"])
def estimators(request, setup):
    system, prior, _ = setup
    return (WienerEstimator.fit(system, prior, 1e-5, normalized=request.param, mixture=True),
            WienerEstimator.fit(system, prior, 1e-5, normalized=request.param))


@pytest.mark.parametrize("data", ["random", "realistic"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_mixture_estimate_std_and_posterior_equal_reference(setup, estimators, data, dtype):
    rho = setup[2][data]
    mix = estimators[0]
    assert mix.n_components == 9 and mix._kernel is not None
    err = peak_relative_error(mix.estimate(rho, dtype=dtype, chunk_pixels=256),
                              mix._estimate_reference(rho, dtype=dtype))
    assert err <= (TOL if dtype is np.float64 else TOL_FLOAT32)
    err = peak_relative_error(mix.posterior_std(rho, dtype=dtype, chunk_pixels=256),
                              mix._posterior_std_reference(rho, dtype=dtype))
    assert err <= TOL
    post = mix.component_posterior(rho, dtype=np.float64, chunk_pixels=256)
    np.testing.assert_allclose(post.sum(axis=1), 1.0, atol=1e-12)
    assert np.abs(post - mix._component_posterior_reference(rho, dtype=np.float64)).max() <= TOL


@pytest.mark.parametrize("data", ["random", "realistic"])
def test_per_pixel_noise_variance_equals_reference(setup, estimators, data):
    rho = setup[2][data][:300]
    variance = 1e-3 * np.abs(rho) + 1e-6  # shot-noise-like, per pixel and band
    for est in estimators:
        err = peak_relative_error(est.estimate(rho, noise_variance=variance, chunk_pixels=128),
                                  est._estimate_reference(rho, noise_variance=variance))
        assert err <= TOL
        err = peak_relative_error(est.posterior_std(rho, noise_variance=variance, chunk_pixels=128),
                                  est._posterior_std_reference(rho, noise_variance=variance))
        assert err <= TOL
    mix = estimators[0]
    assert np.abs(mix.component_posterior(rho, noise_variance=variance, dtype=np.float64)
                  - mix._component_posterior_reference(rho, noise_variance=variance, dtype=np.float64)).max() <= TOL


def test_linear_maps_equal_reference(setup, estimators):
    rho = setup[2]["realistic"]
    mix, pooled = estimators
    err = peak_relative_error(pooled.estimate(rho, chunk_pixels=300), pooled._estimate_reference(rho))
    assert err <= TOL
    # fixed weights (a region's mean posterior): the mixture is one linear map
    w = mix.component_posterior(rho[:200], dtype=np.float64).mean(axis=0)
    M, b = mix.linear_map(w)
    maps = [mix._component_map(j) for j in range(mix.n_components)]
    explicit = sum(wj * (rho.astype(np.float64) @ Mj.T + bj) for wj, (Mj, bj) in zip(w, maps, strict=True))
    assert peak_relative_error(apply_linear_map(rho, M, b, chunk_pixels=300), explicit) <= TOL
    assert peak_relative_error(apply_linear_map(rho, M, b, dtype=np.float64), explicit) <= 1e-12


def test_threads_do_not_change_results_and_blas_is_held_to_one(setup, estimators, monkeypatch):
    rho = setup[2]["realistic"]
    mix = estimators[0]
    monkeypatch.setenv("OMNISPECTRAL_THREADS", "1")
    one = mix.estimate(rho, chunk_pixels=100)
    monkeypatch.setenv("OMNISPECTRAL_THREADS", "2")
    two = mix.estimate(rho, chunk_pixels=100)
    np.testing.assert_array_equal(one, two)
    monkeypatch.delenv("OMNISPECTRAL_THREADS")
    with ThreadPoolExecutor(1) as pool:  # inside somebody else's pool: one thread
        assert pool.submit(kernel_threads).result() == 1
    before = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
    with single_threaded_blas(), single_threaded_blas():
        assert all(i["num_threads"] == 1 for i in threadpool_info() if i["user_api"] == "blas")
    assert [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"] == before


def test_singular_component_falls_back_to_reference(setup):
    system, prior, data = setup
    est = WienerEstimator.fit(system, prior, 0.0, mixture=True)
    rho = data["random"][:50]
    if est._kernel is None:  # sigma2 = 0 may leave an innovation covariance singular: the reference path runs
        np.testing.assert_array_equal(est.estimate(rho), est._estimate_reference(rho))
    else:
        assert peak_relative_error(est.estimate(rho, dtype=np.float64),
                                   est._estimate_reference(rho, dtype=np.float64)) <= TOL


def test_estimate_writes_into_a_given_output(setup, estimators):
    """``out=``: the same spectra written in place (every path: mixture, per-pixel noise, one linear map); a wrong
    output is refused before anything is computed."""
    rho = setup[2]["realistic"].reshape(30, 50, 6)
    mix, pooled = estimators
    var = np.full(rho.shape, 1e-4, np.float32)
    for est, kwargs in ((mix, {}), (mix, {"noise_variance": var}), (pooled, {})):
        for dtype in (np.float32, np.float64):
            buf = np.full((30, 50, 61), np.nan, dtype)
            got = est.estimate(rho, dtype=dtype, out=buf, **kwargs)
            assert got is buf
            np.testing.assert_array_equal(buf, est.estimate(rho, dtype=dtype, **kwargs))
    for bad in (np.empty((30, 50, 60), np.float32), np.empty((30, 50, 61), np.float64),
                np.empty((50, 30, 61), np.float32).transpose(1, 0, 2)):
        with pytest.raises(ValueError, match=r"out must be a writeable C-contiguous float32 array of shape "
                                             r"\(30, 50, 61\)"):
            mix.estimate(rho, out=bad)


def test_compiled_posterior_passes_equal_their_numpy_definition(setup):
    """The single-precision estimate's two compiled passes against NumPy: the relative log-likelihoods
    (float64 quadratic forms, floored 69 below the pixel's largest), the normalized posterior and the product's
    rows, the posterior's own rows included; a pixel of zero brightness and a NaN pixel stay in their column."""
    from omnispectral.spectral.wiener import _Workspace
    from omnispectral.spectral.wiener_kernels import mixture_kernels

    system, prior, data = setup
    mix = WienerEstimator.fit(system, prior, 1e-5, mixture=True)
    k, compiled = mix._kernel, mixture_kernels()
    r = np.concatenate([data["realistic"], data["random"][:37], np.zeros((1, 6), np.float32),
                        np.full((1, 6), np.nan, np.float32)])  # 1539 px: a partial last sub-block
    N, K, m = r.shape[0], k.K, k.m
    rel = np.empty((K, N), np.float32)
    compiled.relative_log_likelihoods(r, k.a, k.quad_form, *k.triu, -69.0, rel)

    ws = _Workspace()
    rho_n_t = k.normalized(r, ws)[2]
    feats = np.concatenate([rho_n_t[k.triu[0]] * rho_n_t[k.triu[1]], rho_n_t, np.ones((1, N))])
    log_like = k.quad_form @ feats
    expected = np.maximum(log_like - log_like.max(axis=0), -69.0)
    ok = np.isfinite(expected).all(axis=0)
    assert ok.sum() == N - 1 and not ok[-1]
    # float64 sums in another order: the terms reach ~1e5 where a pixel's log-likelihoods differ by O(1)
    assert np.abs(rel[:, ok] - expected[:, ok]).max() <= 1e-5 * np.abs(log_like[:, ok]).max()
    assert np.isnan(rel[:, -1]).any()

    p = np.exp(rel)
    rows = np.full((K * m + m + K, N), -1.0, np.float32)
    compiled.posterior_weighted_rows(p, r, rows, True)
    reference = k.posterior(rho_n_t, ws, np.float32)
    assert np.abs(p[:, ok] - reference[:, ok]).max() <= 2e-6
    np.testing.assert_allclose(p[:, ok].sum(axis=0), 1.0, atol=1e-6)
    want = np.concatenate([(p[:, None, :] * r.T[None]).reshape(K * m, N), r.T, p])
    np.testing.assert_allclose(rows[:, ok], want[:, ok], rtol=1e-6, atol=0)
    assert np.isnan(rows[:, -1]).any() and not np.isnan(rows[:, :-1]).any()
    # strided pixel rows (every other row of a wider array) take the NumPy passes: the same spectra
    wide = np.zeros((N - 2, 2, 6), np.float32)
    wide[:, 0] = r[:-2]
    strided = wide[:, 0]
    assert not strided.flags.c_contiguous
    assert peak_relative_error(mix.estimate(strided), mix.estimate(r[:-2])) <= TOL
