"""Camera response curves: the identity of a linear sensor and Debevec–Malik recovery for 8-bit brackets.

A response maps each output code ``Z`` of each channel to a value proportional to exposure
``X = E t`` (irradiance times exposure time).  Machine-vision sensors of the rig are linear
(``X = Z``); JPEG/PNG brackets from ordinary cameras and film scans are not, and their response is
recovered from the bracket itself with the least-squares method of

    P. E. Debevec and J. Malik, "Recovering high dynamic range radiance maps from photographs",
    SIGGRAPH 1997, Sec. 2.1 (objective Eq. (3), hat weighting, ``g(Z_mid) = 0``).

Unlike OpenCV's ``CalibrateDebevec`` the sampler here ignores pixels that do not change across the
bracket (borders, dead pixels, the blue frame of the Memorial scans), chooses samples spread over
the whole code range of the middle exposure, and the curve is made monotonic after the solve.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.weights import triangle_weight
from omnispectral.io import atomic_write_json

__all__ = ["CameraResponse", "recover_response", "select_samples", "solve_debevec", "varying_pixels"]


@dataclass(frozen=True)
class CameraResponse:
    """Exposure value (relative units) of each code: ``linear[z, c]`` for code ``z`` of channel ``c``.

    ``derivative`` is ``dX/dZ`` per code (used for the noise weight and variance of non-linear inputs).
    """

    linear: np.ndarray
    kind: str = "linear"
    notes: tuple[str, ...] = field(default=())

    @property
    def n_codes(self) -> int:
        return int(self.linear.shape[0])

    @property
    def is_identity(self) -> bool:
        return self.kind == "linear"

    @property
    def derivative(self) -> np.ndarray:
        """Slope ``dX/dZ`` of each code (central differences, at least a small positive value)."""
        d = np.gradient(self.linear.astype(np.float64), axis=0)
        floor = 1e-6 * np.maximum(self.linear.max(axis=0, keepdims=True), 1e-30)
        return np.maximum(d, floor)

    @classmethod
    def identity(cls, bit_depth: int, channels: int = 1) -> CameraResponse:
        """A linear sensor: ``X = Z``."""
        codes = np.arange(1 << bit_depth, dtype=np.float32)
        return cls(np.repeat(codes[:, None], channels, axis=1), "linear")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "n_codes": self.n_codes, "channels": int(self.linear.shape[1]),
                "linear": self.linear.T.tolist(), "notes": list(self.notes)}

    def save(self, path: str | Path) -> Path:
        """Write as JSON (``linear`` is listed per channel); atomic."""
        return atomic_write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> CameraResponse:
        """Read a response written by :meth:`save`; errors name the file."""

        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            lin = np.asarray(data["linear"], dtype=np.float32).T
        except FileNotFoundError:
            raise InputFileError(path, "file not found") from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputFileError(path, f"not a camera response file ({exc})") from None
        if lin.ndim != 2 or lin.shape[0] < 2 or not np.all(np.isfinite(lin)):
            raise InputFileError(path, f"response table has shape {lin.shape}; expected (channels, codes)")
        if np.any(np.diff(lin, axis=0) < 0):
            raise InputFileError(path, "response is not monotonic (exposure must not fall as the code rises)")
        return cls(lin, str(data.get("kind", "table")), tuple(data.get("notes", ())))


def varying_pixels(frames: Sequence[np.ndarray]) -> np.ndarray:
    """``(H, W)`` mask of pixels that change across the bracket in every channel.

    A pixel whose code is identical in all exposures of a multi-stop bracket is not measuring light
    (a frame border, a dead pixel, or clipped at both ends); it must not drive response recovery.
    """
    stack_min = np.minimum.reduce([np.asarray(f) for f in frames])
    stack_max = np.maximum.reduce([np.asarray(f) for f in frames])
    moving = stack_max > stack_min
    return moving.all(axis=-1) if moving.ndim == 3 else moving


def select_samples(frames: Sequence[np.ndarray], n_samples: int = 400, mask: np.ndarray | None = None,
                   seed: int = 0) -> np.ndarray:
    """Flat pixel indices for response recovery, spread over the code range of the middle exposure.

    Pixels are stratified by the middle exposure's mean code (so dark and bright codes are all
    constrained, Debevec & Malik Sec. 2.1 note ``N(P-1) > Zmax - Zmin``) and, within a stratum, the
    smoothest (lowest local gradient) are preferred: they are least sensitive to misalignment.
    """
    ok = varying_pixels(frames)
    if mask is not None:
        ok &= mask
    middle = np.asarray(frames[len(frames) // 2], dtype=np.float32)
    lum = middle.mean(axis=-1) if middle.ndim == 3 else middle
    gy, gx = np.gradient(lum)
    rough = np.hypot(gx, gy).ravel()
    candidates = np.flatnonzero(ok.ravel())
    if candidates.size < 10:
        raise ConfigurationError("fewer than 10 pixels change across the bracket: cannot recover a response")
    rng = np.random.default_rng(seed)
    n_bins = 32
    edges = np.quantile(lum.ravel()[candidates], np.linspace(0, 1, n_bins + 1))
    strata = np.clip(np.searchsorted(edges, lum.ravel()[candidates], side="right") - 1, 0, n_bins - 1)
    per_bin = max(1, n_samples // n_bins)
    chosen = []
    for b in range(n_bins):
        members = candidates[strata == b]
        if members.size == 0:
            continue
        pool = members if members.size <= 20 * per_bin else rng.choice(members, 20 * per_bin, replace=False)
        chosen.append(pool[np.argsort(rough[pool], kind="stable")[:per_bin]])
    return np.unique(np.concatenate(chosen))


def solve_debevec(codes: np.ndarray, log_exposure_s: np.ndarray, n_codes: int = 256,
                  smoothness: float = 50.0) -> np.ndarray:
    """Solve Debevec & Malik's Eq. (3) for ``g(z) = ln X(z)`` of one channel.

    Parameters
    ----------
    codes
        ``(N, P)`` integer codes of N sample pixels in P exposures.
    log_exposure_s
        ``(P,)`` natural log of the exposure times.
    smoothness
        ``lambda`` of the second-derivative penalty.

    Returns
    -------
    ``(n_codes,)`` log exposure per code, with ``g(mid) = 0``.
    """
    n, p = codes.shape
    if n_codes < 2 or n_codes & (n_codes - 1):
        raise ConfigurationError(f"n_codes must be a power of two (the codes of a bit depth), got {n_codes}")
    # Eq. (2) over the codes; +1 keeps the end codes weakly constrained rather than free
    wz = triangle_weight(np.arange(n_codes), (n_codes - 1).bit_length()).astype(np.float64) + 1.0
    rows = n * p + 1 + (n_codes - 2)
    a = np.zeros((rows, n_codes + n))
    b = np.zeros(rows)
    r = np.arange(n * p)
    z = codes.ravel().astype(np.intp)
    wij = wz[z]
    a[r, z] = wij
    a[r, n_codes + np.repeat(np.arange(n), p)] = -wij
    b[: n * p] = wij * np.tile(log_exposure_s, n)
    a[n * p, n_codes // 2] = 1.0
    k = np.arange(1, n_codes - 1)
    rs = n * p + 1 + np.arange(n_codes - 2)
    lam = smoothness * wz[k]
    a[rs, k - 1] = lam
    a[rs, k] = -2 * lam
    a[rs, k + 1] = lam
    sol, *_ = np.linalg.lstsq(a, b, rcond=None)
    return sol[:n_codes]


def recover_response(frames: Sequence[np.ndarray], exposure_s: Sequence[float], n_samples: int = 400,
                     smoothness: float = 50.0, mask: np.ndarray | None = None, seed: int = 0) -> CameraResponse:
    """Debevec–Malik (1997) response recovery from an 8-bit bracket, per channel.

    Returns a monotonic :class:`CameraResponse` whose ``linear[z, c] = exp(g_c(z))``, scaled so the
    middle code of the green (or only) channel is 1, and all channels share that scale through
    their ``g(mid) = 0`` anchors (the white balance of the recovered curves is the camera's).
    """
    frames = [np.asarray(f) for f in frames]
    if frames[0].dtype != np.uint8:
        raise ConfigurationError(f"response recovery needs 8-bit frames, got {frames[0].dtype} "
                                 "(raw 12/16-bit machine-vision frames are linear: no recovery needed)")
    times = np.asarray(exposure_s, dtype=np.float64)
    if times.size < 2 or np.unique(times).size < 2:
        raise ConfigurationError("response recovery needs at least two different exposure times")
    stack = np.stack([f if f.ndim == 3 else f[..., None] for f in frames], axis=-1)  # (H, W, C, P)
    idx = select_samples(frames, n_samples, mask, seed)
    flat = stack.reshape(-1, stack.shape[2], stack.shape[3])
    curves = []
    for c in range(stack.shape[2]):
        g = solve_debevec(flat[idx, c, :], np.log(times), 256, smoothness)
        curves.append(np.maximum.accumulate(g))
    lin = np.exp(np.stack(curves, axis=1)).astype(np.float32)
    notes = (f"Debevec-Malik 1997 from {len(frames)} exposures, {idx.size} samples, lambda={smoothness}",)
    return CameraResponse(lin, "debevec1997", notes)
