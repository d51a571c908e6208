"""Clear-sky daylight for the procedural scene: sun position, illuminances, sky luminance, spectra.

Everything a sunlit outdoor scene needs, from a date, a clock time and a site:

- **Sun position**: NOAA Global Monitoring Laboratory, "General Solar Position Calculations"
  (fractional year, equation of time and declination from Spencer's Fourier series, J. W.
  Spencer, "Fourier series representation of the position of the Sun", Search 2(5), 1971).  The
  elevation is geometric (no refraction); accuracy is about 0.1° in declination.
- **Illuminances**: the IESNA clear-sky model (IESNA Lighting Handbook, 9th ed., 2000, ch. 8
  "Daylighting"): extraterrestrial solar illuminance ``E_xt = 127.5 klx · (1 + 0.034 cos(2π (J -
  2) / 365))``, direct normal illuminance ``E_dn = E_xt exp(-c m)`` with the clear-sky extinction
  ``c = 0.21`` and the relative air mass ``m`` of Kasten & Young ("Revised optical air mass tables
  and approximation formula", Applied Optics 28(22), 1989), and horizontal sky illuminance
  ``E_kh = 0.8 + 15.5 sin(h)^0.5 klx``.  Below the horizon the sun is gone and ``E_kh`` falls by a
  decade per 2.4° of depression (our own extrapolation: about 3 lx at the end of civil twilight).
- **Sky luminance distribution**: the CIE standard general sky (ISO 15469:2004 / CIE S 011/E:2003,
  R. Kittler, S. Darula, R. Perez), type 12 "CIE standard clear sky, low luminance turbidity"
  (gradation ``a = -1, b = -0.32``, indicatrix ``c = 10, d = -3, e = 0.45``), scaled so that its
  integral over the sky hemisphere gives ``E_kh`` on a horizontal surface.
- **Spectra**: CIE D-series daylight (CIE 015:2018) at a correlated colour temperature that follows
  the sun elevation ``h`` (our mapping, not a fit to measurements): direct sun
  ``T_sun = 4000 K + 2500 K (1 - exp(-h / 10°))`` (4000 K at the horizon, ≈6500 K above 40°) and
  skylight ``T_sky = 6500 K + 5500 K (1 - exp(-h / 10°))`` (6500 K to ≈12000 K, bluer than the sun,
  as clear skylight is).  Below 4000 K the D-series is undefined, so the low sun is clamped there.
  One sky spectrum is used for the whole dome (luminance varies with direction, chromaticity does
  not).  Spectra are normalised to unit luminous quantity (``683 lm/W · Σ S ȳ Δλ = 1`` on
  360-830 nm every 5 nm), so a spectrum times an illuminance in lx is a spectral irradiance in
  W·m⁻²·nm⁻¹ and times a luminance in cd/m² a spectral radiance in W·sr⁻¹·m⁻²·nm⁻¹.

Compass: azimuths are clockwise from north; ``north_lon_deg`` is the scene longitude that faces
north.  Because scene longitude also grows clockwise seen from above, ``lon = north_lon_deg +
azimuth``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from functools import cache

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.sim.scenes.base import direction_to_lonlat, lonlat_to_direction
from omnispectral.spectral.colour import K_M_LM_PER_W, LUMINOUS_GRID_NM, spectrum_cct_K, ybar_5nm
from omnispectral.spectral.curves import resample_spectra
from omnispectral.spectral.library import daylight_spd

__all__ = ["CIE_SKY_TYPE_12", "CLEAR_SKY_EXTINCTION", "SKY_QUADRATURE", "SOLAR_ILLUMINANCE_CONSTANT_LX",
           "SUN_DIAMETER_DEG", "ClearSkyDaylight", "SolarPosition", "cie_sky_relative_luminance", "compass_to_world",
           "diffuse_horizontal_illuminance_lx", "direct_normal_illuminance_lx", "extraterrestrial_illuminance_lx",
           "hemisphere_quadrature", "parse_time_hhmm", "relative_air_mass", "sky_cct_K", "solar_position",
           "sun_cct_K", "unit_luminance_daylight"]

#: IES solar illuminance constant (lx), IESNA Lighting Handbook 9th ed.
SOLAR_ILLUMINANCE_CONSTANT_LX = 127_500.0
#: IES atmospheric extinction coefficient of a clear sky.
CLEAR_SKY_EXTINCTION = 0.21
#: Angular diameter of the sun (degrees), mean value.
SUN_DIAMETER_DEG = 0.533
#: CIE standard general sky type 12 (ISO 15469:2004): gradation a, b and indicatrix c, d, e.
CIE_SKY_TYPE_12 = {"a": -1.0, "b": -0.32, "c": 10.0, "d": -3.0, "e": 0.45}
#: Quadrature of the sky hemisphere used for illuminances: zenith × azimuth midpoint samples.
SKY_QUADRATURE = (180, 720)
_HHMM = re.compile(r"^\s*(\d{1,2}):(\d{2})(?::(\d{2}))?\s*$")


# ------------------------------------------------------------------------------------ sun position
@dataclass(frozen=True)
class SolarPosition:
    """Where the sun is: geometric elevation and azimuth (clockwise from north), degrees."""

    elevation_deg: float
    azimuth_deg: float
    declination_deg: float
    hour_angle_deg: float
    equation_of_time_min: float


def parse_time_hhmm(text: str) -> float:
    """``"HH:MM"`` (or ``"HH:MM:SS"``) local clock time → hours after midnight."""
    m = _HHMM.match(str(text))
    if not m:
        raise ConfigurationError(f"time must be HH:MM (24-hour clock), got {text!r}")
    h, mi, s = int(m.group(1)), int(m.group(2)), int(m.group(3) or 0)
    if h > 24 or mi > 59 or s > 59 or (h == 24 and (mi or s)):
        raise ConfigurationError(f"time must be HH:MM (24-hour clock), got {text!r}")
    return h + mi / 60.0 + s / 3600.0


def solar_position(day_of_year: int, local_time_h: float, latitude_deg: float, longitude_deg: float,
                   utc_offset_h: float) -> SolarPosition:
    """Sun elevation and azimuth after NOAA's "General Solar Position Calculations".

    ``γ = 2π/365 (J - 1 + (hour - 12)/24)``; equation of time ``229.18 (0.000075 + 0.001868 cos γ
    - 0.032077 sin γ - 0.014615 cos 2γ - 0.040849 sin 2γ)`` minutes; declination ``0.006918 -
    0.399912 cos γ + 0.070257 sin γ - 0.006758 cos 2γ + 0.000907 sin 2γ - 0.002697 cos 3γ + 0.00148
    sin 3γ`` rad; true solar time ``= clock minutes + EoT + 4·longitude - 60·UTC offset``; hour
    angle ``= TST/4 - 180°``; ``sin h = sin φ sin δ + cos φ cos δ cos H``; azimuth (clockwise from
    north) ``= atan2(sin H, cos H sin φ - tan δ cos φ) + 180°``.  ``longitude_deg`` is positive east.
    """
    if not 1 <= day_of_year <= 366:
        raise ConfigurationError(f"day_of_year must be 1..366, got {day_of_year}")
    if not -90.0 <= latitude_deg <= 90.0:
        raise ConfigurationError(f"latitude_deg must be within ±90, got {latitude_deg}")
    g = 2.0 * math.pi / 365.0 * (day_of_year - 1 + (local_time_h - 12.0) / 24.0)
    eot_min = 229.18 * (0.000075 + 0.001868 * math.cos(g) - 0.032077 * math.sin(g)
                        - 0.014615 * math.cos(2 * g) - 0.040849 * math.sin(2 * g))
    decl = (0.006918 - 0.399912 * math.cos(g) + 0.070257 * math.sin(g) - 0.006758 * math.cos(2 * g)
            + 0.000907 * math.sin(2 * g) - 0.002697 * math.cos(3 * g) + 0.00148 * math.sin(3 * g))
    tst_min = local_time_h * 60.0 + eot_min + 4.0 * longitude_deg - 60.0 * utc_offset_h
    ha = math.radians(tst_min / 4.0 - 180.0)
    lat = math.radians(latitude_deg)
    sin_h = math.sin(lat) * math.sin(decl) + math.cos(lat) * math.cos(decl) * math.cos(ha)
    elevation = math.degrees(math.asin(max(-1.0, min(1.0, sin_h))))
    azimuth = math.degrees(math.atan2(math.sin(ha), math.cos(ha) * math.sin(lat) - math.tan(decl) * math.cos(lat)))
    return SolarPosition(elevation, (azimuth + 180.0) % 360.0, math.degrees(decl),
                         math.degrees(ha), eot_min)


def compass_to_world(azimuth_deg: float, elevation_deg: float, north_lon_deg: float) -> np.ndarray:
    """Unit world direction of a compass azimuth (clockwise from north) and elevation."""
    return lonlat_to_direction(north_lon_deg + azimuth_deg, elevation_deg)


# ------------------------------------------------------------------------------------ illuminances
def relative_air_mass(elevation_deg: float) -> float:
    """Kasten & Young (1989): ``m = 1 / (sin h + 0.50572 (h + 6.07995°)^-1.6364)``; ``inf`` below -6°."""
    if elevation_deg <= -6.07:
        return math.inf
    return 1.0 / (math.sin(math.radians(elevation_deg)) + 0.50572 * (elevation_deg + 6.07995) ** -1.6364)


def extraterrestrial_illuminance_lx(day_of_year: int) -> float:
    """IES: ``E_xt = 127.5 klx · (1 + 0.034 cos(2π (J - 2) / 365))``."""
    return SOLAR_ILLUMINANCE_CONSTANT_LX * (1.0 + 0.034 * math.cos(2.0 * math.pi * (day_of_year - 2) / 365.0))


def direct_normal_illuminance_lx(elevation_deg: float, day_of_year: int,
                                 extinction: float = CLEAR_SKY_EXTINCTION) -> float:
    """IES clear sky: ``E_dn = E_xt exp(-c m)``; 0 once the sun's centre is below the horizon."""
    if elevation_deg <= 0.0:
        return 0.0
    return extraterrestrial_illuminance_lx(day_of_year) * math.exp(-extinction * relative_air_mass(elevation_deg))


def diffuse_horizontal_illuminance_lx(elevation_deg: float) -> float:
    """IES clear sky: ``E_kh = 0.8 + 15.5 sin(h)^0.5`` klx; below the horizon 800 lx · 10^(h / 2.4°)."""
    if elevation_deg <= 0.0:
        return 800.0 * 10.0 ** (elevation_deg / 2.4)
    return 1000.0 * (0.8 + 15.5 * math.sqrt(math.sin(math.radians(elevation_deg))))


# ---------------------------------------------------------------------------------- sky luminance
def cie_sky_relative_luminance(cos_zenith, cos_sun_angle, sun_zenith_rad: float, params=None) -> np.ndarray:
    """CIE standard general sky (ISO 15469:2004): ``L / L_z = f(χ) φ(Z) / (f(Z_s) φ(0))``.

    ``φ(Z) = 1 + a exp(b / cos Z)`` (``φ = 1`` at and below the horizon), ``f(χ) = 1 + c (exp(d χ) -
    exp(d π/2)) + e cos² χ``; ``cos_sun_angle = cos χ`` between the sky element and the sun.
    Works on float32 arrays (the renderer's hot path).  Default parameters: type 12.
    """
    p = CIE_SKY_TYPE_12 if params is None else params
    cz = np.asarray(cos_zenith)
    cx = np.clip(np.asarray(cos_sun_angle), -1.0, 1.0)
    dtype = np.result_type(cz.dtype, np.float32)
    chi = np.arccos(cx)
    f = 1.0 + p["c"] * (np.exp(p["d"] * chi) - math.exp(p["d"] * math.pi / 2.0)) + p["e"] * cx * cx
    with np.errstate(divide="ignore", over="ignore"):
        phi = 1.0 + p["a"] * np.exp(p["b"] / np.maximum(cz, np.asarray(1e-6, dtype=dtype)))
    chi_s = sun_zenith_rad
    f_s = 1.0 + p["c"] * (math.exp(p["d"] * chi_s) - math.exp(p["d"] * math.pi / 2.0)) + p["e"] * math.cos(chi_s) ** 2
    phi_0 = 1.0 + p["a"] * math.exp(p["b"])
    return (f * phi * (1.0 / (f_s * phi_0))).astype(dtype, copy=False)


@cache
def hemisphere_quadrature(n_zenith: int = SKY_QUADRATURE[0], n_azimuth: int = SKY_QUADRATURE[1]):
    """Midpoint samples of the upper hemisphere: world directions ``(K, 3)`` and solid angles ``(K,)`` (sr)."""
    z = (np.arange(n_zenith) + 0.5) * (0.5 * math.pi / n_zenith)
    a = (np.arange(n_azimuth) + 0.5) * (2.0 * math.pi / n_azimuth)
    zz, aa = np.meshgrid(z, a, indexing="ij")
    d = np.stack((np.sin(zz) * np.cos(aa), np.cos(zz), np.sin(zz) * np.sin(aa)), axis=-1).reshape(-1, 3)
    w = (np.sin(zz) * (0.5 * math.pi / n_zenith) * (2.0 * math.pi / n_azimuth)).reshape(-1)
    d.setflags(write=False)
    w.setflags(write=False)
    return d, w


# --------------------------------------------------------------------------------------- spectra
def sun_cct_K(elevation_deg: float) -> float:
    """Correlated colour temperature of direct sunlight (our mapping, see the module docstring)."""
    return 4000.0 + 2500.0 * (1.0 - math.exp(-max(elevation_deg, 0.0) / 10.0))


def sky_cct_K(elevation_deg: float) -> float:
    """Correlated colour temperature of clear skylight (our mapping, see the module docstring)."""
    return 6500.0 + 5500.0 * (1.0 - math.exp(-max(elevation_deg, 0.0) / 10.0))


def unit_luminance_daylight(cct_K: float, wavelength_nm) -> np.ndarray:
    """CIE D-series spectrum at ``cct_K`` scaled to unit luminous quantity, sampled at ``wavelength_nm``.

    ``S(λ) = D(λ) / (683 Σ_{360..830/5 nm} D ȳ · 5 nm)``: W·m⁻²·nm⁻¹ per lx (or W·sr⁻¹·m⁻²·nm⁻¹
    per cd/m²).  Linear interpolation between the 5-nm D-series samples.
    """
    sd = daylight_spd(float(np.clip(cct_K, 4000.0, 25000.0)))
    k = K_M_LM_PER_W * float(np.sum(np.asarray(sd[LUMINOUS_GRID_NM]) * ybar_5nm())) * 5.0
    return resample_spectra(sd.values, sd.wavelengths, np.asarray(wavelength_nm, dtype=np.float64), outside="edge") / k


# ------------------------------------------------------------------------------------- daylight
class ClearSkyDaylight:
    """Sun and clear sky for one instant at one site, in absolute photometric and spectral units.

    Parameters
    ----------
    day_of_year, time_hhmm, latitude_deg, longitude_deg, utc_offset_h
        Date, local clock time (``"HH:MM"``) and site (longitude positive east).
    north_lon_deg
        Scene longitude of north.
    wavelength_nm
        Grid of the spectra.

    Attributes
    ----------
    sun : SolarPosition
    sun_direction : (3,) unit world vector towards the sun's centre
    direct_normal_lx, diffuse_horizontal_lx : IES clear-sky illuminances
    zenith_luminance_cd_m2 : sky luminance at the zenith (type 12 scaled to ``diffuse_horizontal_lx``)
    sun_luminance_cd_m2 : luminance of the (uniform) solar disk, ``E_dn / Ω_sun``
    sun_spectrum, sky_spectrum : unit-luminance spectra (see :func:`unit_luminance_daylight`)
    """

    def __init__(self, day_of_year: int, time_hhmm: str, latitude_deg: float, longitude_deg: float,
                 utc_offset_h: float, north_lon_deg: float, wavelength_nm):
        self.day_of_year = int(day_of_year)
        self.time_hhmm = str(time_hhmm)
        self.local_time_h = parse_time_hhmm(time_hhmm)
        self.latitude_deg = float(latitude_deg)
        self.longitude_deg = float(longitude_deg)
        self.utc_offset_h = float(utc_offset_h)
        self.north_lon_deg = float(north_lon_deg)
        self.wavelength_nm = np.asarray(wavelength_nm, dtype=np.float64)
        self.sun = solar_position(self.day_of_year, self.local_time_h, self.latitude_deg, self.longitude_deg,
                                  self.utc_offset_h)
        self.sun_direction = compass_to_world(self.sun.azimuth_deg, self.sun.elevation_deg, self.north_lon_deg)
        self.sun_zenith_rad = math.radians(90.0 - self.sun.elevation_deg)
        self.sun_radius_rad = math.radians(SUN_DIAMETER_DEG / 2.0)
        self.sun_solid_angle_sr = 2.0 * math.pi * (1.0 - math.cos(self.sun_radius_rad))
        self.direct_normal_lx = direct_normal_illuminance_lx(self.sun.elevation_deg, self.day_of_year)
        self.diffuse_horizontal_lx = diffuse_horizontal_illuminance_lx(self.sun.elevation_deg)
        self.sun_luminance_cd_m2 = self.direct_normal_lx / self.sun_solid_angle_sr
        self.cct_sun_K = sun_cct_K(self.sun.elevation_deg)
        self.cct_sky_K = sky_cct_K(self.sun.elevation_deg)
        self.sun_spectrum = unit_luminance_daylight(self.cct_sun_K, self.wavelength_nm)
        self.sky_spectrum = unit_luminance_daylight(self.cct_sky_K, self.wavelength_nm)
        dirs, w = hemisphere_quadrature()
        rel = self.relative_sky_luminance(dirs)
        self.zenith_luminance_cd_m2 = self.diffuse_horizontal_lx / float(np.sum(rel * dirs[:, 1] * w))
        self._quad_luminance = rel * self.zenith_luminance_cd_m2 * w
        self._sky_lx: dict[tuple, float] = {}

    # -- luminance of the sky dome ----------------------------------------------------------------
    def relative_sky_luminance(self, directions) -> np.ndarray:
        """``L / L_z`` of the type-12 sky for unit world directions ``(N, 3)`` (horizon value below it)."""
        d = np.asarray(directions)
        s = self.sun_direction.astype(d.dtype)
        # element-wise dot product: a BLAS product may round differently with the number of rays traced at once
        cos_sun = d[:, 0] * s[0] + d[:, 1] * s[1] + d[:, 2] * s[2]
        return cie_sky_relative_luminance(d[:, 1], cos_sun, self.sun_zenith_rad)

    def sky_luminance_cd_m2(self, directions) -> np.ndarray:
        """Sky luminance (cd/m², without the solar disk) for unit world directions ``(N, 3)``."""
        d = np.asarray(directions)
        return self.relative_sky_luminance(d) * d.dtype.type(self.zenith_luminance_cd_m2)

    # -- illuminances on surfaces -----------------------------------------------------------------
    def sky_illuminance_lx(self, normal) -> float:
        """Illuminance (lx) from the sky dome (above the horizon) on a surface with unit ``normal``.

        ``∫ L(ω) max(0, ω·n) dω`` by the midpoint rule of :func:`hemisphere_quadrature`; occlusion
        by scene geometry and light reflected by the ground are not included.
        """
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        key = tuple(np.round(n, 12))
        if key not in self._sky_lx:
            dirs, _ = hemisphere_quadrature()
            self._sky_lx[key] = float(np.sum(self._quad_luminance * np.maximum(dirs @ n, 0.0)))
        return self._sky_lx[key]

    def sun_illuminance_lx(self, normal) -> float:
        """Illuminance (lx) of the unobstructed sun on a surface with unit ``normal``."""
        n = np.asarray(normal, dtype=np.float64)
        return self.direct_normal_lx * max(0.0, float(n @ self.sun_direction) / float(np.linalg.norm(n)))

    def daylight_cct_K(self, normal) -> float:
        """CCT of the daylight (unobstructed sun + sky) falling on a surface of unit ``normal``, on 360-830 nm."""
        wl = LUMINOUS_GRID_NM
        spd = (self.sun_illuminance_lx(normal) * unit_luminance_daylight(self.cct_sun_K, wl)
               + self.sky_illuminance_lx(normal) * unit_luminance_daylight(self.cct_sky_K, wl))
        return spectrum_cct_K(wl, spd)

    def describe(self) -> dict:
        """JSON-able summary of the sun and sky."""
        lon, lat = direction_to_lonlat(self.sun_direction)
        return {
            "model": "IESNA clear sky illuminances + CIE standard general sky type 12 + CIE D-series spectra",
            "day_of_year": self.day_of_year,
            "time_hhmm": self.time_hhmm,
            "latitude_deg": self.latitude_deg,
            "longitude_deg": self.longitude_deg,
            "utc_offset_h": self.utc_offset_h,
            "north_lon_deg": self.north_lon_deg,
            "sun_elevation_deg": self.sun.elevation_deg,
            "sun_azimuth_deg": self.sun.azimuth_deg,
            "sun_lon_deg": float(lon),
            "sun_lat_deg": float(lat),
            "declination_deg": self.sun.declination_deg,
            "equation_of_time_min": self.sun.equation_of_time_min,
            "direct_normal_illuminance_lx": self.direct_normal_lx,
            "diffuse_horizontal_illuminance_lx": self.diffuse_horizontal_lx,
            "global_horizontal_illuminance_lx": self.sun_illuminance_lx([0, 1, 0]) + self.sky_illuminance_lx([0, 1, 0]),
            "zenith_luminance_cd_m2": self.zenith_luminance_cd_m2,
            "sun_luminance_cd_m2": self.sun_luminance_cd_m2,
            "sun_diameter_deg": SUN_DIAMETER_DEG,
            "cct_sun_K": self.cct_sun_K,
            "cct_sky_K": self.cct_sky_K,
            "cct_global_horizontal_K": self.daylight_cct_K([0.0, 1.0, 0.0]),
            "cct_facing_sun_K": self.daylight_cct_K(self.sun_direction) if self.direct_normal_lx > 0 else None,
        }
