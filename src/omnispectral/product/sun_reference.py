"""The saturated sun measured on a diffuse reference lit by it, for captures without an attenuated bracket.

A white or grey Lambertian target of known reflectance ``ρ`` lies in the scene in the sun; the user says
where (its direction from the head, its normal and its reflectance: :class:`SunReference`).  Its band
radiance in the panorama is

    ``L_b = ρ_b^sun E_⊥,b cos θ / π + ρ_b^rest E_rest,b / π``

with ``E_⊥`` the sun's band irradiance at normal incidence (what the ``nd-bracket`` method of
:mod:`omnispectral.product.sun` measures), ``θ`` the angle between the sun's direction and the target's
normal, and ``E_rest`` the irradiance of the target's plane from everything else the panorama holds (sky,
buildings, ground): :func:`omnispectral.product.irradiance.irradiance` of the panorama minus the clipped
sun's pixels, which are replaced by the sky around them.  Hence

    ``E_⊥,b = (π L_b − ρ_b^rest E_rest,b) / (ρ_b^sun cos θ)``.

Where things come from:

- **Direction** ``s``: the centroid of the panorama's clipped group
  (:func:`omnispectral.product.sun.clipped_sun_direction`); its accuracy is a fraction of a panorama pixel.
- **Target radiance** ``L``: the median of every band over the pixels within ``radius_deg`` of the target's
  direction (level 0); its uncertainty from the pixels' spread, ``1.2533 · 1.4826 MAD / √n`` (the median's
  standard error for Gaussian noise; pixels counted as independent, which they are on the rig's native grid).
- **Sky part** ``E_rest``: ``E(n) − Σ_region (L_jk − L_bg) max(0, m_jk · n)`` over the clipped group dilated by
  ``margin_px`` (the mosaic's resampling spreads the clipped disk by a pixel or two), ``L_bg`` the median of a
  ring of ``ring_px`` pixels around it.  Its uncertainty: the ring's spread times the region's weight (the
  sky under the disk is not the ring's median), the share of the plane's hemisphere without data
  (``(1 − covered_fraction) E_rest``), and a relative term ``sky_rel_std`` (default 2 %) for what one
  panorama seen from the head cannot say about the target's own surroundings (near objects occlude its sky
  differently, light between surfaces).
- **Reflectance** ``ρ_b``: a number is flat (``ρ_b = ρ``).  A curve ``ρ(λ)`` gives each band an effective
  reflectance under the light's spectrum, ``ρ_b = R_b (ρ ⊙ S) / R_b S`` (``R`` the rig's system matrix,
  paper Eq. (6)), which needs the spectra: the first pass uses a flat ``S``, the next ones the sun's
  spectrum fitted to ``E_⊥`` (and the sky's to ``E_rest``) by :func:`omnispectral.product.sun.fit_spectrum`
  in the daylight basis :func:`omnispectral.product.sun.daylight_basis` (two passes by default).
- **Spectrum**: the same fit to the final ``E_⊥`` with its variances; ``band_irradiance`` is the measured
  ``E_⊥`` itself (all bands are measured, unfiltered), its ``std`` propagated from ``L``, ``E_rest`` and the
  direction (``δ cos θ = sin θ δθ``, ``δθ`` half a panorama pixel).

Refusals (``recovered: False`` with a ``note``): no clipped sun, the target not covered by the panorama, the
sun behind the target or grazing it (``cos θ < MIN_COS_INCIDENCE``), or a sun term
``Σ_b (L_b − ρ_b E_rest,b / π)`` smaller than ``MIN_SUN_SNR`` times its uncertainty (the target lies in shadow,
or the sky alone explains its radiance).

Units: the panorama's (DN/s per band; irradiance in DN/s·sr; spectra per unit of the system matrix), as in
:mod:`omnispectral.product.sun`.  The sun's angular diameter is the mean 0.533°.

Command-line value (:func:`parse_sun_reference`)::

    LON,LAT[,RADIUS_DEG][,normal=AZ/EL|X/Y/Z][,reflectance=0.95|FILE.csv|SET:SAMPLE][,radius=DEG]

``LON,LAT``: the target's centre as seen in the panorama (degrees, the panorama's longitude and latitude);
``RADIUS_DEG`` / ``radius=``: the patch averaged (default 1°; keep it inside the target);
``normal=AZ/EL``: the direction the target faces as a longitude and elevation in degrees (``0/90``, facing up,
is the default: a horizontal target), or a world vector ``X/Y/Z`` (+Y up); ``reflectance=``: a number in
(0, 1] (flat, default 0.95), a reflectance CSV holding one curve
(:func:`omnispectral.spectral.curves.read_spectral_csv`; the path must not contain a comma), or
``SET:SAMPLE`` of a built-in reflectance set (:func:`omnispectral.spectral.library.load_reflectances`,
e.g. ``colorchecker:white 9.5 (.05 D)``).
Examples: ``-20,-45`` · ``-20,-45,1.5,reflectance=0.99`` · ``35,-10,normal=215/0,reflectance=grey.csv``.
(On a command line, a negative longitude needs ``--option=-20,-45``.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_equirect_pixel, lonlat_to_ray
from omnispectral.product.irradiance import cosine_weights, irradiance, unit_normal
from omnispectral.product.saturation import clipped_mask, saturation_level_dn_s
from omnispectral.product.sun import (
    clipped_sun_direction,
    daylight_basis,
    fit_spectrum,
    sun_radiance_fields,
)
from omnispectral.spectral.curves import read_spectral_csv, resample_spectra
from omnispectral.spectral.library import load_reflectances

__all__ = ["DEFAULT_NORMAL", "DEFAULT_RADIUS_DEG", "DEFAULT_REFLECTANCE", "MARGIN_PX", "METHOD", "MIN_COS_INCIDENCE",
           "MIN_SUN_SNR", "N_PASSES", "PATCH_SPREAD_WARN", "RING_PX", "SKY_REL_STD", "SunReference",
           "effective_reflectance", "load_reflectance_spec", "parse_sun_reference", "recover_sun_reference",
           "sun_free_irradiance", "target_radiance"]

#: The method's name in the sun's record.
METHOD = "diffuse-reference"
#: Defaults of :class:`SunReference`: a horizontal target facing up, flat reflectance, a 1° patch.
DEFAULT_NORMAL = (0.0, 1.0, 0.0)
DEFAULT_REFLECTANCE = 0.95
DEFAULT_RADIUS_DEG = 1.0
#: Refuse when the sun meets the target's plane at a cosine below this (behind it, or grazing).
MIN_COS_INCIDENCE = 0.1
#: Refuse when the sun's share of the target's radiance is below this many times its uncertainty.
MIN_SUN_SNR = 2.0
#: Relative uncertainty of the panorama's irradiance on the target's plane (module docstring).
SKY_REL_STD = 0.02
#: Pixels added around the clipped group (replaced by the sky) and the ring giving that sky.
MARGIN_PX = 3
RING_PX = 3
#: Passes of the effective-reflectance iteration (the first with flat spectra).
N_PASSES = 2
#: Relative spread (1.4826 MAD / median) of the target's patch above which the record warns.
PATCH_SPREAD_WARN = 0.05


# ------------------------------------------------------------------------------------- the target
@dataclass(frozen=True)
class SunReference:
    """A diffuse reference target lit by the sun (module docstring).

    Attributes
    ----------
    lon_deg, lat_deg : float
        Its centre's direction in the panorama (degrees).
    normal : tuple of float
        Unit normal of its surface in the world frame (+Y up; default facing up).
    reflectance : float, str or (wavelength_nm, values)
        A flat reflectance in (0, 1], a reflectance CSV (one curve), ``SET:SAMPLE`` of a built-in set, or a curve.
    radius_deg : float
        Radius of the patch of the panorama averaged on it (degrees).
    """

    lon_deg: float
    lat_deg: float
    normal: tuple[float, float, float] = DEFAULT_NORMAL
    reflectance: float | str | tuple = DEFAULT_REFLECTANCE
    radius_deg: float = DEFAULT_RADIUS_DEG
    _curve_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False, hash=False)

    def __post_init__(self):
        if not (math.isfinite(self.lon_deg) and math.isfinite(self.lat_deg) and abs(self.lat_deg) <= 90):
            raise ConfigurationError(f"a sun reference needs a finite longitude and |latitude| <= 90, got "
                                     f"{self.lon_deg}, {self.lat_deg}")
        if not (math.isfinite(self.radius_deg) and self.radius_deg > 0):
            raise ConfigurationError(f"a sun reference's radius must be > 0 degrees, got {self.radius_deg}")
        object.__setattr__(self, "normal", tuple(float(v) for v in unit_normal(self.normal)))
        if not isinstance(self.reflectance, (str, tuple)):
            value = float(self.reflectance)
            if not 0 < value <= 1:
                raise ConfigurationError(f"a sun reference's reflectance must be in (0, 1], got {value}")
            object.__setattr__(self, "reflectance", value)

    @property
    def ray(self) -> np.ndarray:
        """Unit world direction of the target's centre."""
        return lonlat_to_ray(self.lon_deg, self.lat_deg)

    @property
    def flat(self) -> bool:
        return isinstance(self.reflectance, float)

    def reflectance_on(self, wavelength_nm) -> np.ndarray:
        """The reflectance sampled on ``wavelength_nm`` ``(n,)`` (curves resampled linearly; no extrapolation)."""
        wl = np.asarray(wavelength_nm, np.float64)
        if self.flat:
            return np.full(wl.size, float(self.reflectance))
        key = tuple(np.round(wl, 9))
        if key not in self._curve_cache:
            if isinstance(self.reflectance, tuple):
                src_wl, values = (np.asarray(a, np.float64) for a in self.reflectance)
                if wl.min() < src_wl.min() - 1e-9 or wl.max() > src_wl.max() + 1e-9:
                    raise ConfigurationError(f"the reference's reflectance covers {src_wl.min():g}-{src_wl.max():g} "
                                             f"nm, not {wl.min():g}-{wl.max():g} nm")
                curve = resample_spectra(values, src_wl, wl, outside="edge")
            else:
                curve = load_reflectance_spec(self.reflectance).resample(wl).values[0]
            if not (np.all(np.isfinite(curve)) and curve.max() > 0 and curve.min() >= 0 and curve.max() <= 1.5):
                raise ConfigurationError(f"the reference's reflectance {self.reflectance!r} is not a reflectance "
                                         "(values in [0, 1])")
            self._curve_cache[key] = np.asarray(curve, np.float64)
        return self._curve_cache[key]

    def to_dict(self) -> dict:
        """JSON-able form (for the sun's record)."""
        refl = self.reflectance
        if isinstance(refl, tuple):
            refl = {"wavelength_nm": np.asarray(refl[0], float).tolist(), "values": np.asarray(refl[1], float).tolist()}
        return {"lon_deg": self.lon_deg, "lat_deg": self.lat_deg, "normal": list(self.normal),
                "reflectance": refl, "radius_deg": self.radius_deg}

    @classmethod
    def from_dict(cls, d: dict) -> SunReference:
        """From ``lon_deg``, ``lat_deg`` and optional ``normal``, ``reflectance``, ``radius_deg`` (e.g. a scene's
        description of its reference, or :meth:`to_dict`)."""
        refl = d.get("reflectance", DEFAULT_REFLECTANCE)
        if isinstance(refl, dict):
            refl = (tuple(refl["wavelength_nm"]), tuple(refl["values"]))
        return cls(float(d["lon_deg"]), float(d["lat_deg"]), tuple(d.get("normal", DEFAULT_NORMAL)), refl,
                   float(d.get("radius_deg", DEFAULT_RADIUS_DEG)))


def load_reflectance_spec(spec: str):
    """One reflectance curve (a :class:`~omnispectral.spectral.curves.SpectralSet` of one row) from a CSV path or
    ``SET:SAMPLE`` of a built-in set."""
    text = spec.strip()
    if text.lower().endswith(".csv") or "/" in text or "\\" in text:
        curves = read_spectral_csv(text, "reflectance")
        if len(curves) != 1:
            raise ConfigurationError(f"{text}: a reference's reflectance file must hold one curve, it holds "
                                     f"{len(curves)} ({', '.join(curves.names)})")
        return curves
    if ":" in text:
        set_name, sample = text.split(":", 1)
        return load_reflectances(set_name.strip()).select([sample.strip()])
    raise ConfigurationError(f"reflectance {spec!r}: expected a number in (0, 1], a FILE.csv or SET:SAMPLE")


def _parse_normal(text: str) -> tuple[float, float, float]:
    try:
        parts = [float(x) for x in text.split("/")]
    except ValueError:
        parts = []
    if len(parts) == 2:
        if abs(parts[1]) > 90:
            raise ConfigurationError(f"normal={text}: the elevation must be within ±90°")
        return tuple(float(v) for v in lonlat_to_ray(parts[0], parts[1]))
    if len(parts) == 3:
        return tuple(parts)
    raise ConfigurationError(f"normal={text!r}: expected AZ/EL in degrees (e.g. 0/90: facing up) or a vector X/Y/Z")


def parse_sun_reference(text: str) -> SunReference:
    """A :class:`SunReference` from a command-line value (module docstring)::

        LON,LAT[,RADIUS_DEG][,normal=AZ/EL|X/Y/Z][,reflectance=0.95|FILE.csv|SET:SAMPLE][,radius=DEG]
    """
    usage = ("expected LON,LAT[,RADIUS_DEG][,normal=AZ/EL|X/Y/Z][,reflectance=0.95|FILE.csv|SET:SAMPLE]"
             "[,radius=DEG] in degrees")
    items = [p.strip() for p in str(text).split(",")]
    positional = [p for p in items if "=" not in p]
    keyed = [p for p in items if "=" in p]
    if items[:len(positional)] != positional or not 2 <= len(positional) <= 3:
        raise ConfigurationError(f"sun reference {text!r}: {usage}")
    try:
        numbers = [float(p) for p in positional]
    except ValueError:
        raise ConfigurationError(f"sun reference {text!r}: {usage}") from None
    kwargs: dict = {}
    if len(numbers) == 3:
        kwargs["radius_deg"] = numbers[2]
    for item in keyed:
        key, value = (s.strip() for s in item.split("=", 1))
        key = key.lower()
        if key in kwargs or (key == "radius" and "radius_deg" in kwargs):
            raise ConfigurationError(f"sun reference {text!r}: {key} given twice")
        if key == "normal":
            kwargs["normal"] = _parse_normal(value)
        elif key == "radius":
            try:
                kwargs["radius_deg"] = float(value)
            except ValueError:
                raise ConfigurationError(f"sun reference {text!r}: radius={value!r} is not a number") from None
        elif key == "reflectance":
            try:
                kwargs["reflectance"] = float(value)
            except ValueError:
                load_reflectance_spec(value)  # fail now on a missing file or an unknown sample
                kwargs["reflectance"] = value
        else:
            raise ConfigurationError(f"sun reference {text!r}: unknown key {key!r} ({usage})")
    return SunReference(numbers[0], numbers[1], **kwargs)


# ------------------------------------------------------------------------------------ measurements
def target_radiance(store, reference: SunReference, level: int = 0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Median band radiance over the target's patch, its standard error (module docstring) and the patch's
    statistics (pixels, relative spread); the median is NaN when no pixel of the patch has data."""
    h, w = store.shapes[level]
    px_deg = 360.0 / w
    radius = max(reference.radius_deg, 0.75 * px_deg)
    col, row = lonlat_to_equirect_pixel(reference.lon_deg, reference.lat_deg, w, h)
    r_rows = radius / px_deg + 1
    r_cols = r_rows / max(math.cos(math.radians(abs(reference.lat_deg))), 0.05)
    r0, r1 = int(max(0, math.floor(row - r_rows - 1))), int(min(h, math.ceil(row + r_rows + 2)))
    cols = np.arange(math.floor(col - r_cols - 1), math.ceil(col + r_cols + 2)) % w
    cols = np.unique(cols) if cols.size >= w else cols
    block = store.read(level, slice(r0, r1))[:, cols].astype(np.float64)
    rr, cc = np.meshgrid(np.arange(r0, r1), cols, indexing="ij")
    lon, lat = equirect_pixel_to_lonlat(cc, rr, w, h)
    ang = np.degrees(np.arccos(np.clip(lonlat_to_ray(lon, lat) @ reference.ray, -1, 1)))
    sel = block[ang <= radius]
    sel = sel[np.isfinite(sel).all(axis=1)]
    if sel.shape[0] == 0:
        nan = np.full(block.shape[2], np.nan)
        return nan, nan, {"n_pixels": 0}
    median = np.median(sel, axis=0)
    sigma = 1.4826 * np.median(np.abs(sel - median), axis=0)
    std = 1.2533 * sigma / math.sqrt(sel.shape[0])
    spread = sigma / np.maximum(np.abs(median), 1e-30)
    return median, std, {"n_pixels": int(sel.shape[0]), "radius_deg": radius,
                         "band_radiance": median.tolist(), "band_radiance_std": std.tolist(),
                         "relative_spread": spread.tolist()}


def sun_free_irradiance(store, clipped: dict, normal, margin_px: int = MARGIN_PX, ring_px: int = RING_PX,
                        level_dn_s: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Irradiance of a plane of ``normal`` from the panorama with the clipped sun replaced by the sky around it.

    ``clipped`` is :func:`~omnispectral.product.sun.clipped_sun_direction`'s record.  Returns ``E_rest`` (m,),
    the variance of the replacement and of the uncovered share (m,) (without the relative term), and details.
    """
    n = unit_normal(normal)
    h, w = store.shapes[0]
    total = irradiance(store, n)
    pad = margin_px + ring_px + 1
    r0 = max(0, clipped["rows"][0] - pad)
    r1 = min(h, clipped["rows"][1] + pad)
    cols = np.arange(clipped["cols"][0] - pad, clipped["cols"][1] + pad) % w
    window = store.read(0, slice(r0, r1))[:, cols].astype(np.float64)
    level = saturation_level_dn_s(store.attrs()) if level_dn_s is None else level_dn_s
    if level is None:
        raise ConfigurationError(f"{store.path}: the panorama carries no rig snapshot: no clipping level")
    clip = np.zeros(window.shape[:2], bool)
    runs = np.split(np.arange(cols.size), np.flatnonzero(np.diff(cols) != 1) + 1)
    for run in runs:  # the window may wrap around longitude ±180°
        c0 = int(cols[run[0]])
        clip[:, run] = clipped_mask(store, 0, window[:, run], level, (r0, c0))
    labels, k = ndimage.label(clip, structure=np.ones((3, 3)))
    if k > 1:  # the group around the clipped sun's centroid (its window's centre), not another clipped source
        cy = 0.5 * (clipped["rows"][0] + clipped["rows"][1] - 1) - r0
        cx = 0.5 * (clipped["cols"][0] + clipped["cols"][1] - 1) - (clipped["cols"][0] - pad)
        sizes = ndimage.sum(clip, labels, range(1, k + 1))
        centres = ndimage.center_of_mass(clip, labels, range(1, k + 1))
        dist = [math.hypot(c[0] - cy, c[1] - cx) for c in centres]
        keep = int(np.lexsort((-np.asarray(sizes), dist))[0]) + 1
        clip = labels == keep
    square = np.ones((3, 3), bool)
    region = ndimage.binary_dilation(clip, square, iterations=margin_px) if margin_px > 0 else clip
    outer = ndimage.binary_dilation(region, square, iterations=ring_px)
    ring = outer & ~region & np.isfinite(window).all(axis=2)
    if ring.sum() < 4:
        raise ConfigurationError("the clipped sun's surroundings have no data to replace it with")
    bg = np.median(window[ring], axis=0)
    bg_spread = 1.4826 * np.median(np.abs(window[ring] - bg), axis=0)
    rows = np.arange(r0, r1)
    weight = cosine_weights(rows, h, w, n)[:, cols]
    wr = np.where(region, weight, 0.0)
    excess = (np.nan_to_num(window, nan=0.0) - bg) * wr[..., None]
    removed = excess.sum(axis=(0, 1))
    e_rest = total.band_irradiance_dn_s_sr - removed
    var = (bg_spread * wr.sum()) ** 2 + ((1.0 - total.covered_fraction) * e_rest) ** 2
    return e_rest, var, {"panorama_band_irradiance": total.band_irradiance_dn_s_sr.tolist(),
                         "removed_band_irradiance": removed.tolist(), "background": bg.tolist(),
                         "background_spread": bg_spread.tolist(), "n_replaced_px": int(region.sum()),
                         "n_clipped_px": int(clip.sum()), "covered_fraction": total.covered_fraction}


def effective_reflectance(matrix: np.ndarray, reflectance: np.ndarray, spectrum: np.ndarray) -> np.ndarray:
    """``ρ_b = R_b (ρ ⊙ S) / R_b S`` per band ``(m,)`` (the band's reflectance under the light ``S``)."""
    s = np.clip(np.asarray(spectrum, np.float64), 0.0, None)
    if not s.sum() > 0:
        s = np.ones_like(s)
    num = matrix @ (reflectance * s)
    den = matrix @ s
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), float(np.mean(reflectance)))


# ------------------------------------------------------------------------------------------ the sun
def recover_sun_reference(store, system, band_names: list[str], reference: SunReference, *,
                          sky_rel_std: float = SKY_REL_STD, margin_px: int = MARGIN_PX, ring_px: int = RING_PX,
                          n_passes: int = N_PASSES, direction_std_deg: float | None = None,
                          clipped: dict | None = None) -> dict:
    """The sun's record (as :func:`omnispectral.product.sun.recover_sun_nd`'s, ``"method": "diffuse-reference"``)
    from a diffuse reference target in the panorama ``store`` (module docstring).

    Parameters
    ----------
    store : PanoramaStore
        The product's panorama with the sun clipped (not yet painted).
    system : MultibandSystem
        The rig's spectral system (``matrix`` (m, n), ``wavelength_nm``), e.g. ``rig.system()``.
    band_names : list of str
        The panorama's bands (``A:R`` … ``B:B``), in the system's order.
    reference : SunReference
        Where the target is, its normal and reflectance.
    sky_rel_std : float
        Relative uncertainty of the irradiance from the rest of the panorama (module docstring).
    margin_px, ring_px : int
        Pixels replaced around the clipped group, and the ring that gives the sky there.
    n_passes : int
        Passes of the effective-reflectance iteration (1 is exact for a flat reflectance).
    direction_std_deg : float, optional
        Uncertainty of the sun's direction; default half a panorama pixel.

    Returns
    -------
    dict
        ``method``, ``recovered`` and, when recovered, ``lon_deg``, ``lat_deg``, ``angular_diameter_deg``,
        ``solid_angle_sr``, ``band_names``, ``band_irradiance`` (DN/s·sr at normal incidence),
        ``band_irradiance_std``, ``band_radiance``, ``band_radiance_std``, ``wavelength_nm``,
        ``spectral_radiance``, ``spectral_radiance_std``, ``fit_relative_residual``, ``cos_incidence``,
        ``direction_std_deg``, ``reference``, ``target``, ``rest`` (the irradiance on the target's plane without
        the sun), ``effective_reflectance``, ``sun_term_snr``, ``warnings``; else a ``note`` saying why.
    ``clipped`` is the clipped sun's record when the caller has it (e.g. refined on the merged images by
    :func:`~omnispectral.product.sun.refine_clipped_direction`); default :func:`clipped_sun_direction`.
    """
    matrix = np.asarray(system.matrix, np.float64)
    wl = np.asarray(system.wavelength_nm, np.float64)
    m = matrix.shape[0]
    if len(band_names) != m or store.n_bands != m:
        raise ConfigurationError(f"the system has {m} bands, the panorama {store.n_bands}, band_names "
                                 f"{len(band_names)}")
    base = {"method": METHOD, "recovered": False, "reference": reference.to_dict()}
    clipped = clipped if clipped is not None else clipped_sun_direction(store)
    if clipped is None:
        return {**base, "note": "the panorama holds no clipped sun (nothing saturated in every exposure, or no rig "
                                "snapshot giving the clipping level): nothing to recover"}
    s_ray = lonlat_to_ray(clipped["lon_deg"], clipped["lat_deg"])
    n = np.asarray(reference.normal, np.float64)
    cos_t = float(s_ray @ n)
    base.update({"lon_deg": clipped["lon_deg"], "lat_deg": clipped["lat_deg"], "cos_incidence": cos_t})
    if cos_t < MIN_COS_INCIDENCE:
        where = "behind the target" if cos_t <= 0 else "grazing the target"
        return {**base, "note": f"the sun is {where} (cos θ = {cos_t:.3f} < {MIN_COS_INCIDENCE}): the reference "
                                f"cannot measure it; the sun stays a lower bound"}
    l_t, l_std, target = target_radiance(store, reference)
    if target["n_pixels"] == 0:
        return {**base, "target": target,
                "note": f"the reference at lon {reference.lon_deg:g}°, lat {reference.lat_deg:g}° is not covered by "
                        f"the panorama; the sun stays a lower bound"}
    e_rest, var_rest, rest = sun_free_irradiance(store, clipped, n, margin_px, ring_px)
    var_rest = var_rest + (sky_rel_std * e_rest) ** 2
    w_px = store.shapes[0][1]
    dir_std = (0.5 * 360.0 / w_px) if direction_std_deg is None else float(direction_std_deg)
    rho = reference.reflectance_on(wl)
    basis = daylight_basis(wl, n_components=min(4, m))
    sun_spd = sky_spd = np.ones(wl.size)
    passes = 1 if reference.flat else max(1, int(n_passes))
    for _ in range(passes):
        rho_sun = effective_reflectance(matrix, rho, sun_spd)
        rho_rest = effective_reflectance(matrix, rho, sky_spd)
        sun_term = math.pi * l_t - rho_rest * e_rest  # ρ_sun E_⊥ cos θ, per band
        e_sun = sun_term / (rho_sun * cos_t)
        var_term = math.pi ** 2 * l_std ** 2 + rho_rest ** 2 * var_rest
        tan_t = math.sqrt(max(0.0, 1.0 - cos_t ** 2)) / cos_t
        var_sun = var_term / (rho_sun * cos_t) ** 2 + (e_sun * tan_t * math.radians(dir_std)) ** 2
        sun_spd, sun_std = fit_spectrum(e_sun, np.maximum(var_sun, 1e-30), matrix, basis)
        sky_spd, _ = fit_spectrum(e_rest, np.maximum(var_rest, 1e-30), matrix, basis)
    # the sun term summed over the bands against its uncertainty (the sky's relative part correlated across bands)
    sky_sys = float(np.sum(rho_rest * sky_rel_std * np.abs(e_rest)))
    sky_rand = np.maximum(var_rest - (sky_rel_std * e_rest) ** 2, 0.0)
    sum_std = math.sqrt(float(np.sum(math.pi ** 2 * l_std ** 2 + rho_rest ** 2 * sky_rand))) + sky_sys
    snr = float(np.sum(sun_term)) / max(sum_std, 1e-30)
    band_snr = sun_term / np.sqrt(np.maximum(var_term, 1e-60))
    base.update({"target": target, "sun_term_snr": snr, "band_sun_term_snr": band_snr.tolist()})
    if not snr >= MIN_SUN_SNR:
        return {**base, "rest": {**rest, "band_irradiance": e_rest.tolist()},
                "note": f"the reference looks shadowed: the sky alone explains its radiance (sun term "
                        f"{snr:.1f}× its uncertainty < {MIN_SUN_SNR}); the sun stays a lower bound"}
    warnings = []
    if np.any(e_sun <= 0):
        warnings.append("some bands of the sun came out ≤ 0 (the reference is barely lit in them)")
    spread = np.asarray(target["relative_spread"])
    if np.max(spread) > PATCH_SPREAD_WARN:
        warnings.append(f"the reference's patch is not uniform (relative spread up to {np.max(spread):.2f}): a "
                        "shadow edge, the target's border or something else within radius_deg of it")
    fit_residual = float(np.linalg.norm(matrix @ sun_spd - e_sun) / max(np.linalg.norm(e_sun), 1e-30))
    sun_std_band = np.sqrt(np.maximum(var_sun, 0.0))
    return {**base, "recovered": True, "direction_std_deg": dir_std, "n_clipped_px": clipped["n_clipped_px"],
            **sun_radiance_fields(band_names, e_sun, sun_std_band, wl, sun_spd, sun_std),
            "fit_relative_residual": fit_residual,
            "measured_bands": list(band_names),
            "rest": {**rest, "band_irradiance": e_rest.tolist(), "band_irradiance_std": np.sqrt(var_rest).tolist(),
                     "relative_std_assumed": sky_rel_std},
            "effective_reflectance": {"sun": rho_sun.tolist(), "rest": rho_rest.tolist(), "passes": passes},
            "warnings": warnings}
