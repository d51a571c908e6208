"""Recovery of sessions: the capture order of a session's frames, and a damaged journal rebuilt.

:func:`capture_order` gives every planned frame's position in the capture loop's order (a resumed
simulation uses it: :func:`omnispectral.sim.devices.resume_simulated_devices`).

:func:`repair_session` rebuilds ``journal.jsonl`` from the frames themselves: every raw frame
embeds its journal record in its TIFF description, so a journal with garbage lines (an editor, a
disk error) can be written again from the frames that decode; a dry run reports what would change.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import shutil
from pathlib import Path

from omnispectral.capture.session import FRAME_NAME, Session, read_journal, record_key, sha256_of
from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_text, clean_temp_files
from omnispectral.locking import directory_lock
from omnispectral.rig import MAX_SUN_BRACKETS, SUN_EXPOSURE_BASE

__all__ = ["capture_order", "frame_record_from_file", "repair_session", "sun_bracket_order"]


def sun_bracket_order(plan, cameras: tuple[str, ...]) -> list[tuple[int, str, int]]:
    """Every frame key the sun brackets may have, in capture order: the aimed pose and its retries
    (direction indices from ``plan.n_directions``, ``omnispectral.capture.run``), exposure, camera."""
    if not plan.sun_bracket:
        return []
    n = len(plan.sun_bracket["exposures_s"])
    return [(plan.n_directions + i, c, SUN_EXPOSURE_BASE + k) for i in range(MAX_SUN_BRACKETS) for k in range(n)
            for c in cameras]


def capture_order(session: Session) -> dict[tuple[int, str, int], int]:
    """Position of every planned frame in the capture loop's order (direction, exposure, camera), the sun
    brackets right after the direction that found the sun (its ``sun`` event; at the end when unknown)."""
    plan = session.plan()
    cameras = session.cameras()
    sun_keys = sun_bracket_order(plan, cameras)
    source = next((e.get("source_direction") for e in session.events()
                   if e.get("event") == "sun" and e.get("source_direction") is not None), None)
    order, n = {}, 0
    for d in plan.directions:
        for k in range(len(plan.exposures_s)):
            for c in cameras:
                order[(d.index, c, k)] = n
                n += 1
        if d.index == source:
            for key in sun_keys:
                order[key] = n
                n += 1
    for key in sun_keys:
        if key not in order:
            order[key] = n
            n += 1
    return order


def frame_record_from_file(session: Session, rel: str) -> dict:
    """The journal record a frame file embeds, with its SHA-256 and size; raises ``InputFileError`` if damaged."""
    m = FRAME_NAME.match(rel[len("frames/"):]) if rel.startswith("frames/") else None
    if m is None:
        raise InputFileError(session.path / rel, "not a frame name")
    key = (int(m.group(1)), m.group(2), int(m.group(3)))
    _, meta = session.read_frame(*key)
    if not isinstance(meta, dict):
        raise InputFileError(session.path / rel, "no frame record in the TIFF description")
    try:
        embedded = record_key(meta)
    except (KeyError, TypeError, ValueError):
        raise InputFileError(session.path / rel, "the embedded frame record lacks its key") from None
    if embedded != key:
        raise InputFileError(session.path / rel, f"the embedded record is for {embedded}, not {key}")
    p = session.path / rel
    return {**meta, "sha256": sha256_of(p), "bytes": p.stat().st_size}


def repair_session(path: str | Path, apply: bool = False) -> dict:
    """Rebuild the journal of a session from its frames (dry run unless ``apply``); returns what changed.

    The new journal lists every frame that decodes and whose embedded record matches its file name,
    in capture order, with the file's SHA-256 and size, and keeps the records of referenced frames
    (``import --reference``; ``session verify`` checks their files).  Frames that do not decode are reported (a
    resume captures them again).  With ``apply`` the old journal is kept as ``journal.jsonl.bak-TIME``.
    """
    s = Session.open(path)
    with directory_lock(s.path, "session repair") if apply else contextlib.nullcontext():
        if apply:
            clean_temp_files(s.path)
        old = read_journal(s.journal_path)
        order = capture_order(s)
        rebuilt, damaged = {}, []
        frames_dir = s.path / "frames"
        files = sorted(p.relative_to(frames_dir).as_posix() for p in frames_dir.rglob("*.tif")) \
            if frames_dir.is_dir() else []
        for rel in files:
            if not FRAME_NAME.match(rel):
                continue
            try:
                rec = frame_record_from_file(s, f"frames/{rel}")
            except InputFileError as exc:
                damaged.append({"file": f"frames/{rel}", "problem": exc.problem})
                continue
            key = (int(rec["direction"]), str(rec["camera"]), int(rec["exposure_index"]))
            if key in order:
                rebuilt[key] = rec
        for key, rec in old.records.items():  # referenced frames (import --reference) live outside frames/
            if rec.get("referenced") and key in order and key not in rebuilt:
                rebuilt[key] = rec
        recovered = sorted(set(rebuilt) - set(old.records))
        dropped = sorted(set(old.records) - set(rebuilt))
        changed = [k for k in set(rebuilt) & set(old.records) if rebuilt[k].get("sha256") != old.records[k].get(
            "sha256")]
        report = {"session": str(s.path), "applied": False, "n_frames": len(rebuilt),
                  "n_journal_records": len(old.records), "journal_bad_lines": [n for n, _ in old.bad_lines],
                  "journal_partial_last_line": old.partial_tail, "n_recovered": len(recovered),
                  "n_dropped": len(dropped), "n_changed": len(changed), "damaged_frames": damaged,
                  "recovered": [list(k) for k in recovered[:50]], "dropped": [list(k) for k in dropped[:50]]}
        needed = bool(recovered or dropped or changed or old.bad_lines or old.partial_tail)
        report["needed"] = needed
        if apply and needed:
            stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%S")
            backup = s.path / f"journal.jsonl.bak-{stamp}"
            if s.journal_path.exists():
                shutil.copy2(s.journal_path, backup)
                report["backup"] = str(backup)
            lines = [json.dumps(rebuilt[k], separators=(",", ":")) + "\n" for k in sorted(rebuilt, key=order.get)]
            atomic_write_text(s.journal_path, "".join(lines))
            s.log_event("repair", frames=len(rebuilt), recovered=len(recovered), dropped=len(dropped),
                        bad_lines=len(old.bad_lines))
            report["applied"] = True
    return report
