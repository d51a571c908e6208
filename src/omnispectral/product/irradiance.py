"""Irradiance on a plane from an HDR spectral panorama, split into the sun's part and the sky's (beyond the paper).

A panorama pixel holds the mean radiance ``L`` (DN/s per band) over its solid angle.  The irradiance of
a plane with unit normal ``n`` is

    ``E(n) = ∫_{S²} L(ω) max(0, ω · n) dω``

(e.g. Pharr, Jakob & Humphreys, *Physically Based Rendering*, 4th ed., Sec. 4.1.1).  On the
equirectangular grid (docs/product.md: row ``j`` spans latitudes ``[φ_lo, φ_hi]``, column ``k``
longitudes ``[λ_a, λ_b]``) it is evaluated as

    ``E(n) ≈ Σ_jk L_jk max(0, m_jk · n)``,   ``m_jk = ∫_{pixel jk} ω dω``

with ``ω = (−cos φ sin λ, sin φ, cos φ cos λ)`` (world +Y up, :func:`~omnispectral.imaging.geometry.lonlat_to_ray`)
and each pixel's first moment in closed form:

    ``m_x = C_j (cos λ_b − cos λ_a)``,  ``m_y = Δλ (sin² φ_hi − sin² φ_lo) / 2``,  ``m_z = C_j (sin λ_b − sin λ_a)``,
    ``C_j = ∫ cos² φ dφ = (φ_hi − φ_lo)/2 + (sin 2φ_hi − sin 2φ_lo)/4``.

``m_jk · n / Ω_jk`` is the pixel's exact mean cosine (``Ω_jk`` from
:func:`~omnispectral.imaging.sundisk.equirect_pixel_solid_angle_sr`), so a pixel lying wholly on the lit side
of the plane contributes exactly ``L_jk ∫ ω · n dω``; only pixels that the plane's horizon cuts are
approximated (``max(0, ∫ ω·n) ≤ ∫ max(0, ω·n)``, an error of second order in the pixel size along that one
great circle; none for a horizontal plane on an even number of rows, whose horizon is a row border).
Uniform radiance ``L`` over the upper hemisphere gives ``π L`` on a horizontal plane to rounding.

Units: the panorama's radiance is DN/s per band (per sr, up to the camera's absolute calibration), so
band irradiance is in **DN/s·sr** (``*_dn_s_sr``) and a spectral irradiance in DN/s·sr per unit of the
rig's system matrix (the unit of the estimator's spectra times sr).  Pixels without data (NaN) count as 0;
the result says which share of the plane's projected solid angle (``π``) had data.

Sun and sky (:func:`sun_sky_irradiance`).  When the product recovered the saturated sun
(:mod:`omnispectral.product.sun`: the record ``omnispectral.sun`` of the store's attributes, ``sun.json``),
the painted pixels hold the sky background plus the disk's exact coverage × the sun's radiance, so the
panorama's integral already contains the sun.  The split is

    ``E_sun(n) = E_⊥,sun max(0, s · n)``,   ``E_sky(n) = E(n) − E_painted(n)``,
    ``E_painted(n) = Σ_painted (L_jk − L_background) max(0, m_jk · n)``

with ``E_⊥,sun`` the record's ``band_irradiance`` (normal incidence), ``s`` the sun's direction and the sums
over the record's painted pixels (``pixels``).  ``E_painted ≈ E_sun``: they differ by the sub-pixel
position of the disk (a pixel's mean cosine is not that of the part the disk covers: up to half a pixel
× ``cot h`` relative, 0.5 % for a 0.35° pixel at elevation 30°), and subtracting the painted part rather
than ``E_sun`` keeps that error out of the sky, where it would weigh ~4× more (the sun carries ~80 % of a
clear day's horizontal irradiance).  The total is then ``E_sun + E_sky``; the panorama's own integral
``E(n)`` is reported beside it (``panorama``).  Without the painted pixels, ``E_sky = E − E_sun``.  The
sun's spectral irradiance is ``L_sun,λ Ω_sun max(0, s · n)`` from the record's ``spectral_radiance``; the
sky's is the product's Wiener estimate (paper Eq. (7), mixture prior; :mod:`omnispectral.product.spectra`)
of the sky's band irradiance vector — the estimator is exposure-equivariant, so it applies to an integral
of radiance as to a pixel.  Correlated colour temperatures by :func:`~omnispectral.spectral.colour.spectrum_cct_K`
(CIE 1931 2° observer; CIE 015:2018 Sec. 9.5 defines CCT; Ohno 2013's method in CIE 1960 uv).
Without a recovered sun the sun's part is zero, the sky's holds whatever the saturated disk's pixels
hold (a lower bound), and the result carries the product's note saying so.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import lonlat_to_ray
from omnispectral.imaging.sundisk import equirect_pixel_solid_angle_sr
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.estimator import estimator_from_params
from omnispectral.product.layout import open_product, product_paths
from omnispectral.product.sun import SUN_FILE, sun_lower_bound_note
from omnispectral.spectral.colour import spectrum_cct_K
from omnispectral.spectral.curves import resample_spectra

__all__ = ["BLOCK_PIXELS", "HORIZONTAL_NORMAL", "IRRADIANCE_UNITS", "SPECTRAL_IRRADIANCE_UNITS", "PlaneIrradiance",
           "column_moments", "cosine_weights", "irradiance", "painted_sun_irradiance", "row_moments", "safe_cct_K",
           "sun_sky_irradiance", "unit_normal"]

#: The normal of a horizontal plane facing up (world +Y).
HORIZONTAL_NORMAL = (0.0, 1.0, 0.0)
#: Float64 work per block of rows: about this many pixels (the bands are read in the store's chunk rows).
BLOCK_PIXELS = 2_000_000
#: Units of band irradiance (the panorama's DN/s radiance integrated over solid angle).
IRRADIANCE_UNITS = "DN/s·sr (band irradiance: the panorama's DN/s radiance × sr)"
SPECTRAL_IRRADIANCE_UNITS = "DN/s·sr per unit of the system matrix (spectral irradiance, relative)"


@dataclass(frozen=True)
class PlaneIrradiance:
    """Band irradiance of a plane (module docstring).

    Attributes
    ----------
    normal : tuple of float
        Unit normal of the plane (world frame, +Y up).
    band_irradiance_dn_s_sr : ndarray (m,)
        ``E_b = Σ L_b max(0, m · n)`` per band, DN/s·sr; NaN pixels count as 0.
    covered_fraction : float
        Share of the plane's projected solid angle (``Σ max(0, m · n)`` over all pixels, ``≈ π``) held by
        pixels whose bands are all finite: 1 for a complete panorama.
    covered_solid_angle_fraction : float
        Share of the whole sphere's solid angle (``4π``) held by such pixels.
    """

    normal: tuple[float, float, float]
    band_irradiance_dn_s_sr: np.ndarray
    covered_fraction: float
    covered_solid_angle_fraction: float

    def to_dict(self) -> dict:
        """JSON-able form (``band_irradiance`` in DN/s·sr)."""
        return {"normal": list(self.normal), "band_irradiance": self.band_irradiance_dn_s_sr.tolist(),
                "covered_fraction": self.covered_fraction,
                "covered_solid_angle_fraction": self.covered_solid_angle_fraction, "units": IRRADIANCE_UNITS}


# ------------------------------------------------------------------------------------- geometry
def unit_normal(normal) -> np.ndarray:
    """``normal`` as a unit vector ``(3,)``; a zero or non-finite vector is a :class:`ConfigurationError`."""
    n = np.asarray(normal, dtype=np.float64).reshape(-1)
    norm = float(np.linalg.norm(n)) if n.size == 3 else float("nan")
    if not (np.isfinite(norm) and norm > 0):
        raise ConfigurationError(f"a plane's normal must be a finite non-zero 3-vector, got {normal!r}")
    return n / norm


def column_moments(width: int) -> tuple[np.ndarray, np.ndarray]:
    """``(∫ −sin λ dλ, ∫ cos λ dλ)`` over each column ``[λ_a, λ_b]`` of an equirect grid ``width`` wide."""
    edges = np.radians(-180.0 + np.arange(width + 1) * (360.0 / width))
    return np.cos(edges[1:]) - np.cos(edges[:-1]), np.sin(edges[1:]) - np.sin(edges[:-1])


def row_moments(rows: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """``(C_j, m_y,j)`` of rows ``rows``: ``∫ cos² φ dφ`` and the pixels' ``∫ sin φ dω`` (module docstring)."""
    j = np.asarray(rows, dtype=np.float64)
    hi = np.radians(90.0 - j * (180.0 / height))
    lo = np.radians(90.0 - (j + 1.0) * (180.0 / height))
    c = 0.5 * (hi - lo) + 0.25 * (np.sin(2.0 * hi) - np.sin(2.0 * lo))
    m_y = (math.pi / width) * (np.sin(hi) ** 2 - np.sin(lo) ** 2)
    return c, m_y


def cosine_weights(rows: np.ndarray, height: int, width: int, normal) -> np.ndarray:
    """``max(0, m_jk · n)`` (sr) of every pixel of rows ``rows``, ``(len(rows), width)`` (module docstring)."""
    n = unit_normal(normal)
    sx, sz = column_moments(width)
    c, m_y = row_moments(rows, height, width)
    w = c[:, None] * (n[0] * sx + n[2] * sz)[None, :] + (n[1] * m_y)[:, None]
    return np.maximum(w, 0.0)


# ------------------------------------------------------------------------------------ irradiance
def irradiance(bands_or_store, normal=HORIZONTAL_NORMAL, level: int = 0,
               block_rows: int | None = None) -> PlaneIrradiance:
    """Band irradiance ``E_b(n) = ∫ L_b(ω) max(0, ω · n) dω`` of an equirectangular panorama (module docstring).

    Parameters
    ----------
    bands_or_store : ndarray (H, W, m) or PanoramaStore
        Radiance in DN/s per band on the product's grid (row 0 at latitude +90°, column 0 at longitude −180°),
        or a panorama store, read level ``level`` in blocks of rows (never whole).  A memory-mapped array
        (``np.load(..., mmap_mode="r")``) is read block by block as well.
    normal : array_like (3,)
        The plane's normal in the world frame (+Y up; :data:`HORIZONTAL_NORMAL` by default).
    level : int
        Pyramid level of a store (level 0 holds the painted sun; higher levels are box averages).
    block_rows : int, optional
        Rows per block; default the store's tile (whole chunks), or about :data:`BLOCK_PIXELS` pixels.

    Returns
    -------
    PlaneIrradiance
        Band irradiance in DN/s·sr and the covered fractions.

    Notes
    -----
    ``E_b = Σ_jk L_b,jk max(0, m_jk · n)`` with the pixels' exact first moments ``m_jk = ∫ ω dω``; the sum
    runs in float64.  NaN pixels count as 0.
    """
    n = unit_normal(normal)
    source, height, width, n_bands = _source(bands_or_store, level)
    step = int(block_rows) if block_rows else _default_block_rows(bands_or_store, width)
    if step < 1:
        raise ConfigurationError(f"block_rows must be >= 1, got {block_rows!r}")
    total = np.zeros(n_bands)
    lit_sr = covered_lit_sr = covered_sr = 0.0
    for r0 in range(0, height, step):
        rows = np.arange(r0, min(height, r0 + step))
        block = source(slice(rows[0], rows[-1] + 1))
        weight = cosine_weights(rows, height, width, n)
        finite = np.isfinite(block)
        covered = finite.all(axis=2)
        for b in range(n_bands):
            total[b] += float(np.sum(weight * np.where(finite[..., b], block[..., b], 0.0), dtype=np.float64))
        lit_sr += float(weight.sum())
        covered_lit_sr += float(weight[covered].sum())
        covered_sr += float((covered.sum(axis=1) * equirect_pixel_solid_angle_sr(rows, width, height)).sum())
    return PlaneIrradiance(tuple(float(v) for v in n), total, covered_lit_sr / lit_sr if lit_sr > 0 else 0.0,
                           covered_sr / (4.0 * math.pi))


def _source(bands_or_store, level: int):
    """``(read(rows) → (h, W, m) float array, H, W, m)`` of an array or a store."""
    if isinstance(bands_or_store, PanoramaStore):
        store = bands_or_store
        if not 0 <= level < len(store.shapes):
            raise ConfigurationError(f"level {level} does not exist (0-{len(store.shapes) - 1})")
        h, w = store.shapes[level]
        return (lambda rows: store.read(level, rows)), h, w, store.n_bands
    arr = bands_or_store
    if getattr(arr, "ndim", None) != 3:
        raise ConfigurationError(f"bands must be an (H, W, bands) array or a PanoramaStore, got "
                                 f"{type(arr).__name__} of shape {getattr(arr, 'shape', None)}")
    h, w, m = arr.shape
    if w != 2 * h:
        raise ConfigurationError(f"an equirectangular panorama is twice as wide as high, got {w} × {h}")
    return (lambda rows: np.asarray(arr[rows])), h, w, m


def _default_block_rows(bands_or_store, width: int) -> int:
    """The store's tile (whole chunks per read) or about :data:`BLOCK_PIXELS` pixels of an array."""
    if isinstance(bands_or_store, PanoramaStore):
        return int(bands_or_store.tile)
    return max(1, BLOCK_PIXELS // max(width, 1))


# ------------------------------------------------------------------------------------ sun and sky
def sun_sky_irradiance(store_or_product, normal=HORIZONTAL_NORMAL, *, estimator=None, bands=None,
                       total: PlaneIrradiance | None = None) -> dict:
    """Irradiance of a plane split into the recovered sun's part and the sky's, with spectra and CCTs.

    Parameters
    ----------
    store_or_product : PanoramaStore, or path of a product directory or of its ``panorama.zarr``
        The sun's record is the store's ``omnispectral.sun`` attribute (else the product's ``sun.json``).
    normal : array_like (3,)
        The plane's normal (world frame, +Y up).
    estimator : WienerEstimator, optional
        The product's estimator; default re-fitted from the store's (or ``product.json``'s) parameters.
    bands : ndarray (H, W, m), optional
        Level 0 already in memory (saves re-reading the store).
    total : PlaneIrradiance, optional
        :func:`irradiance` of level 0 for ``normal`` already computed.

    Returns
    -------
    dict
        ``normal``, ``band_names``, ``units``, ``spectral_units``, ``wavelength_nm``, ``sun_method``,
        ``sun_recovered`` (and ``note`` when not recovered); ``panorama`` (:meth:`PlaneIrradiance.to_dict` of
        the panorama's integral ``E``); ``total``, ``sun`` and ``sky`` each with ``band_irradiance``
        (DN/s·sr), ``spectral_irradiance`` and ``cct_K`` (``None`` when undefined), ``sun`` and ``sky``
        also ``spectral_irradiance_std``; ``sun`` also ``cos_incidence`` and ``painted_band_irradiance``
        (``E_painted``, a check on the painting); ``sun_fraction`` per band (``E_sun / E_total``).

    Notes
    -----
    ``E_sun = E_⊥,sun max(0, s · n)``, ``E_sky = E − E_painted``, ``E_total = E_sun + E_sky``; spectral:
    ``E_sun,λ = L_sun,λ Ω_sun max(0, s · n)``, ``E_sky,λ`` = Wiener estimate of ``E_sky`` (module docstring).
    """
    store, est, sun = _open(store_or_product, estimator)
    n = unit_normal(normal)
    tot = total or irradiance(store if bands is None else bands, n)
    wl = np.asarray(est.wavelength_nm, np.float64)
    names = list(sun.get("band_names") or store.attrs().get("omnispectral", {}).get("bands") or [])
    sun_part = _sun_part(store, sun, n, wl, tot.band_irradiance_dn_s_sr.size)
    painted = sun_part["painted_band_irradiance"]
    sky_band = tot.band_irradiance_dn_s_sr - np.asarray(sun_part["band_irradiance"] if painted is None else painted)
    sky_part = {"band_irradiance": sky_band.tolist(), **_estimated_spectrum(est, sky_band)}
    total_band = sky_band + np.asarray(sun_part["band_irradiance"])
    total_spd = np.asarray(sky_part["spectral_irradiance"], float) + np.asarray(sun_part["spectral_irradiance"])
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.asarray(sun_part["band_irradiance"]) / total_band
    out = {"normal": n.tolist(), "band_names": names, "units": IRRADIANCE_UNITS,
           "spectral_units": SPECTRAL_IRRADIANCE_UNITS, "wavelength_nm": wl.tolist(),
           "sun_method": sun.get("method", "none"), "sun_recovered": bool(sun.get("recovered", False)),
           "panorama": tot.to_dict(),
           "total": {"band_irradiance": total_band.tolist(), "spectral_irradiance": total_spd.tolist(),
                     "cct_K": safe_cct_K(wl, total_spd)},
           "sun": sun_part, "sky": sky_part, "sun_fraction": [_finite_or_none(v) for v in fraction]}
    if not out["sun_recovered"]:
        out["note"] = sun.get("note") or sun_lower_bound_note()
    return out


def _open(store_or_product, estimator) -> tuple[PanoramaStore, object, dict]:
    """``(store, estimator or None, sun record)`` of a store, a product directory or a panorama path."""
    sun_file = None
    if isinstance(store_or_product, PanoramaStore):
        store = store_or_product
    elif (Path(store_or_product) / "product.json").is_file():
        _, store, est = open_product(store_or_product)
        sun_file = product_paths(store_or_product)["root"] / SUN_FILE
        estimator = est if estimator is None else estimator
    else:
        store = PanoramaStore.open(store_or_product)
        sun_file = Path(store_or_product).parent / SUN_FILE
    meta = store.attrs().get("omnispectral", {})
    sun = meta.get("sun")
    if sun is None and sun_file is not None and sun_file.is_file():
        sun = json.loads(sun_file.read_text(encoding="utf-8"))
    if estimator is None:
        params = (meta.get("estimator") or {}).get("params")
        if params is None:
            raise ConfigurationError(f"{store.path}: the panorama carries no estimator; pass one")
        estimator, _ = estimator_from_params(params)
    return store, estimator, sun or {"method": "none", "recovered": False, "note": sun_lower_bound_note()}


def _sun_part(store: PanoramaStore, sun: dict, n: np.ndarray, wl: np.ndarray, n_bands: int) -> dict:
    """The sun's band and spectral irradiance on the plane (zero without a recovered sun)."""
    zero = {"band_irradiance": [0.0] * n_bands, "cos_incidence": None, "painted_band_irradiance": None,
            "spectral_irradiance": [0.0] * wl.size, "spectral_irradiance_std": [0.0] * wl.size, "cct_K": None}
    if not sun.get("recovered"):
        return zero
    cos_i = max(0.0, float(lonlat_to_ray(sun["lon_deg"], sun["lat_deg"]) @ n))
    band = np.asarray(sun["band_irradiance"], np.float64) * cos_i
    sun_wl = np.asarray(sun["wavelength_nm"], np.float64)
    scale = float(sun["solid_angle_sr"]) * cos_i
    radiance = np.asarray(sun["spectral_radiance"], np.float64)
    spd = resample_spectra(radiance, sun_wl, wl, outside="edge") * scale
    radiance_std = np.asarray(sun.get("spectral_radiance_std", np.zeros_like(radiance)))
    std = resample_spectra(radiance_std, sun_wl, wl, outside="edge") * scale
    painted = painted_sun_irradiance(store, sun["pixels"], n) if sun.get("pixels") else None
    return {"band_irradiance": band.tolist(), "cos_incidence": cos_i,
            "painted_band_irradiance": None if painted is None else painted.tolist(),
            "spectral_irradiance": spd.tolist(), "spectral_irradiance_std": std.tolist(),
            "cct_K": safe_cct_K(sun_wl, radiance)}


def painted_sun_irradiance(store: PanoramaStore, pixels: dict, normal) -> np.ndarray:
    """``Σ_mask (L_jk − background) max(0, m_jk · n)`` over the painted window of level 0 (DN/s·sr per band).

    ``pixels`` is the record's ``pixels`` (``row0``, ``col0``, ``rows``, ``cols``, ``mask``, ``background``); the
    window may wrap around longitude ±180°.
    """
    h, w = store.shapes[0]
    r0, c0 = int(pixels["row0"]), int(pixels["col0"])
    rows = np.arange(r0, r0 + int(pixels["rows"]))
    cols = (c0 + np.arange(int(pixels["cols"]))) % w
    window = store.read(0, slice(rows[0], rows[-1] + 1))[:, cols].astype(np.float64)
    mask = np.asarray(pixels["mask"], bool)
    excess = np.where(mask[..., None], window - np.asarray(pixels["background"], np.float64), 0.0)
    weight = cosine_weights(rows, h, w, normal)[:, cols]
    return np.nansum(excess * weight[..., None], axis=(0, 1))


def _estimated_spectrum(estimator, band_irradiance: np.ndarray) -> dict:
    """Wiener estimate (and posterior std) of a band irradiance vector, with its CCT."""
    rho = np.asarray(band_irradiance, np.float64)[None]
    if not (np.isfinite(rho).all() and rho.sum() > 0):
        nan = [None] * len(estimator.wavelength_nm)
        return {"spectral_irradiance": nan, "spectral_irradiance_std": nan, "cct_K": None}
    spd = np.asarray(estimator.estimate(rho, dtype=np.float64)[0], np.float64)
    std = np.asarray(estimator.posterior_std(rho, dtype=np.float64)[0], np.float64)
    return {"spectral_irradiance": spd.tolist(), "spectral_irradiance_std": std.tolist(),
            "cct_K": safe_cct_K(estimator.wavelength_nm, spd)}


def safe_cct_K(wavelength_nm, spectrum) -> float | None:
    """:func:`~omnispectral.spectral.colour.spectrum_cct_K` (CIE 015:2018; Ohno 2013), ``None`` where undefined
    (no light, non-finite values, or a chromaticity the method cannot place)."""
    s = np.asarray([np.nan if v is None else v for v in np.ravel(spectrum)], np.float64)
    if s.size == 0 or not np.isfinite(s).all() or not s.sum() > 0:
        return None
    try:
        cct = spectrum_cct_K(wavelength_nm, s)
    except (ValueError, ZeroDivisionError, FloatingPointError):
        return None
    return cct if np.isfinite(cct) and cct > 0 else None


def _finite_or_none(v) -> float | None:
    v = float(v)
    return v if np.isfinite(v) else None
