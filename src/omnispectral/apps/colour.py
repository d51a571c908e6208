"""Colour of spectral images for the applications, computed by colour-science (no copy of the CIE tables here).

Emissive spectra (radiance) integrate against the CIE 1931 2° observer with ``k = 1`` and no illuminant
(``X = Σ L(λ) x̄(λ) Δλ``, colour-science's ``msds_to_XYZ(method="Integration")``); reflectance-like
colours are relative to a white signal (CIE 015, ``Y_white = 1``).
"""

from __future__ import annotations

import functools

import colour
import numpy as np

from omnispectral.errors import ConfigurationError

OBSERVER = "CIE 1931 2 Degree Standard Observer"


def _shape(wavelength_nm: np.ndarray) -> colour.SpectralShape:
    wl = np.asarray(wavelength_nm, float)
    steps = np.diff(wl)
    if wl.size < 2 or not np.allclose(steps, steps[0]):
        raise ConfigurationError("colour of spectra needs a uniform wavelength grid")
    return colour.SpectralShape(float(wl[0]), float(wl[-1]), float(steps[0]))


@functools.lru_cache(maxsize=8)
def _cmf_weights(start: float, stop: float, step: float) -> np.ndarray:
    """``(n, 3)`` CIE 1931 colour-matching functions × Δλ on a grid, from colour-science's table: the weights of
    its ``Integration`` method (checked against ``msds_to_XYZ`` in the tests)."""
    shape = colour.SpectralShape(start, stop, step)
    return (colour.MSDS_CMFS[OBSERVER].copy().align(shape).values * step).astype(np.float64)


def spectra_to_xyz(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIE 1931 XYZ ``Σ S(λ) cmf(λ) Δλ`` of spectra ``(..., n)`` (emissive, no normalisation; NaN kept); float32
    spectra give float32 XYZ."""
    shape = _shape(wavelength_nm)
    w = _cmf_weights(float(shape.start), float(shape.end), float(shape.interval))
    s = np.asarray(spectra)
    if s.shape[-1] != w.shape[0]:
        raise ConfigurationError(f"spectra with {s.shape[-1]} samples do not match {w.shape[0]} wavelengths")
    return s @ w.astype(s.dtype if s.dtype in (np.float32, np.float64) else np.float64)


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear sRGB (Rec. 709 primaries, D65) of XYZ, no clipping, no transfer function (colour-science)."""
    return np.asarray(colour.XYZ_to_RGB(np.asarray(xyz, np.float64), "sRGB", apply_cctf_encoding=False),
                      np.float32)


def spectra_to_linear_srgb(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Linear sRGB of emissive spectra ``(..., n)`` (Y = luminance in the spectra's units × Σȳ)."""
    return xyz_to_linear_srgb(spectra_to_xyz(spectra, wavelength_nm))


def signals_to_lab(signals: np.ndarray, white_signal: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIELAB of colour signals relative to a white signal (the perfect diffuser under the same light)."""
    xyz = spectra_to_xyz(signals, wavelength_nm)
    white = spectra_to_xyz(np.asarray(white_signal)[None], wavelength_nm)[0]
    return np.asarray(colour.XYZ_to_Lab(xyz / white[1], colour.XYZ_to_xy(white / white[1])))


def delta_e_ab(lab_a: np.ndarray, lab_b: np.ndarray) -> np.ndarray:
    """CIE 1976 ΔE*ab (colour-science)."""
    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 1976"))
