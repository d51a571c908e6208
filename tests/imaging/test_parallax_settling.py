"""The per-pixel parallax between blocks and beside depth steps (:mod:`omnispectral.imaging.parallax`):
the sweep's prior on a slanted surface, and the full-resolution depth of a binned analysis where B's colour
misfits A's."""

import numpy as np

from omnispectral.imaging.parallax import (
    _colour_residual,
    block_prior,
    moved_by_parallax,
    settled_at_steps,
    sweep_inverse_depth,
)


def _affine(y, x):
    """Inverse depth of a slanted plane seen by a narrow camera: affine in the pixel (1/m)."""
    return 0.2 + 0.0004 * x + 0.0001 * y


def test_sweep_prior_follows_a_slanted_ground_between_blocks_and_keeps_steps():
    """A texture-less ground's pixels take the sweep's prior.  Block centres every 32 px on a plane whose
    parallax grows 0.03 px per px (72 px·m of field): the nearest block's value is up to 0.5 px off at a
    block's border, the interpolated prior exact; across a depth step no pixel takes a blend."""
    h, w, step = 96, 160, 32
    y_px, x_px = np.arange(step / 2, h, step), np.arange(step / 2, w, step)
    blocks = _affine(y_px[:, None], x_px[None, :]).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    truth = _affine(yy, xx)
    e_px_m = 72.0
    prior = block_prior(blocks, y_px, x_px, h, w, max_span=1.5 / e_px_m)
    inside = (yy >= y_px[0]) & (yy <= y_px[-1]) & (xx >= x_px[0]) & (xx <= x_px[-1])
    assert np.abs(prior - truth)[inside].max() * e_px_m < 1e-3
    nearest = blocks[np.minimum(yy // step, y_px.size - 1), np.minimum(xx // step, x_px.size - 1)]
    assert np.abs(nearest - truth)[inside].max() * e_px_m > 0.45
    # through the sweep: flat images match nowhere, every pixel keeps its prior
    flat = np.full((h, w, 3), 100.0, np.float32)
    field = np.zeros((h, w, 2), np.float32)
    field[..., 1] = e_px_m
    got, _ = sweep_inverse_depth(flat, flat, field, blocks, np.ones_like(blocks, bool), y_px, x_px)
    core = inside & (yy > y_px[0] + 1) & (yy < y_px[-1] - 1) & (xx > x_px[0] + 1) & (xx < x_px[-1] - 1)
    assert np.abs(got - truth)[core].max() * e_px_m < 0.02
    # a step: a near object's blocks beside the far ground's keep their own values
    stepped = blocks.copy()
    stepped[:, 2:] += 0.2                                             # 14 px of parallax nearer
    prior = block_prior(stepped, y_px, x_px, h, w, max_span=1.5 / e_px_m)
    across = (xx > x_px[1]) & (xx < x_px[2])
    own = stepped[np.minimum(yy // step, y_px.size - 1), np.where(xx < (x_px[1] + x_px[2]) / 2, 1, 2)]
    np.testing.assert_array_equal(prior[across], own[across])


def _building_against_sky(h, w, edge_row, shift_px):
    """A lit building below ``edge_row`` (A's grid) against a darker sky, box-sampled; camera B (other filter:
    channels mixed) sees the building's edge ``shift_px`` further down along the epipolar line (down the rows),
    the sky at infinity unmoved."""
    rows = np.arange(h, dtype=np.float64)[:, None]

    def cover(edge):  # the share of each pixel below the edge
        return np.clip(rows + 0.5 - edge, 0.0, 1.0) * np.ones((1, w))

    sky, wall = np.array([300.0, 420.0, 700.0]), np.array([1400.0, 1250.0, 1000.0])
    mix = np.array([[0.9, 0.2, 0.0], [0.1, 0.7, 0.2], [0.0, 0.3, 0.8]])
    a = sky + cover(edge_row)[..., None] * (wall - sky)
    b = (sky + cover(edge_row + shift_px)[..., None] * (wall - sky)) @ mix.T
    return a.astype(np.float32), b.astype(np.float32)


def test_full_resolution_depth_follows_b_at_a_far_silhouette_the_binned_sweep_missed():
    """A building 40 m off (1.8 px of parallax, 0.45 of a 4×-binned pixel): the binned grid found its depth in
    the left columns only and left the rest at infinity, where B's edge lies 1.8 px from A's.  Settled, every
    column's edge pixels show in B what A shows there (misfit from above 0.3 to at most the true depth's, which
    is not 0 at the pixel the edge crosses: bilinear samples of box-sampled pixels), that pixel within 0.5 px of
    the true parallax; pixels whose B colour fitted keep their depth."""
    h, w, f, e_px_m = 64, 96, 4, 72.0
    w_true = 1.8 / e_px_m
    a, b = _building_against_sky(h, w, edge_row=30.3, shift_px=1.8)
    field = np.zeros((h, w, 2), np.float32)
    field[..., 1] = e_px_m
    truth = np.where(np.arange(h)[:, None] >= 30, w_true, 0.0) * np.ones((1, w))
    binned = np.zeros((h // f, w // f), np.float32)
    binned[30 // f:, :4] = w_true                                    # measured in the four left cells
    binned_field = np.zeros((*binned.shape, 2), np.float32)
    binned_field[..., 1] = e_px_m / f
    before = np.repeat(np.repeat(binned, f, axis=0), f, axis=1)
    got = settled_at_steps(a, b, field, before, binned, binned_field, f, reliable=np.ones((h, w), bool))
    mix = np.linalg.lstsq(a.reshape(-1, 3), b.reshape(-1, 3), rcond=None)[0].T

    def misfit(inv_depth):
        return _colour_residual(a, moved_by_parallax(b, field, inv_depth), mix)

    edge_rows = slice(29, 33)
    assert misfit(before)[edge_rows, 16:].max() > 0.3
    assert (misfit(got) - misfit(truth))[edge_rows].max() < 0.01
    assert misfit(truth)[edge_rows].max() < 0.1
    assert np.abs(got - truth)[30, :].max() * e_px_m < 0.5           # the pixel the edge crosses
    fitted = misfit(before) < 0.05
    np.testing.assert_array_equal(got[fitted], before[fitted])


def test_settling_leaves_a_uniform_surface_alone():
    """No edge and B's colour what A predicts: nothing to settle, whatever the binned depths around."""
    h, w, f = 32, 48, 4
    a = np.full((h, w, 3), (500.0, 600.0, 700.0), np.float32)
    b = a @ np.array([[0.9, 0.1, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.9]], np.float32).T
    field = np.zeros((h, w, 2), np.float32)
    field[..., 1] = 50.0
    binned = np.zeros((h // f, w // f), np.float32)
    binned[:, 6:] = 0.2
    binned_field = np.zeros((*binned.shape, 2), np.float32)
    binned_field[..., 1] = 50.0 / f
    before = np.repeat(np.repeat(binned, f, axis=0), f, axis=1)
    got = settled_at_steps(a, b, field, before, binned, binned_field, f, reliable=np.ones((h, w), bool))
    np.testing.assert_array_equal(got, before)
