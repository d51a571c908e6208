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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.prior import SpectralPrior
from omnispectral.spectral.system import MultibandSystem

DEFAULT_CHUNK_PIXELS = 1 << 15


def wiener_matrix(system_matrix: np.ndarray, covariance: np.ndarray, sigma2: float) -> np.ndarray:
    """:math:`W = C R^t (R C R^t + \\sigma^2 I)^{-1}` of Eq. (7), shape ``(n, m)``."""
    R = np.asarray(system_matrix, dtype=np.float64)
    C = np.asarray(covariance, dtype=np.float64)
    CRt = C @ R.T
    A = R @ CRt + sigma2 * np.eye(R.shape[0])
    return np.linalg.solve(A, CRt.T).T  # A symmetric: W^t = A^-1 (C R^t)^t


def _mean_and_covariance(signals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = signals.mean(axis=0)
    d = signals - mean
    return mean, d.T @ d / signals.shape[0]


@dataclass(frozen=True)
class WienerEstimator:
    """A fitted Wiener estimator with one (Eq. (7)) or several (mixture) prior components.

    Build with :meth:`fit`.  Attributes hold the stacked component statistics: ``means``
    ``(K, n)``, ``covariances`` ``(K, n, n)`` and ``weights`` ``(K,)`` (prior probabilities).
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
        """Fit to a system and a prior.

        ``normalized`` selects the exposure-equivariant form; ``mixture`` keeps one prior
        component per light source instead of pooling them (the paper pools).
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

    def _run(self, rho, noise_variance, chunk_pixels, fn, width, dtype):
        """Apply ``fn(rho_chunk, var_chunk)`` over chunks of pixels; reshape to ``(..., width)``."""
        rho = self._check_bands(rho)
        lead = rho.shape[:-1]
        flat = rho.reshape(-1, self.n_bands)
        var = None
        if noise_variance is not None:
            var = np.broadcast_to(np.asarray(noise_variance, dtype=np.float64), rho.shape).reshape(-1, self.n_bands)
        out = np.empty((flat.shape[0], width), dtype=dtype)
        for s in range(0, flat.shape[0], chunk_pixels):
            out[s:s + chunk_pixels] = fn(flat[s:s + chunk_pixels], None if var is None else var[s:s + chunk_pixels])
        return out.reshape(*lead, width)

    def estimate(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                 nonnegative: bool = False, chunk_pixels: int = DEFAULT_CHUNK_PIXELS,
                 dtype=np.float32) -> np.ndarray:
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
        """
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

    def posterior_std(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
                      chunk_pixels: int = DEFAULT_CHUNK_PIXELS // 4, dtype=np.float32) -> np.ndarray:
        """Per-pixel spectral standard deviation of the estimate, ``(..., n)``.

        The square root of the diagonal of the posterior covariance (for a mixture: the
        weighted within-component covariances plus the spread of the component estimates).
        """
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

    def component_posterior(self, rho: np.ndarray, noise_variance: np.ndarray | float | None = None,
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
