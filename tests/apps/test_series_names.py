"""``render-series`` names each slot's folder readably, in time order and uniquely within the series."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_slot_folder_names_are_readable_sortable_and_unique():
    from omnispectral.apps.series import slot_folder_names

    labels = ["2017-06-21T06:00:00+00:00", "2017-06-21T12:30:00+00:00", "2017-06-21T12:30:15+00:00",
              "2017-06-22T00:05:00+00:00"]
    names = slot_folder_names(labels)
    assert names == ["slot_2017-06-21T0600", "slot_2017-06-21T1230", "slot_2017-06-21T123015",
                     "slot_2017-06-22T0005"]
    assert sorted(names) == names  # folder order is time order
    # one time twice (e.g. the hour repeated when clocks go back): still one folder each, in order
    twice = slot_folder_names(["2017-10-29T02:30:00+02:00", "2017-10-29T02:30:00+01:00"])
    assert twice == ["slot_2017-10-29T0230", "slot_2017-10-29T0230_2"] and sorted(twice) == twice
    # a folder of products: each slot keeps its product's folder name, made safe, with one slot_ prefix
    assert slot_folder_names(["slot_0630", "slot_1000", "noon run"]) == ["slot_0630", "slot_1000", "slot_noonrun"]
    assert slot_folder_names(["a:b", "ab", "***"]) == ["slot_ab", "slot_ab_2", "slot"]


def test_render_series_writes_slot_folders_named_by_their_time(tmp_path):
    pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install 'omnispectral[render]')")
    import zarr

    from omnispectral.apps.series import render_series
    from tests.apps.test_render_progress import write_products

    write_products(tmp_path / "series", ["slot_0600", "slot_1230"])
    g = zarr.open_group(str(tmp_path / "series" / "timestack.zarr"), mode="w", zarr_format=3)
    g.attrs.update({"times": ["2017-06-21T06:00:00+00:00", "2017-06-21T12:30:00+00:00"],
                    "products": ["slot_0600", "slot_1230"]})
    out = render_series(tmp_path / "series", tmp_path / "out", width=8, height=8, spp=1, fast=True)
    folders = sorted(p.name for p in (tmp_path / "out").iterdir() if p.name.startswith("slot_"))
    assert folders == ["slot_2017-06-21T0600", "slot_2017-06-21T1230"]
    assert [s["folder"] for s in out["slots"]] == [str(tmp_path / "out" / f) for f in folders]
    summary = json.loads((tmp_path / "out" / "render_series.json").read_text())
    assert [s["folder"] for s in summary["slots"]] == [s["folder"] for s in out["slots"]]
    assert all(np.isfinite(s["total_seconds"]) for s in summary["slots"])
