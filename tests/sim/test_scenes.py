"""Scenes of the simulated rig: conventions, sun and sky, consistency of the fast band path, ground truth."""

from __future__ import annotations

import math

import colour
import numpy as np
import pytest

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.sim.scenes import (
    CubeOnWallScene,
    PanoramaScene,
    ProceduralOutdoorScene,
    direction_to_lonlat,
    equirect_directions,
    equirect_lonlat,
    lonlat_to_direction,
    solar_position,
)
from omnispectral.sim.scenes.procedural import GROUND_ID
from omnispectral.sim.scenes.sky import (
    cie_sky_relative_luminance,
    hemisphere_quadrature,
)
from omnispectral.spectral.colour import cmfs_xyz
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM

WL = DEFAULT_WAVELENGTH_NM
BASELINE_M = 0.06


@pytest.fixture(scope="module")
def noon() -> ProceduralOutdoorScene:
    return ProceduralOutdoorScene(time_hhmm="12:00")


@pytest.fixture(scope="module")
def six_bands() -> np.ndarray:
    """Six smooth positive band sensitivities (× Δλ) on the default grid."""
    centres = np.linspace(430.0, 670.0, 6)
    return np.exp(-0.5 * ((WL[None, :] - centres[:, None]) / 30.0) ** 2) * 5.0 + 1e-3


def luminance_band(wavelength_nm: np.ndarray) -> np.ndarray:
    """683 ȳ Δλ as a one-band sensitivity: band_radiance is then luminance (cd/m²)."""
    return (683.0 * cmfs_xyz(wavelength_nm)[:, 1] * np.gradient(wavelength_nm))[None, :]


def random_directions(n: int, seed: int = 0) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


# ------------------------------------------------------------------------------------ conventions
def test_direction_conventions():
    np.testing.assert_allclose(lonlat_to_direction(0, 0), [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(lonlat_to_direction(90, 0), [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(lonlat_to_direction(-90, 0), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(lonlat_to_direction(0, 90), [0, 1, 0], atol=1e-12)
    lon = np.array([-179.0, -30.0, 0.0, 45.0, 170.0])
    lat = np.array([-80.0, -15.0, 0.0, 30.0, 89.0])
    back = direction_to_lonlat(lonlat_to_direction(lon, lat))
    np.testing.assert_allclose(back, (lon, lat), atol=1e-9)


def test_directions_match_camera_geometry():
    geometry = pytest.importorskip("omnispectral.imaging.geometry")
    lon = np.linspace(-180, 179, 37)[:, None]
    lat = np.linspace(-90, 90, 19)[None, :]
    np.testing.assert_allclose(lonlat_to_direction(lon, lat), geometry.lonlat_to_ray(lon, lat), atol=1e-12)


def test_equirect_pixel_centres():
    lon, lat = equirect_lonlat(8, 4)
    np.testing.assert_allclose(lon, -180 + 45 * (np.arange(8) + 0.5))
    np.testing.assert_allclose(lat, 90 - 45 * (np.arange(4) + 0.5))
    assert equirect_directions(8, 4).shape == (4, 8, 3)


# ------------------------------------------------------------------------------------ sun and sky
def test_solar_noon_at_equinox_and_solstice():
    """Solar noon elevation is 90° - latitude + declination; solar noon in Chiba is ~20 min before 12:00 JST."""
    times = np.arange(11 * 60, 12 * 60 + 30) / 60.0
    for day, decl in ((80, 0.0), (172, 23.44)):
        elev = [solar_position(day, t, 35.63, 140.10, 9.0).elevation_deg for t in times]
        k = int(np.argmax(elev))
        assert elev[k] == pytest.approx(90.0 - 35.63 + decl, abs=0.3)
        sp = solar_position(day, times[k], 35.63, 140.10, 9.0)
        assert sp.azimuth_deg == pytest.approx(180.0, abs=1.0)
        expected_noon_min = 12 * 60 - 4 * (140.10 - 135.0) - sp.equation_of_time_min
        assert times[k] * 60 == pytest.approx(expected_noon_min, abs=1.5)
    assert solar_position(80, 9.0, 35.63, 140.10, 9.0).azimuth_deg < 180 < solar_position(
        80, 15.0, 35.63, 140.10, 9.0).azimuth_deg


def test_cie_type12_reference_value():
    """colour-science's documented example of the CIE 2003 type-12 sky: 0.4544524."""
    z, zs = math.radians(45), math.radians(30)
    cos_chi = math.cos(z) * math.cos(zs) + math.sin(z) * math.sin(zs) * math.cos(math.pi)
    assert float(cie_sky_relative_luminance(math.cos(z), cos_chi, zs)) == pytest.approx(0.4544524, abs=1e-6)


def test_sky_dome_gives_the_diffuse_illuminance(noon):
    """A coarser, independent quadrature of the sky luminance reproduces E_kh; the sky's spectrum is L · S_sky."""
    dl = noon.daylight
    d, w = hemisphere_quadrature(90, 360)
    e = float(np.sum(dl.sky_luminance_cd_m2(d) * d[:, 1] * w))
    assert e == pytest.approx(dl.diffuse_horizontal_lx, rel=2e-3)
    zenith = noon.spectral_radiance([[0.0, 1.0, 0.0]])[0]
    np.testing.assert_allclose(zenith, dl.zenith_luminance_cd_m2 * dl.sky_spectrum, rtol=1e-5)
    np.testing.assert_allclose(noon.band_radiance([[0.0, 1.0, 0.0]], luminance_band(WL))[0, 0],
                               dl.zenith_luminance_cd_m2, rtol=0.02)  # 400-700 nm truncation of ȳ


def test_daylight_cct_follows_the_sun():
    noon = ProceduralOutdoorScene(time_hhmm="12:00").describe()["daylight"]
    evening = ProceduralOutdoorScene(time_hhmm="17:00").describe()["daylight"]
    assert noon["sun_elevation_deg"] > evening["sun_elevation_deg"] > 0
    assert noon["cct_sun_K"] > evening["cct_sun_K"] + 500
    assert noon["cct_facing_sun_K"] > evening["cct_facing_sun_K"]
    for d in (noon, evening):
        assert d["cct_sky_K"] > d["cct_sun_K"]
        assert d["direct_normal_illuminance_lx"] > d["diffuse_horizontal_illuminance_lx"] > 0


def test_sun_below_horizon_is_dark_but_defined():
    night = ProceduralOutdoorScene(time_hhmm="19:30")
    assert night.daylight.sun.elevation_deg < 0
    assert night.daylight.direct_normal_lx == 0.0
    rad = night.spectral_radiance(random_directions(2000))
    assert np.all(np.isfinite(rad)) and rad.min() >= 0


# ------------------------------------------------------------------------------------ procedural
def test_band_radiance_equals_spectral_procedural(noon, six_bands):
    d = np.vstack([random_directions(20000), noon.daylight.sun_direction,
                   [lonlat_to_direction(p["lon_deg"], p["lat_deg"]) for p in noon.colorchecker_patches()]])
    for origin in ((0, 0, 0), (BASELINE_M, 0, 0)):
        spec = noon.spectral_radiance(d, origin).astype(np.float64)
        bands = noon.band_radiance(d, six_bands, origin)
        assert bands.dtype == np.float32 and bands.shape == (d.shape[0], 6)
        np.testing.assert_allclose(bands, spec @ six_bands.T, rtol=1e-4)


def test_dynamic_range_sun_over_shadowed_ground(noon):
    v = luminance_band(WL)
    sun = noon.band_radiance(noon.daylight.sun_direction[None], v)[0, 0]
    d = equirect_directions(720, 360, 180, 360).reshape(-1, 3).astype(np.float32)
    rec = noon.shade(d, np.zeros(3))
    shadow = (rec.obj == GROUND_ID) & (rec.sun == 0)
    assert shadow.sum() > 100
    shadowed = noon.band_radiance(d[shadow], v)[:, 0]
    assert sun / shadowed.max() >= 1e5
    lit = (rec.obj == GROUND_ID) & (rec.sun > 0)
    assert np.median(noon.band_radiance(d[lit], v)) > 3 * np.median(shadowed)


def test_colorchecker_patch_is_lambertian(six_bands):
    for time_hhmm, sunlit in (("12:00", True), ("08:00", False)):
        scene = ProceduralOutdoorScene(time_hhmm=time_hhmm)
        patches = scene.colorchecker_patches()
        assert [p["name"] for p in patches][:2] == ["dark skin", "light skin"] and len(patches) == 24
        for p in patches[::5]:
            centre, normal = np.array(p["centre_m"]), np.array(p["normal"])
            e = scene.surface_irradiance(centre, normal)
            expected = np.array(p["reflectance"]) * e / math.pi
            got = scene.spectral_radiance(lonlat_to_direction(p["lon_deg"], p["lat_deg"])[None])[0]
            np.testing.assert_allclose(got, expected, rtol=1e-4)
            assert (scene.daylight.sun_illuminance_lx(normal) > 0 and not scene.occluded(centre[None])[0]) == sunlit
    # a few hundred pixels per patch in a 7260 × 3630 panorama
    side_px = 2 * patches[0]["half_size_deg"] / (360.0 / 7260)
    assert side_px**2 > 300


def test_near_object_parallax(noon):
    """The post 1.5 m away moves by ≈ baseline / distance between origins 60 mm apart; far buildings do not."""
    post = [b.name for b in noon.boxes].index("post") + 1
    brick = [b.name for b in noon.boxes].index("brick building") + 1
    lon = np.linspace(85.0, 115.0, 3001)
    d = lonlat_to_direction(lon, -10.0).astype(np.float32)
    far_lon = np.linspace(-40.0, 40.0, 8001)
    far_d = lonlat_to_direction(far_lon, 12.0).astype(np.float32)
    centres, edges = [], []
    for origin in (np.zeros(3), np.array([0.0, 0.0, BASELINE_M])):
        on = noon.shade(d, origin).obj == post
        centres.append(lon[on].mean())
        on_far = noon.shade(far_d, origin).obj == brick
        edges.append(far_lon[on_far].min())
    shift = abs(centres[0] - centres[1])
    assert shift > 1.0  # ≈ 0.06 m / 1.5 m · sin(100°) rad ≈ 2.3°
    assert abs(edges[0] - edges[1]) < 0.2
    without = ProceduralOutdoorScene(near_object=False)
    assert "post" not in [b.name for b in without.boxes]


def test_scene_is_deterministic_given_the_seed():
    d = random_directions(3000, seed=3)
    a, b = ProceduralOutdoorScene(seed=7), ProceduralOutdoorScene(seed=7)
    np.testing.assert_array_equal(a.spectral_radiance(d), b.spectral_radiance(d))
    assert a.describe() == b.describe()
    descriptions = {str(ProceduralOutdoorScene(seed=s).describe()["materials"]) for s in range(4)}
    assert len(descriptions) > 1


def test_describe_is_json(noon):
    import json

    text = json.dumps(noon.describe())
    assert '"kind": "procedural"' in text and "cct_sun_K" in text
    json.dumps(noon.colorchecker_patches())


def test_ground_truth_streams_the_band_path(noon, six_bands):
    w, h = 64, 32
    blocks = list(noon.ground_truth_bands(w, h, six_bands, rows=10))
    assert [r0 for r0, _ in blocks] == [0, 10, 20, 30]
    bands = np.concatenate([b for _, b in blocks])
    gt = noon.ground_truth(w, h, six_bands)
    assert gt["spectral_radiance"].shape == (h, w, WL.size) and gt["band_radiance"].shape == (h, w, 6)
    np.testing.assert_array_equal(gt["band_radiance"], bands)
    np.testing.assert_allclose(bands, gt["spectral_radiance"].astype(np.float64) @ six_bands.T, rtol=1e-4)
    with pytest.raises(ConfigurationError):
        noon.ground_truth_spectral(100_000, 50_000)


def test_bad_parameters(noon):
    with pytest.raises(ConfigurationError):
        ProceduralOutdoorScene(time_hhmm="25:00")
    with pytest.raises(ConfigurationError):
        ProceduralOutdoorScene(wavelength_nm=np.arange(380.0, 781.0, 5.0))
    with pytest.raises(ConfigurationError):
        noon.band_radiance(random_directions(3), np.ones((3, 10)))
    with pytest.raises(ConfigurationError):
        noon.spectral_radiance(np.zeros((2, 3)))


# ------------------------------------------------------------------------------------ panorama
def render_srgb(spectral_radiance: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Linear sRGB of spectral radiance divided by 1 cd/m² per unit Y (CIE 1931 2°, no adaptation)."""
    xyz = 683.0 * spectral_radiance.astype(np.float64) @ (cmfs_xyz(wavelength_nm) * np.gradient(wavelength_nm)[:, None])
    return colour.XYZ_to_RGB(xyz, "sRGB", apply_cctf_encoding=False)


def test_panorama_round_trip_to_srgb(shared_data):
    path = shared_data / "hdr_envmaps" / "polyhaven_1k_hdr" / "venice_sunset_1k.hdr"
    wl = np.arange(380.0, 780.0 + 1e-9, 5.0)  # the basis' full range
    scene = PanoramaScene(path, wavelength_nm=wl, scale=2.0)
    h, w = scene.rgb.shape[:2]
    rows = slice(0, h, 7)
    d = equirect_directions(w, h)[rows].reshape(-1, 3)
    ref = scene.rgb[rows].reshape(-1, 3).astype(np.float64)
    rgb = render_srgb(scene.spectral_radiance(d), wl) / 2.0
    y = np.maximum(ref @ [0.2126, 0.7152, 0.0722], 1e-6)
    assert np.max(np.abs(rgb - ref).max(axis=1) / y) < 2e-3
    assert scene.describe()["luminance_cd_m2"]["max"] > 10.0  # HDR kept


def test_panorama_band_path_and_bilinear(six_bands):
    rgb = np.random.default_rng(1).uniform(0.0, 50.0, size=(16, 32, 3)).astype(np.float32)
    scene = PanoramaScene(rgb)
    d = random_directions(5000)
    np.testing.assert_allclose(scene.band_radiance(d, six_bands),
                               scene.spectral_radiance(d).astype(np.float64) @ six_bands.T, rtol=1e-4)
    lon, lat = equirect_lonlat(32, 16)
    mid = lonlat_to_direction(0.5 * (lon[3] + lon[4]), lat[5])[None]
    np.testing.assert_allclose(scene.rgb_at(mid)[0], 0.5 * (rgb[5, 3] + rgb[5, 4]), rtol=1e-4)
    seam = lonlat_to_direction(-180.0, lat[2])[None]
    np.testing.assert_allclose(scene.rgb_at(seam)[0], 0.5 * (rgb[2, 0] + rgb[2, -1]), rtol=1e-4)
    assert np.all(scene.spectral_radiance(d, origin_m=(5.0, 0.0, 0.0)) == scene.spectral_radiance(d))


def test_panorama_files_keep_rgb_order(tmp_path):
    from omnispectral.imaging.bracket import write_float_image

    rgb = np.zeros((8, 16, 3), np.float32)
    rgb[..., 0] = 4.0  # pure red
    rgb[:, 8:, 2] = 0.5
    for suffix in (".hdr", ".exr"):
        path = write_float_image(tmp_path / f"pano{suffix}", rgb)
        np.testing.assert_allclose(PanoramaScene(path).rgb, rgb, rtol=2e-2)
    red = PanoramaScene(rgb).spectral_radiance([[0.0, 0.0, 1.0]])[0]
    assert red[WL >= 620].mean() > 5 * red[WL <= 480].mean()


def test_panorama_bad_inputs(tmp_path):
    with pytest.raises(InputFileError, match="no such file"):
        PanoramaScene(tmp_path / "missing.hdr")
    bad = tmp_path / "bad.hdr"
    bad.write_bytes(b"not an image")
    with pytest.raises(InputFileError, match=r"bad\.hdr"):
        PanoramaScene(bad)
    other = tmp_path / "pano.png"
    other.write_bytes(b"x")
    with pytest.raises(InputFileError, match="unsupported"):
        PanoramaScene(other)
    with pytest.raises(ConfigurationError, match="twice as wide"):
        PanoramaScene(np.ones((10, 10, 3)))
    nan = np.ones((4, 8, 3))
    nan[0, 0, 0] = np.nan
    with pytest.raises(ConfigurationError, match="NaN"):
        PanoramaScene(nan)


# ------------------------------------------------------------------------------------ cube
@pytest.fixture(scope="module")
def cube_file(tmp_path_factory):
    wl = np.arange(390.0, 720.0 + 1e-9, 10.0)
    yy, xx = np.mgrid[0:12, 0:20]
    peak = 420.0 + 260.0 * xx / 19.0
    bump = np.exp(-0.5 * ((wl[None, None, :] - peak[..., None]) / 35.0) ** 2)
    cube = 0.05 + 0.9 * bump * (0.4 + 0.05 * yy)[..., None]
    path = tmp_path_factory.mktemp("cube") / "cube.npz"
    np.savez(path, cube=cube.astype(np.float32), wavelength_nm=wl)
    return path


def test_cube_on_wall_is_reflectance_times_daylight(noon, cube_file, six_bands):
    scene = CubeOnWallScene(cube_file, base=noon)
    assert scene.describe()["panel"]["normal"] == [0.0, 0.0, -1.0]
    for row, col in ((0, 0), (5, 7), (11, 19)):
        p = scene.texel_centre_m(row, col)
        e = noon.surface_irradiance(p, scene.normal)
        got = scene.spectral_radiance(p[None] / np.linalg.norm(p))[0]
        np.testing.assert_allclose(got, scene.reflectance(row, col) * e / math.pi, rtol=1e-4)
    # the cube's reflectance is resampled from its own 10-nm grid
    data = np.load(cube_file)
    np.testing.assert_allclose(scene.reflectance(5, 7), np.interp(WL, data["wavelength_nm"], data["cube"][5, 7]),
                               rtol=1e-6)
    centre = scene.centre_m / np.linalg.norm(scene.centre_m)
    lon, lat = direction_to_lonlat(centre)
    d = lonlat_to_direction(lon + np.random.default_rng(0).uniform(-12, 12, 4000),
                            lat + np.random.default_rng(1).uniform(-8, 8, 4000))
    for origin in ((0, 0, 0), (BASELINE_M, 0, 0)):
        np.testing.assert_allclose(scene.band_radiance(d, six_bands, origin),
                                   scene.spectral_radiance(d, origin).astype(np.float64) @ six_bands.T, rtol=1e-4)
    away = lonlat_to_direction(150.0, 20.0)[None]
    np.testing.assert_array_equal(scene.spectral_radiance(away), noon.spectral_radiance(away))


@pytest.fixture(scope="module")
def fine_cube():
    """A 240 × 240 random-texel cube: ~6 × 6 texels per pixel of a 952-px-wide grid at the near wall."""
    rng = np.random.default_rng(3)
    wl = np.array([400.0, 550.0, 700.0])
    cube = rng.uniform(0.05, 0.9, (240, 240, 3)) * rng.uniform(0.5, 1.0, (1, 1, 3))
    return cube.astype(np.float32), wl


def test_cube_ray_footprint_is_the_mean_of_its_texels(noon, fine_cube, six_bands):
    """A ray with a spread gets the mean of the dense point samples over its angular square (the ground truth of
    the filtering), at a head-on and an oblique view of the panel."""
    scene = CubeOnWallScene(fine_cube, base=noon, lon_deg=-40.0, lat_deg=5.0)
    for lon in (-40.0, -35.0):  # two points of the panel, seen 40° and 35° off its normal
        d = lonlat_to_direction(lon, 3.0).astype(np.float64)
        e1 = np.cross(d, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(d, e1)
        spread = 4e-3  # ~3 × 3 texels head on
        g = (np.arange(64) + 0.5) / 64 - 0.5
        a, b = np.meshgrid(g, g)
        dense = d + spread * (a.reshape(-1, 1) * e1 + b.reshape(-1, 1) * e2)
        dense /= np.linalg.norm(dense, axis=1, keepdims=True)
        want = scene.band_radiance(dense, six_bands, sun_disk=False).mean(axis=0)
        got = scene.band_radiance(d[None], six_bands, sun_disk=False, ray_spread_rad=spread)[0]
        point = scene.band_radiance(d[None], six_bands, sun_disk=False)[0]
        err, err_point = np.abs(got / want - 1).max(), np.abs(point / want - 1).max()
        assert err < 0.01, (lon, err)
        assert err_point > 5 * err, (lon, err_point, err)  # what point sampling would give


def test_truth_filters_a_fine_texture_like_many_rays(noon, fine_cube, six_bands):
    """The truth's 2 × 2 rays per pixel, each filtering the texture over its share of the pixel, give the pixel's
    mean: they match 8 × 8 filtering rays and 16 × 16 point samples on a texture of ~6 × 6 texels per pixel,
    where point samples (2 × 2, refined) miss it by three times as much."""
    from omnispectral.sim.truth import _fill_equirect, render_equirect_bands

    scene = CubeOnWallScene(fine_cube, base=noon, lon_deg=-40.0, lat_deg=5.0)
    width, rows = 952, (218, 230)
    got = render_equirect_bands(scene, six_bands, width, *rows)

    def fill(supersample, filtered):
        out = np.empty_like(got)
        _fill_equirect(out, lambda r, s: scene.band_radiance(r, six_bands, sun_disk=False,
                                                             **({"ray_spread_rad": s} if filtered else {})),
                       64, supersample=supersample, row_offset=rows[0], height=width // 2)
        return out

    centres = lonlat_to_direction(*np.meshgrid((np.arange(width) + 0.5) / width * 360 - 180,
                                               90 - (np.arange(*rows) + 0.5) / (width // 2) * 180)).reshape(-1, 3)
    differs = np.abs(scene.band_radiance(centres, six_bands, sun_disk=False)
                     - noon.band_radiance(centres, six_bands, sun_disk=False)).max(axis=-1)
    on_panel = (differs > 0).reshape(got.shape[:2])
    inner = on_panel & np.roll(on_panel, 1, 1) & np.roll(on_panel, -1, 1)
    inner[1:-1] &= on_panel[:-2] & on_panel[2:]
    assert inner.sum() > 100
    reference = fill(8, True)

    def median_error(x):
        return float(np.median(np.abs(x / reference - 1)[inner]))

    # the texture's refined pixels take 64 lattice points whose filter boxes overlap instead of tiling the pixel
    # as an 8 x 8 grid's do (sim.antialias): 0.0051 here, 0 with the grid (the reference's own rays)
    assert median_error(got) < 0.008
    assert median_error(fill(16, False)) < 0.02  # the reference is the pixels' mean, not the filter's own
    assert median_error(fill(2, False)) > 3 * median_error(got)  # unfiltered, refined: 0.019


def test_cube_bad_inputs(tmp_path, cube_file):
    good = np.load(cube_file)
    cases = {
        "missing.npz": None,
        "corrupt.npz": b"not a zip",
        "keys.npz": {"data": good["cube"], "wavelength_nm": good["wavelength_nm"]},
        "shape.npz": {"cube": good["cube"][..., 0], "wavelength_nm": good["wavelength_nm"]},
        "bands.npz": {"cube": good["cube"], "wavelength_nm": good["wavelength_nm"][:-1]},
        "range.npz": {"cube": good["cube"] * 3.0, "wavelength_nm": good["wavelength_nm"]},
        "order.npz": {"cube": good["cube"], "wavelength_nm": good["wavelength_nm"][::-1]},
        "cover.npz": {"cube": good["cube"], "wavelength_nm": good["wavelength_nm"] + 30.0},
    }
    messages = {"missing.npz": "no such file", "corrupt.npz": "cannot be read", "keys.npz": "missing array",
                "shape.npz": r"shape \(H, W, B\)", "bands.npz": "to match", "range.npz": "0..1",
                "order.npz": "increasing", "cover.npz": "do not cover"}
    for name, content in cases.items():
        path = tmp_path / name
        if isinstance(content, bytes):
            path.write_bytes(content)
        elif content is not None:
            np.savez(path, **content)
        with pytest.raises(InputFileError, match=messages[name]) as info:
            CubeOnWallScene(path)
        assert info.value.path == path
    text = tmp_path / "cube.txt"
    text.write_text("not a cube")
    with pytest.raises(InputFileError, match="unsupported"):
        CubeOnWallScene(text)
    with pytest.raises(ConfigurationError, match="does not meet"):
        CubeOnWallScene(cube_file, lon_deg=150.0)
    with pytest.raises(ConfigurationError, match="does not fit"):
        CubeOnWallScene(cube_file, width_m=20.0)


def test_envi_cube_round_trip(tmp_path):
    """An ENVI cube written by Spectral Python reads back with its wavelengths, like the .npz form."""
    import spectral.io.envi as envi

    from omnispectral.sim.scenes import load_reflectance_cube

    rng = np.random.default_rng(4)
    cube = rng.uniform(0.05, 0.9, (6, 7, 31)).astype(np.float32)
    wl = np.arange(400.0, 701.0, 10.0)
    envi.save_image(str(tmp_path / "cube.hdr"), cube, metadata={"wavelength": [f"{w:g}" for w in wl],
                                                                 "wavelength units": "nm"}, force=True)
    got, got_wl = load_reflectance_cube(tmp_path / "cube.hdr")
    np.testing.assert_allclose(got, cube, rtol=1e-6)
    np.testing.assert_allclose(got_wl, wl)
    (tmp_path / "bare.hdr").write_text("ENVI\nsamples = 2\nlines = 2\nbands = 2\n")
    with pytest.raises(InputFileError, match="bare"):
        CubeOnWallScene(tmp_path / "bare.hdr")


def test_scenes_pickle_for_worker_processes(noon, cube_file, six_bands):
    import pickle

    d = random_directions(500, seed=5)
    for scene in (noon, CubeOnWallScene(cube_file, base=noon), PanoramaScene(np.ones((4, 8, 3)))):
        copy = pickle.loads(pickle.dumps(scene))
        np.testing.assert_array_equal(copy.band_radiance(d, six_bands), scene.band_radiance(d, six_bands))
