"""Compiled passes of the mixture estimate's single-precision path (``wiener._MixtureKernel``).

The component posterior of a pixel is a softmax of K log-likelihoods, each a quadratic form in the pixel's
brightness-normalized bands (Hirai et al. 2018, Eq. (7) with a Gaussian-mixture prior).  In NumPy that is a
dozen passes over a block (the quadratic features, one small product, the maximum, the floor, the
normalization, the rows of the final product); here it is two:

``relative_log_likelihoods(r, a, quad_form, ia, ib, floor, out)``
    For float32 bands ``r`` ``(N, m)``: ``x = r / (a . r)`` (``|a . r|`` held at ``>= 1e-30``, as the NumPy
    path does), the features ``[x_ia x_ib, x, 1]`` and their products with ``quad_form`` ``(K, F)``, all in
    float64, then ``max(L_j - max_k L_k, floor)`` into ``out`` ``(K, N)`` float32.  The pixels run in
    sub-blocks of ``SUB_BLOCK_PIXELS`` so the features stay in the L1 cache, innermost along the pixels
    (vectorised).  The exponentials are left to NumPy, whose ``exp`` is vectorised (Numba's is a libm call).

``posterior_weighted_rows(p, r, rows, with_posterior)``
    From the exponentials ``p`` ``(K, N)`` float32: normalizes them in place (one reciprocal of their sum per
    pixel) and writes the rows of the estimate's product, ``rows`` ``(F', N)`` float32: ``p_j r_c`` at
    ``j m + c``, then ``r_c`` at ``K m + c``, then (``with_posterior``) ``p_j`` at ``K m + m + j``.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["SUB_BLOCK_PIXELS", "mixture_kernels"]

SUB_BLOCK_PIXELS = 128  # 27 float64 features and K = 9 sums x 128 px = 36 KiB: in a 48 KiB L1 data cache


@built_on_first_use
def mixture_kernels(numba):
    """The compiled passes (module docstring), or ``None`` without Numba."""
    options = {"nogil": True, "cache": True, "boundscheck": False, "error_model": "numpy"}  # no checks, no raise
    sub = SUB_BLOCK_PIXELS

    @numba.njit(fastmath={"contract"}, **options)
    def relative_log_likelihoods(r, a, quad_form, ia, ib, floor, out):
        N, m = r.shape
        K, F = quad_form.shape
        nq = ia.shape[0]
        feats = np.empty((F - 1, sub))  # [products, x]; the constant feature is the start of each sum
        scale = np.empty(sub)
        acc = np.empty((K, sub))
        for s0 in range(0, N, sub):
            n = min(sub, N - s0)
            scale[:n] = 0.0
            for c in range(m):
                ac, xc = a[c], feats[nq + c]
                for i in range(n):
                    v = np.float64(r[s0 + i, c])
                    xc[i] = v
                    scale[i] += ac * v
            for i in range(n):
                g = scale[i]
                scale[i] = 1.0 / (1e-30 if abs(g) < 1e-30 else g)
            for c in range(m):
                xc = feats[nq + c]
                for i in range(n):
                    xc[i] *= scale[i]
            for f in range(nq):
                xa, xb, o = feats[nq + ia[f]], feats[nq + ib[f]], feats[f]
                for i in range(n):
                    o[i] = xa[i] * xb[i]
            for j in range(K):
                q, aj = quad_form[j], acc[j]
                aj[:n] = q[F - 1]
                f = 0
                while f + 4 <= F - 1:  # four features per pass: a quarter of the accumulator's loads and stores
                    q0, q1, q2, q3 = q[f], q[f + 1], q[f + 2], q[f + 3]
                    x0, x1, x2, x3 = feats[f], feats[f + 1], feats[f + 2], feats[f + 3]
                    for i in range(n):
                        aj[i] += q0 * x0[i] + q1 * x1[i] + q2 * x2[i] + q3 * x3[i]
                    f += 4
                while f < F - 1:
                    qf, xf = q[f], feats[f]
                    for i in range(n):
                        aj[i] += qf * xf[i]
                    f += 1
            best = scale  # the reciprocals are used up
            best[:n] = acc[0, :n]
            for j in range(1, K):
                aj = acc[j]
                for i in range(n):
                    best[i] = max(best[i], aj[i])
            for j in range(K):
                aj, o = acc[j], out[j]
                for i in range(n):
                    o[s0 + i] = np.float32(max(aj[i] - best[i], floor))
        return out

    @numba.njit(**options)
    def posterior_weighted_rows(p, r, rows, with_posterior):
        K, N = p.shape
        m = r.shape[1]
        inverse = np.zeros(N, np.float32)
        for j in range(K):
            pj = p[j]
            for i in range(N):
                inverse[i] += pj[i]
        one = np.float32(1.0)
        for i in range(N):
            inverse[i] = one / inverse[i]
        for c in range(m):
            rc = rows[K * m + c]
            for i in range(N):
                rc[i] = r[i, c]
        for j in range(K):
            pj = p[j]
            for i in range(N):
                pj[i] *= inverse[i]
            for c in range(m):
                rc, o = rows[K * m + c], rows[j * m + c]
                for i in range(N):
                    o[i] = pj[i] * rc[i]
            if with_posterior:
                rows[K * m + m + j, :] = pj
        return rows

    return SimpleNamespace(relative_log_likelihoods=relative_log_likelihoods,
                           posterior_weighted_rows=posterior_weighted_rows)
