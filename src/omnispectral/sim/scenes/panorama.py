"""Any HDR RGB equirectangular panorama as a spectral scene at infinity.

The panorama's linear Rec. 709 / sRGB values are up-sampled to spectra with the spectral primary
decomposition of Mallett & Yuksel ("Spectral Primary Decomposition for Rendering with sRGB
Reflectance", Eurographics Symposium on Rendering, 2019; basis functions from colour-science's
``MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019``, 380-780 nm / 5 nm): three non-negative basis spectra
``B_r, B_g, B_b`` that sum to one and whose D65-lit colours are the sRGB primaries.  The method is
linear, so HDR values scale without clipping and each pixel's spectrum is ``Σ_c rgb_c B_c(λ)``.
Those are reflectance-like; as radiance the scene uses them lit by D65 (the sRGB white point):

    ``L(λ) = scale · Σ_c rgb_c B_c(λ) · D65(λ) / (683 Σ D65 ȳ Δλ)``     (W·sr⁻¹·m⁻²·nm⁻¹)

so a pixel of Rec. 709 luminance ``Y = 0.2126 R + 0.7152 G + 0.0722 B`` has luminance
``scale · Y`` cd/m², and rendering ``L`` back through the CIE 1931 observer and the sRGB matrix
returns the pixel's RGB (within the basis' round-trip error).

Directions are looked up with bilinear interpolation between pixel centres (column 0 at
longitude -180°, row 0 at latitude +90°, centres at +0.5), wrapping in longitude and holding the
first/last row towards the poles.  The panorama is at infinity: ``origin_m`` has no effect.
"""

from __future__ import annotations

import math
from pathlib import Path

import colour
import cv2
import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bracket import read_exr
from omnispectral.sim.scenes.base import RAY_BLOCK, BandProjectionCache, Scene, as_directions, as_origin
from omnispectral.spectral.colour import K_M_LM_PER_W, LUMINOUS_GRID_NM, cmfs_xyz
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM, resample_spectra

__all__ = ["PanoramaScene", "check_panorama", "lookup_bilinear", "mallett2019_emission_basis", "read_panorama"]


def read_panorama(path: str | Path) -> np.ndarray:
    """Read an HDR panorama (``.hdr`` Radiance RGBE via OpenCV, ``.exr`` via OpenEXR) as linear RGB ``(H, W, 3)``.

    Raises :class:`~omnispectral.errors.InputFileError` naming the file when it is missing, not
    readable, not RGB or not finite.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "no such file")
    suffix = path.suffix.lower()
    if suffix == ".hdr":
        data = np.fromfile(str(path), dtype=np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None or img.ndim != 3 or img.shape[2] < 3:
            raise InputFileError(path, "cannot be read as a Radiance HDR RGB image")
        rgb = img[:, :, 2::-1]  # OpenCV gives BGR
    elif suffix == ".exr":
        img, names = read_exr(path)
        if all(c in names for c in "RGB"):
            rgb = img[:, :, [names.index(c) for c in "RGB"]]
        elif "Y" in names:
            rgb = np.repeat(img[:, :, [names.index("Y")]], 3, axis=2)
        else:
            raise InputFileError(path, f"OpenEXR file has no R, G, B (or Y) channels; channels: {names}")
    else:
        raise InputFileError(path, f"unsupported panorama format {suffix!r}; expected .hdr or .exr")
    return check_panorama(rgb, path)


def check_panorama(rgb, source: str | Path | None = None) -> np.ndarray:
    """Validate an equirectangular RGB array ``(H, W, 3)`` with ``W = 2H``; returns float32, negatives clipped.

    Errors name ``source`` (a file) as :class:`InputFileError`, or are :class:`ConfigurationError` for arrays.
    """
    def fail(problem: str):
        return InputFileError(source, problem) if source is not None else ConfigurationError(f"panorama: {problem}")

    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise fail(f"expected an RGB image of shape (H, W, 3), got {a.shape}")
    h, w = a.shape[:2]
    if h < 2 or abs(w - 2 * h) > 1:
        raise fail(f"an equirectangular panorama is twice as wide as high; got {w}×{h}")
    if a.dtype.kind not in "uif":
        raise fail(f"unsupported pixel type {a.dtype}")
    a = np.ascontiguousarray(a, dtype=np.float32)
    if not np.all(np.isfinite(a)):
        raise fail("contains NaN or infinite values")
    return np.maximum(a, 0.0)


def mallett2019_emission_basis(wavelength_nm) -> np.ndarray:
    """Mallett & Yuksel (2019) basis lit by D65, per unit luminance: ``(3, n)`` W·sr⁻¹·m⁻²·nm⁻¹ per cd/m².

    ``E_c(λ) = B_c(λ) D65(λ) / (683 Σ_{360..830} D65 ȳ Δλ)``, on ``wavelength_nm`` by linear
    interpolation of the 5-nm basis; the grid must lie within 380-780 nm.
    """
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    basis = colour.recovery.MSDS_BASIS_FUNCTIONS_sRGB_MALLETT2019
    if wl.min() < basis.wavelengths[0] - 1e-9 or wl.max() > basis.wavelengths[-1] + 1e-9:
        raise ConfigurationError(f"the Mallett 2019 basis covers {basis.wavelengths[0]:g}-{basis.wavelengths[-1]:g} "
                                 f"nm; the wavelength grid {wl.min():g}-{wl.max():g} nm goes beyond it")
    d65 = colour.SDS_ILLUMINANTS["D65"]
    grid = LUMINOUS_GRID_NM
    d65_on_grid = resample_spectra(d65.values, d65.wavelengths, grid, outside="edge")
    k = K_M_LM_PER_W * float(np.sum(d65_on_grid * cmfs_xyz(grid)[:, 1])) * 5.0
    e = resample_spectra(d65.values, d65.wavelengths, wl, outside="edge") / k
    return np.stack([resample_spectra(basis.values[:, c], basis.wavelengths, wl, outside="edge") * e
                     for c in range(3)])


def lookup_bilinear(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear samples ``(N, C)`` of an equirectangular ``image (H, W, C)`` along unit ``directions (N, 3)``.

    Pixel centres at ``+0.5`` (column 0 at longitude -180°, row 0 at latitude +90°); wraps in
    longitude, holds the edge rows towards the poles.  Coordinates are computed in float64.
    """
    h, w, c = image.shape
    d = np.asarray(directions, dtype=np.float64)
    lon = np.arctan2(-d[:, 0], d[:, 2])
    lat = np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))
    col = (lon + math.pi) * (w / (2.0 * math.pi)) - 0.5
    row = (0.5 * math.pi - lat) * (h / math.pi) - 0.5
    c0 = np.floor(col)
    r0 = np.floor(row)
    fc = (col - c0).astype(np.float32)[:, None]
    fr = (row - r0).astype(np.float32)[:, None]
    c0 = c0.astype(np.int64) % w
    c1 = (c0 + 1) % w
    r1 = np.clip(r0 + 1, 0, h - 1).astype(np.int64)
    r0 = np.clip(r0, 0, h - 1).astype(np.int64)
    flat = image.reshape(-1, c)
    top = flat[r0 * w + c0] * (1.0 - fc) + flat[r0 * w + c1] * fc
    bottom = flat[r1 * w + c0] * (1.0 - fc) + flat[r1 * w + c1] * fc
    return top * (1.0 - fr) + bottom * fr


class PanoramaScene(Scene):
    """An HDR RGB equirectangular panorama at infinity, up-sampled to spectra (see the module docstring).

    Parameters
    ----------
    path_or_array
        A ``.hdr`` / ``.exr`` file or an array ``(H, W, 3)`` of linear sRGB values, ``W = 2H``.
    wavelength_nm
        Spectral grid within 380-780 nm (default 400-700 nm / 5 nm).
    scale
        Luminance in cd/m² of a pixel value of Rec. 709 luminance 1.
    """

    kind = "panorama"

    def __init__(self, path_or_array, wavelength_nm=None, scale: float = 1.0):
        super().__init__(DEFAULT_WAVELENGTH_NM if wavelength_nm is None else wavelength_nm)
        if not (np.isfinite(scale) and scale > 0):
            raise ConfigurationError(f"scale must be a positive number, got {scale}")
        if isinstance(path_or_array, (str, Path)):
            self.source = str(path_or_array)
            self.rgb = read_panorama(path_or_array)
        else:
            self.source = "<array>"
            self.rgb = check_panorama(path_or_array)
        self.scale = float(scale)
        self.emission_basis = mallett2019_emission_basis(self.wavelength_nm) * self.scale
        self._basis32 = self.emission_basis.astype(np.float32)
        self._bands = BandProjectionCache()

    def rgb_at(self, directions) -> np.ndarray:
        """Bilinearly interpolated linear RGB ``(N, 3)`` float32 of the panorama along ``directions``."""
        d, lead = as_directions(directions)
        return lookup_bilinear(self.rgb, d).reshape(*lead, 3)

    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """``Σ_c rgb_c E_c(λ)`` ``(N, n)`` float32; ``origin_m`` is ignored (the panorama is at infinity)."""
        return self._render(directions, origin_m, self._basis32)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """``rgb @ (E @ sensitivity.T)``: the three basis spectra projected on the bands once."""
        s = self.check_sensitivity(sensitivity)
        table = self._bands.get(s, lambda s: (self.emission_basis @ s.T).astype(np.float32))
        return self._render(directions, origin_m, table)

    def _render(self, directions, origin_m, table: np.ndarray) -> np.ndarray:
        as_origin(origin_m)
        d, lead = as_directions(directions)
        out = np.empty((d.shape[0], table.shape[1]), dtype=np.float32)
        for b0 in range(0, d.shape[0], RAY_BLOCK):
            b1 = min(d.shape[0], b0 + RAY_BLOCK)
            out[b0:b1] = lookup_bilinear(self.rgb, d[b0:b1]) @ table
        return out.reshape(*lead, table.shape[1])

    def describe(self) -> dict:
        """Kind, source, size, scale, up-sampling method and the panorama's luminance range."""
        y = self.rgb @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
        positive = y[y > 0]
        return {
            "kind": self.kind,
            "parameters": {"source": self.source, "scale": self.scale},
            "size_px": [int(self.rgb.shape[1]), int(self.rgb.shape[0])],
            "wavelength_nm": {"start": float(self.wavelength_nm[0]), "stop": float(self.wavelength_nm[-1]),
                              "count": int(self.wavelength_nm.size)},
            "radiance_units": self.radiance_units,
            "upsampling": "Mallett & Yuksel 2019 sRGB spectral primary decomposition, lit by D65",
            "luminance_cd_m2": {"max": float(y.max()) * self.scale,
                                "min_positive": float(positive.min()) * self.scale if positive.size else 0.0,
                                "mean": float(y.mean()) * self.scale},
            "at_infinity": True,
        }
