"""Every CIE colorimetric conversion of the package, on colour-science's data: spectra → XYZ → sRGB / CIELAB / CCT.

All use the CIE 1931 2° standard observer (colour-science's ``MSDS_CMFS``, tabulated every 1 nm on
360-830 nm).  The functions differ in how they put the colour-matching functions on a wavelength grid,
and each caller relies on its variant's numbers, so the variants are named rather than merged:

- :func:`cmfs_on_grid` ``(3, n)``: linear interpolation (:meth:`SpectralSet.resample
  <omnispectral.spectral.curves.SpectralSet.resample>`), extrapolation refused (metrics, band selection,
  exports, the applications);
- :func:`cmfs_xyz` ``(n, 3)``: linear interpolation, zero outside 360-830 nm (scene illuminants);
- :func:`ybar_5nm`: ȳ on CIE 015's 360-830 nm / 5 nm summation grid (photometry).

Conversions:

- :func:`signal_to_XYZ`: colour signals relative to a white with ``Y_white = 100`` (CIE 015), and
  :func:`signal_to_Lab` (CIELAB with that white) for colour differences, :func:`delta_e_ab` (CIE 1976);
- :func:`reflectance_lab`: CIELAB of reflectances under D65;
- :func:`spectra_to_xyz` / :func:`xyz_to_linear_srgb` / :func:`spectra_to_linear_srgb`: absolute
  tristimulus ``X = Σ L(λ) x̄(λ) Δλ`` (emissive, ``k = 1``, no illuminant: colour-science's
  ``sd_to_XYZ(method="Integration", k=1)``) and linear sRGB-primaries RGB of radiance spectra
  (exports, previews, renders, relighting);
- :func:`srgb_encode` / :func:`srgb_decode`: the sRGB transfer function (IEC 61966-2-1);
- :func:`spectrum_cct_K`: correlated colour temperature (Ohno 2013).

On a grid of whole nanometres inside 360-830 nm the colour-matching functions are colour-science's table
values themselves (no interpolation happens), so :func:`spectra_to_xyz` equals colour-science's
``Integration`` method there to rounding.
"""

from __future__ import annotations

from functools import cache, lru_cache

import colour
import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.curves import SpectralSet, resample_spectra

__all__ = ["CIE_1931_2", "K_M_LM_PER_W", "LUMINOUS_GRID_NM", "XYZ_TO_LINEAR_SRGB", "cmfs_on_grid", "cmfs_xyz",
           "delta_e_ab", "reflectance_lab", "signal_to_Lab", "signal_to_XYZ", "spectra_to_linear_srgb",
           "spectra_to_xyz", "spectrum_cct_K", "srgb_decode", "srgb_encode", "xyz_to_linear_srgb", "ybar_5nm"]

#: The observer of every conversion here.
CIE_1931_2 = "CIE 1931 2 Degree Standard Observer"
#: Maximum luminous efficacy of radiation (lm/W) at 555 nm (SI definition of the candela).
K_M_LM_PER_W = 683.0
#: CIE 015's summation grid for photometric and colorimetric integrals.
LUMINOUS_GRID_NM = np.arange(360.0, 830.0 + 1e-9, 5.0)
#: XYZ → linear RGB with sRGB/Rec.709 primaries and D65 white, derived from the primaries and white point of
#: IEC 61966-2-1 to 7 digits (colour-science's ``sRGB`` colourspace uses the standard's 4-digit rounding;
#: the two differ by at most 1.5e-4 relative).
XYZ_TO_LINEAR_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                               [-0.9692660, 1.8760108, 0.0415560],
                               [0.0556434, -0.2040259, 1.0572252]], np.float32)


def cmfs_on_grid(wavelength_nm: np.ndarray, observer: str = CIE_1931_2) -> np.ndarray:
    """Colour-matching functions resampled (linearly) onto a wavelength grid.

    Parameters
    ----------
    wavelength_nm
        The grid (nm), within 360-830 nm.
    observer
        A colour-science observer name.

    Returns
    -------
    numpy.ndarray
        ``(3, n)`` float64: x̄, ȳ, z̄.

    Raises
    ------
    InputFileError
        When the grid reaches outside the observer's table (no extrapolation).
    """
    cmfs = colour.MSDS_CMFS[observer]
    return SpectralSet(cmfs.wavelengths, cmfs.values.T, ["x", "y", "z"], "sensitivity", observer).resample(
        wavelength_nm).values


def cmfs_xyz(wavelength_nm) -> np.ndarray:
    """CIE 1931 2° colour-matching functions, zero outside 360-830 nm.

    Parameters
    ----------
    wavelength_nm
        Wavelengths (nm), any range.

    Returns
    -------
    numpy.ndarray
        ``(n, 3)`` float64: linear interpolation of the table, 0 outside it.
    """
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    return np.ascontiguousarray(resample_spectra(cmfs.values.T, cmfs.wavelengths,
                                                 np.asarray(wavelength_nm, dtype=np.float64), outside=0.0).T)


@cache
def ybar_5nm() -> np.ndarray:
    """ȳ on CIE 015's summation grid, no interpolation.

    Returns
    -------
    numpy.ndarray
        ȳ at :data:`LUMINOUS_GRID_NM` (360-830 nm every 5 nm).
    """
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    return np.asarray(cmfs[LUMINOUS_GRID_NM])[:, 1]


def signal_to_XYZ(signals: np.ndarray, white_spd: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Tristimulus values of colour signals relative to a white with ``Y_white = 100``.

    For a reflectance ``r`` under illuminant ``S`` (signal ``r S``, white ``S``) this is CIE 015's
    :math:`X = k\\sum r S \\bar x\\,\\Delta\\lambda`, :math:`k = 100/\\sum S \\bar y\\,\\Delta\\lambda`,
    which colour-science computes as ``sd_to_XYZ(r, illuminant=S, method="Integration")``.

    Parameters
    ----------
    signals
        Colour signals ``(..., n)``.
    white_spd
        The white's signal ``(n,)`` (the illuminant, or the perfect diffuser under it).
    wavelength_nm
        The grid ``(n,)`` (nm).

    Returns
    -------
    numpy.ndarray
        XYZ ``(..., 3)`` float64.
    """
    cmfs = cmfs_on_grid(wavelength_nm)
    k = 100.0 / float(np.asarray(white_spd) @ cmfs[1])
    return k * (np.asarray(signals, dtype=np.float64) @ cmfs.T)


def signal_to_Lab(signals: np.ndarray, white_spd: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIELAB of colour signals with ``white_spd`` as the reference white (:func:`signal_to_XYZ`).

    Parameters
    ----------
    signals
        Colour signals ``(..., n)``.
    white_spd
        The reference white's signal ``(n,)``.
    wavelength_nm
        The grid ``(n,)`` (nm).

    Returns
    -------
    numpy.ndarray
        CIELAB ``(..., 3)``.
    """
    white_xy = colour.XYZ_to_xy(signal_to_XYZ(white_spd, white_spd, wavelength_nm))
    return colour.XYZ_to_Lab(signal_to_XYZ(signals, white_spd, wavelength_nm) / 100.0, white_xy)


def delta_e_ab(lab_a: np.ndarray, lab_b: np.ndarray) -> np.ndarray:
    """CIE 1976 colour difference ΔE*ab (colour-science).

    Parameters
    ----------
    lab_a, lab_b
        CIELAB values ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        ``(...)`` Euclidean distances in CIELAB.
    """
    return np.asarray(colour.delta_E(lab_a, lab_b, method="CIE 1976"))


def reflectance_lab(wavelength_nm: np.ndarray, reflectance: np.ndarray) -> np.ndarray:
    """CIELAB of reflectances under D65 (CIE 1931 2°), summed on their grid.

    Parameters
    ----------
    wavelength_nm
        The grid ``(n,)`` (nm); the observer and D65 are interpolated linearly onto it (their end values
        beyond their tables).
    reflectance
        Reflectances ``(k, n)`` (or ``(n,)``).

    Returns
    -------
    numpy.ndarray
        CIELAB ``(k, 3)`` with D65's white point.
    """
    cmfs = colour.MSDS_CMFS[CIE_1931_2]
    d65 = colour.SDS_ILLUMINANTS["D65"]
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    xyz_bar = np.ascontiguousarray(resample_spectra(cmfs.values.T, cmfs.wavelengths, wl, outside="edge").T)
    e = resample_spectra(d65.values, d65.wavelengths, wl, outside="edge")
    w = xyz_bar * e[:, None]
    xyz = np.atleast_2d(reflectance) @ w / w[:, 1].sum()
    return colour.XYZ_to_Lab(xyz, colour.CCS_ILLUMINANTS[CIE_1931_2]["D65"])


@lru_cache(maxsize=16)
def _cmf_weights(wavelength_nm: tuple[float, ...]) -> np.ndarray:
    """``(n, 3)`` float64 ``cmf(λ) Δλ`` on a grid (``Δλ`` by ``np.gradient``: the step on a uniform grid); read-only."""
    wl = np.asarray(wavelength_nm, float)
    w = cmfs_on_grid(wl).T * np.gradient(wl)[:, None]
    w.flags.writeable = False
    return w


def spectra_to_xyz(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """CIE 1931 2° tristimulus ``Σ S(λ) cmf(λ) Δλ`` of emissive spectra (``k = 1``, no normalisation).

    Parameters
    ----------
    spectra
        Spectra ``(..., n)`` (NaN kept).  float64 spectra are summed in float64; any other dtype in float32.
    wavelength_nm
        The grid ``(n,)`` (nm), within 360-830 nm, uniform or not (``Δλ`` by ``np.gradient``).

    Returns
    -------
    numpy.ndarray
        XYZ ``(..., 3)``: float64 for float64 spectra, else float32.

    Raises
    ------
    ConfigurationError
        When the spectra's last axis does not match the grid.
    InputFileError
        When the grid reaches outside the observer's table.
    """
    wl = np.asarray(wavelength_nm, float)
    s = np.asarray(spectra)
    if s.ndim == 0 or s.shape[-1] != wl.size:
        raise ConfigurationError(f"spectra with {s.shape[-1] if s.ndim else 0} samples do not match "
                                 f"{wl.size} wavelengths")
    w = _cmf_weights(tuple(wl.tolist()))
    if s.dtype == np.float64:
        return s @ w
    return np.asarray(s, np.float32) @ w.astype(np.float32)


def xyz_to_linear_srgb(xyz: np.ndarray) -> np.ndarray:
    """Linear RGB with sRGB/Rec.709 primaries and D65 white (:data:`XYZ_TO_LINEAR_SRGB`), no clipping.

    Parameters
    ----------
    xyz
        CIE XYZ ``(..., 3)``.

    Returns
    -------
    numpy.ndarray
        float32 ``(..., 3)``, computed in float32; no transfer function.
    """
    return np.asarray(xyz, np.float32) @ XYZ_TO_LINEAR_SRGB.T


def spectra_to_linear_srgb(spectra: np.ndarray, wavelength_nm: np.ndarray) -> np.ndarray:
    """Linear sRGB-primaries RGB of emissive spectra: :func:`xyz_to_linear_srgb` of :func:`spectra_to_xyz`.

    An image quantity: computed in float32 throughout (the spectra are cast to float32 first, whatever their
    dtype).

    Parameters
    ----------
    spectra
        Spectral radiance ``(..., n)``.
    wavelength_nm
        The grid ``(n,)`` (nm).

    Returns
    -------
    numpy.ndarray
        float32 ``(..., 3)``; Y = luminance in the spectra's units × Σȳ.
    """
    return xyz_to_linear_srgb(spectra_to_xyz(np.asarray(spectra, np.float32), wavelength_nm))


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1).

    Parameters
    ----------
    linear
        Linear values in [0, 1].

    Returns
    -------
    numpy.ndarray
        Encoded values in [0, 1].
    """
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode` (IEC 61966-2-1).

    Parameters
    ----------
    encoded
        sRGB-encoded values in [0, 1].

    Returns
    -------
    numpy.ndarray
        float64 linear values.
    """
    v = np.asarray(encoded, np.float64)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


def spectrum_cct_K(wavelength_nm, spectrum) -> float:
    """Correlated colour temperature of a spectral power distribution (CIE 1931 2°; Ohno 2013 via CIE 1960 uv).

    Parameters
    ----------
    wavelength_nm
        The grid ``(n,)`` (nm).
    spectrum
        The distribution ``(n,)``.

    Returns
    -------
    float
        CCT in kelvin.
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    xyz = np.asarray(spectrum, dtype=np.float64) @ cmfs_xyz(wl)
    uv = colour.xy_to_UCS_uv(colour.XYZ_to_xy(xyz))
    return float(colour.temperature.uv_to_CCT_Ohno2013(uv)[0])
