"""Benchmarks of the spectral core (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_spectral.py [--skip-select]

1. Filter-pair selection over the 127 Kodak Wratten filters (8001 pairs), target: < 60 s on 2 cores.
2. Wiener estimation throughput on a full CMV2000 frame (2048 x 1088 x 6 float32 -> 61 bands):
   pooled (one matrix product), mixture (9 components), posterior std, per-pixel noise.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np

from omnispectral.spectral.prior import build_prior
from omnispectral.spectral.select import select_filters
from omnispectral.spectral.system import six_band_system
from omnispectral.spectral.wiener import WienerEstimator

WRATTEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "filter_transmittance" / \
    "wratten_visible_400-700nm_10nm_percent.csv"


def timed(fn, repeat=1):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--skip-select", action="store_true")
    args = ap.parse_args()
    rows = []
    system = six_band_system()
    prior = build_prior()
    rng = np.random.default_rng(0)
    frame = rng.uniform(0.01, 1.0, (1088, 2048, 6)).astype(np.float32)
    mpx = frame.shape[0] * frame.shape[1] / 1e6
    pooled = WienerEstimator.fit(system, prior, 1e-5)
    mixture = WienerEstimator.fit(system, prior, 1e-5, mixture=True)
    cases = [
        ("estimate, pooled (one 61x6 matrix)", lambda: pooled.estimate(frame)),
        ("estimate, mixture of 9", lambda: mixture.estimate(frame)),
        ("posterior_std, pooled", lambda: pooled.posterior_std(frame)),
        ("estimate, pooled, per-pixel noise variance", lambda: pooled.estimate(frame, noise_variance=frame * 1e-4)),
    ]
    for name, fn in cases:
        t, _ = timed(fn, repeat=2)
        rows.append((f"{name}, 2048x1088x6 -> 61", f"{t:.2f} s", f"{mpx / t:.1f} Mpx/s"))
    if not args.skip_select and WRATTEN.exists():
        for est in ("pooled", "mixture"):
            t, r = timed(lambda est=est: select_filters(WRATTEN, top=3, mixture=est == "mixture"))
            rows.append((f"select-filters, 127 Wratten filters, {r['n_pairs']} pairs, {est}", f"{t:.1f} s",
                         f"best {r['top'][0]['filter_a']}+{r['top'][0]['filter_b']} NRMSE {r['top'][0]['nrmse']:.4f}; "
                         f"34A+stand-in rank {r['reference']['rank']}"))
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("| benchmark | time | notes |\n|---|---|---|")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]} |")
    print(f"\npeak RSS of the benchmark process: {peak_mb:.0f} MB")


if __name__ == "__main__":
    main()
