"""The simulated rig: render raw frames of a spectral scene through the rig's own geometry and sensor model.

Every sensor pixel's ray comes from the same :class:`~omnispectral.imaging.geometry.CameraModel` the
processing uses (lens distortion, portrait roll, head rotation, camera B's misalignment and
baseline), the scene's spectral radiance is integrated against the camera's sensitivity × filter
(``MultibandSystem.matrix``), scaled by the exposure, and turned into 12-bit codes with the CMV2000
noise model (Poisson shot noise — Gaussian above 30 e⁻ —, 13 e⁻ read noise, quantisation,
saturation).  Frames go through the same session writer and capture loop as real hardware
(:func:`~omnispectral.capture.run.run_capture` on simulated devices with a fake clock starting at the
scene's time of day, so journal timestamps follow the timing model).

Units.  ``electrons_per_unit`` converts the scene's band radiance (scene units · nm) into
photo-electrons per second; it is chosen so that the scene's bright diffuse surfaces (99.5th
percentile of the brightest band, sampled on a coarse grid) reach 80 % of full well at the
bracket's geometric-mean exposure.  The ground truth is stored in DN per second of exposure — the
unit of the HDR merge — so a processed product compares pixel by pixel
(:func:`omnispectral.sim.truth.write_ground_truth`).
"""

from __future__ import annotations

import datetime as _dt
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy import ndimage

from omnispectral.capture.calviews import DEFAULT_N_VIEWS, calibration_folder
from omnispectral.capture.plan import make_plan
from omnispectral.capture.run import RetryPolicy, run_capture
from omnispectral.capture.session import Session
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.bayer import mosaic
from omnispectral.imaging.geometry import (
    CameraModel,
    equirect_pixel_to_lonlat,
    lonlat_to_ray,
)
from omnispectral.imaging.sundisk import disk_samples, n_radial_for_pixel, splat_camera
from omnispectral.io import jsonable
from omnispectral.limits import check_memory, memory_budget, sensor_memory_bytes
from omnispectral.locking import directory_lock
from omnispectral.progress import ProgressCallback
from omnispectral.rig import CameraSpec, Rig, rig_with_camera_settings
from omnispectral.sim.antialias import (
    REFINE_RAYS_PER_SIDE,
    differs_from_neighbours,
    pixels_to_refine,
    refined_mean,
    subpixel_offsets,
    with_neighbours,
)
from omnispectral.sim.boardviews import (
    DEFAULT_BOARD,
    DEFAULT_SQUARE_MM,
    MIN_SQUARE_PX,
    board_rng,
    board_views_complete,
    expose_for_board,
    next_board_scene,
    render_board_views,
    square_px,
)
from omnispectral.sim.devices import (
    FakeClock,
    SimulatedCamera,
    SimulatedFilterChanger,
    SimulatedHead,
    resume_simulated_devices,
)
from omnispectral.sim.scenes.base import SunDisk, footprint_kwargs, scene_sun_disk
from omnispectral.sim.scenes.chessboard import ChessboardScene
from omnispectral.sim.truth import default_ground_truth_width, write_ground_truth
from omnispectral.spectral.library import load_filter
from omnispectral.spectral.noise import SensorNoiseModel
from omnispectral.spectral.system import MultibandSystem

__all__ = ["DEFAULT_MOUNTING_ERROR_DEG", "FILTER_VEIL_FRACTION", "FILTER_VEIL_SIGMA_DEG",
           "SIMULATE_BYTES_PER_SENSOR_PX", "DarkRenderer", "RigRenderer", "SimulatedBoard", "bayer_rig",
           "board_renderer", "calibrate_exposure", "calibration_views_folder", "dark_signal_map", "filter_veil",
           "perturbed_model", "raw_frame", "raw_metadata", "record_simulated_calibration_views", "rgb_rig", "sample_dn",
           "simulate_board_views", "simulate_session", "simulated_board_cameras", "simulated_dark_cameras",
           "true_mounting_error_deg"]

#: Peak working memory of :func:`simulate_session` per pixel of the rig's largest sensor (bytes): rays of the
#: supersampled pixels, their world directions, radiance and electrons of one frame.  Measured as the peak RSS
#: above the interpreter's: 2580 B/px on 256 × 136 sensors, 2010 B/px on 768 × 408 (supersample 2).
SIMULATE_BYTES_PER_SENSOR_PX = 2600

#: Largest error (deg, per axis) of camera B's true mounting against the rig file's in a simulation.
DEFAULT_MOUNTING_ERROR_DEG = 0.5

#: Veiling glare added by a filter in front of the lens: this fraction of the light the filter passes is
#: scattered (haze of the gelatin, reflections between filter and front element) into a halo around its
#: source; the rest forms the image.  Our modelling choice (0.5 % in a Gaussian of 2°), not a measurement
#: of the Wratten 96 nor a datasheet value (veiling glare of an optical system is defined and measured in
#: ISO 9358:1994); it exists so that processing, which does not know it, must measure around it.
FILTER_VEIL_FRACTION = 0.005
#: Standard deviation (deg) of the filter's Gaussian veil around each source.
FILTER_VEIL_SIGMA_DEG = 2.0


def true_mounting_error_deg(seed: int, max_error_deg: float = DEFAULT_MOUNTING_ERROR_DEG) -> tuple[float, float, float]:
    """The (yaw, pitch, roll) by which a simulated camera B really differs from the rig file (uniform, per seed).

    A real rig's camera B is never mounted exactly as its rig file says; the simulator renders B with
    this unknown error so that processing has to estimate B's mounting (``product.rigfit``,
    ``product.boardfit``) and is tested against a truth it cannot read (only ``ground_truth/ground_truth.json``
    records it).
    """
    rng = np.random.default_rng([int(seed), 0x4D4F554E])
    return tuple(float(x) for x in rng.uniform(-max_error_deg, max_error_deg, 3))


def perturbed_model(model: CameraModel, error_deg: tuple[float, float, float]) -> CameraModel:
    """``model`` with ``error_deg`` added to its mounting's misalignment (yaw, pitch, roll)."""

    return replace(model, mounting=model.mounting.with_misalignment_change(error_deg))


def sample_dn(electrons: np.ndarray, noise: SensorNoiseModel, rng: np.random.Generator,
              black_level_dn: float = 0.0) -> np.ndarray:
    """Raw codes of mean photo-electron counts: Poisson shot noise (normal approximation above 30 e⁻),
    Gaussian read noise, the camera's black level added, rounding to DN, clipping at full scale.  float32
    throughout; returns uint16."""
    mu = np.maximum(electrons, 0, dtype=np.float32)
    e = rng.standard_normal(mu.shape, dtype=np.float32)
    small = mu < 30
    shot = np.sqrt(mu) * e
    if small.any():
        mu_small = mu[small]
        shot[small] = rng.poisson(mu_small).astype(np.float32) - mu_small
    read = rng.standard_normal(mu.shape, dtype=np.float32) * np.float32(noise.read_noise_e)
    dn = (mu + shot + read) * np.float32(1.0 / noise.gain_e_per_dn)
    if black_level_dn:
        dn += np.float32(black_level_dn)
    return np.clip(np.rint(dn), 0, noise.max_dn).astype(np.uint16)


def dark_signal_map(cam: CameraSpec, shape: tuple[int, ...]) -> np.ndarray:
    """Relative dark signal of every pixel (mean 1): a log-normal spread of relative standard deviation
    ``cam.dark_signal_nonuniformity`` (its long tail: hot pixels).  A property of the sensor, so it is drawn
    from the camera's name and model, not from a capture's seed: the dark frames and the scene frames of
    one simulated camera share it, as a real sensor's do."""
    if cam.dark_signal_nonuniformity <= 0:
        return np.ones(shape, np.float32)
    sigma2 = np.log1p(cam.dark_signal_nonuniformity ** 2)
    rng = np.random.default_rng([*cam.name.encode(), *cam.model.encode()[:16], 0x44534E55])
    return rng.lognormal(-sigma2 / 2, np.sqrt(sigma2), shape).astype(np.float32)


def raw_frame(cam: CameraSpec, electrons_per_s: np.ndarray, exposure_s: float, rng: np.random.Generator | None,
              dark_map: np.ndarray | None = None) -> np.ndarray:
    """What camera ``cam`` outputs for ``(H, W, 3)`` photo-electrons per second: the Bayer mosaic of a raw camera
    (``cam.raw``) or the three channels, plus the dark signal, noise (``rng``; None = noise-free) and black level."""
    electrons = electrons_per_s * np.float32(exposure_s)
    if cam.raw is not None:
        electrons = mosaic(electrons, cam.raw.cfa_pattern)
    if cam.dark_current_e_s > 0:
        dmap = dark_map if dark_map is not None else dark_signal_map(cam, electrons.shape)
        electrons = electrons + dmap * np.float32(cam.dark_current_e_s * exposure_s)
    noise = cam.noise_model()
    if rng is None:
        return np.clip(np.rint(electrons / noise.gain_e_per_dn + cam.black_level_dn), 0,
                       noise.max_dn).astype(np.uint16)
    return sample_dn(electrons, noise, rng, cam.black_level_dn)


def raw_metadata(cam: CameraSpec) -> dict:
    """What a camera reports about its raw frames (as the GenICam driver does): CFA layout and black level."""
    out = {"cfa_pattern": cam.raw.cfa_pattern} if cam.raw is not None else {}
    if cam.black_level_dn:
        out["black_level"] = cam.black_level_dn
    return out


@dataclass
class DarkRenderer:
    """Dark frames of the simulated rig (lens capped): dark signal, noise and black level, no light.

    Repeated dark frames at one exposure must have independent noise (they are averaged), so the noise
    comes from one stream of ``seed`` advanced frame by frame, not from the camera's per-frame stream
    (which depends only on direction and exposure, for resumable scene captures)."""

    rig: Rig
    noise: bool = True
    seed: int = 0
    _rng: np.random.Generator = field(init=False)

    def __post_init__(self):
        self._rng = np.random.default_rng([int(self.seed), 0x4441524B])

    def __call__(self, camera: str, pan_deg: float, tilt_deg: float, exposure_s: float,
                 rng: np.random.Generator, filter_name: str | None = None) -> np.ndarray:
        cam = self.rig.cameras[camera]  # a filter in front of a capped lens changes nothing
        zeros = np.zeros((cam.height_px, cam.width_px, 3), np.float32)
        return raw_frame(cam, zeros, exposure_s, self._rng if self.noise else None)


@dataclass
class RigRenderer:
    """Renders raw frames of ``scene`` for every camera of ``rig`` (the simulated cameras' ``render``).

    Parameters
    ----------
    rig : Rig
        The rig: cameras (geometry, sensitivity × filter, noise, bit depth), mounting, bracket.
    scene : Scene
        The spectral scene (its ``wavelength_nm`` grid and :meth:`~omnispectral.sim.scenes.base.Scene.band_radiance`).
    noise : bool
        Draw shot and read noise (else the expected codes, rounded).
    electrons_per_unit : float, optional
        Photo-electrons per second per unit of band radiance (scene units · nm); default
        :func:`calibrate_exposure` (the scene's bright diffuse surfaces at 80 % of full well at the bracket's
        geometric-mean exposure).
    b_mounting_error_deg : tuple of float
        Camera B's true ``(yaw, pitch, roll)`` error against the rig file (deg), unknown to processing.
    supersample : int
        Rays per pixel side (a pixel integrates the light over its area).
    refine_per_side : int
        Rays per pixel side where the first ``supersample²`` disagree (an edge crosses the pixel,
        :mod:`omnispectral.sim.antialias`); 0 or ``≤ supersample``: never.

    Attributes
    ----------
    system : MultibandSystem
        The rig's bands on the scene's wavelength grid (sensitivity × filter × Δλ).
    models : dict of str to CameraModel
        The cameras' geometric models (camera B with its mounting error).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eq. (5) (band value = spectral radiance integrated against the band's
       sensitivity, plus noise), Eq. (6), Sec. 3, Fig. 2 (the two cameras on the rotating table).
    .. [2] EMVA Standard 1288, "Standard for Characterization of Image Sensors and Cameras" (the linear camera
       model of the noise: shot noise, read noise, quantisation, saturation).
    """

    rig: Rig
    scene: object
    noise: bool = True
    electrons_per_unit: float | None = None
    #: camera B's true mounting error against the rig file (see :func:`true_mounting_error_deg`)
    b_mounting_error_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    #: rays per pixel side: a pixel integrates the light over its area (box filter, 100 % fill factor)
    #: instead of sampling its centre, which would alias edges and bias sub-pixel registration
    supersample: int = 2
    #: rays per pixel side in the pixels an edge crosses (:mod:`omnispectral.sim.antialias`)
    refine_per_side: int = REFINE_RAYS_PER_SIDE
    system: MultibandSystem = field(init=False)
    models: dict = field(init=False)
    _rays: dict = field(init=False, default_factory=dict)
    _last: dict = field(init=False, default_factory=dict)
    _filters: dict = field(init=False, default_factory=dict)
    _sun_samples: dict = field(init=False, default_factory=dict)

    def __post_init__(self):
        self.system = self.rig.system(np.asarray(self.scene.wavelength_nm))
        self.models = {c: self.rig.camera_model(c) for c in self.rig.camera_names}
        if "B" in self.models:
            self.models["B"] = perturbed_model(self.models["B"], self.b_mounting_error_deg)
        if self.electrons_per_unit is None:
            self.electrons_per_unit = calibrate_exposure(self.rig, self.scene, self.system)

    def set_scene(self, scene) -> None:
        """Render ``scene`` from now on (same cameras, rays and exposure scale; the frame cache is dropped)."""
        self.scene = scene
        self._last.clear()
        self._sun_samples.clear()

    def reuse_rays(self, other: RigRenderer) -> bool:
        """Take ``other``'s cached camera rays when its cameras' models and supersampling are this renderer's
        (the rays depend on nothing else); returns whether they were taken."""
        same = other.supersample == self.supersample and set(other.models) == set(self.models) and all(
            other.models[c].to_dict() == self.models[c].to_dict() for c in self.models)
        if same:
            self._rays = other._rays
        return same

    def filter_transmittance(self, filter_name: str) -> np.ndarray:
        """``(n,)`` transmittance of a filter (:func:`~omnispectral.spectral.library.load_filter`) on the scene's
        wavelength grid (linear interpolation; a filter that does not cover the grid is refused)."""
        if filter_name not in self._filters:
            wl = np.asarray(self.scene.wavelength_nm, np.float64)
            self._filters[filter_name] = load_filter(filter_name).resample(wl).values[0]
        return self._filters[filter_name]

    def band_matrix(self, camera: str, filter_name: str | None = None) -> np.ndarray:
        """(3, n) sensitivity × filter × Δλ of one camera; with ``filter_name`` also × that filter's
        transmittance (a filter held in front of the lens, e.g. the sun bracket's neutral density)."""
        i = self.rig.camera_names.index(camera)
        matrix = self.system.matrix[3 * i:3 * i + 3]
        if filter_name is None:
            return matrix
        return matrix * self.filter_transmittance(filter_name)[None, :]

    def camera_rays(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """Unit camera-frame rays (H*W*s², 3) of ``s × s`` points spread evenly over every pixel's area
        (``s`` = :attr:`supersample`; pixel-major order) and their validity (cached)."""
        if camera not in self._rays:
            m = self.models[camera]
            sub = subpixel_offsets(self.supersample)
            v, u, dv, du = np.meshgrid(np.arange(m.height), np.arange(m.width), sub, sub, indexing="ij")
            px = np.stack([(u + du).ravel(), (v + dv).ravel()], axis=-1).astype(np.float64)
            rays, valid = m.unproject(px)
            self._rays[camera] = (np.nan_to_num(rays).astype(np.float32), valid)
        return self._rays[camera]

    def ray_spread_rad(self, camera: str) -> np.ndarray:
        """``(H*W*s²,)`` float32, in :meth:`camera_rays`' order: the angular side of the part of its pixel each
        ray stands for, ``sqrt(α_x α_y) / s`` with ``α_x``, ``α_y`` the angles from the pixel's centre ray to its
        right and lower neighbours' (a texture finer than the rays is filtered over it,
        :attr:`omnispectral.sim.scenes.base.Scene.ray_footprint`; cached)."""
        key = ("spread", camera)
        if key not in self._rays:
            m = self.models[camera]
            s = max(1, int(self.supersample))
            v, u = np.meshgrid(np.arange(m.height, dtype=np.float64), np.arange(m.width, dtype=np.float64),
                               indexing="ij")
            centre = m.unproject(np.stack([u.ravel(), v.ravel()], axis=-1))[0]
            across = [m.unproject(np.stack([(u + du).ravel(), (v + dv).ravel()], axis=-1))[0]
                      for du, dv in ((1.0, 0.0), (0.0, 1.0))]
            angle = [np.arccos(np.clip(np.einsum("ij,ij->i", centre, x), -1.0, 1.0)) for x in across]
            spread = np.nan_to_num(np.sqrt(angle[0] * angle[1]) / s)
            self._rays[key] = np.repeat(spread.astype(np.float32), s * s)
        return self._rays[key]

    def pixel_valid(self, camera: str) -> np.ndarray:
        """``(H, W)``: pixels all of whose area has rays (inside the lens model's monotonic region)."""
        m = self.models[camera]
        s2 = max(1, int(self.supersample)) ** 2
        return self.camera_rays(camera)[1].reshape(m.height, m.width, s2).all(axis=2)

    def electrons_per_second(self, camera: str, pan_deg: float, tilt_deg: float,
                             filter_name: str | None = None) -> np.ndarray:
        """Noise-free photo-electrons per second of each pixel, ``(H, W, 3)`` float32 (cached per direction and filter).

        The scene's rays give each pixel its mean radiance over ``supersample²`` points; a scene's
        analytic sun (:meth:`~omnispectral.sim.scenes.base.Scene.sun_disk`) is left out of them and
        added exactly (:meth:`sun_image`).  With ``filter_name`` the bands are × the filter's
        transmittance and the filter's veil (:func:`filter_veil`) spreads part of the light.
        """
        key = (pan_deg, tilt_deg, filter_name)
        if self._last.get(camera, (None,))[0] == key:
            return self._last[camera][1]
        m = self.models[camera]
        rays, valid = self.camera_rays(camera)
        world = rays @ m.camera_to_world(pan_deg, tilt_deg).T
        origin_m = m.camera_center_mm(pan_deg, tilt_deg) / 1000.0
        matrix = self.band_matrix(camera, filter_name)
        sun = scene_sun_disk(self.scene)
        no_disk = {"sun_disk": False} if sun is not None else {}
        bands = np.zeros((rays.shape[0], 3), np.float32)
        if valid.any():
            spread = self.ray_spread_rad(camera)[valid] if getattr(self.scene, "ray_footprint", False) else None
            bands[valid] = self.scene.band_radiance(world[valid], matrix, origin_m=origin_m, **no_disk,
                                                    **footprint_kwargs(self.scene, spread))
        s2 = max(1, int(self.supersample)) ** 2
        samples = bands.reshape(m.height * m.width, s2, 3)
        img = samples.mean(axis=1)
        self._refine_edges(camera, pan_deg, tilt_deg, matrix, samples, img)
        img = img.reshape(m.height, m.width, 3)
        if sun is not None:
            img += self.sun_image(camera, pan_deg, tilt_deg, sun, matrix)
        img *= np.float32(self.electrons_per_unit)
        if filter_name is not None:
            img = filter_veil(img, np.radians(FILTER_VEIL_SIGMA_DEG) * 0.5 * (m.fx + m.fy))
        img = img.astype(np.float32)
        self._last[camera] = (key, img)
        return img

    def _refine_edges(self, camera: str, pan_deg: float, tilt_deg: float, matrix: np.ndarray, samples: np.ndarray,
                      img: np.ndarray) -> None:
        """Render again, with :attr:`refine_per_side` ² rays, the valid pixels whose ``samples (H·W, s², 3)``
        disagree (:func:`~omnispectral.sim.antialias.pixels_to_refine`, with their neighbours) or whose mean in
        ``img (H·W, 3)`` differs from a valid neighbour's
        (:func:`~omnispectral.sim.antialias.differs_from_neighbours`), and write their means into ``img``; a pixel
        some of whose new rays fall outside the lens model keeps its first mean."""
        s = max(1, int(self.supersample))
        if self.refine_per_side <= s:
            return
        m = self.models[camera]
        valid = self.pixel_valid(camera).ravel()
        marked = (with_neighbours(pixels_to_refine(samples) & valid, m.height, m.width)
                  | differs_from_neighbours(img, m.height, m.width, valid=valid))
        idx = np.flatnonzero(marked & valid)
        if idx.size == 0:
            return
        v, u = np.divmod(idx, m.width)
        rot = m.camera_to_world(pan_deg, tilt_deg).T
        origin_m = m.camera_center_mm(pan_deg, tilt_deg) / 1000.0
        no_disk = {"sun_disk": False} if scene_sun_disk(self.scene) is not None else {}
        n = self.refine_per_side
        spread = np.repeat(self.ray_spread_rad(camera)[idx * s * s] * np.float32(s / n), n * n)
        valid_rays = []

        def render(points: np.ndarray) -> np.ndarray:
            rays, valid = m.unproject(points)
            valid_rays.append(valid)
            out = np.zeros((points.shape[0], 3), np.float32)
            if valid.any():
                out[valid] = self.scene.band_radiance(rays[valid] @ rot, matrix, origin_m=origin_m, **no_disk,
                                                      **footprint_kwargs(self.scene, spread[valid]))
            return out

        means = refined_mean(render, np.stack([u, v], axis=-1).astype(np.float64), n)
        keep = valid_rays[0].reshape(idx.size, n * n).all(axis=1)
        img[idx[keep]] = means[keep]

    def sun_image(self, camera: str, pan_deg: float, tilt_deg: float, sun: SunDisk, matrix: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` float32 mean band radiance of the sun's disk in each pixel of ``camera``.

        Stratified disk samples (:func:`~omnispectral.imaging.sundisk.disk_samples`, about 80 cells per
        pixel side), each tested for visibility from the camera's centre with the scene's own ray casting,
        are splatted into the pixels they are imaged on as ``Σ w / Ω_pixel``
        (:func:`~omnispectral.imaging.sundisk.splat_camera`) times the disk's band radiance: the frame
        holds exactly the visible disk's energy, ``Σ value · Ω_pixel = L · Ω_visible``.
        """
        m = self.models[camera]
        out = np.zeros((m.height, m.width, 3), np.float32)
        f_px = max(m.fx, m.fy)
        _, near = m.world_to_pixel(sun.direction[None], pan_deg, tilt_deg, margin_px=sun.radius_rad * f_px + 2.0)
        if not near[0]:
            return out
        dirs, weights = self._disk_samples(sun, 1.0 / f_px)
        origin_m = m.camera_center_mm(pan_deg, tilt_deg) / 1000.0
        vis = np.asarray(sun.visible(dirs, origin_m), bool)
        rows, cols, frac = splat_camera(m, dirs[vis], weights[vis], pan_deg, tilt_deg)
        keep = self.pixel_valid(camera)[rows, cols]
        out[rows[keep], cols[keep]] = (frac[keep, None] * sun.band_radiance(matrix)[None, :]).astype(np.float32)
        return out

    def _disk_samples(self, sun: SunDisk, pixel_rad: float) -> tuple[np.ndarray, np.ndarray]:
        n = n_radial_for_pixel(sun.radius_rad, pixel_rad)
        key = (tuple(np.round(sun.direction, 15)), sun.radius_rad, n)
        if key not in self._sun_samples:
            if len(self._sun_samples) > 4:
                self._sun_samples.clear()
            self._sun_samples[key] = disk_samples(sun.direction, sun.radius_rad, n)
        return self._sun_samples[key]

    def __call__(self, camera: str, pan_deg: float, tilt_deg: float, exposure_s: float,
                 rng: np.random.Generator, filter_name: str | None = None) -> np.ndarray:
        """A raw frame of ``camera`` at the head's ``(pan_deg, tilt_deg)``, with ``filter_name`` in front of the
        lens if given (:meth:`electrons_per_second`); noise from ``rng`` unless :attr:`noise` is off."""
        cam = self.rig.cameras[camera]
        return raw_frame(cam, self.electrons_per_second(camera, pan_deg, tilt_deg, filter_name), exposure_s,
                         rng if self.noise else None)


def filter_veil(image: np.ndarray, sigma_px: float, fraction: float = FILTER_VEIL_FRACTION) -> np.ndarray:
    """``(1 − f) · image + f · (image ∗ G_σ)``: a filter's veiling glare (:data:`FILTER_VEIL_FRACTION`).

    ``G_σ`` is a normalised Gaussian of ``sigma_px`` (the :data:`FILTER_VEIL_SIGMA_DEG` at the focal length;
    a pixel's solid angle varies little over a few degrees, so energy per pixel stands for energy per
    steradian).  Light scattered beyond the sensor's edge is lost; light from sources outside the field of
    view is not scattered in (its veil is missing near the frame's borders).  Energy is conserved on the
    sensor up to those borders.
    """
    blurred = ndimage.gaussian_filter(image, (sigma_px, sigma_px, 0.0), mode="constant", truncate=4.0)
    return (1.0 - fraction) * image + fraction * blurred


def simulated_dark_cameras(rig: Rig, seed: int = 0, noise: bool = True) -> dict[str, SimulatedCamera]:
    """The simulated rig's cameras with their lenses capped (:class:`DarkRenderer`), for ``capture darks``."""
    clock = FakeClock(_dt.datetime(2000, 1, 1, tzinfo=_dt.UTC))
    head = SimulatedHead(clock)
    renderer = DarkRenderer(rig, noise, seed)
    return {c: SimulatedCamera(c, head, renderer, clock, rig.cameras[c].bit_depth, rig.cameras[c].readout_s,
                               seed=seed * 2 + i + 7919, metadata=raw_metadata(rig.cameras[c]))
            for i, c in enumerate(rig.camera_names)}


def rgb_rig(rig: Rig) -> Rig:
    """``rig`` with its raw Bayer cameras made RGB ones: the chessboard views serve the geometry only (a real raw
    camera's views are demosaiced as they are recorded, :func:`~omnispectral.capture.calviews.rgb_frame`)."""
    if all(cam.raw is None for cam in rig.cameras.values()):
        return rig
    return replace(rig, cameras={c: replace(cam, raw=None) for c, cam in rig.cameras.items()})


def board_renderer(rig: Rig, mounting_error_deg, *, noise: bool = True, supersample: int = 2,
                   share_rays_with: RigRenderer | None = None) -> RigRenderer:
    """A renderer of a chessboard (:mod:`~omnispectral.sim.boardviews`) through the rig's cameras, camera B
    ``mounting_error_deg`` (yaw, pitch, roll) off the rig file, RGB frames.

    ``share_rays_with``: a session's renderer of the same cameras; its rays are reused instead of computed again
    (they are most of the cost at full scale: about 14 s per camera for 2 × 2 rays per pixel of a 2048 × 1088
    sensor, against about 1 s per rendered pair).
    """
    scene = ChessboardScene(DEFAULT_BOARD, DEFAULT_SQUARE_MM / 1000.0, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0),
                            (0.0, -1.0, 0.0))
    renderer = RigRenderer(rgb_rig(rig), scene, noise=noise, electrons_per_unit=1.0,
                           b_mounting_error_deg=tuple(float(x) for x in mounting_error_deg), supersample=supersample)
    if share_rays_with is not None:
        renderer.reuse_rays(share_rays_with)
    return renderer


def simulate_board_views(output: str | Path, rig: Rig, *, seed: int = 0, n_views: int = 12,
                         board: tuple[int, int] = DEFAULT_BOARD, square_mm: float = DEFAULT_SQUARE_MM,
                         noise: bool = True, mounting_error_deg: float = DEFAULT_MOUNTING_ERROR_DEG,
                         supersample: int = 4, progress: ProgressCallback | None = None) -> dict:
    """``omnispectral simulate-chessboard``: ``n_views`` chessboard pairs in ``output``
    (:func:`~omnispectral.sim.boardviews.render_board_views`; returns its summary).

    Camera B carries :func:`true_mounting_error_deg` of ``seed`` (the same as a simulated session of that
    seed); ``supersample`` rays per pixel side integrate the board's edges.
    """
    renderer = board_renderer(rig, true_mounting_error_deg(seed, mounting_error_deg), noise=noise,
                              supersample=supersample)
    return render_board_views(output, renderer, seed=seed, n_views=n_views, board=board, square_mm=square_mm,
                              progress=progress)


def record_simulated_calibration_views(folder: str | Path, renderer: RigRenderer, *, seed: int = 0,
                                       n_views: int = DEFAULT_N_VIEWS,
                                       progress: ProgressCallback | None = None) -> bool:
    """The chessboard pairs a simulated rig records once per mounting of its cameras, into ``folder``
    (``SESSION/calibration/`` or a time-lapse's ``SERIES/calibration/``), through the cameras of a session's
    ``renderer`` (the same unknown mounting of camera B, its rays reused).  Returns ``False`` when ``folder``
    already holds them (a resumed simulation, the later slots of a time-lapse)."""
    if board_views_complete(folder, seed, n_views, renderer.b_mounting_error_deg):
        return False
    views = board_renderer(renderer.rig, renderer.b_mounting_error_deg, noise=renderer.noise,
                           supersample=renderer.supersample, share_rays_with=renderer)
    with directory_lock(folder, "simulate calibration views"):
        render_board_views(folder, views, seed=seed, n_views=n_views, progress=progress)
    return True


@dataclass
class SimulatedBoard:
    """A chessboard the simulated operator moves in front of the simulated rig: each call puts it at the next
    random pose both cameras see whole (the ``next_view`` of
    :func:`~omnispectral.capture.calviews.record_calibration_views`)."""

    renderer: RigRenderer
    cameras: dict
    rng: np.random.Generator
    board: tuple[int, int] = DEFAULT_BOARD
    square_mm: float = DEFAULT_SQUARE_MM
    moves: int = 0

    def __call__(self, k: int, n: int, problem: str | None = None) -> None:
        self.renderer.set_scene(next_board_scene(self.rng, self.renderer.models, self.board, self.square_mm / 1000.0))
        self.moves += 1
        for cam in self.cameras.values():  # a simulated frame's noise follows its camera's seed: new noise per pose
            cam.seed += 1000


def simulated_board_cameras(rig: Rig, *, seed: int = 0, noise: bool = True,
                            mounting_error_deg: float = DEFAULT_MOUNTING_ERROR_DEG,
                            board: tuple[int, int] = DEFAULT_BOARD, square_mm: float = DEFAULT_SQUARE_MM
                            ) -> tuple[dict[str, SimulatedCamera], SimulatedBoard]:
    """The simulated rig's cameras in front of a chessboard, camera B :func:`true_mounting_error_deg` of ``seed``
    off the rig file (as in a session of that seed), and the board's mover: ``capture calibration-views`` on
    simulated devices.  The board's light puts its white squares at 70 % of camera A's full well at the
    bracket's middle exposure; the capture finds each camera's exposure itself."""
    renderer = board_renderer(rig, true_mounting_error_deg(seed, mounting_error_deg), noise=noise)
    mover_rng = board_rng(seed)
    renderer.set_scene(next_board_scene(mover_rng, renderer.models, board, square_mm / 1000.0))
    expose_for_board(renderer, renderer.scene)
    clock = FakeClock(_dt.datetime(2000, 1, 1, tzinfo=_dt.UTC))
    head = SimulatedHead(clock)
    cams = {c: SimulatedCamera(c, head, renderer, clock, rig.cameras[c].bit_depth, rig.cameras[c].readout_s,
                               seed=seed * 2 + i + 104729) for i, c in enumerate(rig.camera_names)}
    return cams, SimulatedBoard(renderer, cams, mover_rng, board, square_mm)


def bayer_rig(rig: Rig, pattern: str = "RGGB") -> Rig:
    """``rig`` with every camera that has no ``[cameras.X.raw]`` table made a raw Bayer camera of ``pattern``."""
    settings = {c: {"raw": {"cfa_pattern": pattern}} for c, cam in rig.cameras.items() if cam.raw is None}
    return rig_with_camera_settings(rig, settings) if settings else rig


def calibrate_exposure(rig: Rig, scene, system: MultibandSystem, grid: tuple[int, int] = (256, 128)) -> float:
    """Electrons per second per unit band radiance (module docstring: bright surfaces at 80 % of full well
    at the bracket's geometric-mean exposure)."""

    w, h = grid
    col, row = np.meshgrid(np.arange(w), np.arange(h))
    rays = lonlat_to_ray(*equirect_pixel_to_lonlat(col.ravel(), row.ravel(), w, h))
    bands = scene.band_radiance(rays, system.matrix)
    reference = float(np.percentile(bands.max(axis=1), 99.5))
    if not reference > 0:
        raise ConfigurationError("the scene is black: cannot choose an exposure scale")
    t_mid = float(np.exp(np.mean(np.log(rig.bracket.exposures_s))))
    return 0.8 * rig.camera_a.full_well_e / (reference * t_mid)


def simulate_session(output: str | Path, rig: Rig, scene, *, start: _dt.datetime, noise: bool = True,
                     seed: int = 0, ground_truth_width: int | None = None, progress: ProgressCallback | None = None,
                     overlap: float | None = None, mounting_error_deg: float = DEFAULT_MOUNTING_ERROR_DEG,
                     raw: str | None = None, calibration_views: bool | str | Path = True,
                     n_calibration_views: int = DEFAULT_N_VIEWS) -> dict:
    """``capture`` with the simulated rig plus the ground truth; resumable like any capture.

    ``raw="bayer"`` makes every camera raw Bayer cameras (:func:`bayer_rig`): frames are the mosaics the
    sensor records (uint16 ``(H, W)``), the CFA layout and black level go into the rig snapshot and into
    every frame's journal record (``camera_metadata``), and ``process`` demosaics them.

    Camera B is rendered with an unknown mounting error of up to ``mounting_error_deg`` per axis drawn
    from ``seed`` (:func:`true_mounting_error_deg`; 0 renders the rig file's mounting exactly).
    ``progress(stage, done, total)`` follows the frames (:func:`~omnispectral.capture.run.run_capture`).

    ``calibration_views``: the rig records ``n_calibration_views`` chessboard pairs once per mounting of its
    cameras (:func:`record_simulated_calibration_views`; ``process`` fits camera B's mounting from them):
    ``True`` into ``SESSION/calibration/``, a folder (a time-lapse's ``SERIES/calibration/``, which its slots
    share: rendered by the first, found by the others) or ``False`` for none.

    The result is the capture's (:class:`~omnispectral.capture.run.CaptureResult`: ``simulated_s`` is this run's
    simulated time) plus ``capture_s``, the simulated time the session's frames took over every run (a resumed
    session's clock continues from its last recorded frame), the ground truth and the calibration views.
    """

    if raw not in (None, "rgb", "bayer"):
        raise ConfigurationError(f"raw must be 'rgb' or 'bayer', got {raw!r}")
    if raw == "bayer":
        rig = bayer_rig(rig)
    plan = make_plan(rig, overlap=overlap)
    big = max(rig.cameras.values(), key=lambda c: c.width_px * c.height_px)
    check_memory(output, sensor_memory_bytes(big.width_px * big.height_px, SIMULATE_BYTES_PER_SENSOR_PX),
                 memory_budget(), f"simulating {big.width_px} × {big.height_px} frames")  # before any rendering
    renderer = RigRenderer(rig, scene, noise=noise,
                           b_mounting_error_deg=true_mounting_error_deg(seed, mounting_error_deg))
    described = jsonable(scene.describe())
    # the scene's own parameters first, so that a refused resume names them before what they determine
    identity = {"scene_parameters": described.get("parameters") if isinstance(described, dict) else None,
                "scene": described, "noise": noise, "seed": seed, "mounting_error_deg": float(mounting_error_deg)}
    with directory_lock(output, "simulate"):
        session = Session.create(output, rig, plan, kind="simulation", identity=identity,
                                 extra={"simulation": {"scene": jsonable(scene.describe()), "noise": noise,
                                                       "seed": seed, "start": start.isoformat(),
                                                       "electrons_per_unit": renderer.electrons_per_unit}})
        clock = FakeClock(start)
        head = SimulatedHead(clock, rig.head.pan_speed_deg_s, rig.head.tilt_speed_deg_s, rig.head.settle_s)
        cams = {c: SimulatedCamera(c, head, renderer, clock, rig.cameras[c].bit_depth, rig.cameras[c].readout_s,
                                   seed=seed * 2 + i, metadata=raw_metadata(rig.cameras[c]))
                for i, c in enumerate(rig.camera_names)}
        resume_simulated_devices(session, clock, head)
        filters = SimulatedFilterChanger(cams, clock, rig.sun.change_s) if rig.sun is not None else None
        result = run_capture(session, head, cams, clock,
                             RetryPolicy(rig.head.retries, rig.head.timeout_s, rig.head.position_tolerance_deg),
                             progress, filters)
        gt_dir = session.path / "ground_truth"
        if not (gt_dir / "ground_truth.json").exists():
            write_ground_truth(gt_dir, renderer, ground_truth_width or default_ground_truth_width(rig))
        views, note = calibration_views_folder(session.path, calibration_views, renderer)
        if views is not None and not result.complete:
            views, note = None, "recorded once the capture is complete (run the same command again)"
        t_views = time.perf_counter()
        rendered = views is not None and record_simulated_calibration_views(views, renderer, seed=seed,
                                                                            n_views=n_calibration_views)
    # the session's clock counts from its first frame's start, a resume restoring it (resume_simulated_devices):
    # its reading is the capture time of every frame, an interrupted attempt's included (simulated_s: this run's)
    return {**result.to_dict(), "capture_s": clock.monotonic(), "ground_truth": str(gt_dir),
            "electrons_per_unit": renderer.electrons_per_unit,
            "calibration_views": str(views) if views is not None else None, "calibration_views_note": note,
            "calibration_views_s": time.perf_counter() - t_views if rendered else 0.0}


def calibration_views_folder(session: Path, calibration_views: bool | str | Path, renderer: RigRenderer
                             ) -> tuple[Path | None, str | None]:
    """Where :func:`simulate_session` records the calibration views (its ``calibration_views`` argument), or
    ``None`` and why not."""
    if not calibration_views:
        return None, "--no-calibration-views given"
    if "B" not in renderer.models:
        return None, "a one-camera rig: no camera B to calibrate"
    if square_px(renderer.models["A"]) < MIN_SQUARE_PX:
        return None, (f"camera A's {renderer.models['A'].width} px are too few to find a chessboard's corners "
                      f"(squares of {square_px(renderer.models['A']):.1f} px)")
    return (calibration_folder(session) if calibration_views is True else Path(calibration_views)), None
