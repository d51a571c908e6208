"""Every CIE colorimetric conversion of the package, on colour-science's data: spectra → XYZ → sRGB / CIELAB / CCT.

All use the CIE 1931 2° standard observer (colour-science's ``MSDS_CMFS``).  The functions differ
in how they put the colour-matching functions on a wavelength grid, and each caller relies on its
variant's numbers, so the variants are named rather than merged:

- :func:`cmfs_on_grid` ``(3, n)``: colour-science's linear interpolator, extrapolation refused
  (metrics, band selection, exports);
- :func:`cmfs_xyz` ``(n, 3)``: linear interpolation, zero outside 360-830 nm (scene illuminants);
- :func:`ybar_5nm`: ȳ on CIE 015's 360-830 nm / 5 nm summation grid (photometry).

Conversions:

- :func:`signal_to_XYZ`: colour signals relative to a white with ``Y_white = 100`` (CIE 015), and
  :func:`signal_to_Lab` (CIELAB with that white) for colour differences;
- :func:`reflectance_lab`: CIELAB of reflectances under D65;
- :func:`spectra_to_xyz` / :func:`xyz_to_linear_srgb` / :func:`spectra_to_linear_srgb`: absolute
  tristimulus and linear sRGB-primaries RGB of radiance spectra (exports, previews);
- :func:`srgb_encode`: the sRGB transfer function (IEC 61966-2-1);
- :func:`spectrum_cct_K`: correlated colour temperature (Ohno 2013).
"""

from __future__ import annotations

from functools import cache

import colour
import numpy as np

from omnispectral.spectral.curves import SpectralSet

#: The observer of every conversion here.
CIE_1931_2 = "CIE 1931 2 Degree Standard Observer"
#: Maximum luminous efficacy of radiation (lm/W) at 555 nm (SI definition of the candela).
K_M_LM_PER_W = 683.0
#: CIE 015's summation grid for photometric and colorimetric integrals.
LUMINOUS_GRID_NM = np.arange(360.0, 830.0 + 1e-9, 5.0)
#: XYZ → linear RGB with sRGB/Rec.709 primaries and D65 white (IEC 61966-2-1).
XYZ_TO_LINEAR_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                               [-0.9692660, 1.8760108, 0.0415560],
                               [0.0556434, -0.2040259, 1.0572252]], np.float32)


def cmfs_on_grid(wavelength_nm: np.ndarray, observer: str = CIE_1931_2) -> np.ndarray:
    """Colour-matching functions ``(3, n)`` resampled onto ``wavelength_nm`` (colour-science data)."""
    cmfs = colour.MSDS_CMFS[observer]
    return SpectralSet(cmfs.wavelengths, cmfs.values.T, ["x", "y", "z"], "sensitivity", observer).resample(
        wavelength_nm).values


def cmfs_xyz(wavelength_nm) -> np.ndarray:
    """CIE 1931 2° colour-matching functions ``(n, 3)`` at ``wavelength_nm`` (zero outside 360-830 nm)."""
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    return np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, i], left=0.0, right=0.0) for i in range(3)],
                    axis=-1)


@cache
def ybar_5nm() -> np.ndarray:
    """ȳ on :data:`LUMINOUS_GRID_NM` (CIE 015's 5-nm table, no interpolation)."""
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    return np.asarray(cmfs[LUMINOUS_GRID_NM])[:, 1]


def signal_to_XYZ(signals: np.ndarray, white_spd: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Tristimulus values of colour signals ``(..., n)`` relative to a white ``(n,)`` with ``Y_white = 100``.

    For a reflectance ``r`` under illuminant ``S`` (signal ``r S``, white ``S``) this is CIE 015's
    :math:`X = k\\sum r S \\bar x\\,\\Delta\\lambda`, :math:`k = 100/\\sum S \\bar y\\,\\Delta\\lambda`,
    which colour-science computes as ``sd_to_XYZ(r, illuminant=S, method="Integration")``.
    """
    cmfs = cmfs_on_grid(wavelength_nm)
    k = 100.0 / float(np.asarray(white_spd) @ cmfs[1])
    return k * (np.asarray(signals, dtype=np.float64) @ cmfs.T)


def signal_to_Lab(signals: np.ndarray, white_spd: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIELAB ``(..., 3)`` of colour signals with ``white_spd`` as the reference white (:func:`signal_to_XYZ`)."""
    white_xy = colour.XYZ_to_xy(signal_to_XYZ(white_spd, white_spd, wavelength_nm))
    return colour.XYZ_to_Lab(signal_to_XYZ(signals, white_spd, wavelength_nm) / 100.0, white_xy)


def reflectance_lab(wavelength_nm: np.ndarray, reflectance: np.ndarray) -> np.ndarray:
    """CIELAB ``(k, 3)`` of reflectances ``(k, n)`` under D65 (CIE 1931 2°), summed on ``wavelength_nm``."""
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    xyz_bar = np.stack([np.interp(wl, cmfs.wavelengths, cmfs.values[:, i]) for i in range(3)], axis=-1)
    e = np.interp(wl, d65.wavelengths, d65.values)
    w = xyz_bar * e[:, None]
    xyz = np.atleast_2d(reflectance) @ w / w[:, 1].sum()
    return colour.XYZ_to_Lab(xyz, colour.CCS_ILLUMINANTS[CIE_1931_2]["D65"])


def spectra_to_xyz(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIE 1931 2° tristimulus ``Σ S(λ) cmf(λ) Δλ`` of spectra ``(..., n)`` (no normalisation)."""
    cmfs = cmfs_on_grid(np.asarray(wavelength_nm, float)).T  # (n, 3)
    dl = np.gradient(np.asarray(wavelength_nm, float))
    return np.asarray(spectra, np.float32) @ (cmfs * dl[:, None]).astype(np.float32)


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear RGB with sRGB/Rec.709 primaries and D65 white (IEC 61966-2-1 matrix), no clipping."""
    return np.asarray(xyz, np.float32) @ XYZ_TO_LINEAR_SRGB.T


def spectra_to_linear_srgb(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Spectral radiance → linear sRGB-primaries RGB (Y = luminance in the spectra's units × Σȳ)."""
    return xyz_to_linear_srgb(spectra_to_xyz(spectra, wavelength_nm))


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode`: linear values of sRGB-encoded values in [0, 1] (IEC 61966-2-1)."""
    v = np.asarray(encoded, np.float64)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


def spectrum_cct_K(wavelength_nm, spectrum) -> float:
    """CCT of a spectral power distribution (CIE 1931 2°; Ohno 2013 via CIE 1960 uv)."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    xyz = np.asarray(spectrum, dtype=np.float64) @ cmfs_xyz(wl)
    uv = colour.xy_to_UCS_uv(colour.XYZ_to_xy(xyz))
    return float(colour.temperature.uv_to_CCT_Ohno2013(uv)[0])
