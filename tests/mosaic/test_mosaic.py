"""Mosaic engine: Eq. (4), interpolation, composed maps, blending, the engine on known scenes, store and resume."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import (
    CameraModel,
    Mounting,
    equirect_pixel_to_lonlat,
    lonlat_to_ray,
    ray_to_lonlat,
)
from omnispectral.mosaic import (
    Canvas,
    MergedDirections,
    PanoramaStore,
    Rect,
    SourceGeometry,
    mosaic,
    polar_angles_rad,
    polar_image,
    polar_to_image_px,
    remap,
    render_tile,
    source_map,
)
from omnispectral.mosaic.blending import LinearBlend, feather_weight, multiband_blend
from omnispectral.mosaic.interp import METHODS, opencv_is_exact, remap_reference
from omnispectral.mosaic.maps import exact_map, rect_map, tile_cone
from omnispectral.mosaic.options import MosaicOptions
from omnispectral.mosaic.run import run_tasks
from omnispectral.mosaic.sources import MergedDirectionsWriter, encode_image, read_npy_rows
from omnispectral.mosaic.store import box_average_2x2, pyramid_shapes
from omnispectral.mosaic.tile import build_job
from omnispectral.rig import camera_model, load_preset, rig_toml
from omnispectral.sim.synthetic import pad_over_poles, render_source, six_band_panorama, write_synthetic_merged

RIG = load_preset("small")  # the time-lapse geometry (95 x 61 deg, portrait, distortion) on a 256 x 136 sensor
WIDTH = 256  # output panorama width in these tests


def smooth_scene(rays: np.ndarray) -> np.ndarray:
    """A smooth, positive six-band scene, analytic in the ray (..., 3) -> (..., 6)."""
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    rgb = np.stack([2.0 + np.sin(7 * x + 1.0) * np.cos(5 * z), 2.0 + 0.8 * y + 0.5 * np.sin(9 * z * x),
                    1.5 + 0.6 * np.cos(6 * y - x) + 0.3 * z], axis=-1)
    return six_band_panorama(rgb.astype(np.float32))


def smooth_panorama(width: int) -> np.ndarray:
    """:func:`smooth_scene` on a width x width/2 equirect grid."""
    col, row = np.meshgrid(np.arange(width), np.arange(width // 2))
    return smooth_scene(lonlat_to_ray(*equirect_pixel_to_lonlat(col, row, width, width // 2)))


def small_cameras(rig=RIG) -> dict[str, CameraModel]:
    return {c: camera_model(rig, c) for c in ("A", "B")}


def grid_directions(n_pan: int = 12, n_tilt: int = 3) -> list[tuple[float, float]]:
    from omnispectral.capture.plan import direction_grid

    return [(d.pan_deg, d.tilt_deg) for d in direction_grid(n_pan, n_tilt)]


@pytest.fixture(scope="module")
def known(tmp_path_factory):
    """Merged directions of the smooth scene, rendered exactly (the truth is known)."""
    path = tmp_path_factory.mktemp("mosaic") / "merged"
    merged = write_synthetic_merged(path, smooth_scene, small_cameras(), grid_directions(), offset_b_px=(0.4, -0.3),
                                    rig_name=RIG.name, rig_toml=rig_toml(RIG), system=RIG.system().to_dict())
    return merged, smooth_panorama(WIDTH)


def psnr(estimate, truth):
    return 10 * np.log10(truth.max() ** 2 / np.mean((estimate - truth) ** 2))


# ------------------------------------------------------------------------------------------ Eq. (4)
def test_eq4_known_angles_and_inverse():
    f = 500.0
    theta, phi = polar_angles_rad([0.0, f, 0.0, f], [0.0, 0.0, f, f], f)
    np.testing.assert_allclose(np.degrees(theta), [0, 45, 0, 45], atol=1e-12)
    np.testing.assert_allclose(np.degrees(phi), [0, 0, 45, np.degrees(np.arctan(1 / np.sqrt(2)))], atol=1e-12)
    x, y = np.random.default_rng(0).uniform(-800, 800, (2, 100))
    np.testing.assert_allclose(polar_to_image_px(*polar_angles_rad(x, y, f), f), (x, y), atol=1e-9)
    with pytest.raises(ConfigurationError):
        polar_angles_rad(1.0, 1.0, 0.0)


def test_eq4_is_longitude_and_minus_latitude_of_the_ray():
    """θ, -φ are the lon/lat of the pixel's ray for an unrolled camera at pan = tilt = 0 (geometry module)."""
    m = CameraModel.from_fov(400, 300, 70.0)
    x, y = np.random.default_rng(1).uniform(-150, 150, (2, 50))
    rays, _ = m.pixel_to_world(np.stack([x + m.cx, y + m.cy], -1), 0.0, 0.0)
    lon, lat = ray_to_lonlat(rays)
    theta, phi = polar_angles_rad(x, y, m.fx)
    np.testing.assert_allclose(np.radians(lon), theta, atol=1e-12)
    np.testing.assert_allclose(np.radians(lat), -phi, atol=1e-12)


def test_polar_image_spans_the_fields_of_view_like_fig7():
    """A 61 x 95 deg portrait frame: θ spans the horizontal FOV on every row, φ the vertical FOV on the centre
    column only (the top/bottom borders curve inwards, as in the paper's Fig. 7b)."""
    m = CameraModel.from_fov(136, 256, 61.0)
    img = np.random.default_rng(2).random((256, 136)).astype(np.float32)
    p = polar_image(img, m.fx)
    assert p.theta_deg[0] < -30.0 and p.theta_deg[-1] > 30.0 and p.theta_deg[-1] - p.theta_deg[0] < 61.0
    vfov = np.degrees(2 * np.arctan(128.0 / m.fx))
    assert abs((p.phi_deg[-1] - p.phi_deg[0]) - vfov) < 1.0
    centre_rows = p.valid[:, p.valid.shape[1] // 2].sum()
    edge_rows = p.valid[:, 1].sum()
    assert centre_rows == p.valid.shape[0] and edge_rows < 0.95 * centre_rows
    assert np.isnan(p.image[0, 0]) and np.isfinite(p.image[p.image.shape[0] // 2, p.image.shape[1] // 2])


def test_polar_image_equals_the_engines_single_direction_output(tmp_path):
    """Eq. (4) of an unrolled, undistorted camera at pan = tilt = 0 is the engine's equirect output flipped."""
    f = 120.0
    width = 2 * round(np.pi * f)  # equirect pixel = 1/f rad, the polar image's default step
    m = CameraModel.from_fov(200, 160, float(np.degrees(2 * np.arctan(100 / f))))
    truth = smooth_panorama(4 * width)
    padded = pad_over_poles(truth)
    img = render_source(padded, 4 * width, 2 * width, m, "A", 0.0, 0.0)
    p = polar_image(img, m.fx, interp="cubic")
    merged = write_synthetic_merged(tmp_path / "m", truth, {"A": m, "B": m}, [(0.0, 0.0)])
    out = PanoramaStore.open(mosaic(merged, tmp_path / "p.zarr", width=width, tile=64, interp="cubic")["output"])
    pano = out.read(0)[..., :3]
    # equirect pixel (col, row) ↔ θ = lon, φ = -lat; compare where the polar grid hits pixel centres
    lon, lat = equirect_pixel_to_lonlat(np.arange(width), np.arange(width // 2), width, width // 2)
    for i in np.linspace(10, len(p.phi_deg) - 10, 7).astype(int):
        for j in np.linspace(10, len(p.theta_deg) - 10, 7).astype(int):
            c = int(np.argmin(np.abs(lon - p.theta_deg[j])))
            r = int(np.argmin(np.abs(lat + p.phi_deg[i])))
            if abs(lon[c] - p.theta_deg[j]) < 1e-3 and abs(lat[r] + p.phi_deg[i]) < 1e-3:
                np.testing.assert_allclose(pano[r, c], p.image[i, j], rtol=2e-3)


# ------------------------------------------------------------------------------------------ interpolation
@pytest.mark.parametrize("method", METHODS)
def test_remap_matches_the_reference_kernel(method):
    rng = np.random.default_rng(3)
    src = rng.random((40, 50, 3)).astype(np.float32)
    u = rng.uniform(2, 47, (30, 20)).astype(np.float32)
    v = rng.uniform(2, 37, (30, 20)).astype(np.float32)
    np.testing.assert_allclose(remap(src, u, v, method), remap_reference(src, u, v, method), atol=5e-5)


@pytest.mark.parametrize("method", METHODS)
def test_remap_reproduces_pixels_and_constants(method):
    rng = np.random.default_rng(4)
    src = rng.random((30, 30, 3)).astype(np.float32)
    yy, xx = np.mgrid[5:25, 5:25].astype(np.float32)
    np.testing.assert_allclose(remap(src, xx, yy, method), src[5:25, 5:25], atol=2e-5)
    const = np.full((30, 30, 3), 7.25, np.float32)
    u = rng.uniform(0, 29, (10, 10)).astype(np.float32)
    np.testing.assert_allclose(remap(const, u, u.T.copy(), method), 7.25, rtol=1e-6)


def test_clamped_cubic_stays_within_its_four_neighbours_beside_the_sun_and_is_cubic_elsewhere():
    rng = np.random.default_rng(5)
    src = rng.random((40, 50, 3)).astype(np.float32)
    src[20, 25] = 1e5  # an HDR spike: the cubic's negative lobes ring around it
    u = rng.uniform(1, 48, (40, 40)).astype(np.float32)
    v = rng.uniform(1, 38, (40, 40)).astype(np.float32)
    clamped, cubic = remap(src, u, v, "cubic-clamped"), remap(src, u, v, "cubic")
    i, j = np.floor(u).astype(int), np.floor(v).astype(int)
    quad = np.stack([src[j, i], src[j, i + 1], src[j + 1, i], src[j + 1, i + 1]])
    assert (clamped >= quad.min(axis=0) - 1e-3).all() and (clamped <= quad.max(axis=0) + 1e-3).all()
    assert cubic.min() < -100 and clamped.min() >= 0  # plain cubic goes negative beside the spike
    inside = (cubic >= quad.min(axis=0)) & (cubic <= quad.max(axis=0))
    np.testing.assert_array_equal(clamped[inside], cubic[inside])
    assert inside.mean() > 0.5


def test_remap_interpolates_at_the_exact_position():
    """No 1/32-px rounding (OpenCV 4, Lanczos-4, > 4 channels): a 1/100-px shift moves the result as the kernel
    says; linear and the B-spline reproduce a ramp exactly, so there it moves by exactly 1/100."""
    ramp = np.tile(np.arange(64, dtype=np.float32), (16, 1))[..., None].repeat(3, -1)
    ramp += np.sin(np.arange(64, dtype=np.float32))[None, :, None]
    yy, xx = np.mgrid[4:12, 8:40].astype(np.float32)
    for method in METHODS:
        a = remap(ramp, xx + np.float32(0.31), yy, method)
        b = remap(ramp, xx + np.float32(0.32), yy, method)
        ref = remap_reference(ramp, xx + 0.32, yy, method) - remap_reference(ramp, xx + 0.31, yy, method)
        np.testing.assert_allclose(b - a, ref, atol=1e-4)
        assert np.abs(b - a).max() > 2e-3
    lin = np.tile(np.arange(64, dtype=np.float32), (16, 1))
    for method in ("linear", "spline"):
        np.testing.assert_allclose(remap(lin, xx + np.float32(0.32), yy, method), xx + 0.32, atol=2e-4)
    assert isinstance(opencv_is_exact("cubic"), bool)


# ------------------------------------------------------------------------------------------ maps
@pytest.mark.parametrize("rect", [Rect(0, 64, 0, 64), Rect(30, 94, 100, 164), Rect(64, 128, 192, 256)])
def test_source_map_matches_the_exact_composed_geometry(rect):
    canvas = Canvas(WIDTH, WIDTH // 2)
    checked = 0
    for cam in ("A", "B"):
        for pan, tilt in ((-165.0, 60.0), (15.0, 0.0), (165.0, -60.0)):
            geo = SourceGeometry.build(camera_model(RIG, cam), pan, tilt, (0.4, -0.3) if cam == "B" else (0, 0))
            sm = source_map(geo, canvas, rect, tol_px=1e-3)
            full = exact_map(geo, canvas, np.arange(rect.row0, rect.row1), np.arange(rect.col0, rect.col1))
            inside = geo.model.inside(full[..., 0], full[..., 1], 0.0)
            if sm is None:
                assert not inside.any()
                continue
            r, c = sm.row0 - rect.row0, sm.col0 - rect.col0
            sub = full[r:r + sm.u.shape[0], c:c + sm.u.shape[1]]
            assert inside.sum() == inside[r:r + sm.u.shape[0], c:c + sm.u.shape[1]].sum()  # nothing cut off
            ok = geo.model.inside(sub[..., 0], sub[..., 1], 2.0)
            err = np.hypot(sm.u - sub[..., 0], sm.v - sub[..., 1])[ok]
            assert err.max(initial=0.0) < 2e-3
            checked += err.size
    assert checked > 1000



@pytest.mark.parametrize("rect", [Rect(0, 64, 0, 64), Rect(30, 94, 100, 164)])
def test_rect_map_covers_the_whole_rect_and_matches_the_exact_geometry_on_the_image(rect):
    """rect_map (camera A's pixel under camera B's: the parallax lookup) maps every pixel of the rect, within
    2e-3 px of exact_map wherever the position lands on the image (± 2 px), with far fewer exact projections."""
    canvas = Canvas(WIDTH, WIDTH // 2)
    checked = 0
    for pan, tilt in ((-165.0, 60.0), (15.0, 0.0), (165.0, -60.0)):
        geo = SourceGeometry.build(camera_model(RIG, "A"), pan, tilt, (0, 0))
        rm = rect_map(geo, canvas, rect)
        assert (rm.row0, rm.col0, rm.u.shape) == (rect.row0, rect.col0, rect.shape)
        full = exact_map(geo, canvas, np.arange(rect.row0, rect.row1), np.arange(rect.col0, rect.col1))
        ok = geo.model.inside(full[..., 0], full[..., 1], 2.0)
        err = np.hypot(rm.u - full[..., 0], rm.v - full[..., 1])[ok]
        assert err.max(initial=0.0) < 2e-3
        assert np.sum(np.rint(rm.u[ok]) != np.rint(full[..., 0][ok])) <= 0.01 * ok.sum()  # the nearest pixel: the same
        checked += err.size
    assert checked > 1000


def test_tile_cone_contains_every_pixel_of_the_tile():
    canvas = Canvas(1000, 500)
    for rect in (Rect(0, 50, 0, 50), Rect(225, 275, 950, 1000), Rect(450, 500, 480, 530)):
        centre, radius = tile_cone(canvas, rect)
        rays = canvas.rays(np.arange(rect.row0, rect.row1), np.arange(rect.col0, rect.col1)).reshape(-1, 3)
        assert np.arccos(np.clip(rays @ centre, -1, 1)).max() <= radius


# ------------------------------------------------------------------------------------------ blending
def test_feather_weight_is_a_tent_to_the_border():
    w = feather_weight(np.array([-0.5, 49.5, 99.5, 24.5, np.nan, 120.0]), np.array([29.5, 29.5, 29.5, 29.5, 1, 2]),
                       100, 60)
    np.testing.assert_allclose(w, [0.0, 1.0, 0.0, 0.5, 0.0, 0.0], atol=1e-6)


def test_linear_blend_is_a_convex_combination():
    acc = LinearBlend((4, 5), 6)
    rng = np.random.default_rng(5)
    for _ in range(3):
        acc.add((0, 1, 2), 0, 0, np.full((4, 5, 3), 3.5, np.float32), rng.random((4, 5)).astype(np.float32))
    out = acc.result()
    np.testing.assert_allclose(out[..., :3], 3.5, rtol=1e-6)
    assert np.isnan(out[..., 3:]).all()


def test_multiband_blend_keeps_identical_overlaps_and_blends_different_ones():
    h, w = 64, 96
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    scene = (2 + np.sin(xx / 5.0) * np.cos(yy / 7.0))[..., None].repeat(3, -1).astype(np.float32)
    w1 = np.clip(1 - xx / 60, 0, 1).astype(np.float32)
    w2 = np.clip((xx - 30) / 60, 0, 1).astype(np.float32)
    out = multiband_blend([scene, scene], [w1, w2], levels=4)
    np.testing.assert_allclose(out, scene, rtol=1e-5)
    mixed = multiband_blend([scene, 2 * scene], [w1, w2], levels=3)
    ratio = (mixed / scene)[..., 0].mean(axis=0)
    assert abs(ratio[:5].mean() - 1.0) < 0.05 and abs(ratio[-5:].mean() - 2.0) < 0.05
    assert np.all(np.diff(ratio[10:-10]) > -0.02)  # a smooth transition across the seam at x = 45


# ------------------------------------------------------------------------------------------ the engine
UNIFORM = np.array([3.0, 0.25, 1e4, 7.0, 0.5, 123.0], np.float32)


@pytest.fixture(scope="module")
def uniform(tmp_path_factory):
    flat = np.broadcast_to(UNIFORM, (64, 128, 6)).copy()
    return write_synthetic_merged(tmp_path_factory.mktemp("uniform") / "m", flat, small_cameras(), grid_directions(),
                                  (0.4, -0.3))


@pytest.mark.parametrize(("interp", "blend"), [("linear", "linear"), ("cubic", "linear"), ("spline", "linear"),
                                               pytest.param("lanczos", "linear", marks=pytest.mark.slow),
                                               ("spline", "multiband")])
def test_uniform_scene_stitches_to_a_uniform_panorama(uniform, tmp_path, interp, blend):
    """Distorted portrait lenses, camera B misaligned and offset, poles and seam: every pixel keeps the value."""
    value = UNIFORM
    merged = uniform
    s = mosaic(merged, tmp_path / "u.zarr", width=WIDTH, tile=128 if blend == "multiband" else 64, interp=interp,
               blend=blend, multiband_levels=3, workers=2)
    pano = PanoramaStore.open(tmp_path / "u.zarr").read(0)
    assert s["holes_px"] == 0 and np.isfinite(pano).all()
    np.testing.assert_allclose(pano, np.broadcast_to(value, pano.shape), rtol=2e-6 if blend == "linear" else 1e-4)


def test_known_scene_gives_the_known_panorama(known, tmp_path):
    merged, truth = known
    results = {}
    for interp in ("linear", "cubic", "spline"):
        mosaic(merged, tmp_path / "k.zarr", width=WIDTH, tile=64, interp=interp, overwrite=True, workers=2)
        results[interp] = psnr(PanoramaStore.open(tmp_path / "k.zarr").read(0), truth)
    # measured: linear 93, cubic 128, spline 116 (both near float32 rounding), lanczos 86 dB (Lanczos-3 does not
    # reproduce ramps exactly, so on smooth content it falls behind)
    assert results["linear"] > 85.0 and results["cubic"] > 110.0 and results["spline"] > 105.0
    assert min(results["spline"], results["cubic"]) > results["linear"] + 10.0


@pytest.mark.slow
def test_known_scene_with_lanczos(known, tmp_path):
    merged, truth = known
    mosaic(merged, tmp_path / "l.zarr", width=WIDTH, tile=64, interp="lanczos", workers=2)
    assert psnr(PanoramaStore.open(tmp_path / "l.zarr").read(0), truth) > 80.0


def test_pole_directions_are_covered_without_holes(tmp_path):
    """Rings at tilt ±35 (up to latitude ±82.5) plus one direction straight up and one straight down (tilt ±90):
    the caps beyond ±82.5 come from the pole directions alone."""
    directions = [(p + 15.0, t) for t in (-35.0, 35.0) for p in range(-180, 180, 30)] + [(0.0, 90.0), (0.0, -90.0)]
    merged = write_synthetic_merged(tmp_path / "m", smooth_scene, small_cameras(), directions)
    s = mosaic(merged, tmp_path / "pole.zarr", width=WIDTH, tile=64, workers=2)
    pano = PanoramaStore.open(tmp_path / "pole.zarr").read(0)
    assert s["holes_px"] == 0 and np.isfinite(pano).all()
    expected = smooth_panorama(WIDTH)
    for rows in (slice(0, 3), slice(-3, None)):  # the rows around the poles are right, not just filled
        assert psnr(pano[rows], expected[rows]) > 45.0


def test_seam_at_180_is_continuous(known, tmp_path):
    merged, truth = known
    mosaic(merged, tmp_path / "s.zarr", width=WIDTH, tile=64, workers=2)
    pano = PanoramaStore.open(tmp_path / "s.zarr").read(0)
    jump = np.abs(pano[:, 0] - pano[:, -1])
    expected_jump = np.abs(truth[:, 0] - truth[:, -1])
    assert np.abs(jump - expected_jump).max() < 0.02 * truth.max()
    err = np.abs(pano - truth).max(axis=(0, 2))
    assert max(err[0], err[-1]) < 3 * np.median(err) + 1e-3  # no worse at the seam than elsewhere


def test_render_tile_is_the_chunk_written(known, tmp_path):
    merged, _ = known
    mosaic(merged, tmp_path / "t.zarr", width=WIDTH, tile=64, workers=1)
    job = build_job(merged, tmp_path / "t.zarr", MosaicOptions(width=WIDTH, tile=64, interp="spline", blend="linear",
                                                               multiband_levels=4))
    tile, stats = render_tile(job, Rect(64, 128, 128, 192))
    np.testing.assert_array_equal(tile, PanoramaStore.open(tmp_path / "t.zarr").read(0, slice(64, 128),
                                                                                     slice(128, 192)))
    assert stats["n_sources"] > 0 and stats["holes"] == 0


def test_resume_after_an_interrupted_run(known, tmp_path):
    merged, _ = known
    ref = mosaic(merged, tmp_path / "ref.zarr", width=WIDTH, tile=64, workers=1)
    reference = PanoramaStore.open(tmp_path / "ref.zarr").read(0)

    class Stop(Exception):
        pass

    def stop_after_three(stage, done, total):
        if stage == "tiles" and done >= 3:
            raise Stop

    with pytest.raises(Stop):
        mosaic(merged, tmp_path / "r.zarr", width=WIDTH, tile=64, workers=1, progress=stop_after_three)
    store = PanoramaStore.open(tmp_path / "r.zarr")
    done = store.done_markers(0)
    assert 3 <= len(done) < ref["tiles"]
    # a chunk cut in the middle of its write: file present but no marker -> recomputed, not trusted
    ty, tx = next(t for t in [(0, 0), (0, 1), (1, 0), (1, 1), (0, 2)] if t not in done)
    chunk = store._chunk_file(0, ty, tx)
    assert chunk == tmp_path / "r.zarr" / "0" / "c" / "0" / str(ty) / str(tx)  # format 2: chunks (6, tile, tile)
    chunk.parent.mkdir(parents=True, exist_ok=True)
    chunk.write_bytes(b"\x00garbage")
    s = mosaic(merged, tmp_path / "r.zarr", width=WIDTH, tile=64, workers=1)
    assert s["tiles_skipped"] == len(done) and s["tiles_computed"] == ref["tiles"] - len(done)
    np.testing.assert_array_equal(PanoramaStore.open(tmp_path / "r.zarr").read(0), reference)
    for k in range(1, len(store.shapes)):
        np.testing.assert_array_equal(PanoramaStore.open(tmp_path / "r.zarr").read(k),
                                      PanoramaStore.open(tmp_path / "ref.zarr").read(k))


def test_resume_refuses_other_parameters(known, tmp_path):
    merged, _ = known
    mosaic(merged, tmp_path / "x.zarr", width=WIDTH, tile=64, region=(0, 64, 0, 64))
    for other in ({"interp": "linear"}, {"edge_model": False}):
        with pytest.raises(InputFileError, match="other inputs or parameters"):
            mosaic(merged, tmp_path / "x.zarr", width=WIDTH, tile=64, **other)
    s = mosaic(merged, tmp_path / "x.zarr", width=WIDTH, tile=64, interp="linear", overwrite=True)
    assert s["tiles_computed"] == s["tiles"]


def test_region_computes_only_its_tiles_and_later_runs_complete_the_pyramid(known, tmp_path):
    merged, _ = known
    s = mosaic(merged, tmp_path / "g.zarr", width=WIDTH, tile=64, region=(10, 60, 70, 130))
    assert s["tiles"] == 2 and s["tiles_computed"] == 2
    store = PanoramaStore.open(tmp_path / "g.zarr")
    assert np.isnan(store.read(0, slice(64, 128), slice(0, 64))).all()
    full = mosaic(merged, tmp_path / "g.zarr", width=WIDTH, tile=64)
    assert full["tiles_skipped"] == 2
    top = store.read(len(store.shapes) - 1)
    np.testing.assert_allclose(top, box_average_2x2(store.read(len(store.shapes) - 2), top.shape[:2]), rtol=1e-6)
    assert np.isfinite(top).all()


def test_local_cluster_gives_the_same_panorama(known, tmp_path):
    distributed = pytest.importorskip("distributed",
                                      reason="distributed is not installed (pip install 'omnispectral[cluster]')")
    merged, _ = known
    mosaic(merged, tmp_path / "local.zarr", width=WIDTH, tile=64, workers=2)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cl:
        s = mosaic(merged, tmp_path / "dist.zarr", width=WIDTH, tile=64, scheduler=cl.scheduler_address)
    assert s["tiles_computed"] == s["tiles"]
    a, b = PanoramaStore.open(tmp_path / "local.zarr"), PanoramaStore.open(tmp_path / "dist.zarr")
    for k in range(len(a.shapes)):
        np.testing.assert_array_equal(a.read(k), b.read(k))


def test_store_metadata_and_pyramid(known, tmp_path):
    merged, _ = known
    s = mosaic(merged, tmp_path / "m.zarr", width=WIDTH, tile=64)
    store = PanoramaStore.open(tmp_path / "m.zarr")
    attrs = store.attrs()
    meta = attrs["omnispectral"]
    assert meta["bands"] == ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"]
    assert len(meta["sensitivities"]) == 6 and len(meta["sensitivities"][0]) == len(meta["wavelength_nm"])
    assert meta["rig"]["name"] == "small" and meta["mosaic"]["interp"] == "spline" and meta["n_directions"] == 36
    assert meta["units"].startswith("DN per second")
    assert [d["path"] for d in attrs["ome"]["multiscales"][0]["datasets"]] == ["0", "1", "2"]
    assert s["levels"] == [[128, 256], [64, 128], [32, 64]] == [list(x) for x in pyramid_shapes(128, 256, 64)]
    level0, level1 = store.read(0), store.read(1)
    np.testing.assert_allclose(level1, level0.reshape(64, 2, 128, 2, 6).mean(axis=(1, 3)), rtol=1e-6)
    import zarr

    arr = zarr.open_array(str(tmp_path / "m.zarr" / "0"), mode="r")
    assert arr.chunks == (6, 64, 64) and arr.dtype == np.float32 and arr.metadata.zarr_format == 3
    assert arr.metadata.dimension_names == ("c", "y", "x")
    # rig TOML, cameras, sensitivities live in the metadata group, not in the image group's zarr.json
    # the root holds the OME metadata (with the six channel labels), the big metadata its own group
    assert (tmp_path / "m.zarr" / "zarr.json").stat().st_size < 6000 < (tmp_path / "m.zarr" / "omnispectral" /
                                                                         "zarr.json").stat().st_size
    np.testing.assert_array_equal(np.moveaxis(arr[:], 0, -1), level0)


# ------------------------------------------------------------------------------------------ inputs
def test_float16_encoding_keeps_the_hdr_range():
    img = np.exp(np.random.default_rng(6).uniform(np.log(4.0), np.log(2.7e8), (20, 30, 3))).astype(np.float32)
    stored, scale = encode_image(img, "float16")
    assert stored.dtype == np.float16 and np.log2(scale) == int(np.log2(scale))
    rel = np.abs(stored.astype(np.float32) * scale - img) / img
    assert rel.max() <= 2.0 ** -11
    stored32, scale32 = encode_image(img, "float32")
    assert scale32 == 1.0 and np.array_equal(stored32, img)
    # non-finite values are kept and do not set the scale; the stored values are the float32 product rounded once
    img[0, 0, 0], img[1, 1, 1], img[2, 2, 2] = np.nan, np.inf, -np.inf
    stored, scale_nf = encode_image(img, "float16")
    expected = (img * np.float32(1 / scale)).astype(np.float16)
    assert scale_nf == scale and np.array_equal(stored, expected, equal_nan=True)


def test_merged_directions_round_trip_and_crop_reads(tmp_path):
    cams = small_cameras()
    w = MergedDirectionsWriter.create(tmp_path / "m", cams, [{"index": 0, "pan_deg": 0, "tilt_deg": 0},
                                                            {"index": 1, "pan_deg": 30, "tilt_deg": 0}])
    img = np.random.default_rng(7).random((136, 256, 3)).astype(np.float32) * 1000
    w.add(0, 0.1, -0.2, {"A": img, "B": 2 * img}, {"B": (0.5, -0.25)})
    with pytest.raises(InputFileError, match="incomplete"):
        MergedDirections.open(tmp_path / "m")
    partial = MergedDirections.open(tmp_path / "m", require_complete=False)
    src = {s.camera: s for s in partial.sources()}
    assert src["B"].offset_px == (0.5, -0.25) and src["A"].pan_deg == 0.1 and src["A"].tilt_deg == -0.2
    np.testing.assert_allclose(src["A"].read((10, 20), (5, 9)), img[10:20, 5:9], rtol=2 ** -11)
    np.testing.assert_array_equal(read_npy_rows(src["B"].path, 3, 5), np.load(src["B"].path)[3:5])
    again = MergedDirectionsWriter.create(tmp_path / "m", cams, [{"index": 0}, {"index": 1}])  # resumes
    assert again.done() == {0}
    again.add(1, 30.0, 0.0, {"A": img, "B": img})
    merged = MergedDirections.open(tmp_path / "m")
    assert merged.meta["complete"] and len(merged.sources()) == 4
    with pytest.raises(InputFileError, match="another plan"):
        MergedDirectionsWriter.create(tmp_path / "m", cams, [{"index": 5}])


def test_bad_inputs_are_clear_errors(tmp_path):
    with pytest.raises(InputFileError, match="neither a capture session"):
        mosaic(tmp_path, tmp_path / "o.zarr")
    (tmp_path / "merged.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputFileError, match="format"):
        MergedDirections.open(tmp_path)


def test_camera_b_offset_is_applied(tmp_path):
    """Sources rendered with B shifted by (dx, dy): the engine with that offset recovers the scene, without it not."""
    truth = smooth_panorama(4 * WIDTH)
    dirs = grid_directions()
    shifted = write_synthetic_merged(tmp_path / "s", truth, small_cameras(), dirs, offset_b_px=(3.0, -2.0))
    meta = json.loads((tmp_path / "s" / "merged.json").read_text())
    for d in meta["directions"]:
        d["images"]["B"]["offset_px"] = [0.0, 0.0]
    (tmp_path / "n").mkdir()
    for f in (tmp_path / "s").glob("*.npy"):
        (tmp_path / "n" / f.name).symlink_to(f)
    (tmp_path / "n" / "merged.json").write_text(json.dumps(meta))
    expected = smooth_panorama(WIDTH)[..., 3:]
    mosaic(shifted, tmp_path / "a.zarr", width=WIDTH, tile=64)
    mosaic(tmp_path / "n", tmp_path / "b.zarr", width=WIDTH, tile=64)
    with_offset = psnr(PanoramaStore.open(tmp_path / "a.zarr").read(0)[..., 3:], expected)
    without = psnr(PanoramaStore.open(tmp_path / "b.zarr").read(0)[..., 3:], expected)
    assert with_offset > 50.0 and without < with_offset - 6.0


def test_gain_compensation_undoes_exposure_drift(tmp_path):
    truth = smooth_panorama(4 * WIDTH)
    dirs = grid_directions()
    drift = np.random.default_rng(8).uniform(0.85, 1.15, (len(dirs), 6))
    merged = write_synthetic_merged(tmp_path / "m", truth, small_cameras(), dirs, gains=drift)
    expected = smooth_panorama(WIDTH)
    plain = mosaic(merged, tmp_path / "a.zarr", width=WIDTH, tile=64)
    comp = mosaic(merged, tmp_path / "b.zarr", width=WIDTH, tile=64, gain_compensation=True)
    assert plain["holes_px"] == comp["holes_px"] == 0
    gains = np.array(PanoramaStore.open(tmp_path / "b.zarr").attrs()["omnispectral"]["mosaic"]["gains"])
    # the estimated gains undo the drift up to one common factor per band
    product = np.concatenate([gains[0::2] * drift[:, :3], gains[1::2] * drift[:, 3:]], axis=1)
    assert (product.std(axis=0) / product.mean(axis=0)).max() < 0.02
    a = PanoramaStore.open(tmp_path / "a.zarr").read(0)
    b = PanoramaStore.open(tmp_path / "b.zarr").read(0)
    # seams: the mean absolute horizontal gradient drops towards the scene's own
    grad = [np.abs(np.diff(x, axis=1)).mean() for x in (a, b, expected)]
    assert grad[1] - grad[2] < 0.5 * (grad[0] - grad[2])


def test_mounting_portrait_rig_models_are_used():
    cams = small_cameras()
    assert cams["A"].mounting.roll_deg == 90.0 and cams["B"].mounting == Mounting(
        roll_deg=90.0, misalignment_deg=(0.15, -0.08, 0.05), baseline_mm=(60.0, 0.0, 0.0))


class _Probe:
    """Counts the attribute look-ups that reach ``__getattr__`` (Dask's checks of a traversed argument do)."""

    looked_up = 0

    def __getattr__(self, name):
        type(self).looked_up += 1
        raise AttributeError(name)


@dataclasses.dataclass
class _SharedJob:
    sources: list


def _is_shared(shared, k):
    return shared is _SHARED_JOB, k


_SHARED_JOB = _SharedJob([_Probe() for _ in range(50)])


def test_run_tasks_hands_every_task_the_shared_object_untraversed():
    # Dask traverses a dataclass argument, item by item, for every task that takes it: ~0.4 ms per source per
    # task, which for the 7000 tiles x 2520 sources of a gigapixel panorama was hours of graph building.  The
    # tasks must get the one object (a graph node of its own) without Dask looking into it.
    _Probe.looked_up = 0
    results = run_tasks(_is_shared, _SHARED_JOB, [(k,) for k in range(6)], None, 2, None)
    assert sorted(results) == [(True, k) for k in range(6)]
    assert _Probe.looked_up == 0


def test_npy_headers_are_parsed_as_numpy_parses_them_without_its_ast():
    """The merged images' headers are read without ``ast.literal_eval`` (not thread-safe in CPython 3.11):
    the same shape, order and dtype as NumPy's reader, and the file positioned at the data; other layouts
    (a structured dtype) go to NumPy's parser."""
    import io

    from omnispectral.mosaic.sources import _npy_header

    arrays = [np.zeros((52, 96, 3), np.float16), np.zeros(5, np.float32), np.zeros((), np.int64),
              np.zeros((3, 4), ">f8"), np.asfortranarray(np.zeros((3, 4))), np.zeros((2, 3), [("a", "<f4")])]
    for a in arrays:
        ours, theirs = io.BytesIO(), io.BytesIO()
        np.save(ours, a)
        theirs.write(ours.getvalue())
        ours.seek(0)
        theirs.seek(0)
        shape, fortran, dtype = _npy_header(ours)
        np.lib.format.read_magic(theirs)
        assert (shape, fortran, dtype) == tuple(np.lib.format.read_array_header_1_0(theirs))
        assert ours.tell() == theirs.tell()


def _two_surface_sectors(rays):
    """Sectors 30° wide in longitude, alternately two surfaces with other colours in B than in A."""
    lon = np.degrees(np.arctan2(-rays[..., 0], rays[..., 2]))
    first = (np.floor(lon / 30.0) % 2 == 0)[..., None]
    return np.where(first, np.float32([1.0, 2.0, 1.0, 1.5, 3.0, 0.5]), np.float32([0.3, 0.2, 0.4, 0.1, 0.5, 0.2]))


def test_camera_b_at_edges_does_not_depend_on_the_tiling(tmp_path):
    """B's two surfaces mixed in A's share at the sectors' edges (mosaic.unmix): a tile's border pixels read the
    neighbouring tile's pixels through the halo, so tiles of 32 px give the panorama one tile of 256 px gives."""
    merged = write_synthetic_merged(tmp_path / "m", _two_surface_sectors, small_cameras(), grid_directions(),
                                    offset_b_px=(0.4, -0.3))
    panoramas, unmixed = [], []
    for tile in (32, 256):
        s = mosaic(merged, tmp_path / f"t{tile}.zarr", width=WIDTH, tile=tile, workers=1)
        panoramas.append(PanoramaStore.open(tmp_path / f"t{tile}.zarr").read(0))
        unmixed.append(s["unmixed_px"])
    assert unmixed[0] == unmixed[1] > 0
    np.testing.assert_allclose(panoramas[0], panoramas[1], rtol=1e-3, atol=1e-5)
