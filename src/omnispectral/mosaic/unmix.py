"""Camera B's bands at an edge between two surfaces: B's two surfaces mixed in the share camera A shows.

Why.  A product pixel on a sharp edge (a depth edge, a shadow's edge, a patch's border) is a mixture of the two
surfaces it straddles, in the share of its area each covers.  Camera A's value there is close to that mixture:
A's pixels land near the panorama's nodes (the panorama's grid follows camera A's sampling).  Camera B's pixels
land elsewhere (B's mounting angles and parallax put them a fraction of a pixel off), so B's interpolated value
holds another share of each surface, and at a high-contrast edge the difference is a large relative error: the
band error within 2 px of depth edges was 1.6–4.5× camera A's in the registration matrix's 06:30, 09:30 and
12:30 sessions, the most at the edges of a near object against the bright sky.

What.  At a pixel ``p`` whose A brightness changes by more than :data:`EDGE_CONTRAST` within its 3 × 3
neighbourhood, the two surfaces are taken from the flat pixels (A's brightness within :data:`FLAT_TOLERANCE`
over their 3 × 3 neighbourhood) of the ``(2r + 1)²`` window around it (``r`` = :data:`WINDOW_RADIUS_PX`): the
brightest and the darkest in A, ``1`` and ``2``.  When they differ by more than :data:`MIN_SEPARATION` and A at
``p`` lies on the segment between them,

.. math:: \\alpha = \\mathrm{clip}\\Big(\\frac{(a_p - a_2)\\cdot(a_1 - a_2)}{\\lVert a_1 - a_2\\rVert^2}, 0, 1\\Big),
          \\qquad \\lVert a_p - a_2 - \\alpha (a_1 - a_2)\\rVert \\le \\epsilon \\lVert a_p\\rVert,

(ε = :data:`MAX_RESIDUAL`), B's bands become :math:`b_2 + \\alpha (b_1 - b_2)`: what B gave on each surface,
in the share A measured.  This is the two-colour local model of natural-image matting (every pixel of a small
window a mix of two colours; Levin, Lischinski & Weiss 2008) with A as the image whose mix is known and B's
colours taken where A is flat.  A pixel with three surfaces, thin structure or texture around it fails the flat
test or the segment test and keeps its B; so does every pixel of a surface narrower than the flat test's 3 px
(the registration matrix's ColorChecker, whose patches are about 3 px wide, kept every figure).

B's values on both sides take part whether B measured or predicted them: beside a near object the background
B cannot see is predicted (:mod:`omnispectral.mosaic.predict`), and the edge between them is mixed from that
prediction and the object's measured B (06:30 of the registration matrix, seed 0, 1.5 m: 53.6 dB with measured
surfaces only, 60.7 dB with both).

The relative error recorded (the quality layer's ``b_unmixed``, which the estimator adds to B's noise there)
is

.. math:: \\sqrt{(k x)^2 + f^2 + (\\alpha r_1)^2 + ((1 - \\alpha) r_2)^2}, \\qquad
          x = \\min(\\alpha, 1 - \\alpha)\\,\\lVert b_1 - b_2\\rVert / \\lVert b_p\\rVert,

``x`` the share of B that rests on the mix (an error in A's share moves B by about that much), ``k`` =
:data:`SHARE_ERROR_FACTOR`, ``f`` = :data:`ERROR_FLOOR` and ``r1``, ``r2`` the surfaces' prediction errors (0
where measured).  Against the truth on the registration matrix's 06:30, 09:30 and 12:30 sessions (seed 0), the
largest band error of B's chromaticity relative to A's is within it at 88–90 % of the pixels unmixed and within
twice it at 93–94 %.

References
----------
A. Levin, D. Lischinski, Y. Weiss, "A closed-form solution to natural image matting", IEEE TPAMI 30(2), 2008
(the local two-colour model).  T. Porter, T. Duff, "Compositing digital images", SIGGRAPH 1984 (a pixel as the
area-weighted mix of what covers it).
"""

from __future__ import annotations

import cv2
import numpy as np

from omnispectral.imaging.channels import finite_pixels

__all__ = ["EDGE_CONTRAST", "ERROR_FLOOR", "FLAT_TOLERANCE", "HALO_PX", "MAX_RESIDUAL", "MIN_SEPARATION",
           "SHARE_ERROR_FACTOR", "WINDOW_RADIUS_PX", "brightest_and_darkest_flat", "is_flat", "range_3x3",
           "unmix_b_at_edges", "window_offsets"]

#: Half-side (px) of the window the two surfaces are taken from.
WINDOW_RADIUS_PX = 3
#: Pixels beyond a tile that unmixing its border pixels reads (the window and the flat test's 3 × 3): a tile is
#: rendered with this halo so that its border pixels see what the neighbouring tile holds.
HALO_PX = WINDOW_RADIUS_PX + 1
#: A pixel is on an edge when A's brightest 3 × 3 neighbour is this many times its darkest.
EDGE_CONTRAST = 1.3
#: A pixel is flat when A's brightness varies over its 3 × 3 neighbourhood by at most this share.  (B's is not
#: tested: beside a near object B's own edge lies off A's, and requiring B flat too left the pixels between
#: them mixed with the object: 06:30 of the registration matrix read 57.9 dB instead of 60.7 dB.)
FLAT_TOLERANCE = 0.1
#: The two surfaces' A must differ by this share of the brighter one's.
MIN_SEPARATION = 0.2
#: A at the pixel must lie within this share of its own norm from the segment between the two surfaces' A.
MAX_RESIDUAL = 0.03
#: Relative error of an unmixed B: this many times the share of B that rests on the mix, with this floor
#: (module docstring; the errors have a heavy tail: these cover 93-94 % of them at twice the value).
SHARE_ERROR_FACTOR = 1.5
ERROR_FLOOR = 0.03

_SQUARE = np.ones((3, 3), np.uint8)


def unmix_b_at_edges(values: np.ndarray, predicted_rel: np.ndarray | None = None) -> np.ndarray:
    """Replace camera B's bands (3–5) of ``values`` ``(h, w, 6)`` in place at edge pixels that mix two flat
    surfaces (module docstring).

    Parameters
    ----------
    values
        A tile's six bands (DN/s); B's bands measured or already predicted (:mod:`omnispectral.mosaic.predict`).
    predicted_rel
        ``(h, w)``: the relative error of B's bands where they were predicted (NaN or 0 where measured); a
        surface's error enters the error of the B mixed from it.

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` float32: the relative error of the unmixed B (module docstring) where replaced, NaN elsewhere.
    """
    a, b = values[..., :3], values[..., 3:6]
    rel_out = np.full(values.shape[:2], np.nan, np.float32)
    a_ok = finite_pixels(a)
    b_ok = a_ok & finite_pixels(b)
    bright_a = np.where(a_ok, a.sum(axis=-1, dtype=np.float64), np.nan).astype(np.float32)
    top_a, bottom_a = range_3x3(bright_a)
    flat = b_ok & is_flat(bright_a, top_a, bottom_a)
    edge = b_ok & ~flat & (top_a > EDGE_CONTRAST * np.maximum(bottom_a, 0.0))
    ys, xs = np.nonzero(edge)
    if ys.size == 0:
        return rel_out
    (y1, x1), (y2, x2), found = brightest_and_darkest_flat(bright_a, flat, ys, xs, WINDOW_RADIUS_PX)
    ys, xs, y1, x1, y2, x2 = (k[found] for k in (ys, xs, y1, x1, y2, x2))
    a_p, a_1, a_2 = (a[yy, xx].astype(np.float64) for yy, xx in ((ys, xs), (y1, x1), (y2, x2)))
    span = a_1 - a_2
    span_sq = (span ** 2).sum(axis=1)
    alpha = np.clip(((a_p - a_2) * span).sum(axis=1) / np.maximum(span_sq, 1e-300), 0.0, 1.0)
    residual = np.linalg.norm(a_p - a_2 - alpha[:, None] * span, axis=1)
    ok = ((np.sqrt(span_sq) > MIN_SEPARATION * np.linalg.norm(a_1, axis=1))
          & (residual <= MAX_RESIDUAL * np.linalg.norm(a_p, axis=1)))
    if not ok.any():
        return rel_out
    ys, xs, alpha = ys[ok], xs[ok], alpha[ok]
    b_1, b_2 = b[y1[ok], x1[ok]].astype(np.float64), b[y2[ok], x2[ok]].astype(np.float64)
    unmixed = b_2 + alpha[:, None] * (b_1 - b_2)
    share = np.minimum(alpha, 1.0 - alpha) * np.linalg.norm(b_1 - b_2, axis=1) / np.maximum(
        np.linalg.norm(unmixed, axis=1), 1e-300)
    rel_sq = (SHARE_ERROR_FACTOR * share) ** 2 + ERROR_FLOOR ** 2
    if predicted_rel is not None:  # a predicted surface's error, in its share
        known = np.nan_to_num(np.asarray(predicted_rel, np.float64), nan=0.0)
        rel_sq += (alpha * known[y1[ok], x1[ok]]) ** 2 + ((1.0 - alpha) * known[y2[ok], x2[ok]]) ** 2
    b[ys, xs] = unmixed.astype(b.dtype)
    rel_out[ys, xs] = np.sqrt(rel_sq)
    return rel_out


def range_3x3(brightness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest and smallest finite value over each pixel's 3 × 3 neighbourhood (NaN where none is finite; the
    tile's border replicated)."""
    finite = np.isfinite(brightness)
    top = cv2.dilate(np.where(finite, brightness, -np.inf).astype(np.float32), _SQUARE,
                     borderType=cv2.BORDER_REPLICATE)
    bottom = cv2.erode(np.where(finite, brightness, np.inf).astype(np.float32), _SQUARE,
                       borderType=cv2.BORDER_REPLICATE)
    none = ~np.isfinite(top) | ~np.isfinite(bottom)
    return np.where(none, np.nan, top), np.where(none, np.nan, bottom)


def is_flat(brightness: np.ndarray, top: np.ndarray, bottom: np.ndarray) -> np.ndarray:
    """Pixels whose 3 × 3 neighbourhood varies by at most :data:`FLAT_TOLERANCE` of their own brightness."""
    with np.errstate(invalid="ignore"):
        return (top - bottom) <= FLAT_TOLERANCE * brightness


def window_offsets(radius: int) -> np.ndarray:
    """``(K, 2)`` int: the ``(dy, dx)`` of a ``(2 radius + 1)²`` window but its centre, nearest first (rows, then
    columns, among equally near ones): the order in which :func:`brightest_and_darkest_flat` meets them."""
    return np.array(sorted(((dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
                            if dy or dx), key=lambda o: o[0] ** 2 + o[1] ** 2), dtype=np.int64)


def brightest_and_darkest_flat(brightness: np.ndarray, flat: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                                radius: int, nearest: bool = False
                                ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray], np.ndarray]:
    """For each pixel ``(ys, xs)``: the brightest and the darkest ``flat`` pixel of its ``(2 radius + 1)²`` window
    (cut at the tile's border), as ``((y1, x1), (y2, x2), found)``; ``found`` is False where the window has
    fewer than two flat pixels."""
    h, w = flat.shape
    offsets = window_offsets(radius)
    keyed = np.where(flat, brightness, np.nan)
    padded = np.pad(keyed, radius, mode="constant", constant_values=np.nan)
    window = padded[ys[:, None] + radius + offsets[:, 0], xs[:, None] + radius + offsets[:, 1]]  # (n, K)
    n_flat = np.isfinite(window).sum(axis=1)
    found = n_flat >= 2
    hi = np.argmax(np.where(np.isfinite(window), window, -np.inf), axis=1)
    lo = np.argmin(np.where(np.isfinite(window), window, np.inf), axis=1)
    found &= hi != lo
    if nearest:
        rows = np.arange(ys.size)
        mid = 0.5 * (window[rows, hi] + window[rows, lo])
        with np.errstate(invalid="ignore"):
            hi = np.argmax(window > mid[:, None], axis=1)
            lo = np.argmax(window < mid[:, None], axis=1)
    y1, x1 = np.clip(ys + offsets[hi, 0], 0, h - 1), np.clip(xs + offsets[hi, 1], 0, w - 1)
    y2, x2 = np.clip(ys + offsets[lo, 0], 0, h - 1), np.clip(xs + offsets[lo, 1], 0, w - 1)
    return (y1, x1), (y2, x2), found
