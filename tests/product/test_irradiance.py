"""Irradiance of a plane from an equirectangular panorama, and its split into sun and sky (product.irradiance)."""

from __future__ import annotations

import json
import math

import colour
import numpy as np
import pytest

from omnispectral.imaging.sundisk import cap_solid_angle_sr, equirect_disk_coverage
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import rig_estimator
from omnispectral.product.irradiance import irradiance, sun_sky_irradiance
from omnispectral.rig import load_preset, one_camera_rig
from omnispectral.spectral.library import daylight_spd

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]


def _disk_panorama(height: int, lon_deg: float, lat_deg: float, radius_deg: float, radiance: float) -> np.ndarray:
    """A dark panorama holding a uniform disk painted with its exact pixel coverage."""
    pano = np.zeros((height, 2 * height, 1))
    rows, cols, frac = equirect_disk_coverage(lon_deg, lat_deg, radius_deg, 2 * height, height)
    pano[rows, cols, 0] = frac * radiance
    return pano


@pytest.mark.parametrize("height", [90, 180])
def test_irradiance_matches_analytic_answers(height):
    width = 2 * height
    # uniform L over the upper hemisphere: π L on a horizontal plane; NaN below counts as 0 and as uncovered
    sky = np.full((height, width, 2), np.nan, np.float32)
    sky[: height // 2] = (3.0, 0.5)
    up = irradiance(sky)
    np.testing.assert_allclose(up.band_irradiance_dn_s_sr, math.pi * np.array([3.0, 0.5]), rtol=1e-9)
    assert up.covered_fraction == pytest.approx(1.0) and up.covered_solid_angle_fraction == pytest.approx(0.5)
    down = irradiance(sky, normal=(0, -2, 0))  # any length: normalised
    assert down.band_irradiance_dn_s_sr == pytest.approx([0.0, 0.0], abs=1e-12) and down.covered_fraction == 0.0
    # uniform L over the whole sphere: π L for any normal (tilted: its horizon cuts pixels)
    tilted = irradiance(np.ones((height, width, 1)), normal=(0.3, 0.8, -0.5))
    assert tilted.band_irradiance_dn_s_sr[0] == pytest.approx(math.pi, rel=1e-3)
    # a 2° disk of radiance L at elevation h: ∫_cap ω·n dω = π sin²r sin h (= L Ω sin h · (1 + cos r)/2)
    for lat in (5.0, 35.0, 70.0):
        disk = _disk_panorama(height, 20.0, lat, 2.0, 100.0)
        exact = 100.0 * math.pi * math.sin(math.radians(2.0)) ** 2 * math.sin(math.radians(lat))
        assert irradiance(disk).band_irradiance_dn_s_sr[0] == pytest.approx(exact, rel=1e-3)
    # the same disk seen face-on by a plane normal to its direction: L Ω (1 + cos r)/2
    d = np.array([-math.cos(math.radians(35)) * math.sin(math.radians(20)), math.sin(math.radians(35)),
                  math.cos(math.radians(35)) * math.cos(math.radians(20))])
    face = irradiance(_disk_panorama(height, 20.0, 35.0, 2.0, 100.0), normal=d).band_irradiance_dn_s_sr[0]
    omega = cap_solid_angle_sr(math.radians(2.0))
    assert face == pytest.approx(100.0 * omega * (1 + math.cos(math.radians(2.0))) / 2, rel=1e-3)


def _store(path, bands: np.ndarray, tile: int, omnispectral: dict | None = None) -> PanoramaStore:
    h, w, m = bands.shape
    store = PanoramaStore.create(path, h, w, m, tile, {"bands": BANDS[:m]}, fingerprint={"test": 1})
    store.array(0, mode="r+")[:, :, :] = bands
    if omnispectral:
        store.update_attrs({"omnispectral": {**store.attrs()["omnispectral"], **omnispectral}})
    return store


def test_streamed_store_equals_in_memory(tmp_path):
    rng = np.random.default_rng(3)
    bands = rng.uniform(0.0, 1e3, (64, 128, 6)).astype(np.float32)
    bands[5:9, 20:40] = np.nan
    bands[30, 7, 2] = np.nan  # one band missing: the pixel is uncovered, its other bands still count
    store = _store(tmp_path / "p.zarr", bands, tile=16)
    for normal in [(0, 1, 0), (0.2, -0.4, 0.9)]:
        mem = irradiance(bands, normal)
        for streamed in (irradiance(store, normal), irradiance(store, normal, block_rows=5)):
            np.testing.assert_allclose(streamed.band_irradiance_dn_s_sr, mem.band_irradiance_dn_s_sr, rtol=1e-12)
            assert streamed.covered_fraction == pytest.approx(mem.covered_fraction, rel=1e-12)
            assert streamed.covered_solid_angle_fraction == pytest.approx(mem.covered_solid_angle_fraction, rel=1e-12)
        assert mem.covered_solid_angle_fraction < 1.0


@pytest.fixture(scope="module")
def small_estimator():
    est, info = rig_estimator(load_preset("small"))
    return est, info["params"]


def _sun_scene(est, height: int = 180, sun_lon: float = 30.0, sun_lat: float = 40.0):
    """Sky D100 over the upper hemisphere, ground below, a D65 sun painted with exact coverage; and its record."""
    wl = np.asarray(est.wavelength_nm, float)
    matrix = np.asarray(est.system_matrix, float)
    sd = daylight_spd(10000.0)
    sky_bands = matrix @ np.interp(wl, sd.wavelengths, sd.values) * 0.01
    d65 = colour.SDS_ILLUMINANTS["D65"]
    sun_spd = np.interp(wl, d65.wavelengths, d65.values) * 2000.0  # ~10⁵ × the sky: ~70 % of the irradiance
    sun_bands = matrix @ sun_spd
    w = 2 * height
    pano = np.empty((height, w, 6))
    pano[: height // 2] = sky_bands
    pano[height // 2:] = 0.2 * sky_bands
    radius = 0.533 / 2
    rows, cols, frac = equirect_disk_coverage(sun_lon, sun_lat, radius, w, height)
    r0, c0 = rows.min() - 2, cols.min() - 2
    mask = np.zeros((rows.max() - r0 + 3, cols.max() - c0 + 3), int)
    mask[rows - r0, cols - c0] = 1
    pano[rows, cols] += frac[:, None] * sun_bands
    omega = cap_solid_angle_sr(math.radians(radius))
    record = {"method": "nd-bracket", "recovered": True, "lon_deg": sun_lon, "lat_deg": sun_lat,
              "angular_diameter_deg": 2 * radius, "solid_angle_sr": omega, "band_names": BANDS,
              "band_irradiance": (sun_bands * omega).tolist(), "band_radiance": sun_bands.tolist(),
              "band_radiance_std": [0.0] * 6, "wavelength_nm": wl.tolist(), "spectral_radiance": sun_spd.tolist(),
              "spectral_radiance_std": (0.01 * sun_spd).tolist(),
              "pixels": {"row0": int(r0), "col0": int(c0), "rows": mask.shape[0], "cols": mask.shape[1],
                         "mask": mask.tolist(), "n_pixels": int(mask.sum()), "background": sky_bands.tolist()}}
    return pano.astype(np.float32), record, sky_bands


def test_sun_sky_split_adds_up_with_the_suns_cct(tmp_path, small_estimator):
    est, params = small_estimator
    pano, record, sky_bands = _sun_scene(est)
    store = _store(tmp_path / "p.zarr", pano, tile=64, omnispectral={"sun": record, "estimator": {"params": params}})
    out = sun_sky_irradiance(store)  # estimator re-fitted from the store's parameters
    sin_h = math.sin(math.radians(40.0))
    sun = np.array(out["sun"]["band_irradiance"])
    sky = np.array(out["sky"]["band_irradiance"])
    np.testing.assert_allclose(sun, np.array(record["band_irradiance"]) * sin_h, rtol=1e-12)
    np.testing.assert_allclose(sky, math.pi * sky_bands, rtol=1e-5)  # the painted excess comes out exactly
    np.testing.assert_allclose(sun + sky, out["total"]["band_irradiance"], rtol=1e-12)
    # the panorama's own integral holds the painted sun up to its sub-pixel position (1° pixels here)
    np.testing.assert_allclose(out["panorama"]["band_irradiance"], out["total"]["band_irradiance"], rtol=2e-3)
    np.testing.assert_allclose(out["sun"]["painted_band_irradiance"], sun, rtol=1e-2)
    assert out["sun"]["cos_incidence"] == pytest.approx(sin_h)
    assert 0.5 < min(out["sun_fraction"]) < max(out["sun_fraction"]) < 1.0
    assert out["sun"]["cct_K"] == pytest.approx(6504, abs=15)  # D65 (CIE 015:2018)
    assert out["sky"]["cct_K"] == pytest.approx(10000, rel=0.1)  # the Wiener estimate of a D100 sky
    assert out["sun_method"] == "nd-bracket" and out["sun_recovered"] and "note" not in out
    np.testing.assert_allclose(np.array(out["sun"]["spectral_irradiance"]),
                               np.array(record["spectral_radiance"]) * record["solid_angle_sr"] * sin_h, rtol=1e-12)
    # a plane facing down sees no sun: the ground alone
    down = sun_sky_irradiance(store, normal=(0, -1, 0), estimator=est)
    assert down["sun"]["band_irradiance"] == [0.0] * 6 and down["sun"]["cos_incidence"] == 0.0
    np.testing.assert_allclose(down["sky"]["band_irradiance"], math.pi * 0.2 * sky_bands, rtol=1e-5)


def test_without_a_recovered_sun_the_sky_holds_everything_and_says_so(tmp_path, small_estimator):
    est, _ = small_estimator
    pano, _, _ = _sun_scene(est)
    store = _store(tmp_path / "p.zarr", pano, tile=64,
                   omnispectral={"sun": {"method": "none", "recovered": False, "note": "a lower bound"}})
    out = sun_sky_irradiance(store, estimator=est)
    assert not out["sun_recovered"] and out["note"] == "a lower bound" and out["sun"]["cct_K"] is None
    assert out["sun"]["band_irradiance"] == [0.0] * 6
    np.testing.assert_allclose(out["sky"]["band_irradiance"], out["panorama"]["band_irradiance"], rtol=1e-12)


def test_report_section_compares_with_the_truth_and_renders(tmp_path, small_estimator):
    from omnispectral.product.report import _irradiance_html, irradiance_report
    from omnispectral.sim.truth import GroundTruth

    est, _ = small_estimator
    pano, record, _ = _sun_scene(est)
    store = _store(tmp_path / "p.zarr", pano, tile=64, omnispectral={"sun": record})
    gt = tmp_path / "ground_truth"
    gt.mkdir()
    truth = pano.copy()
    truth[..., 1] *= 1.25  # the product reads band A:G 20 % low
    np.save(gt / "bands.npy", truth)
    section = irradiance_report(store, est, BANDS, truth=GroundTruth(gt, {"bands": {"file": "bands.npy",
                                                                                  "names": BANDS}}))
    assert section["sun_method"] == "nd-bracket" and section["sun_cct_K"] == pytest.approx(6504, abs=15)
    np.testing.assert_allclose(section["ratio_to_truth"], [1, 0.8, 1, 1, 1, 1], rtol=1e-6)
    assert section["worst_band"]["name"] == "A:G"
    page = _irradiance_html(section)
    assert page.count("<tr>") == 7 and "A:G" in page and "0.8000" in page and "sun 650" in page
    # a one-camera product against a two-camera truth: the truth's bands of the product's names
    np.save(gt / "bands.npy", truth[..., ::-1])
    store3 = _store(tmp_path / "p3.zarr", np.ascontiguousarray(pano[..., :3]), tile=64,
                    omnispectral={"sun": {"method": "none", "recovered": False, "note": "a lower bound"}})
    section3 = irradiance_report(store3, one_camera_estimator(), BANDS[:3],
                                 truth=GroundTruth(gt, {"bands": {"file": "bands.npy", "names": BANDS[::-1]}}))
    np.testing.assert_allclose(section3["ratio_to_truth"], [1, 0.8, 1], rtol=1e-6)
    assert "a lower bound" in _irradiance_html(section3)


def one_camera_estimator():
    return rig_estimator(one_camera_rig(load_preset("small")))[0]


def test_series_records_and_plots_sun_and_sky_over_the_day(tmp_path, small_estimator):
    from omnispectral.product.series import _append_irradiance, _new_irradiance_series, _plot_irradiance

    est, _ = small_estimator
    series = _new_irradiance_series(BANDS)
    for i, lat in enumerate((10.0, 40.0)):
        pano, record, _ = _sun_scene(est, height=90, sun_lat=lat)
        store = _store(tmp_path / f"p{i}.zarr", pano, tile=64, omnispectral={"sun": record})
        _append_irradiance(series, sun_sky_irradiance(store, estimator=est))
    store = _store(tmp_path / "none.zarr", pano, tile=64, omnispectral={"sun": {"method": "none", "recovered": False}})
    _append_irradiance(series, sun_sky_irradiance(store, estimator=est))
    assert series["sun_recovered"] == [True, True, False] and series["sun_cct_K"][2] is None
    assert np.mean(series["sun"][0]) < np.mean(series["sun"][1])  # the higher sun gives more
    np.testing.assert_allclose(np.add(series["sun"], series["sky"]), series["total"], rtol=1e-12)
    analysis = {"times": ["2024-06-21T08:00:00", "2024-06-21T12:00:00", "2024-06-21T18:30:00"], "irradiance": series}
    json.dumps(analysis, allow_nan=False)  # valid JSON: no NaN
    _plot_irradiance(analysis, tmp_path / "irradiance.png")
    assert (tmp_path / "irradiance.png").stat().st_size > 10_000
