"""Rig description: the cameras and their mounting, the pan/tilt head, the exposure bracket, the grid.

A rig is written in TOML (see ``src/omnispectral/data/rigs/*.toml`` for the built-in presets of the
paper: ``paper-timelapse``, ``paper-gigapixel`` and the small ``small``).  Every value is validated
on load, and an error names the file, the table and the key.  Lens fields of view are the angles
across the sensor's long side (``hfov_deg``, along ``width_px``) and short side (``vfov_deg``);
``orientation = "portrait"`` rolls the camera by 90° on the head, as in the paper, so the long side
then spans tilt.

A rig has camera A and, for the paper's six bands, camera B behind the second filter.  A rig with
camera A alone (one RGB camera: a DSLR on a Merlin head, ``omnispectral import`` of one camera) has
three bands ``A:R, A:G, A:B``; everything downstream takes the band count from the rig.

The rig also knows what its description means for processing: the geometric model of each camera
(:meth:`Rig.camera_model`, lens and mounting) and the spectral system of its cameras, three bands
each (:meth:`Rig.system`).  Capture, simulation, mosaicking and processing all take them from here.

This is a base module of the package (see ``docs/architecture.md``): it builds on ``imaging`` and
``spectral`` and is imported by ``capture``, ``mosaic`` and ``product``, none of which it imports.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import asdict, dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from omnispectral.choices import PRESETS
from omnispectral.errors import ConfigurationError, InputFileError, InvalidFileContent
from omnispectral.imaging.bayer import CFA_PATTERNS, DEMOSAIC_METHODS, ORDERS
from omnispectral.imaging.geometry import CameraModel, Mounting
from omnispectral.io import read_text_file
from omnispectral.limits import (
    MAX_DIRECTIONS,
    MAX_DISTORTION_COEFFICIENT,
    MAX_EXPOSURE_S,
    MAX_IMAGE_SIDE_PX,
    MIN_EXPOSURE_S,
    MIN_FOV_DEG,
    check_exposure_times,
)
from omnispectral.spectral.library import load_camera, load_filter
from omnispectral.spectral.noise import SensorNoiseModel
from omnispectral.spectral.system import MultibandSystem, build_system

__all__ = ["CAMERA_DRIVERS", "CAMERA_NAMES", "DARK_EXPOSURE_BASE", "DEFAULT_SUN_FILTER", "HEAD_DRIVERS", "KIND_NAMES",
           "MAX_SUN_BRACKETS", "ORIENTATIONS", "PRESETS", "SUN_EXPOSURE_BASE", "SUN_FILTER_CHANGERS", "BracketSpec",
           "CameraSpec", "DarkExtensionSpec", "GridSpec", "HeadSpec", "LensSpec", "MountingSpec", "RawSpec", "Rig",
           "SunBracketSpec", "camera_model", "camera_system", "load_preset", "load_rig", "one_camera_rig",
           "resolve_rig", "rig_from_dict", "rig_system", "rig_toml", "rig_with_camera_settings"]

HEAD_DRIVERS = ("simulated", "rodeon", "merlin")
CAMERA_DRIVERS = ("simulated", "genicam")
ORIENTATIONS = {"landscape": 0.0, "portrait": 90.0}
#: Camera names in band order: a rig has camera A (bands 0-2) and optionally camera B (bands 3-5).
CAMERA_NAMES = ("A", "B")


#: How a rig-file error names the type it expected.
KIND_NAMES = {int: "an integer", float: "a number", str: "a string", bool: "true or false", list: "a list",
              dict: "a table"}


class _Reader:
    """Typed access to one TOML table with errors that say where the bad value is."""

    def __init__(self, data: dict, where: str, source: str):
        if not isinstance(data, dict):
            raise InvalidFileContent(source, f"[{where}] must be a table, got {data!r}")
        self.data, self.where, self.source = data, where, source  # where: "" for the top level, or "bracket"…

    def fail(self, key: str, problem: str):
        """``FILE: [table] key: problem`` (top-level keys without a table)."""
        raise InvalidFileContent(self.source, f"[{self.where}] {key}: {problem}" if self.where else f"{key}: {problem}")

    def get(self, key: str, kind: type, default: Any = ..., positive: bool = False, minimum: float | None = None):
        if key not in self.data:
            if default is ...:
                self.fail(key, "missing")
            return default
        v = self.data[key]
        if kind is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, kind) or (isinstance(v, bool) and kind is not bool):
            self.fail(key, f"expected {KIND_NAMES.get(kind, kind.__name__)}, got {v!r}")
        if kind in (int, float):
            if not math.isfinite(v):
                self.fail(key, f"{v!r} is not finite")
            if positive and v <= 0:
                self.fail(key, f"must be positive, got {v!r}")
            if minimum is not None and v < minimum:
                self.fail(key, f"must be >= {minimum}, got {v!r}")
        return v

    def table(self, key: str, default: dict | None = None) -> _Reader:
        where = f"{self.where}.{key}" if self.where else key
        if key not in self.data and default is not None:
            return _Reader(default, where, self.source)
        if key not in self.data:
            self.fail(key, "missing table")
        return _Reader(self.data[key], where, self.source)


@dataclass(frozen=True)
class LensSpec:
    """Angular field of view across the sensor's long and short sides, OpenCV distortion, or a calibration."""

    hfov_deg: float
    vfov_deg: float
    distortion: tuple[float, ...] = ()
    calibration: str | None = None  # lens.json from ``omnispectral calibrate lens`` (overrides the above)


@dataclass(frozen=True)
class RawSpec:
    """A raw Bayer camera (``[cameras.X.raw]``): its CFA layout and how ``process`` demosaics
    (:mod:`omnispectral.imaging.bayer`: method, and whether before or after the HDR merge)."""

    cfa_pattern: str = "RGGB"
    demosaic: str = "menon2007"
    order: str = "merge-first"


@dataclass(frozen=True)
class CameraSpec:
    """One camera (A, or B): sensor, lens, spectral sensitivity, filter, noise, orientation, device."""

    name: str
    model: str
    width_px: int
    height_px: int
    bit_depth: int
    pixel_pitch_um: float
    readout_s: float
    orientation: str
    roll_deg: float
    sensitivity: str
    filter: str
    lens: LensSpec
    full_well_e: float
    read_noise_e: float
    device: dict = field(default_factory=dict)
    #: offset the camera adds to every code (DN); subtracted by ``process`` unless dark frames were recorded
    black_level_dn: float = 0.0
    #: mean dark signal (e-/s) and its pixel-to-pixel spread (relative; hot pixels) of the simulated sensor
    dark_current_e_s: float = 0.0
    dark_signal_nonuniformity: float = 0.0
    raw: RawSpec | None = None  # None: frames are RGB (H, W, 3); else Bayer mosaics (H, W)

    @property
    def max_dn(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def pan_fov_deg(self) -> float:
        """Field of view across pan (horizontal on the head) after the mounting roll."""
        return self.lens.vfov_deg if self.orientation == "portrait" else self.lens.hfov_deg

    @property
    def tilt_fov_deg(self) -> float:
        return self.lens.hfov_deg if self.orientation == "portrait" else self.lens.vfov_deg

    def noise_model(self) -> SensorNoiseModel:
        return SensorNoiseModel(self.full_well_e, self.read_noise_e, self.bit_depth, self.model)


@dataclass(frozen=True)
class MountingSpec:
    """Camera B relative to camera A in the head frame: translation (mm) and a small rotation (deg)."""

    baseline_mm: tuple[float, float, float] = (60.0, 0.0, 0.0)
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    roll_deg: float = 0.0


@dataclass(frozen=True)
class HeadSpec:
    """The pan/tilt head: driver, port, speeds, settle time, tolerances and retry policy."""

    driver: str = "simulated"
    model: str = ""
    port: str = ""
    pan_speed_deg_s: float = 20.0
    tilt_speed_deg_s: float = 20.0
    settle_s: float = 2.0
    position_tolerance_deg: float = 0.05
    timeout_s: float = 30.0
    retries: int = 3
    baud: int = 9600  # serial heads (rodeon, merlin)
    speed_fraction: float = 1.0  # fraction of the head's maximum motor speed the driver commands
    command_timeout_s: float = 0.5  # longest wait for one serial reply
    poll_s: float = 0.05  # position polling interval while a move settles


@dataclass(frozen=True)
class BracketSpec:
    """Exposure times of one direction's bracket, longest first."""

    exposures_s: tuple[float, ...]

    @property
    def total_s(self) -> float:
        return float(sum(self.exposures_s))


#: Exposure index of the first frame of a direction's dark extension (its files are ``A_e64.tif`` …): after any
#: regular bracket (at most 64 exposures) and before the sun bracket's.
DARK_EXPOSURE_BASE = 64


@dataclass(frozen=True)
class DarkExtensionSpec:
    """Longer exposures for a direction whose darkest pixels stay noisy in the bracket's longest exposure.

    After a direction's bracket the capture meters its longest exposure in every camera: the ``percentile``
    of each pixel's darkest channel, above the black level.  Where that signal's signal-to-noise ratio (the
    camera's noise model: shot noise, read noise, quantisation) is below ``snr``, both cameras shoot
    exposures of 2, 4, 8 … times the longest until the darkest pixels would reach ``snr`` or the next
    exposure would pass ``longest_s`` (dawn, dusk, deep shade: ``omnispectral.capture.run``).  Processing
    merges them with the bracket.
    """

    longest_s: float = 1.008
    percentile: float = 1.0
    snr: float = 40.0

    def exposures_s(self, bracket_longest_s: float) -> tuple[float, ...]:
        """The exposures an extension may shoot after a bracket whose longest exposure is ``bracket_longest_s``:
        twice it, four times it, … up to :attr:`longest_s`."""
        out, t = [], 2.0 * bracket_longest_s
        while t <= self.longest_s * (1.0 + 1e-9) and len(out) < SUN_EXPOSURE_BASE - DARK_EXPOSURE_BASE:
            out.append(t)
            t *= 2.0
        return tuple(out)


#: Exposure index of the first frame of a direction's sun bracket (its files are ``A_e100.tif`` …): far from
#: any regular bracket (at most 64 exposures), so the two never share a key in the journal.
SUN_EXPOSURE_BASE = 100
#: Sun brackets a capture may shoot: the one aimed at the sun and its retries for camera B
#: (``omnispectral.capture.run.SUN_RETRY_PAN_FRACTIONS``); their direction indices follow the grid's.
MAX_SUN_BRACKETS = 3
#: Neutral-density filter of the presets' sun bracket (Kodak Wratten No. 96 at optical density 3.0).
DEFAULT_SUN_FILTER = "wratten-96-nd3"


@dataclass(frozen=True)
class SunBracketSpec:
    """The attenuated bracket shot through a neutral-density filter in every direction that holds the sun.

    A direction holds the sun when camera A's shortest regular exposure clips (``clip_fraction`` of the
    maximum code in at least ``min_clipped_px`` pixels); the capture then inserts ``filter`` in front of both
    lenses (``changer``: ``"simulated"`` for the simulated rig, ``"manual"`` asks the operator), shoots
    ``exposures_s`` on both cameras and removes the filter.  ``change_s`` is the time to insert or remove it.
    """

    filter: str = DEFAULT_SUN_FILTER
    exposures_s: tuple[float, ...] = (0.00096, 0.00024, 0.00006, 0.000015)
    changer: str = "simulated"
    change_s: float = 2.0
    clip_fraction: float = 0.98
    min_clipped_px: int = 1

    @property
    def total_s(self) -> float:
        return float(sum(self.exposures_s))


#: How the neutral-density filter of the sun bracket gets in front of the lenses.
SUN_FILTER_CHANGERS = ("simulated", "manual")


@dataclass(frozen=True)
class GridSpec:
    """Direction grid: explicit counts, or an overlap from which the counts follow (see ``plan``)."""

    n_pan: int | None = None
    n_tilt: int | None = None
    overlap: float | None = None


@dataclass(frozen=True)
class Rig:
    """Everything about the hardware a capture needs; ``source`` is where it was read from.

    Parameters
    ----------
    name, description : str
        The rig's name and a one-line description.
    cameras : dict of str to CameraSpec
        Camera ``"A"`` (bands 0-2) and, for six bands, camera ``"B"`` (bands 3-5): sensor size (px), bit depth,
        read-out time (s), lens fields of view (deg) and distortion, orientation, spectral sensitivity and
        filter, noise (electrons), device.
    mounting : MountingSpec
        Camera B relative to camera A in the head frame: baseline (mm) and a small yaw, pitch, roll (deg).
    head : HeadSpec
        The pan/tilt head: driver, pan and tilt speeds (deg/s), settle time (s), tolerance (deg), retries.
    bracket : BracketSpec
        Exposure times of one direction's bracket (s), longest first.
    grid : GridSpec
        The direction grid: counts, or the per-side overlap they follow from.
    source : str
        Where the rig was read from (a file, ``preset:NAME``).
    toml_text : str
        The TOML it was read from (stored with sessions and products).
    sun : SunBracketSpec or None
        The sun bracket (``[sun]`` table), or ``None``: a saturated sun then stays a lower bound.
    dark : DarkExtensionSpec or None
        Longer exposures where the bracket's longest leaves the darkest pixels noisy (``[dark]`` table), or
        ``None``: every direction gets the bracket alone.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3, Fig. 2 (two programmable high-speed colour cameras behind two
       colour filters on a programmable rotating table), Table 1 (hardware), Sec. 4.1 (the bracket),
       Sec. 4.5, Table 2 (directions).
    """

    name: str
    description: str
    cameras: dict[str, CameraSpec]
    mounting: MountingSpec
    head: HeadSpec
    bracket: BracketSpec
    grid: GridSpec
    source: str = ""
    toml_text: str = ""
    #: the sun bracket (``[sun]`` table), or ``None``: a saturated sun then stays a lower bound
    sun: SunBracketSpec | None = None
    #: longer exposures where the bracket leaves the darkest pixels noisy (``[dark]`` table), or ``None``
    dark: DarkExtensionSpec | None = None

    @property
    def camera_a(self) -> CameraSpec:
        return self.cameras["A"]

    @property
    def camera_b(self) -> CameraSpec:
        if "B" not in self.cameras:
            raise ConfigurationError(f"rig {self.name!r} has one camera (A): there is no camera B")
        return self.cameras["B"]

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The rig's cameras in band order: ``("A", "B")`` (six bands) or ``("A",)`` (one RGB camera, three)."""
        return tuple(c for c in CAMERA_NAMES if c in self.cameras)

    @property
    def n_bands(self) -> int:
        """Three bands (R, G, B) per camera."""
        return 3 * len(self.cameras)

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("toml_text")
        return d

    def camera_model(self, name: str) -> CameraModel:
        """The geometric model of camera ``A`` or ``B`` (see :func:`camera_model`)."""
        return camera_model(self, name)

    def system(self, wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
        """The spectral system of the rig's cameras, three bands each (see :func:`rig_system`)."""
        return rig_system(self, wavelength_nm)


def camera_model(rig: Rig, name: str) -> CameraModel:
    """The geometric model of camera ``A`` or ``B`` of a rig: lens (calibration or field of view) and mounting."""
    cam = rig.cameras[name]
    if name == "A":
        mounting = Mounting(roll_deg=cam.roll_deg)
    else:
        m = rig.mounting
        mounting = Mounting(roll_deg=cam.roll_deg, misalignment_deg=(m.yaw_deg, m.pitch_deg, m.roll_deg),
                            baseline_mm=m.baseline_mm)
    if cam.lens.calibration:
        model = CameraModel.from_json(cam.lens.calibration)
        if (model.width, model.height) != (cam.width_px, cam.height_px):
            raise ConfigurationError(f"camera {name}: lens calibration {cam.lens.calibration} is for "
                                     f"{model.width}x{model.height}, the sensor is {cam.width_px}x{cam.height_px}")
        return replace(model, mounting=mounting)
    return _model_from_fovs(cam.width_px, cam.height_px, cam.lens.hfov_deg, cam.lens.vfov_deg, cam.lens.distortion,
                            mounting)


def _model_from_fovs(width: int, height: int, hfov_deg: float, vfov_deg: float, dist, mounting) -> CameraModel:
    """A camera with the rig file's two fields of view: ``fx`` from the horizontal one (solved through the
    distortion), ``fy`` so that the vertical one holds for the pinhole part (non-square pixels when the
    stated angles do not match the sensor's aspect, as for the paper's telephoto: 14.5° × 10.8° on
    2048 × 1088 — square pixels would give 7.7° and leave gaps between the 60 × 21 grid's rows)."""
    model = CameraModel.from_fov(width, height, hfov_deg, dist, mounting)
    fx0 = 0.5 * width / math.tan(math.radians(hfov_deg) / 2)
    fy0 = 0.5 * height / math.tan(math.radians(vfov_deg) / 2)
    return replace(model, fy=model.fx * fy0 / fx0)


def rig_system(rig: Rig, wavelength_nm: np.ndarray | None = None) -> MultibandSystem:
    """The system of a rig (Eq. (6)'s ``R``): camera A's sensitivity × filter A, then camera B's × filter B
    when the rig has a camera B (six bands), else camera A's three bands alone.

    Parameters
    ----------
    rig : Rig
        The rig: each camera's ``sensitivity`` and ``filter`` (names or CSV files).
    wavelength_nm : numpy.ndarray, optional
        The wavelength grid (nm; default 400-700 nm every 5 nm).

    Returns
    -------
    MultibandSystem
        Bands ``A:R, A:G, A:B[, B:R, B:G, B:B]`` (:func:`camera_system`), named after the rig.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3, Fig. 4 (the six-band sensitivities: two RGB cameras behind
       two filters), Eqs. (5)-(6) (``R``).
    """
    pairs = tuple((rig.cameras[c].sensitivity, rig.cameras[c].filter) for c in rig.camera_names)
    return camera_system(pairs, wavelength_nm, rig.name)


def camera_system(pairs: tuple[tuple[str, str], ...], wavelength_nm: np.ndarray | None = None,
                  name: str = "rig") -> MultibandSystem:
    """Bands ``A:R, A:G, A:B[, B:R … B:B]`` of one or two cameras given as (sensitivity, filter) names or CSV
    files, in the order of ``pairs``.

    Parameters
    ----------
    pairs : tuple of (str, str)
        One or two ``(sensitivity, filter)`` pairs: an RGB sensitivity set of
        :func:`~omnispectral.spectral.library.load_camera` and a filter of
        :func:`~omnispectral.spectral.library.load_filter` (names or CSV paths).
    wavelength_nm : numpy.ndarray, optional
        The wavelength grid (nm; default 400-700 nm every 5 nm).
    name : str
        Prefix of the system's description.

    Returns
    -------
    MultibandSystem
        Three bands per camera, each the camera's channel sensitivity times its filter's transmittance,
        with the camera index of every band.

    Raises
    ------
    ConfigurationError
        For no pair or more than two.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3, Fig. 3 (filter transmittances), Fig. 4 (the six-band
       sensitivities), Eqs. (5)-(6) (``R``).
    """
    if not 1 <= len(pairs) <= len(CAMERA_NAMES):
        raise ConfigurationError(f"a rig has 1 or {len(CAMERA_NAMES)} cameras, got {len(pairs)}")
    parts = [build_system(load_camera(sens), [load_filter(filt)], wavelength_nm) for sens, filt in pairs]
    names = CAMERA_NAMES[:len(parts)]
    return MultibandSystem(parts[0].wavelength_nm, np.vstack([p.sensitivity for p in parts]),
                           tuple(f"{c}:{b}" for c in names for b in ("R", "G", "B")),
                           np.repeat(np.arange(len(parts)), 3),
                           f"{name}: " + " | ".join(p.description for p in parts))


def _camera(r: _Reader, name: str) -> CameraSpec:
    orientation = r.get("orientation", str, "landscape")
    if orientation not in ORIENTATIONS:
        r.fail("orientation", f"expected one of {sorted(ORIENTATIONS)}, got {orientation!r}")
    lens = r.table("lens")
    hfov, vfov = lens.get("hfov_deg", float, positive=True), lens.get("vfov_deg", float, positive=True)
    if hfov >= 180 or vfov >= 180:
        lens.fail("hfov_deg", f"fields of view must be below 180 deg, got {hfov} x {vfov}")
    if hfov < MIN_FOV_DEG or vfov < MIN_FOV_DEG:
        lens.fail("hfov_deg", f"fields of view must be at least {MIN_FOV_DEG} deg (a whole-sphere grid would need "
                              f"millions of directions), got {hfov} x {vfov}")
    dist = lens.get("distortion", list, [])
    if len(dist) not in (0, 4, 5, 8, 12, 14) or not all(isinstance(v, int | float) and not isinstance(v, bool)
                                                        and math.isfinite(v) for v in dist):
        lens.fail("distortion", f"expected 4, 5, 8, 12 or 14 numbers (OpenCV order), got {dist!r}")
    if any(abs(v) > MAX_DISTORTION_COEFFICIENT for v in dist):
        lens.fail("distortion", f"coefficient {max(dist, key=abs)!r} is beyond ±{MAX_DISTORTION_COEFFICIENT:g} "
                                f"(no lens is that distorted; the model's polynomials would overflow)")
    calib = lens.get("calibration", str, None)
    if calib is not None and not Path(calib).is_absolute() and r.source and Path(r.source).exists():
        calib = str(Path(r.source).parent / calib)
    noise = r.table("noise", {})
    device = r.table("device", {"driver": "simulated"})
    driver = device.get("driver", str, "simulated")
    if driver not in CAMERA_DRIVERS:
        device.fail("driver", f"expected one of {CAMERA_DRIVERS}, got {driver!r}")
    bit_depth = r.get("bit_depth", int, positive=True)
    if not 8 <= bit_depth <= 16:
        r.fail("bit_depth", f"must be 8-16, got {bit_depth}")
    return CameraSpec(
        name=name, model=r.get("model", str, "camera"), width_px=_side(r, "width_px"),
        height_px=_side(r, "height_px"), bit_depth=bit_depth,
        pixel_pitch_um=r.get("pixel_pitch_um", float, 5.5, positive=True),
        readout_s=r.get("readout_s", float, 0.01, minimum=0.0), orientation=orientation,
        roll_deg=ORIENTATIONS[orientation], sensitivity=r.get("sensitivity", str, "Nikon 5100 (NPL)"),
        filter=r.get("filter", str, "none"),
        lens=LensSpec(hfov, vfov, tuple(float(v) for v in dist), calib),
        full_well_e=noise.get("full_well_e", float, 13500.0, positive=True),
        read_noise_e=noise.get("read_noise_e", float, 13.0, minimum=0.0), device=dict(device.data),
        black_level_dn=_black_level(r, bit_depth),
        dark_current_e_s=noise.get("dark_current_e_s", float, 0.0, minimum=0.0),
        dark_signal_nonuniformity=noise.get("dark_signal_nonuniformity", float, 0.0, minimum=0.0),
        raw=_raw(r))


def _black_level(r: _Reader, bit_depth: int) -> float:
    v = r.get("black_level_dn", float, 0.0, minimum=0.0)
    if v >= (1 << bit_depth) - 1:
        r.fail("black_level_dn", f"{v} DN leaves no range below the largest {bit_depth}-bit code")
    return v


def _raw(r: _Reader) -> RawSpec | None:
    """``[cameras.X.raw]``: a Bayer camera (see :class:`RawSpec`), or None for RGB frames."""
    if "raw" not in r.data:
        return None
    t = r.table("raw")
    spec = RawSpec(t.get("cfa_pattern", str, "RGGB").upper(), t.get("demosaic", str, "menon2007"),
                   t.get("order", str, "merge-first"))
    for key, value, allowed in (("cfa_pattern", spec.cfa_pattern, CFA_PATTERNS),
                                ("demosaic", spec.demosaic, DEMOSAIC_METHODS), ("order", spec.order, ORDERS)):
        if value not in allowed:
            t.fail(key, f"expected one of {', '.join(allowed)}, got {value!r}")
    if spec.demosaic == "opencv-ea" and spec.order == "merge-first":
        t.fail("demosaic", "opencv-ea demosaics integer codes only: use it with order = \"demosaic-first\"")
    return spec


def _side(r: _Reader, key: str) -> int:
    v = r.get(key, int, positive=True)
    if v > MAX_IMAGE_SIDE_PX:
        r.fail(key, f"{v} px is above the limit of {MAX_IMAGE_SIDE_PX} px")
    return v


def _exposure_list(r: _Reader, times) -> tuple[float, ...]:
    """A table's ``exposures_s``: positive seconds within the limits, longest first; else the key's error."""
    if len(times) < 1 or not all(isinstance(t, int | float) and not isinstance(t, bool) and t > 0 for t in times):
        r.fail("exposures_s", f"expected a list of positive seconds, got {times!r}")
    try:
        check_exposure_times(times, "exposures_s")
    except ConfigurationError as exc:
        r.fail("exposures_s", str(exc).removeprefix("exposures_s: "))
    return tuple(sorted((float(t) for t in times), reverse=True))


def _bracket(r: _Reader) -> BracketSpec:
    if "exposures_s" in r.data:
        return BracketSpec(_exposure_list(r, r.get("exposures_s", list)))
    longest = r.get("longest_s", float, positive=True)
    shortest = r.get("shortest_s", float, positive=True)
    count = r.get("count", int, positive=True)
    if shortest > longest:
        r.fail("shortest_s", f"{shortest} s is longer than longest_s {longest} s")
    for key, t in (("longest_s", longest), ("shortest_s", shortest)):
        if not MIN_EXPOSURE_S <= t <= MAX_EXPOSURE_S:
            r.fail(key, f"{t!r} s is outside {MIN_EXPOSURE_S:g}-{MAX_EXPOSURE_S:g} s")
    if count > 64:
        r.fail("count", f"{count} exposures per bracket is above the limit of 64")
    if count == 1:
        return BracketSpec((longest,))
    return BracketSpec(tuple(float(t) for t in np.geomspace(longest, shortest, count)))


def _sun(r: _Reader | None) -> SunBracketSpec | None:
    """The ``[sun]`` table (see :class:`SunBracketSpec`), or ``None`` without one."""
    if r is None:
        return None
    default = SunBracketSpec()
    name = r.get("filter", str, default.filter)
    try:
        load_filter(name)
    except (ConfigurationError, InputFileError) as exc:
        r.fail("filter", str(exc))
    times = r.get("exposures_s", list, list(default.exposures_s))
    if len(times) > 64:
        r.fail("exposures_s", f"{len(times)} exposures is above the limit of 64")
    times = _exposure_list(r, times)
    changer = r.get("changer", str, default.changer)
    if changer not in SUN_FILTER_CHANGERS:
        r.fail("changer", f"expected one of {SUN_FILTER_CHANGERS}, got {changer!r}")
    clip = r.get("clip_fraction", float, default.clip_fraction, positive=True)
    if clip > 1:
        r.fail("clip_fraction", f"must be in (0, 1], got {clip}")
    return SunBracketSpec(name, times, changer,
                          r.get("change_s", float, default.change_s, minimum=0.0), clip,
                          r.get("min_clipped_px", int, default.min_clipped_px, positive=True))


def _dark(r: _Reader | None, bracket: BracketSpec) -> DarkExtensionSpec | None:
    """The ``[dark]`` table (see :class:`DarkExtensionSpec`), or ``None`` without one."""
    if r is None:
        return None
    default = DarkExtensionSpec()
    longest = r.get("longest_s", float, default.longest_s, positive=True)
    if not MIN_EXPOSURE_S <= longest <= MAX_EXPOSURE_S:
        r.fail("longest_s", f"{longest!r} s is outside {MIN_EXPOSURE_S:g}-{MAX_EXPOSURE_S:g} s")
    if longest < 2.0 * max(bracket.exposures_s):
        r.fail("longest_s", f"{longest} s is below twice the bracket's longest exposure ({max(bracket.exposures_s)} s):"
                            " there is no longer exposure to add")
    percentile = r.get("percentile", float, default.percentile, positive=True)
    if percentile >= 100:
        r.fail("percentile", f"must be in (0, 100), got {percentile}")
    return DarkExtensionSpec(longest, percentile, r.get("snr", float, default.snr, positive=True))


def rig_from_dict(data: dict, source: str = "<rig>", toml_text: str = "") -> Rig:
    """Validate a parsed rig description (see the module docstring for the layout)."""
    top = _Reader(data, "", source)
    cams = top.table("cameras")
    for key in cams.data:
        if key not in CAMERA_NAMES:
            cams.fail(key, "cameras are named A and B")
    if "A" not in cams.data:
        cams.fail("A", "missing table (a rig has camera A, and camera B for six bands)")
    cameras = {n: _camera(cams.table(n), n) for n in CAMERA_NAMES if n in cams.data}
    a, b = cameras["A"], cameras.get("B", cameras["A"])
    if (a.width_px, a.height_px) != (b.width_px, b.height_px):
        raise ConfigurationError(f"{source}: cameras A and B have different sensor sizes "
                                 f"{a.width_px}x{a.height_px} and {b.width_px}x{b.height_px}")
    m = top.table("mounting", {})
    baseline = m.get("baseline_mm", list, [60.0, 0.0, 0.0])
    if len(baseline) != 3 or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                                     and abs(v) <= 10_000 for v in baseline):
        m.fail("baseline_mm", f"expected [x, y, z] in mm, got {baseline!r}")
    mounting = MountingSpec(tuple(float(v) for v in baseline), m.get("yaw_deg", float, 0.0),
                            m.get("pitch_deg", float, 0.0), m.get("roll_deg", float, 0.0))
    for key in ("yaw_deg", "pitch_deg", "roll_deg"):
        if abs(getattr(mounting, key)) > 10:
            m.fail(key, f"{getattr(mounting, key)} deg is not a small misalignment (|angle| <= 10)")
    h = top.table("head", {})
    driver = h.get("driver", str, "simulated")
    if driver not in HEAD_DRIVERS:
        h.fail("driver", f"expected one of {HEAD_DRIVERS}, got {driver!r}")
    head = HeadSpec(driver, h.get("model", str, ""), h.get("port", str, ""),
                    h.get("pan_speed_deg_s", float, 20.0, positive=True),
                    h.get("tilt_speed_deg_s", float, 20.0, positive=True),
                    h.get("settle_s", float, 2.0, minimum=0.0),
                    h.get("position_tolerance_deg", float, 0.05, positive=True),
                    h.get("timeout_s", float, 30.0, positive=True), h.get("retries", int, 3, minimum=0),
                    h.get("baud", int, 9600, positive=True), h.get("speed_fraction", float, 1.0, positive=True),
                    h.get("command_timeout_s", float, 0.5, positive=True), h.get("poll_s", float, 0.05, positive=True))
    if head.speed_fraction > 1:
        h.fail("speed_fraction", f"must be in (0, 1], got {head.speed_fraction}")
    if driver != "simulated" and not head.port:
        h.fail("port", f"the {driver} driver needs a serial port")
    g = top.table("grid", {})
    grid = GridSpec(g.get("n_pan", int, None, positive=True), g.get("n_tilt", int, None, positive=True),
                    g.get("overlap", float, None, minimum=0.0))
    if grid.overlap is not None and grid.overlap >= 0.5:
        g.fail("overlap", f"must be below 0.5 (a fraction of the frame per side), got {grid.overlap}")
    if grid.overlap is None and (grid.n_pan is None or grid.n_tilt is None):
        g.fail("n_pan", "give n_pan and n_tilt, or overlap")
    if grid.n_pan is not None and grid.n_tilt is not None and grid.n_pan * grid.n_tilt > MAX_DIRECTIONS:
        g.fail("n_pan", f"{grid.n_pan} x {grid.n_tilt} directions is above the limit of {MAX_DIRECTIONS}")
    bracket = _bracket(top.table("bracket"))
    return Rig(top.get("name", str, Path(source).stem), top.get("description", str, ""), cameras, mounting, head,
               bracket, grid, source, toml_text, _sun(top.table("sun") if "sun" in data else None),
               _dark(top.table("dark") if "dark" in data else None, bracket))


def load_rig(path: str | Path) -> Rig:
    """Read and validate a rig TOML file; errors name the file and the key."""
    path = Path(path)
    text = read_text_file(path, "rig file")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputFileError(path, f"not valid TOML ({exc})") from None
    return rig_from_dict(data, str(path), text)


def load_preset(name: str) -> Rig:
    """A built-in rig of the paper (``paper-timelapse``, ``paper-gigapixel``) or the test rig ``small``.

    Parameters
    ----------
    name : str
        ``"paper-timelapse"`` (wide-angle lens, 12 x 3 directions), ``"paper-gigapixel"`` (telephoto lens,
        60 x 21 directions) or ``"small"``.

    Returns
    -------
    Rig
        The preset, validated, with ``source`` ``preset:NAME`` and its TOML text.

    Raises
    ------
    ConfigurationError
        For another name.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 3 (Baumer HXG20 cameras, 2048 x 1088 px, 12 bits; Kodak No. 34A
       and Fujifilm SP-18 filters; wide-angle 95° x 61° and telephoto 14.5° x 10.8° lenses), Table 1
       (hardware), Sec. 4.1 (fifteen exposures from 252 ms to 0.015 ms), Sec. 4.5, Table 2 (36 and 1260
       directions).
    """
    if name not in PRESETS:
        raise ConfigurationError(f"unknown preset {name!r}; built-in presets are {', '.join(PRESETS)}")
    text = resources.files("omnispectral").joinpath("data", "rigs", f"{name}.toml").read_text(encoding="utf-8")
    return rig_from_dict(tomllib.loads(text), f"preset:{name}", text)


def resolve_rig(preset: str | None = None, rig_path: str | Path | None = None) -> Rig:
    """The rig named on a command line: exactly one of a preset name or a TOML file."""
    if (preset is None) == (rig_path is None):
        raise ConfigurationError("give either --preset NAME or --rig FILE")
    return load_preset(preset) if preset is not None else load_rig(rig_path)


def rig_with_camera_settings(rig: Rig, settings: dict[str, dict]) -> Rig:
    """``rig`` with keys of ``[cameras.X]`` replaced (``{"A": {"raw": {...}, "black_level_dn": 64}}``; a nested
    table such as ``noise`` is updated key by key), validated again, its TOML text rewritten."""
    data = tomllib.loads(rig_toml(rig))
    for name, values in settings.items():
        cam = data["cameras"][name]
        for key, value in values.items():
            if isinstance(value, dict) and isinstance(cam.get(key), dict):
                cam[key] = {**cam[key], **value}
            else:
                cam[key] = value
    text = tomli_w.dumps(data)
    return rig_from_dict(tomllib.loads(text), rig.source, text)


def one_camera_rig(rig: Rig) -> Rig:
    """``rig`` with camera A only (three bands; camera B and its mounting removed), its TOML text rewritten."""
    if rig.camera_names == ("A",):
        return rig
    data = tomllib.loads(rig_toml(rig))
    del data["cameras"]["B"]
    data.pop("mounting", None)
    data["name"] = f"{rig.name}-A"
    description = data.get("description", "")
    data["description"] = f"{description} (camera A only: three bands)" if description else "camera A only"
    text = tomli_w.dumps(data)
    return rig_from_dict(tomllib.loads(text), rig.source, text)


def rig_toml(rig: Rig) -> str:
    """TOML text of a rig (its original text when it was read from TOML, else a faithful rendering)."""
    if rig.toml_text:
        return rig.toml_text

    def drop_none(x):
        if isinstance(x, dict):
            return {k: drop_none(v) for k, v in x.items() if v is not None}
        return [drop_none(v) for v in x] if isinstance(x, list | tuple) else x

    d = drop_none(rig.to_dict())
    d.pop("source", None)
    d["bracket"] = {"exposures_s": list(rig.bracket.exposures_s)}
    if rig.sun is not None:
        d["sun"] = {**d["sun"], "exposures_s": list(rig.sun.exposures_s)}
    return tomli_w.dumps(d)
