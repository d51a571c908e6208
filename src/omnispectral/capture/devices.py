"""Device protocols (camera, pan/tilt head, filter changer, clock), the computer's clock and the operator's filter.

The protocols say what real hardware does: a head is *commanded* to a position and later *reports*
one (which may differ), it takes time to travel and to settle, and it may not answer; a camera is
given an exposure (and may round it), triggered, and its frame is read with a timeout.  The real
drivers (:mod:`omnispectral.capture.drivers`) and the simulated devices (:mod:`omnispectral.sim.devices`)
implement them; the capture loop (:mod:`omnispectral.capture.run`) sees only the protocols.
"""

from __future__ import annotations

import datetime as _dt
import time
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from omnispectral.errors import OmnispectralError

__all__ = ["Camera", "Clock", "DeviceDisconnected", "DeviceError", "DeviceProtocolError", "DeviceTimeout",
           "FilterChanger", "ManualFilterChanger", "PanTiltHead", "SystemClock"]


class DeviceError(OmnispectralError):
    """A device failed (after the retries the caller allows)."""


class DeviceTimeout(DeviceError):
    """A device did not answer within its timeout."""


class DeviceDisconnected(DeviceError):
    """The connection to a device is gone (serial cable pulled, adapter unplugged, port closed)."""


class DeviceProtocolError(DeviceError):
    """A device answered, but with something the protocol does not allow (garbage, an error reply)."""


@runtime_checkable
class Clock(Protocol):
    def now(self) -> _dt.datetime: ...  # timezone-aware wall time

    def monotonic(self) -> float: ...  # seconds

    def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """The computer's clock."""

    def now(self) -> _dt.datetime:
        return _dt.datetime.now(_dt.UTC).astimezone()

    def monotonic(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


@runtime_checkable
class PanTiltHead(Protocol):
    def move_to(self, pan_deg: float, tilt_deg: float) -> None: ...  # command; returns at once

    def position(self) -> tuple[float, float]: ...  # reported (pan, tilt), may raise DeviceTimeout

    def wait_settled(self, timeout_s: float) -> tuple[float, float]: ...  # blocks until arrived and settled

    def close(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    name: str
    bit_depth: int

    def set_exposure(self, exposure_s: float) -> float: ...  # returns the exposure actually set

    def trigger(self) -> None: ...

    def read_frame(self, timeout_s: float) -> tuple[np.ndarray, dict]: ...  # uint16 frame, metadata

    def close(self) -> None: ...


@runtime_checkable
class FilterChanger(Protocol):
    """Puts a filter in front of both lenses and takes it away (the sun bracket's neutral density)."""

    def insert(self, filter_name: str) -> None: ...

    def remove(self) -> None: ...


class ManualFilterChanger:
    """The operator places and removes the filter: ``ask(message)`` returns once it is done (the command line
    waits for Enter on its terminal)."""

    def __init__(self, ask: Callable[[str], None]):
        self.ask = ask
        self.filter_name: str | None = None

    def insert(self, filter_name: str) -> None:
        self.ask(f"put the {filter_name} filter in front of both lenses, then press Enter")
        self.filter_name = filter_name

    def remove(self) -> None:
        self.ask(f"take the {self.filter_name} filter away from the lenses, then press Enter")
        self.filter_name = None


