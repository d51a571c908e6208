"""Error types that name the offending file and the problem.

Every user-facing error raised by the library derives from :class:`OmnispectralError`,
so the CLI can print a one-line message instead of a traceback.
"""

from __future__ import annotations

from pathlib import Path


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
