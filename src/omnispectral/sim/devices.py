"""Simulated devices: a clock that runs only when slept on, a head, cameras and a filter changer, with faults.

They implement the protocols of :mod:`omnispectral.capture.devices` with the same timing rules as real
hardware (travel, settling, exposure and read-out take clock time), so the capture loop runs unchanged on
them; on a :class:`FakeClock` a simulated capture takes no wall time while its timestamps still follow the
timing model.  Faults (no answer, a position off target, a dead device) are injected with
:class:`HeadFaults` / :class:`CameraFaults`.  Each frame's noise comes from its own stream
(:func:`frame_rng`), so a resumed or retried simulation writes the same bytes.
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from omnispectral.capture.devices import Clock, DeviceError, DeviceTimeout, SystemClock
from omnispectral.capture.resume import capture_order
from omnispectral.capture.session import Session
from omnispectral.rig import Rig

__all__ = ["CameraFaults", "FakeClock", "HeadFaults", "Renderer", "SimulatedCamera", "SimulatedFilterChanger",
           "SimulatedHead", "frame_rng", "resume_simulated_devices", "stand_in_head"]


class FakeClock:
    """A clock that advances only when slept on: simulated time, no waiting."""

    def __init__(self, start: _dt.datetime):
        if start.tzinfo is None:
            start = start.replace(tzinfo=_dt.UTC)
        self._start = start
        self._elapsed = 0.0

    def now(self) -> _dt.datetime:
        return self._start + _dt.timedelta(seconds=self._elapsed)

    def monotonic(self) -> float:
        return self._elapsed

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._elapsed += float(seconds)

    def set_elapsed(self, seconds: float) -> None:
        """Set the simulated time since the start exactly (a resumed simulation's clock)."""
        self._elapsed = float(seconds)


@dataclass
class HeadFaults:
    """Injected head faults: silent calls (``silent_calls`` of the next ``position``/``wait`` calls time out),
    a permanent offset of the reported position, or a head that stops answering after ``dead_after_moves``."""

    silent_calls: int = 0
    offset_deg: tuple[float, float] = (0.0, 0.0)
    dead_after_moves: int | None = None


@dataclass
class CameraFaults:
    """Injected camera faults: the next ``timeouts`` reads time out; dead after ``dead_after_frames`` frames."""

    timeouts: int = 0
    dead_after_frames: int | None = None


class SimulatedHead:
    """A pan/tilt head that travels at its speeds and settles on the given clock."""

    def __init__(self, clock: Clock, pan_speed_deg_s: float = 60.0, tilt_speed_deg_s: float = 60.0,
                 settle_s: float = 2.0, faults: HeadFaults | None = None):
        self.clock = clock
        self.pan_speed, self.tilt_speed, self.settle_s = pan_speed_deg_s, tilt_speed_deg_s, settle_s
        self.faults = faults or HeadFaults()
        self._pos = (0.0, 0.0)
        self._target = (0.0, 0.0)
        self._arrive_at = 0.0
        self._placed = False
        self.moves = 0

    def _answer(self) -> None:
        if self.faults.dead_after_moves is not None and self.moves > self.faults.dead_after_moves:
            raise DeviceTimeout("pan/tilt head does not answer")
        if self.faults.silent_calls > 0:
            self.faults.silent_calls -= 1
            raise DeviceTimeout("pan/tilt head did not answer in time")

    def move_to(self, pan_deg: float, tilt_deg: float) -> None:
        if not (np.isfinite(pan_deg) and np.isfinite(tilt_deg)) or abs(tilt_deg) > 90.0 + 1e-9:
            raise DeviceError(f"head cannot go to pan {pan_deg} deg, tilt {tilt_deg} deg")
        self.moves += 1
        self._answer()
        resumed_here, self._placed = self._placed and (float(pan_deg), float(tilt_deg)) == self._pos, False
        if resumed_here:  # already at rest there (a resumed run continuing a direction): nothing moves
            self._arrive_at = self.clock.monotonic()
            return
        travel = max(abs(pan_deg - self._pos[0]) / self.pan_speed, abs(tilt_deg - self._pos[1]) / self.tilt_speed)
        self._target = (float(pan_deg), float(tilt_deg))
        self._arrive_at = self.clock.monotonic() + travel + self.settle_s

    def position(self) -> tuple[float, float]:
        self._answer()
        if self.clock.monotonic() >= self._arrive_at:
            self._pos = self._target
        return (self._pos[0] + self.faults.offset_deg[0], self._pos[1] + self.faults.offset_deg[1])

    def wait_settled(self, timeout_s: float) -> tuple[float, float]:
        self._answer()
        wait = self._arrive_at - self.clock.monotonic()
        if wait > timeout_s:
            self.clock.sleep(timeout_s)
            raise DeviceTimeout(f"head still moving after {timeout_s} s")
        self.clock.sleep(wait)
        return self.position()

    def place_at(self, pan_deg: float, tilt_deg: float) -> None:
        """Put the head at rest at a position (a resumed simulation continues where the last run stopped)."""
        self._pos = self._target = (float(pan_deg), float(tilt_deg))
        self._arrive_at = self.clock.monotonic()
        self._placed = True

    @property
    def true_position(self) -> tuple[float, float]:
        """Where the simulated head really points (what the renderer uses)."""
        return self._target if self.clock.monotonic() >= self._arrive_at else self._pos

    def close(self) -> None:
        pass


def frame_rng(seed: int, camera: str, pan_deg: float, tilt_deg: float, exposure_s: float,
              filter_name: str | None = None) -> np.random.Generator:
    """The noise stream of one simulated frame, spawned from the seed, the camera, the direction (its
    exact pan/tilt), the exposure and the filter in front of the lens, if any (``numpy.random.SeedSequence``):
    a frame's noise does not depend on what was rendered before it, so a resumed or retried simulation
    gives the same frames."""
    words = np.array([pan_deg, tilt_deg, exposure_s], np.float64).view(np.uint32)
    entropy = [int(seed) % (1 << 63), *camera.encode("utf-8")[:8], *(int(w) for w in words)]
    if filter_name:
        entropy += [0x46494C54, *filter_name.encode("utf-8")[:32]]
    return np.random.default_rng(np.random.SeedSequence(entropy))


#: ``render(camera_name, pan_deg, tilt_deg, exposure_s, rng) -> uint16 frame`` of a simulated camera; with a
#: filter in front of the lens the camera adds ``filter_name=NAME``.
Renderer = Callable[..., np.ndarray]


class SimulatedFilterChanger:
    """A filter slider in front of the simulated cameras: each move takes ``change_s`` of clock time."""

    def __init__(self, cameras: dict, clock: Clock, change_s: float = 2.0):
        self.cameras, self.clock, self.change_s = cameras, clock, float(change_s)
        self.filter_name: str | None = None

    def insert(self, filter_name: str) -> None:
        self.clock.sleep(self.change_s)
        self.filter_name = filter_name
        for cam in self.cameras.values():
            cam.filter_name = filter_name

    def remove(self) -> None:
        self.clock.sleep(self.change_s)
        self.filter_name = None
        for cam in self.cameras.values():
            cam.filter_name = None


@dataclass
class SimulatedCamera:
    """A camera whose frames come from a renderer at the head's true position; exposures take clock time."""

    name: str
    head: SimulatedHead
    render: Renderer
    clock: Clock
    bit_depth: int = 12
    readout_s: float = 0.0095
    seed: int = 0
    faults: CameraFaults = field(default_factory=CameraFaults)
    #: what the camera reports with every frame besides time and exposure (a raw camera's CFA layout, black level)
    metadata: dict = field(default_factory=dict)
    exposure_s: float = 0.01
    frames_read: int = 0
    #: the filter a :class:`SimulatedFilterChanger` put in front of the lens (``None``: none)
    filter_name: str | None = None
    #: the longest exposure the camera can set (``None``: any); a longer request is clamped, as real cameras do
    max_exposure_s: float | None = None
    _pending: tuple | None = None


    def set_exposure(self, exposure_s: float) -> float:
        if not (np.isfinite(exposure_s) and exposure_s > 0):
            raise DeviceError(f"camera {self.name}: exposure {exposure_s} s is not positive")
        self.exposure_s = float(exposure_s if self.max_exposure_s is None else min(exposure_s, self.max_exposure_s))
        return self.exposure_s

    def trigger(self) -> None:
        pan, tilt = self.head.true_position
        self._pending = (pan, tilt, self.exposure_s, self.clock.now(), self.clock.monotonic(), self.filter_name)

    def read_frame(self, timeout_s: float) -> tuple[np.ndarray, dict]:
        if self._pending is None:
            raise DeviceError(f"camera {self.name}: read without a trigger")
        if self.faults.dead_after_frames is not None and self.frames_read >= self.faults.dead_after_frames:
            raise DeviceTimeout(f"camera {self.name} does not answer")
        if self.faults.timeouts > 0:
            self.faults.timeouts -= 1
            self.clock.sleep(timeout_s)
            raise DeviceTimeout(f"camera {self.name}: no frame within {timeout_s} s")
        pan, tilt, exposure, t0, t0_mono, filt = self._pending
        # the frame exists after exposure + read-out (cameras triggered together overlap in time)
        self.clock.sleep(t0_mono + exposure + self.readout_s - self.clock.monotonic())
        rng = frame_rng(self.seed, self.name, pan, tilt, exposure, filt)
        frame = (self.render(self.name, pan, tilt, exposure, rng) if filt is None
                 else self.render(self.name, pan, tilt, exposure, rng, filter_name=filt))
        self._pending = None
        self.frames_read += 1
        # the simulated clock's exact state (float seconds) lets a resumed simulation continue bit-identically
        return frame, {"camera_time": t0.isoformat(timespec="milliseconds"), "exposure_s": exposure,
                       "sim_clock_trigger_s": t0_mono, "sim_clock_read_s": self.clock.monotonic(), **self.metadata}

    def close(self) -> None:
        pass


def resume_simulated_devices(session: Session, clock, head) -> bool:
    """Set a :class:`FakeClock` and a simulated head to the state after the
    session's last recorded frame; False when there is nothing to resume (or no clock state recorded).

    Each frame records the simulated clock's exact float state, so that, with the per-frame noise streams of
    :func:`frame_rng`, a simulation killed and resumed any number of times writes the same bytes as one that
    never stopped."""
    records = session.completed()
    if not records:
        return False
    order = capture_order(session)
    known = [k for k in records if k in order]
    if not known:
        return False
    last = max(known, key=order.__getitem__)
    rec = records[last]
    cam = rec.get("camera_metadata") or {}
    if "sim_clock_read_s" not in cam or "sim_clock_trigger_s" not in cam:
        return False
    d, _, k = last
    bracket_done = all((d, c, k) in records for c in session.cameras())
    # both cameras are triggered together: a half-written exposure restarts from its trigger time
    clock.set_elapsed(float(cam["sim_clock_read_s"] if bracket_done else cam["sim_clock_trigger_s"]))
    head.place_at(float(rec["pan_deg_commanded"]), float(rec["tilt_deg_commanded"]))
    return True


def stand_in_head(rig: Rig) -> SimulatedHead:
    """A head for real cameras on a rig whose head is ``driver = "simulated"``: it only takes the time the rig's
    speeds and settling give on the computer's clock (``capture`` with GenICam cameras and no head)."""
    return SimulatedHead(SystemClock(), rig.head.pan_speed_deg_s, rig.head.tilt_speed_deg_s, rig.head.settle_s)
