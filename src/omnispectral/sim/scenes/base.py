"""The scene interface of the simulated rig, direction helpers and equirectangular ground truth.

A scene answers one question: what spectral radiance arrives at a point from a direction.  The
renderer asks it for millions of camera rays per frame, so every scene also has a fast path,
:meth:`Scene.band_radiance`, that integrates the spectra against a set of band sensitivities
without forming them: each scene writes its radiance as a short sum ``Σ_j w_j(ray) s_j(λ)`` of a
few fixed spectra ``s_j`` (material × light, or colour basis), projects those spectra on the bands
once per sensitivity (:class:`BandProjectionCache`) and combines a few per-ray scalars.

Conventions
-----------
Directions are unit vectors in the world frame of :mod:`omnispectral.imaging.geometry`:
right-handed, ``+Y`` up, longitude 0 / latitude 0 along ``+Z``, longitude ``+90°`` along ``-X``
(longitude grows to the right when looking out), so ``lon = atan2(-x, z)``, ``lat = asin(y)``.
A direction is the way one looks (the reverse of the light's travel).  Origins are in metres.
Equirectangular grids put column 0 at longitude -180°, row 0 at latitude +90° and pixel centres
at ``+0.5``.  Spectral radiance is in W·sr⁻¹·m⁻²·nm⁻¹ on the scene's ``wavelength_nm`` grid; a
band value is ``Σ_λ L(λ) S(λ)`` with the sensitivity ``S`` already multiplied by ``Δλ``.
"""

from __future__ import annotations

import hashlib
from abc import ABC, abstractmethod
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import lonlat_to_ray, ray_to_lonlat

__all__ = ["BAND_CACHE_SIZE", "MAX_SPECTRAL_CUBE_BYTES", "RAY_BLOCK", "BandProjectionCache", "Scene", "SunDisk",
           "as_directions", "as_origin", "check_wavelengths", "direction_to_lonlat", "equirect_directions",
           "equirect_lonlat", "footprint_kwargs", "lonlat_to_direction", "render_rows", "scene_sun_disk",
           "sensitivity_key"]

#: Rays processed per internal block: small enough for the per-ray temporaries to stay in cache.
RAY_BLOCK = 1 << 15
#: Sensitivity projections kept per scene (one per distinct sensitivity matrix).
BAND_CACHE_SIZE = 8
#: Largest spectral ground-truth cube :meth:`Scene.ground_truth_spectral` builds in memory.
MAX_SPECTRAL_CUBE_BYTES = 2 << 30


# ------------------------------------------------------------------------------------- directions
def lonlat_to_direction(lon_deg, lat_deg) -> np.ndarray:
    """Unit world directions ``(..., 3)`` (float64): :func:`omnispectral.imaging.geometry.lonlat_to_ray`."""
    return lonlat_to_ray(*np.broadcast_arrays(np.asarray(lon_deg, np.float64), np.asarray(lat_deg, np.float64)))


def direction_to_lonlat(directions) -> tuple[np.ndarray, np.ndarray]:
    """World directions ``(..., 3)`` (any length > 0) → ``(lon_deg, lat_deg)``, ``lon`` in ``[-180, 180)``.

    :func:`omnispectral.imaging.geometry.ray_to_lonlat` on the normalised directions.
    """
    d = np.asarray(directions, dtype=np.float64)
    return ray_to_lonlat(d / np.linalg.norm(d, axis=-1, keepdims=True))


def equirect_lonlat(width: int, height: int, row_start: int = 0,
                    row_stop: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre ``(lon_deg (W,), lat_deg (rows,))`` of rows ``row_start:row_stop`` of a W × H grid."""
    _check_grid(width, height)
    row_stop = height if row_stop is None else row_stop
    lon = (np.arange(width) + 0.5) * (360.0 / width) - 180.0
    lat = 90.0 - (np.arange(row_start, row_stop) + 0.5) * (180.0 / height)
    return lon, lat


def equirect_directions(width: int, height: int, row_start: int = 0, row_stop: int | None = None) -> np.ndarray:
    """Unit directions ``(rows, W, 3)`` (float64) through the pixel centres of an equirectangular grid."""
    lon, lat = equirect_lonlat(width, height, row_start, row_stop)
    return lonlat_to_direction(lon[None, :], lat[:, None])


def render_rows(directions, origin_m, table: np.ndarray, shade: Callable) -> np.ndarray:
    """Radiance ``(..., m)`` float32 of scenes whose ray sees one row of ``table`` times a weight.

    ``shade(d (N, 3) float64, o (3,))`` returns each ray's row in ``table`` and its weight (``None``: 1);
    rays are traced in blocks of :data:`RAY_BLOCK`.
    """
    d, lead = as_directions(directions)
    o = as_origin(origin_m)
    out = np.empty((d.shape[0], table.shape[1]), np.float32)
    for b0 in range(0, d.shape[0], RAY_BLOCK):
        b1 = min(d.shape[0], b0 + RAY_BLOCK)
        row, weight = shade(d[b0:b1].astype(np.float64), o)
        out[b0:b1] = table[row] if weight is None else table[row] * weight[:, None].astype(np.float32)
    return out.reshape(*lead, table.shape[1])


def _check_grid(width: int, height: int) -> None:
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ConfigurationError(f"an equirectangular grid needs positive integer width and height, "
                                 f"got {width}×{height}")


def as_directions(directions) -> tuple[np.ndarray, tuple[int, ...]]:
    """``(..., 3)`` directions → ``(N, 3)`` float32 unit vectors and the leading shape to restore."""
    d = np.asarray(directions)
    if d.ndim < 1 or d.shape[-1] != 3:
        raise ConfigurationError(f"directions must have shape (..., 3), got {d.shape}")
    lead = d.shape[:-1]
    d = d.reshape(-1, 3).astype(np.float32, copy=True)
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    if np.any(~np.isfinite(norm)) or np.any(norm <= 0):
        raise ConfigurationError("directions must be finite and non-zero")
    d /= norm[:, None]
    return d, lead


def as_origin(origin_m) -> np.ndarray:
    """A viewpoint ``(3,)`` in metres (float64)."""
    o = np.asarray(origin_m, dtype=np.float64).reshape(-1)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ConfigurationError(f"origin_m must be 3 finite coordinates in metres, got {origin_m!r}")
    return o


# ----------------------------------------------------------------------------------- projections
def sensitivity_key(sensitivity: np.ndarray) -> tuple:
    """Cache key of a sensitivity matrix: its shape and a BLAKE2 digest of its float64 bytes."""
    s = np.ascontiguousarray(sensitivity, dtype=np.float64)
    return s.shape, hashlib.blake2b(s.tobytes(), digest_size=16).hexdigest()


class BandProjectionCache:
    """Small LRU cache of per-sensitivity projections (e.g. ``spectra @ S.T``), keyed by content."""

    def __init__(self, size: int = BAND_CACHE_SIZE):
        self.size = size
        self._items: OrderedDict[tuple, Any] = OrderedDict()

    def get(self, sensitivity: np.ndarray, build: Callable[[np.ndarray], Any]) -> Any:
        """The projection for ``sensitivity``, built with ``build(sensitivity)`` on first use."""
        key = sensitivity_key(sensitivity)
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = build(sensitivity)
        self._items[key] = value
        while len(self._items) > self.size:
            self._items.popitem(last=False)
        return value


def check_wavelengths(wavelength_nm) -> np.ndarray:
    """A scene's wavelength grid: strictly increasing nm, float64 ``(n,)``."""
    wl = np.asarray(wavelength_nm, dtype=np.float64).reshape(-1)
    if wl.size < 2 or np.any(np.diff(wl) <= 0) or not np.all(np.isfinite(wl)):
        raise ConfigurationError("wavelength_nm must be a strictly increasing array of at least 2 wavelengths")
    return wl


# ------------------------------------------------------------------------------------- sun disk
@dataclass(frozen=True)
class SunDisk:
    """A scene's analytic sun: a uniform disk the renderers add exactly instead of ray-sampling it.

    A scene that has one renders it in :meth:`Scene.spectral_radiance` / :meth:`Scene.band_radiance`
    by default (a ray inside the disk gets its radiance) and leaves it out with ``sun_disk=False``;
    the simulator then adds it with :mod:`omnispectral.imaging.sundisk` (stratified disk samples,
    each tested with :attr:`visible`, splatted into the pixels they fall in), so that a truth or a
    camera frame holds the disk's energy whatever its pixel size.

    Attributes
    ----------
    direction : ndarray (3,)
        Unit world direction of the disk's centre.
    radius_rad : float
        Angular radius.
    spectral_radiance : ndarray (n,)
        The disk's (uniform) spectral radiance, W·sr⁻¹·m⁻²·nm⁻¹ on the scene's ``wavelength_nm``.
    visible : callable
        ``visible(directions (N, 3), origin_m) -> bool (N,)``: whether a ray from ``origin_m`` reaches the
        sky (no ground, building, chart or hill in the way).
    """

    direction: np.ndarray
    radius_rad: float
    spectral_radiance: np.ndarray
    visible: Callable[[np.ndarray, Any], np.ndarray]

    def band_radiance(self, sensitivity) -> np.ndarray:
        """``(m,)`` float64: the disk's radiance integrated against ``sensitivity (m, n)`` (× Δλ)."""
        return np.atleast_2d(np.asarray(sensitivity, np.float64)) @ self.spectral_radiance


def footprint_kwargs(scene, ray_spread_rad) -> dict:
    """``{"ray_spread_rad": ray_spread_rad}`` for a scene whose rendering takes it (:attr:`Scene.ray_footprint`),
    else ``{}``: what a renderer adds to its rendering calls."""
    return {"ray_spread_rad": ray_spread_rad} if getattr(scene, "ray_footprint", False) else {}


def scene_sun_disk(scene) -> SunDisk | None:
    """``scene.sun_disk()`` for scenes that have the method (any object can be rendered), else None."""
    method = getattr(scene, "sun_disk", None)
    return method() if callable(method) else None


# ---------------------------------------------------------------------------------------- scene
class Scene(ABC):
    """A scene of the simulated rig: spectral radiance arriving at a point from unit directions.

    Subclasses implement :meth:`spectral_radiance`, :meth:`band_radiance` and :meth:`describe`;
    the ground-truth helpers are shared.
    """

    #: Short name of the scene kind (``describe()["kind"]``).
    kind: str = "scene"
    #: Units of :meth:`spectral_radiance`.
    radiance_units: str = "W sr-1 m-2 nm-1"
    #: Whether the rendering methods take ``ray_spread_rad`` (each ray's angular footprint, to filter a
    #: texture finer than the rays: :mod:`omnispectral.sim.scenes.cube`); renderers pass it when True
    #: (:func:`footprint_kwargs`).
    ray_footprint: bool = False

    def __init__(self, wavelength_nm):
        self.wavelength_nm = check_wavelengths(wavelength_nm)

    # -- the interface --------------------------------------------------------------------------
    @abstractmethod
    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Spectral radiance ``(N, n)`` float32 arriving at ``origin_m`` from unit ``directions (N, 3)``."""

    @abstractmethod
    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """``spectral_radiance(directions, origin_m) @ sensitivity.T`` as ``(N, m)`` float32, without the spectra.

        Parameters
        ----------
        directions : array_like
            ``(N, 3)`` unit directions in the world frame (the way one looks).
        sensitivity : array_like
            ``(m, n)`` band sensitivities on the scene's ``wavelength_nm`` grid, already multiplied by the
            sampling interval ``Δλ`` (nm).
        origin_m : array_like
            ``(3,)`` the point the light arrives at, in metres.

        Returns
        -------
        numpy.ndarray
            ``(N, m)`` float32 band values ``Σ_λ L(λ) S(λ)``: spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) integrated
            against each band, noise-free.

        References
        ----------
        .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
           J. Imaging 4(4):53, 2018, Eq. (5) (the signal part ``s_i = ∫ E(λ) R_i(λ) dλ`` of a band value),
           Eq. (6) (``s = R e``).
        """

    @abstractmethod
    def describe(self) -> dict:
        """JSON-able description: kind, parameters and the quantities a report needs."""

    def band_radiance_and_depth(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0),
                                **kwargs) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`band_radiance` and each ray's hit distance ``(N,)`` float32 (m from ``origin_m``; inf where
        the ray reaches the sky), from the same ray casts.

        This default has no geometry to give (an environment map is light at infinity whose depth is not
        known): the distances are None.  Ray-traced scenes override it.
        """
        return self.band_radiance(directions, sensitivity, origin_m, **kwargs), None

    def colorchecker_patches(self, origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
        """ColorChecker patches visible in the scene (none unless the scene has a chart)."""
        return []

    def sun_disk(self) -> SunDisk | None:
        """The scene's analytic sun (:class:`SunDisk`), or None (a panorama's sun is pixels, not a disk).

        Scenes that return one accept ``sun_disk=False`` in :meth:`spectral_radiance` and
        :meth:`band_radiance` to leave the disk out of ray-traced radiance.
        """
        return None

    # -- helpers for subclasses -----------------------------------------------------------------
    def check_sensitivity(self, sensitivity) -> np.ndarray:
        """``sensitivity`` as float64 ``(m, n)`` on this scene's grid, or a clear error."""
        s = np.asarray(sensitivity, dtype=np.float64)
        if s.ndim == 1:
            s = s[None, :]
        if s.ndim != 2 or s.shape[1] != self.wavelength_nm.size:
            raise ConfigurationError(f"sensitivity must have shape (m, {self.wavelength_nm.size}) on the scene's "
                                     f"wavelength grid, got {np.shape(sensitivity)}")
        if not np.all(np.isfinite(s)):
            raise ConfigurationError("sensitivity contains non-finite values")
        return s

    # -- ground truth ---------------------------------------------------------------------------
    def ground_truth_bands(self, width: int, height: int, sensitivity, rows: int = 64,
                           origin_m=(0.0, 0.0, 0.0)) -> Iterator[tuple[int, np.ndarray]]:
        """Stream the exact band response on a W × H equirectangular grid, ``rows`` rows at a time.

        Yields ``(row_start, block)`` with ``block`` of shape ``(rows, W, m)`` float32 (the last
        block may be shorter).  Never forms the spectral cube, so a 7260 × 3630 six-band response
        needs only the output (or a memory map) plus one block of rays.
        """
        _check_grid(width, height)
        s = self.check_sensitivity(sensitivity)
        if rows < 1:
            raise ConfigurationError(f"rows must be >= 1, got {rows}")
        for r0 in range(0, height, rows):
            r1 = min(height, r0 + rows)
            d = equirect_directions(width, height, r0, r1).reshape(-1, 3)
            yield r0, self.band_radiance(d, s, origin_m).reshape(r1 - r0, width, s.shape[0])

    def ground_truth_spectral(self, width: int, height: int, origin_m=(0.0, 0.0, 0.0), rows: int = 64) -> np.ndarray:
        """Spectral radiance ``(H, W, n)`` float32 on an equirectangular grid (for small grids)."""
        _check_grid(width, height)
        n = self.wavelength_nm.size
        size = width * height * n * 4
        if size > MAX_SPECTRAL_CUBE_BYTES:
            raise ConfigurationError(f"a {width}×{height}×{n} spectral cube needs {size / 2**30:.1f} GiB; use "
                                     "ground_truth_bands() or a smaller grid")
        out = np.empty((height, width, n), dtype=np.float32)
        for r0 in range(0, height, rows):
            r1 = min(height, r0 + rows)
            d = equirect_directions(width, height, r0, r1).reshape(-1, 3)
            out[r0:r1] = self.spectral_radiance(d, origin_m).reshape(r1 - r0, width, n)
        return out

    def ground_truth(self, width: int, height: int, sensitivity=None, origin_m=(0.0, 0.0, 0.0)) -> dict:
        """Equirectangular ground truth at pixel-centre rays.

        Returns ``{"wavelength_nm" (n,), "spectral_radiance" (H, W, n) float32}`` and, when
        ``sensitivity (m, n)`` is given, ``"band_radiance" (H, W, m)`` computed by the exact band
        path (:meth:`ground_truth_bands`).
        """
        out = {"wavelength_nm": self.wavelength_nm.copy(),
               "spectral_radiance": self.ground_truth_spectral(width, height, origin_m)}
        if sensitivity is not None:
            s = self.check_sensitivity(sensitivity)
            bands = np.empty((height, width, s.shape[0]), dtype=np.float32)
            for r0, block in self.ground_truth_bands(width, height, s, origin_m=origin_m):
                bands[r0:r0 + block.shape[0]] = block
            out["band_radiance"] = bands
        return out
