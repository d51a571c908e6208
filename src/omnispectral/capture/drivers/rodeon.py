"""Dr. Clauss RODEON VR Station (the paper's head) over its serial line.

Protocol facts (``shared/notes/pan-tilt-head-protocols.md``, from Kolor's public wiki): the bus has
three elements, 0 = transceiver, 1 = pan motor, 2 = tilt motor.  A request is the byte
``0xC0 + element``, a command letter, optional ASCII parameters and CR; the reply starts with
``0xA0 + element`` (possibly repeated), echoes the letter, carries the value for queries and ends with
CR, some replies in two CR-terminated parts.  Start-up: transceiver ``R m w v``; per motor
``R Y w m v u f``, wait until it stops, ``N``.  A move: ``S%+08d`` target steps, ``F%05d`` speed,
``G0``; then poll ``p`` until the position stops changing (an empty ``p`` answer has been seen on
arrival and is taken as "at the target").  ``O3`` stops a motor.

Uncertain details handled tolerantly: the brand answer is logged (not required to be ``CLAUSS``),
a second reply part is accepted after any answer, and the speed sent is ``speed_fraction`` × the
maximum the motor reports with ``f`` (the angular speed that gives is not documented).
"""

from __future__ import annotations

import logging
import time

from omnispectral.capture.devices import DeviceProtocolError, DeviceTimeout
from omnispectral.capture.drivers.head_base import SerialHead
from omnispectral.capture.drivers.serial_link import BadReply, SerialLink

__all__ = ["COMMANDS", "ELEMENT", "ELEMENT_NAMES", "RodeonHead", "parse_rodeon_reply", "rodeon_request"]

log = logging.getLogger(__name__)

TRANSCEIVER, PAN_MOTOR, TILT_MOTOR = 0, 1, 2
ELEMENT = {"pan": PAN_MOTOR, "tilt": TILT_MOTOR}
ELEMENT_NAMES = {TRANSCEIVER: "transceiver", PAN_MOTOR: "pan motor", TILT_MOTOR: "tilt motor"}
COMMANDS = {"R": "reset", "m": "brand", "w": "reference number", "v": "firmware version", "u": "steps per turn",
            "f": "maximum speed", "Y": "go to factory zero", "N": "set zero", "p": "position", "S": "target",
            "F": "speed", "G": "go", "O": "stop", "x": "battery", "L": "output lines"}


def rodeon_request(element: int, letter: str, params: str = "") -> bytes:
    """Bytes of one request: address byte ``0xC0 + element``, the letter, parameters, CR."""
    return bytes([0xC0 + element]) + (letter + params).encode("ascii") + b"\r"


def parse_rodeon_reply(reply: bytes, element: int, letter: str) -> list[str]:
    """The value parts of a reply (``[]`` for a bare echo); raises BadReply when it is not an answer to the request.

    ``reply`` ends with CR; leading repeats of the address byte ``0xA0 + element`` are skipped, the
    next byte must echo ``letter``; what follows is split into its CR-terminated parts.
    """
    addr = 0xA0 + element
    i = 0
    while i < len(reply) and reply[i] == addr:
        i += 1
    if i == 0:
        raise BadReply(f"expected the address byte 0x{addr:02X} of the {ELEMENT_NAMES.get(element, element)}")
    if i >= len(reply) or reply[i:i + 1] != letter.encode("ascii"):
        got = reply[i:i + 1].decode("latin-1") if i < len(reply) else "nothing"
        raise BadReply(f"echoed {got!r} instead of {letter!r}")
    body = reply[i + 1:]
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        raise BadReply("non-ASCII value") from None
    parts = text.split("\r")[:-1]  # the reply ends with CR
    return [p.strip() for p in parts] if any(p.strip() for p in parts) else []


def _integer(parts: list[str], what: str) -> int:
    try:
        return int(parts[0])
    except (IndexError, ValueError):
        raise BadReply(f"{what} is not an integer: {parts!r}") from None


class RodeonHead(SerialHead):
    """A RODEON VR Station on a serial port, implementing :class:`~omnispectral.capture.devices.PanTiltHead`.

    ``command_timeout_s`` bounds each reply, ``retries`` the re-sends of a request; ``init_timeout_s``
    bounds the wait for the factory-zero move at start-up.  The other parameters are those of
    :class:`~omnispectral.capture.drivers.head_base.SerialHead`.
    """

    device = "RODEON head"

    def __init__(self, port: str, *, baud: int = 9600, command_timeout_s: float = 0.5, retries: int = 2,
                 init_timeout_s: float = 60.0, reply_gap_s: float = 0.01, **kwargs):
        self.init_timeout_s = init_timeout_s
        self.max_speed: dict[str, int] = {}
        link = SerialLink(self.device, port, baud, command_timeout_s, retries, gap_s=reply_gap_s)
        try:
            super().__init__(link, **kwargs)
        except BaseException:
            link.close()
            raise

    def _ask(self, element: int, letter: str, params: str = "") -> list[str]:
        what = f"{ELEMENT_NAMES[element]} {COMMANDS.get(letter, letter)}"
        return self.link.exchange(rodeon_request(element, letter, params),
                                  lambda r: parse_rodeon_reply(r, element, letter), what)

    def _ask_int(self, element: int, letter: str, allow_empty: bool = False) -> int | None:
        """A query whose answer is an integer (None for an empty answer when ``allow_empty``)."""
        what = f"{ELEMENT_NAMES[element]} {COMMANDS.get(letter, letter)}"

        def parse(reply: bytes) -> int | None:
            parts = parse_rodeon_reply(reply, element, letter)
            return None if allow_empty and not parts else _integer(parts, COMMANDS[letter])

        return self.link.exchange(rodeon_request(element, letter), parse, what)

    def _init(self) -> None:
        self._ask(TRANSCEIVER, "R")
        brand = " ".join(self._ask(TRANSCEIVER, "m"))
        if "CLAUSS" not in brand.upper():
            log.warning("%s: brand answer %r (expected CLAUSS)", self.name, brand)
        self.info["brand"] = brand
        self.info["reference"] = " ".join(self._ask(TRANSCEIVER, "w"))
        self.info["firmware"] = " ".join(self._ask(TRANSCEIVER, "v"))
        for axis, element in ELEMENT.items():
            self._ask(element, "R")
            self._ask(element, "Y")
            self._ask(element, "w")
            self._ask(element, "m")
            self.info[f"{axis}_firmware"] = " ".join(self._ask(element, "v"))
            steps, speed = self._ask_int(element, "u"), self._ask_int(element, "f")
            if steps <= 0 or speed <= 0:
                raise DeviceProtocolError(f"{self.name}: {axis} motor reports {steps} steps per turn and maximum "
                                          f"speed {speed}")
            self.steps_per_turn[axis], self.max_speed[axis] = steps, speed
        for axis, element in ELEMENT.items():
            self._wait_still(element)
            self._ask(element, "N")
            self._target_steps[axis] = 0

    def _wait_still(self, element: int) -> None:
        """Poll ``p`` until the motor stops changing (after the factory-zero move), within init_timeout_s."""
        t0, prev = time.monotonic(), None
        while True:
            pos = self._ask_int(element, "p", allow_empty=True)
            if pos is None or (prev is not None and pos == prev):
                return
            if time.monotonic() - t0 > self.init_timeout_s:
                raise DeviceTimeout(f"{self.name}: {ELEMENT_NAMES[element]} still moving to factory zero after "
                                    f"{self.init_timeout_s:g} s (at {pos} steps)")
            prev = pos
            time.sleep(self.poll_s)

    def _axis_goto(self, axis: str, target_steps: int) -> None:
        element = ELEMENT[axis]
        self._ask(element, "S", f"{target_steps:+08d}")
        self._ask(element, "F", f"{max(1, round(self.speed_fraction * self.max_speed[axis])):05d}")
        self._ask(element, "G", "0")

    def _axis_steps(self, axis: str) -> int | None:
        return self._ask_int(ELEMENT[axis], "p", allow_empty=True)

    def _axis_stop(self, axis: str) -> None:
        self._ask(ELEMENT[axis], "O", "3")
