"""A time-lapse day (paper Sec. 5.3): every slot processed by ``process-series``; per-slot time and the total.

    .venv/bin/python benchmarks/bench_timelapse.py [--preset small | --rig FILE.toml] [--from 06:00] [--to 17:00]
                                                   [--every 5min] [--work DIR] [--json-out FILE]
                                                   [--follow [--drop-frames]]

By default the series is simulated first (``omnispectral timelapse``, not timed; resumable), then
:func:`omnispectral.product.series.process_series` processes every slot — camera B's mounting fitted on
the first slot and reused, the Wiener estimator fitted once per process (cached) — stacks the
panoramas and estimates the region spectra over the day.  Reported: the wall time of the whole
``process-series``, each slot's wall time (between successive slot callbacks) and its stage timings
from ``product.json``, and the load average before and after.

``--follow`` pipelines the two for a long day: the simulator runs as a child process while this
process calls ``process_series`` again whenever slots have completed (finished products are kept, so
each call processes only the new slots; the last call stacks the whole day).  Each processed slot's
wall and CPU time (this process, all its threads) are appended to ``WORK/slot_times.jsonl`` as it
finishes, so an interrupted run resumes with the times it had; ``--drop-frames`` deletes a slot's
frames and ground truth once its product exists (a ``small`` slot is ~260 MB of TIFF frames: 133 of
them would be 35 GB).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from omnispectral.cli import main as cli
from omnispectral.product.series import process_series


def _cpu_s() -> float:
    """CPU time (user + system) of this process, all its threads."""
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def timed_process_series(series: Path, out: Path, log: Path | None = None) -> tuple[dict, list[float], float]:
    """``process_series`` with the wall time of every slot it processed in this call (skipped slots excluded)."""
    done_before = {p.name for p in out.glob("slot_*") if (p / "product.json").exists()}
    marks: list[tuple[int, float, float]] = []
    t0, cpu0 = time.perf_counter(), _cpu_s()

    def progress(stage, done, total):
        if stage == "slots":
            marks.append((done, time.perf_counter(), _cpu_s()))

    summary = process_series(series, out, progress=progress)
    total_s = time.perf_counter() - t0
    # slots only ever become complete in time order: the index read now lists the ones processed first
    index = json.loads((series / "series.json").read_text())
    names = [e["session"] for e in index["slots"] if e["status"] == "complete"]
    slot_s, prev, prev_cpu = [], t0, cpu0
    for done, t, cpu in marks:
        name = names[done - 1]
        if name not in done_before:
            slot_s.append(t - prev)
            if log is not None:
                with log.open("a") as fh:
                    fh.write(json.dumps({"slot": name, "seconds": t - prev, "cpu_s": cpu - prev_cpu,
                                         "load": os.getloadavg()}) + "\n")
        prev, prev_cpu = t, cpu
    return summary, slot_s, total_s


def drop_frames(series: Path, out: Path) -> None:
    """Delete the frames and ground truth of slots whose product is finished (the product keeps what it needs)."""
    for session in series.glob("slot_*"):
        if (out / session.name / "product.json").exists():
            for sub in ("frames", "ground_truth"):
                shutil.rmtree(session / sub, ignore_errors=True)


def follow(a, rig_args: list[str], series: Path, out: Path) -> dict:
    """Simulate in a child process and process the completed slots as they come (module docstring)."""
    log = a.work / "slot_times.jsonl"
    cmd = [sys.executable, "-m", "omnispectral", "timelapse", *rig_args, "--from", a.start, "--to", a.end,
           "--every", a.every, "-o", str(series)]
    t0 = time.perf_counter()
    # --attach: a simulator started earlier (an interrupted --follow run) is still writing the series
    sim = None if a.attach else subprocess.Popen(cmd, stdout=subprocess.DEVNULL)
    load_before = os.getloadavg()
    summary, calls = None, 0
    while True:
        index = json.loads((series / "series.json").read_text()) if (series / "series.json").exists() else None
        finished = sim.poll() is not None if sim is not None else \
            bool(index) and all(e["status"] not in ("pending", "incomplete") for e in index["slots"])
        complete = [e["session"] for e in index["slots"] if e["status"] == "complete"] if index else []
        new = [n for n in complete if not (out / n / "product.json").exists()]
        if new or (finished and complete):
            summary, _, _ = timed_process_series(series, out, log)
            calls += 1
            if a.drop_frames:
                drop_frames(series, out)
        if finished and not [n for n in complete if not (out / n / "product.json").exists()]:
            break
        if not new:
            time.sleep(5.0)
    if sim is not None and sim.returncode != 0:
        raise SystemExit(f"simulating the series failed ({sim.returncode})")
    wall_s = time.perf_counter() - t0
    times = [json.loads(line) for line in log.read_text().splitlines()]
    slot_s = [t["seconds"] for t in times if "seconds" in t]  # (other lines mark restarts)
    slot_cpu = [t["cpu_s"] for t in times if "cpu_s" in t]
    sim_s = [e["duration_s"] for e in index["slots"] if e.get("duration_s") is not None]
    return {"rig": str(a.rig or a.preset or "small"), "mode": "follow", "slots": summary["n_slots"],
            "wall_s_this_run": wall_s, "process_series_calls": calls, "slots_s": sum(slot_s),
            "per_slot_s": {"median": statistics.median(slot_s), "min": min(slot_s), "max": max(slot_s),
                           "first": slot_s[0]},
            "per_slot_cpu_s": {"median": statistics.median(slot_cpu), "n": len(slot_cpu)} if slot_cpu else None,
            "simulated_capture_per_slot_s": {"median": statistics.median(sim_s), "total": sum(sim_s)},
            "stack_shape": summary["stack_shape"], "load_before": load_before, "load_after": os.getloadavg(),
            "per_slot_all_s": slot_s}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    rig = ap.add_mutually_exclusive_group()
    rig.add_argument("--preset", default=None)
    rig.add_argument("--rig", type=Path, default=None)
    ap.add_argument("--from", dest="start", default="06:00")
    ap.add_argument("--to", dest="end", default="17:00")
    ap.add_argument("--every", default="5min")
    ap.add_argument("--work", type=Path, default=Path("bench-timelapse"))
    ap.add_argument("--json-out", type=Path, default=None)
    ap.add_argument("--follow", action="store_true", help="process slots while the series is simulated")
    ap.add_argument("--drop-frames", action="store_true", help="with --follow: delete processed slots' frames")
    ap.add_argument("--attach", action="store_true",
                    help="with --follow: do not start the simulator (one already runs on WORK/series)")
    a = ap.parse_args(argv)
    a.work = a.work.absolute()
    a.work.mkdir(parents=True, exist_ok=True)
    series, out = a.work / "series", a.work / "products"
    rig_args = ["--rig", str(a.rig)] if a.rig else ["--preset", a.preset or "small"]
    if a.follow:
        result = follow(a, rig_args, series, out)
    else:
        t0 = time.perf_counter()
        code = cli(["timelapse", *rig_args, "--from", a.start, "--to", a.end, "--every", a.every, "-o", str(series)])
        if code not in (0, None):
            raise SystemExit(f"simulating the series failed ({code})")
        simulate_s = time.perf_counter() - t0
        load_before = os.getloadavg()
        summary, slot_s, total_s = timed_process_series(series, out)
        result = {"rig": str(a.rig or a.preset or "small"), "slots": summary["n_slots"], "simulate_s": simulate_s,
                  "process_series_s": total_s, "slots_s": sum(slot_s),
                  "stack_and_spectra_s": total_s - sum(slot_s),
                  "per_slot_s": {"median": statistics.median(slot_s), "min": min(slot_s), "max": max(slot_s),
                                 "first": slot_s[0]},
                  "load_before": load_before, "load_after": os.getloadavg(), "per_slot_all_s": slot_s}
    stages: dict[str, list[float]] = {}
    calibrations = set()
    for prod in sorted(out.glob("slot_*")):
        index = json.loads((prod / "product.json").read_text())
        for k, v in index["timings_s"].items():
            stages.setdefault(k, []).append(v)
        calibration = index["registration"].get("rig_calibration") or {}
        calibrations.add(json.dumps(calibration.get("camera_b_mounting"), sort_keys=True))
    result.update({"stage_medians_s": {k: statistics.median(v) for k, v in stages.items()},
                   "stage_first_slot_s": {k: v[0] for k, v in stages.items()},
                   "distinct_camera_b_mountings": len(calibrations)})
    print(json.dumps({k: v for k, v in result.items() if k != "per_slot_all_s"}, indent=1))
    if a.json_out:
        a.json_out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
