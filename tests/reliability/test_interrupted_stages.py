"""Every interrupted stage resumes to the result of an uninterrupted run, and a damaged ground truth costs only the
report's accuracy section.

* ``process-series`` interrupted while a slot's report is written: the resume writes that report (the slot's
  ``product.json`` alone does not make a slot finished) and ends with the files of an uninterrupted run.
* ``timelapse`` interrupted during a slot's capture: the resumed slot's record states the capture time spent on
  its frames (the interrupted attempt's included) and the series' index matches an uninterrupted run's.
* a damaged ground truth (``SESSION/ground_truth/``): one warning line naming the file, the product and its
  report are written without accuracy, exit 0 — in ``process``, ``report`` and ``process-series``.
"""

from __future__ import annotations

import datetime as dt
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.sim.truth import GroundTruth

from .test_fault_injection import NOON, simulate_tiny, tiny_rig

#: The fake clock's precision: datetimes hold microseconds.
CLOCK_PRECISION_S = 2e-6


def _files(root: Path) -> list[str]:
    """Every file under ``root`` (relative names), without the lock file a run leaves."""
    return sorted(p.relative_to(root).as_posix() for p in root.rglob("*")
                  if p.is_file() and p.name != ".omnispectral.lock")


# ------------------------------------------------------------------ process-series: the report of a slot
def _tiny_series(path: Path, hours: tuple[int, ...] = (11, 13)) -> Path:
    from omnispectral.capture.timelapse import run_timelapse
    from omnispectral.sim.devices import FakeClock
    from omnispectral.sim.simulate import simulate_session

    from .test_fault_injection import tiny_scene

    slots = [NOON.replace(hour=h) for h in hours]
    clock = FakeClock(slots[0])

    def capture(session_dir, t):
        res = simulate_session(session_dir, tiny_rig(), tiny_scene(f"{t:%H:%M}"), start=clock.now(),
                               ground_truth_width=64, progress=False, calibration_views=False)
        clock.sleep(res["capture_s"])
        return res

    run_timelapse(path, slots, clock, capture)
    return path


@pytest.fixture(scope="module")
def series(tmp_path_factory) -> Path:
    return _tiny_series(tmp_path_factory.mktemp("series") / "series")


@pytest.mark.slow
def test_process_series_interrupted_in_a_report_resumes_to_the_same_files(series, tmp_path, monkeypatch):
    import omnispectral.product.process as process_module
    from omnispectral.product.series import process_series

    reference = tmp_path / "reference"
    process_series(series, reference)
    real = process_module.write_report
    calls = []

    def killed_once(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the second slot's report: a kill while it is written
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(process_module, "write_report", killed_once)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        process_series(series, out)
    monkeypatch.setattr(process_module, "write_report", real)
    second = sorted(p for p in out.iterdir() if p.is_dir())[1]
    assert (second / "product.json").is_file() and not (second / "report" / "report.json").exists()
    summary = process_series(series, out)  # the resume
    assert summary["n_slots"] == 2
    for slot in ("slot_1100", "slot_1300"):
        index = json.loads((out / slot / "product.json").read_text())
        assert index.get("report") and Path(index["report"]["json"]).is_file(), slot
    assert _files(out) == _files(reference)


# ------------------------------------------------------------------ timelapse: the interrupted slot's duration
def _timelapse(rig_file: Path, out: Path) -> int:
    return main(["-q", "timelapse", "--rig", str(rig_file), "--every", "20min", "--from", "12:00", "--to", "12:40",
                 "--gt-width", "32", "--no-calibration-views", "-o", str(out), "--json"])


def _interrupt_capture_once(monkeypatch, at_call: int) -> None:
    """The ``at_call``-th exposure of the run raises KeyboardInterrupt (a kill during a slot's capture)."""
    import omnispectral.capture.run as run_module

    real = run_module.expose_and_write
    calls = []

    def once(*args, **kwargs):
        calls.append(1)
        if len(calls) == at_call:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(run_module, "expose_and_write", once)


def _slot_times(entry: dict) -> tuple:
    return (entry["status"], dt.datetime.fromisoformat(entry["started"]), dt.datetime.fromisoformat(entry["finished"]),
            entry["duration_s"])


@pytest.mark.slow
def test_timelapse_resumed_after_a_kill_records_the_capture_time_of_the_slot(tmp_path, monkeypatch, capsys):
    from omnispectral.capture.session import Session

    rig_file = tmp_path / "tiny.toml"
    rig_file.write_text(tiny_rig().toml_text)
    assert _timelapse(rig_file, tmp_path / "reference") == 0
    reference = json.loads((tmp_path / "reference" / "series.json").read_text())
    n_exposures = 6 * 12  # exposures of one slot (both cameras at once): interrupt half-way through the second slot
    _interrupt_capture_once(monkeypatch, n_exposures + n_exposures // 2)
    assert _timelapse(rig_file, tmp_path / "s") == 130
    monkeypatch.undo()
    assert _timelapse(rig_file, tmp_path / "s") == 0
    capsys.readouterr()
    got = json.loads((tmp_path / "s" / "series.json").read_text())
    assert [e["status"] for e in got["slots"]] == [e["status"] for e in reference["slots"]]
    assert (got["n_complete"], got["n_skipped"]) == (reference["n_complete"], reference["n_skipped"])
    for mine, theirs in zip(got["slots"], reference["slots"], strict=True):
        if theirs["status"] != "complete":
            continue
        status, started, finished, duration_s = _slot_times(mine)
        r_status, r_started, r_finished, r_duration_s = _slot_times(theirs)
        assert status == r_status
        assert abs((started - r_started).total_seconds()) <= CLOCK_PRECISION_S, mine
        assert abs((finished - r_finished).total_seconds()) <= CLOCK_PRECISION_S, mine
        assert abs(duration_s - r_duration_s) <= CLOCK_PRECISION_S, mine
    # the frames of the interrupted slot are those of the uninterrupted one: the duration is their capture time
    for name in ("slot_1220",):
        frames = Session.open(tmp_path / "s" / name).completed()
        ref = Session.open(tmp_path / "reference" / name).completed()
        assert {k: v["timestamp"] for k, v in frames.items()} == {k: v["timestamp"] for k, v in ref.items()}



def test_slot_duration_is_the_capture_time_the_capture_states(tmp_path):
    """A resumed capture states the time of all its frames (``capture_s``): that, not this run's clock time, is
    the slot's duration; a capture that states nothing is timed on the clock."""
    from omnispectral.capture.timelapse import run_timelapse
    from omnispectral.sim.devices import FakeClock

    slots = [NOON, NOON.replace(minute=30)]
    clock = FakeClock(NOON)

    def capture(session_dir, t):
        clock.sleep(40.0)  # this run: the rest of an interrupted capture
        return {"complete": True, **({"capture_s": 100.0} if t == NOON else {})}

    index = run_timelapse(tmp_path / "series", slots, clock, capture)
    assert [e["duration_s"] for e in index["slots"]] == [100.0, 40.0]

# ------------------------------------------------------------------ a damaged ground truth
def _damage_json(gt: Path) -> Path:
    (gt / "ground_truth.json").write_text('{"format": "omnispectral-ground-truth", "bands": ')
    return gt / "ground_truth.json"


def _damage_bands(gt: Path) -> Path:
    p = gt / "bands.npy"
    p.write_bytes(p.read_bytes()[:200])  # cut: the header is whole, the pixels are not
    return p


def _damage_header(gt: Path) -> Path:
    p = gt / "spectral.npy"
    data = bytearray(p.read_bytes())
    data[:10] = b"garbage!!!"
    p.write_bytes(bytes(data))
    return p


DAMAGES = {"json": _damage_json, "bands-cut": _damage_bands, "spectral-header": _damage_header}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("truth")
    simulate_tiny(root / "s")
    return root / "s"


def _one_warning(err: str, file: Path) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "warning" in lines[0] and str(file) in lines[0] and "Traceback" not in err, err


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_damaged_ground_truth_is_one_warning_and_no_accuracy(tiny, tmp_path, damage, capsys, caplog):
    session = tmp_path / "s"
    shutil.copytree(tiny, session)
    bad = DAMAGES[damage](session / "ground_truth")
    with caplog.at_level("WARNING"):
        assert GroundTruth.of_session(session) is None
    _one_warning("\n".join(r.getMessage() for r in caplog.records), bad)
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(["-q", "process", str(session), "-o", str(tmp_path / "p"), "--json"]) == 0
    capsys.readouterr()
    _one_warning("\n".join(r.getMessage() for r in caplog.records), bad)
    report = json.loads((tmp_path / "p" / "report" / "report.json").read_text())
    assert report["accuracy"] is None and (tmp_path / "p" / "report" / "report.html").is_file()
    caplog.clear()
    with caplog.at_level("WARNING"):
        assert main(["-q", "report", str(tmp_path / "p"), "--json"]) == 0
    _one_warning("\n".join(r.getMessage() for r in caplog.records), bad)
    assert json.loads(capsys.readouterr().out)["accuracy"] is None


def test_intact_ground_truth_is_read(tiny):
    truth = GroundTruth.of_session(tiny)
    assert truth is not None and truth.bands().shape == tuple(truth.meta["bands"]["shape"])
    assert np.isfinite(truth.spectral()).all()


@pytest.mark.slow
def test_process_series_with_a_damaged_slot_truth_writes_every_product(series, tmp_path, caplog):
    damaged = tmp_path / "series"
    shutil.copytree(series, damaged)
    bad = _damage_bands(damaged / "slot_1300" / "ground_truth")
    with caplog.at_level("WARNING"):
        assert main(["-q", "process-series", str(damaged), "-o", str(tmp_path / "out"), "--json"]) == 0
    _one_warning("\n".join(r.getMessage() for r in caplog.records), bad)
    first = json.loads((tmp_path / "out" / "slot_1100" / "report" / "report.json").read_text())
    second = json.loads((tmp_path / "out" / "slot_1300" / "report" / "report.json").read_text())
    assert first["accuracy"] is not None and second["accuracy"] is None
