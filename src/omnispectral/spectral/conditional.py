"""Camera B's three bands predicted from camera A's under the spectral prior (where B saw nothing).

Where camera B cannot see what camera A sees (a nearer surface hides the point from B, the point lies
beyond B's frame, or B's views of it disagree), the panorama still needs six bands.  The prior that
the Wiener estimator uses (:mod:`omnispectral.spectral.wiener`) describes colour signals ``s`` by the
second moments :math:`G = R\\,E[ss^t]\\,R^t` of their bands (normalized form: unit brightness, mixture
components pooled with their weights).  The linear least-squares predictor of B's bands from A's,

.. math:: \\hat\\rho_B = M\\rho_A, \\qquad M = G_{BA}G_{AA}^{-1}, \\qquad
          \\Sigma_{B\\mid A} = G_{BB} - M G_{AB},

is exposure-equivariant (no intercept: doubling the light doubles both cameras' bands), and
:math:`\\sqrt{(\\Sigma_{B\\mid A})_{kk}/(G_{BB})_{kk}}` is its relative error per band over the prior
(Kay, *Fundamentals of Statistical Signal Processing: Estimation Theory*, 1993, Sec. 12.4: the linear
MMSE estimator from second moments).  :func:`omnispectral.mosaic.predict` adapts ``M ρ_A`` to the
surface around each pixel (the ratio of measured to predicted B bands on neighbours that look alike
in A) and records the remaining relative error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BandPredictor", "b_from_a_predictor"]


@dataclass(frozen=True)
class BandPredictor:
    """``b ≈ matrix @ a`` for one camera's three bands from the other's, with the relative error per band."""

    matrix: np.ndarray  # (3, 3)
    rel_std: np.ndarray  # (3,)

    def to_dict(self) -> dict:
        return {"matrix": np.asarray(self.matrix).tolist(), "rel_std": np.asarray(self.rel_std).tolist()}

    @classmethod
    def from_dict(cls, data: dict) -> BandPredictor:
        return cls(np.asarray(data["matrix"], np.float64).reshape(3, 3),
                   np.asarray(data["rel_std"], np.float64).reshape(3))


def band_second_moments(estimator) -> np.ndarray:
    """``G = R E[ssᵀ] Rᵀ`` of a fitted :class:`~omnispectral.spectral.wiener.WienerEstimator`'s prior
    (components pooled with their weights; in the estimator's normalized units)."""
    w = np.asarray(estimator.weights, np.float64)
    mu = np.asarray(estimator.means, np.float64)
    second = np.einsum("k,kij->ij", w, estimator.covariances) + (w[:, None] * mu).T @ mu
    r = np.asarray(estimator.system_matrix, np.float64)
    return r @ second @ r.T


def b_from_a_predictor(estimator) -> BandPredictor:
    """The prior's linear predictor of bands 3–5 (camera B) from bands 0–2 (camera A), module docstring.

    Parameters
    ----------
    estimator
        A six-band :class:`~omnispectral.spectral.wiener.WienerEstimator` (its prior and system matrix).

    Returns
    -------
    BandPredictor
        ``M`` (3 × 3) and the prior's relative error of ``M ρ_A`` per band of B.
    """
    g = band_second_moments(estimator)
    if g.shape != (6, 6):
        raise ValueError(f"a six-band estimator is needed, got {g.shape[0]} bands")
    g_aa, g_ab, g_bb = g[:3, :3], g[:3, 3:], g[3:, 3:]
    m = np.linalg.solve(g_aa, g_ab).T  # G_BA G_AA⁻¹ (G symmetric)
    resid = g_bb - m @ g_ab
    rel = np.sqrt(np.clip(np.diag(resid), 0.0, None) / np.diag(g_bb))
    return BandPredictor(m, rel)
