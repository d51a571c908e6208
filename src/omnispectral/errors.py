"""Error types that name the offending file and the problem.

Every user-facing error raised by the library derives from :class:`OmnispectralError`,
so the CLI can print a one-line message instead of a traceback.
"""

from __future__ import annotations

import errno
import os
import re
from pathlib import Path

__all__ = ["ConfigurationError", "DamagedFrameError", "InputFileError", "InvalidFileContent", "OmnispectralError",
           "describe_os_error",
           "os_errno", "os_problem"]


class OmnispectralError(Exception):
    """Base class for errors the CLI reports as a clear one-line message."""


class InputFileError(OmnispectralError, ValueError):
    """A file given by the user cannot be used.

    Parameters
    ----------
    path
        The file concerned.
    problem
        What is wrong, in words a user understands.
    line
        1-based line number in a text file, when the problem is on one line.
    """

    def __init__(self, path: str | Path, problem: str, line: int | None = None):
        self.path = Path(path)
        self.problem = problem
        self.line = line
        where = f"{self.path}" if line is None else f"{self.path}, line {line}"
        super().__init__(f"{where}: {problem}")


class ConfigurationError(OmnispectralError, ValueError):
    """A parameter or a combination of parameters makes no sense."""



class DamagedFrameError(InputFileError):
    """A session frame that fails its check as it is read (journal checksum, decoding, pixels): the read that
    uses a frame checked it (:meth:`omnispectral.capture.session.Session.check_frames_on_read`)."""

class InvalidFileContent(InputFileError, ConfigurationError):
    """A file that was read but holds a value that makes no sense (e.g. a rig file's key).

    Both an :class:`InputFileError` (the CLI exits 1: the input is bad, not the command line) and a
    :class:`ConfigurationError` (what callers of the readers have always caught).
    """


_OS_PROBLEMS = {errno.ENOSPC: "disk full", errno.EDQUOT: "disk quota exceeded", errno.EACCES: "permission denied",
                errno.EPERM: "permission denied", errno.EROFS: "read-only file system",
                errno.ENOENT: "no such file or directory", errno.EISDIR: "is a directory",
                errno.ENOTDIR: "not a directory"}


_ERRNO_IN_TEXT = re.compile(r"\[Errno (\d+)\]")


def os_errno(exc: OSError) -> int | None:
    """The error number of ``exc``, also when a library raised it without the ``(errno, strerror)`` form:
    ``OSError(28)`` or ``OSError("[Errno 28] No space left on device")``; ``None`` when it has none."""
    if exc.errno is not None:
        return exc.errno
    if len(exc.args) == 1 and isinstance(exc.args[0], int) and not isinstance(exc.args[0], bool):
        return exc.args[0]
    m = _ERRNO_IN_TEXT.search(str(exc))
    return int(m.group(1)) if m else None


def os_problem(exc: OSError) -> str:
    """The problem of an operating-system error in plain words (``disk full``, ``permission denied``…)."""
    code = os_errno(exc)
    if code in _OS_PROBLEMS:
        return _OS_PROBLEMS[code]
    if exc.strerror:
        return exc.strerror
    if code is not None:
        return os.strerror(code)
    return str(exc) or type(exc).__name__


def describe_os_error(exc: OSError) -> str:
    """One line for an operating-system error: the path concerned and the problem in plain words
    (``disk full``, ``permission denied``, ``read-only file system``…)."""
    problem = os_problem(exc)
    path = exc.filename if exc.filename is not None else "(no file name)"
    extra = f" → {exc.filename2}" if getattr(exc, "filename2", None) else ""
    return f"{path}{extra}: {problem}"
