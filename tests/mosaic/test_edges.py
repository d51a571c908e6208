"""Partial-area resampling at straight edges (omnispectral.mosaic.edges)."""

import numpy as np
import pytest

from omnispectral.mosaic.edges import area_share, area_share_offset, resample_edges
from omnispectral.mosaic.interp import remap

BRIGHT = np.array([900.0, 400.0, 150.0])
DARK = np.array([60.0, 45.0, 30.0])
SUBSAMPLES = 41


def _box_samples(inside, shape, origin, side=1.0):
    """Each pixel's share of ``inside(x, y)`` (bool), by SUBSAMPLES² points: pixel ``(r, c)`` is the square of
    ``side`` centred at ``origin + side * (c, r)``."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]]
    g = ((np.arange(SUBSAMPLES) + 0.5) / SUBSAMPLES - 0.5) * side
    x = origin[0] + side * cols[..., None, None] + g[None, None, None, :]
    y = origin[1] + side * rows[..., None, None] + g[None, None, :, None]
    return inside(x, y).mean(axis=(-2, -1))


def _colour(share):
    return (DARK + share[..., None] * (BRIGHT - DARK)).astype(np.float32)


def _rms(x, truth):
    return float(np.sqrt(((x - truth) ** 2).mean()))


@pytest.mark.parametrize(("a", "b", "s"), [(1.0, 0.0, 0.2), (0.8, 0.6, -0.3), (0.3, 0.95, 0.6), (2.0, -0.5, 0.4),
                                           (0.707, 0.707, 0.05)])
def test_area_share_is_the_half_planes_share_of_the_square(a, b, s):
    w = np.random.default_rng(0).uniform(-0.5, 0.5, (400_000, 2))
    share = float(area_share(np.array(s), np.array(a), np.array(b)))
    assert abs(share - np.mean(a * w[:, 0] + b * w[:, 1] < s)) < 3e-3
    assert float(area_share_offset(np.array(share), np.array(a), np.array(b))) == pytest.approx(s, abs=1e-9)


@pytest.mark.parametrize("side", [1.0, 0.8])
@pytest.mark.parametrize("angle", [0.0, 0.3, 0.785, 1.2, 2.5])
def test_a_slanted_step_gets_each_output_pixels_share(angle, side):
    """A straight edge box-sampled by the source; output pixels at another phase (and, with ``side`` 0.8, a
    smaller footprint): the interpolation errs by up to a sixth of the contrast; the edge model by < 3 %."""
    normal = np.array([np.cos(angle), np.sin(angle)])

    def bright(x, y):
        return normal[0] * x + normal[1] * y < normal @ [20.3, 19.6]

    src = _colour(_box_samples(bright, (40, 40), (0.0, 0.0)))
    origin = (4.37, 4.21)
    n = int(31 / side)
    rows, cols = np.mgrid[0:n, 0:n]
    u, v = (origin[0] + side * cols).astype(np.float32), (origin[1] + side * rows).astype(np.float32)
    truth = _colour(_box_samples(bright, (n, n), origin, side))
    values = remap(src, u, v, "cubic-clamped")
    before = values.copy()
    moved = resample_edges(src, u, v, values, np.ones(u.shape, bool))
    assert moved > 0
    assert _rms(values, truth) < _rms(before, truth) / 5
    assert np.abs(values - truth).max() < 0.03 * (BRIGHT - DARK).max()


def test_texture_and_a_thin_wire_keep_their_interpolated_values():
    """Where no straight edge between two flat surfaces explains the 3 × 3 window, nothing moves: random
    texture, and a dark wire narrower than a pixel."""
    rng = np.random.default_rng(1)
    rows, cols = np.mgrid[0:24, 0:24]
    u, v = (3.4 + cols).astype(np.float32), (3.3 + rows).astype(np.float32)
    texture = rng.lognormal(6.0, 0.5, (32, 32, 3)).astype(np.float32)
    values = remap(texture, u, v, "cubic-clamped")
    assert resample_edges(texture, u, v, values.copy(), np.ones(u.shape, bool)) == 0

    for width_px in (0.5, 0.9):
        wire = _colour(_box_samples(lambda x, y, w=width_px: np.abs(x - 15.8) > w / 2, (32, 32), (0.0, 0.0)))
        values = remap(wire, u, v, "cubic-clamped")
        before = values.copy()
        resample_edges(wire, u, v, values, np.ones(u.shape, bool))
        core = np.abs(u - 15.8) < 1.6
        np.testing.assert_array_equal(values[core], before[core])


@pytest.mark.parametrize("turn_rad", [0.0, 0.2, 0.6])
def test_a_squares_corners_and_sides_get_their_share(turn_rad):
    """At a corner no straight edge fits the window, or one does loosely; the wedge of the two sides' edges
    fits: the corners' error falls below 0.6× the interpolation's at every phase (0.81–1.18× with straight
    edges alone), the whole square's below 0.3× (0.43–0.61×)."""
    c, s = np.cos(turn_rad), np.sin(turn_rad)

    def inside(x, y):
        return (np.abs(c * (x - 15.6) + s * (y - 16.2)) < 6.3) & (np.abs(-s * (x - 15.6) + c * (y - 16.2)) < 6.3)

    rows, cols = np.mgrid[0:24, 0:24]
    for phase in [(0.4, 0.3), (0.1, 0.45), (0.25, 0.05), (0.5, 0.5)]:
        u, v = (3 + phase[0] + cols).astype(np.float32), (3 + phase[1] + rows).astype(np.float32)
        square = _colour(_box_samples(inside, (32, 32), (0.0, 0.0)))
        truth = _colour(_box_samples(inside, u.shape, (3 + phase[0], 3 + phase[1])))
        values = remap(square, u, v, "cubic-clamped")
        before = values.copy()
        resample_edges(square, u, v, values, np.ones(u.shape, bool))
        corners = np.zeros(u.shape, bool)
        for sx in (-1, 1):
            for sy in (-1, 1):
                cx, cy = 15.6 + 6.3 * (c * sx - s * sy), 16.2 + 6.3 * (s * sx + c * sy)
                corners |= (np.abs(u - cx) < 1.6) & (np.abs(v - cy) < 1.6)
        assert _rms(values[corners], truth[corners]) < 0.6 * _rms(before[corners], truth[corners])
        assert _rms(values, truth) < 0.3 * _rms(before, truth)


PLATE, GROUND, SHADOW = BRIGHT, np.array([200.0, 150.0, 100.0]), np.array([40.0, 35.0, 30.0])


def _plate_on_its_shadow(turn_rad):
    """Box samples of a bright wedge (a plate's corner, 17° wide) whose lower side casts a shadow on the ground:
    three surfaces meeting at ``(16.3, 15.7)``, turned by ``turn_rad``."""
    c, s = np.cos(turn_rad), np.sin(turn_rad)

    def regions(x, y):
        xr, yr = c * (x - 16.3) + s * (y - 15.7), -s * (x - 16.3) + c * (y - 15.7)
        plate = (xr > 0) & (yr < 0.3 * xr)
        return plate, ~plate & (yr > -0.8 * xr) & (yr > 0.3 * xr)

    def render(shape, origin):
        plate = _box_samples(lambda x, y: regions(x, y)[0], shape, origin)
        shadow = _box_samples(lambda x, y: regions(x, y)[1], shape, origin)
        return (plate[..., None] * PLATE + shadow[..., None] * SHADOW
                + (1.0 - plate - shadow)[..., None] * GROUND).astype(np.float32)

    return render


@pytest.mark.parametrize("turn_rad", [0.0, 0.4, 1.3, 2.5])
def test_where_three_surfaces_meet_each_gets_its_share(turn_rad):
    """A plate's corner lying on the edge of its own shadow: no model between two surfaces fits the windows at the
    junction; the plate's wedge and the shadow's edge, taken from the straight edges around, do. The junction's
    error falls below 0.5× the interpolation's at every phase (0.03–0.45× measured; 0.45–0.98× with two-surface
    models alone), the whole scene's below 0.25× (0.06–0.22×; 0.15–0.49× before)."""
    render = _plate_on_its_shadow(turn_rad)
    rows, cols = np.mgrid[0:24, 0:24]
    src = render((32, 32), (0.0, 0.0))
    for phase in [(0.4, 0.3), (0.1, 0.45), (0.25, 0.05)]:
        u, v = (3 + phase[0] + cols).astype(np.float32), (3 + phase[1] + rows).astype(np.float32)
        truth = render(u.shape, (3 + phase[0], 3 + phase[1]))
        values = remap(src, u, v, "cubic-clamped")
        before = values.copy()
        resample_edges(src, u, v, values, np.ones(u.shape, bool))
        junction = (np.abs(u - 16.3) < 2.6) & (np.abs(v - 15.7) < 2.6)
        assert _rms(values[junction], truth[junction]) < 0.5 * _rms(before[junction], truth[junction])
        assert _rms(values, truth) < 0.25 * _rms(before, truth)


def test_unused_and_invalid_pixels_are_left_alone():
    def bright(x, y):
        return x < 12.4

    src = _colour(_box_samples(bright, (24, 24), (0.0, 0.0)))
    rows, cols = np.mgrid[0:16, 0:16]
    u, v = (4.3 + cols).astype(np.float32), (4.2 + rows).astype(np.float32)
    values = remap(src, u, v, "cubic-clamped")
    before = values.copy()
    used = np.zeros(u.shape, bool)
    assert resample_edges(src, u, v, values, used) == 0
    bad = np.zeros(src.shape[:2], bool)
    bad[:, 11:14] = True  # the edge's pixels themselves are not valid: no edge to model
    assert resample_edges(src, u, v, values, ~used, bad) == 0
    np.testing.assert_array_equal(values, before)


def test_the_compiled_kernel_finds_the_numpy_definitions_edges():
    """``kernels.edge_models``, ``kernels.corner_models`` and ``kernels.three_surface_models`` against the NumPy
    path (:func:`omnispectral.mosaic.edges._edge_models` with ``compiled=False``) on noisy slanted steps, a square,
    two plates on their shadows and texture: the same pixels get a model (the square's corners a wedge, the
    junctions three surfaces), and its sides and surfaces agree to rounding."""
    from omnispectral.mosaic import edges
    from omnispectral.mosaic.kernels import compiled_kernels

    if compiled_kernels() is None:
        pytest.skip("Numba is not installed")
    rng = np.random.default_rng(3)
    scenes = [_colour(_box_samples(lambda x, y, a=a: np.cos(a) * x + np.sin(a) * y < 30.0, (48, 48), (0.0, 0.0)))
              for a in (0.1, 0.7, 1.9, 3.5)]
    scenes.append(_colour(_box_samples(lambda x, y: (np.abs(x - 20.3) < 9.1) & (np.abs(y - 23.8) < 7.4), (48, 48),
                                       (0.0, 0.0))))
    scenes += [_plate_on_its_shadow(turn)((32, 32), (0.0, 0.0)) for turn in (0.4, 2.5)]
    scenes.append(rng.lognormal(6.0, 0.4, (48, 48, 3)).astype(np.float32))
    n_models = n_corners = n_three = 0
    for scene in scenes:
        noisy = (scene * rng.normal(1.0, 0.004, scene.shape)).astype(np.float32)
        compiled, reference = edges._edge_models(noisy, None), edges._edge_models(noisy, None, compiled=False)
        assert (compiled is None) == (reference is None)
        if compiled is None:
            continue
        np.testing.assert_array_equal(compiled[0], reference[0])
        np.testing.assert_array_equal(compiled[1], reference[1])
        for got, want in zip(compiled[2:], reference[2:], strict=True):
            finite = np.isfinite(want)
            np.testing.assert_array_equal(got[~finite], want[~finite])
            np.testing.assert_allclose(got[finite], want[finite], rtol=1e-9, atol=1e-9)
        n_models += len(reference[1])
        n_corners += int(np.isfinite(reference[2][:, 5]).sum())
        n_three += int(np.isfinite(reference[5][:, 2]).sum())
    assert n_models > 300
    assert n_corners >= 4  # the square's
    assert n_three >= 10  # the junctions' windows


def test_area_resampling_a_box_sampled_edge_is_not_the_box_of_the_coarser_grid():
    """Why a truth rendered on another grid (the report's ``truth_grid``) is not the reference for edges: area
    resampling of box samples spreads each edge pixel's mix over its area, an eighth of the contrast and more off the
    coarser grid's own box samples here, where the edge model on the sensor's samples errs by < 3 %."""
    import cv2

    from omnispectral.product.report import _truth_grid_note

    def bright(x, y):
        return np.cos(0.4) * x + np.sin(0.4) * y < 20.0

    fine = _box_samples(bright, (50, 50), (0.0, 0.0))
    coarse = _box_samples(bright, (40, 40), (0.125, 0.125), side=1.25)  # the same scene on a 1.25× grid
    resampled = cv2.resize(fine.astype(np.float32), (40, 40), interpolation=cv2.INTER_AREA)
    assert np.abs(resampled - coarse).max() > 0.12
    assert _truth_grid_note(50, 50) == {"width": 50, "resampled": False}
    note = _truth_grid_note(50, 40)
    assert note["resampled"] and "50 px" in note["note"] and "40 px" in note["note"]


@pytest.mark.parametrize("union", [False, True])
def test_a_wedges_share_of_a_footprint_is_its_clipped_area(union):
    """The share of a slanted parallelogram in a wedge (and, with ``union``, in the union of the half-planes),
    compiled and NumPy alike, against 400 000 random points of the footprint."""
    from omnispectral.mosaic import edges
    from omnispectral.mosaic.kernels import compiled_kernels

    rng = np.random.default_rng(5)
    wedge = np.array([np.cos(0.3), np.sin(0.3), 0.2, np.cos(2.0), np.sin(2.0), -0.1, float(union)])
    jac = np.array([[0.9, -0.3], [0.4, 0.7]])
    centre = np.array([0.15, -0.2])
    w = rng.uniform(-0.5, 0.5, (400_000, 2))
    points = centre + w @ jac.T
    inside = [(points @ wedge[0:2] < wedge[2]), (points @ wedge[3:5] < wedge[5])]
    want = np.mean(inside[0] | inside[1]) if union else np.mean(inside[0] & inside[1])
    assert 0.1 < want < 0.9
    args = (np.array([centre[0]]), np.array([centre[1]]), jac[None], wedge[None])
    reference = edges._footprint_shares(*args, compiled=False)
    assert abs(reference[0] - want) < 3e-3
    if compiled_kernels() is not None:
        np.testing.assert_allclose(edges._footprint_shares(*args), reference, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["half-plane", "wedge", "union"])
def test_a_footprints_shares_of_three_regions_are_their_clipped_areas(kind):
    """A three-surface model's regions ``X`` (a half-plane, a wedge or a union of two half-planes) and ``Y``
    (outside ``X``, inside the split): the shares of a slanted parallelogram, compiled and NumPy alike, against
    400 000 random points of the footprint."""
    from omnispectral.mosaic import edges
    from omnispectral.mosaic.kernels import compiled_kernels

    rng = np.random.default_rng(7)
    second = (np.inf, 0.0) if kind == "half-plane" else (-0.1, float(kind == "union"))
    wedge = np.array([np.cos(0.3), np.sin(0.3), 0.2, np.cos(2.0), np.sin(2.0), second[0], second[1]])
    if kind == "half-plane":
        wedge[3:5] = (1.0, 0.0)
    if kind == "union":
        wedge[[2, 5]] = (-0.25, -0.35)
    split = np.array([np.cos(-1.2), np.sin(-1.2), 0.05])
    jac = np.array([[0.9, -0.3], [0.4, 0.7]])
    centre = np.array([0.15, -0.2])
    points = centre + rng.uniform(-0.5, 0.5, (400_000, 2)) @ jac.T
    one, two = points @ wedge[0:2] < wedge[2], points @ wedge[3:5] < wedge[5]
    x = one if kind == "half-plane" else (one | two if kind == "union" else one & two)
    want = np.array([x.mean(), (~x & (points @ split[:2] < split[2])).mean()])
    assert (want > 0.05).all() and want.sum() < 0.95
    args = (np.array([centre[0]]), np.array([centre[1]]), jac[None], wedge[None], split[None])
    reference = edges._footprint_region_shares(*args, compiled=False)
    np.testing.assert_allclose(reference[0], want, atol=3e-3)
    if compiled_kernels() is not None:
        np.testing.assert_allclose(edges._footprint_region_shares(*args), reference, rtol=1e-12, atol=1e-12)
