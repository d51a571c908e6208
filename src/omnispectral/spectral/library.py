"""Built-in spectral data: cameras, filters, illuminants and reflectance sets.

Everything here is either shipped by colour-science (camera sensitivities measured by NPL,
ColorChecker spectra, CIE illuminants and light sources, the RAW to ACES training set, CIE and
NIST colour samples) or shipped in this package under a permissive licence (Kodak Wratten 34A and 96,
Vrhel et al. 1994 reflectances via ISETCam, MIT).  See ``omnispectral/data/README.md``.

Every ``load_*`` function also accepts the path of a CSV file in the format of
:func:`~omnispectral.spectral.curves.read_spectral_csv`.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path

import colour
import numpy as np
from colour.characterisation import read_training_data_rawtoaces_v1
from colour.quality import SDS_TCS, SDS_VS

from omnispectral.choices import DEFAULT_CAMERA, DEFAULT_FILTERS, DEFAULT_ILLUMINANT, DEFAULT_TARGET
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.spectral.curves import SpectralSet, read_spectral_csv

__all__ = ["CALIBRATION_ILLUMINANTS", "CALIBRATION_REFLECTANCE_SETS", "DEFAULT_CAMERA", "DEFAULT_FILTERS",
           "DEFAULT_ILLUMINANT", "DEFAULT_TARGET", "MIN_FILTER_PEAK", "PRIOR_ILLUMINANTS",
           "PRIOR_REFLECTANCE_SETS", "camera_names",
           "daylight_spd", "denser_filter", "filter_names", "illuminant_names", "load_camera", "load_filter",
           "load_illuminant", "load_reflectances", "reflectance_set_names", "sp18_standin_transmittance"]

# Nine light sources for the prior (paper Sec. 4.6: "nine spectral power distributions of
# different light sources"): daylight from 4000 K to 10000 K, tungsten, three fluorescents and
# two white LEDs.
#: Smallest peak transmittance of a filter file (optical density 9; the paper's sun filter is density 3).
MIN_FILTER_PEAK = 1e-9
PRIOR_ILLUMINANTS = ("A", "D50", "D65", "D75", "D100", "FL2", "FL11", "LED-B3", "LED-V1")
# Light sources under which the noise variance is tuned (paper: "under various light sources").
CALIBRATION_ILLUMINANTS = ("A", "D50", "D65", "FL11", "LED-B3")

_PACKAGE_FILTERS = {
    "wratten-34a": "wratten_34a.csv",
    "wratten-96": "wratten_96.csv",
}
#: Stacked (or denser) versions of a shipped neutral-density filter: name -> (base filter, power of its transmittance).
_DENSER_FILTERS = {
    "wratten-96-nd3": ("wratten-96", 3),
}
_PACKAGE_REFLECTANCES = {
    "vrhel-objects": "vrhel_objects.csv",
    "vrhel-munsell": "vrhel_munsell.csv",
    "vrhel-dupont": "vrhel_dupont.csv",
}
PRIOR_REFLECTANCE_SETS = ("vrhel-objects", "vrhel-munsell", "vrhel-dupont", "rawtoaces-training")
CALIBRATION_REFLECTANCE_SETS = ("cie-tcs", "nist-cqs")


def _data_file(*parts: str) -> Path:
    return Path(str(resources.files("omnispectral").joinpath("data", *parts)))


def _looks_like_path(name: str) -> bool:
    return name.lower().endswith(".csv") or "/" in name or "\\" in name


# --------------------------------------------------------------------------------------- cameras
def camera_names() -> list[str]:
    """Names of the built-in camera sensitivity sets (colour-science, measured by NPL)."""
    return list(colour.MSDS_CAMERA_SENSITIVITIES.keys())


def load_camera(name: str = DEFAULT_CAMERA) -> SpectralSet:
    """RGB spectral sensitivities of a camera: a built-in name or a CSV file with three curves.

    Built-in: colour-science's ``MSDS_CAMERA_SENSITIVITIES`` (Nikon D5100 and Sigma SD Merrill
    measured by the UK National Physical Laboratory), matched case-insensitively; ``nikon``
    and ``sigma`` are accepted as short names.  The curves are scaled so the largest value is 1.
    """
    if _looks_like_path(name):
        cam = read_spectral_csv(name, "sensitivity")
        if len(cam) != 3:
            raise InputFileError(name, f"a camera needs 3 sensitivity curves (R, G, B); found {len(cam)}")
    else:
        match = [k for k in camera_names() if k.lower() == name.lower() or k.lower().startswith(name.lower())]
        if not match:
            raise ConfigurationError(f"unknown camera {name!r}; built-in: {camera_names()} or a CSV file")
        msds = colour.MSDS_CAMERA_SENSITIVITIES[match[0]]
        cam = SpectralSet(msds.wavelengths, msds.values.T, ["R", "G", "B"], "sensitivity", match[0])
    peak = cam.values.max()
    if peak <= 0:
        raise InputFileError(cam.source, "camera sensitivities are all zero")
    return SpectralSet(cam.wavelength_nm, cam.values / peak, cam.names, cam.kind, cam.source, cam.notes)


# --------------------------------------------------------------------------------------- filters
def sp18_standin_transmittance(wavelength_nm: np.ndarray, centre_nm: float = 545.0, width_nm: float = 55.0,
                               peak: float = 0.85, floor: float = 0.04) -> np.ndarray:
    """A synthetic middle-wavelength filter standing in for the Fujifilm SP-18.

    No transmittance curve of the Fujifilm SP-18 is published.  The paper (Sec. 3) describes its
    role: it "shifts the sensitivities to the middle wavelength", complementing the Kodak 34A
    which passes the short and long ends.  This stand-in is a smooth super-Gaussian pass band
    ``floor + (peak - floor) * exp(-((λ - centre) / width)^4 / 2)``: flat-topped around 545 nm
    and closing towards 450 and 640 nm, like a green-yellow gelatin filter.  Replace it with a
    measured curve (``--filter FILE.csv``) for real work.
    """
    x = (np.asarray(wavelength_nm, dtype=np.float64) - centre_nm) / width_nm
    return floor + (peak - floor) * np.exp(-0.5 * x**4)


def filter_names() -> list[str]:
    """Names of the built-in filters."""
    return [*_PACKAGE_FILTERS, *_DENSER_FILTERS, "sp18-standin", "none"]


def denser_filter(base: SpectralSet, power: int, label: str) -> SpectralSet:
    """A neutral-density filter ``power`` times as dense as ``base``: ``T_k(λ) = T_1(λ)^k``.

    Optical (transmission) density is ``D(λ) = -log10 T(λ)`` (ISO 5-1 notation).  By the Beer-Lambert
    law the absorbance of one dye is proportional to the amount of dye in the light path, so a layer
    ``k`` times as dense, or ``k`` stacked layers (inter-reflections neglected), has density ``k D(λ)``
    and transmittance ``T(λ)^k``.  Kodak makes its Wratten No. 96 gelatin neutral-density filters in
    densities 0.1-4.0 from the same dye (Kodak, *Kodak Wratten Filters for Scientific and Technical
    Use*, A. C. Peed Jr.), so ``wratten-96-nd3`` (ND 3.0) is the tabulated ND 1.0 curve cubed
    (0.008-0.09 % on 400-700 nm).  The cube is our derivation, not a tabulated curve.
    """
    if int(power) != power or power < 1:
        raise ConfigurationError(f"a denser filter needs a positive integer power, got {power!r}")
    return SpectralSet(base.wavelength_nm, base.values ** int(power), [label], base.kind,
                       f"{base.source} ^ {int(power)}", base.notes)


def load_filter(name: str) -> SpectralSet:
    """Transmittance of a filter: ``wratten-34a``, ``wratten-96`` (Kodak neutral density 1.0, as tabulated),
    ``wratten-96-nd3`` (neutral density 3.0, the ND 1.0 curve cubed: :func:`denser_filter`),
    ``sp18-standin``, ``none`` or a CSV file (one curve).

    Parameters
    ----------
    name : str
        A built-in filter name (case-insensitive; ``sp-18`` and ``sp18`` name the stand-in too) or the path of a
        transmittance CSV with exactly one curve.

    Returns
    -------
    SpectralSet
        One transmittance curve (fraction, 0-1) on its own wavelength grid (nm): the tabulated grid of a
        shipped or CSV filter, 360-830 nm every 1 nm for the synthetic SP-18 stand-in and ``none``.

    Raises
    ------
    InputFileError
        For a CSV that does not hold exactly one curve, or whose transmittance is zero everywhere.
    ConfigurationError
        For an unknown name.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3, Fig. 3 (transmittances of 36 colour filters; KODAK No. 34A and
       FUJIFILM SP-18 selected), Fig. 4.
    .. [2] Kodak, "Kodak Wratten Filters for Scientific and Technical Use" (A. C. Peed Jr.), the source of the
       Wratten No. 34A and No. 96 tables (``omnispectral/data/README.md``).
    """
    key = name.lower()
    if key in _DENSER_FILTERS:
        base, power = _DENSER_FILTERS[key]
        return denser_filter(load_filter(base), power, f"{name} ({base} ^ {power})")
    if _looks_like_path(name):
        f = read_spectral_csv(name, "transmittance")
        if len(f) != 1:
            raise InputFileError(name, f"a filter file needs exactly one transmittance curve; found {len(f)}")
        if not np.any(f.values > 0):
            raise InputFileError(name, "the filter's transmittance is zero at every wavelength")
        if float(f.values.max()) < MIN_FILTER_PEAK:
            raise InputFileError(name, f"the filter's transmittance peaks at {float(f.values.max()):g} (below "
                                       f"{MIN_FILTER_PEAK:g}, optical density > 9): no usable light passes")
        return f
    if key in _PACKAGE_FILTERS:
        path = _data_file("filters", _PACKAGE_FILTERS[key])
        f = read_spectral_csv(path, "transmittance")
        return SpectralSet(f.wavelength_nm, f.values, f.names, f.kind, f"{name} ({path.name})", f.notes)
    wl = np.arange(360.0, 830.0 + 1e-9, 1.0)
    if key in ("sp18-standin", "sp-18", "sp18"):
        return SpectralSet(wl, sp18_standin_transmittance(wl)[None], ["SP-18 stand-in (synthetic)"],
                           "transmittance", "sp18-standin (synthetic, not a measurement)")
    if key == "none":
        return SpectralSet(wl, np.ones((1, wl.size)), ["no filter"], "transmittance", "none")
    raise ConfigurationError(f"unknown filter {name!r}; built-in: {filter_names()} or a CSV file")


# ----------------------------------------------------------------------------------- illuminants
_DAYLIGHT_RE = re.compile(r"^D(\d{2,3})$", re.IGNORECASE)
_CCT_RE = re.compile(r"^(\d{4,5})\s*K$", re.IGNORECASE)


def daylight_spd(cct_K: float) -> colour.SpectralDistribution:
    """CIE daylight (D-series) spectral power distribution at correlated colour temperature ``cct_K``.

    Uses the CIE 015:2018 daylight locus (colour-science ``CCT_to_xy_CIE_D``) and basis functions.
    Valid from 4000 K to 25000 K.
    """
    if not 4000.0 <= cct_K <= 25000.0:
        raise ConfigurationError(f"CIE daylight is defined for 4000-25000 K, got {cct_K:g} K")
    xy = colour.temperature.CCT_to_xy_CIE_D(cct_K * 1.4388 / 1.4380)
    return colour.sd_CIE_illuminant_D_series(xy)


def illuminant_names() -> list[str]:
    """Names of built-in illuminants and light sources (plus ``D<nn>`` and ``<cct>K`` daylights)."""
    return [*colour.SDS_ILLUMINANTS.keys(), *colour.SDS_LIGHT_SOURCES.keys()]


def load_illuminant(name: str) -> SpectralSet:
    """Spectral power distribution of a light source.

    ``name`` is a CIE illuminant or light source known to colour-science (``D65``, ``A``,
    ``FL11``, ``LED-B3`` ...), a daylight as ``D<cct/100>`` (``D100`` = 10000 K) or ``<cct>K``
    (``5500K``), or a CSV file with one curve.
    """
    if _looks_like_path(name):
        s = read_spectral_csv(name, "illuminant")
        if len(s) != 1:
            raise InputFileError(name, f"an illuminant file needs exactly one curve; found {len(s)}")
        return s
    for table in (colour.SDS_ILLUMINANTS, colour.SDS_LIGHT_SOURCES):
        for key in table:
            if key.lower() == name.lower():
                return SpectralSet.from_colour(table[key], "illuminant", key, names=[key])
    m = _DAYLIGHT_RE.match(name) or _CCT_RE.match(name)
    if m:
        cct = float(m.group(1)) * (100.0 if _DAYLIGHT_RE.match(name) else 1.0)
        return SpectralSet.from_colour(daylight_spd(cct), "illuminant", f"CIE daylight {cct:.0f} K",
                                       names=[name])
    raise ConfigurationError(f"unknown illuminant {name!r}; try D65, A, FL11, LED-B3, D100, 5500K or a CSV file")


# ---------------------------------------------------------------------------------- reflectances
def reflectance_set_names() -> list[str]:
    """Names of built-in reflectance sets."""
    return ["colorchecker", "colorchecker-babel", "colorchecker-iso17321", *_PACKAGE_REFLECTANCES,
            "rawtoaces-training", "cie-tcs", "nist-cqs"]


def _colour_mapping_set(mapping, source: str) -> SpectralSet:
    return SpectralSet.from_colour(dict(mapping), "reflectance", source)


def load_reflectances(name: str) -> SpectralSet:
    """A set of surface reflectances (fractions).

    Built-in sets: ``colorchecker`` (X-Rite ColorChecker, N. Ohta's measurement, the evaluation
    target of paper Sec. 5.2), ``colorchecker-babel`` (BabelColor average),
    ``colorchecker-iso17321``, ``vrhel-objects`` / ``vrhel-munsell`` / ``vrhel-dupont`` (Vrhel et
    al. 1994, 170 + 64 + 120 samples), ``rawtoaces-training`` (190 RAW to ACES training
    spectra), ``cie-tcs`` (14 CIE 13.3 test colour samples) and ``nist-cqs`` (15 NIST CQS 9.0
    samples).  Anything else is read as a CSV file.
    """
    key = name.lower()
    if _looks_like_path(name):
        return read_spectral_csv(name, "reflectance")
    if key in ("colorchecker", "colorchecker-ohta"):
        return _colour_mapping_set(colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"], "ColorChecker N Ohta")
    if key == "colorchecker-babel":
        return _colour_mapping_set(colour.SDS_COLOURCHECKERS["BabelColor Average"], "BabelColor Average")
    if key == "colorchecker-iso17321":
        return _colour_mapping_set(colour.SDS_COLOURCHECKERS["ISO 17321-1"], "ISO 17321-1")
    if key in _PACKAGE_REFLECTANCES:
        path = _data_file("reflectances", _PACKAGE_REFLECTANCES[key])
        s = read_spectral_csv(path, "reflectance", percent=False)
        return SpectralSet(s.wavelength_nm, s.values, s.names, s.kind, key)
    if key == "rawtoaces-training":
        return SpectralSet.from_colour(read_training_data_rawtoaces_v1(), "reflectance", key)
    if key == "cie-tcs":
        return _colour_mapping_set(SDS_TCS["CIE 1995"], key)
    if key == "nist-cqs":
        return _colour_mapping_set(SDS_VS["NIST CQS 9.0"], key)
    raise ConfigurationError(f"unknown reflectance set {name!r}; built-in: {reflectance_set_names()} or a CSV file")
