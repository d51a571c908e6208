"""Real device drivers, and opening the devices a rig file names.

- :mod:`~omnispectral.capture.drivers.rodeon`, :mod:`~omnispectral.capture.drivers.merlin`: serial pan/tilt
  heads (pyserial), on the shared :mod:`~omnispectral.capture.drivers.head_base` and
  :mod:`~omnispectral.capture.drivers.serial_link`;
- :mod:`~omnispectral.capture.drivers.gentl`: GenICam cameras through a GenTL producer (harvesters);
- :mod:`~omnispectral.sim.emulators`: both heads emulated on pseudo-terminals, with faults.

A rig's ``[head]`` table selects ``driver = "rodeon" | "merlin"`` and ``port``; each camera's
``device`` table ``driver = "genicam"`` with the keys in :data:`GENICAM_KEYS`.
"""

from __future__ import annotations

from pathlib import Path

from serial.tools import list_ports

from omnispectral.capture.devices import Camera, DeviceError, PanTiltHead
from omnispectral.capture.drivers.merlin import MerlinHead
from omnispectral.capture.drivers.rodeon import RodeonHead
from omnispectral.errors import ConfigurationError
from omnispectral.rig import Rig

#: keys of a camera's ``device = { driver = "genicam", … }`` table
GENICAM_KEYS = ("driver", "cti", "serial", "user_id", "pixel_format", "gain_db", "fixed_exposure", "frame_rate_hz")


def head_kwargs(rig: Rig) -> dict:
    """Driver parameters from the rig's ``[head]`` table."""
    h = rig.head
    return {"baud": h.baud, "command_timeout_s": h.command_timeout_s, "retries": h.retries,
            "tolerance_deg": h.position_tolerance_deg, "settle_s": h.settle_s, "speed_fraction": h.speed_fraction,
            "poll_s": h.poll_s}


def open_head(rig: Rig) -> PanTiltHead:
    """Connect to and initialise the serial head the rig names (``rodeon`` or ``merlin``)."""
    drivers = {"rodeon": RodeonHead, "merlin": MerlinHead}
    if rig.head.driver not in drivers:
        raise ConfigurationError(f"{rig.source}: [head] driver {rig.head.driver!r} is not a serial head driver")
    return drivers[rig.head.driver](rig.head.port, **head_kwargs(rig))


def camera_options(rig: Rig, name: str) -> dict:
    """The checked ``device`` table of a GenICam camera as keyword arguments of ``GenTLSystem.open``."""
    spec = rig.cameras[name]
    dev = dict(spec.device)
    unknown = sorted(set(dev) - set(GENICAM_KEYS))
    if unknown:
        raise ConfigurationError(f"{rig.source}: [cameras.{name}] device: unknown keys {unknown} "
                                 f"(known: {', '.join(GENICAM_KEYS)})")
    if "serial" not in dev and "user_id" not in dev:
        raise ConfigurationError(f"{rig.source}: [cameras.{name}] device: give serial or user_id")
    opts = {k: dev[k] for k in ("pixel_format", "gain_db", "fixed_exposure", "frame_rate_hz") if k in dev}
    if "serial" in dev:
        opts["serial"] = str(dev["serial"])
    if "user_id" in dev:
        opts["user_id"] = str(dev["user_id"])
    return {**opts, "width_px": spec.width_px, "height_px": spec.height_px, "bit_depth": spec.bit_depth}


def rig_producers(rig: Rig) -> list[str]:
    """GenTL producers named by the rig's cameras (``cti`` keys; relative paths from the rig file's folder)."""
    out = []
    for spec in rig.cameras.values():
        cti = spec.device.get("cti")
        if cti and cti != "simulator" and not Path(cti).is_absolute() and rig.source and Path(rig.source).exists():
            cti = str(Path(rig.source).parent / cti)
        if cti and cti not in out:
            out.append(cti)
    return out


def open_cameras(rig: Rig):
    """Open both GenICam cameras of the rig; returns ``(cameras by name, GenTLSystem)`` (close the system)."""
    # lazy: harvesters and genicam load the GenTL native libraries, only wanted when cameras are used
    from omnispectral.capture.drivers.gentl import GenTLSystem, producer_paths

    system = GenTLSystem(producer_paths(rig_producers(rig)))
    cams: dict[str, Camera] = {}
    try:
        for name in rig.cameras:
            cams[name] = system.open(name, **camera_options(rig, name))
    except BaseException:
        system.close()
        raise
    return cams, system


def rig_device_kind(rig: Rig) -> str:
    """``"simulated"`` (everything simulated), ``"real"`` (GenICam cameras, any head), or an error for mixtures."""
    cams = {c.device.get("driver", "simulated") for c in rig.cameras.values()}
    if cams == {"simulated"} and rig.head.driver == "simulated":
        return "simulated"
    if cams == {"genicam"}:
        return "real"
    raise ConfigurationError(f"{rig.source}: cameras {sorted(cams)} with head {rig.head.driver!r}: simulated cameras "
                             "render what the simulated head points at, so they need driver = \"simulated\" for the "
                             "head too; real cameras need driver = \"genicam\" on both")


def list_serial_ports() -> list[dict]:
    """Serial ports the operating system reports (device, description, hardware id)."""
    return [{"device": p.device, "description": p.description, "hwid": p.hwid} for p in list_ports.comports()]


__all__ = ["GENICAM_KEYS", "DeviceError", "camera_options", "head_kwargs", "list_serial_ports", "open_cameras",
           "open_head", "rig_device_kind", "rig_producers"]
