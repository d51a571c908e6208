"""Camera B's bands where B saw nothing: the prior's predictor (spectral.conditional) and its neighbourhood
adaptation (mosaic.predict)."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.mosaic.predict import fill_missing_b, tile_predictor
from omnispectral.spectral.conditional import BandPredictor, b_from_a_predictor


@pytest.fixture(scope="module")
def estimator():
    from omnispectral.product.estimator import rig_estimator
    from omnispectral.rig import load_preset

    return rig_estimator(load_preset("small"))[0]


def test_prior_predictor_equals_least_squares_on_samples_of_the_prior(estimator):
    rng = np.random.default_rng(0)
    k = rng.choice(len(estimator.weights), size=40000, p=estimator.weights)
    chol = np.linalg.cholesky(estimator.covariances + 1e-12 * np.eye(estimator.covariances.shape[1]))
    z = rng.standard_normal((k.size, estimator.means.shape[1]))
    signals = estimator.means[k] + np.einsum("kij,kj->ki", chol[k], z)
    bands = signals @ estimator.system_matrix.T
    m_lstsq, *_ = np.linalg.lstsq(bands[:, :3], bands[:, 3:], rcond=None)
    resid = bands[:, 3:] - bands[:, :3] @ m_lstsq
    pred = b_from_a_predictor(estimator)
    np.testing.assert_allclose(pred.matrix, m_lstsq.T, rtol=0.05, atol=0.05 * np.abs(pred.matrix).max())
    rel = np.sqrt((resid ** 2).mean(axis=0) / (bands[:, 3:] ** 2).mean(axis=0))
    np.testing.assert_allclose(pred.rel_std, rel, rtol=0.05)
    back = BandPredictor.from_dict(pred.to_dict())
    np.testing.assert_array_equal(back.matrix, pred.matrix)
    np.testing.assert_array_equal(back.rel_std, pred.rel_std)


def _two_surfaces(shape=(40, 60)):
    """Left half: a = (1, 2, 1), b = 1.5 · M a; right half: a = (2, 1, 1) · 3, b = 0.6 · M a (M = identity)."""
    h, w = shape
    img = np.zeros((h, w, 6), np.float32)
    img[:, : w // 2, :3] = (1.0, 2.0, 1.0)
    img[:, w // 2:, :3] = (6.0, 3.0, 3.0)
    img[:, : w // 2, 3:] = 1.5 * img[:, : w // 2, :3]
    img[:, w // 2:, 3:] = 0.6 * img[:, w // 2:, :3]
    return img


def test_missing_b_is_predicted_from_the_surface_that_looks_alike_in_a():
    img = _two_surfaces()
    truth = img.copy()
    missing = np.zeros(img.shape[:2], bool)
    missing[10:20, 25:35] = True  # straddles the edge between the two surfaces
    img[missing, 3:] = np.nan
    prior = BandPredictor(np.eye(3), np.full(3, 0.4))
    rel = fill_missing_b(img, missing, prior)
    assert np.isfinite(img).all()
    err = np.abs(img[missing, 3:] - truth[missing, 3:]) / truth[missing, 3:]
    assert err.max() < 1e-4  # each side takes its own surface's ratio (1.5 or 0.6), never the mix
    assert np.isfinite(rel[missing]).all() and not np.isfinite(rel[~missing]).any()
    assert rel[missing].max() < 0.4 * 0.5  # many agreeing neighbours: well below the prior's error


def test_without_neighbours_the_prior_stands_with_its_error():
    img = _two_surfaces((30, 30))
    missing = np.ones(img.shape[:2], bool)
    img[..., 3:] = np.nan
    prior = BandPredictor(np.diag([2.0, 1.0, 0.5]), np.array([0.1, 0.3, 0.2]))
    rel = fill_missing_b(img, missing, prior)
    np.testing.assert_allclose(img[..., 3:], img[..., :3] * np.array([2.0, 1.0, 0.5]), rtol=1e-6)
    np.testing.assert_allclose(rel, 0.3)


def test_b_outside_camera_a_coverage_is_dropped_and_a_tile_fits_its_own_predictor():
    img = _two_surfaces()
    img[:5, :, :3] = np.nan  # camera A covers nothing there: neither camera counts
    missing = ~np.isfinite(img[..., 3:]).all(axis=-1)
    missing[20, 5] = True
    img[20, 5, 3:] = np.nan
    fill_missing_b(img, missing, None)
    assert not np.isfinite(img[:5]).any()
    np.testing.assert_allclose(img[20, 5, 3:], 1.5 * img[20, 5, :3], rtol=1e-3)
    assert tile_predictor(np.ones((10, 3)), np.ones((10, 3))) is None  # too few pixels to fit


def test_b_from_another_surface_than_a_is_flagged_but_an_unusual_colour_is_not():
    from omnispectral.mosaic.predict import implausible_b

    img = _two_surfaces((60, 80))
    prior = BandPredictor(np.eye(3), np.full(3, 0.4))
    img[10:40, 30:33, 3:] *= 250.0  # B sees the sun past a thin pole that A sees
    flagged = implausible_b(img, prior)
    assert flagged[10:40, 30:33].all() and flagged.sum() == 90
    exotic = _two_surfaces((60, 80))
    exotic[..., 3:] *= 20.0  # a colour far from the prior, but the whole surface: its own neighbourhood agrees
    assert not implausible_b(exotic, prior).any()
    assert not implausible_b(img, None).any()  # no predictor, no test


@pytest.mark.parametrize("code", [1.0, 2.0])
def test_b_that_shows_another_surface_is_not_used_but_predicted(tmp_path, code):
    """Every direction's camera B shows another (five times brighter) surface on the left half of its frame.
    Flagged hidden (1) those views still count where no direction sees the surface, and some pixels keep the
    wrong bands; flagged as showing another surface (2) they are never used: those pixels are predicted from
    A and their neighbours, and every covered pixel holds B's true bands."""
    from omnispectral.capture.plan import direction_grid
    from omnispectral.mosaic import PanoramaStore, mosaic
    from omnispectral.mosaic.sources import MergedDirectionsWriter
    from omnispectral.rig import camera_model, load_preset
    from omnispectral.sim.synthetic import render_scene

    model = camera_model(load_preset("small"), "A")
    value = np.asarray([1.0, 2.0, 3.0, 2.0, 3.0, 1.0], np.float32)

    def scene(rays):
        return np.broadcast_to(value, (*rays.shape[:-1], 6)).copy()

    dirs = [(d.pan_deg, d.tilt_deg) for d in direction_grid(12, 3)]
    writer = MergedDirectionsWriter.create(tmp_path / "m", {"A": model, "B": model},
                                           [{"index": k, "pan_deg": p, "tilt_deg": t} for k, (p, t) in enumerate(dirs)])
    for k, (pan, tilt) in enumerate(dirs):
        a, b = (render_scene(scene, model, cam, pan, tilt, (0.0, 0.0)) for cam in "AB")
        b[:, : model.width // 2] *= 5.0
        writer.add(k, pan, tilt, {"A": a, "B": b})
        record = np.zeros((model.height, model.width, 3), np.float32)
        record[..., 1] = 1.0
        record[:, : model.width // 2 + 2, 2] = code
        writer.save_parallax(k, record, {})
    mosaic(writer.close(), tmp_path / "p.zarr", width=256, tile=64, interp="linear", progress=False)
    bands = PanoramaStore.open(tmp_path / "p.zarr").read(0)
    covered = np.isfinite(bands[..., :3]).all(axis=-1)
    assert covered.mean() > 0.9 and np.isfinite(bands[covered]).all()
    worst = float(np.abs(bands[covered][:, 3:] / value[3:] - 1.0).max())
    if code == 2.0:
        assert worst < 1e-3
    else:
        assert worst > 1.0


def test_b_darker_than_a_allows_is_flagged_unless_b_may_be_clipped():
    from omnispectral.mosaic.predict import b_outliers, too_dark_b

    prior = BandPredictor(np.eye(3), np.full(3, 0.4))
    img = _two_surfaces((60, 80))
    img[10:40, 30:34, 3:] /= 140.0  # B shows a dark post's edge fattened 4 px into the bright sky A sees
    bright, dark = b_outliers(img, prior)
    assert dark[10:40, 30:34].all() and dark.sum() == 120 and not bright.any()
    np.testing.assert_array_equal(too_dark_b(img, prior), dark)
    clipped = _two_surfaces((60, 80))
    clipped[10:40, 30:34, 3:] = clipped[..., 3:].max()  # B at its brightest: a lower bound, A brighter still
    clipped[10:40, 30:34, :3] *= 1000.0
    assert not too_dark_b(clipped, prior).any()
    exotic = _two_surfaces((60, 80))
    exotic[..., 3:] /= 20.0  # a whole surface far from the prior: its own neighbourhood agrees
    assert not too_dark_b(exotic, prior).any()
    # filled from the sky's own neighbours, not kept below what B measured
    missing = ~np.isfinite(img[..., 3]) | dark
    fill_missing_b(img, missing, prior)
    np.testing.assert_allclose(img[10:40, 30:34, 3:], _two_surfaces((60, 80))[10:40, 30:34, 3:], rtol=0.02)


def test_the_ceiling_of_a_too_dark_b_is_the_brightest_b_measured_around_it():
    from omnispectral.mosaic.predict import IMPLAUSIBLE_WINDOW_PX, brightest_measured_b

    img = _two_surfaces((60, 80))
    missing = np.zeros((60, 80), bool)
    missing[30, 20] = True
    img[30, 20, 3:] = 1e6  # a missing pixel's value never counts
    img[10, 10, 3:] = np.nan
    ceiling = brightest_measured_b(img, missing)
    half = IMPLAUSIBLE_WINDOW_PX // 2
    window = img[30 - half:30 + half + 1, 20 - half:20 + half + 1, 3:].copy()
    window[half, half] = 0.0
    np.testing.assert_allclose(ceiling[30, 20], np.nanmax(window.reshape(-1, 3), axis=0), rtol=1e-6)
    assert ceiling[30, 20].max() < 1e6


def _sky_with_a_post(shape=(40, 60)):
    """A smooth 'sky' (A rising left to right, B = 1.2 A), the pixels B cannot see beside a post (x = 30..33,
    missing) and the post (x = 34..39: A reddish and dark, B = 0.8 A)."""
    h, w = shape
    img = np.zeros((h, w, 6), np.float32)
    ramp = np.linspace(1.0, 3.0, w, dtype=np.float32)[None, :, None]
    img[..., :3] = ramp * np.array([1.0, 2.0, 1.5], np.float32)
    img[..., 3:] = 1.2 * img[..., :3]
    img[:, 34:40, :3] = (0.5, 0.1, 0.1)
    img[:, 34:40, 3:] = 0.8 * img[:, 34:40, :3]
    missing = np.zeros((h, w), bool)
    missing[:, 30:34] = True
    return img, missing


@pytest.mark.parametrize("alpha", [0.4, 1.0])
def test_b_beside_a_predicted_pixel_that_took_in_the_occluder_is_flagged(alpha):
    """B's samples of the sky within 2 px of the sky it cannot see took in the post (a fraction ``alpha`` of
    it): flagged and predicted again within 1 % of the truth; the post's own pixels stay, and so does a
    darker B far from anything hidden."""
    from omnispectral.mosaic.predict import BESIDE_MISSING_PX, contaminated_beside

    img, missing = _sky_with_a_post()
    truth = img.copy()
    post_b = img[0, 35, 3:].copy()
    for x in (28, 29):
        img[:, x, 3:] = (1 - alpha) * img[:, x, 3:] + alpha * post_b
    img[:20, 10, 3:] *= 0.5  # far from anything hidden
    prior = BandPredictor(np.eye(3), np.full(3, 0.3))
    flagged = contaminated_beside(img, missing, prior)
    assert BESIDE_MISSING_PX == 2
    assert flagged[:, 28:30].all() and flagged.sum() == 2 * img.shape[0]
    fill_missing_b(img, missing | flagged, prior)
    err = np.abs(img[:, 28:30, 3:] / truth[:, 28:30, 3:] - 1.0)
    assert err.max() < 0.01


def test_a_small_patch_of_its_own_colour_keeps_its_measured_b():
    """A small patch whose colour nothing near it shares (a chart's 3-px patch, here wholly within the 2 px
    re-examined) beside a predicted pixel keeps what B measured, however far from the prior: its
    look-alikes in A are not around it."""
    from omnispectral.mosaic.predict import contaminated_beside

    img, missing = _sky_with_a_post()
    img[10:13, 28:30, :3] = (6.0, 1.0, 1.0)
    img[10:13, 28:30, 3:] = 0.5 * img[10:13, 28:30, :3]  # half what the prior says, 7 times its error
    prior = BandPredictor(np.eye(3), np.full(3, 0.1))
    assert not contaminated_beside(img, missing, prior).any()
    assert not contaminated_beside(img, missing, None).any()  # no predictor, no test


def test_a_patch_b_sees_unlike_its_look_alikes_in_a_keeps_its_measured_b():
    """A patch beside the hidden pixels whose look-alikes in A nearby (another surface of the same colour in A)
    are another colour in B: the prediction from them is 3 times off, but the patch is not the surface that
    is hidden there, so its measurement stands (a chart's yellow patch beside orange, the chart hiding the
    background from B)."""
    from omnispectral.mosaic.predict import contaminated_beside

    img, missing = _sky_with_a_post()
    img[5:18, 22:27, :3] = (4.0, 2.0, 2.0)
    img[5:18, 22:27, 3:] = img[5:18, 22:27, :3]
    img[10:13, 28:30, :3] = (4.0, 2.0, 2.0)
    img[10:13, 28:30, 3:] = 3.0 * img[10:13, 28:30, :3]
    prior = BandPredictor(np.eye(3), np.full(3, 0.3))
    assert not contaminated_beside(img, missing, prior)[10:13, 28:30].any()


def test_a_partly_hidden_patch_brighter_in_b_than_anything_around_keeps_its_measured_b():
    """A 3-px patch whose right column B cannot see (a chart's yellow patch beside the hidden pixels), with a
    look-alike in A nearby that is another colour in B: the prediction from it is 3 times below what B
    measured, and below every other surface around, so the measurement took in nothing around it and stands;
    a sky pixel darkened by the post beside the same hidden pixels is still flagged."""
    from omnispectral.mosaic.predict import contaminated_beside

    img, missing = _sky_with_a_post()
    img[5:18, 20:25, :3] = (4.0, 2.0, 2.0)
    img[5:18, 20:25, 3:] = img[5:18, 20:25, :3]
    img[10:13, 28:31, :3] = (4.0, 2.0, 2.0)
    img[10:13, 28:31, 3:] = 3.0 * img[10:13, 28:31, :3]
    post_b = img[0, 35, 3:].copy()
    img[30, 29, 3:] = 0.4 * img[30, 29, 3:] + 0.6 * post_b
    prior = BandPredictor(np.eye(3), np.full(3, 0.3))
    flagged = contaminated_beside(img, missing, prior)
    assert not flagged[10:13, 28:30].any()
    assert flagged[30, 29]
