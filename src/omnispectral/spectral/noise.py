"""Sensor noise model for simulation and for noise-aware estimation.

The paper's cameras (Baumer HXG20) use the CMOSIS CMV2000 sensor: 2048 x 1088 pixels, 12-bit
output, full well 13 500 e-, read noise 13 e- (CMOSIS CMV2000 datasheet v3.x).  A pixel value is
modelled as

    electrons ~ Poisson(mu) + Normal(0, read_noise_e^2),   DN = clip(round(electrons / gain), 0, 2^bits - 1)

with ``gain = full_well_e / (2^bits - 1)`` electrons per DN, so that full well maps to the
largest code (EMVA 1288's linear camera model without dark current).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError

__all__ = ["CMV2000", "SensorNoiseModel", "exposure_scale_per_camera", "measure_patches"]


@dataclass(frozen=True)
class SensorNoiseModel:
    """Photon shot noise, read noise, quantisation and saturation of a linear sensor."""

    full_well_e: float = 13_500.0
    read_noise_e: float = 13.0
    bit_depth: int = 12
    name: str = "CMOSIS CMV2000"

    def __post_init__(self) -> None:
        if self.full_well_e <= 0 or self.read_noise_e < 0 or not 1 <= self.bit_depth <= 16:
            raise ConfigurationError(f"invalid sensor noise model {self}")

    @property
    def max_dn(self) -> int:
        """Largest output code, ``2^bits - 1``."""
        return (1 << self.bit_depth) - 1

    @property
    def gain_e_per_dn(self) -> float:
        """Electrons per digital number."""
        return self.full_well_e / self.max_dn

    def sample_dn(self, electrons_mean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Draw pixel values (DN, float64 integers) for mean photo-electron counts ``electrons_mean``."""
        mu = np.clip(np.asarray(electrons_mean, dtype=np.float64), 0.0, None)
        electrons = rng.poisson(mu).astype(np.float64)
        electrons += rng.normal(0.0, self.read_noise_e, size=mu.shape)
        return np.clip(np.round(electrons / self.gain_e_per_dn), 0, self.max_dn)

    def variance_dn2(self, dn: np.ndarray) -> np.ndarray:
        """Expected variance (DN^2) of a pixel whose mean value is ``dn``: shot + read + quantisation."""
        g = self.gain_e_per_dn
        signal_e = np.clip(np.asarray(dn, dtype=np.float64), 0.0, None) * g
        return (signal_e + self.read_noise_e**2) / g**2 + 1.0 / 12.0

    def dn_for_snr(self, snr: float) -> float:
        """The mean value (DN) at which a pixel's signal-to-noise ratio ``dn / sqrt(variance_dn2(dn))`` is ``snr``:
        the positive root of ``dn^2 = snr^2 (dn / g + read^2 / g^2 + 1/12)``, ``g`` the gain (e-/DN)."""
        g = self.gain_e_per_dn
        b = snr**2 / g
        c = snr**2 * (self.read_noise_e**2 / g**2 + 1.0 / 12.0)
        return 0.5 * (b + math.sqrt(b * b + 4.0 * c))

    def to_dict(self) -> dict:
        return {"name": self.name, "full_well_e": self.full_well_e, "read_noise_e": self.read_noise_e,
                "bit_depth": self.bit_depth}


CMV2000 = SensorNoiseModel()
"""The paper's sensor (12 bit, 13 500 e- full well, 13 e- read noise)."""


def exposure_scale_per_camera(signal: np.ndarray, camera_of_band: np.ndarray, noise: SensorNoiseModel,
                              white_fraction: float = 0.8) -> np.ndarray:
    """Electrons per unit of band signal, per band: each camera's brightest value at ``white_fraction`` of full well.

    This is how an operator exposes a chart: each camera (behind its own filter) gets its own
    exposure time so that the white patch sits just below saturation.
    """
    if not 0 < white_fraction <= 1:
        raise ConfigurationError(f"white_fraction must be in (0, 1], got {white_fraction}")
    signal = np.asarray(signal, dtype=np.float64).reshape(-1, signal.shape[-1])
    scale = np.empty(signal.shape[-1])
    for cam in np.unique(camera_of_band):
        bands = camera_of_band == cam
        peak = signal[:, bands].max()
        if peak <= 0:
            raise ConfigurationError(f"camera {cam} sees no signal; cannot set its exposure")
        scale[bands] = white_fraction * noise.full_well_e / peak
    return scale


def measure_patches(signal: np.ndarray, camera_of_band: np.ndarray, noise: SensorNoiseModel | None,
                    rng: np.random.Generator | None = None, patch_px: int = 32,
                    white_fraction: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """Simulate measuring chart patches: each band value averaged over ``patch_px x patch_px`` noisy pixels.

    Parameters
    ----------
    signal
        Noise-free band values ``(P, m)`` (``R e`` of Eq. (6)), in any consistent unit.
    camera_of_band
        Camera index of each band (bands of one camera share the exposure).
    noise
        Sensor model, or ``None`` for a noise-free measurement.
    rng : numpy.random.Generator, optional
        The noise's random numbers (default: seeded with 0).
    patch_px
        Side of the square region averaged per patch (default 32 px, as when measuring a chart).
    white_fraction : float
        Each camera exposed so its brightest band value sits at this fraction of full well, in (0, 1]
        (:func:`exposure_scale_per_camera`).

    Returns
    -------
    measured, variance
        Patch means in the unit of ``signal`` ``(P, m)``, and the variance of each mean in that
        unit squared (the ``sigma_i^2`` of Eq. (5) for the signal-dependent estimator).

    Raises
    ------
    ConfigurationError
        For ``patch_px`` below 1, ``white_fraction`` outside (0, 1], or a camera that sees no signal.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eq. (5) (the noise ``σ_i`` of a band value), Sec. 3 (12-bit cameras).
    .. [2] EMVA Standard 1288, "Standard for Characterization of Image Sensors and Cameras" (the linear camera
       model: shot noise, read noise, quantisation, saturation).
    """
    signal = np.asarray(signal, dtype=np.float64)
    if noise is None:
        return signal.copy(), np.zeros_like(signal)
    if patch_px < 1:
        raise ConfigurationError(f"patch_px must be >= 1, got {patch_px}")
    rng = np.random.default_rng(0) if rng is None else rng
    scale = exposure_scale_per_camera(signal, camera_of_band, noise, white_fraction)
    electrons = signal * scale  # (P, m)
    n_px = patch_px * patch_px
    dn = noise.sample_dn(np.broadcast_to(electrons[:, None, :], (signal.shape[0], n_px, signal.shape[1])), rng)
    dn_mean = dn.mean(axis=1)
    to_signal = noise.gain_e_per_dn / scale
    measured = dn_mean * to_signal
    variance = noise.variance_dn2(dn_mean) / n_px * to_signal**2
    return measured, variance
