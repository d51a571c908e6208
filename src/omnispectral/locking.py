"""Exclusive locks on a session or product directory: one writer at a time, stale locks recognised.

A run that writes into a directory (``simulate``/``capture`` into a session, ``process`` into a
product, ``session repair``) holds ``DIR/.omnispectral.lock`` for its whole duration:

* the lock is an ``fcntl.flock`` on that file, so the kernel releases it when the holder dies
  (SIGKILL, power loss on a local disk): a crashed run never blocks the next one;
* the file holds the holder's pid, host name, command and start time, so a second run is refused
  with one line that says who holds it (:class:`LockedError`);
* a lock file left by a holder that is gone (its flock released by the kernel when that process ended)
  is *stale*: it is taken over and reported in :attr:`DirectoryLock.stale_holder`.

Locks are re-entrant within one process (a nested ``with directory_lock(d)`` of the same directory
is a no-op), because ``flock`` locks of two open file descriptions conflict even in one process.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import os
import socket
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from omnispectral.errors import OmnispectralError

__all__ = ["LOCK_NAME", "DirectoryLock", "LockedError", "directory_lock", "read_holder"]

LOCK_NAME = ".omnispectral.lock"

_held: dict[str, int] = {}  # resolved directory -> nesting depth (this process)
_held_guard = threading.Lock()


class LockedError(OmnispectralError):
    """Another run holds the directory's lock."""


@dataclass
class DirectoryLock:
    """A held lock: where, and the record of a stale holder it replaced (if any)."""

    directory: Path
    stale_holder: dict | None = None


def _holder_record(what: str) -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "what": what,
            "command": " ".join(sys.argv[:4])[:200],
            "since_utc": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}


def read_holder(directory: str | Path) -> dict | None:
    """The record written by the lock's last holder.

    Parameters
    ----------
    directory
        The locked (or once locked) directory.

    Returns
    -------
    dict or None
        ``pid``, ``host``, ``what``, ``command``, ``since_utc``; ``None`` without a readable lock file.
    """
    p = Path(directory) / LOCK_NAME
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _describe(holder: dict | None) -> str:
    if not holder:
        return "another run"
    return (f"pid {holder.get('pid')} on {holder.get('host')} ({holder.get('what', '?')}, since "
            f"{holder.get('since_utc', '?')})")


@contextlib.contextmanager
def directory_lock(directory: str | Path, what: str = "writing") -> Iterator[DirectoryLock]:
    """Hold the exclusive lock of ``directory`` (created if needed) for the ``with`` block.

    Parameters
    ----------
    directory
        The session or product directory.
    what
        What the holder does, written in the lock file for a refused second run to name.

    Yields
    ------
    DirectoryLock
        The held lock, with the record of a stale holder it took over (if any).

    Raises
    ------
    LockedError
        Naming the holder, when another live run holds the lock.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    key = str(directory.resolve())
    with _held_guard:
        if key in _held:
            _held[key] += 1
            reentrant = True
        else:
            reentrant = False
    if reentrant:
        try:
            yield DirectoryLock(directory)
        finally:
            with _held_guard:
                _held[key] -= 1
        return
    path = directory / LOCK_NAME
    fd, previous = _acquire(path, directory, what)
    with _held_guard:
        _held[key] = 1
    try:
        yield DirectoryLock(directory, previous)
    finally:
        with _held_guard:
            _held.pop(key, None)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)  # unlinked while still locked: a waiter re-checks the inode (see _acquire)
        os.close(fd)


def _acquire(path: Path, directory: Path, what: str) -> tuple[int, dict | None]:
    """Open, flock and stamp the lock file; returns the descriptor and a stale previous holder's record."""
    for _ in range(20):
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            holder = read_holder(directory)
            raise LockedError(f"{directory}: in use by {_describe(holder)}; wait for it to finish (or stop it). "
                              f"The lock {path.name} is released when that process ends.") from None
        # the previous holder may have unlinked the file between our open and flock: lock the live inode
        try:
            same = os.stat(path).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if not same:
            os.close(fd)
            continue
        with os.fdopen(os.dup(fd), "r", encoding="utf-8") as fh:
            text = fh.read()
        previous = None
        if text.strip():
            try:
                previous = json.loads(text)
            except ValueError:
                previous = {"unreadable": text[:100]}
        record = _holder_record(what)
        os.ftruncate(fd, 0)
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, (json.dumps(record) + "\n").encode())
        os.fsync(fd)
        return fd, previous
    raise LockedError(f"{directory}: the lock file {path.name} keeps changing; another run is starting")
