"""Capture with the real devices a rig names: run (resumable), dry run (plan only) and probe (talk to each device).

The capture loop is :func:`omnispectral.capture.run.run_capture`, the same one the simulator uses;
this module only opens the devices the rig file names (:mod:`omnispectral.capture.drivers`), runs
the loop on the computer's clock, and always closes the devices again (the head's motors are
stopped).  A run stopped by a device (a pulled cable, a head that never arrives) leaves a valid
session; running the same command again resumes it after its last complete frame.  Where a rig names
simulated devices, the caller passes them in (``head``, ``cameras``: :mod:`omnispectral.sim.devices`);
this module never simulates.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from omnispectral.capture import drivers
from omnispectral.capture.calviews import DEFAULT_N_VIEWS, operator_next_view, record_calibration_views
from omnispectral.capture.darks import record_darks
from omnispectral.capture.devices import DeviceError, ManualFilterChanger, SystemClock
from omnispectral.capture.plan import format_duration, make_plan
from omnispectral.capture.run import RetryPolicy, run_capture
from omnispectral.capture.session import Session
from omnispectral.errors import ConfigurationError, OmnispectralError
from omnispectral.progress import ProgressCallback
from omnispectral.rig import Rig

__all__ = ["capture_calibration_views", "capture_darks", "capture_with_devices", "dry_run", "policy_of", "probe_rig",
           "real_filter_changer"]

log = logging.getLogger(__name__)


def policy_of(rig: Rig) -> RetryPolicy:
    return RetryPolicy(rig.head.retries, rig.head.timeout_s, rig.head.position_tolerance_deg)


def real_filter_changer(rig: Rig, ask=None):
    """The sun bracket's filter changer on real devices: ``changer = "manual"`` asks the operator through
    ``ask(message)`` (default: a prompt on the terminal); a ``"simulated"`` changer has nothing to move on a
    real rig, so the sun bracket is not shot (logged) and the saturated sun stays a lower bound."""
    if rig.sun is None:
        return None
    if rig.sun.changer == "manual":
        return ManualFilterChanger(ask or _ask_on_terminal)
    log.warning("%s: [sun] changer = %r has no device on a real rig: no sun bracket (set changer = \"manual\")",
                rig.source, rig.sun.changer)
    return None


def _ask_on_terminal(message: str) -> None:
    """Print ``message`` on standard error and wait for Enter on standard input."""
    print(f"omnispectral capture: {message}", file=sys.stderr, flush=True)
    sys.stdin.readline()


def capture_with_devices(output: str | Path, rig: Rig, *, progress: ProgressCallback | None = None, ask=None,
                         head=None) -> dict:
    """Capture (or resume) a session at ``output`` with the rig's real devices; returns the run summary.

    ``ask(message)`` waits for the operator to move the sun bracket's filter (:func:`real_filter_changer`).
    ``head``: a head to use instead of opening the rig's (real cameras on a stand-in head, when the rig's head is
    ``driver = "simulated"``: :func:`omnispectral.sim.devices.stand_in_head`); it is closed at the end."""
    if drivers.rig_device_kind(rig) != "real":
        raise ConfigurationError(f"{rig.source}: the rig's devices are all simulated; use 'omnispectral simulate'")
    plan = make_plan(rig)
    session = Session.create(output, rig, plan, kind="capture")
    if head is None and rig.head.driver == "simulated":
        raise ConfigurationError(f"{rig.source}: the rig's head is simulated; pass a stand-in head")
    cams = system = None
    try:
        head = head if head is not None else drivers.open_head(rig)
        cams, system = drivers.open_cameras(rig)
        session.log_event("devices", head=_head_info(rig, head), cameras={n: getattr(c, "info", {})
                                                                         for n, c in cams.items()})
        result = run_capture(session, head, cams, SystemClock(), policy_of(rig), progress,
                             real_filter_changer(rig, ask)).to_dict()
    except DeviceError as exc:  # opening failed: nothing captured this time, the session stays resumable
        session.log_event("stop", reason=str(exc), frames_done=len(session.completed()))
        n_done = len(session.completed())
        result = {"session": str(session.path), "n_planned": Session.n_planned(plan, rig.camera_names), "n_written": 0,
                  "n_already_done": n_done, "complete": n_done >= Session.n_planned(plan, rig.camera_names),
                  "stopped_reason": str(exc)}
    finally:
        if system is not None:
            system.close()
        if head is not None:
            head.close()
    return result


def capture_darks(session_path: str | Path, n_frames: int = 8, *, cameras: dict | None = None,
                  progress: ProgressCallback | None = None) -> dict:
    """Dark frames for every exposure of a session's bracket with the cameras its rig names (lenses capped:
    :func:`omnispectral.capture.darks.record_darks`), or with ``cameras`` when given (an all-simulated rig's
    sensors: :func:`omnispectral.sim.simulate.simulated_dark_cameras`)."""
    session = Session.open(session_path)
    rig = session.rig()
    system = None
    try:
        if cameras is not None:
            cams = cameras
        else:
            cams, system = drivers.open_cameras(rig)
        return record_darks(session, cams, n_frames, rig.head.timeout_s, progress)
    finally:
        if system is not None:
            system.close()


def capture_calibration_views(root: str | Path, rig: Rig, *, n_views: int = DEFAULT_N_VIEWS,
                              board: tuple[int, int] = (9, 6), square_mm: float = 60.0,
                              interval_s: float | None = None, ask=None, say=None, devices=None,
                              progress: ProgressCallback | None = None) -> dict:
    """Chessboard pairs with the rig's cameras into ``ROOT/calibration/`` (:mod:`omnispectral.capture.calviews`;
    ``ROOT`` a session or a time-lapse series): the rig's GenICam cameras with the operator moving the board
    between shots (asked through ``ask(message)``, default a prompt on the terminal, or given ``interval_s``
    seconds), or ``devices = (cameras, next_view)`` when given (an all-simulated rig's cameras in front of a
    simulated board: :func:`omnispectral.sim.simulate.simulated_board_cameras`)."""
    system = None
    try:
        if devices is not None:
            cams, next_view = devices
        else:
            cams, system = drivers.open_cameras(rig)
            next_view = operator_next_view(None if interval_s is not None else (ask or _ask_on_terminal),
                                           interval_s, SystemClock(), say)
        return record_calibration_views(root, rig, cams, next_view, n_views=n_views, board=board,
                                        square_mm=square_mm, timeout_s=rig.head.timeout_s, progress=progress)
    finally:
        if system is not None:
            system.close()


def _head_info(rig: Rig, head) -> dict:
    return {"driver": rig.head.driver, "port": rig.head.port, **getattr(head, "info", {}),
            "steps_per_turn": getattr(head, "steps_per_turn", {})}


def dry_run(rig: Rig, output: str | Path | None = None) -> dict:
    """What a capture would do, without talking to any device: plan, timing, devices named, frames already done,
    and ``problems``: what would stop the capture before its first frame (:func:`drivers.device_problems`: a
    missing GenTL producer, two cameras with one serial number, a head port that is not there…; empty when the
    rig looks usable)."""
    drivers.rig_device_kind(rig)
    plan = make_plan(rig)
    out = {"rig": rig.name, "n_directions": plan.n_directions, "exposures_s": list(plan.exposures_s),
           "n_frames": Session.n_planned(plan, rig.camera_names), "estimated_s": plan.estimated_s,
           "estimated": format_duration(plan.estimated_s),
           "head": {"driver": rig.head.driver, "port": rig.head.port,
                    "port_exists": bool(rig.head.port) and Path(rig.head.port).exists()},
           "cameras": {n: dict(rig.cameras[n].device) for n in rig.camera_names},
           "moves": [{"direction": d.index, "pan_deg": d.pan_deg, "tilt_deg": d.tilt_deg} for d in plan.directions],
           "n_already_done": 0, "session": str(output) if output else None,
           "problems": drivers.device_problems(rig)}
    if output and (Path(output) / "session.json").exists():
        session = Session.open(output)
        if session.plan().to_dict()["directions"] != plan.to_dict()["directions"]:
            raise ConfigurationError(f"{output}: holds a session with a different plan")
        out["n_already_done"] = len(session.completed())
    return out


def probe_rig(rig: Rig) -> list[dict]:
    """Talk to each device the rig names and collect what it answered (one entry per device, errors included)."""
    report = []
    if rig.head.driver != "simulated":
        entry = {"device": f"head ({rig.head.driver})", "port": rig.head.port}
        try:
            head = drivers.open_head(rig)
            try:
                pan, tilt = head.position()
                entry.update(ok=True, info=dict(head.info), steps_per_turn=dict(head.steps_per_turn),
                             resolution_deg={a: 360.0 / n for a, n in head.steps_per_turn.items()},
                             pan_deg=pan, tilt_deg=tilt)
            finally:
                head.close()
        except OmnispectralError as exc:
            entry.update(ok=False, error=str(exc))
        report.append(entry)
    if any(c.device.get("driver") == "genicam" for c in rig.cameras.values()):
        try:
            cams, system = drivers.open_cameras(rig)
        except OmnispectralError as exc:
            report.append({"device": "cameras (genicam)", "ok": False, "error": str(exc)})
        else:
            try:
                for name, cam in cams.items():
                    entry = {"device": f"camera {name}", "ok": True, **cam.info, "pixel_format": cam.pixel_format,
                             "bit_depth": cam.bit_depth, "software_trigger": cam.software_trigger,
                             "exposure_feature": cam.has("ExposureTime") or cam.has("ExposureTimeAbs"),
                             "temperature_c": cam.temperature_c()}
                    report.append(entry)
            finally:
                system.close()
    return report
