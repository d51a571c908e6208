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
is the distribution of a sum of two uniform variables (a trapezoid), in closed form.

Corners. Where the nine shares lie between two surfaces but no straight edge reproduces them (or one does only
loosely, :data:`CORNER_TRY_FIT`), the window is tried as a corner: the bright side is a wedge, ``m_1 · x < s_1`` and
(a convex bright corner; or, a concave one) ``m_2 · x < s_2``, whose sides are two of the straight edges fitted
within :data:`CORNER_RADIUS_PX` (each moved into this window's frame; near-duplicates once, sides 35°–145° apart),
the pair and the join that best reproduce the nine shares, kept when they do within :data:`MAX_FIT_ERROR` (and
within :data:`CORNER_GAIN` of a loose straight edge's error). A footprint's share of a wedge is its parallelogram
clipped by both half-planes (Sutherland & Hodgman 1974), exact (the square in ``tests/mosaic/test_edges.py``: its
corners' error 0.13–0.50× the interpolation's, 0.81–1.18× with straight edges alone).

Three surfaces. Where a window beside an edge has no model between two surfaces (a plate's corner lying on the edge
of its own shadow: plate, ground and shadow; the ground and the shadow can be of one hue, so colour alone cannot
tell a pixel's mix), the surfaces are three brightness levels among the flat pixels around and the sides of the
straight edges within :data:`CORNER_RADIUS_PX` (the brightest, the darkest, and the one farthest from both in
ratio, at least :data:`~omnispectral.mosaic.unmix.EDGE_CONTRAST` from each; each surface the mean of the samples
nearest its level). Each of those straight edges (at most :data:`THREE_MAX_LINES`, nearest first) whose sides'
colours match two of the surfaces within :data:`THREE_COLOUR_TOL` bounds those two. One surface ``X`` is a
half-plane or a wedge (or a union) of one or two of them, and the rest is split between the other two by a third;
the choice that best reproduces the nine pixels' values is kept when each is within :data:`MAX_FIT_ERROR` of the
brightest and darkest surfaces' difference. An output pixel then gets its footprint's share of each region (the
parallelogram clipped by up to three half-planes) in each surface's value. Texture and structure narrower than the
flat test's 3 px (a plate's one-pixel side face) fail a test and keep the interpolated value (the plate on its
shadow in ``tests/mosaic/test_edges.py``: the junction's error 0.03–0.45× the interpolation's, 0.45–0.98× with
two-surface models alone).

Measured. On that session camera A's edge error fell to 0.033 and B's to 0.073 (smooth surfaces 0.0043 and 0.0058);
with corners and three surfaces A's reads 0.0328 (the scene has few). On the ``small`` preset's 09:30 scene, whose
plate lies on its shadow, corners took A's edge error from 0.030 to 0.023 and B's from 0.043 to 0.036, three
surfaces to 0.019 and 0.033 (against a 32 × 32-ray truth; docs/benchmarks.md, "Registration across
conditions"). Against a truth rendered on another grid and area-resampled onto the panorama's, which blurs its
edges by up to one of its pixels, the model reads worse than interpolation (docs/benchmarks.md, "Processing").

References
----------
I. E. Sutherland, G. W. Hodgman, "Reentrant polygon clipping", Communications of the ACM 17(1), 1974 (a convex
polygon cut by a half-plane). A. Trujillo-Pino, K. Krissian, M. Alemán-Flores, D. Santana-Cedrés, "Accurate subpixel
edge location based on partial area effect", Image and Vision Computing 31(1), 2013 (the edge's position from the
area its pixels hold). T. Porter, T. Duff, "Compositing digital images", SIGGRAPH 1984 (a pixel as the area-weighted
mix of what covers it).
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

#: A window between two surfaces that no straight edge fits is tried as a corner: two of the straight edges
#: fitted within this many px of it (in the source), as the sides of a wedge.
CORNER_RADIUS_PX = 3
#: At most this many distinct straight edges are tried per corner (met in the window's row order).
CORNER_MAX_LINES = 16
#: Two straight edges whose normals are within 3° and whose offsets (px) are within this are one.
SAME_LINE_COS = float(np.cos(np.deg2rad(3.0)))
SAME_LINE_PX = 0.1
#: A wedge's sides meet at 35°–145° (the sine of the angle between their normals at least this): the normals of
#: one straight edge's windows differ by up to the fit's turns (±23°), and two of them made a false corner.
CORNER_MIN_SIN = float(np.sin(np.deg2rad(35.0)))
#: A window that a straight edge fits only to more than this (its largest share error) is tried as a corner
#: too, and the wedge kept where its largest error is at most :data:`CORNER_GAIN` of the straight edge's: a window
#: holding a corner's tip can fit a straight edge within :data:`MAX_FIT_ERROR` and misplace the tip.
CORNER_TRY_FIT = 0.03
CORNER_GAIN = 0.5

#: A window beside an edge that no two-surface model fits is tried between three surfaces (a corner lying on an
#: edge of what is behind it: a plate on its own shadow): three brightness levels among the flat pixels around and
#: the nearby straight edges' sides (the brightest, the darkest, and the one farthest from both in ratio, at least
#: :data:`~omnispectral.mosaic.unmix.EDGE_CONTRAST` from each); a nearby straight edge bounds two of them when
#: its sides' colours lie within this share of the brightest and darkest surfaces' difference from their means.
THREE_COLOUR_TOL = 0.3
#: At most this many distinct straight edges are tried per three-surface window (the nearest first).
THREE_MAX_LINES = 8

#: Source pixels around an output position that its edge model reads: the nearest pixel (½), its 3 × 3 window
#: (1), the surfaces' window (:data:`~omnispectral.mosaic.unmix.WINDOW_RADIUS_PX`), their flat test (1), and a
#: corner's straight edges (:data:`CORNER_RADIUS_PX`).
REACH_PX = 3 + WINDOW_RADIUS_PX + CORNER_RADIUS_PX

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
    the straight edges and corners of ``src`` (module docstring).

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
    index, centre, wedge, bright, dark, split, other = model
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
    px, py = u[oy, ox] - centre[kk, 1], v[oy, ox] - centre[kk, 0]
    here = values[oy, ox].astype(np.float64)
    three = np.isfinite(split[kk, 2])
    two = ~three
    k2 = kk[two]
    share = _footprint_shares(px[two], py[two], jac[two], wedge[k2])
    span = bright[k2] - dark[k2]
    alpha = ((here[two] - dark[k2]) * span).sum(axis=1) / np.maximum((span ** 2).sum(axis=1), 1e-300)
    here[two] += (share - alpha)[:, None] * span
    if three.any():
        # three surfaces: the footprint's shares of each, the surfaces' values mixed in them
        k3 = kk[three]
        shares = _footprint_region_shares(px[three], py[three], jac[three], wedge[k3], split[k3])
        here[three] = (shares[:, :1] * bright[k3] + shares[:, 1:] * dark[k3]
                       + (1.0 - shares.sum(axis=1, keepdims=True)) * other[k3])
    values[oy, ox] = here.astype(values.dtype)
    return int(oy.size)


def _footprint_shares(px: np.ndarray, py: np.ndarray, jac: np.ndarray, wedge: np.ndarray,
                      compiled: bool = True) -> np.ndarray:
    """``(n,)``: the share on the bright side of each output footprint (the square mapped by ``jac``, centred
    at ``(px, py)`` from its model's source pixel) of its model ``wedge`` ``(n, 7)``: a straight edge in closed
    form (the footprint's half-plane is ``(Jᵀ m) · w < s − m · p``), a corner by clipping the parallelogram."""
    mx, my = wedge[:, 0], wedge[:, 1]
    # the output square's edges in sensor px: columns of J; the half-plane's normal on that square is Jᵀ m
    na = mx * jac[:, 0, 0] + my * jac[:, 1, 0]
    nb = mx * jac[:, 0, 1] + my * jac[:, 1, 1]
    share = area_share(wedge[:, 2] - mx * px - my * py, na, nb)
    corner = np.isfinite(wedge[:, 5])
    if corner.any():
        args = (px[corner].astype(np.float64), py[corner].astype(np.float64), np.ascontiguousarray(jac[corner]),
                np.ascontiguousarray(wedge[corner]))
        kernels = compiled_kernels() if compiled else None
        if kernels is not None:
            out = np.empty(args[0].size)
            kernels.footprint_wedge_shares(*args, out)
        else:
            out = np.array([_wedge_share(x, y, (j[0, 0], j[1, 0]), (j[0, 1], j[1, 1]), w)
                            for x, y, j, w in zip(*args, strict=True)])
        share[corner] = out
    return share


def _footprint_region_shares(px: np.ndarray, py: np.ndarray, jac: np.ndarray, wedge: np.ndarray, split: np.ndarray,
                             compiled: bool = True) -> np.ndarray:
    """``(n, 2)``: each output footprint's shares of its three-surface model's regions ``X`` (``wedge``) and
    ``Y`` (outside ``X``, inside ``split``), by clipping its parallelogram."""
    args = (np.ascontiguousarray(px, np.float64), np.ascontiguousarray(py, np.float64), np.ascontiguousarray(jac),
            np.ascontiguousarray(wedge), np.ascontiguousarray(split))
    kernels = compiled_kernels() if compiled else None
    out = np.empty((args[0].size, 2))
    if kernels is not None:
        kernels.footprint_region_shares(*args, out)
        return out
    for i, (x, y, j, w, m) in enumerate(zip(*args, strict=True)):
        out[i] = _region_shares(x, y, (j[0, 0], j[1, 0]), (j[0, 1], j[1, 1]), w, m)
    return out


def _edge_models(src: np.ndarray, bad: np.ndarray | None, compiled: bool = True):
    """The straight edge, corner or three-surface model around every source pixel whose 3 × 3 neighbourhood holds
    one (module docstring): ``(index, centre, wedge, bright, dark, split, other)``, ``index`` ``(H, W)`` float32
    the row of the pixel's model in the other arrays (−1 where none), ``centre`` its ``(row, column)``, ``wedge``
    ``(n, 7)`` its sides ``(m1x, m1y, s1, m2x, m2y, s2, union)`` (bright where ``m1 · x < s1`` and (or, with
    ``union``) ``m2 · x < s2``, ``x`` in px from the centre; a straight edge has ``s2 = +inf``); ``split``
    ``(n, 3)`` NaN for a model between two surfaces (``bright`` and ``dark``), else the line ``m3 · x < s3``
    that holds ``dark`` outside the wedge (``other`` beyond it); or None where no pixel has one.  ``compiled``:
    the compiled kernels where Numba is installed (else, and with False, the NumPy definitions)."""
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
    zone_ys, zone_xs, flat = zone
    kernels = compiled_kernels() if compiled else None
    ys, xs, alpha, bright, dark, normal, offset, fit_error = _two_surface_models(src, brightness, finite, flat,
                                                                                zone_ys, zone_xs, kernels)
    straight = fit_error <= MAX_FIT_ERROR
    wedge = np.column_stack([normal, offset, np.ones(ys.size), np.zeros(ys.size), np.full(ys.size, np.inf),
                             np.zeros(ys.size)])
    ok = straight.copy()
    model_index = np.full(src.shape[:2], -1, np.int64)
    model_index[ys[straight], xs[straight]] = np.arange(int(straight.sum()))
    lines = np.ascontiguousarray(wedge[straight, :3])
    # corners: where no straight edge fits, and where one fits loosely and a wedge better
    limit = np.where(straight, CORNER_GAIN * fit_error, MAX_FIT_ERROR)
    ci = np.flatnonzero(~straight | (fit_error > CORNER_TRY_FIT))
    if straight.any() and ci.size:
        found, sides = _corner_models(model_index, lines, ys[ci], xs[ci], np.ascontiguousarray(alpha[ci]),
                                      np.ascontiguousarray(limit[ci]), kernels)
        wedge[ci[found]] = sides[found]
        ok[ci[found]] = True
    line_colours = np.ascontiguousarray(np.hstack([bright[straight], dark[straight]]))
    ys, xs, wedge, bright, dark = (k[ok] for k in (ys, xs, wedge, bright, dark))
    split, other = np.full((ys.size, 3), np.nan), np.full((ys.size, 3), np.nan)
    # three surfaces: the windows beside an edge that no model between two fits
    modelled = np.zeros(src.shape[:2], bool)
    modelled[ys, xs] = True
    rest = np.flatnonzero(~modelled[zone_ys, zone_xs])
    if lines.shape[0] and rest.size:
        found, params = _three_surface_models(src, flat, zone_ys[rest], zone_xs[rest], model_index,
                                              lines, line_colours, kernels)
        if found.any():
            params = params[found]
            ys, xs = np.concatenate([ys, zone_ys[rest][found]]), np.concatenate([xs, zone_xs[rest][found]])
            wedge, split = np.concatenate([wedge, params[:, :7]]), np.concatenate([split, params[:, 7:10]])
            bright, dark = np.concatenate([bright, params[:, 10:13]]), np.concatenate([dark, params[:, 13:16]])
            other = np.concatenate([other, params[:, 16:19]])
    if ys.size == 0:
        return None
    index = np.full(src.shape[:2], -1.0, np.float32)  # float32 for OpenCV's lookup: exact below 2²⁴ models
    index[ys, xs] = np.arange(ys.size, dtype=np.float32)
    return index, np.stack([ys, xs], axis=1), wedge, bright, dark, split, other


def _two_surface_models(src: np.ndarray, brightness: np.ndarray, finite: np.ndarray, flat: np.ndarray,
                        ys: np.ndarray, xs: np.ndarray, kernels):
    """Of the pixels ``(ys, xs)`` beside an edge, those whose 3 × 3 window lies between two flat surfaces, with
    the straight edge that best reproduces their nine shares: ``(ys, xs, alpha (n, 9), bright (n, 3),
    dark (n, 3), normal (n, 2), offset (n,), fit_error (n,))`` (``fit_error`` inf where no straight edge is
    tried; the compiled kernel, or with ``kernels`` None the NumPy definitions)."""
    if kernels is not None:
        status, params = np.empty(ys.size, np.int8), np.empty((ys.size, 19))
        kernels.edge_models(src, brightness, flat, finite, ys, xs,
                            window_offsets(WINDOW_RADIUS_PX), np.asarray(ANGLE_STEPS_RAD, np.float64), TIE,
                            MIN_SEPARATION, MAX_RESIDUAL, MAX_FIT_ERROR, status, params)
        keep = status > 0
        ys, xs, status, params = ys[keep], xs[keep], status[keep], params[keep]
        fit_error = np.where(status == 1, params[:, 18], np.inf)
        return ys, xs, params[:, 9:18], params[:, 3:6], params[:, 6:9], params[:, :2], params[:, 2], fit_error
    ys, xs, alpha, bright, dark = _two_surface_shares(src, brightness, finite, flat, ys, xs)
    normal, offset, fit_error = _straight_edge(alpha)
    return ys, xs, alpha, bright, dark, normal, offset, np.where(fit_error <= MAX_FIT_ERROR, fit_error, np.inf)


def _corner_models(model_index: np.ndarray, lines: np.ndarray, ys: np.ndarray, xs: np.ndarray, alpha: np.ndarray,
                   limits: np.ndarray, kernels) -> tuple[np.ndarray, np.ndarray]:
    """For the windows ``(ys, xs)`` between two surfaces whose shares ``alpha`` ``(n, 9)`` no straight edge fits,
    or one fits loosely: the wedge of two straight edges fitted within :data:`CORNER_RADIUS_PX` (``model_index``
    their rows in ``lines`` ``(m, 3)``) that best reproduces the shares, and whether its largest error is within
    the window's ``limits`` ``(n,)``: ``(found (n,), wedge (n, 7))`` (the compiled kernel, or with ``kernels``
    None the NumPy definition)."""
    found, sides = np.zeros(ys.size, bool), np.zeros((ys.size, 7))
    settings = (CORNER_RADIUS_PX, CORNER_MAX_LINES, SAME_LINE_COS, SAME_LINE_PX, CORNER_MIN_SIN, TIE, limits)
    if kernels is not None:
        kernels.corner_models(model_index, lines, ys, xs, alpha, *settings, found, sides)
        return found, sides
    for i in range(ys.size):
        sides[i], found[i] = _corner_model(model_index, lines, int(ys[i]), int(xs[i]), alpha[i], limits[i])
    return found, sides


def _corner_model(model_index: np.ndarray, lines: np.ndarray, y: int, x: int, alpha: np.ndarray, limit: float
                  ) -> tuple[np.ndarray, bool]:
    """One window of :func:`_corner_models` (the NumPy definition of the compiled ``corner_models``)."""
    h, w = model_index.shape
    r = CORNER_RADIUS_PX
    cand: list[tuple[float, float, float]] = []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            yy, xx = y + dy, x + dx
            if not (0 <= yy < h and 0 <= xx < w) or model_index[yy, xx] < 0:
                continue
            mx, my, s = lines[model_index[yy, xx]]
            if not np.isfinite(s):
                continue
            c = s + mx * dx + my * dy
            if not any(mx * a + my * b > SAME_LINE_COS and abs(c - o) < SAME_LINE_PX for a, b, o in cand) \
                    and len(cand) < CORNER_MAX_LINES:
                cand.append((mx, my, c))
    best, pick = np.inf, None
    for a in range(len(cand)):
        for b in range(a + 1, len(cand)):
            if abs(cand[a][0] * cand[b][1] - cand[a][1] * cand[b][0]) < CORNER_MIN_SIN:
                continue
            for union in (False, True):
                wedge = (*cand[a], *cand[b], float(union))
                err = sum((_wedge_share(q % 3 - 1.0, q // 3 - 1.0, (1.0, 0.0), (0.0, 1.0), wedge) - alpha[q]) ** 2
                          for q in range(9))
                if err < best * (1.0 - TIE) - TIE:
                    best, pick = err, wedge
    if pick is None:
        return np.zeros(7), False
    fit = max(abs(_wedge_share(q % 3 - 1.0, q // 3 - 1.0, (1.0, 0.0), (0.0, 1.0), pick) - alpha[q]) for q in range(9))
    return np.array(pick), bool(fit <= limit)


def _three_surface_models(src: np.ndarray, flat: np.ndarray, ys: np.ndarray, xs: np.ndarray,
                          model_index: np.ndarray, lines: np.ndarray, line_colours: np.ndarray, kernels
                          ) -> tuple[np.ndarray, np.ndarray]:
    """For the windows ``(ys, xs)`` beside an edge that no model between two surfaces fits: the three surfaces
    around (module docstring), and the surface ``X`` bounded by one or two of the straight edges fitted within
    :data:`CORNER_RADIUS_PX` (``model_index`` their rows in ``lines`` ``(m, 3)``, whose sides' colours are
    ``line_colours`` ``(m, 6)``) with the other two split by a third, that best reproduce the nine pixels, kept
    when every one is within :data:`MAX_FIT_ERROR` of the brightest and darkest surfaces' difference:
    ``(found (n,), params (n, 19))``, ``params`` ``X``'s wedge (7), the split ``(m3x, m3y, s3)`` holding ``Y``,
    and the colours of ``X``, ``Y`` and ``Z`` (the compiled kernel, or with ``kernels`` None the NumPy
    definition)."""
    found, params = np.zeros(ys.size, bool), np.zeros((ys.size, 19))
    settings = (_nearest_first(CORNER_RADIUS_PX), THREE_MAX_LINES, SAME_LINE_COS, SAME_LINE_PX, CORNER_MIN_SIN,
                EDGE_CONTRAST, THREE_COLOUR_TOL, MAX_FIT_ERROR, TIE)
    if kernels is not None:
        kernels.three_surface_models(src, flat, ys, xs, window_offsets(WINDOW_RADIUS_PX), model_index,
                                     lines, line_colours, *settings, found, params)
        return found, params
    for i in range(ys.size):
        params[i], found[i] = _three_surface_model(src, flat, int(ys[i]), int(xs[i]), model_index, lines,
                                                   line_colours)
    return found, params


def _nearest_first(radius: int) -> np.ndarray:
    """``(K, 2)``: the ``(dy, dx)`` of a ``(2 radius + 1)²`` window, its centre first, then nearest first."""
    return np.vstack([np.zeros((1, 2), np.int64), window_offsets(radius)])


def _surface_levels(samples: np.ndarray) -> np.ndarray | None:
    """The three surfaces among the colours ``samples`` ``(k, 3)`` (module docstring): their colours ``(3, 3)``,
    darkest first, each the mean of the samples nearest its level in ratio; None where they do not hold three
    levels."""
    values = samples[:, 0] + samples[:, 1] + samples[:, 2]
    if values.size == 0:
        return None
    top, bottom = values.max(), values.min()
    if not (bottom > 0.0 and top > EDGE_CONTRAST * EDGE_CONTRAST * bottom):
        return None
    ratio = np.minimum(values / bottom, top / values)
    middle, score = values[np.argmax(ratio)], ratio.max()
    if not score >= EDGE_CONTRAST:
        return None
    nearest = np.abs(np.log(values)[:, None] - np.log([bottom, middle, top])[None]).argmin(axis=1)
    colours = np.zeros((3, 3))
    for k, c in enumerate(nearest):  # in the samples' order, as the compiled kernel sums them
        colours[c] += samples[k]
    return colours / np.bincount(nearest, minlength=3)[:, None]


def _three_surface_model(src: np.ndarray, flat: np.ndarray, y: int, x: int,
                         model_index: np.ndarray, lines: np.ndarray, line_colours: np.ndarray
                         ) -> tuple[np.ndarray, bool]:
    """One window of :func:`_three_surface_models` (the NumPy definition of the compiled
    ``three_surface_models``)."""
    h, w = model_index.shape
    near = [(dy, dx, model_index[y + dy, x + dx]) for dy, dx in _nearest_first(CORNER_RADIUS_PX)
            if 0 <= y + dy < h and 0 <= x + dx < w and model_index[y + dy, x + dx] >= 0
            and np.isfinite(lines[model_index[y + dy, x + dx], 2])]
    flats = [src[y + dy, x + dx] for dy, dx in window_offsets(WINDOW_RADIUS_PX)
             if 0 <= y + dy < h and 0 <= x + dx < w and flat[y + dy, x + dx]]
    edge_sides = [line_colours[m].reshape(2, 3) for _, _, m in near]
    colours = _surface_levels(np.concatenate([np.reshape(flats, (-1, 3)), *edge_sides]).astype(np.float64))
    if colours is None:
        return np.zeros(19), False
    spread = float(np.sqrt(((colours[2] - colours[0]) ** 2).sum()))
    cand: list[tuple[float, float, float, int, int]] = []
    for dy, dx, m in near:
        d = ((line_colours[m].reshape(2, 1, 3) - colours[None]) ** 2).sum(axis=2)  # (side, surface)
        sides = d.argmin(axis=1)
        if sides[0] == sides[1] or not (np.sqrt(d[[0, 1], sides]) <= THREE_COLOUR_TOL * spread).all():
            continue
        mx, my = lines[m, 0], lines[m, 1]
        c = lines[m, 2] + mx * dx + my * dy
        if not any(mx * a + my * b > SAME_LINE_COS and abs(c - o) < SAME_LINE_PX and (p, q) == tuple(sides)
                   for a, b, o, p, q in cand) and len(cand) < THREE_MAX_LINES:
            cand.append((mx, my, c, int(sides[0]), int(sides[1])))
    window = np.array([src[y + q // 3 - 1, x + q % 3 - 1] for q in range(9)], np.float64)
    if not np.isfinite(window).all():
        return np.zeros(19), False

    def side_of(line, surface):
        return 1.0 if line[3] == surface else (-1.0 if line[4] == surface else 0.0)

    def misfit(wedge, split, sx, sy, sz):
        shares = [_region_shares(q % 3 - 1.0, q // 3 - 1.0, (1.0, 0.0), (0.0, 1.0), wedge, split) for q in range(9)]
        return np.array([np.sqrt(((a * colours[sx] + b * colours[sy] + (1.0 - a - b) * colours[sz]
                                   - window[q]) ** 2).sum()) for q, (a, b) in enumerate(shares)])

    best, pick = np.inf, None
    for sx in range(3):
        sy, sz = (k for k in range(3) if k != sx)
        for a in range(len(cand)):
            ta = side_of(cand[a], sx)
            if ta == 0.0:
                continue
            for bb in range(a, len(cand)):
                tb = side_of(cand[bb], sx)
                if tb == 0.0 or (bb > a and abs(cand[a][0] * cand[bb][1] - cand[a][1] * cand[bb][0])
                                 < CORNER_MIN_SIN):
                    continue
                for union in ((0.0,) if bb == a else (0.0, 1.0)):
                    first = (ta * cand[a][0], ta * cand[a][1], ta * cand[a][2])
                    wedge = (*first, 1.0, 0.0, np.inf, 0.0) if bb == a else \
                        (*first, tb * cand[bb][0], tb * cand[bb][1], tb * cand[bb][2], union)
                    for cc in range(len(cand)):
                        tc = 1.0 if cand[cc][3:] == (sy, sz) else (-1.0 if cand[cc][3:] == (sz, sy) else 0.0)
                        if tc == 0.0:
                            continue
                        split = (tc * cand[cc][0], tc * cand[cc][1], tc * cand[cc][2])
                        err = float((misfit(wedge, split, sx, sy, sz) ** 2).sum())
                        if err < best * (1.0 - TIE) - TIE:
                            best, pick = err, (wedge, split, sx, sy, sz)
    if pick is None:
        return np.zeros(19), False
    wedge, split, sx, sy, sz = pick
    params = np.concatenate([wedge, split, colours[sx], colours[sy], colours[sz]])
    return params, bool(misfit(wedge, split, sx, sy, sz).max() <= MAX_FIT_ERROR * spread)


def _wedge_share(cx: float, cy: float, e1: tuple[float, float], e2: tuple[float, float], wedge) -> float:
    """Share of the parallelogram ``c + [-½, ½] e1 + [-½, ½] e2`` on the bright side of ``wedge`` (the sides
    ``m1 · x < s1`` and, or with ``union`` or, ``m2 · x < s2``): the polygon clipped by both half-planes (with
    ``union``, 1 − the share of the dark wedge)."""
    m1x, m1y, s1, m2x, m2y, s2, union = (float(k) for k in wedge)
    sign = -1.0 if union > 0.5 else 1.0
    share = _clip_share(cx, cy, e1, e2, [(sign * m1x, sign * m1y, sign * s1), (sign * m2x, sign * m2y, sign * s2)])
    return 1.0 - share if union > 0.5 else share


def _region_shares(cx: float, cy: float, e1: tuple[float, float], e2: tuple[float, float], wedge, split
                   ) -> tuple[float, float]:
    """Shares of the parallelogram (as in :func:`_wedge_share`) in a three-surface model's regions: ``X`` inside
    ``wedge``, and ``Y`` outside it and inside ``split`` (``m3 · x < s3``)."""
    m1x, m1y, s1, m2x, m2y, s2, union = (float(k) for k in wedge)
    third = tuple(float(k) for k in split)
    if not np.isfinite(s2):  # X a half-plane
        return (_clip_share(cx, cy, e1, e2, [(m1x, m1y, s1)]),
                _clip_share(cx, cy, e1, e2, [(-m1x, -m1y, -s1), third]))
    sign = -1.0 if union > 0.5 else 1.0
    sides = [(sign * m1x, sign * m1y, sign * s1), (sign * m2x, sign * m2y, sign * s2)]
    inside = _clip_share(cx, cy, e1, e2, sides)
    both = _clip_share(cx, cy, e1, e2, [*sides, third])
    if union > 0.5:  # X the union: outside it is the wedge of the sides' complements
        return 1.0 - inside, both
    return inside, _clip_share(cx, cy, e1, e2, [third]) - both


def _clip_share(cx: float, cy: float, e1: tuple[float, float], e2: tuple[float, float],
                planes: list[tuple[float, float, float]]) -> float:
    """Share of the parallelogram ``c + [-½, ½] e1 + [-½, ½] e2`` in the half-planes ``a x + b y < s`` of
    ``planes`` (Sutherland & Hodgman 1974, one clipping edge after another)."""
    poly = [(cx - 0.5 * e1[0] - 0.5 * e2[0], cy - 0.5 * e1[1] - 0.5 * e2[1]),
            (cx + 0.5 * e1[0] - 0.5 * e2[0], cy + 0.5 * e1[1] - 0.5 * e2[1]),
            (cx + 0.5 * e1[0] + 0.5 * e2[0], cy + 0.5 * e1[1] + 0.5 * e2[1]),
            (cx - 0.5 * e1[0] + 0.5 * e2[0], cy - 0.5 * e1[1] + 0.5 * e2[1])]
    for a, b, s in planes:
        poly = _clip_half_plane(poly, a, b, s)
    n = len(poly)
    area = 0.0
    for k in range(n):
        area += poly[k][0] * poly[(k + 1) % n][1] - poly[(k + 1) % n][0] * poly[k][1]
    whole = abs(e1[0] * e2[1] - e1[1] * e2[0])
    return min(max(0.5 * abs(area) / max(whole, 1e-300), 0.0), 1.0)


def _clip_half_plane(poly: list[tuple[float, float]], a: float, b: float, s: float) -> list[tuple[float, float]]:
    """The convex polygon ``poly`` cut to ``a x + b y < s`` (Sutherland & Hodgman 1974, one clipping edge)."""
    out = []
    n = len(poly)
    for k in range(n):
        (x0, y0), (x1, y1) = poly[k], poly[(k + 1) % n]
        d0, d1 = a * x0 + b * y0 - s, a * x1 + b * y1 - s
        if d0 < 0.0:
            out.append((x0, y0))
        if (d0 < 0.0) != (d1 < 0.0):
            t = d0 / (d0 - d1)
            out.append((x0 + t * (x1 - x0), y0 + t * (y1 - y0)))
    return out


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
    :data:`~omnispectral.mosaic.unmix.WINDOW_RADIUS_PX`) (the NumPy definition of the compiled ``edge_models``)."""
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
    mx, my = np.where(one_side, 1.0, mx), np.where(one_side, 0.0, my)  # any normal: the compiled kernel's
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
