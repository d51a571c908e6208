"""Recovery of sessions: the capture order of a session's frames, and a damaged journal rebuilt.

:func:`capture_order` gives every planned frame's position in the capture loop's order (a resumed
simulation uses it: :func:`omnispectral.sim.devices.resume_simulated_devices`).

:func:`repair_session` rebuilds ``journal.jsonl`` from the frames themselves: every raw frame
embeds its journal record in its TIFF description, so a journal with garbage lines (an editor, a
disk error) can be written again from the frames that decode; a dry run reports what would change.
A repair never blesses damaged pixels: a frame that fails the checksum its journal line holds, the pixel
checksum its own description holds, or holds a value above the camera's full scale is moved to
``quarantine/`` and left out of the journal, so that a resume shoots it again.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
import shutil
from pathlib import Path

from omnispectral.capture.session import (
    FRAME_NAME,
    QUARANTINE_DIR,
    Session,
    bracket_indices,
    dark_extensions,
    decode_frame,
    file_record_checksums,
    pixel_problem,
    read_journal,
    record_key,
)
from omnispectral.errors import InputFileError
from omnispectral.io import atomic_write_text, clean_temp_files
from omnispectral.locking import directory_lock
from omnispectral.rig import MAX_SUN_BRACKETS, SUN_EXPOSURE_BASE

__all__ = ["capture_order", "frame_record_from_file", "quarantine_frame", "quarantine_relpath", "repair_session",
           "sun_bracket_order"]


def sun_bracket_order(plan, cameras: tuple[str, ...]) -> list[tuple[int, str, int]]:
    """Every frame key the sun brackets may have, in capture order: the aimed pose and its retries
    (direction indices from ``plan.n_directions``, ``omnispectral.capture.run``), exposure, camera."""
    if not plan.sun_bracket:
        return []
    n = len(plan.sun_bracket["exposures_s"])
    return [(plan.n_directions + i, c, SUN_EXPOSURE_BASE + k) for i in range(MAX_SUN_BRACKETS) for k in range(n)
            for c in cameras]


def capture_order(session: Session) -> dict[tuple[int, str, int], int]:
    """Position of every planned frame in the capture loop's order (direction, exposure, camera), a direction's
    dark extension (its ``dark`` event) right after its bracket, the sun brackets right after the direction that
    found the sun (its ``sun`` event; at the end when unknown)."""
    plan = session.plan()
    cameras = session.cameras()
    sun_keys = sun_bracket_order(plan, cameras)
    source = next((e.get("source_direction") for e in session.events()
                   if e.get("event") == "sun" and e.get("source_direction") is not None), None)
    extensions = dark_extensions(session, plan)
    order, n = {}, 0
    for d in plan.directions:
        for k in bracket_indices(plan, extensions.get(d.index, 0)):
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


def frame_record_from_file(session: Session, rel: str, journal_record: dict | None = None,
                           max_dn: int | None = None) -> dict:
    """The journal record a frame file embeds, with its SHA-256 and size; raises ``InputFileError`` if damaged.

    Parameters
    ----------
    session
        The session holding the frame.
    rel
        The frame's path relative to the session (``frames/dNNNN/{A,B}_eKK.tif``).
    journal_record
        The frame's journal record, when the journal still holds one: a file whose SHA-256 differs from the
        one it holds is damaged (never given a new checksum).
    max_dn
        The camera's full scale; ``None``: the session's rig's (:meth:`Session.full_scale_dn`).

    Notes
    -----
    Damaged also: a file that does not decode, whose embedded record is not for its name, whose pixels
    differ from the ``pixels_sha256`` the embedded record holds, or that holds a value above ``max_dn``
    (:func:`~omnispectral.capture.session.pixel_problem`).  Frames written before ``pixels_sha256``
    existed lack it: for them the SHA-256 of the journal line is the only checksum, so when that line is lost
    only decoding, shape and full scale are checked.
    """
    m = FRAME_NAME.match(rel[len("frames/"):]) if rel.startswith("frames/") else None
    p = session.path / rel
    if m is None:
        raise InputFileError(p, "not a frame name")
    key = (int(m.group(1)), m.group(2), int(m.group(3)))
    content = p.read_bytes()
    sha256 = hashlib.sha256(content).hexdigest()
    expected = journal_record.get("sha256") if journal_record is not None else None
    if isinstance(expected, str) and sha256 != expected:
        raise InputFileError(p, "checksum mismatch with its journal record (the file changed after the capture)")
    pixels, meta = decode_frame(p, content)
    try:
        embedded = record_key(meta)
    except (KeyError, TypeError, ValueError):
        raise InputFileError(p, "the embedded frame record lacks its key") from None
    if embedded != key:
        raise InputFileError(p, f"the embedded record is for {embedded}, not {key}")
    if max_dn is None:
        max_dn = session.full_scale_dn().get(key[1])
    problem = pixel_problem(pixels, meta, max_dn)
    if problem:
        raise InputFileError(p, problem)
    return {**meta, **file_record_checksums(content)}


def quarantine_relpath(session: Session, rel: str) -> str:
    """Where :func:`quarantine_frame` moves the frame ``rel`` (``frames/…``): ``quarantine/frames/…``, with
    ``.2``, ``.3``… before ``.tif`` when a frame of that name was quarantined before (never overwritten)."""
    target = f"{QUARANTINE_DIR}/{rel}"
    n = 1
    while (session.path / target).exists():
        n += 1
        target = f"{QUARANTINE_DIR}/{rel[:-len('.tif')]}.{n}.tif"
    return target


def quarantine_frame(session: Session, rel: str) -> str:
    """Move the damaged frame ``rel`` aside into the session's quarantine folder (never deleted); returns its
    new path relative to the session."""
    target = quarantine_relpath(session, rel)
    (session.path / target).parent.mkdir(parents=True, exist_ok=True)
    os.replace(session.path / rel, session.path / target)
    return target


def _frame_files(session: Session) -> list[str]:
    """The final frame files under ``frames/`` (``frames/dNNNN/{A,B}_eKK.tif``), sorted."""
    frames_dir = session.path / "frames"
    if not frames_dir.is_dir():
        return []
    names = sorted(p.relative_to(frames_dir).as_posix() for p in frames_dir.rglob("*.tif"))
    return [f"frames/{rel}" for rel in names if FRAME_NAME.match(rel)]


def _read_frames(session: Session, journal: dict) -> tuple[dict, list[dict]]:
    """The records of the frames that pass :func:`frame_record_from_file`, by key, and the refused ones
    (``file``, ``problem``, ``quarantine``: where a repair moves it)."""
    full_scale = session.full_scale_dn()
    good, refused = {}, []
    for rel in _frame_files(session):
        m = FRAME_NAME.match(rel[len("frames/"):])
        key = (int(m.group(1)), m.group(2), int(m.group(3)))
        line = journal.get(key)
        try:
            rec = frame_record_from_file(session, rel, None if line is None or line.get("referenced") else line,
                                         full_scale.get(key[1]))
        except InputFileError as exc:
            refused.append({"file": rel, "problem": exc.problem, "quarantine": quarantine_relpath(session, rel)})
            continue
        good[key] = rec
    return good, refused


def repair_session(path: str | Path, apply: bool = False) -> dict:
    """Rebuild the journal of a session from its frames (dry run unless ``apply``); returns what changed.

    The new journal lists every frame that decodes and whose embedded record matches its file name,
    in capture order, with the file's SHA-256 and size, and keeps the records of referenced frames
    (``import --reference``; ``session verify`` checks their files).  Damaged frames are never given a new
    checksum: a file that fails the SHA-256 its journal line holds, does not decode, or whose pixels fail
    :func:`frame_record_from_file`'s checks (the pixel checksum its description embeds, the camera's full
    scale) is listed in ``damaged_frames`` and, with ``apply``, moved to ``quarantine/frames/…`` (never
    deleted) and left out of the journal, so that a resume captures it again.  With ``apply`` the old journal
    is kept as ``journal.jsonl.bak-TIME`` and the repair is logged (``repair`` event naming the quarantined
    frames).
    """
    s = Session.open(path)
    with directory_lock(s.path, "session repair") if apply else contextlib.nullcontext():
        if apply:
            clean_temp_files(s.path)
        old = read_journal(s.journal_path)
        order = capture_order(s)
        found, damaged = _read_frames(s, old.records)
        rebuilt = {k: rec for k, rec in found.items() if k in order}
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
                  "n_quarantined": len(damaged), "quarantined": [d["quarantine"] for d in damaged],
                  "recovered": [list(k) for k in recovered[:50]], "dropped": [list(k) for k in dropped[:50]]}
        needed = bool(recovered or dropped or changed or damaged or old.bad_lines or old.partial_tail)
        report["needed"] = needed
        if apply and needed:
            _apply_repair(s, old, rebuilt, order, damaged, report)
    return report


def _apply_repair(s: Session, old, rebuilt: dict, order: dict, damaged: list[dict], report: dict) -> None:
    """Quarantine the damaged frames, then write the rebuilt journal (the old one kept), then log the repair.

    The frames move first: a repair killed in between leaves journalled frames that are missing (``session
    verify`` names them; a second repair drops their lines), never a damaged frame without its line."""
    for d in damaged:
        d["quarantine"] = quarantine_frame(s, d["file"])
    report["quarantined"] = [d["quarantine"] for d in damaged]
    stamp = _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%S")
    backup = s.path / f"journal.jsonl.bak-{stamp}"
    if s.journal_path.exists():
        shutil.copy2(s.journal_path, backup)
        report["backup"] = str(backup)
    lines = [json.dumps(rebuilt[k], separators=(",", ":")) + "\n" for k in sorted(rebuilt, key=order.get)]
    atomic_write_text(s.journal_path, "".join(lines))
    s.log_event("repair", frames=len(rebuilt), recovered=report["n_recovered"], dropped=report["n_dropped"],
                bad_lines=len(old.bad_lines), quarantined=report["quarantined"])
    report["applied"] = True
