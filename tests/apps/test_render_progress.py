"""``render`` and ``render-series`` report progress from their start: before the product's environment is
loaded and before any Mitsuba pass (or slot) is done, then per pass and per slot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install 'omnispectral[render]')")

from omnispectral.apps import render as render_module
from omnispectral.apps import series as series_module
from omnispectral.product.estimator import estimator_params, rig_estimator
from omnispectral.rig import load_preset


def write_products(root: Path, names: list[str]) -> None:
    """Tiny products (a smooth sky of the small rig's six bands, 16 x 32 px), one per name under ``root``."""
    from omnispectral.product.layout import write_band_product

    rig = load_preset("small")
    est = rig_estimator(rig)[0]
    h = 16
    lat = np.radians(90 - (np.arange(h) + 0.5) / h * 180)
    spectra = (1.0 + 0.5 * np.sin(lat))[:, None, None] * np.ones((h, 2 * h, est.system_matrix.shape[1]))
    bands = (1000 * spectra @ est.system_matrix.T).astype(np.float32)
    for name in names:
        write_band_product(root / name, bands, {"bands": list(est.band_names), "units": "DN/s",
                                                "estimator": {"params": estimator_params(rig)}}, tile=16)


@pytest.fixture(scope="module")
def products(tmp_path_factory):
    root = tmp_path_factory.mktemp("products")
    write_products(root, ["slot_a", "slot_b"])
    return root


def _recording(monkeypatch, module, name: str, events: list) -> None:
    """Record each call of ``module.name`` (the work) in ``events`` beside the progress reports."""
    work = getattr(module, name)

    def recorded(*args, **kwargs):
        result = work(*args, **kwargs)
        events.append(("done", name))
        return result

    monkeypatch.setattr(module, name, recorded)


@pytest.mark.parametrize("fast", [False, True])
def test_render_reports_before_loading_and_before_the_first_pass(products, tmp_path, monkeypatch, fast):
    events = []
    _recording(monkeypatch, render_module, "environment_from_product", events)
    _recording(monkeypatch, render_module, "render_rgb", events)
    render_module.render_product(products / "slot_a", tmp_path / "r", width=8, height=8, spp=1,
                                 wavelength_step_nm=50.0, fast=fast,
                                 progress=lambda stage, done, total: events.append((stage, done, total)))
    n = 2 if fast else 3
    assert events[0] == ("environment", 0, 1)  # before the product is read and its estimator set up
    assert events[1:3] == [("done", "environment_from_product"), ("environment", 1, 1)]
    assert events[3] == ("render passes", 0, n)  # before the first Mitsuba pass
    passes = events[4:]
    assert passes == [e for k in range(1, n + 1) for e in (("done", "render_rgb"), ("render passes", k, n))]


def test_render_series_reports_before_the_first_slot(products, tmp_path, monkeypatch):
    events = []
    _recording(monkeypatch, series_module, "render_product", events)
    series_module.render_series(products, tmp_path / "s", width=8, height=8, spp=1, fast=True,
                                progress=lambda stage, done, total: events.append((stage, done, total)))
    assert events[0] == ("slots", 0, 2)  # before the first slot's rendering starts
    slots = [e for e in events if e[0] in ("slots", "done")]
    assert slots == [("slots", 0, 2), ("done", "render_product"), ("slots", 1, 2), ("done", "render_product"),
                     ("slots", 2, 2)]
    # within each slot, its passes are reported too
    assert events[1] == ("environment", 0, 1) and events.count(("render passes", 0, 2)) == 2
