"""HDR synthesis from an exposure bracket of a linear sensor (paper Sec. 4.1, Eqs. (1)-(2)).

.. math::  I^{HDR}_{ij} = \\frac{\\sum_k w(I^k_{ij})\\, I^k_{ij} / t^k}{\\sum_k w(I^k_{ij})}

Weights:

``"triangle"`` (default, Eq. (2) generalised to the bit depth)
    ``w(I) = I`` for ``I <= M/2`` and ``M - I`` above, with ``M = 2^bits - 1``.
``"noise"`` (Granados et al., CVPR 2010, for a linear sensor)
    ``w = t^2 / Var(I)`` with ``Var`` from the sensor noise model: the inverse variance of each
    exposure's radiance estimate ``I/t``.  The triangle weight gives 1-DN values of short exposures
    as much say as well-exposed long ones in dark regions; this one does not.

Saturated values (``I >= saturation_dn``) get zero weight.  A pixel saturated in every exposure
takes the shortest exposure's value and is flagged; one that is dark (zero weight) in every
exposure takes the longest exposure's value and is flagged.  The merge also returns each pixel's
variance (for the Wiener estimator's signal-dependent noise).  Work is done in row chunks in
float32: no per-exposure float64 image is ever formed.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.noise import CMV2000, SensorNoiseModel

WEIGHTS = ("triangle", "noise")


@dataclass(frozen=True)
class HDRResult:
    """Merged radiance (DN per second), its variance, and per-pixel flags, all ``(H, W, C)``."""

    radiance: np.ndarray
    variance: np.ndarray
    saturated: np.ndarray
    dark: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """True where at least one exposure was usable (neither saturated everywhere nor dark everywhere)."""
        return ~(self.saturated | self.dark)


def triangle_weight(dn: np.ndarray, bit_depth: int) -> np.ndarray:
    """Eq. (2) generalised to ``bit_depth``: rises from 0 to mid-range, falls to 0 at full scale."""
    top = float((1 << bit_depth) - 1)
    dn = dn.astype(np.float32, copy=False)
    return np.minimum(dn, top - dn).clip(0.0)


def _check_inputs(frames: Sequence[np.ndarray], exposure_s: Sequence[float], bit_depth: int):
    if len(frames) == 0:
        raise ConfigurationError("no exposures to merge")
    times = np.asarray(exposure_s, dtype=np.float64)
    if times.shape != (len(frames),):
        raise ConfigurationError(f"{len(frames)} frames but {times.size} exposure times")
    if np.any(~np.isfinite(times)) or np.any(times <= 0):
        k = int(np.flatnonzero(~np.isfinite(times) | (times <= 0))[0])
        raise ConfigurationError(f"exposure {k}: exposure time {times[k]!r} s is not positive")
    if not 1 <= bit_depth <= 16:
        raise ConfigurationError(f"bit depth {bit_depth} is outside 1-16")
    shape = np.shape(frames[0])
    for k, f in enumerate(frames):
        if np.shape(f) != shape:
            raise ConfigurationError(f"exposure {k} has shape {np.shape(f)}, exposure 0 has {shape}")
        if not np.issubdtype(np.asarray(f).dtype, np.integer):
            raise ConfigurationError(f"exposure {k} has dtype {np.asarray(f).dtype}; expected uint8 or uint16 raw")
    return times


def merge_exposures(frames: Sequence[np.ndarray], exposure_s: Sequence[float], bit_depth: int = 12,
                    weight: str = "triangle", noise: SensorNoiseModel | None = None,
                    saturation_dn: float | None = None, chunk_rows: int = 64) -> HDRResult:
    """Merge an exposure bracket into linear radiance per second (Eqs. (1)-(2)).

    Parameters
    ----------
    frames
        N raw frames, each ``(H, W)`` or ``(H, W, C)``, unsigned integers with ``bit_depth`` bits.
    exposure_s
        Exposure time of each frame in seconds (> 0).
    weight
        ``"triangle"`` (paper) or ``"noise"`` (inverse variance, Granados et al. 2010).
    noise
        Sensor model for the variance estimate and the noise weight (default CMV2000 with
        ``bit_depth`` bits).
    saturation_dn
        Values at or above this are saturated (default: the largest code minus 1 %).

    Returns
    -------
    HDRResult
        ``radiance`` float32 ``(H, W, C)`` in DN/s, ``variance`` of it (DN/s)^2, ``saturated`` and
        ``dark`` flags.
    """
    if weight not in WEIGHTS:
        raise ConfigurationError(f"unknown weight {weight!r}; expected one of {WEIGHTS}")
    times = _check_inputs(frames, exposure_s, bit_depth)
    top = (1 << bit_depth) - 1
    sat = float(saturation_dn) if saturation_dn is not None else 0.99 * top
    if noise is None:
        noise = CMV2000 if bit_depth == CMV2000.bit_depth else SensorNoiseModel(bit_depth=bit_depth)
    frames = [f if np.ndim(f) == 3 else np.asarray(f)[..., None] for f in frames]
    h, w, c = frames[0].shape
    order = np.argsort(times)
    shortest, longest = int(order[0]), int(order[-1])
    out = HDRResult(np.empty((h, w, c), np.float32), np.empty((h, w, c), np.float32),
                    np.zeros((h, w, c), bool), np.zeros((h, w, c), bool))
    inv_t = (1.0 / times).astype(np.float32)
    for r0 in range(0, h, chunk_rows):
        rows = slice(r0, min(r0 + chunk_rows, h))
        num = np.zeros((rows.stop - r0, w, c), np.float32)
        den = np.zeros_like(num)
        var_num = np.zeros_like(num)
        any_unsat = np.zeros(num.shape, bool)
        for k, frame in enumerate(frames):
            dn = frame[rows].astype(np.float32)
            unsat = dn < sat
            any_unsat |= unsat
            var_dn = noise.variance_dn2(dn).astype(np.float32)
            if weight == "triangle":
                wk = triangle_weight(dn, bit_depth)
            else:
                wk = (times[k] ** 2 / var_dn).astype(np.float32)
            wk *= unsat
            num += wk * dn * inv_t[k]
            den += wk
            var_num += wk * wk * var_dn * inv_t[k] ** 2
        ok = den > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            rad = np.where(ok, num / den, 0.0)
            var = np.where(ok, var_num / den**2, 0.0)
        saturated = ~any_unsat
        dark = ~ok & ~saturated
        for flag, k in ((saturated, shortest), (dark, longest)):
            if flag.any():
                dn = frames[k][rows].astype(np.float32)
                rad = np.where(flag, dn * inv_t[k], rad)
                var = np.where(flag, noise.variance_dn2(dn).astype(np.float32) * inv_t[k] ** 2, var)
        out.radiance[rows] = rad
        out.variance[rows] = var
        out.saturated[rows] = saturated
        out.dark[rows] = dark
    return out
