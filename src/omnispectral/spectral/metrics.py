"""Accuracy metrics for estimated spectra (paper Sec. 5.2).

NRMSE (as in paper Sec. 5.2 and Fig. 11): both spectra are scaled to unit L2 norm over the
wavelength grid (61 samples for 400-700 nm / 5 nm), then the RMS difference is taken over
wavelengths; a set's figure is the mean over its spectra.  Colour differences use CIE 1931 2°
XYZ, with the light source as the white (a perfect reflecting diffuser under it has Y = 100),
and colour-science's CIELAB, ΔE*ab (CIE 1976) and ΔE00 (CIE 2000); the conversions are in
:mod:`omnispectral.spectral.colour`.
"""

from __future__ import annotations

import colour
import numpy as np

from omnispectral.spectral.colour import signal_to_Lab

__all__ = ["NRMSE_DEFINITION", "colour_differences", "nrmse", "spectral_angle_deg", "spectral_report"]

NRMSE_DEFINITION = (
    "NRMSE: estimated and true spectra each scaled to unit L2 norm over the wavelength grid "
    "({n} samples, {lo:g}-{hi:g} nm), RMS difference over wavelengths, mean over targets. "
    "Delta E: CIE 1931 2 deg XYZ of the colour signals with the illuminant as white (Y=100), "
    "CIELAB, CIE 1976 (Delta E*ab) and CIE 2000 (Delta E00), mean over targets."
)


def nrmse(estimated: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Normalised RMSE per spectrum: unit-L2-norm spectra, RMS over wavelengths. Shapes ``(..., n)``.

    Parameters
    ----------
    estimated, true : array_like
        Spectra ``(..., n)`` on the same wavelength grid, in any (the same or different) units: each is
        scaled to unit L2 norm first.

    Returns
    -------
    numpy.ndarray
        ``(...)`` float64 NRMSE, dimensionless (0 when one spectrum is a positive multiple of the other).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.2, Fig. 9 (normalized RMSE of the ColorChecker), Fig. 11 (spectra
       normalized as ``||e_m||² = ||ê||² = 1``).
    """
    e = np.asarray(estimated, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    en = e / np.maximum(np.linalg.norm(e, axis=-1, keepdims=True), 1e-300)
    tn = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-300)
    return np.sqrt(np.mean((en - tn) ** 2, axis=-1))


def spectral_angle_deg(estimated: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Spectral angle (degrees) between spectra ``(..., n)`` (Kruse et al. 1993, SAM)."""
    e = np.asarray(estimated, dtype=np.float64)
    t = np.asarray(true, dtype=np.float64)
    cos = (e * t).sum(-1) / np.maximum(np.linalg.norm(e, axis=-1) * np.linalg.norm(t, axis=-1), 1e-300)
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def colour_differences(estimated: np.ndarray, true: np.ndarray, white_spd: np.ndarray,
                       wavelength_nm: np.ndarray) -> dict[str, np.ndarray]:
    """ΔE*ab and ΔE00 between estimated and true colour signals, viewed under ``white_spd``."""
    lab_e = signal_to_Lab(estimated, white_spd, wavelength_nm)
    lab_t = signal_to_Lab(true, white_spd, wavelength_nm)
    return {
        "delta_e_ab": np.asarray(colour.delta_E(lab_t, lab_e, method="CIE 1976")),
        "delta_e_2000": np.asarray(colour.delta_E(lab_t, lab_e, method="CIE 2000")),
    }


def spectral_report(estimated: np.ndarray, true: np.ndarray, white_spd: np.ndarray,
                    wavelength_nm: np.ndarray) -> dict:
    """All metrics, per target and averaged: ``nrmse``, ``delta_e_ab``, ``delta_e_2000``, ``spectral_angle_deg``.

    Parameters
    ----------
    estimated, true : numpy.ndarray
        ``(P, n)`` estimated and true colour signals (spectral power of the light leaving each target).
    white_spd : numpy.ndarray
        ``(n,)`` the light source: the white of the colour differences (a perfect reflecting diffuser under it
        has Y = 100).
    wavelength_nm : numpy.ndarray
        ``(n,)`` the wavelength grid (nm).

    Returns
    -------
    dict
        Means over the targets of ``nrmse``, ``spectral_angle_deg`` (degrees), ``delta_e_ab`` and
        ``delta_e_2000``; ``delta_e_ab_max``; and ``per_target`` (each metric per target, as lists).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.2, Fig. 9 (average normalized RMSE and ΔE*ab over the ColorChecker).
    .. [2] CIE 015:2018, Colorimetry, 4th ed. (CIE 1931 2° XYZ, CIELAB, ΔE*ab (CIE 1976) and ΔE00 (CIE 2000)).
    .. [3] Kruse et al. 1993 (the spectral angle, SAM).
    """
    per = {
        "nrmse": nrmse(estimated, true),
        "spectral_angle_deg": spectral_angle_deg(estimated, true),
        **colour_differences(estimated, true, white_spd, wavelength_nm),
    }
    summary = {k: float(np.mean(v)) for k, v in per.items()}
    summary["delta_e_ab_max"] = float(np.max(per["delta_e_ab"]))
    summary["per_target"] = {k: [float(x) for x in v] for k, v in per.items()}
    return summary
