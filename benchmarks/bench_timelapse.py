"""A time-lapse day (paper Sec. 5.3): every slot processed by ``process-series``; per-slot time and the total.

    .venv/bin/python benchmarks/bench_timelapse.py [--preset small | --rig FILE.toml] [--from 06:00] [--to 17:00]
                                                   [--every 5min] [--work DIR] [--json-out FILE]

The series is simulated first (``omnispectral timelapse``, not timed; resumable), then
:func:`omnispectral.product.series.process_series` processes every slot — camera B's mounting fitted on
the first slot and reused, the Wiener estimator fitted once per process (cached) — stacks the
panoramas and estimates the region spectra over the day.  Reported: the wall time of the whole
``process-series``, each slot's wall time (between successive slot callbacks) and its stage timings
from ``product.json``, and the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

from omnispectral.cli import main as cli
from omnispectral.product.series import process_series


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
    a = ap.parse_args(argv)
    a.work.mkdir(parents=True, exist_ok=True)
    series, out = a.work / "series", a.work / "products"
    rig_args = ["--rig", str(a.rig)] if a.rig else ["--preset", a.preset or "small"]
    t0 = time.perf_counter()
    code = cli(["timelapse", *rig_args, "--from", a.start, "--to", a.end, "--every", a.every, "-o", str(series)])
    if code not in (0, None):
        raise SystemExit(f"simulating the series failed ({code})")
    simulate_s = time.perf_counter() - t0
    load_before = os.getloadavg()
    marks: list[float] = []
    t0 = time.perf_counter()
    summary = process_series(series, out, progress=lambda stage, done, total: marks.append(time.perf_counter())
                             if stage == "slots" else None)
    total_s = time.perf_counter() - t0
    load_after = os.getloadavg()
    slot_s = [b - a_ for a_, b in zip([t0, *marks[:-1]], marks, strict=True)]
    stages: dict[str, list[float]] = {}
    calibrations = set()
    for prod in sorted(out.glob("slot_*")):
        index = json.loads((prod / "product.json").read_text())
        for k, v in index["timings_s"].items():
            stages.setdefault(k, []).append(v)
        calibration = index["registration"].get("rig_calibration") or {}
        calibrations.add(json.dumps(calibration.get("camera_b_mounting"), sort_keys=True))
    result = {"rig": str(a.rig or a.preset or "small"), "slots": summary["n_slots"], "simulate_s": simulate_s,
              "process_series_s": total_s, "slots_s": sum(slot_s),
              "stack_and_spectra_s": total_s - sum(slot_s),
              "per_slot_s": {"median": statistics.median(slot_s), "min": min(slot_s), "max": max(slot_s),
                             "first": slot_s[0]},
              "stage_medians_s": {k: statistics.median(v) for k, v in stages.items()},
              "stage_first_slot_s": {k: v[0] for k, v in stages.items()},
              "distinct_camera_b_mountings": len(calibrations), "stack_shape": summary["stack_shape"],
              "load_before": load_before, "load_after": load_after, "per_slot_all_s": slot_s}
    print(json.dumps({k: v for k, v in result.items() if k != "per_slot_all_s"}, indent=1))
    if a.json_out:
        a.json_out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
