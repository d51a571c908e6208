"""Fingerprints of intermediates: a product's ``merged/`` is reused only for exactly what made it.

``process`` writes ``PRODUCT/merged/`` (HDR-merged directions, camera B's offsets or parallax maps)
and resumes from it.  What determined those files is recorded in ``merged/fingerprint.json`` *before*
the first of them is written (:func:`product_fingerprint`):

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

import hashlib
import json
import shutil
from pathlib import Path

from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_json

FINGERPRINT_VERSION = 1
FINGERPRINT_FILE = "fingerprint.json"


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def session_identity(session_path: str | Path) -> dict:
    """Identity and content of a session: creation time, kind, rig, and a hash of all its frame records."""
    from omnispectral.capture.session import Session, read_journal

    s = Session.open(session_path)
    meta = s.metadata()
    records = read_journal(s.journal_path).records
    h = hashlib.sha256()
    for key in sorted(records):
        rec = records[key]
        h.update(json.dumps([list(key), rec.get("sha256"), rec.get("bytes"), rec.get("exposure_s")]).encode())
    return {"created_utc": meta.get("created_utc"), "kind": meta.get("kind"), "rig": meta.get("rig"),
            "n_frames": len(records), "frames_sha256": h.hexdigest()}


def product_fingerprint(session_path: str | Path, *, hdr_weight: str, registration: str,
                        min_confidence: float | None = None, rig_calibration: str | Path | None = None,
                        skipped_directions=(), merged_format_version: int | None = None) -> dict:
    """Everything that determines a product's ``merged/`` directory (module docstring)."""
    from omnispectral.mosaic.sources import FORMAT_VERSION

    session = Path(session_path)
    rig_file = session / "rig.toml"
    plan = json.loads((session / "plan.json").read_text(encoding="utf-8"))
    reg: dict = {"method": registration}
    if registration == "paper":
        reg["min_confidence"] = None if min_confidence is None else float(min_confidence)
    else:
        reg["rig_calibration_sha256"] = None if rig_calibration is None else file_sha256(rig_calibration)
    return {"fingerprint_version": FINGERPRINT_VERSION,
            "merged_format_version": merged_format_version if merged_format_version is not None else FORMAT_VERSION,
            "session": session_identity(session), "rig_sha256": file_sha256(rig_file),
            "exposures_s": [float(t) for t in plan.get("exposures_s", [])],
            "hdr_weight": hdr_weight, "registration": reg,
            "skipped_directions": sorted(int(d) for d in skipped_directions)}


def flatten(d: dict, prefix: str = "") -> dict:
    """``{"a": {"b": 1}}`` → ``{"a.b": 1}`` (lists stay values)."""
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
    """What differs between two fingerprints (or two parameter sets), one ``key: old → new`` each; top-level
    keys first (the parameter a user changed before the quantities derived from it)."""
    a, b = flatten(recorded), flatten(wanted)
    keys = sorted(set(a) | set(b), key=lambda k: (k.count("."), k))
    return [f"{k}: {_short(a.get(k))} → {_short(b.get(k))}" for k in keys if a.get(k) != b.get(k)]


def read_fingerprint(directory: str | Path) -> dict | None:
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
    """Make ``merged_dir`` hold intermediates of exactly ``wanted``: ``"new"``, ``"resume"`` or ``"overwritten"``.

    Another fingerprint (or intermediates without one) is refused naming the differences unless
    ``overwrite``, which removes ``merged_dir`` and the ``dependents`` (products derived from it).
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
        shutil.rmtree(merged_dir)
        for dep in dependents:
            dep = Path(dep)
            if dep.is_dir():
                shutil.rmtree(dep)
            elif dep.exists():
                dep.unlink()
    merged_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(merged_dir / FINGERPRINT_FILE, wanted)
    return state
