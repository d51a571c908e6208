"""Spectral core: curves, the six-band system (Eqs. (5)-(6)), the prior, Wiener estimation (Eq. (7)),
metrics, the Sec. 5.2 evaluation protocol and filter selection."""

from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM, SpectralSet, read_spectral_csv, write_spectral_csv
from omnispectral.spectral.evaluate import Protocol, evaluate
from omnispectral.spectral.noise import CMV2000, SensorNoiseModel
from omnispectral.spectral.prior import SpectralPrior, build_prior
from omnispectral.spectral.system import MultibandSystem, build_system, rgb_system, six_band_system
from omnispectral.spectral.wiener import WienerEstimator, wiener_matrix

__all__ = [
    "CMV2000", "DEFAULT_WAVELENGTH_NM", "MultibandSystem", "Protocol", "SensorNoiseModel", "SpectralPrior",
    "SpectralSet", "WienerEstimator", "build_prior", "build_system", "evaluate", "read_spectral_csv",
    "rgb_system", "six_band_system", "wiener_matrix", "write_spectral_csv",
]
