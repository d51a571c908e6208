"""The sun estimated from the clear sky around it (``sky-model``): published model values, a synthetic panorama,
refusals, and end to end on a simulated session against the simulator's truth."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest

from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_ray
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.saturation import saturation_level_dn_s
from omnispectral.product.sun_sky_model import (
    clear_sky_state,
    hemisphere_integrals,
    ineichen_perez,
    perez_clearness,
    perez_coefficients,
    perez_efficacies,
    perez_relative_luminance,
    recover_sun_sky_model,
    relative_air_mass,
)
from omnispectral.rig import load_preset, rig_toml
from omnispectral.spectral.library import daylight_spd

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]


# ------------------------------------------------------------------------------ published values
#: pvlib 0.16.1 ``pvlib.clearsky.ineichen(zenith, kasten1966 air mass, linke_turbidity=3, altitude=0,
#: dni_extra=1364)``: (zenith°, ghi, dni, dhi) in W/m².
PVLIB_INEICHEN_TL3 = [(30.0, 896.8049165979705, 916.5135230761449, 103.08092270205361),
                      (60.0, 469.7056176278109, 788.0240992802593, 75.69356798768115),
                      (75.0, 196.93283941414356, 568.3640134238755, 49.829408189139826)]


@pytest.mark.parametrize(("zenith", "ghi", "dni", "dhi"), PVLIB_INEICHEN_TL3)
def test_ineichen_perez_matches_pvlib(zenith, ghi, dni, dhi):
    out = ineichen_perez(zenith, 3.0, dni_extra=1364.0)
    assert float(out["ghi"]) == pytest.approx(ghi, rel=1e-9)
    assert float(out["dni"]) == pytest.approx(dni, rel=1e-9)
    assert float(out["dhi"]) == pytest.approx(dhi, rel=1e-9)


def test_ineichen_perez_against_live_pvlib_when_installed():
    clearsky = pytest.importorskip("pvlib.clearsky")
    atmosphere = pytest.importorskip("pvlib.atmosphere")
    z = np.array([10.0, 45.0, 70.0, 85.0])
    for tl in (2.0, 4.5, 7.0):
        am = atmosphere.get_relative_airmass(z, "kasten1966")
        ref = clearsky.ineichen(z, am, np.full(z.shape, tl), altitude=0, dni_extra=1361.0)
        out = ineichen_perez(z, tl)
        for key in ("ghi", "dni", "dhi"):
            np.testing.assert_allclose(out[key], np.asarray(ref[key]), rtol=1e-9)


def test_kasten_air_mass_and_perez_definitions():
    assert float(relative_air_mass(0.0)) == pytest.approx(1.0, abs=1e-3)  # Kasten 1966 at the zenith: 0.9995
    assert float(relative_air_mass(60.0)) == pytest.approx(1.9928, abs=1e-3)  # ≈ sec Z
    # ε = 1 for a sky without direct light; Perez's bin-8 coefficients at Z = 0, Δ = 0 are the table's x1
    assert float(perez_clearness(100.0, 0.0, 0.5)) == pytest.approx(1.0)
    assert perez_coefficients(10.0, 0.0, 0.0) == pytest.approx((-1.05, -0.325, 31.0625, -7.2312, 1.5))
    # bin 1 (overcast): c = exp((Δ (c1 + c2 Z))^c3) − c4, d = −exp(Δ (d1 + d2 Z)) + d3 + Δ d4
    c = perez_coefficients(1.0, 0.3, 0.5)
    assert c[2] == pytest.approx(math.exp((0.3 * (2.8 + 0.6004 * 0.5)) ** 1.2375) - 1.0)
    assert c[3] == pytest.approx(-math.exp(0.3 * (1.8734 + 0.6297 * 0.5)) + 0.9738 + 0.3 * 0.2809)


def test_clear_sky_efficacies_and_ratio_are_in_the_published_range():
    """Perez et al. 1990: clear-sky direct normal efficacy ≈ 100 lm/W, diffuse ≈ 120-150 lm/W (blue skylight);
    the Ineichen-Perez clear sky at T_L = 3 and 53° has I/D ≈ 9 and a clear Perez clearness (ε > 6.2)."""
    state = clear_sky_state(53.0, 3.0)
    assert state["epsilon"] > 6.2 and 0.05 < state["delta"] < 0.2
    assert 95.0 < state["efficacy_direct_lm_w"] < 110.0 and 120.0 < state["efficacy_diffuse_lm_w"] < 160.0
    assert 8.0 < state["irradiance_ratio"] < 10.0
    assert state["luminous_ratio"] == pytest.approx(state["irradiance_ratio"] * state["efficacy_direct_lm_w"]
                                                    / state["efficacy_diffuse_lm_w"])
    k_dn, k_d = perez_efficacies(1.0, 0.3, 0.8)  # overcast: diffuse efficacy ≈ 110-125
    assert 100.0 < k_d < 130.0 and k_dn >= 0.0
    # a more turbid sky: less direct light per diffuse
    assert clear_sky_state(53.0, 5.0)["irradiance_ratio"] < state["irradiance_ratio"] / 1.5


def test_hemisphere_integral_of_a_uniform_sky_is_pi():
    horizontal, cone = hemisphere_integrals((0.0, 0.0, 0.0, 0.0, 0.0), math.radians(40.0))
    assert horizontal == pytest.approx(math.pi, rel=1e-4)
    assert cone == pytest.approx(2 * math.pi * (1 - math.cos(math.radians(2.5))), rel=1e-3)


# ------------------------------------------------------------------------------ synthetic panorama
def _sky_store(path, sun_lon, sun_lat, relative_luminance, height=180, clip=True):
    """A 1°-per-pixel panorama: the sky ``relative_luminance(cos ζ, γ)`` in a daylight colour, a dark building
    low in the sky, grey ground, and a clipped sun disk; with the small rig's snapshot (its clipping level)."""
    rig = load_preset("small")
    system = rig.system()
    wl = np.asarray(system.wavelength_nm, float)
    sd = daylight_spd(12000.0)
    sky_colour = np.asarray(system.matrix, float) @ np.interp(wl, sd.wavelengths, sd.values)
    sky_colour = sky_colour / sky_colour.max() * 2000.0  # DN/s at unit relative luminance
    w = 2 * height
    rows, cols = np.mgrid[0:height, 0:w]
    lon, lat = equirect_pixel_to_lonlat(cols, rows, w, height)
    rays = lonlat_to_ray(lon, lat)
    gamma = np.arccos(np.clip(rays @ lonlat_to_ray(sun_lon, sun_lat), -1, 1))
    f = relative_luminance(np.sin(np.radians(lat)), gamma)
    bands = f[..., None] * sky_colour
    bands[lat < 0] = 0.3 * sky_colour.mean()
    building = (lat >= 0) & (lat < 15) & (lon > -60) & (lon < -20)
    bands[building] = 0.05 * sky_colour.mean()
    store = PanoramaStore.create(path, height, w, 6, 64, {"bands": BANDS}, fingerprint={"test": 1})
    attrs = store.attrs()["omnispectral"]
    store.update_attrs({"omnispectral": {**attrs, "rig": {"toml": rig_toml(rig)}}})
    if clip:
        level = saturation_level_dn_s(store.attrs())
        bands[np.degrees(gamma) <= 1.0] = level
    store.array(0, mode="r+")[:, :, :] = bands.astype(np.float32)
    return store, system, sky_colour


def test_a_perez_sky_gives_back_its_turbidity_and_its_sun(tmp_path):
    """A sky drawn from the model itself (T_L = 3, sun at 40°): the fit finds the turbidity, the diffuse
    band irradiance and the luminous direct-to-diffuse ratio of the models."""
    sun_lon, sun_lat, tl = 70.0, 40.0, 3.0
    state = clear_sky_state(sun_lat, tl)
    store, system, colour_b = _sky_store(tmp_path / "p.zarr", sun_lon, sun_lat,
                                         lambda cz, g: perez_relative_luminance(cz, g, state["coefficients"]))
    rec = recover_sun_sky_model(store, system, BANDS)
    assert rec["recovered"] and rec["model_estimate"] and rec["method"] == "sky-model"
    assert "model estimate" in rec["note"]
    assert rec["fit"]["linke_turbidity"] == pytest.approx(tl, abs=0.1)
    assert rec["fit"]["rms_log_residual"] < 0.01
    rejected = rec["fit"]["n_sky_samples"] * (1.0 / rec["fit"]["sky_fraction_used"] - 1.0)
    assert rejected >= 270  # the building (7 × 40 samples above 8°) was rejected as not sky
    horizontal, _ = hemisphere_integrals(state["coefficients"], state["zenith_rad"])
    np.testing.assert_allclose(rec["sky_diffuse_horizontal_band_irradiance"], colour_b * horizontal, rtol=0.01)
    assert abs(rec["lon_deg"] - sun_lon) < 0.2 and abs(rec["lat_deg"] - sun_lat) < 0.2
    # the sun's luminous part over the sky's is the models' luminous ratio (less the aureole, < 1 %)
    from omnispectral.spectral.colour import cmfs_xyz

    wl = np.asarray(rec["wavelength_nm"])
    ybar = cmfs_xyz(wl)[:, 1]
    y_sun = np.asarray(rec["spectral_radiance"]) @ ybar * rec["solid_angle_sr"]
    sky_y = np.linalg.lstsq(np.asarray(system.matrix, float), np.asarray(rec["sky_diffuse_horizontal_band_irradiance"]),
                            rcond=None)[0]
    assert y_sun / (sky_y @ ybar) == pytest.approx(state["luminous_ratio"], rel=0.05)
    # the record has the nd-bracket record's fields, with honest spreads
    for key in ("band_irradiance", "band_radiance", "band_radiance_std", "spectral_radiance", "spectral_radiance_std"):
        assert len(rec[key]) == (6 if key.startswith("band") else wl.size)
    assert rec["relative_std"] >= 0.5
    assert np.all(np.asarray(rec["band_radiance_std"]) >= 0.5 * np.asarray(rec["band_radiance"]))
    json.dumps(rec)  # JSON-able as sun.json


def test_refusals(tmp_path):
    store, system, _ = _sky_store(tmp_path / "a.zarr", 0.0, 40.0, lambda cz, g: 1.0 + 0 * cz, clip=False)
    rec = recover_sun_sky_model(store, system, BANDS)
    assert not rec["recovered"] and "no clipped sun" in rec["note"]
    store, system, _ = _sky_store(tmp_path / "b.zarr", 0.0, 3.0, lambda cz, g: 1.0 + 0 * cz)
    rec = recover_sun_sky_model(store, system, BANDS)
    assert not rec["recovered"] and "below" in rec["note"]
    # an overcast sky (CIE overcast gradation, no circumsolar brightening) is no clear sky
    store, system, _ = _sky_store(tmp_path / "c.zarr", 0.0, 40.0, lambda cz, g: (1.0 + 2.0 * cz) / 3.0)
    rec = recover_sun_sky_model(store, system, BANDS)
    assert not rec["recovered"] and "clear" in rec["note"] and rec["model_estimate"]
    # a patchy (cloudy) sky leaves a large residual
    rng = np.random.default_rng(1)
    state = clear_sky_state(40.0, 3.0)
    store, system, _ = _sky_store(tmp_path / "d.zarr", 0.0, 40.0, lambda cz, g: perez_relative_luminance(
        cz, g, state["coefficients"]) * np.exp(rng.normal(0.0, 0.6, np.shape(cz))))
    rec = recover_sun_sky_model(store, system, BANDS)
    assert not rec["recovered"] and "not the clear sky" in rec["note"]


# ------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_simulated_session_sun_from_the_sky_model(tmp_path):
    """Small preset at 12:30 (day 80, seed 0), processed without the sun bracket: the sky model puts the sun in
    the right place, within the factor it claims of the truth's irradiance, and its record paints and splits.

    Measured (this module's docstring): horizontal irradiance 0.33-0.56 of the truth per band (blue worst),
    spectrum NRMSE 0.033, direction 0.03°; the bounds below leave a margin around those."""
    from omnispectral.product.irradiance import cosine_weights, sun_sky_irradiance
    from omnispectral.product.layout import open_product
    from omnispectral.product.process import process
    from omnispectral.product.sun import paint_sun
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.scenes.sky import unit_luminance_daylight
    from omnispectral.sim.simulate import simulate_session
    from omnispectral.spectral.metrics import nrmse

    simulate_session(tmp_path / "s", load_preset("small"), ProceduralOutdoorScene(time_hhmm="12:30"),
                     start=dt.datetime(2017, 3, 21, 12, 30, tzinfo=dt.UTC), progress=False, seed=0)
    process(tmp_path / "s", tmp_path / "p", progress=False, sun="none")
    _, store, estimator = open_product(tmp_path / "p")
    rig = load_preset("small")
    rec = recover_sun_sky_model(store, rig.system(), list(store.attrs()["omnispectral"]["bands"]))
    assert rec["recovered"] and rec["model_estimate"]

    gt_dir = tmp_path / "s" / "ground_truth"
    gt = json.loads((gt_dir / "ground_truth.json").read_text())
    truth_ray = np.asarray(gt["sun_disk"]["direction"])
    ray = lonlat_to_ray(rec["lon_deg"], rec["lat_deg"])
    assert math.degrees(math.acos(min(1.0, float(ray @ truth_ray)))) < 0.2
    # the truth's sun: its disk in the ground-truth panorama, above the sky around it, on a horizontal plane
    truth = np.load(gt_dir / "bands.npy", mmap_mode="r")
    h, w, _ = truth.shape
    lat0 = math.degrees(math.asin(truth_ray[1]))
    lon0 = math.degrees(math.atan2(-truth_ray[0], truth_ray[2]))
    rows = np.arange(int((90 - lat0) / 180 * h) - 12, int((90 - lat0) / 180 * h) + 13)
    block = np.asarray(truth[rows[0]:rows[-1] + 1], float)
    cc, rr = np.meshgrid(np.arange(w), rows)
    ang = np.degrees(np.arccos(np.clip(lonlat_to_ray(*equirect_pixel_to_lonlat(cc, rr, w, h))
                                       @ lonlat_to_ray(lon0, lat0), -1, 1)))
    r_deg, px = math.degrees(gt["sun_disk"]["radius_rad"]), 360.0 / w
    bg = np.median(block[(ang > r_deg + 3 * px) & (ang <= r_deg + 6 * px)], axis=0)
    truth_sun = ((block - bg) * cosine_weights(rows, h, w, (0, 1, 0))[..., None])[ang <= r_deg + 2 * px].sum(axis=0)
    ratio = np.asarray(rec["band_irradiance"]) * ray[1] / truth_sun
    assert np.all(ratio > 0.25) and np.all(ratio < 0.75), ratio
    # within the record's own spread in the least-wrong band; the claimed relative spread is ≥ 0.5
    assert rec["relative_std"] >= 0.5
    wl = np.asarray(rec["wavelength_nm"])
    day = gt["scene"]["daylight"]
    assert float(nrmse(np.asarray(rec["spectral_radiance"]), unit_luminance_daylight(day["cct_sun_K"], wl))) < 0.06
    # the diffuse sky the model integrates is the truth's within 8 %
    sky_truth = np.load(gt_dir / "system_matrix.npy") @ unit_luminance_daylight(day["cct_sky_K"], wl) \
        * day["diffuse_horizontal_illuminance_lx"] * gt["dn_per_second_per_unit"]
    np.testing.assert_allclose(rec["sky_diffuse_horizontal_band_irradiance"], sky_truth, rtol=0.08)
    # the record paints and splits like the nd-bracket one
    rec["pixels"] = paint_sun(store, rec)
    store.update_attrs({"omnispectral": {**store.attrs()["omnispectral"], "sun": rec}})
    split = sun_sky_irradiance(store, estimator=estimator)
    assert split["sun_recovered"] and split["sun_method"] == "sky-model"
    np.testing.assert_allclose(split["sun"]["painted_band_irradiance"], split["sun"]["band_irradiance"], rtol=0.03)
