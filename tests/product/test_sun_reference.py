"""The saturated sun from a diffuse reference lit by it (product.sun_reference)."""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_ray
from omnispectral.imaging.sundisk import cap_solid_angle_sr
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.irradiance import irradiance
from omnispectral.product.saturation import saturation_level_dn_s
from omnispectral.product.sun_reference import (
    SunReference,
    effective_reflectance,
    parse_sun_reference,
    recover_sun_reference,
)
from omnispectral.rig import load_preset
from omnispectral.spectral.library import daylight_spd

BANDS = ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]


# ------------------------------------------------------------------------------------------- parser
def test_parse_sun_reference_defaults_keys_and_errors(tmp_path):
    r = parse_sun_reference("-20,-45")
    assert (r.lon_deg, r.lat_deg, r.normal, r.reflectance, r.radius_deg) == (-20.0, -45.0, (0.0, 1.0, 0.0), 0.95, 1.0)
    r = parse_sun_reference("10.5, -30, 1.5, reflectance=0.99, normal=0/90")
    assert r.radius_deg == 1.5 and r.reflectance == 0.99
    np.testing.assert_allclose(r.normal, (0.0, 1.0, 0.0), atol=1e-12)
    r = parse_sun_reference("35,-10,normal=215/0,radius=2")  # a vertical target facing longitude 215 (= -145)
    np.testing.assert_allclose(r.normal, lonlat_to_ray(-145.0, 0.0), atol=1e-12)
    assert r.radius_deg == 2.0
    np.testing.assert_allclose(parse_sun_reference("0,-40,normal=0/3/4").normal, (0.0, 0.6, 0.8))
    csv = tmp_path / "grey.csv"
    csv.write_text("wavelength_nm,grey\n380,0.5\n550,0.52\n780,0.55\n")
    r = parse_sun_reference(f"0,-40,reflectance={csv}")
    wl = np.arange(400.0, 701.0, 5.0)
    assert r.reflectance_on(wl)[0] == pytest.approx(0.5 + 0.02 * 20 / 170) and not r.flat
    r = parse_sun_reference("0,-40,reflectance=colorchecker:white 9.5 (.05 D)")
    assert 0.8 < r.reflectance_on(wl).mean() < 0.95
    assert SunReference.from_dict(r.to_dict()) == r
    for bad in ("10", "a,b", "1,2,3,4", "1,95", "1,2,-1", "1,2,normal=0/95", "1,2,normal=0/0/0", "1,2,colour=3",
                "1,2,reflectance=1.5", "1,2,reflectance=nope", "1,2,radius=1,radius=2", "1,2,reflectance=0.9,5",
                f"1,2,reflectance={tmp_path / 'missing.csv'}"):
        with pytest.raises(ConfigurationError if "missing" not in bad else Exception):
            parse_sun_reference(bad)


# ------------------------------------------------------------------------------------ synthetic store
SUN_LON, SUN_LAT = -29.5, 39.5  # a pixel centre of the 1° grid
TARGET_LON, TARGET_LAT = 100.5, -45.5


def _sky_spectrum(wl):
    sd = daylight_spd(10000.0)
    return np.interp(wl, sd.wavelengths, sd.values)


def _sun_spectrum(wl):
    sd = daylight_spd(5500.0)
    return np.interp(wl, sd.wavelengths, sd.values)


def _synthetic(tmp_path, reflectance, shadowed=False, height=180):
    """A panorama (1° pixels) with a smooth D100 sky, a clipped sun blurred over its neighbours, and a diffuse
    horizontal target whose radiance is exact: ρ/π (E_⊥ sin h + E_rest) per band (spectrally integrated)."""
    rig = load_preset("small")
    system = rig.system()
    matrix = np.asarray(system.matrix, np.float64)
    wl = np.asarray(system.wavelength_nm, np.float64)
    w = 2 * height
    cols, rows = np.meshgrid(np.arange(w), np.arange(height))
    lon, lat = equirect_pixel_to_lonlat(cols, rows, w, height)
    sky_spd = _sky_spectrum(wl)
    sky_spd *= 1e5 / (matrix @ sky_spd)[1]  # band A:G of the zenith sky: 1e5 DN/s
    shape = np.where(lat > 0, 1.0 + 0.6 * np.cos(np.radians(lat)) + 0.3 * np.cos(np.radians(lon - SUN_LON)), 0.25)
    sky_bands = matrix @ sky_spd
    pano = shape[..., None] * sky_bands[None, None, :]
    # the sun: E_⊥ four times the sky's horizontal irradiance, held in the panorama as a clipped lower bound
    sun_spd = _sun_spectrum(wl)
    e_rest_spectral = irradiance(shape[..., None]).band_irradiance_dn_s_sr[0] * sky_spd  # spectral E_rest
    sun_spd *= 4.0 * (matrix @ e_rest_spectral)[1] / (matrix @ sun_spd)[1]
    e_sun_true = matrix @ sun_spd
    level = saturation_level_dn_s({"omnispectral": {"rig": {"toml": rig.toml_text}}})
    r0 = round(90 - SUN_LAT - 0.5)
    c0 = round(SUN_LON + 180 - 0.5)
    pano[r0 - 1:r0 + 2, c0 - 1:c0 + 2] = 0.97 * level  # clipped: the disk blurred over its 8 neighbours
    pano[r0, c0] = level
    for dr in range(-3, 4):  # the blur's unclipped tail
        for dc in range(-3, 4):
            if max(abs(dr), abs(dc)) >= 2:
                pano[r0 + dr, c0 + dc] += 0.02 * level / (abs(dr) + abs(dc))
    # the target: ρ/π (E_sun cos θ + E_rest) integrated over each band, on a 3° disk
    ref = SunReference(TARGET_LON, TARGET_LAT, reflectance=reflectance, radius_deg=2.0)
    rho = ref.reflectance_on(wl)
    cos_t = math.sin(math.radians(SUN_LAT))
    light = (0.0 if shadowed else cos_t) * sun_spd + e_rest_spectral
    target = matrix @ (rho * light) / math.pi
    ang = np.degrees(np.arccos(np.clip(lonlat_to_ray(lon, lat) @ lonlat_to_ray(TARGET_LON, TARGET_LAT), -1, 1)))
    rng = np.random.default_rng(1)
    on = ang <= 3.0
    pano[on] = target * (1.0 + 0.003 * rng.standard_normal((int(on.sum()), 6)))
    store = PanoramaStore.create(tmp_path / "p.zarr", height, w, 6, 64,
                                 {"bands": BANDS, "rig": {"name": rig.name, "toml": rig.toml_text}},
                                 fingerprint={"test": 1})
    store.array(0, mode="r+")[:, :, :] = pano.astype(np.float32)
    return store, system, ref, e_sun_true, sun_spd


@pytest.mark.parametrize("reflectance", [0.95, "ramp"])
def test_recovers_the_suns_band_irradiance_from_a_white_target(tmp_path, reflectance):
    if reflectance == "ramp":  # a coloured (non-flat) target: effective band reflectances under each light
        wl = np.arange(380.0, 781.0, 5.0)
        reflectance = (tuple(wl), tuple(0.3 + 0.5 * (wl - 380.0) / 400.0))
    store, system, ref, e_sun_true, sun_spd = _synthetic(tmp_path, reflectance)
    rec = recover_sun_reference(store, system, BANDS, ref)
    assert rec["recovered"] and rec["method"] == "diffuse-reference", rec.get("note")
    assert rec["lon_deg"] == pytest.approx(SUN_LON, abs=0.01) and rec["lat_deg"] == pytest.approx(SUN_LAT, abs=0.01)
    np.testing.assert_allclose(rec["band_irradiance"], e_sun_true, rtol=0.01)
    omega = cap_solid_angle_sr(math.radians(rec["angular_diameter_deg"] / 2))
    np.testing.assert_allclose(rec["band_radiance"], e_sun_true / omega, rtol=0.01)
    spd = np.array(rec["spectral_radiance"]) * omega
    assert np.linalg.norm(spd - sun_spd) / np.linalg.norm(sun_spd) < 0.02
    std = np.array(rec["band_irradiance_std"])
    assert np.all(std > 0) and np.all(std < 0.05 * e_sun_true)
    assert len(rec["spectral_radiance_std"]) == len(rec["wavelength_nm"]) and min(rec["band_radiance_std"]) > 0
    assert rec["rest"]["n_clipped_px"] == 9 and rec["rest"]["n_replaced_px"] >= 49
    assert rec["sun_term_snr"] > 10 and rec["warnings"] == []
    json.dumps(rec)  # a JSON-able record, as sun.json


def test_refuses_a_shadowed_target_or_a_sun_behind_it(tmp_path):
    store, system, ref, _, _ = _synthetic(tmp_path, 0.95, shadowed=True)
    rec = recover_sun_reference(store, system, BANDS, ref)
    assert not rec["recovered"] and "shadow" in rec["note"] and abs(rec["sun_term_snr"]) < 2
    facing_down = SunReference(TARGET_LON, TARGET_LAT, normal=(0.0, -1.0, 0.0), radius_deg=2.0)
    rec = recover_sun_reference(store, system, BANDS, facing_down)
    assert not rec["recovered"] and "behind" in rec["note"] and rec["cos_incidence"] < 0
    s = lonlat_to_ray(SUN_LON, SUN_LAT)
    u = np.cross(s, [0.0, 1.0, 0.0])
    u = np.cross(u, s) / np.linalg.norm(np.cross(u, s))  # ⟂ s, upwards
    grazing = SunReference(TARGET_LON, TARGET_LAT, normal=tuple(0.05 * s + math.sqrt(1 - 0.05**2) * u), radius_deg=2.0)
    rec = recover_sun_reference(store, system, BANDS, grazing)
    assert not rec["recovered"] and "grazing" in rec["note"] and rec["cos_incidence"] == pytest.approx(0.05, abs=1e-3)


def test_effective_reflectance_is_the_band_weighted_mean_under_the_light():
    matrix = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]])
    rho = np.array([0.2, 0.4, 0.6])
    np.testing.assert_allclose(effective_reflectance(matrix, rho, np.ones(3)), [0.3, 0.5])
    np.testing.assert_allclose(effective_reflectance(matrix, rho, np.array([3.0, 1.0, 0.0])), [0.25, 0.4])


# ------------------------------------------------------------------------------------------ end to end
@pytest.mark.slow
def test_simulated_session_sun_from_the_scenes_white_plate(tmp_path):
    from omnispectral.product.process import process
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.simulate import simulate_session

    scene = ProceduralOutdoorScene(time_hhmm="12:00")
    rig = load_preset("small")
    simulate_session(tmp_path / "s", rig, scene, start=dt.datetime(2017, 3, 21, 3, 0, tzinfo=dt.UTC), progress=False)
    process(tmp_path / "s", tmp_path / "p", progress=False, sun="none", report=False)
    gt = json.loads((tmp_path / "s" / "ground_truth" / "ground_truth.json").read_text())
    plate = gt["scene"]["reference"]  # what the user wrote down about their target; processing never reads it
    reference = SunReference(plate["lon_deg"], plate["lat_deg"], tuple(plate["normal"]), plate["reflectance"],
                             radius_deg=0.6 * plate["half_size_deg"])
    store = PanoramaStore.open(tmp_path / "p" / "panorama.zarr")
    system = rig.system()
    rec = recover_sun_reference(store, system, list(store.attrs()["omnispectral"]["bands"]), reference)
    assert rec["recovered"], rec.get("note")
    sun = scene.sun_disk()
    omega = cap_solid_angle_sr(sun.radius_rad)
    truth = sun.band_radiance(system.matrix) * gt["dn_per_second_per_unit"] * omega * sun.direction[1]
    ray = lonlat_to_ray(rec["lon_deg"], rec["lat_deg"])
    horizontal = np.asarray(rec["band_irradiance"]) * ray[1]
    np.testing.assert_allclose(horizontal, truth, rtol=0.05)
    # the clipped group's centroid: within the half panorama pixel the method states as its uncertainty
    half_pixel_deg = 0.5 * 360.0 / store.shapes[0][1]
    assert math.degrees(math.acos(min(1.0, float(ray @ sun.direction)))) < half_pixel_deg
