"""Emulated RODEON and Merlin heads on pseudo-terminals, with motors that take time and injectable faults.

An emulator opens a pseudo-terminal (``os.openpty``), serves the head's protocol from a thread on
the master side and gives the slave's path as :attr:`HeadEmulator.port`, so a driver (or the CLI,
through a rig file) opens it like a real serial port.  Optionally the port is published under a
stable symlink (``link=``) that a later emulator can take over, as ``/dev/serial/by-id/…`` does
when a cable is plugged back in.  Motors move at a constant angular speed (``max_speed_deg_s`` at
full speed), scaled in time by ``time_scale`` so tests run fast.

Faults (:class:`EmulatorFaults`): requests that get no answer, garbage answers, protocol error answers,
moves that stop part-way and never arrive, and the cable pulled during a move (the master side is
closed; the driver's next read or write fails as with an unplugged USB adapter).
"""

from __future__ import annotations

import contextlib
import logging
import os
import select
import threading
import time
import tty
from dataclasses import dataclass
from pathlib import Path

from omnispectral.capture.drivers.merlin import ZERO, decode_u24, encode_u24

__all__ = ["EmulatorFaults", "HeadEmulator", "MerlinEmulator", "Motor", "RodeonEmulator"]

log = logging.getLogger(__name__)


@dataclass
class EmulatorFaults:
    """Faults an emulator injects; the counters are consumed request by request (or move by move)."""

    no_answer: int = 0  # the next N requests get no answer at all
    garbage: int = 0  # the next N requests get bytes that are not a reply
    error_replies: int = 0  # the next N requests get a protocol error reply
    stall_moves: int = 0  # the next N moves stop at ``stall_fraction`` of the way and never arrive
    stall_fraction: float = 0.5
    pull_cable_on_move: int | None = None  # the cable is pulled during this move (1 = the first go-to)
    pull_cable_after_s: float = 0.05  # … this long (wall time) after that move started
    empty_position_on_arrival: bool = False  # RODEON: answer ``p`` with an empty value once a move arrived


class Motor:
    """One axis: position in steps as a function of (scaled) time, constant speed towards a target."""

    def __init__(self, steps_per_turn: int, max_speed_deg_s: float, start_steps: int = 0):
        self.steps_per_turn, self.max_speed_deg_s = steps_per_turn, max_speed_deg_s
        self._from, self._to, self._t0, self._speed = start_steps, start_steps, 0.0, 0.0
        self._stop_at: int | None = None

    def steps(self, t: float) -> int:
        if self._speed <= 0:
            return self._to
        travel = self._speed * (t - self._t0)
        span = self._to - self._from
        end = self._to if self._stop_at is None else self._stop_at
        if travel >= abs(end - self._from):
            return end
        return round(self._from + travel * (1 if span >= 0 else -1))

    def running(self, t: float) -> bool:
        end = self._to if self._stop_at is None else self._stop_at
        return self._speed > 0 and self.steps(t) != end

    def go(self, target: int, speed_fraction: float, t: float, stall_fraction: float | None = None) -> None:
        here = self.steps(t)
        self._from, self._to, self._t0 = here, target, t
        self._speed = max(speed_fraction, 1e-6) * self.max_speed_deg_s * self.steps_per_turn / 360.0
        self._stop_at = None if stall_fraction is None else round(here + stall_fraction * (target - here))

    def stop(self, t: float) -> None:
        here = self.steps(t)
        self._from = self._to = here
        self._stop_at, self._speed = None, 0.0

    def rezero(self, t: float) -> None:
        """Declare the current position step 0 (keeps a move in progress consistent)."""
        self.stop(t)
        self._from = self._to = 0


class HeadEmulator:
    """Base of the emulators: the pseudo-terminal, the serving thread, scaled time and the fault counters."""

    name = "head emulator"

    def __init__(self, *, time_scale: float = 1.0, faults: EmulatorFaults | None = None,
                 link: str | Path | None = None):
        self.time_scale = time_scale
        self.faults = faults or EmulatorFaults()
        self.requests: list[bytes] = []
        self.moves = 0
        self._pull_at: float | None = None
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self.link = Path(link) if link else None
        if self.link:
            tmp = self.link.with_name(self.link.name + ".tmp")
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            os.symlink(self.port, tmp)
            os.replace(tmp, self.link)
        self._stop = threading.Event()
        self.cable_pulled = False
        self._thread = threading.Thread(target=self._serve, name=self.name, daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """What a rig file names as the port: the stable link when there is one, else the pseudo-terminal."""
        return str(self.link) if self.link else self.port

    def now(self) -> float:
        """Emulated time in seconds (wall time × ``time_scale``)."""
        return time.monotonic() * self.time_scale

    # ------------------------------------------------------------------ serving
    def _serve(self) -> None:
        buf = b""
        while not self._stop.is_set():
            if self._pull_at is not None and time.monotonic() >= self._pull_at:
                self.pull_cable()
                return
            try:
                ready, _, _ = select.select([self._master], [], [], 0.002)
                if not ready:
                    continue
                buf += os.read(self._master, 4096)
            except OSError:
                return
            while b"\r" in buf:
                request, buf = buf.split(b"\r", 1)
                self.requests.append(request)
                reply = self._faulty_reply(request)
                if reply:
                    try:
                        os.write(self._master, reply)
                    except OSError:
                        return

    def _faulty_reply(self, request: bytes) -> bytes | None:
        f = self.faults
        if f.no_answer > 0:
            f.no_answer -= 1
            return None
        if f.garbage > 0:
            f.garbage -= 1
            return b"\x15\x7f#?" + os.urandom(3).replace(b"\r", b"") + b"\r"
        if f.error_replies > 0:
            f.error_replies -= 1
            return self.error_reply(request)
        return self.reply(request)

    def _move_started(self) -> float | None:
        """Count a go-to; returns the stall fraction if this move is to stall, and arms a pulled cable."""
        self.moves += 1
        f = self.faults
        if f.pull_cable_on_move is not None and self.moves == f.pull_cable_on_move:
            self._pull_at = time.monotonic() + f.pull_cable_after_s
        if f.stall_moves > 0:
            f.stall_moves -= 1
            return f.stall_fraction
        return None

    def reply(self, request: bytes) -> bytes | None:  # pragma: no cover - abstract
        raise NotImplementedError

    def error_reply(self, request: bytes) -> bytes:  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------------------ faults and shutdown
    def pull_cable(self) -> None:
        """Pull the cable: close both ends of the pseudo-terminal (the port's path disappears)."""
        self.cable_pulled = True
        self._stop.set()
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._master = self._slave = -1

    def close(self) -> None:
        self._stop.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout=2)
        if not self.cable_pulled:
            self.pull_cable()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RodeonEmulator(HeadEmulator):
    """A RODEON VR Station: transceiver (element 0), pan motor (1), tilt motor (2).

    ``steps_per_turn`` and ``max_speed`` are what ``u`` and ``f`` answer (emulator choices, not
    published values); at ``F`` = ``max_speed`` a motor turns at ``max_speed_deg_s``.  The motors
    power up ``power_on_deg`` away from their factory zero, so ``Y`` is a real move.
    """

    name = "RODEON emulator"

    def __init__(self, *, steps_per_turn: int = 172800, max_speed: int = 2000, max_speed_deg_s: float = 30.0,
                 power_on_deg: float = 3.0, **kwargs):
        self.max_speed = max_speed
        start = round(power_on_deg / 360 * steps_per_turn)
        self.motors = {1: Motor(steps_per_turn, max_speed_deg_s, start), 2: Motor(steps_per_turn, max_speed_deg_s,
                                                                                    -start)}
        self.speed = {1: max_speed, 2: max_speed}
        self.target = {1: 0, 2: 0}
        self._arrived_empty_sent = {1: False, 2: False}
        super().__init__(**kwargs)

    def _answer(self, element: int, letter: str, *parts: str) -> bytes:
        body = "".join(p + "\r" for p in parts) if parts else "\r"
        return bytes([0xA0 + element, 0xA0 + element]) + letter.encode("ascii") + body.encode("ascii")

    def error_reply(self, request: bytes) -> bytes:
        element = request[0] - 0xC0 if request and 0xC0 <= request[0] <= 0xC2 else 0
        return self._answer(element, "?")

    def reply(self, request: bytes) -> bytes | None:
        if len(request) < 2 or not 0xC0 <= request[0] <= 0xC2:
            return None  # not addressed to an element on this bus
        element, letter, params = request[0] - 0xC0, chr(request[1]), request[2:].decode("ascii", "replace")
        t = self.now()
        if element == 0:
            answers = {"R": (), "m": ("CLAUSS",), "w": ("0815",), "v": ("V2.10", "HD"), "x": ("095",), "L": ()}
            return self._answer(0, letter, *answers[letter]) if letter in answers else self.error_reply(request)
        motor = self.motors[element]
        if letter in "RwmvufNYpSFGO":
            if letter == "u":
                return self._answer(element, letter, str(motor.steps_per_turn))
            if letter == "f":
                return self._answer(element, letter, str(self.max_speed))
            if letter in "wmv":
                return self._answer(element, letter, {"w": "0815", "m": "CLAUSS", "v": "V2.10"}[letter])
            if letter == "Y":
                motor.go(0, 1.0, t)
            elif letter == "N":
                motor.rezero(t)
            elif letter == "p":
                steps = motor.steps(t)
                if (self.faults.empty_position_on_arrival and not motor.running(t) and steps == self.target[element]
                        and not self._arrived_empty_sent[element]):
                    self._arrived_empty_sent[element] = True
                    return self._answer(element, letter)
                return self._answer(element, letter, f"{steps:+d}")
            elif letter == "S":
                try:
                    self.target[element] = int(params)
                except ValueError:
                    return self.error_reply(request)
            elif letter == "F":
                try:
                    self.speed[element] = max(1, min(int(params), self.max_speed))
                except ValueError:
                    return self.error_reply(request)
            elif letter == "G":
                stall = self._move_started() if element == 1 else None
                self._arrived_empty_sent[element] = False
                motor.go(self.target[element], self.speed[element] / self.max_speed, t, stall)
            elif letter == "O":
                motor.stop(t)
            return self._answer(element, letter)
        return self.error_reply(request)


class MerlinEmulator(HeadEmulator):
    """A Merlin/Orion-type head: two axes on one line, 24-bit encoders with the zero at 0x800000.

    ``steps_per_circle`` is what ``a`` answers (an emulator choice); an axis turns at
    ``max_speed_deg_s`` × ``fastest_period`` / ``I``.  Commands other than ``e``, ``a``, ``F`` before
    ``F`` answer ``!4`` (not initialised).
    """

    name = "Merlin emulator"

    def __init__(self, *, steps_per_circle: int = 9024000, max_speed_deg_s: float = 25.0, fastest_period: int = 18,
                 **kwargs):
        self.fastest_period = fastest_period
        self.motors = {"1": Motor(steps_per_circle, max_speed_deg_s), "2": Motor(steps_per_circle, max_speed_deg_s)}
        self.target = {"1": 0, "2": 0}
        self.period = {"1": fastest_period, "2": fastest_period}
        self.initialised = {"1": False, "2": False}
        self.output = False
        super().__init__(**kwargs)

    def error_reply(self, request: bytes) -> bytes:
        return b"!2\r"  # motor not stopped

    def reply(self, request: bytes) -> bytes | None:
        text = request.decode("ascii", "replace")
        if len(text) < 3 or text[0] != ":" or text[2] not in self.motors:
            return b"!0\r" if text.startswith(":") else None
        letter, axis, params = text[1], text[2], text[3:]
        motor, t = self.motors[axis], self.now()
        if letter not in "eaF" and not self.initialised[axis]:
            return b"!4\r"
        try:
            if letter == "e":
                data = "020C01"
            elif letter == "a":
                data = encode_u24(motor.steps_per_turn)
            elif letter == "F":
                self.initialised[axis], data = True, ""
            elif letter == "D":
                data = encode_u24(0x0003C1)
            elif letter == "j":
                data = encode_u24(ZERO + motor.steps(t))
            elif letter == "f":
                data = f"1{int(motor.running(t))}1"
            elif letter == "L":
                motor.stop(t)
                data = ""
            elif letter == "G":
                if motor.running(t):
                    return b"!2\r"
                data = ""
            elif letter == "S":
                self.target[axis], data = decode_u24(params) - ZERO, ""
            elif letter == "I":
                self.period[axis], data = max(1, decode_u24(params)), ""
            elif letter == "J":
                stall = self._move_started() if axis == "1" else None
                motor.go(self.target[axis], self.fastest_period / self.period[axis], t, stall)
                data = ""
            elif letter == "O":
                self.output, data = params == "1", ""
            else:
                return b"!0\r"
        except ValueError:
            return b"!3\r"
        return f"={data}\r".encode("ascii")
