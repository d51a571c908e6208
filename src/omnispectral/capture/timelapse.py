"""Time-lapse: one capture session per time slot, in a series directory with an index.

Slots are ``from, from + every, …`` up to ``to`` (inclusive), in the clock's time zone.  The loop waits
for each slot on the :class:`~omnispectral.capture.devices.Clock`, runs the capture into
``SERIES/slot_HHMM[SS]/``, and if the capture ran past the following slots' start times those slots
are recorded as skipped (the paper's 5-minute interval holds when one capture takes ~180 s).  The
index ``SERIES/series.json`` is rewritten atomically after every slot, so a series can be resumed:
complete slots are not captured again, slots whose time has passed are marked missed.
"""

from __future__ import annotations

import datetime as _dt
import json
import re
from collections.abc import Callable
from pathlib import Path

from omnispectral.capture.devices import Clock
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.io import atomic_write_json
from omnispectral.ownership import claim_output_directory
from omnispectral.progress import ProgressCallback, report_progress

__all__ = ["INDEX", "parse_hhmm", "parse_interval_s", "run_timelapse", "slot_duration_s", "slot_name", "slot_times"]

INDEX = "series.json"


def parse_interval_s(text: str) -> float:
    """``5min``, ``300s``, ``1h``, ``90`` (seconds) → seconds."""
    m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(s|sec|min|m|h)?\s*", str(text).lower())
    if not m:
        raise ConfigurationError(f"interval {text!r} is not like 5min, 300s or 1h")
    value = float(m.group(1)) * {"s": 1, "sec": 1, None: 1, "min": 60, "m": 60, "h": 3600}[m.group(2)]
    if value <= 0:
        raise ConfigurationError(f"interval {text!r} must be positive")
    return value


def parse_hhmm(text: str, day: _dt.date, tz: _dt.tzinfo) -> _dt.datetime:
    """``HH:MM`` (or ``HH:MM:SS``) on ``day`` in ``tz``."""
    try:
        t = _dt.time.fromisoformat(text)
    except ValueError:
        raise ConfigurationError(f"time {text!r} is not HH:MM") from None
    return _dt.datetime.combine(day, t, tzinfo=tz)


def slot_times(start: _dt.datetime, end: _dt.datetime, every_s: float) -> list[_dt.datetime]:
    if end < start:
        raise ConfigurationError(f"the series ends ({end:%H:%M}) before it starts ({start:%H:%M})")
    n = int((end - start).total_seconds() // every_s) + 1
    return [start + _dt.timedelta(seconds=i * every_s) for i in range(n)]


def slot_name(t: _dt.datetime) -> str:
    return f"slot_{t:%H%M}" + (f"{t:%S}" if t.second else "")


def slot_duration_s(result: dict, started: _dt.datetime, finished: _dt.datetime) -> float:
    """The capture time (s) a slot's frames took: the capture's ``capture_s`` when it states it (a resumed capture
    counts the runs an interruption cut short: the time up to their last recorded frame), else the time this run
    took on the clock (``finished - started``), which is all of it for a capture that was never interrupted.

    Parameters
    ----------
    result : dict
        What ``capture_slot`` returned.
    started, finished : datetime.datetime
        The series' clock before and after this run of the capture.

    Returns
    -------
    float
        Seconds.
    """
    stated = result.get("capture_s")
    if isinstance(stated, (int, float)) and not isinstance(stated, bool) and stated >= 0:
        return float(stated)
    return (finished - started).total_seconds()


def run_timelapse(series_dir: str | Path, slots: list[_dt.datetime], clock: Clock,
                  capture_slot: Callable[[Path, _dt.datetime], dict], meta: dict | None = None,
                  on_slot: Callable[[dict], None] | None = None, progress: ProgressCallback | None = None) -> dict:
    """Capture every slot that is still to come; returns the index (also written to ``series.json``).

    ``capture_slot(session_dir, slot_time)`` runs one capture and returns at least ``{"complete": bool}``;
    it reports its own frames (e.g. passes the caller's progress callback on to the capture).  A slot whose capture
    was interrupted (the series killed during it) is captured again on resume: the capture resumes its session,
    and the slot's ``duration_s`` is the capture time of all its frames (:func:`slot_duration_s`: the capture's
    ``capture_s``, which a simulated capture states; a capture that does not state it is timed on the clock).

    Parameters
    ----------
    series_dir : str or pathlib.Path
        The series directory (created if needed): ``series.json`` and one ``slot_HHMM[SS]/`` session per slot.
    slots : list of datetime.datetime
        The slot start times (timezone-aware, ascending; :func:`slot_times`); a resumed series must have the
        same times.
    clock : Clock
        The clock the loop waits on (``now``, ``sleep`` in seconds).
    capture_slot : callable
        ``capture_slot(session_dir, slot_time) -> dict`` runs one capture; ``"complete"`` (bool) and
        ``"stopped_reason"`` of its result are recorded, and ``"capture_s"`` (optional, seconds) is the capture
        time of the session's frames over every run of it.
    meta : dict, optional
        Extra fields of a new index (e.g. the rig and the interval).
    on_slot : callable, optional
        ``on_slot(entry)`` after each slot's entry is recorded and the index saved.
    progress : ProgressCallback, optional
        ``progress("slots", done, total)``: once at the start (before waiting for the first slot, the slots a
        resumed series had settled as done), then after each slot (captured, missed, or skipped by an overrun).

    Returns
    -------
    dict
        The index: ``slots`` (per slot ``time``, ``session``, ``status`` -- ``complete``, ``incomplete``,
        ``skipped``, ``missed`` or ``pending`` -- and for captured slots ``started``, ``finished``,
        ``duration_s`` in seconds and ``reason``), ``n_complete``, ``n_skipped`` and ``meta``'s fields.

    Raises
    ------
    InputFileError
        When ``series.json`` is unreadable or holds other slot times.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.3, Fig. 12 (a time-lapse sequence captured from 6:00 to 17:00 at
       5-min intervals), Table 2 (about 180 s per omnidirectional capture).
    """
    series = claim_output_directory(series_dir, "timelapse")  # a folder of the user's: refused
    index = _load_index(series) or {"format": "omnispectral-series", "format_version": 1, **(meta or {}),
                                    "slots": [{"time": t.isoformat(), "session": slot_name(t), "status": "pending"}
                                              for t in slots]}
    entries = index["slots"]
    if [e["time"] for e in entries] != [t.isoformat() for t in slots]:
        raise InputFileError(series / INDEX, "holds a series with other slot times; choose another directory")
    settled = {i for i, e in enumerate(entries) if e["status"] in ("complete", "skipped", "missed")}
    report_progress(progress or None, "slots", len(settled), len(entries))
    for i, (entry, t) in enumerate(zip(entries, slots, strict=True)):
        if i in settled:
            continue
        now = clock.now()
        later = slots[i + 1] if i + 1 < len(slots) else None
        if later is not None and now >= later:
            entry.update(status="missed", reason=f"slot time passed (now {now:%H:%M:%S})")
            _save(series, index, on_slot, entry)
            settled.add(i)
            report_progress(progress or None, "slots", len(settled), len(entries))
            continue
        clock.sleep((t - now).total_seconds())
        started = clock.now()
        result = capture_slot(series / entry["session"], t)
        finished = clock.now()
        entry.update(status="complete" if result.get("complete") else "incomplete", started=started.isoformat(),
                     finished=finished.isoformat(), duration_s=slot_duration_s(result, started, finished),
                     reason=result.get("stopped_reason"))
        settled.add(i)
        for j, (later_entry, lt) in enumerate(zip(entries[i + 1:], slots[i + 1:], strict=True), start=i + 1):
            if lt > finished:
                break
            if later_entry["status"] == "pending":
                later_entry.update(status="skipped", reason=f"the {t:%H:%M} capture overran until {finished:%H:%M:%S}")
                settled.add(j)
        _save(series, index, on_slot, entry)
        report_progress(progress or None, "slots", len(settled), len(entries))
    return index


def _save(series: Path, index: dict, on_slot, entry: dict) -> None:
    index["n_complete"] = sum(e["status"] == "complete" for e in index["slots"])
    index["n_skipped"] = sum(e["status"] in ("skipped", "missed") for e in index["slots"])
    atomic_write_json(series / INDEX, index)
    if on_slot is not None:
        on_slot(entry)


def _load_index(series: Path) -> dict | None:
    p = series / INDEX
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputFileError(p, f"unreadable series index ({exc})") from None
