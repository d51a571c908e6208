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

import importlib.util
import os
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


#: ``cti = "simulator"``: the simulated producer shipped in the ``genicam`` package (:mod:`.gentl`)
SIMULATOR_ALIAS = "simulator"


def camera_producer(rig: Rig, name: str) -> str | None:
    """The GenTL producer a camera's ``cti`` key names: ``"simulator"``, or a path (``~`` expanded, relative
    paths from the rig file's folder); ``None`` without a ``cti`` key."""
    cti = rig.cameras[name].device.get("cti")
    if not cti:
        return None
    cti = str(cti)
    if cti == SIMULATOR_ALIAS:
        return cti
    path = Path(cti).expanduser()
    if not path.is_absolute() and rig.source and Path(rig.source).exists():
        path = Path(rig.source).resolve().parent / path
    return str(path)


def rig_producers(rig: Rig) -> list[str]:
    """GenTL producers named by the rig's cameras (``cti`` keys: :func:`camera_producer`), each once."""
    out = []
    for name in rig.cameras:
        cti = camera_producer(rig, name)
        if cti and cti not in out:
            out.append(cti)
    return out


def _installed(module: str) -> bool:
    """Whether ``module`` can be imported, without importing it (harvesters and genicam load native libraries)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def simulated_producer_file() -> Path | None:
    """Where the ``genicam`` package's simulated producer ``viky.cti`` is, without importing the package
    (``None``: genicam is not installed)."""
    try:
        spec = importlib.util.find_spec("genicam")
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None:
        return None
    return Path(spec.origin).resolve().parent / "viky.cti"


def environment_producers() -> list[Path]:
    """``*.cti`` files in the ``GENICAM_GENTL64_PATH`` directories (where a capture also looks for producers)."""
    out: list[Path] = []
    for d in os.environ.get("GENICAM_GENTL64_PATH", "").split(os.pathsep):
        if d and Path(d).is_dir():
            out.extend(sorted(Path(d).glob("*.cti")))
    return out


def _port_exists(port: str) -> bool | None:
    """Whether a head's serial port is there (a device file or a port the system lists); ``None`` for a pyserial
    URL (``socket://…``, ``rfc2217://…``), which only connecting can tell."""
    if "://" in port:
        return None
    if Path(port).exists():
        return True
    return port in {p.device for p in list_ports.comports()}


def device_problems(rig: Rig) -> list[str]:
    """What would stop a capture with the rig's devices before its first frame, found without talking to any
    device: the head's serial port, the cameras' device tables, their GenTL producers (``cti`` files that do
    not exist, or none at all) and two cameras with one serial number or user id.  One sentence per problem,
    naming the rig file's table; an empty list when nothing is wrong (or the rig is all simulated)."""
    problems: list[str] = []
    if rig.head.driver in ("rodeon", "merlin"):
        if not rig.head.port:
            problems.append(f"[head] port: not given (the serial port of the {rig.head.driver} head, e.g. "
                            "/dev/ttyUSB0; 'omnispectral devices list' lists them)")
        elif _port_exists(rig.head.port) is False:
            problems.append(f"[head] port {rig.head.port}: not found ('omnispectral devices list' lists the serial "
                            "ports; is the head plugged in?)")
    genicam = [n for n in rig.camera_names if rig.cameras[n].device.get("driver") == "genicam"]
    if not genicam:
        return problems
    missing = [m for m in ("harvesters", "genicam") if not _installed(m)]
    if missing:
        problems.append(f"GenICam cameras need {' and '.join(missing)}: pip install 'omnispectral[devices]'")
    for name in genicam:
        try:
            camera_options(rig, name)
        except ConfigurationError as exc:
            problems.append(str(exc).removeprefix(f"{rig.source}: "))
    by_producer: dict[str, list[str]] = {}
    for name in genicam:
        cti = camera_producer(rig, name)
        if cti is not None:
            by_producer.setdefault(cti, []).append(name)
    for cti, names in by_producer.items():
        tables = ", ".join(f"[cameras.{n}]" for n in names)
        if cti == SIMULATOR_ALIAS:
            path = simulated_producer_file()
            if path is None:
                if "genicam" not in missing:
                    problems.append(f"{tables} device: cti = \"simulator\" is the producer shipped in the genicam "
                                    "package, which is not installed: pip install 'omnispectral[devices]'")
            elif not path.is_file():
                problems.append(f"{tables} device: cti = \"simulator\": the genicam package has no {path}")
        elif not Path(cti).is_file():
            relative = not Path(str(rig.cameras[names[0]].device["cti"])).expanduser().is_absolute()
            problems.append(f"{tables} device: GenTL producer {cti} "
                            + ("is not a file" if Path(cti).exists() else "does not exist")
                            + (" (a relative cti is read from the rig file's folder)" if relative else ""))
    if not by_producer and not environment_producers():
        problems.append("no GenTL producer: give the camera maker's .cti file as cti = \"…\" in each camera's device "
                        "table (or \"simulator\"), or set GENICAM_GENTL64_PATH to its folder")
    for key in ("serial", "user_id"):
        seen: dict[str, list[str]] = {}
        for name in genicam:
            value = rig.cameras[name].device.get(key)
            if value is not None:
                seen.setdefault(str(value), []).append(name)
        for value, names in seen.items():
            if len(names) > 1:
                problems.append(f"{', '.join(f'[cameras.{n}]' for n in names)} device: the same {key} {value!r}: "
                                f"each camera needs its own {key} ('omnispectral devices list' shows them)")
    return problems


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


__all__ = ["GENICAM_KEYS", "SIMULATOR_ALIAS", "DeviceError", "camera_options", "camera_producer", "device_problems",
           "environment_producers", "head_kwargs", "list_serial_ports", "open_cameras", "open_head", "rig_device_kind",
           "rig_producers", "simulated_producer_file"]
