"""The estimator a product carries: re-fitted exactly from its parameters, accurate on the held-out chart."""

from __future__ import annotations

import json

import numpy as np

from omnispectral.product.estimator import _fit_cached, estimator_from_params, rig_estimator
from omnispectral.rig import load_preset, rig_system
from omnispectral.spectral.library import load_illuminant, load_reflectances
from omnispectral.spectral.metrics import nrmse


def test_estimator_refits_identically_from_its_parameters():
    rig = load_preset("small")
    est, info = rig_estimator(rig)
    params = json.loads(json.dumps(info["params"]))  # as stored in a product
    _fit_cached.cache_clear()
    again, info2 = estimator_from_params(params)
    assert again is not est and info2["sigma2"] == info["sigma2"]
    rho = np.random.default_rng(0).uniform(10, 1000, (50, 6))
    np.testing.assert_array_equal(again.estimate(rho), est.estimate(rho))


def test_held_out_colorchecker_is_estimated_like_the_spectral_core():
    rig = load_preset("small")
    est, info = rig_estimator(rig)
    system = rig_system(rig)
    wl = system.wavelength_nm
    chart = load_reflectances("colorchecker").resample(wl).values
    d65 = load_illuminant("D65").resample(wl).values[0]
    signals = chart * d65 * 123.0  # any exposure: the normalized form is scale-equivariant
    estimate = est.estimate(system.response(signals))
    err = nrmse(estimate, signals)
    assert info["prior"]["n_excluded_as_held_out"] > 0
    assert float(np.mean(err)) < 0.02  # noise-free six bands; spectral core: 0.0128 with CMV2000 noise
