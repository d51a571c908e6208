"""The Wiener estimator attached to a product: fitted for the rig's bands, described by parameters.

A product stores its bands (six for two cameras, three for a one-camera rig) plus the estimator
(DESIGN: "spectra are a linear view").  The estimator is stored twice over: as its parameters (rig
sensitivities and filters, prior, σ², form), from which :func:`estimator_from_params` re-fits exactly
the same estimator, and as ``WienerEstimator.to_dict()`` (the per-component linear maps, usable without
this package).  σ² is tuned on the calibration chart (CIE TCS + NIST CQS) measured through the rig's own
noise model, and the ColorChecker is held out of prior and calibration, so an accuracy report on the
chart in the panorama is not circular.
"""

from __future__ import annotations

import functools
import json

from omnispectral.rig import Rig, camera_system
from omnispectral.spectral.conditional import BandPredictor, b_from_a_predictor
from omnispectral.spectral.evaluate import Protocol, fit_for_protocol
from omnispectral.spectral.library import load_reflectances
from omnispectral.spectral.noise import SensorNoiseModel
from omnispectral.spectral.wiener import WienerEstimator

__all__ = ["HELD_OUT", "b_predictor", "estimator_from_params", "estimator_params", "rig_estimator"]

HELD_OUT = "colorchecker"


def estimator_params(rig: Rig, mixture: bool = True) -> dict:
    """Everything :func:`estimator_from_params` needs, JSON-able (stored in the product); a one-camera rig has
    no ``sensitivity_b`` / ``filter_b`` (three bands)."""
    a = rig.camera_a
    b = {"sensitivity_b": rig.camera_b.sensitivity, "filter_b": rig.camera_b.filter} if "B" in rig.cameras else {}
    return {"sensitivity_a": a.sensitivity, "filter_a": a.filter, **b, "full_well_e": a.full_well_e,
            "read_noise_e": a.read_noise_e, "bit_depth": a.bit_depth, "mixture": bool(mixture), "normalized": True,
            "held_out": HELD_OUT}


@functools.lru_cache(maxsize=4)
def _fit_cached(params_json: str) -> tuple[WienerEstimator, str]:
    p = json.loads(params_json)
    system = _system_from_params(p)
    noise = SensorNoiseModel(p["full_well_e"], p["read_noise_e"], p["bit_depth"])
    protocol = Protocol(target=p["held_out"], noise=noise, normalized=p["normalized"], mixture=p["mixture"])
    est, info = fit_for_protocol(system, protocol, [load_reflectances(p["held_out"]).resample(system.wavelength_nm)])
    return est, json.dumps({"sigma2": info["sigma2"], "prior": info["prior"]}, default=str)


def _system_from_params(p: dict):
    pairs = [(p["sensitivity_a"], p["filter_a"])]
    if p.get("sensitivity_b") is not None:
        pairs.append((p["sensitivity_b"], p["filter_b"]))
    return camera_system(tuple(pairs))


def estimator_from_params(params: dict) -> tuple[WienerEstimator, dict]:
    """Fit (or fetch from this process's cache) the estimator a product describes; returns it and its info."""
    est, info = _fit_cached(json.dumps(params, sort_keys=True))
    return est, json.loads(info)


def rig_estimator(rig: Rig, mixture: bool = True) -> tuple[WienerEstimator, dict]:
    """The estimator for a rig's bands, with its parameters and fit information.

    Parameters
    ----------
    rig : Rig
        The rig: each camera's sensitivity and filter (its bands), and camera A's sensor noise (full well and
        read noise in electrons, bit depth) for the σ² tuning.
    mixture : bool
        One prior component per light source (:meth:`WienerEstimator.fit`); the paper pools them.

    Returns
    -------
    estimator : WienerEstimator
        The normalized-form estimator of the rig's six (or three) bands, σ² tuned on the calibration chart
        with the ColorChecker held out (fitted once per process for the same parameters).
    info : dict
        ``params`` (:func:`estimator_params`, JSON-able, stored with the product), ``sigma2`` and ``prior``
        (the prior's description).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.6, Eqs. (6)-(7) (the Wiener estimator of the system's bands; σ²
       determined by minimising the estimation error on a chart under various light sources).
    """
    params = estimator_params(rig, mixture)
    est, info = estimator_from_params(params)
    return est, {"params": params, **info}


def b_predictor(estimator: WienerEstimator) -> BandPredictor | None:
    """The prior's predictor of camera B's bands from A's for a six-band estimator (used where B saw nothing,
    :mod:`omnispectral.mosaic.predict`); ``None`` for a three-band one."""
    return b_from_a_predictor(estimator) if estimator.n_bands == 6 else None
