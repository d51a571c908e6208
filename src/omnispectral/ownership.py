"""What a command may delete or replace: only what omnispectral can prove it wrote, never an input.

Three rules, each checked before anything is written or removed:

1. **An output is never an input.**  :func:`check_output_outside_inputs`: no output path may be, or lie
   inside, an input of the same command (a session, product, series, rig or calibration file): writing
   ``calibrate rig SESSION -o SESSION/rig.toml`` would replace the session's own rig.
2. **A directory output is ours or new.**  :func:`claim_output_directory`: a command that writes a
   directory of files (``render``, ``relight``, ``process-series``, …) writes into a directory that does
   not exist, is empty, or holds the marker :data:`OUTPUT_MARKER` (or the index of an omnispectral
   product, session or series); anything else is a user's directory and is refused, so that no file of
   theirs with one of our file names is replaced.
3. **A tree is removed only when every file in it is ours.**  :func:`remove_owned_tree` lists the files
   a rebuild (``--overwrite``) would delete and refuses, before deleting any, when one of them does not
   match the names the tree's writer uses (:data:`MERGED_NAMES`, :data:`STORE_NAMES`): a user's note kept
   inside ``merged/`` or ``panorama.zarr/`` survives and the rebuild says why it stopped.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shutil
from collections.abc import Iterable
from pathlib import Path

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.io import TEMP_MARK, atomic_write_json
from omnispectral.locking import LOCK_NAME

__all__ = ["INDEX_FILES", "MERGED_NAMES", "OUTPUT_MARKER", "STORE_NAMES", "check_output_outside_inputs",
           "check_owned_tree", "claim_output_directory", "foreign_files", "json_format", "remove_owned_tree",
           "written_by_omnispectral"]

#: Marker a directory output carries: ``{"format": "omnispectral-output", "command": …}``.
OUTPUT_MARKER = ".omnispectral-output.json"
#: Index files whose ``format`` names omnispectral: a directory holding one was written by us.
INDEX_FILES = ("product.json", "session.json", "series.json", "series_product.json", "render_series.json",
               "relight.json", "merged.json", "zarr.json", "board.json", "merged/merged.json",
               "product/product.json", "session/session.json")
_ALWAYS_OURS = re.compile(rf"(.*/)?({re.escape(LOCK_NAME)}|[^/]*{re.escape(TEMP_MARK)}[^/]*)(/.*)?")
#: Files of a merged-directions directory (``mosaic.sources``): images, parallax maps, index, fingerprint.
MERGED_NAMES = re.compile(r"d\d{4,}_[A-Z]\.npy|merged\.json|fingerprint\.json")
#: Files of a panorama store (``mosaic.store``): Zarr v3 metadata, chunk keys, completion markers.
STORE_NAMES = re.compile(r"([^/]+/)*zarr\.json|[^/]+/c(/\d+)+|\d+/\.done/\d+_\d+\.json")


def _inside(path: Path, directory: Path) -> bool:
    return path == directory or directory in path.parents


def check_output_outside_inputs(outputs: Iterable[str | Path], inputs: Iterable[str | Path]) -> None:
    """Refuse an output that is an input or lies inside an input directory (rule 1 of the module docstring).

    Parameters
    ----------
    outputs
        The paths a command will write.
    inputs
        The paths it reads; names that do not exist on disk (a scene or filter name) are ignored.

    Raises
    ------
    ConfigurationError
        ``"OUT: is the input IN …"`` or ``"OUT: lies inside the input IN …"`` (exit 2).
    """
    existing = [(str(i), Path(i).resolve()) for i in inputs if isinstance(i, str | os.PathLike) and Path(i).exists()]
    for out in outputs:
        if not isinstance(out, str | os.PathLike):
            continue
        o = Path(out).resolve()
        for shown, i in existing:
            if o == i or (o.exists() and o.samefile(i)):  # a hard link is the same file too
                raise ConfigurationError(f"{out}: is the input {shown} of this command; choose another output")
            if i.is_dir() and _inside(o, i):
                raise ConfigurationError(f"{out}: lies inside the input {shown} of this command, whose files it "
                                         f"could replace; choose an output outside it")


def json_format(path: Path) -> str:
    """The ``format`` a small JSON file of ours declares (at the top level or under ``attributes.omnispectral``,
    as a Zarr group's ``zarr.json``), or ``""``."""
    try:
        if path.stat().st_size > 1 << 26:
            return ""
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    if not isinstance(data, dict):
        return ""
    attributes = data.get("attributes")
    inner = attributes.get("omnispectral") if isinstance(attributes, dict) else None
    fmt = data.get("format") or (inner.get("format") if isinstance(inner, dict) else "")
    return fmt if isinstance(fmt, str) else ""


def written_by_omnispectral(path: str | Path) -> bool:
    """Whether ``path`` is something omnispectral wrote and may replace.

    That is an empty directory, a directory with our fingerprint or ``merged.json``, a Zarr store or JSON file
    whose format names omnispectral.  Anything else — a user's file or folder in the way — is never deleted,
    ``--overwrite`` or not.

    Parameters
    ----------
    path
        A file or directory.

    Returns
    -------
    bool
        True when omnispectral wrote it.
    """
    path = Path(path)
    if path.is_dir():
        if not any(path.iterdir()):
            return True
        if (path / "fingerprint.json").is_file() or (path / "merged.json").is_file():
            return True
        return json_format(path / "zarr.json").startswith("omnispectral")
    return path.is_file() and path.suffix == ".json" and json_format(path).startswith("omnispectral")


def _is_ours(directory: Path) -> bool:
    if (directory / OUTPUT_MARKER).is_file():
        return True
    return any(json_format(directory / name).startswith("omnispectral") for name in INDEX_FILES
               if (directory / name).is_file())


def claim_output_directory(path: str | Path, command: str) -> Path:
    """Make ``path`` a directory ``command`` may write into (rule 2 of the module docstring).

    Parameters
    ----------
    path
        The output directory.
    command
        The command's name, recorded in the marker.

    Returns
    -------
    Path
        ``path``, created if needed, holding :data:`OUTPUT_MARKER`.

    Raises
    ------
    InputFileError
        When ``path`` is a file, or a non-empty directory omnispectral did not write.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputFileError(path, "is a file; the output of this command is a directory")
    if path.is_dir() and not _is_ours(path):
        visible = [p for p in path.iterdir() if not _ALWAYS_OURS.fullmatch(p.name)]
        if visible:
            raise InputFileError(path, f"is a directory omnispectral did not write ({visible[0].name} is in it): "
                                       f"nothing was replaced; choose a new or empty directory")
    path.mkdir(parents=True, exist_ok=True)
    if not (path / OUTPUT_MARKER).is_file():
        created = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
        atomic_write_json(path / OUTPUT_MARKER, {"format": "omnispectral-output", "command": command,
                                                 "created_utc": created})
    return path


def foreign_files(root: str | Path, names: re.Pattern) -> list[Path]:
    """Files under ``root`` whose path relative to it does not match ``names`` (nor a lock or temporary file)."""
    root = Path(root)
    if root.is_file():
        return [] if names.fullmatch(root.name) else [root]
    out = []
    for p in sorted(root.rglob("*")):
        if p.is_dir() and not p.is_symlink():
            continue
        rel = p.relative_to(root).as_posix()
        if not (names.fullmatch(rel) or _ALWAYS_OURS.fullmatch(rel)):
            out.append(p)
    return out


def check_owned_tree(root: str | Path, names: re.Pattern, what: str) -> None:
    """Refuse, naming the first one, when a file under ``root`` does not match ``names`` (rule 3).

    Parameters
    ----------
    root
        The directory (or file) a rebuild would remove; nothing to check if it does not exist.
    names
        The relative paths its writer uses (:data:`MERGED_NAMES`, :data:`STORE_NAMES`).
    what
        What ``root`` is, for the message (``"merged directions"``).

    Raises
    ------
    InputFileError
        Naming the first file that is not ours (or ``root`` itself when it is a symbolic link).
    """
    root = Path(root)
    if root.is_symlink():
        raise InputFileError(root, f"is a symbolic link, not {what} omnispectral wrote: nothing was removed")
    if not root.exists():
        return
    foreign = foreign_files(root, names)
    if foreign:
        more = f" (and {len(foreign) - 1} more)" if len(foreign) > 1 else ""
        raise InputFileError(foreign[0], f"is inside the {what} being rebuilt but omnispectral did not write "
                                         f"it{more}: nothing was removed; move it out and rerun")


def remove_owned_tree(root: str | Path, names: re.Pattern, what: str) -> None:
    """Delete ``root`` when every file in it matches ``names`` (:func:`check_owned_tree`, rule 3)."""
    root = Path(root)
    check_owned_tree(root, names, what)
    if root.is_dir():
        shutil.rmtree(root)
    elif root.exists():
        root.unlink()
