"""End-to-end processing of a full-scale time-lapse frame (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_simulate.py --keep /tmp/full        # makes /tmp/full/session (~6 min)
    .venv/bin/python benchmarks/bench_process.py /tmp/full/session [--out /tmp/full/product]

36 directions x 2 cameras x 15 exposures of 2048 x 1088 -> a 7260 x 3630 six-band panorama (the
paper's time-lapse frame).  Target: <= 60 s on 2 idle cores (a third of the paper's 180 s acquisition), with peak
memory <= 8 GiB.  Prints the per-stage timings and the peak RSS of the process.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import sys
import time
from pathlib import Path

from omnispectral.product.process import process
from omnispectral.sim.truth import GroundTruth

CPU_AT_STAGE_END: dict[str, float] = {}


def process_cpu_s() -> float:
    """User + system CPU seconds of this process so far (all its threads)."""
    t = os.times()
    return t.user + t.system


def stage_progress(stage: str, done: int, total: int) -> None:
    """Progress on stderr: one line per stage at its end, with the process's CPU seconds since the previous end
    (CPU / wall near 2 means both cores were busy)."""
    if done == total:
        cpu = process_cpu_s()
        spent = cpu - max(CPU_AT_STAGE_END.values(), default=0.0)
        CPU_AT_STAGE_END[stage] = cpu
        print(f"{time.strftime('%H:%M:%S')} {stage}: {total} done ({spent:.1f} CPU-s since the last stage)",
              file=sys.stderr, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("session")
    ap.add_argument("--out", default=None)
    ap.add_argument("--width", type=int, default=7260)
    ap.add_argument("--keep", action="store_true", help="keep the product")
    ap.add_argument("--report", action="store_true", help="also write the report (accuracy at full size)")
    ap.add_argument("--sun", default="auto", help="process --sun method (default auto: the attenuated bracket)")
    ap.add_argument("--rig-calibration", default=None, metavar="FILE.json",
                    help="camera B's mounting from this file (e.g. calibrate rig --chessboard) instead of fitted")
    args = ap.parse_args()
    out = Path(args.out) if args.out else Path(args.session).parent / "product-bench"
    if out.exists():
        shutil.rmtree(out)
    t0 = time.perf_counter()
    CPU_AT_STAGE_END["start"] = process_cpu_s()
    index = process(args.session, out, truth=GroundTruth.of_session(args.session),
                    width=args.width, report=args.report, progress=stage_progress,
                    rig_calibration=args.rig_calibration, sun=args.sun)
    wall = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(json.dumps({"wall_s": round(wall, 1), "peak_rss_gib": round(rss, 2),
                      "cpu_s": round(process_cpu_s() - CPU_AT_STAGE_END["start"], 1), "size": [index["width"],
                      index["height"]], "timings_s": {k: round(v, 1) for k, v in index["timings_s"].items()},
                      "sun": index.get("sun")},
                     indent=1))
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
