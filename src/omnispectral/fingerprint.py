"""Fingerprints of intermediates: a product's ``merged/`` is reused only for exactly what made it.

``process`` writes ``PRODUCT/merged/`` (HDR-merged directions, camera B's offsets or parallax maps)
and resumes from it.  What determined those files is recorded in ``merged/fingerprint.json`` *before*
the first of them is written (:func:`omnispectral.product.fingerprint.product_fingerprint`):

* the session's identity and content — its creation time, kind, and a SHA-256 over every frame
  record of its journal (each record holds the frame file's own SHA-256), so another session, a
  re-simulated one, or one with other frames never matches;
* the rig snapshot (``rig.toml``) and the plan's exposures;
* the HDR weight, the registration method and its settings (``min_confidence``; the rig
  calibration file's content), the directions left out as bad;
* the formats of the merged directory and of this fingerprint (code format versions).

A run finds either no fingerprint (fresh or half-created directory: it starts), the same one (it
resumes), or another one: then :func:`check_merged` refuses with one line naming what differs, or
with ``overwrite`` removes the stale intermediates and starts again.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_json
from omnispectral.ownership import (
    MERGED_NAMES,
    STORE_NAMES,
    check_owned_tree,
    remove_owned_tree,
    written_by_omnispectral,
)

__all__ = ["FINGERPRINT_FILE", "FINGERPRINT_VERSION", "check_merged", "differences", "flatten",
           "read_fingerprint"]

FINGERPRINT_VERSION = 1
FINGERPRINT_FILE = "fingerprint.json"


def flatten(d: dict, prefix: str = "") -> dict:
    """Nested dictionaries as one level of dotted keys: ``{"a": {"b": 1}}`` → ``{"a.b": 1}``.

    Parameters
    ----------
    d
        The nested dictionary (lists stay values).
    prefix
        Prepended to every key.

    Returns
    -------
    dict
        The flat dictionary.
    """
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "."))
        else:
            out[name] = v
    return out


def _short(v) -> str:
    text = json.dumps(v)
    return text if len(text) <= 40 else text[:18] + "…" + text[-18:]


def differences(recorded: dict, wanted: dict) -> list[str]:
    """What differs between two fingerprints (or two parameter sets).

    Parameters
    ----------
    recorded, wanted
        The two (nested) dictionaries.

    Returns
    -------
    list of str
        One ``key: old → new`` per differing dotted key; top-level keys first (the parameter a user changed
        before the quantities derived from it).
    """
    a, b = flatten(recorded), flatten(wanted)
    keys = sorted(set(a) | set(b), key=lambda k: (k.count("."), k))
    return [f"{k}: {_short(a.get(k))} → {_short(b.get(k))}" for k in keys if a.get(k) != b.get(k)]


def read_fingerprint(directory: str | Path) -> dict | None:
    """The fingerprint recorded in a ``merged/`` directory.

    Parameters
    ----------
    directory
        The directory.

    Returns
    -------
    dict or None
        The fingerprint; ``None`` when there is none; ``{"unreadable": True}`` when it cannot be read.
    """
    p = Path(directory) / FINGERPRINT_FILE
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError):
        return {"unreadable": True}
    return data if isinstance(data, dict) else {"unreadable": True}


def check_merged(merged_dir: str | Path, wanted: dict, overwrite: bool = False,
                 dependents: tuple[str | Path, ...] = ()) -> str:
    """Make ``merged_dir`` hold intermediates of exactly ``wanted``.

    Another fingerprint (or intermediates without one) is refused naming the differences unless
    ``overwrite``, which removes ``merged_dir`` and the ``dependents`` (products derived from it) — only
    what :func:`written_by_omnispectral` recognises: anything else in the way is refused, ``overwrite``
    or not, before anything is removed.

    Parameters
    ----------
    merged_dir
        The intermediates' directory (``PRODUCT/merged``).
    wanted
        The fingerprint of this run.
    overwrite
        Remove intermediates made from something else (and the ``dependents``) instead of refusing.
    dependents
        Paths derived from the intermediates, removed with them.

    Returns
    -------
    str
        ``"new"``, ``"resume"`` or ``"overwritten"``.

    Raises
    ------
    InputFileError
        On another fingerprint without ``overwrite``, or something in the way that omnispectral did not write.
    """
    merged_dir = Path(merged_dir)
    state = "new"
    if merged_dir.exists():
        recorded = read_fingerprint(merged_dir)
        has_data = (merged_dir / "merged.json").exists()
        if recorded == wanted:
            return "resume"
        if recorded is not None or has_data:
            if not overwrite:
                what = ("has no fingerprint (made by an older version or another command)" if recorded is None
                        else "was made from other inputs or settings: " + "; ".join(differences(recorded, wanted)[:4]))
                raise InputFileError(merged_dir, f"{what}. Rerun with --overwrite to rebuild the product, or "
                                                 f"choose another output directory")
            state = "overwritten"
        targets = [(merged_dir, MERGED_NAMES, "merged directions")] + [
            (Path(d), STORE_NAMES if Path(d).is_dir() else re.compile(re.escape(Path(d).name)), "product")
            for d in dependents]
        for path, names, what in targets:  # everything checked before anything is removed
            if path.exists() and not written_by_omnispectral(path):
                raise InputFileError(path, "is in the way and was not written by omnispectral: nothing was "
                                           "removed; move it, or choose another output directory")
            check_owned_tree(path, names, what)
        for path, names, what in targets:
            remove_owned_tree(path, names, what)
    merged_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(merged_dir / FINGERPRINT_FILE, wanted)
    return state
