"""Adaptive supersampling of the simulator's pixels: more rays where a pixel's first rays disagree.

A sensor pixel integrates the light over its area; the simulator estimates that integral with ``s × s`` rays
spread evenly over the pixel (``s = 2`` by default, :attr:`omnispectral.sim.simulate.RigRenderer.supersample`).
Where a geometric edge crosses the pixel (an object's silhouette, a shadow's edge) ``s × s`` points quantise the
covered share to steps of ``1 / s²``: with 2 × 2 points a white plate's edge on grass is off by up to an eighth
of the contrast in every pixel along it, in the cameras' frames and in the ground truth alike (measured on the
demo's truth, rows 340–400: band NRMSE 0.084 between 2 × 2 and 16 × 16 points within 2 px of depth edges, 0.0036
elsewhere; 0.011 and 0.0008 with the refinement below).
Textures are not the problem: a scene that filters its texture over each ray's footprint
(:func:`omnispectral.sim.scenes.base.footprint_kwargs`) already gives every ray its share's mean (a textured
pixel whose rays differ by more than the bound below is refined all the same).

So pixels whose first ``s²`` rays spread by more than :data:`REFINE_RELATIVE_RANGE` of their mean in some band
(:func:`pixels_to_refine`), with their 8 neighbours, and pixels whose mean differs by as much from a
4-neighbour's (:func:`differs_from_neighbours`: an edge along a row or column within a quarter of a pixel of the
border between two pixels straddles neither pixel's first rays, and would keep an error of up to a quarter of a
pixel) are rendered again with :data:`REFINE_RAYS_PER_SIDE` ² rays (Whitted's adaptive supersampling, "An
improved illumination model for shaded display", CACM 23(6), 1980; Mitchell, "Generating antialiased images at
low sampling densities", SIGGRAPH 1987, for the contrast test), and those rays' mean replaces theirs.  An edge
then carries a coverage error of at most about ``1 / 8`` of a pixel's width.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["REFINE_RAYS_PER_SIDE", "REFINE_RELATIVE_RANGE", "differs_from_neighbours", "pixels_to_refine",
           "refined_mean", "subpixel_offsets", "unlike_pairs", "with_neighbours"]

#: Rays per pixel side where a pixel is refined.
REFINE_RAYS_PER_SIDE = 8
#: A pixel is refined when, in some band, its rays' range exceeds this fraction of their mean.
REFINE_RELATIVE_RANGE = 0.05


def subpixel_offsets(per_side: int) -> np.ndarray:
    """``(per_side,)`` offsets from a pixel's centre (px) of ``per_side`` points spread evenly over its width."""
    s = max(1, int(per_side))
    return (np.arange(s) + 0.5) / s - 0.5


def pixels_to_refine(samples: np.ndarray, relative_range: float = REFINE_RELATIVE_RANGE) -> np.ndarray:
    """``(P,)`` bool: pixels whose rays disagree (module docstring).

    Parameters
    ----------
    samples : ndarray (P, r, c)
        Each pixel's ``r`` ray values in ``c`` bands (non-negative radiance).
    relative_range : float
        Largest spread ``max − min`` of a band, as a fraction of the band's mean over the rays, that is left as
        it is.
    """
    if samples.shape[1] < 2:
        return np.zeros(samples.shape[0], bool)
    spread = samples.max(axis=1) - samples.min(axis=1)
    mean = samples.mean(axis=1)
    return (spread > relative_range * mean).any(axis=1)


def with_neighbours(marked: np.ndarray, height: int, width: int, wrap_columns: bool = False) -> np.ndarray:
    """``(P,)`` bool: the ``marked (P,)`` pixels of a ``height × width`` image and their 8 neighbours.

    An edge can cross a pixel's corner between its first rays and leave them all on one side; the rays of a
    neighbour it also crosses see it, so the neighbours of a refined pixel are refined too.  ``wrap_columns``:
    the first and last columns are neighbours (an equirectangular image's longitude).
    """
    grid = marked.reshape(height, width)
    if wrap_columns:
        grid = np.pad(grid, ((0, 0), (1, 1)), mode="wrap")
    grown = ndimage.binary_dilation(grid, structure=np.ones((3, 3), bool))
    return (grown[:, 1:-1] if wrap_columns else grown).ravel()


def unlike_pairs(first: np.ndarray, second: np.ndarray, relative_range: float = REFINE_RELATIVE_RANGE) -> np.ndarray:
    """``(…,)`` bool: pixel means ``first`` and ``second`` (``(…, c)``, non-negative) that differ, in some band, by
    more than ``relative_range`` of the pair's mean (the contrast test of :func:`pixels_to_refine`, between two
    pixels)."""
    return (np.abs(first - second) > relative_range * 0.5 * (first + second)).any(axis=-1)


def differs_from_neighbours(means: np.ndarray, height: int, width: int,
                            relative_range: float = REFINE_RELATIVE_RANGE, wrap_columns: bool = False,
                            valid: np.ndarray | None = None) -> np.ndarray:
    """``(P,)`` bool: pixels of a ``height × width`` image whose mean (``means (P, c)``) differs from a 4-neighbour's
    (:func:`unlike_pairs`).

    An edge that runs along a row or column within a quarter of a pixel of the border between two pixels leaves
    each pixel's first rays on one side (their own rays agree), but the two pixels' means differ: both are
    marked.  ``wrap_columns``: the first and last columns are neighbours; ``valid (P,)``: only pairs of valid
    pixels count (a pixel beside one outside the lens model is not marked for that).
    """
    grid = means.reshape(height, width, -1)
    ok = np.ones((height, width), bool) if valid is None else valid.reshape(height, width)
    marked = np.zeros((height, width), bool)
    down = unlike_pairs(grid[1:], grid[:-1], relative_range) & ok[1:] & ok[:-1]
    marked[1:] |= down
    marked[:-1] |= down
    across = unlike_pairs(grid[:, 1:], grid[:, :-1], relative_range) & ok[:, 1:] & ok[:, :-1]
    marked[:, 1:] |= across
    marked[:, :-1] |= across
    if wrap_columns:
        seam = unlike_pairs(grid[:, 0], grid[:, -1], relative_range) & ok[:, 0] & ok[:, -1]
        marked[:, 0] |= seam
        marked[:, -1] |= seam
    return marked.ravel()


def refined_mean(render, positions: np.ndarray, per_side: int) -> np.ndarray:
    """``(P, c)`` mean of ``render(points)`` over ``per_side²`` points spread over each of ``P`` pixels.

    ``positions (P, 2)``: the pixels' centres (``x, y`` in pixels); ``render(points (P·per_side², 2))`` returns
    ``(P·per_side², c)`` values, pixel-major.
    """
    sub = subpixel_offsets(per_side)
    dy, dx = np.meshgrid(sub, sub, indexing="ij")
    points = positions[:, None, :] + np.stack([dx.ravel(), dy.ravel()], axis=-1)[None]
    values = np.asarray(render(points.reshape(-1, 2)))
    return values.reshape(positions.shape[0], per_side * per_side, -1).mean(axis=1)
