"""Adaptive supersampling of the simulator's pixels (omnispectral.sim.antialias): edges get their covered share."""

import datetime as dt

import numpy as np
import pytest

from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_ray
from omnispectral.rig import load_preset
from omnispectral.sim import truth
from omnispectral.sim.antialias import (
    differs_from_neighbours,
    lattice_offsets,
    pixels_to_refine,
    refined_mean,
    with_neighbours,
)
from omnispectral.sim.scenes.base import footprint_kwargs
from omnispectral.sim.scenes.build import build_scene
from omnispectral.sim.simulate import RigRenderer

NOON = dt.datetime(2026, 6, 21, 12, 0, tzinfo=dt.UTC)


def half_plane(normal, offset):
    """Renders 1 where ``normal · point > offset`` (a straight edge), as ``(N, 1)``."""
    return lambda points: (points @ np.asarray(normal) > offset).astype(np.float64)[:, None]


def exact_coverage(normal, offset, centre) -> float:
    """The share of the unit pixel around ``centre`` on the bright side, from a 2048 × 2048 grid of points."""
    sub = (np.arange(2048) + 0.5) / 2048 - 0.5
    y, x = np.meshgrid(sub + centre[1], sub + centre[0], indexing="ij")
    return float(np.mean(normal[0] * x + normal[1] * y > offset))


def grid_mean(fn, per_side: int) -> float:
    """The mean of ``fn`` over a ``per_side × per_side`` grid of points in the unit pixel around the origin."""
    sub = (np.arange(per_side) + 0.5) / per_side - 0.5
    y, x = np.meshgrid(sub, sub, indexing="ij")
    return float(fn(np.stack([x.ravel(), y.ravel()], axis=-1)).mean())


def test_lattice_offsets_put_every_point_in_a_column_and_row_of_its_own():
    for n in (16, 64, 256, 1000):
        offsets = lattice_offsets(n)
        assert offsets.shape == (n, 2)
        assert np.all(np.abs(offsets) < 0.5)
        for axis in (0, 1):
            np.testing.assert_allclose(np.sort(offsets[:, axis]), (np.arange(n) + 0.5) / n - 0.5, atol=1e-12)
    # the 64-point generator keeps its points apart: smallest distance at least 0.8 of a 64-point grid's 1/8
    d = np.linalg.norm(lattice_offsets(64)[:, None] - lattice_offsets(64)[None], axis=-1)
    assert np.min(d[~np.eye(64, dtype=bool)]) > 0.8 / 8


def test_refined_mean_gives_an_edge_its_covered_share():
    rng = np.random.default_rng(3)
    errors = {2: [], 8: [], "grid 8": []}
    axis_errors = {8: [], "grid 8": []}
    for k in range(80):
        angle = rng.uniform(0, np.pi) if k < 40 else rng.choice([0.0, 0.5 * np.pi])  # half along rows / columns
        normal = (np.cos(angle), np.sin(angle))
        offset = rng.uniform(-0.6, 0.6)
        exact = exact_coverage(normal, offset, (0.0, 0.0))
        fn = half_plane(normal, offset)
        found = {n: refined_mean(fn, np.zeros((1, 2)), n)[0, 0] for n in (2, 8)}
        found["grid 8"] = grid_mean(fn, 8)
        for n, value in found.items():
            (errors if k < 40 else axis_errors).get(n, []).append(abs(value - exact))
    # 2 x 2 points quantise the share to quarters; 64 lattice points to 1/64 along a row or column, where a
    # grid of 8 x 8 points quantises it to eighths; at other angles the two are alike (0.0085 and 0.0075 here)
    assert max(errors[2]) > 0.1
    assert max(errors[8]) < 0.05
    assert np.mean(errors[8]) < 0.25 * np.mean(errors[2])
    assert np.mean(errors[8]) < 1.5 * np.mean(errors["grid 8"])
    assert max(axis_errors[8]) < 0.5 / 64 + 1e-3
    assert np.mean(axis_errors["grid 8"]) > 3 * np.mean(axis_errors[8])


def test_pixels_to_refine_marks_disagreeing_rays_only():
    flat = np.full((1, 4, 3), 5.0)
    slight = flat * np.array([1.0, 1.01, 0.99, 1.0])[None, :, None]
    step = flat * np.array([1.0, 1.0, 0.2, 1.0])[None, :, None]
    dark_edge = np.zeros((1, 4, 3))
    dark_edge[0, 0, 2] = 1e-3  # a faint band on black: relative to its own mean
    assert pixels_to_refine(np.concatenate([flat, slight, step, dark_edge])).tolist() == [False, False, True, True]
    grown = with_neighbours(np.eye(1, 25, 12, dtype=bool)[0], 5, 5).reshape(5, 5)
    assert grown.sum() == 9 and grown[1:4, 1:4].all()
    at_seam = np.zeros((5, 5), bool)
    at_seam[2, 0] = True
    plain = with_neighbours(at_seam.ravel(), 5, 5).reshape(5, 5)
    wrapped = with_neighbours(at_seam.ravel(), 5, 5, wrap_columns=True).reshape(5, 5)
    assert plain.sum() == 6 and not plain[:, 4].any()
    assert wrapped.sum() == 9 and wrapped[1:4, 4].all() and wrapped[1:4, :2].all()


def test_differs_from_neighbours_marks_both_sides_of_a_step_between_pixels():
    means = np.ones((5, 6, 2))
    means[3:, :, 1] = 0.5  # a step between rows 2 and 3 in one band
    marked = differs_from_neighbours(means.reshape(-1, 2), 5, 6).reshape(5, 6)
    assert marked[2:4].all() and not marked[[0, 1, 4]].any()
    assert not differs_from_neighbours(np.ones((30, 3)) * [1.0, 1.04, 0.97], 5, 6).any()  # 4 % apart: left
    seam = np.ones((4, 5, 1))
    seam[:, 0] = 2.0
    plain = differs_from_neighbours(seam.reshape(-1, 1), 4, 5).reshape(4, 5)
    wrapped = differs_from_neighbours(seam.reshape(-1, 1), 4, 5, wrap_columns=True).reshape(4, 5)
    assert plain[:, :2].all() and not plain[:, 4].any() and wrapped[:, 4].all()
    valid = np.ones((5, 6), bool)
    valid[3:] = False  # the darker rows are outside the lens model: no pair across the step counts
    assert not differs_from_neighbours(means.reshape(-1, 2), 5, 6, valid=valid.ravel()).any()


@pytest.mark.parametrize("edge_row", [21, 24])  # inside a chunk of 8 rows, and at a chunk's first row
def test_truth_refines_an_edge_along_a_row_between_two_pixels_rays(edge_row):
    """A boundary of constant latitude 0.1 px below the top of a truth row: no pixel's 2 × 2 rays straddle it;
    the two rows beside it differ, so both are refined (across a chunk border too)."""
    width, height = 64, 32
    _, lat_edge = equirect_pixel_to_lonlat(np.array([0.0]), np.array([edge_row - 0.5 + 0.1]), width, height)
    bright_above = lonlat_to_ray(0.0, float(lat_edge[0]))[1]

    def fn(rays, spread):
        return np.where(rays[:, 1:2] > bright_above, 1.0, 0.2) * np.ones((1, 2))

    arr = np.empty((height, width, 2), np.float32)
    truth._fill_equirect(arr, fn, 8, supersample=2, height=height)
    exact = 0.1 * 1.0 + 0.9 * 0.2
    assert np.abs(arr[edge_row] - exact).max() <= 0.125 * 0.8 * 0.3  # a share of 1/8 of the rays, at most
    assert np.allclose(arr[edge_row - 1], 1.0) and np.allclose(arr[edge_row + 1], 0.2)
    with pytest.MonkeyPatch.context() as m:  # the contrast between pixels left out: 2 x 2 rays miss the edge
        m.setattr(truth, "differs_from_neighbours", lambda means, *a, **k: np.zeros(means.shape[0], bool))
        m.setattr(truth, "unlike_pairs", lambda a, b: np.zeros(a.shape[0], bool))
        plain = np.empty_like(arr)
        truth._fill_equirect(plain, fn, 8, supersample=2, height=height)
    assert np.abs(plain[edge_row] - exact).max() > 0.07


@pytest.fixture(scope="module")
def scene():
    return build_scene("procedural", None, NOON, seed=0)


def test_camera_edges_match_a_densely_sampled_frame(scene):
    """A frame of camera A with 2 × 2 rays refined to 64 at edges against 12 × 12 rays everywhere."""
    rig = load_preset("small")
    frames = {}
    for key, kwargs in {"refined": {}, "plain": {"refine_per_side": 0},
                        "dense": {"supersample": 12, "refine_per_side": 0}}.items():
        r = RigRenderer(rig, scene, noise=False, electrons_per_unit=1.0, **kwargs)
        frames[key] = r.electrons_per_second("A", 150.0, -40.0).astype(np.float64)
    dense = frames["dense"]
    edges = np.abs(frames["plain"] - dense).max(axis=2) > 0.05 * dense.max(axis=2)
    assert edges.sum() > 50  # the frame has edges the 2 x 2 rays miss

    def nrmse(img):
        return np.sqrt(((img - dense)[edges] ** 2).sum() / (dense[edges] ** 2).sum())

    assert nrmse(frames["plain"]) > 0.05
    assert nrmse(frames["refined"]) < 0.3 * nrmse(frames["plain"])


def test_truth_edges_match_a_densely_sampled_truth(scene, monkeypatch):
    """Rows of the demo's 952-px truth across the sunlit white plate's edges against 12 × 12 points per pixel."""
    rig = load_preset("small")
    r = RigRenderer(rig, scene, noise=False, electrons_per_unit=1.0)
    matrix = r.system.matrix
    width, rows = 952, (356, 384)

    def render(supersample):
        arr = np.empty((rows[1] - rows[0], width, matrix.shape[0]), np.float32)
        truth._fill_equirect(arr, lambda rays, spread: scene.band_radiance(
            rays, matrix, sun_disk=False, **footprint_kwargs(scene, spread)), 16, supersample=supersample,
            row_offset=rows[0], height=width // 2)
        return arr.astype(np.float64)

    refined = render(2)
    with monkeypatch.context() as m:
        m.setattr(truth, "REFINE_RAYS_PER_SIDE", 2)
        plain = render(2)
        dense = render(12)
    edges = np.abs(plain - dense).max(axis=2) > 0.05 * dense.max(axis=2)
    assert edges.sum() > 50

    def nrmse(img):
        return np.sqrt(((img - dense)[edges] ** 2).sum() / (dense[edges] ** 2).sum())

    assert nrmse(plain) > 0.05
    assert nrmse(refined) < 0.3 * nrmse(plain)
