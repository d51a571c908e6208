"""Merlin / Orion (Skywatcher-type) pan/tilt heads over their serial line.

Protocol facts (``shared/notes/pan-tilt-head-protocols.md``): 9600 baud 8N1; a request is ``:``, a
command letter, the axis digit (``1`` pan, ``2`` tilt), an optional hex parameter and CR; the reply
is ``=`` + data + CR, or ``!`` + one error character + CR.  Numbers are 24-bit values sent as six hex
digits, least significant byte first; positions are offset so that 0x800000 is the zero angle and
angle = (encoder − 0x800000) × 360 / steps per circle (``a``).  Start-up: ``e`` (firmware), ``a``,
``F`` (initialise).  A go-to: ``L`` (stop), ``G00`` (go-to mode), ``S<target>``, ``I<speed>``, ``J``;
then poll ``j`` (position) and ``f`` (status) until arrived.

Uncertain details handled tolerantly: the status word is read as three hex digits whose second digit's
lowest bit means "running" (when it does not parse, arrival is judged from the position alone), and
the speed value ``I`` is a step period (larger is slower): the driver sends
``round(fastest_period / speed_fraction)`` with ``fastest_period`` a parameter.  An ``!`` error reply
is retried like garbage and then reported with its code.
"""

from __future__ import annotations

import logging

from omnispectral.capture.devices import DeviceProtocolError
from omnispectral.capture.drivers.head_base import SerialHead
from omnispectral.capture.drivers.serial_link import BadReply, ErrorReply, SerialLink

__all__ = ["AXIS_DIGIT", "COMMANDS", "ERROR_CODES", "ZERO", "MerlinHead", "decode_u24", "encode_u24",
           "merlin_request", "parse_merlin_reply"]

log = logging.getLogger(__name__)

ZERO = 0x800000
AXIS_DIGIT = {"pan": "1", "tilt": "2"}
#: Error codes as commonly documented for Skywatcher-type motor controllers (uncertain for Merlin heads).
ERROR_CODES = {"0": "unknown command", "1": "command length error", "2": "motor not stopped",
               "3": "invalid character", "4": "not initialised", "5": "driver sleeping"}
COMMANDS = {"F": "initialise", "L": "stop", "e": "firmware version", "a": "steps per circle", "D": "sidereal rate",
            "j": "position", "f": "status", "G": "motion mode", "S": "go-to target", "I": "speed", "J": "start",
            "O": "output"}


def encode_u24(value: int) -> str:
    """A 24-bit value as six hex digits, least significant byte first (0x123456 → ``563412``).

    Parameters
    ----------
    value
        An integer in ``[0, 2**24)``.

    Returns
    -------
    str
        Six upper-case hex digits.

    Raises
    ------
    ValueError
        When the value does not fit in 24 bits.
    """
    if not 0 <= value < 1 << 24:
        raise ValueError(f"{value} does not fit in 24 bits")
    return "".join(f"{(value >> s) & 0xFF:02X}" for s in (0, 8, 16))


def decode_u24(text: str) -> int:
    """Inverse of :func:`encode_u24`.

    Parameters
    ----------
    text
        Six hex digits, least significant byte first.

    Returns
    -------
    int
        The 24-bit value.

    Raises
    ------
    ValueError
        When ``text`` is not six hex digits.
    """
    if len(text) != 6:
        raise ValueError(f"expected six hex digits, got {text!r}")
    b = [int(text[i:i + 2], 16) for i in (0, 2, 4)]
    return b[0] | b[1] << 8 | b[2] << 16


def merlin_request(letter: str, axis: str, params: str = "") -> bytes:
    """One request: ``:``, the command letter, the axis digit, the parameter and CR.

    Parameters
    ----------
    letter
        The command letter (:data:`COMMANDS`).
    axis
        ``"pan"`` or ``"tilt"``.
    params
        The command's parameter (hex digits), if any.

    Returns
    -------
    bytes
        The request in ASCII.
    """
    return f":{letter}{AXIS_DIGIT[axis]}{params}\r".encode("ascii")


def parse_merlin_reply(reply: bytes) -> str:
    """The data of an ``=`` reply.

    Parameters
    ----------
    reply
        The reply with its closing CR.

    Returns
    -------
    str
        The data after ``=``.

    Raises
    ------
    ErrorReply
        For ``!<code>`` (the code's meaning from :data:`ERROR_CODES`).
    BadReply
        For anything else.
    """
    try:
        text = reply.decode("ascii")
    except UnicodeDecodeError:
        raise BadReply("not ASCII") from None
    text = text[:-1]  # the closing CR
    if text.startswith("!") and len(text) == 2:
        raise ErrorReply(f"error {text} ({ERROR_CODES.get(text[1], 'unknown code')})")
    if not text.startswith("=") or "\r" in text:
        raise BadReply("expected '=' + data")
    return text[1:]


class MerlinHead(SerialHead):
    """A Merlin/Orion-type head on a serial port, implementing :class:`~omnispectral.capture.devices.PanTiltHead`."""

    device = "Merlin head"
    wrap_pan = True  # 24-bit encoders centred on 0x800000

    def __init__(self, port: str, *, baud: int = 9600, command_timeout_s: float = 0.5, retries: int = 2,
                 fastest_period: int = 18, **kwargs):
        self.fastest_period = fastest_period
        link = SerialLink(self.device, port, baud, command_timeout_s, retries)
        try:
            super().__init__(link, **kwargs)
        except BaseException:
            link.close()
            raise

    def _ask(self, letter: str, axis: str, params: str = "", convert=None):
        def parse(reply: bytes):
            data = parse_merlin_reply(reply)
            if convert is None:
                return data
            try:
                return convert(data)
            except ValueError as exc:
                raise BadReply(f"{COMMANDS.get(letter, letter)}: {exc}") from None

        return self.link.exchange(merlin_request(letter, axis, params), parse,
                                  f"{axis} {COMMANDS.get(letter, letter)}")

    def _init(self) -> None:
        for axis in AXIS_DIGIT:
            self.info[f"{axis}_firmware"] = self._ask("e", axis)
            steps = self._ask("a", axis, convert=decode_u24)
            if steps <= 0:
                raise DeviceProtocolError(f"{self.name}: {axis} axis reports {steps} steps per circle")
            self.steps_per_turn[axis] = steps
        for axis in AXIS_DIGIT:
            self._ask("F", axis)
            self._target_steps[axis] = self._ask("j", axis, convert=decode_u24) - ZERO

    def _axis_goto(self, axis: str, target_steps: int) -> None:
        self._ask("L", axis)
        self._ask("G", axis, "00")
        self._ask("S", axis, encode_u24(ZERO + target_steps))
        self._ask("I", axis, encode_u24(max(1, round(self.fastest_period / self.speed_fraction))))
        self._ask("J", axis)

    def _axis_steps(self, axis: str) -> int:
        return self._ask("j", axis, convert=decode_u24) - ZERO

    def _axis_running(self, axis: str) -> bool | None:
        status = self._ask("f", axis)
        try:
            return bool(int(status[1], 16) & 1)
        except (IndexError, ValueError):
            log.info("%s: status %r of the %s axis not understood", self.name, status, axis)
            return None

    def _axis_stop(self, axis: str) -> None:
        self._ask("L", axis)
