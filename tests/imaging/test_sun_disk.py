"""The sun as an exact disk: cap geometry, pixel coverage, the sun's energy in truth and frames, the ND filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnispectral.imaging.geometry import CameraModel, lonlat_to_ray, ray_to_lonlat
from omnispectral.imaging.sundisk import (
    cap_solid_angle_sr,
    disk_samples,
    equirect_disk_coverage,
    equirect_pixel_solid_angle_sr,
    n_radial_for_pixel,
    pixel_solid_angles_sr,
    splat_camera,
    splat_equirect,
)
from omnispectral.rig import load_preset
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.scenes.base import SunDisk
from omnispectral.sim.simulate import FILTER_VEIL_FRACTION, RigRenderer
from omnispectral.sim.truth import add_sun_disk_equirect, render_equirect_bands
from omnispectral.spectral.library import filter_names, load_filter

SUN_RADIUS_DEG = 0.533 / 2


@pytest.mark.parametrize("lon_deg, lat_deg, radius_deg", [
    (10.3, 40.2, SUN_RADIUS_DEG), (179.9, 20.0, SUN_RADIUS_DEG), (-180.0, -5.0, SUN_RADIUS_DEG),
    (33.0, 89.5, SUN_RADIUS_DEG), (33.0, 89.9, SUN_RADIUS_DEG), (-60.0, -89.95, SUN_RADIUS_DEG),
    (170.0, 80.0, 20.0), (0.0, 0.0, 5.0)])
def test_equirect_coverage_sums_to_the_cap(lon_deg, lat_deg, radius_deg):
    omega = cap_solid_angle_sr(math.radians(radius_deg))
    for width in (333, 512, 1024, 2048):
        rows, cols, frac = equirect_disk_coverage(lon_deg, lat_deg, radius_deg, width, width // 2)
        assert np.all((frac > 0) & (frac <= 1.0))
        assert len(set(zip(rows.tolist(), cols.tolist(), strict=True))) == rows.size
        total = float(np.sum(frac * equirect_pixel_solid_angle_sr(rows, width, width // 2)))
        assert abs(total / omega - 1.0) < 1e-6, (width, total / omega - 1.0)


def test_cap_solid_angle():
    assert cap_solid_angle_sr(math.pi) == pytest.approx(4 * math.pi, rel=1e-15)
    assert cap_solid_angle_sr(0.5 * math.pi) == pytest.approx(2 * math.pi, rel=1e-15)
    r = math.radians(SUN_RADIUS_DEG)
    assert cap_solid_angle_sr(r) == pytest.approx(2 * math.pi * (1 - math.cos(r)), rel=1e-9)


def test_disk_samples_weights_and_directions():
    centre = lonlat_to_ray(-37.0, 51.0)
    r = math.radians(SUN_RADIUS_DEG)
    dirs, w = disk_samples(centre, r)
    assert dirs.shape == (w.size, 3) and w.size >= 20_000
    assert abs(w.sum() / cap_solid_angle_sr(r) - 1.0) < 1e-12
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-14)
    assert np.all(dirs @ centre >= math.cos(r) - 1e-15)
    mean = np.average(dirs, axis=0, weights=w)
    np.testing.assert_allclose(mean / np.linalg.norm(mean), centre, atol=1e-9)
    again, _ = disk_samples(centre, r)
    assert np.array_equal(dirs, again)


@pytest.mark.parametrize("lon_deg, lat_deg", [(10.3, 40.2), (-180.0, -5.0), (45.0, 12.345)])
def test_splatted_samples_match_the_exact_coverage(lon_deg, lat_deg):
    """Each pixel's splatted value is within 0.5 % of the disk's radiance of its exact coverage."""
    r = math.radians(SUN_RADIUS_DEG)
    for width in (512, 2048, 7260):
        height = width // 2
        rows, cols, frac = equirect_disk_coverage(lon_deg, lat_deg, SUN_RADIUS_DEG, width, height)
        pixel = min(math.pi / height, 2 * math.pi / width * math.cos(math.radians(abs(lat_deg)) + r))
        dirs, w = disk_samples(lonlat_to_ray(lon_deg, lat_deg), r, n_radial_for_pixel(r, pixel))
        sr, sc, sf = splat_equirect(dirs, w, width, height)
        exact = dict(zip(zip(rows.tolist(), cols.tolist(), strict=True), frac, strict=True))
        splat = dict(zip(zip(sr.tolist(), sc.tolist(), strict=True), sf, strict=True))
        err = max(abs(exact.get(k, 0.0) - splat.get(k, 0.0)) for k in exact.keys() | splat.keys())
        assert err < 0.005, (width, err)


def test_partly_hidden_disk_adds_only_its_visible_part():
    r = math.radians(SUN_RADIUS_DEG)
    centre = lonlat_to_ray(20.0, 30.0)
    half = SunDisk(centre, r, np.ones(3), lambda d, o: np.asarray(d)[:, 1] > centre[1])  # lower half hidden
    arr = np.zeros((256, 512, 1), np.float32)
    add_sun_disk_equirect(arr, half, np.array([2.0]))
    rows, cols = np.nonzero(arr[..., 0])
    total = float(np.sum(arr[rows, cols, 0] * equirect_pixel_solid_angle_sr(rows, 512, 256)))
    assert total == pytest.approx(2.0 * cap_solid_angle_sr(r) / 2, rel=2e-3)


def test_pixel_solid_angles_of_a_pinhole_sum_to_its_field_of_view():
    m = CameraModel.from_fov(64, 48, 60.0)
    omega = pixel_solid_angles_sr(m)
    a = math.atan((m.width / 2) / m.fx)
    b = math.atan((m.height / 2) / m.fy)
    assert float(omega.sum()) == pytest.approx(4 * math.asin(math.sin(a) * math.sin(b)), rel=1e-6)
    centre = pixel_solid_angles_sr(m, np.array([31]), np.array([23]))
    assert float(centre[0]) == pytest.approx(1 / (m.fx * m.fy), rel=1e-3)


@pytest.mark.parametrize("time_hhmm", ["07:00", "12:50", "17:00"])
def test_truth_horizontal_irradiance_matches_the_daylight_model_on_any_grid(time_hhmm):
    """Nothing above the horizon: the truth's horizontal irradiance is E_dn sin h + E_kh (in one band) on every grid.

    The sun's irradiance normal to it is exact on any grid; projected on the horizontal it carries the
    grid's own position error (the disk's light sits at its pixel's latitude: up to ±cot h · ½ row, 0.7 %
    at 512 px and h = 15°), the sky the error of 2 × 2 rays per pixel.  Before the disk was added exactly,
    point-sampling it moved this total by 4-30 % between grids."""
    scene = ProceduralOutdoorScene(time_hhmm, seed=13, buildings=False, skyline=False, near_object=False)
    dl = scene.daylight
    band = np.full((1, scene.wavelength_nm.size), 5.0)
    normal = dl.direct_normal_lx * float((band @ dl.sun_spectrum)[0])
    model = normal * math.sin(math.radians(dl.sun.elevation_deg)) \
        + dl.diffuse_horizontal_lx * float((band @ dl.sky_spectrum)[0])
    sun = scene.sun_disk()
    rel = []
    for width in (512, 1024, 2048):
        height = width // 2
        upper = render_equirect_bands(scene, band, width, 0, height // 2)[..., 0].astype(np.float64)
        rows = np.arange(height // 2)
        top, bottom = np.radians(90 - rows * 180 / height), np.radians(90 - (rows + 1) * 180 / height)
        sin_weight = (2 * math.pi / width) * 0.5 * (np.sin(top) ** 2 - np.sin(bottom) ** 2)  # ∫ sin φ dΩ per pixel
        rel.append(float(upper.sum(axis=1) @ sin_weight) / model - 1.0)
        sun_only = np.zeros((height // 2, width, 1), np.float32)
        add_sun_disk_equirect(sun_only, sun, sun.band_radiance(band), height=height)
        r, c = np.nonzero(sun_only[..., 0])
        sun_normal = float(sun_only[r, c, 0].astype(np.float64) @ equirect_pixel_solid_angle_sr(r, width, height))
        assert sun_normal == pytest.approx(normal, rel=1e-6), width
    rel = np.array(rel)
    assert np.all(np.abs(rel) < np.array([1.5e-2, 3e-3, 1e-3])), rel


class _NoSun(ProceduralOutdoorScene):
    """The same scene without the sun's disk (the background of a sun frame)."""

    def sun_disk(self):
        return None

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0), sun_disk=True):
        return super().band_radiance(directions, sensitivity, origin_m, sun_disk=False)


@pytest.fixture(scope="module")
def sun_renderer():
    return RigRenderer(load_preset("small"), ProceduralOutdoorScene("12:50", seed=13), noise=False)


def _sun_frames(renderer, camera, pan, tilt, filter_name, exposure_s=None):
    scene = renderer.scene
    with_sun = renderer.electrons_per_second(camera, pan, tilt, filter_name).astype(np.float64)
    frames = None
    if exposure_s is not None:
        frames = [renderer(camera, pan, tilt, exposure_s, None, filter_name=filter_name).astype(np.float64)]
    renderer.set_scene(_NoSun("12:50", seed=13))
    try:
        without = renderer.electrons_per_second(camera, pan, tilt, filter_name).astype(np.float64)
        if exposure_s is not None:
            frames.append(renderer(camera, pan, tilt, exposure_s, None, filter_name=filter_name).astype(np.float64))
    finally:
        renderer.set_scene(scene)
    return with_sun - without, frames


@pytest.mark.parametrize("camera, filter_name, offset_deg", [("A", None, 0.0), ("A", "wratten-96-nd3", 0.0),
                                                             ("B", "wratten-96-nd3", 0.37), ("A", "wratten-96", 15.0)])
def test_frames_hold_the_disk_irradiance(sun_renderer, camera, filter_name, offset_deg):
    r = sun_renderer
    sun = r.scene.sun_disk()
    lon, lat = ray_to_lonlat(sun.direction)
    pan, tilt = float(lon) + offset_deg, float(lat) + offset_deg / 3
    diff, _ = _sun_frames(r, camera, pan, tilt, filter_name)
    got = (diff * pixel_solid_angles_sr(r.models[camera])[..., None]).sum(axis=(0, 1))
    expected = r.electrons_per_unit * cap_solid_angle_sr(sun.radius_rad) * sun.band_radiance(
        r.band_matrix(camera, filter_name))
    np.testing.assert_allclose(got, expected, rtol=1e-4)
    if filter_name is not None:  # the veil: part of the light around the sun's pixels
        peak = np.unravel_index(np.argmax(diff[..., 1]), diff.shape[:2])
        far = diff[peak[0], min(peak[1] + 8, diff.shape[1] - 1), 1]
        assert 0 < far < 0.01 * diff[peak][1]


def test_nd_raw_frame_holds_the_disk_irradiance(sun_renderer):
    """A noise-free ND 3.0 frame of the sun: Σ (DN/s − background) · Ω_pixel = T-weighted disk irradiance (1 %)."""
    r = sun_renderer
    sun = r.scene.sun_disk()
    lon, lat = ray_to_lonlat(sun.direction)
    cam = r.rig.cameras["A"]
    gain = cam.noise_model().gain_e_per_dn
    diff, _ = _sun_frames(r, "A", float(lon), float(lat), "wratten-96-nd3")
    exposure_s = 0.7 * cam.full_well_e / float(diff.max())
    _, (frame, background) = _sun_frames(r, "A", float(lon), float(lat), "wratten-96-nd3", exposure_s)
    assert frame.max() < cam.noise_model().max_dn
    dn_per_s = (frame - background) / exposure_s
    got = (dn_per_s * pixel_solid_angles_sr(r.models["A"])[..., None]).sum(axis=(0, 1))
    expected = r.electrons_per_unit / gain * cap_solid_angle_sr(sun.radius_rad) * sun.band_radiance(
        r.band_matrix("A", "wratten-96-nd3"))
    np.testing.assert_allclose(got, expected, rtol=0.01)
    assert np.all(got < expected)  # the veil's faint tail rounds away: at most FILTER_VEIL_FRACTION lost
    assert np.all(got > expected * (1 - FILTER_VEIL_FRACTION - 2e-3))


def test_neutral_density_filters_are_registered():
    names = filter_names()
    assert "wratten-96" in names and "wratten-96-nd3" in names
    nd1 = load_filter("wratten-96")
    nd3 = load_filter("wratten-96-nd3")
    np.testing.assert_allclose(nd3.values, nd1.values ** 3)
    assert 0.04 < nd1.values.min() and nd1.values.max() < 0.1
    assert 3.0 < -np.log10(nd3.values[0, nd3.wavelength_nm == 550.0][0]) < 3.2


def test_splat_drops_edge_pixels_without_a_solid_angle():
    """A wide lens whose distortion model ends inside the sensor's last pixel: a direction imaged there has
    no measurable pixel solid angle and is dropped, not splatted as NaN (was: NaN photo-electrons in a
    simulated frame at 07:00 with the sun at the frame's corner)."""
    import tomllib

    from omnispectral.rig import camera_model, rig_from_dict

    text = load_preset("small").toml_text.replace("hfov_deg = 95.0", "hfov_deg = 120.0")
    text = text.replace("width_px = 256", "width_px = 96").replace("height_px = 136", "height_px = 52")
    model = camera_model(rig_from_dict(tomllib.loads(text), "wide", text), "A")
    omega = pixel_solid_angles_sr(model)
    assert np.isnan(omega).any()  # the case this test is about exists on this lens
    rows, cols = np.nonzero(np.isnan(omega))
    rays = model.unproject(np.stack([cols, rows], axis=-1).astype(float))[0]
    world = rays @ model.camera_to_world(0.0, 0.0).T
    r, c, fraction = splat_camera(model, world, np.full(len(world), 1e-6), 0.0, 0.0)
    assert np.all(np.isfinite(fraction))
    assert not np.any(np.isnan(omega[r, c]))
