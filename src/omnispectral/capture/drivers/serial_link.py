"""One request/reply serial line to a device, with bounded waits, bounded retries and pulled-cable detection.

Both pan/tilt head protocols (RODEON, Merlin/Orion; see ``shared/notes/pan-tilt-head-protocols.md``)
send a short request ending in CR and get back a reply ending in CR (the RODEON sometimes in two
CR-terminated parts).  :class:`SerialLink` does the part common to both: drop stale bytes, write the
request, read the reply within a timeout, let the protocol parse it, and re-send a bounded number of
times when the reply is missing or unparseable.  Every failure becomes one
:class:`~omnispectral.capture.devices.DeviceError` line that names the device, the port, the request
and what came back.  A port that disappears under pyserial (USB adapter unplugged, pseudo-terminal
closed) is reported as :class:`~omnispectral.capture.devices.DeviceDisconnected` and never retried.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import TypeVar

import serial

from omnispectral.capture.devices import DeviceDisconnected, DeviceProtocolError, DeviceTimeout

__all__ = ["CR", "BadReply", "ErrorReply", "SerialLink", "T", "show_bytes"]

try:  # pyserial's POSIX flush (tcdrain) raises termios.error, not an OSError, when the cable is pulled
    import termios

    PORT_ERRORS: tuple[type[BaseException], ...] = (serial.SerialException, OSError, termios.error)
except ImportError:  # Windows
    PORT_ERRORS = (serial.SerialException, OSError)

log = logging.getLogger(__name__)

T = TypeVar("T")
CR = b"\r"


class BadReply(ValueError):
    """Raised by a protocol's reply parser: the bytes are not a valid answer to the request."""


class ErrorReply(BadReply):
    """The device answered with an explicit protocol error (e.g. Merlin ``!<code>``)."""


def show_bytes(data: bytes, limit: int = 40) -> str:
    """Printable form of raw bytes for an error line (non-ASCII as ``\\xNN``, CR as ``\\r``)."""
    text = data[:limit].decode("latin-1").encode("unicode_escape").decode("ascii")
    return "'" + text + ("…" if len(data) > limit else "") + "'"


class SerialLink:
    """A serial port to one device.

    Parameters
    ----------
    device
        Name used in error messages, e.g. ``"RODEON head"``.
    port
        Device path (``/dev/ttyUSB0``, a pseudo-terminal) or a pyserial URL (``loop://``).
    baud
        Line speed (8N1).
    timeout_s
        Longest wait for one reply.
    retries
        Re-sends of a request after a missing or unparseable reply (so at most ``retries + 1`` tries).
    gap_s
        After a CR, how long to wait for a second reply part before deciding the reply is complete.
    """

    def __init__(self, device: str, port: str, baud: int = 9600, timeout_s: float = 0.5, retries: int = 2,
                 gap_s: float = 0.0):
        self.device, self.port, self.timeout_s, self.retries, self.gap_s = device, port, timeout_s, retries, gap_s
        try:
            self.ser = serial.serial_for_url(port, baudrate=baud, bytesize=8, parity="N", stopbits=1,
                                             timeout=timeout_s, write_timeout=timeout_s)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DeviceDisconnected(f"{device}: cannot open serial port {port} ({_reason(exc)})") from None

    @property
    def name(self) -> str:
        return f"{self.device} on {self.port}"

    def _lost(self, exc: Exception, doing: str) -> DeviceDisconnected:
        return DeviceDisconnected(f"{self.name}: serial port lost while {doing} ({_reason(exc)}); "
                                  "cable pulled or adapter unplugged?")

    def _read_reply(self, doing: str) -> bytes:
        try:
            data = self.ser.read_until(CR)
            if data.endswith(CR) and self.gap_s > 0:
                time.sleep(self.gap_s)
                if self.ser.in_waiting:
                    data += self.ser.read_until(CR)
        except PORT_ERRORS as exc:
            raise self._lost(exc, doing) from None
        return data

    def exchange(self, request: bytes, parse: Callable[[bytes], T], what: str = "") -> T:
        """Send ``request`` and return ``parse(reply)``; re-send on silence or garbage (bounded)."""
        doing = f"sending {show_bytes(request)}" + (f" ({what})" if what else "")
        problem, kind = "", DeviceTimeout
        if not self.ser.is_open:
            raise DeviceDisconnected(f"{self.name}: the port is closed (while {doing})")
        for attempt in range(self.retries + 1):
            try:
                if self.ser.in_waiting:
                    stale = self.ser.read(self.ser.in_waiting)
                    log.debug("%s: dropped stale bytes %s", self.name, show_bytes(stale))
                self.ser.write(request)
                self.ser.flush()
            except PORT_ERRORS as exc:
                raise self._lost(exc, doing) from None
            reply = self._read_reply(doing)
            log.debug("%s: %s -> %s", self.name, show_bytes(request), show_bytes(reply))
            if not reply:
                problem, kind = f"no answer within {self.timeout_s:g} s", DeviceTimeout
                continue
            if not reply.endswith(CR):
                problem, kind = f"answered {show_bytes(reply)} without the closing CR", DeviceProtocolError
                continue
            try:
                return parse(reply)
            except BadReply as exc:
                problem, kind = f"answered {show_bytes(reply)} ({exc})", DeviceProtocolError
                log.info("%s: bad reply to %s on attempt %d: %s", self.name, show_bytes(request), attempt + 1, exc)
        raise kind(f"{self.name}: {problem} to {show_bytes(request)}" + (f" ({what})" if what else "")
                   + f", {self.retries + 1} attempts")

    def close(self) -> None:
        try:
            self.ser.close()
        except PORT_ERRORS:
            pass


def _reason(exc: Exception) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__

