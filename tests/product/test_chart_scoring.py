"""ColorChecker scoring against the ground truth: patches crossed by a shadow edge have no one reference."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.product.report import MAX_PATCH_RADIANCE_SPREAD, chart_scores
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.truth import patch_radiance_spread


def _scene(time_hhmm: str, distance_m: float) -> ProceduralOutdoorScene:
    # the registration matrix's chart: same angular patch size at every distance (benchmarks/)
    return ProceduralOutdoorScene(time_hhmm, seed=0, chart_distance_m=distance_m,
                                  chart_patch_m=0.05 * distance_m / 2.5,
                                  chart_lat_deg=-15.0 if distance_m <= 2.5 else -10.0)


def _spreads(scene) -> dict[str, float]:
    return {p["name"]: patch_radiance_spread(scene, p["lon_deg"], p["lat_deg"], p["half_size_deg"])
            for p in scene.colorchecker_patches()}


def test_a_shadow_edge_across_a_patch_is_found_and_sky_light_is_not():
    """At 17:00 a shadow edge crosses the chart 5 m away (15 % of the board is shaded, traced
    independently here); at noon the whole chart is in sun and only the sky's gradient varies."""
    noon = _spreads(_scene("12:00", 5.0))
    assert max(noon.values()) < 0.01
    late_scene = _scene("17:00", 5.0)
    late = _spreads(late_scene)
    crossed = {n for n, s in late.items() if s > MAX_PATCH_RADIANCE_SPREAD}
    assert "white 9.5 (.05 D)" in crossed and 1 <= len(crossed) <= 6
    # cross-check with the scene's own shadow rays: a crossed patch has lit and shaded points, the others not
    for p in late_scene.colorchecker_patches():
        g = np.linspace(-0.8, 0.8, 9) * p["half_size_deg"]
        lat = p["lat_deg"] + np.repeat(g, 9)
        lon = p["lon_deg"] + np.tile(g, 9) / np.cos(np.radians(p["lat_deg"]))
        from omnispectral.imaging.geometry import lonlat_to_ray

        sun = late_scene.shade(lonlat_to_ray(lon, lat).astype(np.float32), np.zeros(3)).sun
        assert ((sun.min() == 0) and (sun.max() > 0)) == (p["name"] in crossed), p["name"]


def test_chart_scores_leave_out_patches_that_are_not_one_colour():
    patches = [{"name": f"p{i}", "radiance_spread": 0.0} for i in range(24)]
    patches[18]["radiance_spread"] = 1.07
    de = np.full(24, 1.0)
    de[18] = 19.0
    de[3] = 3.0
    errs = np.full(24, 0.01)
    errs[18] = 0.2
    seen = np.ones(24, bool)
    seen[5] = False
    de[5] = errs[5] = np.nan
    s = chart_scores(patches, errs, de, seen)
    assert s["n_patches_seen"] == 23 and s["n_patches_scored"] == 22
    assert s["delta_e_ab_max"] == pytest.approx(3.0)
    assert s["delta_e_ab"] == pytest.approx((21 * 1.0 + 3.0) / 22)
    assert s["nrmse"] == pytest.approx(0.01)
    assert s["not_uniformly_lit"] == [{"name": "p18", "radiance_spread": 1.07, "delta_e_ab": 19.0}]
    assert [p["scored"] for p in s["per_patch"]].count(False) == 2
    # a session made before the spread was recorded scores every seen patch
    old = chart_scores([{"name": p["name"]} for p in patches], errs, de, seen)
    assert old["n_patches_scored"] == 23 and old["delta_e_ab_max"] == pytest.approx(19.0)
