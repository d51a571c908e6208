"""Full-scale simulated capture (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_simulate.py [--preset paper-timelapse] [--keep DIR]

Simulates the ``paper-timelapse`` rig (36 directions x 2 cameras x 15 exposures of 2048 x 1088,
CMV2000 noise) on the procedural scene at 12:00 into a temporary session and reports the wall time
(target: <= 10 min on 2 cores), the disk used and the peak memory.  The session is deleted unless
``--keep`` is given.
"""

from __future__ import annotations

import argparse
import datetime as dt
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

from omnispectral.rig import load_preset
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.simulate import simulate_session


def frame_progress(stage: str, done: int, total: int) -> None:
    """Progress on stderr every 100 frames."""
    if done % 100 == 0 or done == total:
        print(f"{time.strftime('%H:%M:%S')} {stage}: {done}/{total}", file=sys.stderr, flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="paper-timelapse")
    ap.add_argument("--keep", default=None, metavar="DIR")
    args = ap.parse_args()
    rig = load_preset(args.preset)
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="omnispectral-bench-"))
    try:
        t0 = time.perf_counter()
        out = simulate_session(work / "session", rig, ProceduralOutdoorScene(time_hhmm="12:00"),
                               start=dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC), progress=frame_progress)
        wall = time.perf_counter() - t0
        size = sum(p.stat().st_size for p in (work / "session").rglob("*") if p.is_file())
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        print(f"{args.preset}: {out['n_written']} frames + ground truth in {wall:.1f} s "
              f"({wall / max(out['n_written'], 1) * 1e3:.0f} ms per frame), session {size / 2**30:.2f} GiB, "
              f"peak RSS {rss:.2f} GiB; the capture would take {out['simulated_s']:.0f} s; of the wall time, "
              f"{out['calibration_views_s']:.1f} s rendered the calibration views ({out['calibration_views']})")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
