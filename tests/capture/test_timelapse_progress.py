"""``timelapse`` reports progress from its start (before the first slot's capture), then per slot and per frame."""

from __future__ import annotations

import datetime as dt

import pytest

from omnispectral.capture.plan import format_duration, make_plan
from omnispectral.capture.timelapse import parse_hhmm, parse_interval_s, run_timelapse, slot_times
from omnispectral.rig import load_preset
from omnispectral.sim.devices import FakeClock

TZ = dt.UTC
DAY = dt.date(2026, 6, 21)


def _slots(start: str, end: str, every: str = "5min") -> list[dt.datetime]:
    return slot_times(parse_hhmm(start, DAY, TZ), parse_hhmm(end, DAY, TZ), parse_interval_s(every))


def test_run_timelapse_reports_slots_from_the_start(tmp_path):
    events = []
    clock = FakeClock(dt.datetime(2026, 6, 21, 5, 58, tzinfo=TZ))
    slots = _slots("06:00", "06:20")
    durations = iter([180.0, 700.0, 180.0])  # the 06:05 capture overruns 06:10 and 06:15

    def capture(session_dir, t):
        events.append(("capture", f"{t:%H%M}"))
        clock.sleep(next(durations))
        return {"complete": True}

    def progress(stage, done, total):
        events.append(("progress", stage, done, total))

    run_timelapse(tmp_path / "series", slots, clock, capture, progress=progress)
    # the first report comes before any slot is captured (and before waiting for the first slot's time)
    assert events[0] == ("progress", "slots", 0, 5)
    assert events == [("progress", "slots", 0, 5),
                      ("capture", "0600"), ("progress", "slots", 1, 5),
                      ("capture", "0605"), ("progress", "slots", 4, 5),  # 06:10 and 06:15 skipped
                      ("capture", "0620"), ("progress", "slots", 5, 5)]
    # a resumed series that is done says so at once
    again = []
    run_timelapse(tmp_path / "series", slots, clock, lambda *a: again.append("captured"),
                  progress=lambda *a: again.append(a))
    assert again == [("slots", 5, 5)]


def test_cli_timelapse_draws_slots_then_each_slots_frames(tmp_path, monkeypatch, capsys):
    """The command passes its progress bars to the loop (slots) and to each slot's capture (frames)."""
    from omnispectral.cli import main
    from omnispectral.cli import simulate as cli_simulate

    events = []

    class Bars:
        def __init__(self, *args, **kwargs):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return None

        def __call__(self, stage, done, total):
            events.append((stage, done, total))

    def fake_session(session_dir, rig, scene, *, progress=None, **kwargs):
        events.append(("simulate", session_dir.name))
        for k in range(3):
            progress("capture", k, 2)
        return {"complete": True, "simulated_s": 60.0}

    monkeypatch.setattr(cli_simulate, "ProgressBars", Bars)
    monkeypatch.setattr(cli_simulate, "simulate_session", fake_session)
    monkeypatch.setattr(cli_simulate, "build_scene", lambda *a, **k: None)
    assert main(["timelapse", "--preset", "small", "--every", "5min", "--from", "06:00", "--to", "06:05",
                 "-o", str(tmp_path / "series")]) == 0
    assert events == [("slots", 0, 2),
                      ("simulate", "slot_0600"), ("capture", 0, 2), ("capture", 1, 2), ("capture", 2, 2),
                      ("slots", 1, 2),
                      ("simulate", "slot_0605"), ("capture", 0, 2), ("capture", 1, 2), ("capture", 2, 2),
                      ("slots", 2, 2)]
    out = capsys.readouterr().out
    assert "slot_0605: complete" in out and "between slots" not in out  # the small preset's plan fits in 5 min
    # slots closer than a capture can take at dusk: said before the first slot
    events.clear()
    assert main(["timelapse", "--preset", "small", "--every", "1min", "--from", "06:00", "--to", "06:01",
                 "-o", str(tmp_path / "tight")]) == 0
    out = " ".join(capsys.readouterr().out.split())
    plan = make_plan(load_preset("small"))
    assert plan.estimated_max_s == pytest.approx(plan.estimated_s + 36 * plan.dark_extension["max_s_per_direction"])
    assert (f"A capture takes {format_duration(plan.estimated_s)}, {format_duration(plan.estimated_max_s)} with the "
            "dark extension in every direction: longer than the 1 min 00 s between slots") in out


def test_progress_bars_start_a_stage_again_for_the_next_slot():
    """A stage that reports fewer units than before (the next slot's frames) starts its bar and clock again."""
    from omnispectral.cli._common import ProgressBars

    with ProgressBars(enabled=False) as bars:
        ticks = iter(range(1000))
        bars.bar.get_time = lambda: float(next(ticks))  # a clock that always advances
        bars("capture", 0, 4)
        bars("capture", 4, 4)
        task = bars.bar.tasks[0]
        first_start = task.start_time
        bars("capture", 0, 6)
        task = bars.bar.tasks[0]
        assert len(bars.bar.tasks) == 1 and task.completed == 0 and task.total == 6
        assert task.start_time > first_start  # its elapsed time counts from the new start
        bars("capture", 2, 6)
        assert bars.bar.tasks[0].completed == 2
