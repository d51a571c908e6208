"""Compiled loops (Numba) of the mosaic engine: work NumPy can only do in several passes over memory.

Each kernel has a NumPy definition it is tested against (bit for bit where the float32 operations
are the same, to float32 rounding where they are not):

``spline(coef, u, v, out)``
    cubic B-spline evaluation at exact positions (Unser, Aldroubi & Eden 1991) from prefiltered
    coefficients: the 4 × 4 taps in one pass (:func:`omnispectral.mosaic.interp.remap`; reference
    :func:`~omnispectral.mosaic.interp.remap_reference`);
``keys(src, u, v, clamp, out)``
    Keys cubic convolution (``a = -1/2``) at exact positions, the 4 × 4 taps in one pass, and with ``clamp``
    the result clipped to the range of the 2 × 2 source pixels around the position (``cubic`` and
    ``cubic-clamped`` of :func:`omnispectral.mosaic.interp.remap`; reference
    :func:`~omnispectral.mosaic.interp.remap_reference`; to float32 rounding: the reference sums taps in
    another order);
``disagreeing(sums, weights, tol, out)``
    the views that disagree with the median of the voting views, pixel by pixel
    (:func:`omnispectral.mosaic.blending.reject_inconsistent`; the same float32 median and comparisons);
``accumulate(num, den, row0, col0, band0, values, weight)`` / ``divide(num, den, band0, n, out)``
    the linear blend's ``Σ w x``, ``Σ w`` and ``Σ w x / Σ w``
    (:class:`omnispectral.mosaic.blending.LinearBlend`; the same float32 products and sums);
``catmull_rom(nodes, kr, wr, kc, wc, out)``
    the map's separable Catmull–Rom interpolation of a node grid
    (:func:`omnispectral.mosaic.maps.interpolate_nodes`; the same float64 sums in the same order);
``feather(u, v, 2 / W, 2 / H, out)``
    the linear-blending tent weight of float32 positions (:func:`omnispectral.mosaic.blending.feather_weight`;
    the same float32 operations);
``nearest_pixels(u, v, width, height, ia, ja)`` / ``gather_records(records, ia, ja, row0, col0, out)``
    the nearest sensor pixel of each position (NaN as -1, clipped to the sensor; NumPy's ``rint``) with the
    bounds of those pixels, then the records (camera B's parallax map) at them
    (:func:`omnispectral.mosaic.tile.parallax_positions`; the same pixels and values);
``edge_models(src, brightness, flat, finite, ys, xs, around, turns, tie, …, status, params)``
    the straight edge around each source pixel ``(ys, xs)`` (:mod:`omnispectral.mosaic.edges`: its surfaces, the
    nine shares and their tests, the normal's turns and the fit in one pass per pixel; the same float64
    arithmetic as the NumPy path, to its rounding); the windows between two surfaces that no straight edge fits
    are marked with their nine shares;
``corner_models(model_index, lines, ys, xs, alpha, …, ok, params)`` /
``footprint_wedge_shares(px, py, jac, wedges, out)``
    the wedge of two nearby straight edges that best reproduces such a window's shares, and a footprint's share
    of a wedge by clipping its parallelogram (:mod:`omnispectral.mosaic.edges`; the same float64 arithmetic as
    the NumPy definitions, to their rounding);
``three_surface_models(src, flat, ys, xs, around, model_index, lines, line_colours, …, ok, params)`` /
``footprint_region_shares(px, py, jac, wedges, splits, out)``
    the three surfaces around a window that no two-surface model fits, and the regions bounded by nearby straight
    edges that best reproduce its nine pixels; a footprint's shares of those regions by clipping
    (:mod:`omnispectral.mosaic.edges`; the same float64 arithmetic as the NumPy definitions, to their rounding);
``box_average(src, out)``
    the pyramid's 2 × 2 means ignoring NaN (:func:`omnispectral.mosaic.store.box_average_2x2`; float64
    sums of float32 values, exact for all but extreme dynamic ranges, so the same result).

Numba is imported on first use (compiling costs ~1-2 s once per environment; the results are
cached on disk next to this module); ``compiled_kernels()`` returns ``None`` without Numba, and
the callers then run their NumPy definitions.  The kernels release the GIL (Dask's threads run
them in parallel) and start no threads of their own.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["compiled_kernels"]


@built_on_first_use
def compiled_kernels(numba) -> SimpleNamespace | None:
    """The kernels (module docstring), or ``None`` if Numba is not installed."""
    # the inlined helpers are module globals, not closure cells: Numba keys its disk cache on the pickled
    # closure, which differs in every process, and would compile the kernels that call them on every run
    global cubic_weights, spline_taps, tap_grid, keys_weights, keys_rows, half_plane_share, half_plane_offset
    global clip_half_plane, wedge_share, clip_share, region_shares, line_at

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def cubic_weights(t):  # pragma: no cover - compiled
        """The four cubic B-spline weights at fraction ``t`` of the interval (the last from the sum to 1)."""
        sixth = np.float32(1.0 / 6.0)
        one, three, four, six = np.float32(1.0), np.float32(3.0), np.float32(4.0), np.float32(6.0)
        t2 = t * t
        t3 = t2 * t
        w0 = (one - three * t + three * t2 - t3) * sixth
        w1 = (four - six * t2 + three * t3) * sixth
        w3 = t3 * sixth
        return w0, w1, one - w0 - w1 - w3, w3

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def spline_taps(r0, r1, r2, r3, x0, x1, x2, x3, wx, wy, c):  # pragma: no cover - compiled
        """``Σ_k wy_k Σ_l wx_l r_k[x_l, c]`` over the 4 × 4 taps, in the definition's order (float32)."""
        wx0, wx1, wx2, wx3 = wx
        wy0, wy1, wy2, wy3 = wy
        return (wy0 * (wx0 * r0[x0, c] + wx1 * r0[x1, c] + wx2 * r0[x2, c] + wx3 * r0[x3, c])
                + wy1 * (wx0 * r1[x0, c] + wx1 * r1[x1, c] + wx2 * r1[x2, c] + wx3 * r1[x3, c])
                + wy2 * (wx0 * r2[x0, c] + wx1 * r2[x1, c] + wx2 * r2[x2, c] + wx3 * r2[x3, c])
                + wy3 * (wx0 * r3[x0, c] + wx1 * r3[x1, c] + wx2 * r3[x2, c] + wx3 * r3[x3, c]))

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def tap_grid(img, x, y):  # pragma: no cover - compiled
        """The 4 × 4 taps around finite position ``(x, y)`` of ``img`` ``(H, W, C)``: fractions ``(tx, ty)``, the
        four columns, the four rows (views) and the row and column of ``floor`` (all inside, borders replicated)."""
        hs, ws = img.shape[0], img.shape[1]
        # beyond 2 px outside, every tap is the replicated border pixel
        x = min(max(x, np.float32(-2.0)), np.float32(ws + 1))
        y = min(max(y, np.float32(-2.0)), np.float32(hs + 1))
        fx, fy = np.floor(x), np.floor(y)
        ix, iy = int(fx), int(fy)
        cols = (min(max(ix - 1, 0), ws - 1), min(max(ix, 0), ws - 1), min(max(ix + 1, 0), ws - 1),
                min(max(ix + 2, 0), ws - 1))
        # the four rows as views: 2.6x faster than indexing img[y, x, c] (same sums, same order)
        rows = (img[min(max(iy - 1, 0), hs - 1)], img[min(max(iy, 0), hs - 1)], img[min(max(iy + 1, 0), hs - 1)],
                img[min(max(iy + 2, 0), hs - 1)])
        return x - fx, y - fy, cols, rows, min(max(iy, 0), hs - 1)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def spline(coef, u, v, out):  # pragma: no cover - compiled (tested through remap)
        nc = coef.shape[2]
        for i in range(u.shape[0]):
            for j in range(u.shape[1]):
                x, y = u[i, j], v[i, j]
                if not (np.isfinite(x) and np.isfinite(y)):
                    for c in range(nc):
                        out[i, j, c] = np.nan
                    continue
                tx, ty, (x0, x1, x2, x3), (r0, r1, r2, r3), _ = tap_grid(coef, x, y)
                wx, wy = cubic_weights(tx), cubic_weights(ty)
                if nc == 3:  # the engine's case: a constant trip count lets LLVM unroll the channels
                    for c in range(3):
                        out[i, j, c] = spline_taps(r0, r1, r2, r3, x0, x1, x2, x3, wx, wy, c)
                else:
                    for c in range(nc):
                        out[i, j, c] = spline_taps(r0, r1, r2, r3, x0, x1, x2, x3, wx, wy, c)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def keys_weights(t):  # pragma: no cover - compiled
        """Keys' (a = -1/2) weights of the taps at -1, 0, 1, 2 for fraction ``t`` (Keys 1981, Eq. (15))."""
        half, two, three = np.float32(0.5), np.float32(2.0), np.float32(3.0)
        four, five = np.float32(4.0), np.float32(5.0)
        t2 = t * t
        t3 = t2 * t
        return ((-t3 + two * t2 - t) * half, (three * t3 - five * t2 + two) * half,
                (-three * t3 + four * t2 + t) * half, (t3 - t2) * half)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def keys_rows(src, u, v, clamp, out, nc):  # pragma: no cover - compiled
        """:func:`keys` for ``nc`` channels (a constant 3 lets LLVM unroll the channel loop: 1.2x faster)."""
        hs, ws = src.shape[0], src.shape[1]
        for i in range(u.shape[0]):
            for j in range(u.shape[1]):
                x, y = u[i, j], v[i, j]
                if not (np.isfinite(x) and np.isfinite(y)):
                    for c in range(nc):
                        out[i, j, c] = np.nan
                    continue
                tx, ty, (x0, x1, x2, x3), (r0, r1, r2, r3), ny0 = tap_grid(src, x, y)
                wx, wy = keys_weights(tx), keys_weights(ty)
                # the clamp's 2 x 2 neighbours: floor(position) and the next pixel, both inside the source
                nx0, nx1 = x1, min(x1 + 1, ws - 1)
                s0, s1 = src[ny0], src[min(ny0 + 1, hs - 1)]
                for c in range(nc):
                    value = spline_taps(r0, r1, r2, r3, x0, x1, x2, x3, wx, wy, c)
                    if clamp:
                        a, b = s0[nx0, c], s0[nx1, c]
                        d, e = s1[nx0, c], s1[nx1, c]
                        lo = min(min(a, b), min(d, e))
                        hi = max(max(a, b), max(d, e))
                        if value < lo:
                            value = lo
                        elif value > hi:
                            value = hi
                        if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(d) and np.isfinite(e)):
                            value = np.nan
                    out[i, j, c] = value

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def keys(src, u, v, clamp, out):  # pragma: no cover - compiled (tested through remap)
        if src.shape[2] == 3:  # the engine's case
            keys_rows(src, u, v, clamp, out, 3)
        else:
            keys_rows(src, u, v, clamp, out, src.shape[2])

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def disagreeing(sums, weights, tol, out):  # pragma: no cover - compiled (tested through reject_inconsistent)
        n, h, w = sums.shape
        votes = np.empty(n, np.float32)
        any_set = False
        for r in range(h):
            for q in range(w):
                top = np.float32(0.0)
                for i in range(n):
                    top = max(top, weights[i, r, q])
                k = 0
                for i in range(n):
                    x = sums[i, r, q]
                    if weights[i, r, q] > np.float32(1e-3) * top and np.isfinite(x):
                        # insertion into the sorted votes
                        m = k
                        while m > 0 and votes[m - 1] > x:
                            votes[m] = votes[m - 1]
                            m -= 1
                        votes[m] = x
                        k += 1
                if k < 3:
                    continue
                ref = votes[k // 2] if k % 2 else (votes[k // 2 - 1] + votes[k // 2]) / np.float32(2.0)
                bound = tol * abs(ref)
                for i in range(n):
                    if abs(sums[i, r, q] - ref) > bound:
                        out[i, r, q] = True
                        any_set = True
        return any_set

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def accumulate(num, den, row0, col0, band0, values, weight):  # pragma: no cover - compiled
        nc = values.shape[2]
        for i in range(weight.shape[0]):
            for j in range(weight.shape[1]):
                wt = weight[i, j]
                for c in range(nc):
                    num[row0 + i, col0 + j, band0 + c] += wt * values[i, j, c]
                den[row0 + i, col0 + j] += wt

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def divide(num, den, band0, nc, out):  # pragma: no cover - compiled
        for i in range(den.shape[0]):
            for j in range(den.shape[1]):
                d = den[i, j]
                if d > 0:
                    for c in range(band0, band0 + nc):
                        out[i, j, c] = num[i, j, c] / d

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def catmull_rom(nodes, kr, wr, kc, wc, out):  # pragma: no cover - compiled
        h, w = kr.shape[0], kc.shape[0]
        tmp = np.empty((nodes.shape[0], w), np.float64)
        for r in range(nodes.shape[0]):
            for j in range(w):
                k = kc[j]
                tmp[r, j] = (nodes[r, k] * wc[j, 0] + nodes[r, k + 1] * wc[j, 1]) + nodes[r, k + 2] * wc[j, 2] \
                    + nodes[r, k + 3] * wc[j, 3]
        for i in range(h):
            k = kr[i]
            for j in range(w):
                out[i, j] = (tmp[k, j] * wr[i, 0] + tmp[k + 1, j] * wr[i, 1]) + tmp[k + 2, j] * wr[i, 2] \
                    + tmp[k + 3, j] * wr[i, 3]

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def box_average(src, out):  # pragma: no cover - compiled
        hs, ws, nc = src.shape
        for i in range(out.shape[0]):
            for j in range(out.shape[1]):
                for c in range(nc):
                    total = 0.0
                    count = 0
                    for r in range(2 * i, min(2 * i + 2, hs)):
                        for q in range(2 * j, min(2 * j + 2, ws)):
                            x = src[r, q, c]
                            if np.isfinite(x):
                                total += np.float64(x)
                                count += 1
                    out[i, j, c] = np.float32(total / count) if count else np.float32(np.nan)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def feather(u, v, sx, sy, out):  # pragma: no cover - compiled
        one, half, zero = np.float32(1.0), np.float32(0.5), np.float32(0.0)
        for i in range(u.shape[0]):
            for j in range(u.shape[1]):
                x, y = u[i, j], v[i, j]
                if not (np.isfinite(x) and np.isfinite(y)):
                    out[i, j] = zero
                    continue
                wu = min(max(one - abs(sx * (x + half) - one), zero), one)
                wv = min(max(one - abs(sy * (y + half) - one), zero), one)
                out[i, j] = wu * wv

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def nearest_pixels(u, v, width, height, ia, ja):  # pragma: no cover - compiled
        bounds = np.array([width, -1, height, -1], np.int64)  # column min, max; row min, max
        for i in range(u.shape[0]):
            for j in range(u.shape[1]):
                x, y = u[i, j], v[i, j]
                x = np.float32(-1.0) if x != x else x
                y = np.float32(-1.0) if y != y else y
                c = np.int64(min(max(np.rint(x), np.float32(0.0)), np.float32(width - 1)))
                r = np.int64(min(max(np.rint(y), np.float32(0.0)), np.float32(height - 1)))
                ia[i, j], ja[i, j] = c, r
                bounds[0], bounds[1] = min(bounds[0], c), max(bounds[1], c)
                bounds[2], bounds[3] = min(bounds[2], r), max(bounds[3], r)
        return bounds

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def gather_records(records, ia, ja, row0, col0, out):  # pragma: no cover - compiled
        for i in range(ia.shape[0]):
            for j in range(ia.shape[1]):
                r, c = ja[i, j] - row0, ia[i, j] - col0
                for k in range(records.shape[2]):
                    out[i, j, k] = records[r, c, k]

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def half_plane_share(s, a, b):  # pragma: no cover - compiled
        hi, lo = 0.5 * max(abs(a), abs(b)), 0.5 * min(abs(a), abs(b))
        hi = max(hi, 1e-12)
        lo = max(lo, 1e-12 * hi)
        if s < lo - hi:
            r = max(s + hi + lo, 0.0) ** 2 / (8.0 * hi * lo)
        elif s < hi - lo:
            r = (s + hi) / (2.0 * hi)
        else:
            r = 1.0 - max(hi + lo - s, 0.0) ** 2 / (8.0 * hi * lo)
        return min(max(r, 0.0), 1.0)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def half_plane_offset(share, a, b):  # pragma: no cover - compiled
        hi, lo = 0.5 * max(abs(a), abs(b)), 0.5 * min(abs(a), abs(b))
        hi = max(hi, 1e-12)
        lo = max(lo, 1e-12 * hi)
        corner = lo / (2.0 * hi)
        share = min(max(share, 0.0), 1.0)
        if share < corner:
            return np.sqrt(8.0 * hi * lo * share) - hi - lo
        if share <= 1.0 - corner:
            return 2.0 * hi * share - hi
        return hi + lo - np.sqrt(8.0 * hi * lo * (1.0 - share))

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def clip_half_plane(px, py, n, a, b, s, qx, qy):  # pragma: no cover - compiled
        """The convex polygon ``(px, py)[:n]`` cut to ``a x + b y < s``, into ``(qx, qy)``; its vertex count."""
        m = 0
        for k in range(n):
            x0, y0, x1, y1 = px[k], py[k], px[(k + 1) % n], py[(k + 1) % n]
            d0, d1 = a * x0 + b * y0 - s, a * x1 + b * y1 - s
            if d0 < 0.0:
                qx[m], qy[m] = x0, y0
                m += 1
            if (d0 < 0.0) != (d1 < 0.0):
                t = d0 / (d0 - d1)
                qx[m], qy[m] = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
                m += 1
        return m

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def clip_share(cx, cy, e1x, e1y, e2x, e2y, planes, k, buf):  # pragma: no cover - compiled
        """Share of the parallelogram ``c + [-1/2, 1/2] e1 + [-1/2, 1/2] e2`` in the first ``k`` half-planes
        ``planes[j, 0] x + planes[j, 1] y < planes[j, 2]``; ``buf`` ``(4, 8)`` scratch."""
        px, py, qx, qy = buf[0], buf[1], buf[2], buf[3]
        px[0], py[0] = cx - 0.5 * e1x - 0.5 * e2x, cy - 0.5 * e1y - 0.5 * e2y
        px[1], py[1] = cx + 0.5 * e1x - 0.5 * e2x, cy + 0.5 * e1y - 0.5 * e2y
        px[2], py[2] = cx + 0.5 * e1x + 0.5 * e2x, cy + 0.5 * e1y + 0.5 * e2y
        px[3], py[3] = cx - 0.5 * e1x + 0.5 * e2x, cy - 0.5 * e1y + 0.5 * e2y
        n = 4
        for j in range(k):
            n = clip_half_plane(px, py, n, planes[j, 0], planes[j, 1], planes[j, 2], qx, qy)
            for v in range(n):
                px[v], py[v] = qx[v], qy[v]
        area = 0.0
        for v in range(n):
            area += px[v] * py[(v + 1) % n] - px[(v + 1) % n] * py[v]
        whole = abs(e1x * e2y - e1y * e2x)
        return min(max(0.5 * abs(area) / max(whole, 1e-300), 0.0), 1.0)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def region_shares(cx, cy, e1x, e1y, e2x, e2y, wedge, split, planes, buf):  # pragma: no cover - compiled
        """Shares of the parallelogram in a three-surface model's regions: ``X`` (the half-plane or wedge
        ``wedge``, as in ``wedge_share``) and ``Y`` (outside ``X`` and inside ``split``: ``m3 x < s3``)."""
        for c in range(3):
            planes[2, c] = split[c]
        if not np.isfinite(wedge[5]):  # X a half-plane
            planes[0, 0], planes[0, 1], planes[0, 2] = wedge[0], wedge[1], wedge[2]
            share_x = clip_share(cx, cy, e1x, e1y, e2x, e2y, planes, 1, buf)
            planes[1, 0], planes[1, 1], planes[1, 2] = -wedge[0], -wedge[1], -wedge[2]
            return share_x, clip_share(cx, cy, e1x, e1y, e2x, e2y, planes[1:], 2, buf)
        sign = -1.0 if wedge[6] > 0.5 else 1.0
        planes[0, 0], planes[0, 1], planes[0, 2] = sign * wedge[0], sign * wedge[1], sign * wedge[2]
        planes[1, 0], planes[1, 1], planes[1, 2] = sign * wedge[3], sign * wedge[4], sign * wedge[5]
        inside = clip_share(cx, cy, e1x, e1y, e2x, e2y, planes, 2, buf)
        both = clip_share(cx, cy, e1x, e1y, e2x, e2y, planes, 3, buf)
        if sign < 0.0:  # X the union: outside it is the wedge of the sides' complements
            return 1.0 - inside, both
        return inside, clip_share(cx, cy, e1x, e1y, e2x, e2y, planes[2:], 1, buf) - both

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def wedge_share(cx, cy, e1x, e1y, e2x, e2y, m1x, m1y, s1, m2x, m2y, s2, union, planes, buf):  # pragma: no cover
        """Share of the parallelogram ``c + [-1/2, 1/2] e1 + [-1/2, 1/2] e2`` in the wedge ``m1 x < s1`` and
        ``m2 x < s2`` (with ``union``: or); ``planes`` ``(3, 3)`` and ``buf`` ``(4, 8)`` scratch."""
        sign = -1.0 if union else 1.0
        planes[0, 0], planes[0, 1], planes[0, 2] = sign * m1x, sign * m1y, sign * s1
        planes[1, 0], planes[1, 1], planes[1, 2] = sign * m2x, sign * m2y, sign * s2
        share = clip_share(cx, cy, e1x, e1y, e2x, e2y, planes, 2, buf)
        return 1.0 - share if union else share

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def line_at(model_index, lines, yy, xx):  # pragma: no cover - compiled
        """The row in ``lines`` of the straight edge fitted at ``(yy, xx)``, or -1 (outside, none)."""
        if yy < 0 or yy >= model_index.shape[0] or xx < 0 or xx >= model_index.shape[1]:
            return -1
        m = model_index[yy, xx]
        return m if m >= 0 and np.isfinite(lines[m, 2]) else -1

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def three_surface_models(src, flat, ys, xs, around, model_index, lines, line_colours, reach,
                             max_lines, same_cos, same_px, min_sin, contrast, colour_tol, max_fit, tie, ok,
                             params):  # pragma: no cover - compiled (tested against edges' NumPy path)
        h, w = flat.shape
        colours, counts, level = np.empty((3, 3)), np.empty(3), np.empty(3)
        cand, kind = np.empty((max_lines, 3)), np.empty((max_lines, 2), np.int64)
        planes, buf = np.empty((3, 3)), np.empty((4, 8))
        wedge, split, best_wedge, best_split = np.empty(7), np.empty(3), np.empty(7), np.empty(3)
        window, sides = np.empty((9, 3)), np.empty(2, np.int64)
        samples = np.empty((around.shape[0] + 2 * reach.shape[0], 3))
        for i in range(ys.shape[0]):
            y, x = ys[i], xs[i]
            ok[i] = False
            # the surfaces seen around: the flat pixels, and the sides of the straight edges nearby
            ns = 0
            for k in range(around.shape[0]):
                yy, xx = y + around[k, 0], x + around[k, 1]
                if 0 <= yy < h and 0 <= xx < w and flat[yy, xx]:
                    for c in range(3):
                        samples[ns, c] = src[yy, xx, c]
                    ns += 1
            for k in range(reach.shape[0]):
                m = line_at(model_index, lines, y + reach[k, 0], x + reach[k, 1])
                if m >= 0:
                    for c in range(6):
                        samples[ns + c // 3, c % 3] = line_colours[m, c]
                    ns += 2
            # three brightness levels among them: the brightest, the darkest, and the one farthest from both in
            # ratio; each surface the mean of the samples nearest its level
            top, bottom = -np.inf, np.inf
            for k in range(ns):
                b = samples[k, 0] + samples[k, 1] + samples[k, 2]
                top, bottom = max(top, b), min(bottom, b)
            if not (bottom > 0.0 and top > contrast * contrast * bottom):
                continue
            middle, score = 0.0, 0.0
            for k in range(ns):
                b = samples[k, 0] + samples[k, 1] + samples[k, 2]
                r = min(b / bottom, top / b)
                if r > score:
                    middle, score = b, r
            if not score >= contrast:
                continue
            level[0], level[1], level[2] = np.log(bottom), np.log(middle), np.log(top)
            colours[:] = 0.0
            counts[:] = 0.0
            for k in range(ns):
                lb = np.log(samples[k, 0] + samples[k, 1] + samples[k, 2])
                c = 0
                for j in range(1, 3):
                    if abs(lb - level[j]) < abs(lb - level[c]):
                        c = j
                counts[c] += 1.0
                for b in range(3):
                    colours[c, b] += samples[k, b]
            for c in range(3):
                for b in range(3):
                    colours[c, b] /= counts[c]
            spread = 0.0
            for b in range(3):
                spread += (colours[2, b] - colours[0, b]) ** 2
            spread = np.sqrt(spread)
            # the straight edges around, nearest first, each between two of the surfaces (by its sides' colours)
            n = 0
            for k in range(reach.shape[0]):
                dy, dx = reach[k, 0], reach[k, 1]
                m = line_at(model_index, lines, y + dy, x + dx)
                if m < 0:
                    continue
                near = True
                for side in range(2):
                    best_d, best_c = np.inf, 0
                    for c in range(3):
                        d = 0.0
                        for b in range(3):
                            d += (line_colours[m, 3 * side + b] - colours[c, b]) ** 2
                        if d < best_d:
                            best_d, best_c = d, c
                    sides[side] = best_c
                    near &= np.sqrt(best_d) <= colour_tol * spread
                if not near or sides[0] == sides[1]:
                    continue
                mx, my = lines[m, 0], lines[m, 1]
                c = lines[m, 2] + mx * dx + my * dy
                seen = False
                for j in range(n):
                    if (mx * cand[j, 0] + my * cand[j, 1] > same_cos and abs(c - cand[j, 2]) < same_px
                            and kind[j, 0] == sides[0] and kind[j, 1] == sides[1]):
                        seen = True
                        break
                if not seen and n < max_lines:
                    cand[n, 0], cand[n, 1], cand[n, 2] = mx, my, c
                    kind[n, 0], kind[n, 1] = sides[0], sides[1]
                    n += 1
            finite = True
            for q in range(9):
                for b in range(3):
                    window[q, b] = src[y + q // 3 - 1, x + q % 3 - 1, b]
                    finite &= np.isfinite(window[q, b])
            if not finite:
                continue
            # the surface X bounded by one or two of them, the other two split by a third
            best, best_x = np.inf, -1
            for sx in range(3):
                sy, sz = (1, 2) if sx == 0 else ((0, 2) if sx == 1 else (0, 1))
                for a in range(n):
                    ta = 1.0 if kind[a, 0] == sx else (-1.0 if kind[a, 1] == sx else 0.0)
                    if ta == 0.0:
                        continue
                    for bb in range(a, n):
                        tb = 1.0 if kind[bb, 0] == sx else (-1.0 if kind[bb, 1] == sx else 0.0)
                        if tb == 0.0 or (bb > a and abs(cand[a, 0] * cand[bb, 1] - cand[a, 1] * cand[bb, 0]) < min_sin):
                            continue
                        for u in range(1 if bb == a else 2):
                            wedge[0], wedge[1], wedge[2] = ta * cand[a, 0], ta * cand[a, 1], ta * cand[a, 2]
                            if bb == a:
                                wedge[3], wedge[4], wedge[5], wedge[6] = 1.0, 0.0, np.inf, 0.0
                            else:
                                wedge[3], wedge[4], wedge[5] = tb * cand[bb, 0], tb * cand[bb, 1], tb * cand[bb, 2]
                                wedge[6] = float(u)
                            for cc in range(n):
                                if kind[cc, 0] == sy and kind[cc, 1] == sz:
                                    tc = 1.0
                                elif kind[cc, 0] == sz and kind[cc, 1] == sy:
                                    tc = -1.0
                                else:
                                    continue
                                split[0], split[1], split[2] = tc * cand[cc, 0], tc * cand[cc, 1], tc * cand[cc, 2]
                                err, bound = 0.0, best * (1.0 - tie) - tie
                                for q in range(9):  # the sum only grows: stop once it cannot beat the best
                                    share_x, share_y = region_shares(q % 3 - 1.0, q // 3 - 1.0, 1.0, 0.0, 0.0, 1.0,
                                                                     wedge, split, planes, buf)
                                    for b in range(3):
                                        err += (share_x * colours[sx, b] + share_y * colours[sy, b]
                                                + (1.0 - share_x - share_y) * colours[sz, b] - window[q, b]) ** 2
                                    if not err < bound:
                                        break
                                if err < bound:
                                    best, best_x = err, sx
                                    best_wedge[:] = wedge
                                    best_split[:] = split
            if best_x < 0:
                continue
            sx = best_x
            sy, sz = (1, 2) if sx == 0 else ((0, 2) if sx == 1 else (0, 1))
            worst = 0.0
            for q in range(9):
                share_x, share_y = region_shares(q % 3 - 1.0, q // 3 - 1.0, 1.0, 0.0, 0.0, 1.0, best_wedge,
                                                 best_split, planes, buf)
                d = 0.0
                for b in range(3):
                    d += (share_x * colours[sx, b] + share_y * colours[sy, b]
                          + (1.0 - share_x - share_y) * colours[sz, b] - window[q, b]) ** 2
                worst = max(worst, np.sqrt(d))
            if not worst <= max_fit * spread:
                continue
            ok[i] = True
            params[i, :7] = best_wedge
            params[i, 7:10] = best_split
            for b in range(3):
                params[i, 10 + b], params[i, 13 + b], params[i, 16 + b] = (colours[sx, b], colours[sy, b],
                                                                          colours[sz, b])

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def footprint_region_shares(px, py, jac, wedges, splits, out):  # pragma: no cover - compiled (tested through edges)
        planes, buf = np.empty((3, 3)), np.empty((4, 8))
        for i in range(px.shape[0]):
            out[i, 0], out[i, 1] = region_shares(px[i], py[i], jac[i, 0, 0], jac[i, 1, 0], jac[i, 0, 1], jac[i, 1, 1],
                                                 wedges[i], splits[i], planes, buf)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def corner_models(model_index, lines, ys, xs, alpha, radius, max_lines, same_cos, same_px, min_sin, tie, limits,
                      ok, params):  # pragma: no cover - compiled (tested against edges' NumPy path)
        cand = np.empty((max_lines, 3))
        planes, buf = np.empty((3, 3)), np.empty((4, 8))
        for i in range(ys.shape[0]):
            y, x = ys[i], xs[i]
            ok[i] = False
            # the straight edges around, each as a line in this window's frame, near-duplicates once
            n = 0
            for dy in range(-radius, radius + 1):
                for dx in range(-radius, radius + 1):
                    k = line_at(model_index, lines, y + dy, x + dx)
                    if k < 0:
                        continue
                    mx, my = lines[k, 0], lines[k, 1]
                    c = lines[k, 2] + mx * dx + my * dy
                    seen = False
                    for j in range(n):
                        if mx * cand[j, 0] + my * cand[j, 1] > same_cos and abs(c - cand[j, 2]) < same_px:
                            seen = True
                            break
                    if not seen and n < max_lines:
                        cand[n, 0], cand[n, 1], cand[n, 2] = mx, my, c
                        n += 1
            best, bi, bj, bu = np.inf, -1, -1, False
            for a in range(n):
                for b in range(a + 1, n):
                    if abs(cand[a, 0] * cand[b, 1] - cand[a, 1] * cand[b, 0]) < min_sin:
                        continue
                    for u in range(2):
                        err = 0.0
                        for q in range(9):
                            share = wedge_share(q % 3 - 1.0, q // 3 - 1.0, 1.0, 0.0, 0.0, 1.0, cand[a, 0], cand[a, 1],
                                                cand[a, 2], cand[b, 0], cand[b, 1], cand[b, 2], u == 1, planes, buf)
                            err += (share - alpha[i, q]) ** 2
                        if err < best * (1.0 - tie) - tie:
                            best, bi, bj, bu = err, a, b, u == 1
            if bi < 0:
                continue
            fit = 0.0
            for q in range(9):
                share = wedge_share(q % 3 - 1.0, q // 3 - 1.0, 1.0, 0.0, 0.0, 1.0, cand[bi, 0], cand[bi, 1],
                                    cand[bi, 2], cand[bj, 0], cand[bj, 1], cand[bj, 2], bu, planes, buf)
                fit = max(fit, abs(share - alpha[i, q]))
            if not fit <= limits[i]:
                continue
            ok[i] = True
            params[i, 0], params[i, 1], params[i, 2] = cand[bi, 0], cand[bi, 1], cand[bi, 2]
            params[i, 3], params[i, 4], params[i, 5] = cand[bj, 0], cand[bj, 1], cand[bj, 2]
            params[i, 6] = 1.0 if bu else 0.0

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def footprint_wedge_shares(px, py, jac, wedges, out):  # pragma: no cover - compiled (tested through edges)
        planes, buf = np.empty((3, 3)), np.empty((4, 8))
        for i in range(px.shape[0]):
            out[i] = wedge_share(px[i], py[i], jac[i, 0, 0], jac[i, 1, 0], jac[i, 0, 1], jac[i, 1, 1], wedges[i, 0],
                                 wedges[i, 1], wedges[i, 2], wedges[i, 3], wedges[i, 4], wedges[i, 5],
                                 wedges[i, 6] > 0.5, planes, buf)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def edge_models(src, brightness, flat, finite, ys, xs, around, turns, tie, min_separation, max_residual,
                    max_fit, status, params):  # pragma: no cover - compiled (tested against edges' NumPy path)
        h, w = flat.shape
        alpha = np.empty(9)
        for i in range(ys.shape[0]):
            y, x = ys[i], xs[i]
            status[i] = 0
            # the surfaces: the nearest flat pixels above and below the middle of the brightest and darkest
            khi, klo, n_flat = -1, -1, 0
            top, bottom = np.float32(-np.inf), np.float32(np.inf)
            for k in range(around.shape[0]):
                yy, xx = y + around[k, 0], x + around[k, 1]
                if yy < 0 or yy >= h or xx < 0 or xx >= w or not flat[yy, xx]:
                    continue
                n_flat += 1
                b = brightness[yy, xx]
                if b > top:
                    top, khi = b, k
                if b < bottom:
                    bottom, klo = b, k
            if n_flat < 2 or khi == klo:
                continue
            mid = np.float32(0.5) * (top + bottom)
            khi, klo = -1, -1
            for k in range(around.shape[0]):
                yy, xx = y + around[k, 0], x + around[k, 1]
                if yy < 0 or yy >= h or xx < 0 or xx >= w or not flat[yy, xx]:
                    continue
                b = brightness[yy, xx]
                if khi < 0 and b > mid:
                    khi = k
                if klo < 0 and b < mid:
                    klo = k
            y1, x1, y2, x2 = y + around[khi, 0], x + around[khi, 1], y + around[klo, 0], x + around[klo, 1]
            span_sq, bright_sq = 0.0, 0.0
            for c in range(3):
                span_sq += (np.float64(src[y1, x1, c]) - src[y2, x2, c]) ** 2
                bright_sq += np.float64(src[y1, x1, c]) ** 2
            if not np.sqrt(span_sq) > min_separation * np.sqrt(bright_sq):
                continue
            ok = True
            total, gx, gy = 0.0, 0.0, 0.0
            for q in range(9):
                yy, xx = y + q // 3 - 1, x + q % 3 - 1
                if not finite[yy, xx]:
                    ok = False
                    break
                dot, norm_sq = 0.0, 0.0
                for c in range(3):
                    dark = np.float64(src[y2, x2, c])
                    dot += (src[yy, xx, c] - dark) * (src[y1, x1, c] - dark)
                    norm_sq += np.float64(src[yy, xx, c]) ** 2
                a = min(max(dot / max(span_sq, 1e-300), 0.0), 1.0)
                res_sq = 0.0
                for c in range(3):
                    dark = np.float64(src[y2, x2, c])
                    res_sq += (src[yy, xx, c] - dark - a * (src[y1, x1, c] - dark)) ** 2
                if not np.sqrt(res_sq) <= max_residual * np.sqrt(norm_sq):
                    ok = False
                    break
                alpha[q] = a
                total += a
                gx += a * (q % 3 - 1)
                gy += a * (q // 3 - 1)
            if not ok:
                continue
            # two surfaces: their values and the nine shares, whether or not a straight edge fits them
            status[i] = 2
            for c in range(3):
                params[i, 3 + c] = src[y1, x1, c]
                params[i, 6 + c] = src[y2, x2, c]
            for q in range(9):
                params[i, 9 + q] = alpha[q]
            total /= 9.0
            uniform = True
            for q in range(1, 9):
                uniform &= alpha[q] == alpha[0]
            if uniform and (total == 0.0 or total == 1.0):  # one surface: every footprint on that side
                mx, my, offset, fit = 1.0, 0.0, np.inf if total == 1.0 else -np.inf, 0.0
            else:
                if np.sqrt(gx * gx + gy * gy) <= 1e-6:  # no plane through the shares
                    continue
                base = np.arctan2(-gy, -gx)
                best, angle = np.inf, base
                for t in range(turns.shape[0]):
                    cx, cy = np.cos(base + turns[t]), np.sin(base + turns[t])
                    off = 3.0 * half_plane_offset(total, cx, cy)
                    err = 0.0
                    for q in range(9):
                        err += (half_plane_share(off - cx * (q % 3 - 1) - cy * (q // 3 - 1), cx, cy) - alpha[q]) ** 2
                    if err < best * (1.0 - tie) - tie:
                        best, angle = err, base + turns[t]
                mx, my = np.cos(angle), np.sin(angle)
                offset = 3.0 * half_plane_offset(total, mx, my)
                fit = 0.0
                for q in range(9):
                    fit = max(fit, abs(half_plane_share(offset - mx * (q % 3 - 1) - my * (q // 3 - 1), mx, my)
                                       - alpha[q]))
                if not fit <= max_fit:
                    continue
            status[i] = 1
            params[i, 0], params[i, 1], params[i, 2], params[i, 18] = mx, my, offset, fit

    return SimpleNamespace(spline=spline, keys=keys, disagreeing=disagreeing, accumulate=accumulate,
                           divide=divide, catmull_rom=catmull_rom, box_average=box_average, feather=feather,
                           nearest_pixels=nearest_pixels, gather_records=gather_records, edge_models=edge_models,
                           corner_models=corner_models, footprint_wedge_shares=footprint_wedge_shares,
                           three_surface_models=three_surface_models,
                           footprint_region_shares=footprint_region_shares)
