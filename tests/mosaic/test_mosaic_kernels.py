"""The mosaic engine's compiled kernels (Numba) against their NumPy definitions, and the whole engine with and
without them (the compiled kernels must not change the panorama)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import spline_filter1d

import omnispectral.mosaic.blending as blending
import omnispectral.mosaic.interp as interp
import omnispectral.mosaic.maps as maps
import omnispectral.mosaic.store as store
import omnispectral.mosaic.tile as tile
from omnispectral.errors import InputFileError
from omnispectral.mosaic import PanoramaStore, mosaic
from omnispectral.mosaic.kernels import compiled_kernels
from omnispectral.mosaic.sources import SourceImage, read_npy_window
from omnispectral.rig import load_preset, rig_toml
from omnispectral.sim.synthetic import write_synthetic_merged
from tests.mosaic.test_mosaic import WIDTH, grid_directions, small_cameras, smooth_panorama, smooth_scene

pytestmark = pytest.mark.skipif(compiled_kernels() is None, reason="Numba is not installed")
USERS = (interp, blending, maps, store, tile)  # the modules that call the kernels


@pytest.fixture
def numpy_only(monkeypatch):
    """Run the NumPy / OpenCV definitions instead of the compiled kernels."""

    def off():
        for module in USERS:
            monkeypatch.setattr(module, "compiled_kernels", lambda: None)

    return off


def hdr_image(rng, shape) -> np.ndarray:
    return (rng.random(shape) ** 6 * 1e4 + 1e-3).astype(np.float32)


def test_spline_prefilter_equals_the_recursive_filter():
    """The ±14-tap FIR equals SciPy's recursive B-spline filter (float64) to float32 rounding, borders included,
    and the interpolated coefficients give back the pixels."""
    rng = np.random.default_rng(0)
    img = hdr_image(rng, (70, 90, 3))
    ref = img.astype(np.float64)
    for axis in (0, 1):
        ref = spline_filter1d(ref, order=3, axis=axis, mode="mirror")
    coef = interp.spline_prefilter(img)
    assert coef.dtype == np.float32 and coef.shape == img.shape
    assert np.abs(coef - ref).max() <= 2e-6 * np.abs(ref).max()
    yy, xx = np.mgrid[0:70, 0:90].astype(np.float32)
    back = interp.remap(coef, xx, yy, "spline", prefiltered=True)
    # (the outermost pixels are read with replicated borders: the feathering weight is 0 there)
    np.testing.assert_allclose(back[1:-1, 1:-1], img[1:-1, 1:-1], rtol=1e-5, atol=1e-6 * img.max())
    small = hdr_image(rng, (9, 40, 2))  # smaller than the filter: the recursive filter
    assert np.array_equal(interp.spline_prefilter(small), spline_filter1d(
        spline_filter1d(small, order=3, axis=0, output=np.float32, mode="mirror"), order=3, axis=1,
        output=np.float32, mode="mirror"))


def test_spline_kernel_equals_the_definition_everywhere():
    """The compiled B-spline equals the 4 × 4-tap definition (remap_reference) inside, at and far beyond the
    borders (replicated), NaN at non-finite positions; and the OpenCV four-fetch form to its position rounding."""
    rng = np.random.default_rng(1)
    img = hdr_image(rng, (60, 80, 3))
    u = rng.uniform(-6, 86, (40, 50)).astype(np.float32)
    v = rng.uniform(-6, 66, (40, 50)).astype(np.float32)
    u[0, :4] = [np.nan, np.inf, 1e30, -1e30]
    v[1, :2] = [np.nan, -np.inf]
    got = interp.remap(img, u, v, "spline")
    ok = np.isfinite(u) & np.isfinite(v)
    assert np.isnan(got[~ok]).all() and np.isfinite(got[ok]).all()
    uc, vc = np.clip(u, -2, 81), np.clip(v, -2, 61)  # beyond 2 px every tap is the border pixel
    ref = interp.remap_reference(img, np.where(ok, uc, 0), np.where(ok, vc, 0), "spline")
    assert np.abs(got - ref)[ok].max() <= 2e-6 * img.max()
    coef = interp.spline_prefilter(img)
    fetches = interp._separable_fetches(coef, interp._spline_taps(uc), interp._spline_taps(vc), True)
    assert np.abs(got - fetches)[ok].max() <= 1e-4 * img.max()
    # other channel counts take the general loop: the same values as each channel alone
    for channels in ((0,), (2, 0), (0, 1, 2, 1, 0)):
        stacked = interp.remap(img[..., list(channels)], u, v, "spline")
        assert np.array_equal(stacked, got[..., list(channels)], equal_nan=True)



@pytest.mark.parametrize("method", ["cubic", "cubic-clamped"])
def test_keys_kernel_equals_the_definition_everywhere(method, numpy_only):
    """The compiled Keys cubic (and its clamp) equals the 4 × 4-tap definition (remap_reference) inside, at and far
    beyond the borders (replicated), NaN at non-finite positions; and the nine-fetch OpenCV path it replaced."""
    rng = np.random.default_rng(2)
    img = hdr_image(rng, (60, 80, 3))
    u = rng.uniform(-6, 86, (40, 50)).astype(np.float32)
    v = rng.uniform(-6, 66, (40, 50)).astype(np.float32)
    u[2, :6] = np.arange(6) + 0.5  # half-way between pixels, where the clamp and the cubic differ most
    u[0, :4] = [np.nan, np.inf, 1e30, -1e30]
    v[1, :2] = [np.nan, -np.inf]
    got = interp.remap(img, u, v, method)
    ok = np.isfinite(u) & np.isfinite(v)
    assert np.isnan(got[~ok]).all() and np.isfinite(got[ok]).all()
    uc, vc = np.where(ok, np.clip(u, -2, 81), 0), np.where(ok, np.clip(v, -2, 61), 0)
    ref = interp.remap_reference(img, uc, vc, method)
    assert np.abs(got - ref)[ok].max() <= 2e-6 * img.max()
    if method == "cubic-clamped":  # the clamp acted somewhere, and every value lies within its neighbours
        assert (interp.remap(img, u, v, "cubic") != got)[ok].any()
    for channels in ((0,), (2, 0), (0, 1, 2, 1, 0)):  # other channel counts: each channel as alone
        assert np.array_equal(interp.remap(img[..., list(channels)], u, v, method), got[..., list(channels)],
                              equal_nan=True)
    numpy_only()
    fetches = interp.remap(img, uc, vc, method)
    assert np.abs(got - fetches)[ok].max() <= 1e-4 * img.max()



def test_vote_kernel_rejects_the_same_views_as_the_numpy_median(numpy_only):
    """reject_inconsistent's compiled vote (insertion-sorted median of the voting views) drops exactly the views the
    NumPy nanmedian definition drops: odd and even counts of voters, uncovered and faint views, tiles with no
    three voters."""
    rng = np.random.default_rng(3)
    cases = []
    for n in (3, 4, 5, 6, 9):
        shape = (23, 31)
        values, weights, offsets = [], [], []
        for _ in range(n):
            h, w = rng.integers(10, 24), rng.integers(12, 32)
            r, c = rng.integers(0, shape[0] - h + 1), rng.integers(0, shape[1] - w + 1)
            v = (1 + 0.3 * rng.standard_normal((h, w, 3))).astype(np.float32)
            wt = rng.random((h, w)).astype(np.float32)
            wt[rng.random((h, w)) < 0.2] = 0.0
            wt[rng.random((h, w)) < 0.1] = 1e-6  # too faint to vote
            values.append(v)
            weights.append(wt)
            offsets.append((int(r), int(c)))
        cases.append((values, weights, offsets, shape))
    fast = [blending.reject_inconsistent(*case) for case in cases]
    numpy_only()
    slow = [blending.reject_inconsistent(*case) for case in cases]
    changed = 0
    for a, b, case in zip(fast, slow, cases, strict=True):
        for x, y, w in zip(a, b, case[1], strict=True):
            assert np.array_equal(x, y)
            changed += int((x != w).sum())
    assert changed > 100  # views were dropped: the comparison is not vacuous


def test_linear_blend_kernels_are_the_numpy_sums(numpy_only):
    rng = np.random.default_rng(2)
    parts = [((0, 1, 2), 3, 5, hdr_image(rng, (20, 30, 3)), rng.random((20, 30)).astype(np.float32)),
             ((3, 4, 5), 0, 0, hdr_image(rng, (32, 40, 3)), rng.random((32, 40)).astype(np.float32)),
             ((0, 1, 2), 10, 2, hdr_image(rng, (22, 38, 3)), np.zeros((22, 38), np.float32))]
    parts[1][4][:5] = 0.0

    def blend():
        acc = blending.LinearBlend((32, 40), 6)
        for bands, r, c, val, wt in parts:
            acc.add(bands, r, c, val, wt)
        return acc.numerator.copy(), acc.result()

    num_c, out_c = blend()
    numpy_only()
    num_n, out_n = blend()
    assert np.array_equal(num_c, num_n)
    assert np.array_equal(out_c, out_n, equal_nan=True) and np.isnan(out_c[:5, :, 3:]).all()


def test_map_feather_and_pyramid_kernels_are_the_numpy_results(numpy_only):
    rng = np.random.default_rng(3)
    nodes = rng.normal(size=(42, 52)) * 900.0
    nodes[3, 4] = np.nan
    rows, cols = maps.catmull_rom_weights(np.arange(0, 300), 8), maps.catmull_rom_weights(np.arange(5, 380), 8)
    u = rng.uniform(-50, 2100, (64, 80)).astype(np.float32)
    v = rng.uniform(-50, 1140, (64, 80)).astype(np.float32)
    u[0, 0], v[1, 1] = np.nan, np.inf
    src = hdr_image(rng, (63, 79, 6))
    src[rng.random(src.shape) < 0.3] = np.nan
    src[:2, :2] = np.nan
    compiled = (maps.interpolate_nodes(nodes, rows, cols), blending.feather_weight(u, v, 2048, 1088),
                store.box_average_2x2(src, (32, 40)))
    numpy_only()
    reference = (maps.interpolate_nodes(nodes, rows, cols), blending.feather_weight(u, v, 2048, 1088),
                 store.box_average_2x2(src, (32, 40)))
    for got, ref in zip(compiled, reference, strict=True):
        assert got.dtype == ref.dtype and np.array_equal(got, ref, equal_nan=True)
    assert np.isnan(compiled[2][0, 0]).all() and np.isfinite(compiled[2]).mean() > 0.95


def test_window_reads_are_the_array_slices(tmp_path):
    rng = np.random.default_rng(4)
    a = hdr_image(rng, (50, 60, 3))
    np.save(tmp_path / "a.npy", a)
    for rows, cols in [((3, 17), (5, 40)), ((0, 50), (0, 60)), ((49, 50), (59, 60)), ((45, 70), (-3, 10)), ((5, 5),
                                                                                                         (0, 3))]:
        got = read_npy_window(tmp_path / "a.npy", rows, cols)
        assert got.flags.writeable and got.flags.c_contiguous
        assert np.array_equal(got, a[max(0, rows[0]):rows[1], max(0, cols[0]):cols[1]])


def test_parallax_records_at_nearest_pixels_are_the_numpy_gather(tmp_path, numpy_only):
    """Camera B's float16 parallax records at A's nearest pixels: positions on .5 ties, off the sensor on every
    side, NaN and infinite; the same records with the kernels as with the NumPy gather."""
    rng = np.random.default_rng(8)
    h, w = 40, 56
    np.save(tmp_path / "p.npy", rng.uniform(-1, 2, (h, w, 3)).astype(np.float16))
    img = SourceImage(0, "B", 0.0, 0.0, tmp_path / "b.npy", parallax=tmp_path / "p.npy")
    u = rng.uniform(-3, w + 3, (23, 31)).astype(np.float32)
    v = rng.uniform(5, 20, (23, 31)).astype(np.float32)  # a window of rows, not the whole map
    u[0, :4], v[1, :4] = [np.nan, np.inf, -np.inf, 10.5], [np.nan, np.inf, -np.inf, 11.5]
    u[2, :3] = [0.5, 1.5, 2.5]
    np.save(tmp_path / "small.npy", np.zeros((h - 30, w, 3), np.float16))  # does not cover A's sensor
    small = SourceImage(0, "B", 0.0, 0.0, tmp_path / "b.npy", parallax=tmp_path / "small.npy")
    compiled = tile._records_at_nearest_pixels(img, u, v, w, h)
    for kernels in (True, False):
        if not kernels:
            numpy_only()
        with pytest.raises(InputFileError, match=r"small\.npy.*does not cover"):  # by name, never read beyond
            tile._records_at_nearest_pixels(small, u, v, w, h)
    plain = tile._records_at_nearest_pixels(img, u, v, w, h)
    assert compiled.dtype == plain.dtype == np.float32 and compiled.shape == (23, 31, 3)
    assert np.array_equal(compiled, plain)


def test_engine_gives_the_same_panorama_with_and_without_the_kernels(tmp_path, numpy_only):
    """The whole engine (B-spline, linear blending, camera B offset, pyramid) with the kernels against the NumPy /
    OpenCV path it replaced: equal to 2e-6 of the panorama's peak, and as close to the known scene."""
    rig = load_preset("small")
    merged = write_synthetic_merged(tmp_path / "merged", smooth_scene, small_cameras(rig), grid_directions(),
                                    offset_b_px=(0.4, -0.3), rig_name=rig.name, rig_toml=rig_toml(rig))
    mosaic(merged, tmp_path / "c.zarr", width=WIDTH, tile=64, workers=2)
    numpy_only()
    mosaic(merged, tmp_path / "n.zarr", width=WIDTH, tile=64, workers=2)
    truth = smooth_panorama(WIDTH)
    a, b = PanoramaStore.open(tmp_path / "c.zarr"), PanoramaStore.open(tmp_path / "n.zarr")
    for level in range(len(a.shapes)):
        x, y = a.read(level), b.read(level)
        assert np.array_equal(np.isfinite(x), np.isfinite(y))
        assert np.nanmax(np.abs(x - y)) <= 2e-6 * np.nanmax(y)
    x, y = a.read(0), b.read(0)
    err_c, err_n = np.abs(x - truth).max(), np.abs(y - truth).max()
    assert err_c <= 1.05 * err_n + 1e-6 * truth.max()


def test_canvas_rays_are_the_per_pixel_rays():
    """``Canvas.rays`` computes the trigonometry per row and per column: bit for bit the per-pixel rays,
    beyond the canvas too (over the poles, across the seam)."""
    canvas = maps.Canvas(952, 476)
    for rows, cols in [(np.arange(-20, 500), np.arange(-30, 990)), ([3.5], [7.25]),
                       (np.arange(0, 476, 8) - 8, np.arange(900, 1100, 8))]:
        col, row = np.meshgrid(np.asarray(cols, np.float64), np.asarray(rows, np.float64))
        got, ref = canvas.rays(rows, cols), canvas.rays_at(row, col)
        assert got.shape == ref.shape and np.array_equal(got, ref)


def test_kernels_compile_once_then_load_from_the_disk_cache():
    """Numba keys its disk cache on a kernel's closure: a kernel calling helpers held in closure cells compiled
    again in every process (~1 s per run).  A second process loads every kernel that calls helpers."""
    import subprocess
    import sys

    code = """if True:
        import numpy as np
        from omnispectral.imaging.distortion_kernel import compiled_undistort
        from omnispectral.mosaic.interp import remap
        from omnispectral.mosaic.kernels import compiled_kernels
        src = np.random.default_rng(0).random((16, 16, 3), dtype=np.float32)
        u = np.full((4, 4), 5.5, np.float32)
        for method in ("cubic", "cubic-clamped", "spline"):
            remap(src, u, u, method)
        x = np.linspace(-0.5, 0.5, 8)
        undistort = compiled_undistort()
        undistort(x, x, np.array([-0.3, 0.1] + [0.0] * 12), 1.0, 1e-12, 60, x.copy(), x.copy(), x.copy())
        k = compiled_kernels()
        print(sum(f.stats.cache_misses.get(s, 0) for f in (k.keys, k.spline, undistort) for s in f.signatures))
        """
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True) for _ in range(2)]
    assert int(runs[1].stdout.split()[-1]) == 0, runs[1]
