"""Resampling at straight edges: the share of each output pixel's footprint on either side of a sub-pixel edge.

Why.  A sensor pixel on a sharp edge holds the two surfaces in the share of its area each covers (the partial
area effect).  Interpolating those box samples at a position between pixels does not give the box sample of
a pixel centred there: at a step, bilinear interpolation at a phase φ from the pixel whose area the edge cuts
at ``c`` errs by ``φ (1 − c)`` of the contrast, and cubic kernels likewise; the pixel beside the edge takes in
some of the other surface through the kernel's taps.  At full scale (the ``paper-timelapse`` session at the
cameras' native width, the truth rendered on the same grid), interpolation alone left camera A's band error
within 2 px of depth edges at 0.079 against 0.0056 on smooth surfaces, camera B's at 0.099.

What.  Around a sensor pixel ``n`` whose 3 × 3 neighbourhood lies beside an edge between two flat surfaces (the
edge and flat tests of :mod:`omnispectral.mosaic.unmix`; the surfaces are the nearest flat pixels brighter and
darker than the midpoint of the window's brightest and darkest, so that a gradient across a surface (the sky)
does not pull them apart), each of the nine pixels' share ``α_q`` of the bright surface ``1`` (its value
projected on the segment between the surfaces' values, as in :mod:`~omnispectral.mosaic.unmix`) is the area of
that pixel on the bright side of a straight edge ``m · (x − n) < s``.  The normal ``m`` starts from the
direction in which the shares fall (a least-squares plane through them) and is turned by
:data:`ANGLE_STEPS_RAD` to the half-plane that best reproduces the nine; ``s`` is the offset at which the
half-plane holds the nine pixels' summed share (exact for a straight edge whatever its position: Trujillo-Pino
et al. 2013).  When that half-plane reproduces every one of the nine shares within :data:`MAX_FIT_ERROR` (or
all nine lie on one surface: a kernel reaching beyond the window took in some of the other), an output pixel
whose nearest sensor pixel is ``n`` gets the share of its own footprint on the bright side (the output pixel's
square mapped into the sensor by the local Jacobian ``J`` of the output grid's map; for camera B the map at
infinity, whose differences do not jump at depth edges as its parallax-corrected positions do),

.. math:: c = P\\big((J^\\top m) \\cdot w < s - m \\cdot (p - n)\\big), \\quad w \\sim U([-\\tfrac12, \\tfrac12]^2),

and its interpolated value ``v`` moves along the segment to that share: ``v + (c − α_v)(v_1 − v_2)``.  ``P``
is the distribution of a sum of two uniform variables (a trapezoid), in closed form.  Texture, three surfaces
and structure narrower than the flat test's 3 px fail a test and keep the interpolated value; at a corner a
window may still fit a straight edge (the tests bound the corner's error to 1.25× the interpolation's).

Measured.  On that session camera A's edge error fell to 0.033 and B's to 0.073 (smooth surfaces 0.0043 and
0.0058).  Against a truth rendered on another grid and area-resampled onto the panorama's, which blurs its
edges by up to one of its pixels, the model reads worse than interpolation (docs/benchmarks.md, "Processing").

References
----------
A. Trujillo-Pino, K. Krissian, M. Alemán-Flores, D. Santana-Cedrés, "Accurate subpixel edge location based on
partial area effect", Image and Vision Computing 31(1), 2013 (the edge's position from the area its pixels
hold).  T. Porter, T. Duff, "Compositing digital images", SIGGRAPH 1984 (a pixel as the area-weighted mix of
what covers it).
"""

from __future__ import annotations

import cv2
import numpy as np

from omnispectral.mosaic.kernels import compiled_kernels
from omnispectral.mosaic.unmix import (
    EDGE_CONTRAST,
    MAX_RESIDUAL,
    MIN_SEPARATION,
    WINDOW_RADIUS_PX,
    brightest_and_darkest_flat,
    is_flat,
    range_3x3,
    window_offsets,
)

__all__ = ["ANGLE_STEPS_RAD", "HALO_PX", "MAX_FIT_ERROR", "REACH_PX", "area_share",
           "area_share_offset", "resample_edges"]

#: The straight edge must reproduce each of the nine pixels' shares within this (a share is 0–1).
MAX_FIT_ERROR = 0.15
#: Output pixels beyond a tile whose positions the tile's border pixels read (their footprint's differences).
HALO_PX = 1
#: Turns (rad) of the plane fit's normal tried; the one whose half-plane best reproduces the nine shares is
#: kept (the plane fit is biased between the axes and the diagonals).
ANGLE_STEPS_RAD = tuple(np.linspace(-0.4, 0.4, 9))

#: Relative margin by which a turn's fit must beat the best so far (below it: a tie, the first turn kept, so
#: that the compiled kernel and the NumPy definition choose alike whatever their rounding).
TIE = 1e-9

#: Source pixels around an output position that its edge model reads: the nearest pixel (½), its 3 × 3 window
#: (1), the surfaces' window (:data:`~omnispectral.mosaic.unmix.WINDOW_RADIUS_PX`) and their flat test (1).
REACH_PX = 3 + WINDOW_RADIUS_PX

_OFFSETS = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
_SQUARE = np.ones((3, 3), np.uint8)
_BAND_SUM = np.ones((1, 3), np.float32)


def area_share(s: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Share of the square ``[-½, ½]²`` with ``a x + b y < s`` (the distribution function of ``a X + b Y`` with
    ``X, Y`` uniform on ``[-½, ½]``: a trapezoid's integral)."""
    hi, lo = _half_ranges(a, b)
    rise = np.clip(s + hi + lo, 0.0, None) ** 2 / (8.0 * hi * lo)
    fall = 1.0 - np.clip(hi + lo - s, 0.0, None) ** 2 / (8.0 * hi * lo)
    middle = (s + hi) / (2.0 * hi)
    return np.clip(np.where(s < lo - hi, rise, np.where(s < hi - lo, middle, fall)), 0.0, 1.0)


def area_share_offset(share: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The inverse of :func:`area_share` in ``s``: the offset at which the half-plane holds ``share`` (0–1) of
    the square."""
    hi, lo = _half_ranges(a, b)
    corner = lo / (2.0 * hi)
    share = np.clip(share, 0.0, 1.0)
    return np.where(share < corner, np.sqrt(8.0 * hi * lo * share) - hi - lo,
                    np.where(share <= 1.0 - corner, 2.0 * hi * share - hi,
                             hi + lo - np.sqrt(8.0 * hi * lo * (1.0 - share))))


def _half_ranges(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Half-ranges of ``a X`` and ``b Y`` over the unit square, larger first, kept away from 0 (a trapezoid's
    half-width and half-slope)."""
    hi = np.maximum(0.5 * np.maximum(np.abs(a), np.abs(b)), 1e-12)
    return hi, np.maximum(0.5 * np.minimum(np.abs(a), np.abs(b)), 1e-12 * hi)


def resample_edges(src: np.ndarray, u: np.ndarray, v: np.ndarray, values: np.ndarray, used: np.ndarray,
                   bad: np.ndarray | None = None, grid_uv: tuple[np.ndarray, np.ndarray] | None = None) -> int:
    """Move ``values`` (``src`` interpolated at ``(u, v)``) in place to their footprint's share of each side of
    the straight edges of ``src`` (module docstring).

    Parameters
    ----------
    src
        ``(H, W, 3)`` float32: the source pixels (box samples).
    u, v
        ``(h, w)`` float32: positions in ``src`` (px; pixel centres at integers) of the output pixels, on the
        output's regular grid (their differences give the footprint).
    values
        ``(h, w, 3)`` float32: the interpolated values, changed in place.
    used
        ``(h, w)`` bool: output pixels to consider.
    bad
        ``(H, W)`` bool: source pixels that are not valid (never a surface, never an edge).
    grid_uv
        ``(u, v)`` of a smooth map of the same output grid, whose differences give the footprint (default
        ``(u, v)``): camera B's positions jump at depth edges with its parallax, its map at infinity does not.

    Returns
    -------
    int
        How many output pixels moved.
    """
    model = _edge_models(src, bad)
    if model is None:
        return 0
    index, centre, normal, offset, bright, dark = model
    # each output pixel's nearest source pixel's model, in one OpenCV pass (positions outside: none)
    k = cv2.remap(index, np.ascontiguousarray(u, np.float32), np.ascontiguousarray(v, np.float32),
                  cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    oy, ox = np.nonzero((k >= 0) & used & np.isfinite(u) & np.isfinite(v))
    if oy.size == 0:
        return 0
    kk = k[oy, ox].astype(np.intp)
    jac, known = _footprint_jacobian(*(grid_uv if grid_uv is not None else (u, v)), oy, ox)
    oy, ox, kk, jac = oy[known], ox[known], kk[known], jac[known]
    if oy.size == 0:
        return 0
    mx, my = normal[kk, 0], normal[kk, 1]
    # the output square's edges in sensor px: columns of J; the half-plane's normal on that square is Jᵀ m
    na = mx * jac[:, 0, 0] + my * jac[:, 1, 0]
    nb = mx * jac[:, 0, 1] + my * jac[:, 1, 1]
    shift = offset[kk] - mx * (u[oy, ox] - centre[kk, 1]) - my * (v[oy, ox] - centre[kk, 0])
    share = area_share(shift, na, nb)
    span = bright[kk] - dark[kk]
    here = values[oy, ox].astype(np.float64)
    alpha = ((here - dark[kk]) * span).sum(axis=1) / np.maximum((span ** 2).sum(axis=1), 1e-300)
    values[oy, ox] = (here + (share - alpha)[:, None] * span).astype(values.dtype)
    return int(oy.size)


def _edge_models(src: np.ndarray, bad: np.ndarray | None, compiled: bool = True):
    """The straight edge around every source pixel whose 3 × 3 neighbourhood holds one (module docstring):
    ``(index, centre, normal, offset, bright, dark)``, ``index`` ``(H, W)`` float32 the row of the pixel's model
    in the other arrays (−1 where none), ``centre`` its ``(row, column)``; or None where no pixel has one.
    ``compiled``: the compiled kernel where Numba is installed (else, and with False, the NumPy definition)."""
    # the bands' sum in one OpenCV pass (NumPy's reduction over a last axis of 3 is ~50x slower); it is finite
    # exactly where every band is
    src = np.ascontiguousarray(src, np.float32)
    brightness = cv2.transform(src, _BAND_SUM).reshape(src.shape[:2])
    finite = np.isfinite(brightness)
    if bad is not None:
        finite &= ~bad
    if not finite.all():
        brightness = np.where(finite, brightness, np.float32(np.nan))
    zone = _beside_edges(brightness, finite)
    if zone is None:
        return None
    ys, xs, flat = zone
    kernels = compiled_kernels() if compiled else None
    if kernels is not None:
        valid, params = np.empty(ys.size, bool), np.empty((ys.size, 9))
        kernels.edge_models(src, brightness, flat, finite, ys, xs,
                            window_offsets(WINDOW_RADIUS_PX), np.asarray(ANGLE_STEPS_RAD, np.float64), TIE,
                            MIN_SEPARATION, MAX_RESIDUAL, MAX_FIT_ERROR, valid, params)
        ok, normal, offset, bright, dark = valid, params[:, :2], params[:, 2], params[:, 3:6], params[:, 6:9]
    else:
        shares = _two_surface_shares(src, brightness, finite, flat, ys, xs)
        if shares is None:
            return None
        ys, xs, alpha, bright, dark = shares
        normal, offset, fit_error = _straight_edge(alpha)
        ok = fit_error <= MAX_FIT_ERROR
    if not ok.any():
        return None
    index = np.full(src.shape[:2], -1.0, np.float32)  # float32 for OpenCV's lookup: exact below 2²⁴ models
    index[ys[ok], xs[ok]] = np.arange(int(ok.sum()), dtype=np.float32)
    return index, np.stack([ys[ok], xs[ok]], axis=1), normal[ok], offset[ok], bright[ok], dark[ok]


def _beside_edges(brightness: np.ndarray, finite: np.ndarray):
    """The source pixels beside an edge (within 1 px of a pixel whose 3 × 3 brightness range exceeds
    :data:`~omnispectral.mosaic.unmix.EDGE_CONTRAST`, not on the border) and the flat pixels: ``(ys, xs, flat)``,
    or None where there is no edge."""
    top, bottom = range_3x3(brightness)
    flat = finite & is_flat(brightness, top, bottom)
    with np.errstate(invalid="ignore"):
        edge = finite & ~flat & (top > EDGE_CONTRAST * np.maximum(bottom, 0.0))
    near = cv2.dilate(edge.astype(np.uint8), _SQUARE) > 0
    near[[0, -1], :] = False
    near[:, [0, -1]] = False
    ys, xs = np.nonzero(near)
    return None if ys.size == 0 else (ys, xs, flat)


def _two_surface_shares(src: np.ndarray, brightness: np.ndarray, finite: np.ndarray, flat: np.ndarray,
                        ys: np.ndarray, xs: np.ndarray):
    """Of the pixels ``(ys, xs)``, those whose 3 × 3 window lies between two flat surfaces: ``(ys, xs, alpha,
    bright, dark)`` with ``alpha`` ``(n, 9)`` the nine pixels' shares of the bright surface and ``bright``,
    ``dark`` ``(n, 3)`` the surfaces' values (the nearest flat pixels on each side, within
    :data:`~omnispectral.mosaic.unmix.WINDOW_RADIUS_PX`); None where there is none (the NumPy definition of the
    compiled ``edge_models``)."""
    (y1, x1), (y2, x2), found = brightest_and_darkest_flat(brightness, flat, ys, xs, WINDOW_RADIUS_PX,
                                                           nearest=True)
    ys, xs, y1, x1, y2, x2 = (k[found] for k in (ys, xs, y1, x1, y2, x2))
    bright, dark = src[y1, x1].astype(np.float64), src[y2, x2].astype(np.float64)
    span = bright - dark
    span_sq = (span ** 2).sum(axis=1)
    wy, wx = ys[:, None] + _OFFSETS[:, 0], xs[:, None] + _OFFSETS[:, 1]
    window = src[wy, wx].astype(np.float64)  # (n, 9, 3)
    alpha = np.clip(((window - dark[:, None]) * span[:, None]).sum(axis=2)
                    / np.maximum(span_sq, 1e-300)[:, None], 0.0, 1.0)
    residual = np.linalg.norm(window - dark[:, None] - alpha[..., None] * span[:, None], axis=2)
    ok = ((np.sqrt(span_sq) > MIN_SEPARATION * np.linalg.norm(bright, axis=1))
          & (residual <= MAX_RESIDUAL * np.linalg.norm(window, axis=2)).all(axis=1)
          & finite[wy, wx].all(axis=1))
    if not ok.any():
        return None
    return ys[ok], xs[ok], alpha[ok], bright[ok], dark[ok]


def _straight_edge(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The half-plane ``m · x < s`` (x in px from the window's centre) whose share of each of the nine pixels
    best matches ``alpha`` ``(n, 9)`` while holding their summed share: ``(m (n, 2), s (n,), the largest
    difference from a share (n,))``.  ``m`` starts from a least-squares plane through the shares and is turned
    by :data:`ANGLE_STEPS_RAD`."""
    gx = (alpha * _OFFSETS[:, 1]).sum(axis=1)
    gy = (alpha * _OFFSETS[:, 0]).sum(axis=1)
    base = np.arctan2(-gy, -gx)  # the shares fall along m
    total = alpha.mean(axis=1)
    best = np.full(alpha.shape[0], np.inf)
    angle = base.copy()
    for turn in ANGLE_STEPS_RAD:
        err = ((_window_shares(total, base + turn) - alpha) ** 2).sum(axis=1)
        better = err < best * (1.0 - TIE) - TIE  # a turn must beat the one before by more than rounding
        best = np.where(better, err, best)
        angle = np.where(better, base + turn, angle)
    mx, my = np.cos(angle), np.sin(angle)
    fit_error = np.abs(_window_shares(total, angle) - alpha).max(axis=1)
    offset = 3.0 * area_share_offset(total, mx, my)
    # a window on one surface: every footprint in it is on that side (an interpolation kernel reaching past the
    # window took some of the other); no plane through the shares: no straight edge
    one_side = (alpha == alpha[:, :1]).all(axis=1) & ((total == 0.0) | (total == 1.0))
    offset = np.where(one_side, np.where(total == 1.0, np.inf, -np.inf), offset)
    no_plane = ~one_side & (np.hypot(gx, gy) <= 1e-6)
    return np.stack([mx, my], axis=1), offset, np.where(one_side, 0.0, np.where(no_plane, np.inf, fit_error))


def _window_shares(total: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """``(n, 9)``: each 3 × 3 window pixel's share of the half-plane with normal angle ``angle`` that holds
    ``total`` of the window."""
    mx, my = np.cos(angle), np.sin(angle)
    offset = 3.0 * area_share_offset(total, mx, my)  # the 3 × 3 square is the unit one scaled by 3
    return area_share(offset[:, None] - mx[:, None] * _OFFSETS[:, 1] - my[:, None] * _OFFSETS[:, 0],
                      mx[:, None], my[:, None])


def _footprint_jacobian(u: np.ndarray, v: np.ndarray, oy: np.ndarray, ox: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 2, 2)`` d(u, v)/d(column, row) at the output pixels ``(oy, ox)`` (the output pixel's square in
    source px): central differences, one-sided at the grid's border; and ``(n,)`` whether it is finite."""
    h, w = u.shape
    jac = np.zeros((oy.size, 2, 2))
    for j, (dy, dx) in enumerate(((0, 1), (1, 0))):  # along columns, then rows
        ay, ax = np.minimum(oy + dy, h - 1), np.minimum(ox + dx, w - 1)
        by, bx = np.maximum(oy - dy, 0), np.maximum(ox - dx, 0)
        steps = ((ay - by) + (ax - bx)).astype(np.float64)
        with np.errstate(invalid="ignore", divide="ignore"):
            jac[:, 0, j] = (u[ay, ax].astype(np.float64) - u[by, bx]) / steps
            jac[:, 1, j] = (v[ay, ax].astype(np.float64) - v[by, bx]) / steps
    return jac, np.isfinite(jac).all(axis=(1, 2))
