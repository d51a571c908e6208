"""Crash-safe file writing: every file is written to a temporary name and renamed into place."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from omnispectral.errors import InputFileError, os_errno, os_problem

__all__ = ["TEMP_MARK", "atomic_path", "atomic_write_json", "atomic_write_text", "clean_temp_files", "current_umask",
           "error_naming_output", "follow_umask", "is_temp_name", "jsonable", "names_temp_file_of", "read_text_file"]

#: Every temporary file of :func:`atomic_path` is named ``.NAME.omnitmp-XXXXXXXX[.suffix]``: it starts with
#: a dot (final names never do) and carries this mark, so that readers never take it for a finished
#: file and :func:`clean_temp_files` can remove the leftovers of a killed process.
TEMP_MARK = ".omnitmp-"


def is_temp_name(name: str) -> bool:
    """Whether ``name`` is a temporary file of :func:`atomic_path` (never a finished file)."""
    return name.startswith(".") and TEMP_MARK in name


def clean_temp_files(directory: str | Path, recursive: bool = True) -> list[Path]:
    """Remove the temporary files a killed writer left in ``directory``; returns what was removed.

    Call it only while holding the directory's lock (:mod:`omnispectral.locking`): a temporary file of
    a running writer would otherwise be removed under its feet.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return []
    removed = []
    pattern = f".*{TEMP_MARK}*"
    for p in (directory.rglob(pattern) if recursive else directory.glob(pattern)):
        if is_temp_name(p.name) and p.is_file():
            with contextlib.suppress(FileNotFoundError):
                p.unlink()
                removed.append(p)
    return removed


def current_umask() -> int:
    """The process's file-creation mask (``/proc/self/status`` on Linux; else set-and-restore, not thread-safe)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def follow_umask(path: str | Path, directory: bool = False) -> None:
    """Give ``path`` the mode an ordinary ``open``/``mkdir`` would: ``0o666`` (``0o777`` for a directory) minus
    the umask.  :func:`tempfile.mkstemp` and :func:`tempfile.mkdtemp` create ``0o600``/``0o700`` whatever the
    umask says; a file renamed from such a temporary name would otherwise stay private."""
    os.chmod(path, (0o777 if directory else 0o666) & ~current_umask())


def names_temp_file_of(name: str | os.PathLike | None, path: Path) -> bool:
    """Whether ``name`` is one of :func:`atomic_path`'s temporary files for ``path`` (or names no file at all)."""
    if name is None:
        return True
    if isinstance(name, int):  # a file descriptor
        return False
    other = Path(os.path.abspath(os.fsdecode(name)))
    return other.parent == Path(os.path.abspath(path)).parent and other.name.startswith(f".{path.name}{TEMP_MARK}")


def error_naming_output(exc: OSError, path: Path) -> OSError:
    """``exc`` as an error of the output ``path`` when it names a temporary file of ``path`` or no file (a
    failed ``write`` names none): the user asked for ``path`` and never saw the temporary name.  Other
    errors (a parent directory, an input) come back unchanged."""
    if not names_temp_file_of(exc.filename, path) \
            or not (exc.filename2 is None or os.path.abspath(os.fsdecode(exc.filename2)) == os.path.abspath(path)):
        return exc
    code = os_errno(exc)  # also of OSError(28) or OSError("[Errno 28] …"), which some writers raise
    if code is None:
        return OSError(None, os_problem(exc), str(path))
    return OSError(code, exc.strerror or os.strerror(code), str(path))  # OSError picks the subclass (PermissionError…)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` if the block succeeds.

    The temporary file lives in the same directory (so the rename is atomic on POSIX) and keeps
    the target's suffix (so libraries that choose a format by extension still work).  On error
    the temporary file is removed and ``path`` is left untouched; an operating-system error of the
    temporary file is raised as one of ``path`` (:func:`error_naming_output`).  The file gets the
    permissions the umask gives new files (:func:`follow_umask`), not :func:`tempfile.mkstemp`'s ``0o600``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}{TEMP_MARK}",
                                   suffix=suffix if suffix is not None else path.suffix, dir=path.parent)
    except OSError as exc:
        renamed = error_naming_output(exc, path)
        if renamed is exc:
            raise
        raise renamed from exc
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        follow_umask(tmp_path)
        with open(tmp_path, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp_path, path)
    except OSError as exc:
        _remove_quietly(tmp_path)
        renamed = error_naming_output(exc, path)
        if renamed is exc:
            raise
        raise renamed from exc
    except RuntimeError as exc:  # a writer library's own error about the file (OpenEXR: "File too large")
        _remove_quietly(tmp_path)
        text = str(exc)
        if tmp_path.name not in text:
            raise
        raise InputFileError(path, "could not be written: " + text.replace(str(tmp_path), str(path))
                             .replace(tmp_path.name, path.name)) from exc
    except BaseException:
        _remove_quietly(tmp_path)
        raise


def _remove_quietly(path: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        path.unlink()


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def jsonable(x: Any) -> Any:
    """``x`` with NumPy arrays and scalars as lists and numbers, anything else JSON cannot hold as its ``str``."""
    return json.loads(json.dumps(x, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def atomic_write_json(path: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON to ``path`` atomically."""
    return atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_text_file(path: str | Path, what: str = "file", encoding: str = "utf-8") -> str:
    """The text of a user's file; a missing or unreadable one is an ``InputFileError`` naming it."""

    path = Path(path)
    try:
        return path.read_text(encoding=encoding)
    except FileNotFoundError:
        raise InputFileError(path, f"{what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFileError(path, f"cannot read the {what} ({exc})") from None
