"""GenICam cameras through a GenTL producer with ``harvesters``.

A GenTL producer (a ``.cti`` file from the camera maker, e.g. Baumer's for the paper's HXG20) exposes
the cameras; harvesters loads it, lists the devices and opens one as an image acquirer whose features
follow the GenICam SFNC names: ``PixelFormat``, ``Width``/``Height``, ``ExposureTime`` (µs; older
devices ``ExposureTimeAbs``), ``Gain`` (dB), ``TriggerMode``/``TriggerSource``/``TriggerSoftware``,
``DeviceTemperature``.  :class:`GenICamCamera` implements
:class:`~omnispectral.capture.devices.Camera` with them: the exposure is read back after it is set,
frames are fetched with a timeout, and the buffer's timestamp and the device temperature (when the
device has them) go into the frame metadata that the capture loop stores in the journal.

Producers are found from explicit paths, the standard ``GENICAM_GENTL64_PATH`` directories, and the
alias ``"simulator"``: the simulated producer ``viky.cti`` shipped inside the PyPI package ``genicam``
(three simulated cameras, serial numbers 0, 1, 2, 400 x 400 px, RGBa8 or Mono8, free-running, with no
exposure, gain, trigger, timestamp or temperature features).  A device without a software trigger is
run free-running and :meth:`GenICamCamera.trigger` discards the frames queued before it; a device without
an exposure feature is refused unless the rig allows it with ``fixed_exposure = true`` (the frames then
record ``exposure_controlled: false``).
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path

import genicam
import numpy as np
from harvesters.core import Harvester

from omnispectral.capture.devices import DeviceDisconnected, DeviceError, DeviceTimeout
from omnispectral.capture.drivers import SIMULATOR_ALIAS, environment_producers
from omnispectral.errors import ConfigurationError

__all__ = ["SIMULATOR_ALIAS", "GenICamCamera", "GenTLSystem", "bits_of_pixel_format", "cfa_pattern_of",
           "frame_to_uint16", "producer_paths", "simulated_producer_path"]

log = logging.getLogger(__name__)

_GENTL_ERRORS = (genicam.gentl.GenericException, genicam.genapi.GenericException)


def simulated_producer_path() -> Path:
    """The simulated GenTL producer ``viky.cti`` inside the installed ``genicam`` package."""
    return Path(genicam.__file__).resolve().parent / "viky.cti"


def producer_paths(extra: list[str] | tuple[str, ...] = (), environment: bool = True) -> list[Path]:
    """GenTL producers to load: ``extra`` (paths or ``"simulator"``), then ``*.cti`` in ``GENICAM_GENTL64_PATH``."""
    out: list[Path] = []
    for item in extra:
        p = simulated_producer_path() if item == SIMULATOR_ALIAS else Path(item).expanduser()
        if not p.is_file():
            raise ConfigurationError(f"GenTL producer {p} does not exist")
        out.append(p.resolve())
    if environment:
        out.extend(p.resolve() for p in environment_producers())
    return list(dict.fromkeys(out))


def bits_of_pixel_format(pixel_format: str) -> int:
    """Significant bits per sample of an SFNC pixel format name (``BayerRG12`` → 12, ``RGBa8`` → 8)."""
    m = re.search(r"(\d+)(?:p|Packed)?$", pixel_format)
    if not m:
        raise ConfigurationError(f"pixel format {pixel_format!r}: cannot tell its bit depth")
    return int(m.group(1))


def cfa_pattern_of(pixel_format: str) -> str | None:
    """The 2 x 2 colour filter layout of an SFNC Bayer format, first row first (``BayerRG12`` → ``RGGB``)."""
    m = re.match(r"Bayer(RG|GR|GB|BG)", pixel_format)
    return None if m is None else {"RG": "RGGB", "GR": "GRBG", "GB": "GBRG", "BG": "BGGR"}[m.group(1)]


def frame_to_uint16(data: np.ndarray, width: int, height: int, pixel_format: str) -> np.ndarray:
    """A GenTL image component as the session's uint16 frame: (H, W) for Mono/Bayer, (H, W, 3) RGB for colour.

    RGBa/BGRa lose their alpha channel; BGR orders are reversed to RGB; samples keep their values.
    """
    n = data.size // (width * height)
    if n * width * height != data.size:
        raise DeviceError(f"{data.size} samples do not make a {width} x {height} image ({pixel_format})")
    img = data.reshape(height, width, n) if n > 1 else data.reshape(height, width)
    if n > 1:
        img = img[..., :3]
        if pixel_format.upper().startswith("BGR"):
            img = img[..., ::-1]
    return np.ascontiguousarray(img, dtype=np.uint16)


def _describe(info) -> dict:
    d = info.property_dict  # harvesters fills in None for what the producer does not report
    return {"vendor": d.get("vendor") or "", "model": d.get("model") or "", "serial": d.get("serial_number") or "",
            "user_id": d.get("user_defined_name") or "", "id": d.get("id_") or ""}


# GenApi access modes (EAccessMode): not implemented, not available, write-only, read-only, read-write
_NI, _NA, _WO, _RO, _RW = range(5)


def _available(node) -> bool:
    return node.get_access_mode() not in (_NI, _NA)


def _writable(node) -> bool:
    return node.get_access_mode() in (_WO, _RW)


class GenTLSystem:
    """Loaded GenTL producers (one ``harvesters.Harvester``) from which cameras are listed and opened."""

    def __init__(self, producers: list[Path]):
        if not producers:
            raise ConfigurationError("no GenTL producer: give a .cti file (or 'simulator') or set "
                                     "GENICAM_GENTL64_PATH")
        self.producers = producers
        self.harvester = Harvester()
        try:
            for p in producers:
                self.harvester.add_file(str(p), check_existence=True, check_validity=True)
            self.harvester.update()
        except (*_GENTL_ERRORS, OSError, FileNotFoundError) as exc:
            self.harvester.reset()
            raise DeviceError(f"GenTL producers {[str(p) for p in producers]} could not be loaded: {exc}") from None
        self._open: list[GenICamCamera] = []

    def devices(self) -> list[dict]:
        """Every camera the producers offer: vendor, model, serial, user id, GenTL id."""
        return [_describe(info) for info in self.harvester.device_info_list]

    def find(self, serial: str | None = None, user_id: str | None = None) -> int:
        """Index of the device with this serial number or user id (exactly one must match)."""
        found = self.devices()
        hits = [i for i, d in enumerate(found)
                if (serial is None or d["serial"] == str(serial)) and (user_id is None or d["user_id"] == user_id)]
        if len(hits) != 1:
            wanted = f"serial {serial!r}" if serial is not None else f"user id {user_id!r}"
            seen = ", ".join(f"{d['model']} serial {d['serial']!r}" + (f" id {d['user_id']!r}" if d["user_id"] else "")
                             for d in found) or "none"
            raise DeviceError(f"GenICam camera with {wanted}: {'not found' if not hits else 'ambiguous'} "
                              f"(cameras found: {seen})")
        return hits[0]

    def open(self, name: str, *, serial: str | None = None, user_id: str | None = None, **options) -> GenICamCamera:
        """Open one camera (see :class:`GenICamCamera` for the options)."""
        if serial is None and user_id is None:
            raise ConfigurationError(f"camera {name}: give the device's serial or user_id")
        index = self.find(serial, user_id)
        info = self.devices()[index]
        try:
            ia = self.harvester.create(index)
        except _GENTL_ERRORS as exc:
            raise DeviceError(f"camera {name} ({info['model']} serial {info['serial']}): cannot open ({exc})") from None
        cam = GenICamCamera(name, ia, info, **options)
        self._open.append(cam)
        return cam

    def close(self) -> None:
        for cam in self._open:
            cam.close()
        self._open.clear()
        self.harvester.reset()


class GenICamCamera:
    """One GenICam camera (see the module docstring), implementing :class:`~omnispectral.capture.devices.Camera`.

    Parameters
    ----------
    name
        The rig's name for it (``A``/``B``), used in every error message.
    pixel_format
        SFNC name to set (``BayerRG12``, ``Mono16``…); None keeps the device's current format.
    width_px, height_px
        Frame size the rig expects; set on the device when writable, else checked.
    bit_depth
        The rig's bit depth; must match the pixel format's.
    gain_db
        Analogue gain to set (needs a ``Gain`` feature); None leaves it.
    fixed_exposure
        Accept a device that has no exposure feature (test pattern generators).
    frame_rate_hz
        Free-running devices only: frame rate to request (when writable).
    """

    def __init__(self, name: str, ia, info: dict, *, pixel_format: str | None = None, width_px: int | None = None,
                 height_px: int | None = None, bit_depth: int | None = None, gain_db: float | None = None,
                 fixed_exposure: bool = False, frame_rate_hz: float | None = None):
        self.name, self.ia, self.info = name, ia, info
        self.label = f"camera {name} ({info['vendor']} {info['model']} serial {info['serial']})"
        self.nodes = ia.remote_device.node_map
        self.exposure_s: float | None = None
        self.fixed_exposure = fixed_exposure
        self._trigger_time: float | None = None
        self._closed = False
        try:
            self._configure(pixel_format, width_px, height_px, bit_depth, gain_db, frame_rate_hz)
            self.ia.start()
        except _GENTL_ERRORS as exc:
            self.close()
            raise DeviceError(f"{self.label}: configuration failed ({_one_line(exc)})") from None
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ features
    def _node(self, *names: str):
        for n in names:
            if self.nodes.has_node(n):
                node = self.nodes.get_node(n)
                if _available(node):
                    return node
        return None

    def has(self, name: str) -> bool:
        return self._node(name) is not None

    def _configure(self, pixel_format, width_px, height_px, bit_depth, gain_db, frame_rate_hz) -> None:
        fmt = self._node("PixelFormat")
        if pixel_format is not None:
            offered = tuple(fmt.symbolics) if fmt is not None else ()
            if pixel_format not in offered:
                raise DeviceError(f"{self.label}: pixel format {pixel_format!r} not offered (offers "
                                  f"{', '.join(offered) or 'none'})")
            fmt.value = pixel_format
        self.pixel_format = str(fmt.value) if fmt is not None else "Mono8"
        self.bit_depth = bits_of_pixel_format(self.pixel_format)
        if bit_depth is not None and bit_depth != self.bit_depth:
            raise ConfigurationError(f"{self.label}: the rig says bit_depth {bit_depth} but pixel format "
                                     f"{self.pixel_format} has {self.bit_depth} bits")
        for key, want in (("Width", width_px), ("Height", height_px)):
            node = self._node(key)
            if want is None or node is None or node.value == want:
                continue
            if _writable(node) and node.min <= want <= node.max:
                node.value = int(want)
            else:
                raise ConfigurationError(f"{self.label}: the rig expects {key.lower()} {want} px, the camera gives "
                                         f"{node.value} px and cannot be set to {want}")
        for auto in ("ExposureAuto", "GainAuto"):
            node = self._node(auto)
            if node is not None and _writable(node) and "Off" in node.symbolics:
                node.value = "Off"
        if gain_db is not None:
            gain = self._node("Gain", "GainRaw")
            if gain is None:
                raise DeviceError(f"{self.label}: the rig sets gain_db = {gain_db} but the camera has no Gain feature")
            gain.value = float(min(max(gain_db, gain.min), gain.max))
        self.software_trigger = self._node("TriggerSoftware") is not None and self._node("TriggerMode") is not None
        if self.software_trigger:
            sel = self._node("TriggerSelector")
            if sel is not None and "FrameStart" in sel.symbolics:
                sel.value = "FrameStart"
            self._node("TriggerMode").value = "On"
            src = self._node("TriggerSource")
            if src is not None:
                src.value = "Software"
        else:
            rate = self._node("AcquisitionFrameRate")
            if frame_rate_hz is not None and rate is not None and _writable(rate):
                rate.value = float(min(max(frame_rate_hz, rate.min), rate.max))
            log.info("%s: no software trigger; running free and discarding frames queued before each trigger",
                     self.label)
        if self._node("ExposureTime", "ExposureTimeAbs") is None and not self.fixed_exposure:
            raise DeviceError(f"{self.label}: the camera has no ExposureTime feature, so it cannot bracket "
                              "exposures (set fixed_exposure = true in the rig's device table to accept it)")

    # ------------------------------------------------------------------ Camera
    def set_exposure(self, exposure_s: float) -> float:
        """Set the exposure (clamped to the device's range) and return the value the camera reports back."""
        if not (np.isfinite(exposure_s) and exposure_s > 0):
            raise DeviceError(f"{self.label}: exposure {exposure_s} s is not positive")
        node = self._node("ExposureTime", "ExposureTimeAbs")
        if node is None:  # fixed_exposure: nothing to set
            self.exposure_s = None
            return float(exposure_s)
        try:
            node.value = float(min(max(exposure_s * 1e6, node.min), node.max))
            self.exposure_s = float(node.value) * 1e-6
        except _GENTL_ERRORS as exc:
            raise DeviceError(f"{self.label}: setting the exposure to {exposure_s} s failed "
                              f"({_one_line(exc)})") from None
        return self.exposure_s

    def trigger(self) -> None:
        """Start one exposure: a software trigger, or on a free-running camera, drop the frames queued so far."""
        try:
            if self.software_trigger:
                self._node("TriggerSoftware").execute()
            else:
                while (buf := self.ia.try_fetch(timeout=0.001)) is not None:
                    buf.queue()
        except _GENTL_ERRORS as exc:
            raise DeviceDisconnected(f"{self.label}: trigger failed ({_one_line(exc)})") from None
        self._trigger_time = time.time()

    def read_frame(self, timeout_s: float) -> tuple[np.ndarray, dict]:
        """The next frame (uint16) and its metadata: pixel format, exposure read back, timestamp, temperature."""
        if self._trigger_time is None:
            raise DeviceError(f"{self.label}: read without a trigger")
        try:
            buf = self.ia.try_fetch(timeout=timeout_s)
        except _GENTL_ERRORS as exc:
            raise DeviceDisconnected(f"{self.label}: fetching a frame failed ({_one_line(exc)})") from None
        if buf is None:
            raise DeviceTimeout(f"{self.label}: no frame within {timeout_s:g} s")
        try:
            comp = buf.payload.components[0]
            frame = frame_to_uint16(comp.data, comp.width, comp.height, str(comp.data_format))
            meta = {"device": self.info["model"], "serial": self.info["serial"], "pixel_format": str(comp.data_format),
                    "bit_depth": self.bit_depth, "exposure_controlled": self.exposure_s is not None,
                    "host_trigger_time_unix": round(self._trigger_time, 6)}
            if self.exposure_s is not None:
                meta["exposure_s"] = self.exposure_s
            cfa = cfa_pattern_of(meta["pixel_format"])
            if cfa is not None:  # a raw mosaic: kept as the camera gave it, with its layout and black level
                meta["cfa_pattern"] = cfa
                black = self._node("BlackLevel")
                if black is not None:
                    meta["black_level"] = float(black.value)
            try:
                meta["camera_timestamp_ns"] = int(buf.timestamp_ns)
            except _GENTL_ERRORS:
                pass  # the producer keeps no timestamps
        finally:
            buf.queue()
        temp = self.temperature_c()
        if temp is not None:
            meta["device_temperature_c"] = temp
        gain = self._node("Gain")
        if gain is not None:
            meta["gain_db"] = float(gain.value)
        self._trigger_time = None
        return frame, meta

    def temperature_c(self) -> float | None:
        """The device's temperature (``DeviceTemperature``, °C), or None when it has no such feature."""
        node = self._node("DeviceTemperature")
        return None if node is None else float(node.value)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self.ia.is_acquiring():
                self.ia.stop()
            self.ia.destroy()
        except _GENTL_ERRORS as exc:
            log.info("%s: close: %s", self.label, exc)


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())
