"""The saturated sun recovered, so that the panorama holds the scene's whole light (beyond the paper).

The sun saturates every regular exposure; the HDR merge (Eq. (1)) then keeps the shortest exposure's
value, a lower bound (on a clear day the sun carries ~80 % of the horizontal irradiance).  This module
measures the sun from what a real capture has and writes it into the product:

``nd-bracket``
    The attenuated bracket shot through a neutral-density filter in every direction that holds the sun
    (:mod:`omnispectral.capture.run`).  Per direction and camera the bracket is merged (Eq. (1)); the sun's
    image is found (its energy peak), its band irradiance through the filter is the background-subtracted
    sum ``Σ (I − b) Ω_pixel`` over an aperture of a few sun radii (``Ω_pixel`` from the camera model), and
    its direction is the energy centroid unprojected through the camera model and the head's pose.
    The spectrum follows from the six filtered bands ``ρ = (R ⊙ T) s`` (``T`` the filter's transmittance,
    ``R`` the rig's system matrix of Eq. (6)) by weighted least squares in a daylight basis
    (:func:`daylight_basis`), and the unfiltered band irradiance is ``R s``.
``none``
    No way to recover it: the product says the sun is a lower bound.

The recovered sun is painted into the panorama (:func:`paint_sun`): every pixel within reach of the disk
becomes the sky background around it plus ``coverage × L_sun`` with the disk's exact coverage of each
pixel's solid angle (:func:`omnispectral.imaging.sundisk.equirect_disk_coverage`), so the panorama's
integral over the disk is the measured irradiance, and the pixels are listed in the store's attributes
(``omnispectral.sun.pixels``) as recovered, not measured.

Units: the panorama's (DN/s per band, spectra in DN/s per unit of the system matrix, per sr for radiance).
The sun's angular diameter is the mean 0.533° (it varies by ±1.7 % over the year with the Earth's distance;
the irradiance, which is what is measured, does not depend on it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import colour
import numpy as np
from scipy import ndimage

from omnispectral.imaging.bayer import demosaic
from omnispectral.imaging.geometry import (
    CameraModel,
    equirect_pixel_to_lonlat,
    lonlat_to_equirect_pixel,
    lonlat_to_ray,
    ray_to_lonlat,
)
from omnispectral.imaging.hdr import merge_exposures
from omnispectral.imaging.sundisk import cap_solid_angle_sr, equirect_disk_coverage, pixel_solid_angles_sr
from omnispectral.product.merge import RawSettings, read_bracket
from omnispectral.product.saturation import SATURATION_FRACTION, clipped_mask, saturation_level_dn_s
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.rig import SUN_EXPOSURE_BASE
from omnispectral.spectral.curves import resample_spectra
from omnispectral.spectral.library import daylight_spd, load_filter

__all__ = ["APERTURE_MIN_PX", "APERTURE_RADII", "SUN_DIAMETER_DEG", "SUN_FILE", "SunImage", "best_images",
           "clipped_sun_direction", "daylight_basis", "daylight_prior", "daylight_set", "filter_matrix",
           "fit_spectrum", "measure_sun_image", "merge_sun_bracket", "paint_sun", "recover_sun_nd",
           "refine_clipped_direction", "sun_directions", "sun_from_images", "sun_lower_bound_note",
           "sun_radiance_fields", "sun_summary"]

#: Mean angular diameter of the sun (degrees).
SUN_DIAMETER_DEG = 0.533
#: The aperture that sums the sun's image: this many sun radii, and at least ``APERTURE_MIN_PX`` px.
APERTURE_RADII = 3.0
APERTURE_MIN_PX = 4.0
#: The product's file holding the sun's record.
SUN_FILE = "sun.json"


# ------------------------------------------------------------------------------------------ basis
def daylight_set(wavelength_nm) -> np.ndarray:
    """Daylight and low-sun spectra at unit norm ``(N, n)``: CIE D-series daylight from 4000 K to 25000 K
    (CIE 015:2018) and Planckian radiators from 2000 K to 4000 K (the reddened sun near the horizon)."""
    wl = np.asarray(wavelength_nm, np.float64)
    rows = []
    for cct in np.geomspace(4000.0, 24900.0, 24):
        sd = daylight_spd(float(cct))
        rows.append(resample_spectra(sd.values, sd.wavelengths, wl, outside="edge"))
    for cct in np.linspace(2000.0, 4000.0, 9):
        sd = colour.sd_blackbody(float(cct), colour.SpectralShape(float(wl.min()), float(wl.max()), 1.0))
        rows.append(resample_spectra(sd.values, sd.wavelengths, wl, outside="edge"))
    a = np.array(rows)
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def daylight_basis(wavelength_nm, n_components: int = 4) -> np.ndarray:
    """Principal spectral components ``(n, k)`` of :func:`daylight_set`: the first ``k`` right singular
    vectors (no centring: the mean is the first vector).  Four components reproduce every member to
    < 0.3 % (unit-norm RMS)."""
    _, _, vt = np.linalg.svd(daylight_set(wavelength_nm), full_matrices=False)
    return vt[:n_components].T


def daylight_prior(wavelength_nm, n_components: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation ``(k,)`` of each basis coefficient relative to the first one over
    :func:`daylight_set` (the first: 1 and 0): the shape prior of :func:`fit_spectrum`."""
    basis = daylight_basis(wavelength_nm, n_components)
    c = daylight_set(wavelength_nm) @ basis
    r = c / c[:, :1]
    return r.mean(axis=0), r.std(axis=0)


def fit_spectrum(bands: np.ndarray, band_var: np.ndarray, matrix: np.ndarray, basis: np.ndarray,
                 prior: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Spectrum ``s = B x`` with ``matrix @ s ≈ bands``, by least squares weighted by ``1 / band_var``.

    With a ``prior`` (:func:`daylight_prior`: each coefficient ``x_j ≈ m_j x_0 ± σ_j x_0``) the fit is the
    maximum a posteriori estimate under that Gaussian shape prior, the scale ``x_0`` free (two rounds, the
    prior's width set from the previous round's ``x_0``): it decides what few bands cannot, e.g. the sun
    seen by one camera only.  Returns the spectrum ``(n,)`` and its standard deviation ``(n,)`` (from the
    coefficients' posterior covariance, ``(Aᵀ W A + P)⁻¹``, ``A = matrix @ B``).
    """
    a = matrix @ basis
    w = 1.0 / np.maximum(band_var, 1e-30 + 1e-12 * np.max(band_var))
    normal = a.T @ (a * w[:, None])
    cov = np.linalg.pinv(normal)
    x = cov @ (a.T @ (w * bands))
    for _ in range(2 if prior is not None else 0):
        mean, std = prior
        k = basis.shape[1]
        rows = np.zeros((k - 1, k))
        rows[:, 0] = -mean[1:]
        rows[np.arange(k - 1), np.arange(1, k)] = 1.0
        scale = max(abs(float(x[0])), 1e-30)
        pw = 1.0 / (np.maximum(std[1:], 1e-6) * scale) ** 2
        cov = np.linalg.pinv(normal + rows.T @ (rows * pw[:, None]))
        x = cov @ (a.T @ (w * bands))
    spectrum = basis @ x
    std = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", basis, cov, basis), 0.0))
    return spectrum, std


# ---------------------------------------------------------------------------------- one sun image
@dataclass(frozen=True)
class SunImage:
    """The sun seen by one camera in one direction of the attenuated bracket."""

    direction: int
    camera: str
    centroid_px: tuple[float, float]
    ray_world: np.ndarray
    band_irradiance: np.ndarray  # (3,) through the filter: Σ (I − b) Ω, DN/s · sr
    band_var: np.ndarray  # (3,)
    complete: bool  # the aperture lies inside the frame and nothing in it saturated
    edge_distance_px: float

    def to_dict(self) -> dict:
        lon, lat = ray_to_lonlat(self.ray_world)
        return {"direction": self.direction, "camera": self.camera, "centroid_px": list(self.centroid_px),
                "lon_deg": float(lon), "lat_deg": float(lat), "band_irradiance": self.band_irradiance.tolist(),
                "complete": self.complete, "edge_distance_px": self.edge_distance_px}


def measure_sun_image(radiance: np.ndarray, variance: np.ndarray, saturated: np.ndarray, model: CameraModel,
                      pan_deg: float, tilt_deg: float, direction: int = -1, camera: str = "A",
                      sun_radius_rad: float = math.radians(SUN_DIAMETER_DEG / 2)) -> SunImage | None:
    """Find and measure the sun in an attenuated HDR image ``(H, W, 3)`` (module docstring).

    ``None`` when the image holds no source standing out of its background.
    """
    total = np.nan_to_num(radiance, nan=0.0).sum(axis=2)
    h, w = total.shape
    smooth = ndimage.uniform_filter(total, 3)
    py, px = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    r_sun_px = sun_radius_rad * float(model.fx)
    r_ap = max(APERTURE_RADII * r_sun_px, APERTURE_MIN_PX)
    r_bg = r_ap + max(3.0, r_sun_px)
    y0, y1 = max(0, int(py - r_bg - 2)), min(h, int(py + r_bg + 3))
    x0, x1 = max(0, int(px - r_bg - 2)), min(w, int(px + r_bg + 3))
    yy, xx = np.mgrid[y0:y1, x0:x1]
    win = np.nan_to_num(radiance[y0:y1, x0:x1], nan=0.0).astype(np.float64)
    ring = (np.hypot(yy - py, xx - px) > r_ap + 1.0) & (np.hypot(yy - py, xx - px) <= r_bg)
    if ring.sum() < 8:
        return None
    bg = np.median(win[ring], axis=0)
    noise = 1.4826 * np.median(np.abs(win[ring] - bg), axis=0)
    excess = win - bg
    ap = np.hypot(yy - py, xx - px) <= r_ap
    peak = excess[ap].sum(axis=1).max()
    if not peak > 10.0 * max(float(noise.sum()), 1e-12):
        return None
    # refine the aperture's centre on the energy centroid, then measure there
    for _ in range(2):
        wts = np.clip(excess.sum(axis=2), 0.0, None) * ap
        cy, cx = float((wts * yy).sum() / wts.sum()), float((wts * xx).sum() / wts.sum())
        ap = np.hypot(yy - cy, xx - cx) <= r_ap
    omega = np.nan_to_num(pixel_solid_angles_sr(model, xx, yy), nan=0.0)
    e = (excess * omega[..., None])[ap].sum(axis=0)
    var = (np.nan_to_num(variance[y0:y1, x0:x1], nan=0.0) * omega[..., None] ** 2)[ap].sum(axis=0) \
        + (noise ** 2) * float((omega[ap] ** 2).sum()) * 2.0
    edge = float(min(cx, cy, w - 1 - cx, h - 1 - cy))
    complete = edge >= r_ap + 1.0 and not bool(saturated[y0:y1, x0:x1][ap].any())
    ray, _ = model.pixel_to_world(np.array([cx, cy]), pan_deg, tilt_deg)
    return SunImage(direction, camera, (cx, cy), ray / np.linalg.norm(ray), e, var, complete, edge)


# ---------------------------------------------------------------------------------- the session
def sun_directions(session) -> dict[int, dict[str, list[int]]]:
    """Directions holding a sun bracket: ``{direction: {camera: [exposure indices]}}`` from the journal."""
    out: dict[int, dict[str, list[int]]] = {}
    for (d, c, k), rec in session.completed().items():
        if k >= SUN_EXPOSURE_BASE and rec.get("filter"):
            out.setdefault(d, {}).setdefault(c, []).append(k)
    return {d: {c: sorted(ks) for c, ks in cams.items()} for d, cams in sorted(out.items())}


def merge_sun_bracket(session, direction: int, camera: str, indices: list[int], raw: RawSettings | None = None):
    """HDR merge (Eq. (1), inverse-variance weight) of one camera's attenuated bracket (frames read by
    :func:`~omnispectral.product.merge.read_bracket`); returns the merge result, the reported pose and the
    filter's name."""
    b = read_bracket(session, direction, camera, indices, raw)
    result = merge_exposures(b.frames, b.times, b.bit_depth, weight="noise")
    if b.pattern is not None:  # a raw mosaic: merged first, then demosaiced once
        rad = demosaic(np.squeeze(result.radiance).astype(np.float32), b.pattern, "bilinear")
        var = demosaic(np.squeeze(result.variance).astype(np.float32), b.pattern, "bilinear")
        sat = np.repeat(np.squeeze(result.saturated)[..., None], 3, axis=2)
        result = SimpleNamespace(radiance=rad, variance=var, saturated=sat)
    return result, b.pose, b.filter_name


def filter_matrix(matrix: np.ndarray, wavelength_nm: np.ndarray, filter_name: str) -> np.ndarray:
    """The system matrix seen through a filter: ``R ⊙ T`` (``T`` resampled to the matrix's wavelengths)."""
    t = load_filter(filter_name).resample(np.asarray(wavelength_nm, np.float64)).values[0]
    return matrix * np.clip(t, 0.0, None)[None, :]


def best_images(images: list[SunImage]) -> dict[str, list[SunImage]]:
    """Per camera, the complete sun images (aperture inside the frame, nothing saturated), else none."""
    out: dict[str, list[SunImage]] = {}
    for im in images:
        if im.complete:
            out.setdefault(im.camera, []).append(im)
    return out


def sun_from_images(images: list[SunImage], system, filter_name: str, band_names: list[str],
                    sun_radius_rad: float) -> dict | None:
    """The sun's record (direction, band radiance, spectrum with uncertainties) from its measured images."""
    per_camera = best_images(images)
    if "A" not in per_camera:
        return None
    cams = [c for c in ("A", "B") if c in per_camera and 3 * ("AB".index(c)) < len(band_names)]
    bands, var, rows = [], [], []
    for c in cams:
        ims = per_camera[c]
        bands.append(np.mean([im.band_irradiance for im in ims], axis=0))
        var.append(np.mean([im.band_var for im in ims], axis=0) / len(ims))
        i = "AB".index(c)
        rows.extend(range(3 * i, 3 * i + 3))
    bands, var = np.concatenate(bands), np.concatenate(var)
    wl = np.asarray(system.wavelength_nm, np.float64)
    m_nd = filter_matrix(np.asarray(system.matrix, np.float64), wl, filter_name)[rows]
    # four daylight components under the daylight shape prior: it decides what one camera's three bands
    # cannot when the other camera did not see the sun (docs/benchmarks.md, "The sun across the day")
    n_components = 4
    spectrum_irr, std_irr = fit_spectrum(bands, var, m_nd, daylight_basis(wl, n_components),
                                         daylight_prior(wl, n_components))
    band_irr = np.asarray(system.matrix, np.float64) @ spectrum_irr
    # every image of camera A (the reference geometry) votes for the direction; B's agree at infinity
    rays = np.array([im.ray_world for im in per_camera["A"]])
    ray = rays.mean(axis=0)
    ray /= np.linalg.norm(ray)
    spread = float(np.degrees(np.max(np.arccos(np.clip(rays @ ray, -1, 1))))) if len(rays) > 1 else 0.0
    lon, lat = ray_to_lonlat(ray)
    fit_residual = float(np.linalg.norm(m_nd @ spectrum_irr - bands) / max(np.linalg.norm(bands), 1e-30))
    band_std = np.sqrt(np.asarray(system.matrix) ** 2 @ std_irr ** 2)
    return {"lon_deg": float(lon), "lat_deg": float(lat), "direction_spread_deg": spread,
            **sun_radiance_fields(band_names, band_irr, band_std, wl, spectrum_irr, std_irr, sun_radius_rad),
            "filter": filter_name,
            "measured_bands": [band_names[r] for r in rows], "fit_relative_residual": fit_residual,
            "daylight_components": n_components,
            **({"note": f"only camera {cams[0]} saw the sun whole in the attenuated bracket: the other camera's "
                        f"bands of the sun are predicted through the daylight basis"} if len(cams) < 2
               and len(band_names) > 3 else {}),
            "images": [im.to_dict() for im in images]}


def sun_radiance_fields(band_names: list[str], band_irradiance, band_irradiance_std, wavelength_nm,
                        spectral_irradiance, spectral_irradiance_std,
                        sun_radius_rad: float = math.radians(SUN_DIAMETER_DEG / 2)) -> dict:
    """The fields every method's sun record shares: the disk's size, and its band and spectral irradiance at
    normal incidence turned into the disk's mean radiance (``/ Ω_sun``), with standard deviations."""
    omega = cap_solid_angle_sr(sun_radius_rad)
    e, e_std = np.asarray(band_irradiance, float), np.asarray(band_irradiance_std, float)
    s, s_std = np.asarray(spectral_irradiance, float), np.asarray(spectral_irradiance_std, float)
    return {"angular_diameter_deg": math.degrees(2 * sun_radius_rad), "solid_angle_sr": omega,
            "band_names": list(band_names), "band_irradiance": e.tolist(), "band_irradiance_std": e_std.tolist(),
            "band_radiance": (e / omega).tolist(), "band_radiance_std": (e_std / omega).tolist(),
            "wavelength_nm": np.asarray(wavelength_nm, float).tolist(), "spectral_radiance": (s / omega).tolist(),
            "spectral_radiance_std": (s_std / omega).tolist()}


def recover_sun_nd(session, models: dict[str, CameraModel], system, band_names: list[str],
                   progress: ProgressCallback | None = None) -> dict | None:
    """The sun from the session's attenuated brackets (module docstring), or ``None`` without any;
    ``progress("sun", done, total)`` over the bracket's (direction, camera) pairs."""
    found = sun_directions(session)
    if not found:
        return None
    rig = session.rig()
    radius = math.radians(SUN_DIAMETER_DEG / 2)
    images, filt = [], None
    todo = [(d, c, ks) for d, cams in found.items() for c, ks in cams.items() if c in models]
    for i, (d, c, ks) in enumerate(todo):
        res, (pan, tilt), f = merge_sun_bracket(session, d, c, ks, RawSettings.of(session, rig, c))
        filt = filt or f
        im = measure_sun_image(res.radiance, res.variance, res.saturated, models[c], pan, tilt, d, c, radius)
        if im is not None:
            images.append(im)
        report_progress(progress, "sun", i + 1, len(todo))
    if filt is None:
        return None
    record = sun_from_images(images, system, filt, band_names, radius)
    if record is None:
        return {"method": "nd-bracket", "recovered": False, "images": [im.to_dict() for im in images],
                "note": "the attenuated bracket shows no complete image of the sun in camera A"}
    return {"method": "nd-bracket", "recovered": True, **record}


# ------------------------------------------------------------------------- without a sun bracket
def clipped_sun_direction(store) -> dict | None:
    """Where the panorama's clipped sun is: the centroid of the largest group of level-0 pixels at the
    shortest exposure's clipping level (:mod:`omnispectral.product.saturation`), as ``lon_deg``, ``lat_deg``,
    the group's size and its window (``cols`` unwrapped: ``[c0, c1)`` may pass the right edge, read modulo the
width); ``None`` when nothing clipped.  For the methods without an attenuated
    image; its accuracy is a fraction of a pixel of the panorama (the clipped group is the disk blurred by
    the mosaic's resampling)."""
    level = saturation_level_dn_s(store.attrs())
    if level is None:
        return None
    h, w = store.shapes[0]
    found = []
    step = max(store.tile, 256)
    for r0 in range(0, h, step):  # streamed: a full-scale panorama is not read whole
        block = store.read(0, slice(r0, min(h, r0 + step)))
        mask = clipped_mask(store, 0, block, level, (r0, 0))
        rows, cols = np.nonzero(mask)
        found.extend(zip((rows + r0).tolist(), cols.tolist(), strict=True))
    if not found:
        return None
    grid = np.zeros((h, w), bool)
    rr, cc = np.array(found).T
    grid[rr, cc] = True
    empty = np.flatnonzero(~grid.any(axis=0))
    shift = int(empty[0]) if empty.size else 0
    grid = np.roll(grid, -shift, axis=1)  # start at a column without clipped pixels: no group is cut by the seam
    labels, n = ndimage.label(grid, structure=np.ones((3, 3)))
    sizes = ndimage.sum(grid, labels, range(1, n + 1))
    pick = labels == (int(np.argmax(sizes)) + 1)
    rows, cols = np.nonzero(pick)
    cols = cols + shift  # unwrapped: may pass the right edge, use modulo the width
    lon, lat = equirect_pixel_to_lonlat(cols % w, rows, w, h)
    rays = lonlat_to_ray(lon, lat)
    centre = rays.mean(axis=0)
    lon0, lat0 = ray_to_lonlat(centre / np.linalg.norm(centre))
    return {"lon_deg": float(lon0), "lat_deg": float(lat0), "n_clipped_px": int(pick.sum()),
            "rows": [int(rows.min()), int(rows.max()) + 1], "cols": [int(cols.min()), int(cols.max()) + 1]}


def refine_clipped_direction(clipped: dict, merged, level_dn_s: float) -> dict:
    """``clipped`` (:func:`clipped_sun_direction`) with its direction from camera A's merged images instead of
    the panorama: in every direction whose image holds a clipped group away from the frame's edges, the
    group's centroid through camera A's model; their mean.  The mosaic's resampling blurs the panorama's
    clipped group; the native images do not, and several directions average their pixel phases (on the small
    preset 0.011° from the true sun with 12 directions, 0.040° with two, against 0.060-0.069° from the
    panorama).  Unchanged when no image qualifies."""
    centre = lonlat_to_ray(clipped["lon_deg"], clipped["lat_deg"])
    rays = []
    for src in merged.sources():
        if src.camera != "A":
            continue
        ray = _clipped_centroid_ray(src, merged, level_dn_s)
        if ray is not None and float(ray @ centre) > math.cos(math.radians(2.0)):
            rays.append(ray)
    if not rays:
        return clipped
    mean = np.mean(rays, axis=0)
    lon, lat = ray_to_lonlat(mean / np.linalg.norm(mean))
    return {**clipped, "lon_deg": float(lon), "lat_deg": float(lat),
            "direction_from": f"camera A's merged images ({len(rays)} directions)"}


def _clipped_centroid_ray(src, merged, level_dn_s: float) -> np.ndarray | None:
    """The world ray of the largest clipped group's centroid in one merged image, or ``None`` (nothing clipped,
    or the group touches the frame's edge)."""
    img = src.read()
    clip = np.nan_to_num(img, nan=0.0).max(axis=2) >= SATURATION_FRACTION * level_dn_s
    if not clip.any():
        return None
    labels, n = ndimage.label(clip, structure=np.ones((3, 3)))
    sizes = ndimage.sum(clip, labels, range(1, n + 1))
    rows, cols = np.nonzero(labels == int(np.argmax(sizes)) + 1)
    h, w = clip.shape
    if rows.min() == 0 or cols.min() == 0 or rows.max() == h - 1 or cols.max() == w - 1:
        return None
    d = next(x for x in merged.directions if int(x["index"]) == src.direction)
    ray, _ = merged.cameras["A"].pixel_to_world(np.array([cols.mean(), rows.mean()]), float(d["pan_deg"]),
                                                float(d["tilt_deg"]))
    return ray / np.linalg.norm(ray)


# ----------------------------------------------------------------------------------- painting
def paint_sun(store, sun: dict, margin_px: int = 2) -> dict:
    """Write the recovered sun into level 0 of the panorama and rebuild the pyramid above it (module
    docstring); returns what was painted (pixel window and mask, for the store's attributes)."""
    h, w = store.shapes[0]
    radius_deg = sun["angular_diameter_deg"] / 2.0
    col, row = lonlat_to_equirect_pixel(sun["lon_deg"], sun["lat_deg"], w, h)
    px_deg = 360.0 / w
    reach = radius_deg / (px_deg * max(math.cos(math.radians(abs(sun["lat_deg"]))), 0.05)) + margin_px + 1
    reach_r = radius_deg / px_deg + margin_px + 1
    r0, r1 = max(0, math.floor(row - reach_r - 4)), min(h, math.ceil(row + reach_r + 5))
    c0, c1 = math.floor(col - reach - 4), math.ceil(col + reach + 5)
    cols = np.arange(c0, c1) % w
    window = store.read(0, slice(r0, r1))[:, cols].astype(np.float64)
    rr, cc = np.mgrid[r0:r1, c0:c1]
    lon, lat = equirect_pixel_to_lonlat(cc, rr, w, h)
    ang = np.degrees(np.arccos(np.clip(lonlat_to_ray(lon, lat) @ lonlat_to_ray(sun["lon_deg"], sun["lat_deg"]), -1, 1)))
    region = ang <= radius_deg + margin_px * px_deg
    ring = (ang > radius_deg + (margin_px + 1) * px_deg) & (ang <= radius_deg + (margin_px + 4) * px_deg)
    ring &= np.isfinite(window).all(axis=2)
    bg = np.median(window[ring], axis=0) if ring.any() else np.zeros(window.shape[2])
    rows_c, cols_c, frac = equirect_disk_coverage(sun["lon_deg"], sun["lat_deg"], radius_deg, w, h)
    coverage = np.zeros(region.shape)
    where = {int(c): j for j, c in enumerate(cols)}  # level-0 column -> window column
    for r, c, f in zip(rows_c, cols_c, frac, strict=True):
        j = where.get(int(c))
        if 0 <= int(r) - r0 < coverage.shape[0] and j is not None:
            coverage[int(r) - r0, j] += f
    region |= coverage > 0
    radiance = np.asarray(sun["band_radiance"], np.float64)
    painted = bg[None, None, :] + coverage[..., None] * radiance[None, None, :]
    window[region] = painted[region]
    _write_level0_window(store, r0, cols, window)
    quality = store.read_quality(slice(r0, r1))[:, cols] if store.has_quality() else None
    if quality is not None and quality.shape[2] > 2:  # the quality layer's sun flag: 1 where painted
        store.write_quality_layer(2, r0, cols, np.where(region, 1.0, quality[..., 2]))
    t = store.tile  # the level-0 chunks rewritten in place: their markers' checksums follow
    store.refresh_checksums(0, {(ty, int(c) // t) for ty in range(r0 // t, (r1 - 1) // t + 1) for c in cols})
    return {"row0": r0, "col0": int(c0 % w), "rows": int(r1 - r0), "cols": int(c1 - c0),
            "mask": region.astype(int).tolist(), "n_pixels": int(region.sum()),
            "background": bg.tolist()}


def _write_level0_window(store, r0: int, cols: np.ndarray, window: np.ndarray) -> None:
    """Write a window (possibly wrapping in longitude) into level 0 and rebuild the chunks above it."""
    arr = store.array(0, mode="r+")
    runs = np.split(np.arange(len(cols)), np.flatnonzero(np.diff(cols) != 1) + 1)
    touched = set()
    for run in runs:
        c0, c1 = int(cols[run[0]]), int(cols[run[-1]]) + 1
        arr[r0:r0 + window.shape[0], c0:c1, :] = window[:, run[0]:run[-1] + 1].astype(np.float32)
        touched.add((r0, r0 + window.shape[0], c0, c1))
    for level in range(1, len(store.shapes)):
        f = 2 ** level
        chunks = set()
        for a0, a1, b0, b1 in touched:
            for ty in range(a0 // f // store.tile, (a1 - 1) // f // store.tile + 1):
                for tx in range(b0 // f // store.tile, (b1 - 1) // f // store.tile + 1):
                    chunks.add((ty, tx))
        for ty, tx in sorted(chunks):
            store.write_chunk(level, ty, tx, store.downsample_chunk(level, ty, tx))


def sun_summary(sun: dict) -> dict:
    """The sun's record without its per-wavelength arrays and pixel mask (for ``product.json``)."""
    keep = ("method", "recovered", "model_estimate", "note", "lon_deg", "lat_deg", "direction_spread_deg",
            "angular_diameter_deg", "band_names", "band_irradiance", "band_radiance", "band_radiance_std", "filter",
            "fit_relative_residual", "reference")
    out = {k: sun[k] for k in keep if k in sun}
    if "pixels" in sun:
        out["n_pixels_painted"] = sun["pixels"]["n_pixels"]
    return {**out, "file": SUN_FILE}


def sun_lower_bound_note() -> str:
    """What every consumer says when the sun could not be recovered."""
    return ("the sun is saturated in every exposure and was not recovered: its pixels hold a lower bound "
            "(the panorama misses most of the direct sunlight)")
