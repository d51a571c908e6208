"""Prior database of colour signals for Wiener estimation (paper Sec. 4.6).

The paper builds its covariance :math:`C_{ss}` from "1378 surface spectral reflectances of various
natural and artificial objects" multiplied by "nine spectral power distributions of different
light sources".  We do the same with permissively licensed sets: Vrhel et al. (1994) objects,
Munsell and DuPont paint chips (354), the RAW to ACES training spectra (190), under nine light
sources spanning daylight (5000-10000 K), tungsten, fluorescent and LED.

The prior must not contain the evaluation target, nor the calibration set used to tune
:math:`\\sigma^2`: :func:`exclude_near` drops any prior reflectance that is (nearly) a copy of one of
them, and the prior records how many it dropped.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM, SpectralSet, concatenate
from omnispectral.spectral.library import (
    CALIBRATION_ILLUMINANTS,
    CALIBRATION_REFLECTANCE_SETS,
    PRIOR_ILLUMINANTS,
    PRIOR_REFLECTANCE_SETS,
    load_illuminant,
    load_reflectances,
)

__all__ = ["EXCLUSION_RMS", "SpectralPrior", "build_prior", "calibration_signals", "colour_signals", "exclude_near",
           "load_illuminant_set"]

EXCLUSION_RMS = 0.01
"""Prior reflectances closer than this RMS difference (reflectance units) to a held-out spectrum are dropped."""


def colour_signals(reflectances: SpectralSet, illuminants: SpectralSet) -> np.ndarray:
    """Colour signals ``e = r(λ) E(λ)`` for every reflectance under every illuminant.

    Both sets must be on the same grid.  Each illuminant is first scaled to unit mean over the
    grid so that no light source dominates the statistics by its absolute level.  Returns
    ``(len(illuminants) * len(reflectances), n)``, illuminant-major.
    """
    if not np.allclose(reflectances.wavelength_nm, illuminants.wavelength_nm):
        raise ConfigurationError("reflectances and illuminants must be resampled onto the same grid")
    spd = illuminants.values / illuminants.values.mean(axis=1, keepdims=True)
    return (spd[:, None, :] * reflectances.values[None, :, :]).reshape(-1, reflectances.values.shape[1])


def exclude_near(candidates: SpectralSet, held_out: SpectralSet, rms: float = EXCLUSION_RMS) -> np.ndarray:
    """Mask of ``candidates`` to keep: farther than ``rms`` (RMS over wavelength) from every held-out spectrum."""
    a = candidates.values
    b = held_out.resample(candidates.wavelength_nm).values
    d2 = (a**2).sum(1)[:, None] + (b**2).sum(1)[None, :] - 2 * a @ b.T
    dist = np.sqrt(np.maximum(d2, 0.0) / a.shape[1])
    return dist.min(axis=1) > rms


@dataclass(frozen=True)
class SpectralPrior:
    """Colour-signal database and its statistics.

    Attributes
    ----------
    wavelength_nm
        Grid ``(n,)``.
    signals
        Colour signals ``(K, n)``.
    reflectance_sources, illuminant_names
        What the signals were built from.
    n_excluded
        Prior reflectances dropped because they were (near) copies of held-out spectra.
    """

    wavelength_nm: np.ndarray
    signals: np.ndarray
    reflectance_sources: tuple[str, ...]
    illuminant_names: tuple[str, ...]
    n_reflectances: int
    n_excluded: int = 0
    excluded_names: tuple[str, ...] = field(default=())
    reflectances: SpectralSet | None = None

    @property
    def component_index(self) -> np.ndarray:
        """Light source index of each signal ``(K,)`` (signals are illuminant-major)."""
        return np.repeat(np.arange(len(self.illuminant_names)), self.n_reflectances)

    @property
    def mean(self) -> np.ndarray:
        """Mean spectrum :math:`\\bar{e}` of Eq. (7)."""
        return self.signals.mean(axis=0)

    @property
    def covariance(self) -> np.ndarray:
        """Covariance :math:`C_{ss} = E[(e - \\bar e)(e - \\bar e)^t]` of Eq. (7)."""
        d = self.signals - self.mean
        return d.T @ d / self.signals.shape[0]

    def summary(self) -> dict:
        return {
            "n_signals": int(self.signals.shape[0]),
            "n_reflectances": self.n_reflectances,
            "n_illuminants": len(self.illuminant_names),
            "reflectance_sets": list(self.reflectance_sources),
            "illuminants": list(self.illuminant_names),
            "n_excluded_as_held_out": self.n_excluded,
            "mean_spectrum": self.mean.tolist(),
        }


def load_illuminant_set(names: tuple[str, ...] | list[str], wavelength_nm: np.ndarray | None = None) -> SpectralSet:
    """Several illuminants (built-in names or CSV paths) stacked on one grid."""
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else wavelength_nm
    parts = [load_illuminant(n).resample(wl) for n in names]
    return SpectralSet(wl, np.vstack([p.values for p in parts]), [p.names[0] for p in parts], "illuminant",
                       "+".join(names))


def build_prior(reflectance_sets: tuple[str, ...] | list[str] = PRIOR_REFLECTANCE_SETS,
                illuminants: tuple[str, ...] | list[str] = PRIOR_ILLUMINANTS,
                held_out: list[SpectralSet] | None = None,
                wavelength_nm: np.ndarray | None = None) -> SpectralPrior:
    """Build the colour-signal prior from reflectance sets and light sources, minus held-out spectra.

    Parameters
    ----------
    reflectance_sets
        Names understood by :func:`~omnispectral.spectral.library.load_reflectances` (or CSV paths).
    illuminants
        Names understood by :func:`~omnispectral.spectral.library.load_illuminant`.
    held_out
        Reflectance sets that must not be in the prior (the evaluation target and the
        calibration set); near copies (RMS < :data:`EXCLUSION_RMS`) are removed.
    wavelength_nm
        The wavelength grid (default 400-700 nm every 5 nm).

    Returns
    -------
    SpectralPrior
        The colour signals (every reflectance under every light source) whose mean and covariance Eq. (7) uses.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System
       for Omnidirectional Scene Capture", J. Imaging 4(4):53, 2018, Sec. 4
       (the prior of Eq. (7): reflectances under nine light sources).
    """
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, dtype=np.float64)
    refl = concatenate([load_reflectances(n) for n in reflectance_sets], wl, source="prior")
    keep = np.ones(len(refl), dtype=bool)
    for h in held_out or []:
        keep &= exclude_near(refl, h)
    excluded = tuple(n for n, k in zip(refl.names, keep, strict=True) if not k)
    refl = refl.subset(keep)
    if len(refl) < 10:
        raise ConfigurationError(f"only {len(refl)} prior reflectances left after exclusion; need at least 10")
    illum = load_illuminant_set(tuple(illuminants), wl)
    return SpectralPrior(wl, colour_signals(refl, illum), tuple(reflectance_sets), tuple(illum.names),
                         len(refl), len(excluded), excluded, refl)


def calibration_signals(held_out: list[SpectralSet] | None = None,
                        reflectance_sets: tuple[str, ...] = CALIBRATION_REFLECTANCE_SETS,
                        illuminants: tuple[str, ...] = CALIBRATION_ILLUMINANTS,
                        wavelength_nm: np.ndarray | None = None) -> tuple[SpectralSet, SpectralSet]:
    """The calibration set for tuning :math:`\\sigma^2`: reflectances and the light sources to view them under.

    Paper Sec. 4.6 tunes the noise variance on a chart "under various light sources".  Our
    default chart is the CIE 13.3 test colour samples plus the NIST CQS 9.0 samples (29
    reflectances), disjoint from the ColorChecker evaluation target; any sample close to a
    ``held_out`` spectrum is removed as well.
    """
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, dtype=np.float64)
    refl = concatenate([load_reflectances(n) for n in reflectance_sets], wl, source="calibration")
    keep = np.ones(len(refl), dtype=bool)
    for h in held_out or []:
        keep &= exclude_near(refl, h)
    return refl.subset(keep), load_illuminant_set(tuple(illuminants), wl)
