"""What the RODEON and Merlin drivers share: angles ↔ motor steps, and waiting until a move has settled.

A head driver knows how to send a go-to to each axis and how to read an axis' position in steps
(and, when the protocol has one, whether the axis is still running).  :class:`SerialHead` turns that
into the :class:`~omnispectral.capture.devices.PanTiltHead` protocol: ``move_to`` commands and returns,
``wait_settled`` polls until both axes stop within the tolerance of their targets, waits the
mechanical settle time and reports the angles read back from the head.  An axis whose position stops
changing short of its target ("never arrives") or that is still moving at the timeout raises a
:class:`~omnispectral.capture.devices.DeviceTimeout` naming the axis, where it stopped and its target,
so the capture loop's bounded retry re-sends the move.
"""

from __future__ import annotations

import logging
import math
import time

from omnispectral.capture.devices import DeviceError, DeviceTimeout
from omnispectral.capture.drivers.serial_link import SerialLink

__all__ = ["AXES", "SerialHead", "deg_to_steps", "steps_to_deg"]

log = logging.getLogger(__name__)

AXES = ("pan", "tilt")


def deg_to_steps(angle_deg: float, steps_per_turn: int) -> int:
    """Nearest motor step to an angle (one full turn = ``steps_per_turn`` steps)."""
    return round(angle_deg / 360.0 * steps_per_turn)


def steps_to_deg(steps: int, steps_per_turn: int) -> float:
    return steps * 360.0 / steps_per_turn


class SerialHead:
    """Base of the serial pan/tilt head drivers (subclasses implement the ``_axis_*`` methods and ``_init``)."""

    device = "head"
    #: the protocol's positions cover one turn around zero: pan targets are wrapped into [-180, 180) and
    #: reported back in the turn they were commanded in (so 345 deg goes to -15 deg and reads 345 deg)
    wrap_pan = False

    def __init__(self, link: SerialLink, *, tolerance_deg: float = 0.05, settle_s: float = 0.0,
                 speed_fraction: float = 1.0, poll_s: float = 0.05, stall_s: float = 2.0):
        if not 0 < speed_fraction <= 1:
            raise DeviceError(f"{link.name}: speed fraction {speed_fraction} must be in (0, 1]")
        self.link = link
        self.tolerance_deg, self.settle_s, self.speed_fraction = tolerance_deg, settle_s, speed_fraction
        self.poll_s, self.stall_s = poll_s, stall_s
        self.steps_per_turn: dict[str, int] = {}
        self.info: dict[str, str] = {}
        self._target_steps: dict[str, int] = {"pan": 0, "tilt": 0}
        self._pan_turn_deg = 0.0
        self._init()
        for axis in AXES:
            res = 360.0 / self.steps_per_turn[axis]
            if res > tolerance_deg:
                log.warning("%s: %s resolution %.4f deg is coarser than the tolerance %.4f deg", self.name, axis,
                            res, tolerance_deg)

    @property
    def name(self) -> str:
        return self.link.name

    # ---------------------------------------------------------------- protocol specifics
    def _init(self) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _axis_goto(self, axis: str, target_steps: int) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def _axis_steps(self, axis: str) -> int | None:  # pragma: no cover - abstract
        """Position in steps; None when the head gave no number (the RODEON's empty answer on arrival)."""
        raise NotImplementedError

    def _axis_running(self, axis: str) -> bool | None:
        """Whether the axis reports running; None when the protocol cannot tell."""
        return None

    def _axis_stop(self, axis: str) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    # ---------------------------------------------------------------- PanTiltHead
    def move_to(self, pan_deg: float, tilt_deg: float) -> None:
        """Command both axes to the angles (pan and tilt in degrees from the head's zero); returns at once."""
        if not (math.isfinite(pan_deg) and math.isfinite(tilt_deg)) or abs(tilt_deg) > 90.0 + 1e-9:
            raise DeviceError(f"{self.name}: cannot go to pan {pan_deg} deg, tilt {tilt_deg} deg")
        if self.wrap_pan:
            wrapped = (pan_deg + 180.0) % 360.0 - 180.0
            self._pan_turn_deg, pan_deg = pan_deg - wrapped, wrapped
        for axis, angle in zip(AXES, (pan_deg, tilt_deg), strict=True):
            self._target_steps[axis] = deg_to_steps(angle, self.steps_per_turn[axis])
            self._axis_goto(axis, self._target_steps[axis])

    def _steps_now(self, axis: str) -> int:
        steps = self._axis_steps(axis)
        if steps is None:  # seen on the RODEON when the motor has arrived: the position is the target
            log.info("%s: empty %s position answer, taken as arrived", self.name, axis)
            return self._target_steps[axis]
        return steps

    def position(self) -> tuple[float, float]:
        """The angles the head reports now (degrees)."""
        pan, tilt = (steps_to_deg(self._steps_now(a), self.steps_per_turn[a]) for a in AXES)
        return pan + self._pan_turn_deg, tilt

    def _off_target(self, axis: str, steps: int) -> float:
        return abs(steps - self._target_steps[axis]) * 360.0 / self.steps_per_turn[axis]

    def wait_settled(self, timeout_s: float) -> tuple[float, float]:
        """Poll until both axes stopped within the tolerance of their targets, wait the settle time, report.

        An axis is stopped when its position did not change between two polls (and, when the protocol
        says, it is not running).  Raises DeviceTimeout when an axis is still moving at ``timeout_s``,
        or has stood still for ``stall_s`` away from its target (a move that never arrives).
        """
        t0 = time.monotonic()
        last: dict[str, tuple[int, float]] = {}
        while True:
            now = time.monotonic()
            arrived = []
            for axis in AXES:
                steps = self._steps_now(axis)
                prev = last.get(axis)
                if prev is None or prev[0] != steps:
                    last[axis] = (steps, now)
                still = prev is not None and prev[0] == steps
                running = self._axis_running(axis) if still else None
                on_target = self._off_target(axis, steps) <= self.tolerance_deg
                arrived.append(still and on_target and running is not True)
                if still and not on_target and running is not True and now - last[axis][1] >= self.stall_s:
                    raise DeviceTimeout(self._where(axis, steps, f"stopped for {now - last[axis][1]:.1f} s"))
            if all(arrived):
                break
            if now - t0 >= timeout_s:
                axis = next(a for a, ok in zip(AXES, arrived, strict=True) if not ok)
                raise DeviceTimeout(self._where(axis, last[axis][0], f"not settled after {timeout_s:g} s"))
            time.sleep(self.poll_s)
        if self.settle_s > 0:
            time.sleep(self.settle_s)
        return self.position()

    def _where(self, axis: str, steps: int, what: str) -> str:
        n = self.steps_per_turn[axis]
        return (f"{self.name}: {axis} axis {what} at {steps_to_deg(steps, n):.3f} deg, target "
                f"{steps_to_deg(self._target_steps[axis], n):.3f} deg ({self._off_target(axis, steps):.3f} deg off)")

    def stop(self) -> None:
        """Stop both axes now."""
        for axis in AXES:
            self._axis_stop(axis)

    def close(self) -> None:
        """Stop the motors (best effort: the line may already be gone) and release the port."""
        if not self.link.ser.is_open:
            return
        try:
            self.stop()
        except DeviceError as exc:
            log.info("%s: stop on close failed: %s", self.name, exc)
        self.link.close()
