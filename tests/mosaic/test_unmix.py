"""Camera B at edges between two surfaces: B's two surfaces mixed in camera A's share (mosaic.unmix)."""

from __future__ import annotations

import itertools

import numpy as np

from omnispectral.mosaic import unmix
from omnispectral.mosaic.unmix import ERROR_FLOOR, SHARE_ERROR_FACTOR, unmix_b_at_edges

A1, B1 = np.array([1.0, 2.0, 1.0]), np.array([1.5, 3.0, 0.5])  # surface 1 (bright in A)
A2, B2 = np.array([0.3, 0.2, 0.4]), np.array([0.1, 0.5, 0.2])  # surface 2 (dark in A, another hue in B)


def _box_fraction(inside, shape, phase=(0.0, 0.0), n=16):
    """Share of each pixel ``[c, c + 1) × [r, r + 1)`` moved by ``phase`` (x, y) where ``inside(x, y)`` holds
    (``n × n`` samples per pixel)."""
    h, w = shape
    s = (np.arange(n) + 0.5) / n
    y = np.arange(h)[:, None, None, None] + s[None, None, :, None] + phase[1]
    x = np.arange(w)[None, :, None, None] + s[None, None, None, :] + phase[0]
    return np.broadcast_to(inside(x, y), (h, w, n, n)).mean(axis=(2, 3))


def _scene(alpha_a, alpha_b):
    """Six bands: A mixes the two surfaces in share ``alpha_a``, B in ``alpha_b`` (another sampling phase)."""
    img = np.empty((*alpha_a.shape, 6), np.float32)
    img[..., :3] = alpha_a[..., None] * A1 + (1 - alpha_a[..., None]) * A2
    img[..., 3:] = alpha_b[..., None] * B1 + (1 - alpha_b[..., None]) * B2
    return img


def _step_edge(shape=(20, 40)):
    """A vertical edge at x = 20.3 seen by A at the grid's phase and by B 0.45 px off: ``(image, A's share,
    the truth's B)``."""
    left_of_edge = lambda x, y: x < 20.3  # noqa: E731
    alpha_a = _box_fraction(left_of_edge, shape)
    truth_b = alpha_a[..., None] * B1 + (1 - alpha_a[..., None]) * B2
    return _scene(alpha_a, _box_fraction(left_of_edge, shape, phase=(0.45, 0.0))), alpha_a, truth_b


def test_a_step_edge_takes_b_in_a_share_where_b_sampled_another_share():
    img, alpha_a, truth_b = _step_edge()
    before = np.abs(img[..., 3:] - truth_b).max(axis=-1) / np.linalg.norm(truth_b, axis=-1)
    assert before.max() > 0.5  # B's column 19 took 15 % of surface 2, column 20 none of surface 1
    rel = unmix_b_at_edges(img)
    np.testing.assert_allclose(img[..., 3:], truth_b, rtol=1e-5, atol=1e-6)
    changed = np.isfinite(rel)
    # columns 19-21 see the edge within 1 px; 19 and 21 are one surface in A, which B's phase had mixed
    assert changed[:, 19:22].all() and not changed[:, :19].any() and not changed[:, 22:].any()
    # the error recorded: the floor where the pixel is one surface, the mix's share of B where it mixes them
    np.testing.assert_allclose(rel[:, 19], ERROR_FLOOR, rtol=1e-5)
    f = alpha_a[0, 20]  # 5 of the 16 sample columns lie left of the edge
    share = f * np.linalg.norm(B1 - B2) / np.linalg.norm(f * B1 + (1 - f) * B2)
    np.testing.assert_allclose(rel[:, 20], np.hypot(SHARE_ERROR_FACTOR * share, ERROR_FLOOR), rtol=1e-5)


def test_a_slanted_edge_with_noise_is_unmixed_within_the_error_it_records():
    rng = np.random.default_rng(3)
    shape = (48, 48)
    edge = lambda x, y: y < 0.37 * x + 12.2  # noqa: E731
    alpha_a = _box_fraction(edge, shape)
    img = _scene(alpha_a, _box_fraction(edge, shape, phase=(0.37, -0.21)))
    img *= (1 + 0.003 * rng.standard_normal(img.shape)).astype(np.float32)
    truth_b = alpha_a[..., None] * B1 + (1 - alpha_a[..., None]) * B2
    mixed = (alpha_a > 0.02) & (alpha_a < 0.98)
    err_before = np.linalg.norm(img[..., 3:] - truth_b, axis=-1) / np.linalg.norm(truth_b, axis=-1)
    rel = unmix_b_at_edges(img)
    err_after = np.linalg.norm(img[..., 3:] - truth_b, axis=-1) / np.linalg.norm(truth_b, axis=-1)
    inner = np.zeros(shape, bool)
    inner[4:-4, 4:-4] = True
    assert np.isfinite(rel[mixed & inner]).mean() > 0.95
    assert np.mean(err_after[mixed & inner]) < 0.25 * np.mean(err_before[mixed & inner])
    done = np.isfinite(rel)
    assert np.mean(err_after[done] <= 2 * rel[done]) > 0.9


def _on_a_segment(colours, tol):
    """Whether some colour lies within ``tol`` of its norm from the segment between two others (the test of
    :func:`unmix_b_at_edges`)."""
    for p, q, r in itertools.permutations(range(len(colours)), 3):
        d = colours[q] - colours[r]
        t = np.clip((colours[p] - colours[r]) @ d / (d @ d), 0, 1)
        if np.linalg.norm(colours[p] - colours[r] - t * d) <= tol * np.linalg.norm(colours[p]):
            return True
    return False


def test_a_patchwork_of_unrelated_colours_keeps_every_measured_b():
    rng = np.random.default_rng(1)
    colours_a = rng.uniform(0.1, 1.0, (12, 3))
    assert not _on_a_segment(colours_a, unmix.MAX_RESIDUAL)  # no patch's A is a mix of two others
    labels = rng.integers(0, 12, (8, 10)).repeat(4, axis=0).repeat(4, axis=1)  # 4-px patches
    img = np.empty((*labels.shape, 6), np.float32)
    img[..., :3] = colours_a[labels]
    img[..., 3:] = rng.uniform(0.1, 1.0, (12, 3))[labels]
    before = img.copy()
    unmix_b_at_edges(img)  # (a border pixel may take its own patch's B)
    np.testing.assert_array_equal(img, before)


def test_a_thin_line_darker_than_both_surfaces_keeps_its_measured_b():
    shape = (20, 40)
    img = _scene(_box_fraction(lambda x, y: x < 20.0, shape), _box_fraction(lambda x, y: x < 20.0, shape))
    img[10, :, :3] = 0.05  # a wire across both surfaces, darker than either in A
    img[10, :, 3:] = (0.9, 0.1, 0.1)
    unmix_b_at_edges(img)
    np.testing.assert_array_equal(img[10, :, 3:], np.tile(np.float32([0.9, 0.1, 0.1]), (40, 1)))


def test_a_predicted_surface_takes_part_and_its_error_enters_the_mix():
    img, alpha_a, truth_b = _step_edge()
    predicted_rel = np.full(alpha_a.shape, np.nan, np.float32)
    predicted_rel[:, 20:] = 0.2  # surface 2's B (and the mixed column) predicted with a 20 % error
    rel = unmix_b_at_edges(img, predicted_rel)
    np.testing.assert_allclose(img[..., 3:], truth_b, rtol=1e-5, atol=1e-6)
    f = alpha_a[0, 20]
    share = f * np.linalg.norm(B1 - B2) / np.linalg.norm(f * B1 + (1 - f) * B2)
    expected = np.sqrt((SHARE_ERROR_FACTOR * share) ** 2 + ERROR_FLOOR ** 2 + ((1 - f) * 0.2) ** 2)
    np.testing.assert_allclose(rel[:, 20], expected, rtol=1e-5)
    np.testing.assert_allclose(rel[:, 19], ERROR_FLOOR, rtol=1e-5)  # surface 1 alone: measured
    np.testing.assert_allclose(rel[:, 21], np.hypot(ERROR_FLOOR, 0.2), rtol=1e-5)  # surface 2 alone: predicted
