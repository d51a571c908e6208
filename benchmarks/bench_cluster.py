"""The mosaic on a multi-process Dask cluster: scaling with 1, 2, 4 worker processes (numbers for docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_cluster.py [--work DIR] [--width 3808] [--tile 256] [--workers 1 2 4]
                                                 [--repeat 3] [--json-out FILE]

A ``small`` session (simulated here unless ``--session`` is given) is processed once locally; its merged
directions are then stitched by :func:`omnispectral.mosaic.engine.mosaic` at ``--width`` (default 4× the
native 952 px, 16× the pixels, so the tiles dominate) on:

- the local threaded scheduler with 1 and 2 threads (what ``process`` does without ``--scheduler``);
- a cluster of separate ``dask scheduler`` / ``dask worker`` processes
  (:func:`omnispectral.mosaic.cluster.process_cluster`) with 1, 2 and 4 workers of one thread each.

All clusters are up for the whole run and the configurations alternate round-robin (one untimed warm-up
each: a fresh worker imports the package on its first task), medians of ``--repeat``; every output is
compared bit for bit with the first local one.  Load average noted before and after.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import signal
import statistics
import sys
import time
import warnings
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from omnispectral.mosaic.cluster import process_cluster
from omnispectral.mosaic.engine import mosaic
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.process import process
from omnispectral.rig import load_preset
from omnispectral.sim.simulate import simulate_session


def prepare(work: Path, session: Path | None) -> MergedDirections:
    """Merged directions (with camera B's parallax) of a processed ``small`` session."""
    if session is None:
        session = work / "session"
        if not (session / "session.json").is_file():
            from omnispectral.sim.scenes import ProceduralOutdoorScene

            simulate_session(session, load_preset("small"), ProceduralOutdoorScene(time_hhmm="12:00"),
                             start=dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC), progress=False)
    product = work / "product"
    if not (product / "product.json").is_file():
        process(session, product, progress=False, report=False)
    return MergedDirections.open(product / "merged")


def levels(path: Path) -> list[np.ndarray]:
    store = PanoramaStore.open(path)
    return [store.read(k) for k in range(len(store.shapes))] + ([store.read_quality()] if store.has_quality else [])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("bench-cluster"))
    ap.add_argument("--session", type=Path, default=None, help="a processed-size session (default: simulate small)")
    ap.add_argument("--width", type=int, default=3808)
    ap.add_argument("--tile", type=int, default=256)
    ap.add_argument("--interp", default="linear", help="as 'process' (default linear)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json-out", type=Path, default=None)
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")  # distributed's version-mismatch notes (optional packages)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # a killed run still stops its clusters (finally)
    a.work.mkdir(parents=True, exist_ok=True)
    merged = prepare(a.work, a.session)
    load_before = os.getloadavg()
    configs: dict[str, dict] = {f"local, {t} thread{'s' * (t > 1)}": {"scheduler": None, "workers": t} for t in (1, 2)}
    with ExitStack() as stack:
        for n in a.workers:
            t0 = time.perf_counter()
            address = stack.enter_context(process_cluster(n, 1, directory=a.work / f"cluster-{n}"))
            configs[f"cluster, {n} worker process{'es' * (n > 1)} × 1 thread"] = {
                "scheduler": address, "workers": None, "startup_s": time.perf_counter() - t0}
        times: dict[str, list[dict]] = {k: [] for k in configs}
        reference = None
        for rep in range(a.repeat + 1):  # repetition 0: warm-up
            for name, cfg in configs.items():
                out = a.work / f"out-{list(configs).index(name)}.zarr"
                t0 = time.perf_counter()
                summary = mosaic(merged, out, width=a.width, tile=a.tile, interp=a.interp,
                                 scheduler=cfg["scheduler"], workers=cfg["workers"], overwrite=True)
                wall = time.perf_counter() - t0
                data = levels(out)
                if reference is None:
                    reference = data
                identical = len(data) == len(reference) and all(np.array_equal(x, y, equal_nan=True)
                                                                for x, y in zip(data, reference, strict=True))
                row = {"wall_s": wall, **{f"{k}_s": v for k, v in summary["seconds"].items()}, "identical": identical}
                print(f"round {rep} {name}: {wall:.1f} s (tiles {summary['seconds']['tiles']:.1f} s) "
                      f"identical={identical} load={os.getloadavg()[0]:.2f}", flush=True)
                if rep > 0:
                    times[name].append(row)
                else:
                    cfg["warmup_s"] = wall
    load_after = os.getloadavg()
    base = statistics.median(r["wall_s"] for r in times["local, 1 thread"])
    table = {}
    for name, rows in times.items():
        med = statistics.median(r["wall_s"] for r in rows)
        table[name] = {"wall_s_median": med, "wall_s": [r["wall_s"] for r in rows],
                       "tiles_s_median": statistics.median(r["tiles_s"] for r in rows),
                       "speedup_vs_local_1": base / med, "identical": all(r["identical"] for r in rows),
                       **{k: v for k, v in configs[name].items() if k.endswith("_s")}}
    store = PanoramaStore.open(a.work / "out-0.zarr")
    result = {"width": a.width, "height": a.width // 2, "tile": a.tile, "interp": a.interp,
              "tiles": int(np.prod(store.n_chunks(0))), "levels": len(store.shapes), "repeat": a.repeat,
              "cores": len(os.sched_getaffinity(0)), "load_before": load_before, "load_after": load_after,
              "configs": table}
    print(json.dumps(result, indent=1))
    if a.json_out:
        a.json_out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
