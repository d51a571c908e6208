"""Wiener estimation of spectra from multiband values (paper Eq. (7)) and its mixture extension.

.. math::

    \\hat e = \\bar e + W(\\rho - R\\bar e), \\qquad W = C_{ss} R^t (R C_{ss} R^t + \\sigma^2 I)^{-1}

Forms
-----
``normalized=False``
    Eq. (7) verbatim: :math:`\\bar e` and :math:`C_{ss}` in the absolute units of the prior.  Right
    when the scene has the prior's brightness (a chart lit like the prior).
``normalized=True`` (default)
    Every prior colour signal is scaled to unit brightness :math:`a^t R e = 1` (``a`` = band mean)
    and the observation is scaled the same way before Eq. (7) and back after it:
    :math:`\\hat e = g(\\bar e + W(\\rho/g - R\\bar e))`, :math:`g = a^t\\rho`.  Since ``g`` is linear
    in :math:`\\rho` this is one linear map :math:`\\hat e = M\\rho`, :math:`M = W + (I - WR)\\bar e a^t`:
    spectra stay a linear view of the bands and the estimate is exposure-equivariant, so an HDR
    scene spanning 10^5 in radiance is estimated alike in the shadows and in the sky.
    :math:`\\sigma^2` is then a variance relative to the squared brightness.

Mixture (beyond the paper)
--------------------------
The paper pools colour signals under nine light sources into one covariance.  With
``mixture=True`` the prior keeps one Gaussian component per light source (a Gaussian-mixture
prior); the minimum-mean-square-error estimate is then the posterior-weighted sum of the
per-component Wiener estimates,

.. math:: \\hat e = \\sum_j p(j\\mid\\rho)\\,\\hat e_j, \\qquad
          p(j\\mid\\rho) \\propto \\pi_j\\,\\mathcal N(\\rho; R\\bar e_j, RC_jR^t + \\sigma^2 I),

which adapts to the light a pixel is lit by.  The weights depend only on chromaticity (the
normalized bands), so for fixed weights the estimate is again one linear map
(:meth:`WienerEstimator.linear_map` with ``weights``), e.g. per scene or per region.

Also beyond the paper: the posterior covariance (per-pixel spectral standard deviation, with
the between-component spread for mixtures), a per-pixel, per-band noise variance (from the HDR
merge) added to :math:`\\sigma^2 I`, and clipping to non-negative spectra.  All functions work on
arrays of any leading shape, in chunks of pixels.

Speed
-----
The per-pixel work runs as a few stacked matrix products per block of pixels (:class:`_MixtureKernel`):
the K log-likelihoods from one product of the 28 quadratic features of the normalized bands
(:math:`\\rho_a\\rho_b`, :math:`\\rho_a`, 1) with the coefficients of
:math:`-\\tfrac12(\\rho-R\\bar e_j)^t(RC_jR^t+\\sigma^2I)^{-1}(\\rho-R\\bar e_j)`, and the estimate
:math:`\\sum_j p_j M_j\\rho = \\bar M\\rho + \\sum_j p_j (M_j-\\bar M)\\rho` from one product of the
``(K m)`` coefficients :math:`p\\otimes\\rho` with the stacked map differences (float32 for float32
output; the prior-weighted mean map :math:`\\bar M` in float64, which keeps the float32 rounding of
the cancelling terms small).  With a per-pixel noise variance each pixel's ``m x m`` system is
inverted by a Cholesky factorisation vectorised over the pixels.  Blocks run on
:func:`omnispectral.threads.kernel_threads` threads with BLAS held to one thread.  The original
one-component-at-a-time evaluation stays available as ``_estimate_reference`` and friends; the
tests hold the two to 1e-6.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.prior import SpectralPrior
from omnispectral.spectral.system import MultibandSystem
from omnispectral.spectral.wiener_kernels import mixture_kernels
from omnispectral.threads import blocks, kernel_threads, single_threaded_blas

__all__ = ["BLOCK_PIXELS", "DEFAULT_CHUNK_PIXELS", "NOISY_BLOCK_PIXELS", "SMALL_CALL_PIXELS", "WienerEstimator",
           "apply_linear_map", "wiener_matrix"]

DEFAULT_CHUNK_PIXELS = 1 << 15
BLOCK_PIXELS = 4096  # pixels per block of the fast kernels: the block's temporaries stay in the L2 cache
SMALL_CALL_PIXELS = 256  # below this no thread control: its overhead (~0.1 ms) would dominate
#: pixels per block of the mixture estimate: its float32 product and posterior run faster on longer blocks
#: (one thread, output reused, per 2048 × 1088 frame: 4096 → 0.46 s, 8192 and 16384 → 0.41-0.42 s, 32768 → 0.45 s)
ESTIMATE_BLOCK_PIXELS = 16384
NOISY_BLOCK_PIXELS = 16384  # per-pixel noise: ~100 vector operations per component, longer vectors amortise them


def wiener_matrix(system_matrix: np.ndarray, covariance: np.ndarray, sigma2: float) -> np.ndarray:
    """:math:`W = C R^t (R C R^t + \\sigma^2 I)^{-1}` of Eq. (7), shape ``(n, m)``.

    Parameters
    ----------
    system_matrix : array_like
        ``R`` ``(m, n)``: the bands' sensitivities with the sampling interval folded in
        (:attr:`MultibandSystem.matrix <omnispectral.spectral.system.MultibandSystem.matrix>`).
    covariance : array_like
        ``C`` ``(n, n)``: the prior covariance of the spectra (:math:`C_{ss}`), in the spectra's units squared.
    sigma2 : float
        The noise variance :math:`\\sigma^2`, in the band values' units squared (added to every band).

    Returns
    -------
    numpy.ndarray
        ``W`` ``(n, m)`` float64: ``ê - ē = W (ρ - R ē)``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eq. (7).
    .. [2] S. M. Kay, Fundamentals of Statistical Signal Processing: Estimation Theory, Prentice Hall, 1993,
       Ch. 12 (the linear MMSE (Wiener) estimator).
    """
    R = np.asarray(system_matrix, dtype=np.float64)
    C = np.asarray(covariance, dtype=np.float64)
    CRt = C @ R.T
    A = R @ CRt + sigma2 * np.eye(R.shape[0])
    return np.linalg.solve(A, CRt.T).T  # A symmetric: W^t = A^-1 (C R^t)^t


def _mean_and_covariance(signals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = signals.mean(axis=0)
    d = signals - mean
    return mean, d.T @ d / signals.shape[0]


def _spd_inverse_logdet(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse and log-determinant of symmetric positive-definite ``m x m`` matrices stored ``(m, m, N)``.

    Cholesky factorisation :math:`A = LL^t`, :math:`A^{-1} = L^{-t}L^{-1}`, vectorised over the last
    axis (each step is one operation on N-vectors); non-positive-definite pixels give NaN.
    """
    m = A.shape[0]
    L = np.zeros_like(A)
    with np.errstate(invalid="ignore", divide="ignore"):
        for j in range(m):
            L[j, j] = np.sqrt(A[j, j] - np.einsum("kN,kN->N", L[j, :j], L[j, :j]))
            inv = 1.0 / L[j, j]
            for i in range(j + 1, m):
                L[i, j] = (A[i, j] - np.einsum("kN,kN->N", L[i, :j], L[j, :j])) * inv
        logdet = 2.0 * np.log(np.stack([L[j, j] for j in range(m)])).sum(axis=0)
        Linv = np.zeros_like(A)
        for i in range(m):
            Linv[i, i] = 1.0 / L[i, i]
            for j in range(i):
                Linv[i, j] = -np.einsum("kN,kN->N", L[i, j:i], Linv[j:i, j]) * Linv[i, i]
    Ainv = np.empty_like(A)
    for i in range(m):
        for j in range(i, m):
            Ainv[i, j] = Ainv[j, i] = np.einsum("kN,kN->N", Linv[j:, i], Linv[j:, j])
    return Ainv, logdet


def _spread_quadratic(basis: np.ndarray) -> np.ndarray:
    """``(K, q(q+1)/2, n)`` coefficients with ``(x B_j)^2 = quad(x) @ Q_j`` for bases ``B_j`` ``(q, n)``."""
    ia, ib = np.triu_indices(basis.shape[1])
    twice = np.where(ia == ib, 1.0, 2.0)[None, :, None]
    return twice * basis[:, ia] * basis[:, ib]


def _weighted_spread(p: np.ndarray, x: np.ndarray, basis: np.ndarray, quad: np.ndarray | None) -> np.ndarray:
    """``sum_j p_j (E_j - sum_k p_k E_k)^2`` for ``E_j = x_j @ basis_j`` (``p`` ``(N, K)``, ``x`` ``(N, K, q)``).

    With ``quad`` (:func:`_spread_quadratic` of the bases) the spread is
    ``sum_j p_j E_j^2 - (sum_j p_j E_j)^2``: two matrix products of the posterior-weighted
    (quadratic) coordinates, no ``(N, K, n)`` stack.  The bases are centred on the mean component
    (which leaves the spread unchanged), so in the normalized form (values ~1 per unit brightness)
    the difference keeps ~1e-12 of the spread.  ``quad=None`` forms the differences explicitly, one
    component at a time: for the absolute form, whose bright pixels would cancel too much.
    """
    N, K, q = x.shape
    mean = (p[:, :, None] * x).reshape(N, K * q) @ basis.reshape(K * q, -1)
    if quad is None:
        spread = np.zeros_like(mean)
        for j in range(K):
            d = x[:, j] @ basis[j]
            d -= mean
            d *= d
            d *= p[:, j, None]
            spread += d
        return spread
    ia, ib = np.triu_indices(q)
    xt = np.moveaxis(x, 0, -1)  # (K, q, N): products along contiguous pixels
    feats = xt[:, ia] * xt[:, ib]
    feats *= p.T[:, None, :]
    second = feats.reshape(-1, N).T @ quad.reshape(-1, quad.shape[-1])
    second -= mean * mean
    return second


def _finish_std(variance: np.ndarray, g: np.ndarray, out: np.ndarray) -> None:
    """``out = |g| sqrt(max(variance, 0))`` (variance per unit squared brightness), in place."""
    np.clip(variance, 0.0, None, out=variance)
    np.sqrt(variance, out=variance)
    variance *= np.abs(g)[:, None]
    out[...] = variance


def _checked_output(out: np.ndarray, shape: tuple[int, ...], dtype) -> np.ndarray:
    """``out`` when it is a C-contiguous array of ``shape`` and ``dtype`` (an ``out=`` argument), else ValueError."""
    if not isinstance(out, np.ndarray) or out.shape != tuple(shape) or out.dtype != np.dtype(dtype) \
            or not out.flags.c_contiguous or not out.flags.writeable:
        raise ValueError(f"out must be a writeable C-contiguous {np.dtype(dtype).name} array of shape {tuple(shape)}, "
                         f"got {getattr(out, 'dtype', type(out).__name__)} of shape {getattr(out, 'shape', None)}")
    return out


class _Workspace(dict):
    """Per-thread scratch arrays reused from block to block (no allocation, no page faults per block)."""

    def get(self, name: str, shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
        key = (name, shape, np.dtype(dtype))
        arr = dict.get(self, key)
        if arr is None:
            arr = self[key] = np.empty(shape, dtype)
        return arr


class _MixtureKernel:
    """Stacked per-component constants of a fitted estimator and the fused per-block evaluations.

    Shapes: ``m`` bands, ``n`` wavelengths, ``K`` components.  ``T[j] = M_j^t`` ``(m, n)`` maps bands
    to spectra (``b[j]`` the offset of the absolute form), ``T_mean`` the prior-weighted mean map,
    ``D`` ``(K m, n)`` the stacked differences ``T[j] - T_mean``; ``quad_form`` ``(K, 28)`` the
    log-likelihoods as coefficients of the quadratic features; ``log_norm``
    ``log pi_j - log det(A_j) / 2``; ``spread_*`` / ``noisy_*`` the bases of the posterior std.
    """

    def __init__(self, est: WienerEstimator):
        R = est.system_matrix
        m, n = R.shape
        K = est.n_components
        self.m, self.n, self.K = m, n, K
        self.a = est.normalization
        self.sigma2 = est.sigma2
        eye = np.eye(m)
        log_norm, maps, offsets, post_var, rc, rmu = [], [], [], [], [], []
        for j in range(K):
            C, mu = est.covariances[j], est.means[j]
            RC = R @ C
            A = RC @ R.T + est.sigma2 * eye
            np.linalg.cholesky(A)  # raises LinAlgError unless A is positive definite: the caller falls back
            A_inv = np.linalg.inv(A)
            log_norm.append(np.log(est.weights[j]) - 0.5 * np.linalg.slogdet(A)[1])
            M, b = est._component_map(j)
            maps.append(M.T)
            offsets.append(b)
            post_var.append(np.diag(C) - np.einsum("mn,mk,kn->n", RC, A_inv, RC))
            rc.append(RC)
            rmu.append(R @ mu)
        self.log_norm = np.array(log_norm)
        with np.errstate(divide="ignore"):
            self.log_prior = np.log(est.weights)
        self.T = np.array(maps)  # (K, m, n)
        self.b = np.array(offsets)  # (K, n)
        self.has_offset = bool(np.any(self.b))
        self.T_mean = np.einsum("k,kmn->mn", est.weights, self.T)
        self.D64 = (self.T - self.T_mean).reshape(K * m, n)
        # single precision, one product: rows [p (x) rho | rho | p] against [D; T_mean; b] (the last without offsets)
        self.stacked32 = np.concatenate([self.D64, self.T_mean, *([self.b] if self.has_offset else [])]
                                        ).astype(np.float32)
        self.post_var = np.array(post_var)  # (K, n) per unit squared brightness in the normalized form
        self.means = est.means
        self.prior_A = np.array([rc[j] @ R.T + est.sigma2 * eye for j in range(K)])  # (K, m, m)
        self.RC = np.array(rc)  # (K, m, n)
        self.Rmu = np.array(rmu)  # (K, m)
        self.diagC = np.array([np.diag(c) for c in est.covariances])  # (K, n)
        iu = np.triu_indices(m)
        # -1/2 (x - c)^t A^-1 (x - c) + log_norm as coefficients of [x_i x_j (i <= j), x_i, 1]
        twice = np.where(iu[0] == iu[1], 1.0, 2.0)
        quad = []
        for j in range(K):
            Ai = np.linalg.inv(self.prior_A[j])
            c = self.Rmu[j]
            quad.append(np.concatenate([-0.5 * twice * Ai[iu], Ai @ c, [-0.5 * c @ Ai @ c + self.log_norm[j]]]))
        self.quad_form = np.array(quad)  # (K, m(m+1)/2 + m + 1)
        # spread of the component estimates: bases centred on the prior-weighted mean component
        D = self.T - self.T_mean
        if self.has_offset:  # x = [rho, 1]: the last row carries b_j - b_mean
            D = np.concatenate([D, (self.b - est.weights @ self.b)[:, None, :]], axis=1)
        self.spread_basis = D
        self.spread_quad = _spread_quadratic(D)
        self.mean_of_means = est.weights @ self.means
        # per-pixel noise: E_j = mu_j + x_j RC_j = mean_of_means + [x_j, 1] [RC_j; mu_j - mean_of_means]
        self.noisy_basis = np.concatenate([self.RC, (self.means - self.mean_of_means)[:, None, :]], axis=1)
        self.noisy_quad = _spread_quadratic(self.noisy_basis)
        # diag(RC^t A^-1 RC) = sum over i <= j of A^-1_ij RC_i RC_j (2 - delta_ij): one product per pixel block
        self.triu = tuple(np.asarray(i, np.int64) for i in iu)
        self.quad = np.array([(self.RC[j][iu[0]] * self.RC[j][iu[1]])
                              * np.where(iu[0] == iu[1], 1.0, 2.0)[:, None] for j in range(K)])  # (K, m(m+1)/2, n)

    # ------------------------------------------------------------------ constant noise (sigma2 I)
    def normalized(self, r: np.ndarray, ws: _Workspace) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``rho`` (float64), brightness ``g = a^t rho`` and ``(rho / g)^t`` ``(m, N)``, as the reference does.

        ``g = 1`` for the absolute form.  Buffers come from the thread's workspace ``ws``.
        """
        N = r.shape[0]
        r64 = ws.get("r64", (N, self.m))
        np.copyto(r64, r)
        g = ws.get("g", (N,))
        rho_n_t = ws.get("rho_n_t", (self.m, N))
        if self.a is None:
            g[...] = 1.0
            np.copyto(rho_n_t, r64.T)
        else:
            np.matmul(r64, self.a, out=g)
            g[np.abs(g) < 1e-30] = 1e-30
            np.divide(r64.T, g, out=rho_n_t)
        return r64, g, rho_n_t

    def posterior(self, rho_n_t: np.ndarray, ws: _Workspace, dtype=np.float64) -> np.ndarray:
        """Component posterior ``p(j | rho)`` ``(K, N)`` under ``sigma2 I`` noise, in ``ws``.

        The K log-likelihoods are one product of the quadratic features of ``rho_n`` (products,
        values, 1) with ``quad_form`` ``(K, F)``, in float64 (the quadratic terms cancel); the softmax
        runs in ``(K, N)`` layout (reductions over K along contiguous rows), in place.  Subnormal numbers
        would slow the products that follow tenfold: in float64, log-likelihoods are floored 100 below
        the pixel's largest and posteriors below 1e-30 set to zero; in float32 (the estimate's single
        precision path) the floor is 69 below (e^-69 ≈ 1e-30, a normal float32, far below what moves an
        estimate), and the exponentials keep ~1e-5 of their value at worst (a float32 log-likelihood
        difference near -69), ~2e-6 where they matter.
        """
        N = rho_n_t.shape[1]
        p = ws.get("posterior", (self.K, N), dtype)
        if self.K == 1:
            p[...] = 1.0
            return p
        n_quad = len(self.triu[0])
        feats = ws.get("features", (self.quad_form.shape[1], N))
        for i, (a, b) in enumerate(zip(*self.triu, strict=True)):
            np.multiply(rho_n_t[a], rho_n_t[b], out=feats[i])
        feats[n_quad:-1] = rho_n_t
        feats[-1] = 1.0
        single = np.dtype(dtype) == np.float32
        log_like = ws.get("log_likelihood", (self.K, N)) if single else p  # float64: in place
        np.matmul(self.quad_form, feats, out=log_like)
        column = ws.get("column", (N,))
        np.max(log_like, axis=0, out=column)
        log_like -= column
        np.maximum(log_like, -69.0 if single else -100.0, out=log_like)
        if single:
            np.copyto(p, log_like)
        np.exp(p, out=p)
        if not single:
            p[p < 1e-30] = 0.0
        total = ws.get("total", (N,), dtype)
        np.sum(p, axis=0, out=total)
        p /= total
        return p

    def posterior_into(self, r: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """Component posterior of a block into ``out`` ``(N, K)``."""
        out[...] = self.posterior(self.normalized(r, ws)[2], ws).T

    def estimate(self, r: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """Mixture estimate of a block ``r`` ``(N, m)`` into ``out`` ``(N, n)`` (float32 or float64).

        ``out = rho @ T_mean + (p (x) rho) @ D (+ p @ b)``.  For float32 input and output in the
        normalized form the whole sum is one float32 BLAS ``gemm`` of the stacked rows
        ``[p (x) rho | rho | p]`` against ``stacked32``, written into ``out`` (measured error <= 6e-7 of
        each spectrum's peak: the terms of ``D`` cancel ~10x); the absolute form's maps cancel ~25x, so
        it and float64 data run in float64, the mean map first and the differences accumulated onto it.
        All temporaries live in the thread's workspace ``ws``.
        """
        if out.dtype == np.float32 and r.dtype == np.float32 and self.a is not None and out.flags.c_contiguous:
            self._estimate_single(r, out, ws)
            return
        N = r.shape[0]
        r64, _, rho_n_t = self.normalized(r, ws)
        p = self.posterior(rho_n_t, ws)
        coef_t = ws.get("coef_t", (self.K, self.m, N))  # (p (x) rho)^t, pixels contiguous
        np.multiply(p[:, None, :], r64.T[None, :, :], out=coef_t)
        base = ws.get("base", (N, self.n))
        np.matmul(r64, self.T_mean, out=base)
        if self.has_offset:
            base += p.T @ self.b
        product = ws.get("product", (N, self.n))
        np.matmul(coef_t.reshape(self.K * self.m, N).T, self.D64, out=product)
        base += product
        out[...] = base

    def _estimate_single(self, r: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """:meth:`estimate`'s float32 path: one float32 product of ``[p (x) rho | rho | p]`` into ``out``.

        The posterior and the rows come from two compiled passes
        (:mod:`omnispectral.spectral.wiener_kernels`) around NumPy's vectorised ``exp``: the quantities of
        :meth:`posterior`'s float32 form, summed in another order (within 2e-6 of its posterior); without Numba,
        or for strided rows, from :meth:`posterior`.
        """
        N, K, m = r.shape[0], self.K, self.m
        rows = ws.get("rows_t", (self.stacked32.shape[0], N), np.float32)
        compiled = mixture_kernels() if K > 1 and r.flags.c_contiguous else None  # strided rows: one compilation less
        if compiled is not None:
            p = ws.get("posterior", (K, N), np.float32)
            compiled.relative_log_likelihoods(r, self.a, self.quad_form, *self.triu, -69.0, p)
            np.exp(p, out=p)
            compiled.posterior_weighted_rows(p, r, rows, self.has_offset)
        else:
            p = self.posterior(self.normalized(r, ws)[2], ws, np.float32)
            r_t = rows[K * m:K * m + m]
            np.copyto(r_t, r.T)
            np.multiply(p[:, None, :], r_t[None, :, :], out=rows[:K * m].reshape(K, m, N))
            if self.has_offset:
                rows[K * m + m:] = p
        # NumPy's matmul calls sgemm on the transposed view and releases the GIL (SciPy's BLAS wrappers hold it,
        # which kept a second thread idle)
        np.matmul(rows.T, self.stacked32, out=out)

    def posterior_std(self, r: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """Posterior standard deviation (within-component variance plus spread of the component estimates).

        The component estimates per unit brightness are ``E_j = x B_j`` up to a common term, with
        ``x = [rho_n, 1]`` (the 1 carries the absolute form's offsets) and ``B_j`` the centred maps
        ``spread_basis``.  Normalized form: the spread ``sum_j p_j E_j^2 - (sum_j p_j E_j)^2`` from
        two products of posterior-weighted (quadratic) features of ``x``, computed once for all
        components; absolute form: the differences formed explicitly (:func:`_weighted_spread`).
        """
        _, g, rho_n_t = self.normalized(r, ws)
        N = r.shape[0]
        p = self.posterior(rho_n_t, ws)  # (K, N)
        within = ws.get("within", (N, self.n))
        np.matmul(p.T, self.post_var, out=within)
        if self.a is None:
            x = rho_n_t.T
            if self.has_offset:
                x = np.concatenate([x, np.ones((N, 1))], axis=1)
            within += _weighted_spread(p.T, np.broadcast_to(x[:, None, :], (N, self.K, x.shape[1])),
                                       self.spread_basis, None)
        else:
            q = self.spread_basis.shape[1]  # = m (no offsets in the normalized form)
            pairs = list(zip(*np.triu_indices(q), strict=True))
            weighted = ws.get("p_x", (self.K, q, N))
            np.multiply(p[:, None, :], rho_n_t[None, :, :], out=weighted)
            mean = ws.get("spread_mean", (N, self.n))
            np.matmul(weighted.reshape(-1, N).T, self.spread_basis.reshape(-1, self.n), out=mean)
            quad = ws.get("quad", (len(pairs), N))
            for i, (a, b) in enumerate(pairs):
                np.multiply(rho_n_t[a], rho_n_t[b], out=quad[i])
            weighted_quad = ws.get("p_quad", (self.K, len(pairs), N))
            np.multiply(p[:, None, :], quad[None, :, :], out=weighted_quad)
            second = ws.get("spread_second", (N, self.n))
            np.matmul(weighted_quad.reshape(-1, N).T, self.spread_quad.reshape(-1, self.n), out=second)
            mean *= mean
            second -= mean
            within += second
        _finish_std(within, g, out)

    # ------------------------------------------------------------------ per-pixel noise variance
    def _noisy_components(self, r, v, ws):
        """Per component: ``x = A^-1 (rho_n - R mu)`` ``(N, K, m)``, posterior ``(N, K)`` and ``A^-1`` (upper)."""
        _, g, rho_n_t = self.normalized(r, ws)
        rho_n = rho_n_t.T
        var_n = v / (g * g)[:, None] if self.a is not None else v
        N, m = rho_n.shape
        logp = np.empty((self.K, N))
        xs = np.empty((N, self.K, m + 1))
        xs[:, :, m] = 1.0
        a_upper = np.empty((N, self.K, len(self.triu[0])))
        idx = np.arange(m)
        for j in range(self.K):
            A = np.repeat(self.prior_A[j][:, :, None], N, axis=2)
            A[idx, idx] += var_n.T
            A_inv, logdet = _spd_inverse_logdet(A)
            d = (rho_n - self.Rmu[j]).T  # (m, N)
            x = np.einsum("ijN,jN->iN", A_inv, d)
            xs[:, j, :m] = x.T
            logp[j] = self.log_prior[j] - 0.5 * (np.einsum("iN,iN->N", x, d) + logdet)
            a_upper[:, j] = A_inv[self.triu].T
        logp -= logp.max(axis=0, keepdims=True)
        p = np.exp(logp)
        p /= p.sum(axis=0, keepdims=True)
        return g, p.T, xs, a_upper

    def estimate_noisy(self, r: np.ndarray, v: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """Estimate with noise covariance ``sigma2 I + diag(v)`` per pixel: ``g (mu_bar + sum_j p_j [x_j, 1] B_j)``."""
        g, p, xs, _ = self._noisy_components(r, v.astype(np.float64), ws)
        est = (p[:, :, None] * xs).reshape(r.shape[0], -1) @ self.noisy_basis.reshape(-1, self.n)
        est += self.mean_of_means
        est *= g[:, None]
        out[...] = est

    def posterior_std_noisy(self, r: np.ndarray, v: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        """Posterior std with per-pixel noise: ``diag(C_j) - diag(RC_j^t A^-1 RC_j)`` plus the spread."""
        g, p, xs, a_upper = self._noisy_components(r, v.astype(np.float64), ws)
        within = p @ self.diagC
        within -= (p[:, :, None] * a_upper).reshape(r.shape[0], -1) @ self.quad.reshape(-1, self.n)
        within += _weighted_spread(p, xs, self.noisy_basis, self.noisy_quad if self.a is not None else None)
        _finish_std(within, g, out)

    def posterior_noisy(self, r: np.ndarray, v: np.ndarray, out: np.ndarray, ws: _Workspace) -> None:
        out[...] = self._noisy_components(r, v.astype(np.float64), ws)[1]


def apply_linear_map(rho: np.ndarray, matrix: np.ndarray, offset: np.ndarray | None = None, dtype=np.float32,
                     chunk_pixels: int = DEFAULT_CHUNK_PIXELS) -> np.ndarray:
    """``rho @ matrix.T + offset`` for band values ``(..., m)`` → ``(..., n)``: a linear spectral map applied fast.

    E.g. ``WienerEstimator.linear_map(weights)`` for fixed mixture weights.  Single precision for
    float32 output (the map's ``m`` terms add no visible rounding), blocks of
    ``min(chunk_pixels, BLOCK_PIXELS)`` pixels written straight into the output, on
    :func:`~omnispectral.threads.kernel_threads` threads with BLAS held to one thread.
    """
    rho = np.asarray(rho)
    M = np.asarray(matrix, dtype=np.float64)
    if rho.shape[-1] != M.shape[1]:
        raise ConfigurationError(f"input has {rho.shape[-1]} bands; the map expects {M.shape[1]}")
    work = np.float32 if np.dtype(dtype) == np.float32 else np.float64
    Mt = np.ascontiguousarray(M.T, dtype=work)
    b = None if offset is None or not np.any(offset) else np.asarray(offset, dtype=work)
    lead = rho.shape[:-1]
    flat = rho.reshape(-1, M.shape[1])
    out = np.empty((flat.shape[0], M.shape[0]), dtype=dtype)
    direct = out.dtype == work

    def run(part: list[slice]) -> None:
        for s in part:
            r = flat[s].astype(work, copy=False)
            if direct:
                np.matmul(r, Mt, out=out[s])
            else:
                out[s] = r @ Mt
            if b is not None:
                out[s] += b

    slices = blocks(flat.shape[0], max(1, min(int(chunk_pixels), BLOCK_PIXELS)))
    threads = min(kernel_threads(), len(slices))
    if flat.shape[0] < SMALL_CALL_PIXELS:  # a few small products: BLAS starts no threads for them
        run(slices)
    elif threads <= 1:
        with single_threaded_blas():
            run(slices)
    else:
        parts = [list(p) for p in np.array_split(np.array(slices, dtype=object), threads)]
        with single_threaded_blas(), ThreadPoolExecutor(threads) as pool:
            list(pool.map(run, parts))
    return out.reshape(*lead, M.shape[0])


@dataclass(frozen=True)
class WienerEstimator:
    """A fitted Wiener estimator with one (Eq. (7)) or several (mixture) prior components.

    Build with :meth:`fit`.  Attributes hold the stacked component statistics: ``means``
    ``(K, n)``, ``covariances`` ``(K, n, n)`` and ``weights`` ``(K,)`` (prior probabilities).

    Parameters
    ----------
    wavelength_nm : numpy.ndarray
        ``(n,)`` wavelengths of the spectra (nm).
    system_matrix : numpy.ndarray
        ``R`` ``(m, n)`` of Eq. (6), the sampling interval folded in.
    means : numpy.ndarray
        ``(K, n)`` prior mean :math:`\\bar e_j` of each component (in the normalized form: colour signals
        scaled to unit brightness ``a^t R e = 1``; else in the prior's units).
    covariances : numpy.ndarray
        ``(K, n, n)`` prior covariance :math:`C_j` of each component, in the means' units squared.
    weights : numpy.ndarray
        ``(K,)`` prior probability of each component (its share of the prior's colour signals).
    sigma2 : float
        The noise variance :math:`\\sigma^2` of Eq. (7) (relative to the squared brightness in the
        normalized form).
    normalization : numpy.ndarray or None
        ``a`` ``(m,)`` (the band mean, ``1/m`` each) of the normalized form; ``None`` for Eq. (7) verbatim.
    band_names : tuple of str
        The bands' names.
    component_names : tuple of str
        ``("pooled",)`` (the paper's single component) or the prior's light sources (mixture).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.6, Eq. (7) (the Wiener estimate with a prior from reflectances under
       nine light sources, pooled).
    .. [2] S. M. Kay, Fundamentals of Statistical Signal Processing: Estimation Theory, Prentice Hall, 1993,
       Ch. 11-12 (minimum-mean-square-error estimation: the linear MMSE (Wiener) estimator and its posterior
       covariance; with a Gaussian-mixture prior, the posterior mean).
    """

    wavelength_nm: np.ndarray
    system_matrix: np.ndarray  # R (m, n), sampling interval folded in
    means: np.ndarray  # (K, n)
    covariances: np.ndarray  # (K, n, n)
    weights: np.ndarray  # (K,)
    sigma2: float
    normalization: np.ndarray | None  # a (m,) for the normalized form, None for Eq. (7) verbatim
    band_names: tuple[str, ...] = ()
    component_names: tuple[str, ...] = ("pooled",)

    @classmethod
    def fit(cls, system: MultibandSystem, prior: SpectralPrior, sigma2: float, normalized: bool = True,
            mixture: bool = False) -> WienerEstimator:
        """Fit Eq. (7) to a system and a prior.

        Parameters
        ----------
        system : MultibandSystem
            The bands' system matrix R (:func:`~omnispectral.spectral.system.six_band_system`).
        prior : SpectralPrior
            The colour signals (:func:`~omnispectral.spectral.prior.build_prior`).
        sigma2 : float
            The noise variance :math:`\\sigma^2` of Eq. (7) (relative to the squared brightness when ``normalized``).
        normalized : bool
            The exposure-equivariant form (module docstring); False: Eq. (7) verbatim.
        mixture : bool
            One prior component per light source instead of pooling them (the paper pools).

        Returns
        -------
        WienerEstimator

        References
        ----------
        .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System
           for Omnidirectional Scene Capture", J. Imaging 4(4):53, 2018, Eq. (7).
        """
        if sigma2 < 0 or not np.isfinite(sigma2):
            raise ConfigurationError(f"noise variance sigma2 must be finite and >= 0, got {sigma2}")
        if not np.allclose(system.wavelength_nm, prior.wavelength_nm):
            raise ConfigurationError("system and prior are sampled on different wavelength grids")
        R = system.matrix
        signals = prior.signals
        a = None
        if normalized:
            a = np.full(R.shape[0], 1.0 / R.shape[0])
            g = signals @ R.T @ a
            if np.any(g <= 0):
                raise ConfigurationError("a prior colour signal gives no camera response; cannot normalise")
            signals = signals / g[:, None]
        if mixture:
            comp = prior.component_index
            stats = [_mean_and_covariance(signals[comp == j]) for j in range(len(prior.illuminant_names))]
            names = tuple(prior.illuminant_names)
            counts = np.bincount(comp).astype(np.float64)
        else:
            stats = [_mean_and_covariance(signals)]
            names = ("pooled",)
            counts = np.ones(1)
        return cls(system.wavelength_nm.copy(), R, np.array([s[0] for s in stats]),
                   np.array([s[1] for s in stats]), counts / counts.sum(), float(sigma2), a,
                   tuple(system.band_names), names)

    # ------------------------------------------------------------------------------ properties
    @property
    def n_bands(self) -> int:
        return self.system_matrix.shape[0]

    @property
    def n_components(self) -> int:
        return self.means.shape[0]

    @property
    def mean(self) -> np.ndarray:
        """Prior mean :math:`\\bar e` (over all components)."""
        return self.weights @ self.means

    @property
    def covariance(self) -> np.ndarray:
        """Prior covariance :math:`C_{ss}` (over all components: within plus between)."""
        d = self.means - self.mean
        return np.einsum("k,kij->ij", self.weights, self.covariances) + (self.weights[:, None] * d).T @ d

    @property
    def W(self) -> np.ndarray:
        """The Wiener matrix of Eq. (7) for the pooled prior, ``(n, m)``."""
        return wiener_matrix(self.system_matrix, self.covariance, self.sigma2)

    def _component_map(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        W = wiener_matrix(self.system_matrix, self.covariances[j], self.sigma2)
        residual_mean = self.means[j] - W @ (self.system_matrix @ self.means[j])
        if self.normalization is None:
            return W, residual_mean
        return W + np.outer(residual_mean, self.normalization), np.zeros_like(residual_mean)

    def linear_map(self, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(M, b)`` with ``e_hat = M @ rho + b`` (``b = 0`` in the normalized form).

        For a mixture estimator, ``weights`` ``(K,)`` fixes the component weights (e.g. the
        scene's or a region's mean posterior from :meth:`component_posterior`); it is required.
        """
        if self.n_components == 1:
            return self._component_map(0)
        if weights is None:
            raise ConfigurationError("a mixture estimator is linear only for fixed component weights")
        w = np.asarray(weights, dtype=np.float64)
        if w.shape != (self.n_components,) or np.any(w < 0) or not np.isclose(w.sum(), 1.0):
            raise ConfigurationError(f"weights must be {self.n_components} non-negative values summing to 1")
        maps = [self._component_map(j) for j in range(self.n_components)]
        return sum(wj * m[0] for wj, m in zip(w, maps, strict=True)), sum(
            wj * m[1] for wj, m in zip(w, maps, strict=True))

    def posterior_covariance(self, component: int | None = None) -> np.ndarray:
        """:math:`C - W R C` of a component (or of the pooled prior), constant-noise case.

        In the normalized form it is relative: multiply by the squared brightness ``(a^t rho)^2``.
        """
        C = self.covariance if component is None else self.covariances[component]
        W = wiener_matrix(self.system_matrix, C, self.sigma2)
        return C - W @ self.system_matrix @ C

    # ----------------------------------------------------------------------------------- apply
    def _check_bands(self, rho: np.ndarray) -> np.ndarray:
        rho = np.asarray(rho)
        if rho.shape[-1] != self.n_bands:
            raise ConfigurationError(f"input has {rho.shape[-1]} bands; the estimator expects {self.n_bands}")
        return rho

    def _flat_inputs(self, rho, noise_variance) -> tuple[tuple, np.ndarray, np.ndarray | None]:
        """Leading shape, pixels as rows ``(n, bands)`` and their noise variances alike (or ``None``)."""
        rho = self._check_bands(rho)
        flat = rho.reshape(-1, self.n_bands)
        var = None
        if noise_variance is not None:
            var = np.broadcast_to(np.asarray(noise_variance, dtype=np.float64), rho.shape).reshape(-1, self.n_bands)
        return rho.shape[:-1], flat, var

    def _run(self, rho, noise_variance, chunk_pixels, fn, width, dtype):
        """Apply ``fn(rho_chunk, var_chunk)`` over chunks of pixels; reshape to ``(..., width)``."""
        lead, flat, var = self._flat_inputs(rho, noise_variance)
        out = np.empty((flat.shape[0], width), dtype=dtype)
        for s in range(0, flat.shape[0], chunk_pixels):
            out[s:s + chunk_pixels] = fn(flat[s:s + chunk_pixels], None if var is None else var[s:s + chunk_pixels])
        return out.reshape(*lead, width)

    @cached_property
    def _kernel(self) -> _MixtureKernel | None:
        """Stacked constants of the fast path; ``None`` when a component's innovation covariance is singular."""
        try:
            kernel = _MixtureKernel(self)
        except np.linalg.LinAlgError:
            return None
        finite = all(np.all(np.isfinite(x)) for x in (kernel.quad_form, kernel.T_mean, kernel.D64, kernel.post_var))
        return kernel if finite else None

    def _run_fast(self, rho, noise_variance, chunk_pixels, kernel_fn, width, dtype,
                  block_pixels: int = BLOCK_PIXELS, out: np.ndarray | None = None) -> np.ndarray:
        """Apply ``kernel_fn(rho_block, var_block, out_block, workspace)`` over blocks of pixels on a few threads.

        Blocks are at most ``min(chunk_pixels, block_pixels)`` pixels, so the temporaries stay bounded
        and cache-resident; the threads take contiguous runs of blocks (one thread inside another
        pool, see :func:`omnispectral.threads.kernel_threads`) with BLAS held to one thread.  ``out``
        (:func:`_checked_output`) is written in place.
        """
        lead, flat, var = self._flat_inputs(rho, noise_variance)
        given = out
        out = (np.empty((flat.shape[0], width), dtype=dtype) if given is None
               else _checked_output(given, (*lead, width), dtype).reshape(flat.shape[0], width))
        block = max(1, min(int(chunk_pixels), block_pixels))
        slices = blocks(flat.shape[0], block)

        def run(part: list[slice]) -> None:
            ws = _Workspace()
            for s in part:
                kernel_fn(flat[s], None if var is None else var[s], out[s], ws)

        if flat.shape[0] < SMALL_CALL_PIXELS:  # a few small products: BLAS starts no threads for them
            run(slices)
            return out.reshape(*lead, width) if given is None else given
        threads = min(kernel_threads(), len(slices))
        parts = [list(p) for p in np.array_split(np.array(slices, dtype=object), threads)]
        with single_threaded_blas():
            if threads == 1:
                run(slices)
            else:
                with ThreadPoolExecutor(threads) as pool:
                    list(pool.map(run, parts))
        return out.reshape(*lead, width) if given is None else given

    def estimate(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                 nonnegative: bool = False, chunk_pixels: int = DEFAULT_CHUNK_PIXELS,
                 dtype=np.float32, out: np.ndarray | None = None) -> np.ndarray:
        """Estimate spectra for band values ``rho`` ``(..., m)``; returns ``(..., n)``.

        Parameters
        ----------
        noise_variance
            Optional per-pixel (and per-band) noise variance of ``rho`` in the same units squared,
            broadcastable to ``rho``; added to :math:`\\sigma^2` (signal-dependent noise, e.g. from
            the HDR merge).  Without it a single-component estimator is one matrix product.
        nonnegative
            Clip negative spectral values to zero (light is non-negative).
        chunk_pixels
            Pixels per chunk; bounds the temporary memory.
        dtype
            The output's float type.
        out
            A C-contiguous ``(..., n)`` array of ``dtype`` to write the spectra into (frames of one size in a
            loop: no fresh output to fault in each time); returned.

        Returns
        -------
        ndarray
            ``(..., n)`` spectra on :attr:`wavelength_nm`, in the bands' units per unit of the system matrix.

        References
        ----------
        .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System
           for Omnidirectional Scene Capture", J. Imaging 4(4):53, 2018, Eq. (7).
        """
        kernel = self._kernel
        width = self.means.shape[1]
        if out is not None:  # refused before anything is computed
            _checked_output(out, (*self._check_bands(rho).shape[:-1], width), dtype)
        if self.n_components == 1 and noise_variance is None:
            M, b = self.linear_map()
            result = apply_linear_map(self._check_bands(rho), M, b, dtype=dtype, chunk_pixels=chunk_pixels)
        elif kernel is None:
            result = self._estimate_reference(rho, noise_variance, False, chunk_pixels, dtype)
        elif noise_variance is None:
            result = self._run_fast(rho, None, chunk_pixels, lambda r, v, o, ws: kernel.estimate(r, o, ws), width,
                                    dtype, ESTIMATE_BLOCK_PIXELS, out)
        else:
            result = self._run_fast(rho, noise_variance, chunk_pixels, kernel.estimate_noisy, width, dtype,
                                    NOISY_BLOCK_PIXELS, out)
        if out is not None and result is not out:  # the paths that make their own array
            out[...] = result
            result = out
        return np.maximum(result, 0, out=result) if nonnegative else result

    def posterior_std(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                      chunk_pixels: int = DEFAULT_CHUNK_PIXELS // 4, dtype=np.float32) -> np.ndarray:
        """Per-pixel spectral standard deviation of the estimate, ``(..., n)``.

        The square root of the diagonal of the posterior covariance (for a mixture: the
        weighted within-component covariances plus the spread of the component estimates).

        Parameters
        ----------
        rho : ndarray
            ``(..., m)`` band values.
        noise_variance : ndarray or float, optional
            Per-pixel (and per-band) noise variance of ``rho``, added to :math:`\\sigma^2` (as in :meth:`estimate`).
        chunk_pixels : int
            Pixels per chunk; bounds the temporary memory.
        dtype
            The output's float type.

        Returns
        -------
        ndarray
            ``(..., n)`` standard deviations in the units of :meth:`estimate`.

        References
        ----------
        .. [1] S. M. Kay, Fundamentals of Statistical Signal Processing: Estimation Theory, Prentice Hall, 1993,
           Ch. 11-12 (the posterior covariance of the linear MMSE estimator).
        """
        kernel = self._kernel
        if kernel is None or (self.n_components == 1 and noise_variance is None):
            return self._posterior_std_reference(rho, noise_variance, chunk_pixels, dtype)
        if noise_variance is None:
            return self._run_fast(rho, None, chunk_pixels, lambda r, v, o, ws: kernel.posterior_std(r, o, ws),
                                  self.means.shape[1], dtype, BLOCK_PIXELS // 2)
        return self._run_fast(rho, noise_variance, chunk_pixels, kernel.posterior_std_noisy,
                              self.means.shape[1], dtype, NOISY_BLOCK_PIXELS // 2)

    def component_posterior(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                            chunk_pixels: int = DEFAULT_CHUNK_PIXELS, dtype=np.float32) -> np.ndarray:
        """Posterior probability of each prior component (light source) per pixel, ``(..., K)``."""
        kernel = self._kernel
        if kernel is None:
            return self._component_posterior_reference(rho, noise_variance, chunk_pixels, dtype)
        if noise_variance is None:
            def fn(r, v, o, ws):
                kernel.posterior_into(r, o, ws)
        else:
            fn = kernel.posterior_noisy
        return self._run_fast(rho, noise_variance, chunk_pixels, fn, self.n_components, dtype,
                              BLOCK_PIXELS if noise_variance is None else NOISY_BLOCK_PIXELS)

    # ------------------------------------------------------------------ reference implementation
    # One component at a time with np.linalg per pixel: the definition the fast path is tested against.
    def _estimate_reference(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                 nonnegative: bool = False, chunk_pixels: int = DEFAULT_CHUNK_PIXELS,
                 dtype=np.float32) -> np.ndarray:
        """The pre-fast-path :meth:`estimate` (same parameters), kept to check the fast path against."""
        if self.n_components == 1 and noise_variance is None:
            M, b = self.linear_map()
            # the fast path: one matrix product, in single precision for float32 output
            work = np.float32 if np.dtype(dtype) == np.float32 else np.float64
            Mt, b = M.T.astype(work), b.astype(work)

            def fn(r, v):
                out = r.astype(work, copy=False) @ Mt
                return out + b if b.any() else out
        else:
            def fn(r, v):
                return self._solve(r.astype(np.float64), v, want_std=False)[0]

        out = self._run(rho, noise_variance, chunk_pixels, fn, self.means.shape[1], dtype)
        return np.maximum(out, 0, out=out) if nonnegative else out

    def _posterior_std_reference(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                      chunk_pixels: int = DEFAULT_CHUNK_PIXELS // 4, dtype=np.float32) -> np.ndarray:
        """The NumPy reference of :meth:`posterior_std` (same arguments and result; also the path for one
        component without per-pixel noise)."""
        if self.n_components == 1 and noise_variance is None:  # constant covariance, scaled by brightness
            base = np.sqrt(np.clip(np.diag(self.posterior_covariance(0)), 0.0, None))
            if self.normalization is None:
                return self._run(rho, None, chunk_pixels, lambda r, v: np.broadcast_to(base, (r.shape[0], base.size)),
                                 base.size, dtype)
            a = self.normalization
            return self._run(rho, None, chunk_pixels, lambda r, v: np.abs(r.astype(np.float64) @ a)[:, None] * base,
                             base.size, dtype)
        return self._run(rho, noise_variance, chunk_pixels,
                         lambda r, v: self._solve(r.astype(np.float64), v, want_std=True)[1],
                         self.means.shape[1], dtype)

    def _component_posterior_reference(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                            chunk_pixels: int = DEFAULT_CHUNK_PIXELS, dtype=np.float32) -> np.ndarray:
        """Posterior probability of each prior component (light source) per pixel, ``(..., K)``."""
        return self._run(rho, noise_variance, chunk_pixels,
                         lambda r, v: self._solve(r.astype(np.float64), v, want_std=False)[2], self.n_components, dtype)

    def _solve(self, rho: np.ndarray, var: np.ndarray | None, want_std: bool):
        """Eq. (7) per component with noise covariance ``sigma2 I (+ diag(var))``; mixture by posterior weights."""
        R = self.system_matrix
        m = R.shape[0]
        n_px = rho.shape[0]
        if self.normalization is not None:
            g = rho @ self.normalization
            g = np.where(np.abs(g) < 1e-30, 1e-30, g)
            rho_n = rho / g[:, None]
            var_n = None if var is None else var / (g * g)[:, None]
        else:
            g = np.ones(n_px)
            rho_n, var_n = rho, var
        K = self.n_components
        ests = np.empty((K, n_px, self.means.shape[1]))
        logp = np.empty((K, n_px))
        post_vars = np.empty((K, n_px, self.means.shape[1])) if want_std else None
        eye = np.eye(m)
        for j in range(K):
            C, mu = self.covariances[j], self.means[j]
            RC = R @ C
            A0 = RC @ R.T + self.sigma2 * eye
            innovation = rho_n - R @ mu
            if var_n is None:
                A_inv = np.linalg.inv(A0)
                x = innovation @ A_inv  # A symmetric
                logdet = np.linalg.slogdet(A0)[1]
                if want_std:
                    post_vars[j] = np.diag(C) - np.einsum("mn,mk,kn->n", RC, A_inv, RC)[None, :]
            else:
                A = np.broadcast_to(A0, (n_px, m, m)).copy()
                A[:, np.arange(m), np.arange(m)] += var_n
                x = np.linalg.solve(A, innovation[..., None])[..., 0]
                logdet = np.linalg.slogdet(A)[1]
                if want_std:
                    AinvRC = np.linalg.solve(A, np.broadcast_to(RC, (n_px, *RC.shape)))
                    post_vars[j] = np.diag(C)[None, :] - np.einsum("kmn,mn->kn", AinvRC, RC)
            ests[j] = mu[None, :] + x @ RC
            logp[j] = np.log(self.weights[j]) - 0.5 * ((x * innovation).sum(1) + logdet)
        logp -= logp.max(axis=0, keepdims=True)
        post = np.exp(logp)
        post /= post.sum(axis=0, keepdims=True)  # (K, N)
        est_n = np.einsum("kN,kNn->Nn", post, ests)
        std = None
        if want_std:
            spread = np.einsum("kN,kNn->Nn", post, (ests - est_n[None]) ** 2)
            within = np.einsum("kN,kNn->Nn", post, post_vars)
            std = np.abs(g)[:, None] * np.sqrt(np.clip(within + spread, 0.0, None))
        return g[:, None] * est_n, std, post.T

    def to_dict(self) -> dict:
        """Everything needed to apply the estimator without this package (stored with products)."""
        comps = []
        for j in range(self.n_components):
            M, b = self._component_map(j)
            comps.append({
                "name": self.component_names[j],
                "prior_weight": float(self.weights[j]),
                "matrix": M.tolist(),
                "offset": b.tolist(),
                "mean": self.means[j].tolist(),
                "posterior_std_relative": np.sqrt(np.clip(np.diag(self.posterior_covariance(j)), 0, None)).tolist(),
            })
        return {
            "equation": "Hirai et al. 2018 Eq. (7) (Wiener estimation)"
                        + ("; Gaussian-mixture prior, one component per light source" if self.n_components > 1
                           else ""),
            "form": "normalized" if self.normalization is not None else "absolute",
            "wavelength_nm": self.wavelength_nm.tolist(),
            "band_names": list(self.band_names),
            "system_matrix": self.system_matrix.tolist(),
            "sigma2": self.sigma2,
            "normalization": None if self.normalization is None else self.normalization.tolist(),
            "components": comps,
        }
