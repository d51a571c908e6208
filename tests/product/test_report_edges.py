"""The report's per-pixel section: depth discontinuities and the edge band, errors, worst pixels, holes, maps."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest

from omnispectral.imaging.geometry import equirect_pixel_to_lonlat
from omnispectral.product.report_edges import (
    PixelErrors,
    depth_discontinuities,
    depth_edge_figures,
    edge_band,
    hole_figures,
    hole_mask,
    pixel_errors,
    region_figures,
    worst_pixels,
)
from omnispectral.sim.truth import GroundTruth
from omnispectral.spectral.colour import signal_to_Lab

NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)


def columns(mask: np.ndarray) -> set[int]:
    """Columns marked in every row (and no other column marked anywhere)."""
    assert (mask == mask[:1]).all(), "the marks differ between rows"
    return set(np.flatnonzero(mask[0]).tolist())


def test_a_depth_step_gives_a_band_of_two_pixels_either_side_across_the_longitude_seam():
    depth = np.full((12, 40), 10.0)
    depth[:, :10] = 5.0  # a near object over columns 0-9: steps at 9|10 and, across the seam, at 39|0
    marks = depth_discontinuities(depth)
    assert columns(marks) == {39, 0, 9, 10}
    assert columns(edge_band(marks)) == {38, 39, 0, 1, 8, 9, 10, 11}  # within 2 px of either step


def test_slanted_planes_are_not_edges_but_the_sky_boundary_and_thin_objects_are():
    rows = np.arange(30, dtype=float)[:, None]
    cols = np.arange(60, dtype=float)[None, :]
    # inverse depth affine along the rows, smooth and periodic in longitude: depth jumps up to 500 % per pixel
    ground = 1.0 / (0.002 + 0.01 * rows + 0.003 * (1 + np.cos(2 * np.pi * cols / 60)))
    assert not depth_discontinuities(ground).any()
    sky = ground.copy()
    sky[:8] = np.inf
    assert set(np.flatnonzero(depth_discontinuities(sky).any(axis=1)).tolist()) == {7, 8}
    post = np.full((10, 60), 20.0)
    post[:, 30] = 2.0  # one pixel wide, in front
    assert columns(depth_discontinuities(post)) == {29, 30, 31}
    small = np.full((10, 60), 20.0)
    small[:, 30] = 20.5  # a 2.5 % step is no discontinuity
    assert not depth_discontinuities(small).any()


class LinearEstimator:
    """Spectra = bands @ basis on 400-700 nm: enough to check that both sides go through the same estimator."""

    wavelength_nm = np.arange(400.0, 701.0, 10.0)

    def __init__(self):
        wl = self.wavelength_nm
        self.basis = np.stack([np.exp(-0.5 * ((wl - 450) / 40) ** 2), np.exp(-0.5 * ((wl - 600) / 50) ** 2)])

    def estimate(self, bands):
        return np.asarray(bands, np.float64) @ self.basis


def test_the_errors_of_a_hand_computed_case(monkeypatch):
    truth = np.array([[[3.0, 4.0], [6.0, 8.0], [1.0, 1.0], [2.0, 2.0]]])  # ‖t‖ = 5, 10, √2, √8
    bands = truth + np.array([[[0.3, 0.4], [0.0, 0.0], [0.1, -0.1], [0.0, 0.0]]])
    scored = np.ones((1, 4), bool)
    edge = np.array([[True, True, False, False]])
    est = LinearEstimator()
    white = est.estimate(np.array([10.0, 10.0]))
    errors = pixel_errors(bands, truth, scored, est, white, edge)
    np.testing.assert_allclose(errors.band_nrmse[0], [0.1, 0.0, 0.1, 0.0], atol=1e-6)
    lab_b = signal_to_Lab(est.estimate(bands[0]), white, est.wavelength_nm)
    lab_t = signal_to_Lab(est.estimate(truth[0]), white, est.wavelength_nm)
    delta_e = np.linalg.norm(lab_b - lab_t, axis=-1)
    np.testing.assert_allclose(errors.delta_e_ab[0], delta_e, rtol=1e-5)
    assert delta_e[0] > 1 and delta_e[1] == 0

    figures = depth_edge_figures(errors)
    e, s = figures["edge"], figures["smooth"]
    assert e["n_pixels"] == s["n_pixels"] == 2 and figures["edge_fraction"] == 0.5
    assert e["band_nrmse"] == pytest.approx(math.sqrt(0.25 / (25 + 100)))  # pooled: sqrt(Σ‖b − t‖² / Σ‖t‖²)
    assert s["band_nrmse"] == pytest.approx(math.sqrt(0.02 / (2 + 8)))
    assert e["band_nrmse_median"] == pytest.approx(0.05)
    assert e["delta_e_ab"] == pytest.approx(delta_e[:2].mean(), rel=1e-5)
    assert s["delta_e_ab"] == pytest.approx(delta_e[2:].mean(), rel=1e-5)
    assert figures["ratio"]["band_nrmse"] == pytest.approx(math.sqrt(0.25 / 125) / math.sqrt(0.02 / 10))
    assert figures["ratio"]["delta_e_ab"] == pytest.approx(delta_e[:2].mean() / delta_e[2:].mean(), rel=1e-5)
    monkeypatch.setattr("omnispectral.product.report_edges.ESTIMATE_BLOCK_PX", 4)  # one row per block
    twice = pixel_errors(np.vstack([bands, bands]), np.vstack([truth, truth]), np.ones((2, 4), bool), est, white,
                         np.vstack([edge, edge]))
    np.testing.assert_array_equal(twice.delta_e_ab, np.vstack([errors.delta_e_ab] * 2))
    np.testing.assert_array_equal(twice.band_nrmse, np.vstack([errors.band_nrmse] * 2))
    unscored = PixelErrors(errors.error_sq, errors.truth_sq, errors.delta_e_ab, np.zeros((1, 4), bool), edge)
    assert region_figures(unscored, edge)["band_nrmse"] is None

    by_camera = depth_edge_figures(pixel_errors(bands, truth, scored, est, white, edge, ["A:R", "B:R"]))
    assert by_camera["edge"]["band_nrmse"] == pytest.approx(e["band_nrmse"])
    assert by_camera["edge"]["band_nrmse_by_camera"]["A"] == pytest.approx(math.sqrt(0.09 / (9 + 36)))
    assert by_camera["edge"]["band_nrmse_by_camera"]["B"] == pytest.approx(math.sqrt(0.16 / (16 + 64)))
    assert by_camera["ratio"]["band_nrmse_by_camera"]["B"] == pytest.approx(
        math.sqrt(0.16 / 80) / math.sqrt(0.01 / 5))


def test_worst_pixels_are_the_largest_errors_worst_first_with_their_directions():
    rng = np.random.default_rng(1)
    h, w = 20, 40
    nrmse = rng.uniform(0, 0.01, (h, w)).astype(np.float32)
    bad = [(3, 7, 0.9), (15, 39, 0.5), (0, 0, 0.7)]
    for r, c, v in bad:
        nrmse[r, c] = v
    scored = np.ones((h, w), bool)
    scored[5, 5] = False
    nrmse[5, 5] = 99.0  # not scored: never listed
    edge = np.zeros((h, w), bool)
    edge[3, 7] = True
    errors = PixelErrors(nrmse[..., None] ** 2, np.ones((h, w, 1), np.float32), 2 * nrmse, scored, edge)
    worst = worst_pixels(errors, fraction=3 / scored.sum())
    assert [(p["row"], p["col"]) for p in worst] == [(3, 7), (0, 0), (15, 39)]
    lon, lat = equirect_pixel_to_lonlat(7, 3, w, h)
    assert worst[0]["lon_deg"] == pytest.approx(float(lon), abs=1e-4) and worst[0]["lat_deg"] == pytest.approx(
        float(lat), abs=1e-4)
    assert worst[0]["band_nrmse"] == pytest.approx(0.9, rel=1e-6) and worst[0]["delta_e_ab"] == pytest.approx(1.8)
    assert [p["at_depth_edge"] for p in worst] == [True, False, False]
    assert len(worst_pixels(errors)) == 1  # 0.1 % of 799 pixels: at least one


def test_holes_are_pixels_camera_a_covers_with_a_band_missing():
    names = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]
    bands = np.ones((4, 5, 6), np.float32)
    bands[0, :] = np.nan  # nothing covers row 0
    bands[1, 2, 4] = np.nan  # a hole
    bands[2, 3, 3:] = np.nan  # a hole
    bands[3, 1, 0] = np.nan  # A itself missing: not a hole
    mask = hole_mask(bands, names)
    assert sorted(zip(*np.nonzero(mask), strict=True)) == [(1, 2), (2, 3)]
    assert hole_figures(int(mask.sum()), 14)["n_pixels"] == 2
    assert not hole_mask(bands[..., :3], names[:3]).any()  # a one-camera product has none


def test_the_truth_records_depth_from_its_own_ray_casts(tmp_path):
    from omnispectral.rig import load_preset
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.scenes.panorama import PanoramaScene
    from omnispectral.sim.simulate import RigRenderer
    from omnispectral.sim.truth import write_ground_truth

    rig = load_preset("small")
    scene = ProceduralOutdoorScene(time_hhmm="12:00", chart_distance_m=2.5)
    meta = write_ground_truth(tmp_path / "gt", RigRenderer(rig, scene, electrons_per_unit=1.0), 64)
    depth = np.load(tmp_path / "gt" / meta["depth"]["file"])
    assert depth.shape == (32, 64) and depth.dtype == np.float32 and meta["depth"]["units"] == "m"
    assert np.isinf(depth[0]).all()  # the zenith row sees the sky
    nadir = 1.5 / math.sin(math.radians(90 - 0.25 * 180 / 32))  # the nearest of the bottom pixels' 2 × 2 rays
    assert depth[-1] == pytest.approx(np.full(64, nadir), rel=1e-4)
    env = PanoramaScene(np.full((16, 32, 3), 0.5, np.float32))
    meta = write_ground_truth(tmp_path / "env", RigRenderer(rig, env, electrons_per_unit=1.0), 32)
    assert meta["depth"] is None and "no geometry" in meta["depth_note"]
    assert not (tmp_path / "env" / "depth_m.npy").exists()


def test_every_ray_traced_scene_gives_its_bands_and_depth_from_one_cast():
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.scenes.base import equirect_directions
    from omnispectral.sim.scenes.cube import CubeOnWallScene
    from omnispectral.sim.scenes.indoor import IndoorScene

    base = ProceduralOutdoorScene(time_hhmm="12:00")
    wl = base.wavelength_nm
    cube = (np.full((2, 3, 2), 0.4, np.float32), np.array([wl[0], wl[-1]]))
    d = equirect_directions(32, 16).reshape(-1, 3)
    sensitivity = np.ones((2, wl.size)) * np.linspace(0, 1, 2)[:, None]
    for scene, sky in ((base, True), (CubeOnWallScene(cube, base=base), True), (IndoorScene("D65"), False)):
        bands, depth = scene.band_radiance_and_depth(d, sensitivity)
        np.testing.assert_array_equal(bands, scene.band_radiance(d, sensitivity))
        assert depth.shape == (d.shape[0],) and (depth > 0).all() and np.isinf(depth).any() == sky


def test_a_simulated_report_shows_edges_worst_pixels_holes_and_quality(tmp_path):
    from omnispectral.product.process import process
    from omnispectral.product.report import write_report
    from omnispectral.sim.simulate import simulate_session
    from tests.reliability.test_fault_injection import tiny_rig, tiny_scene

    simulate_session(tmp_path / "s", tiny_rig(), tiny_scene(), start=NOON, ground_truth_width=256, progress=False)
    process(tmp_path / "s", tmp_path / "p", truth=GroundTruth.of_session(tmp_path / "s"), width=256, progress=False)
    report = json.loads((tmp_path / "p" / "report" / "report.json").read_text())
    pe = report["accuracy"]["pixel_errors"]
    de = pe["depth_edges"]
    for region in (pe["all"], de["edge"], de["smooth"]):
        assert region["n_pixels"] > 0 and all(math.isfinite(region[k]) for k in
                                              ("band_nrmse", "band_nrmse_median", "delta_e_ab", "delta_e_ab_median"))
    ratios = [v for k, v in de["ratio"].items() if k != "band_nrmse_by_camera"]
    assert len(ratios) == 4 and all(math.isfinite(v) and v > 0 for v in ratios)
    assert set(de["ratio"]["band_nrmse_by_camera"]) == {"A", "B"}
    worst = pe["worst_pixels"]
    assert worst["n"] == math.ceil(0.001 * worst["n_scored_pixels"]) == len(worst["pixels"])
    assert all(math.isfinite(p["band_nrmse"]) and -180 <= p["lon_deg"] < 180 for p in worst["pixels"])
    assert report["holes"]["n_pixels"] >= 0 and report["holes"]["a_covered_pixels"] > 0
    files = report["files"]
    assert {"error_map", "worst_pixels_map"} <= set(files)
    html = (tmp_path / "p" / "report" / "report.html").read_text()
    assert "error_map.png" in html and "worst_pixels.png" in html and "edge / smooth" in html

    # a session simulated before the truth had depth still reports, and says why the edges are missing
    gt = tmp_path / "s" / "ground_truth"
    (gt / "depth_m.npy").unlink()
    meta = json.loads((gt / "ground_truth.json").read_text())
    del meta["depth"]
    (gt / "ground_truth.json").write_text(json.dumps(meta))
    truth = GroundTruth.of_session(tmp_path / "s")
    old = write_report(tmp_path / "p", truth=truth)["report"]["accuracy"]["pixel_errors"]
    assert old["depth_edges"] is None and "no depth map" in old["depth_edges_note"]
    assert math.isfinite(old["all"]["band_nrmse"]) and old["worst_pixels"]["pixels"][0]["at_depth_edge"] is None
