"""HDR merge throughput and accuracy against a warm OpenCV (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_hdr.py [--repeat 5] [--threads 1 2] [--colour-hdri] [--json-out FILE]

A bracket of the paper (15 exposures, 252 ms -> 0.015 ms) of one CMV2000 frame, 2048 x 1088 x 3,
12 bits in uint16, simulated from a real HDR panorama (scaled so the sky saturates the longest
exposures) with the CMV2000 noise model.  For each thread count, alternating in one process,
``--repeat`` rounds (medians reported):

* ours: ``merge_exposures`` (Eq. (1), triangle weight of Eq. (2); and the noise-optimal weight),
  ``workers`` = the thread count;
* OpenCV ``MergeDebevec`` with a linear response, warm: the same process, its output buffer
  reused (``dst=``), three warm-up calls first, ``cv2.setNumThreads`` = the thread count.  It merges
  8-bit frames only, so it gets the frames shifted to 8 bits (its result is judged against the same
  ground truth).  Its first call in the process (cold: allocations not yet reused) is reported too;
* plain NumPy float32 Eq. (1): one exposure at a time, whole-frame float32 temporaries (one thread);
* optionally colour-hdri ``image_stack_to_HDRI`` (float frames in 0..1, Debevec weighting), once.

Reported: median wall time, output megapixels per second, ratios to the warm OpenCV, the median/mean
relative error against the ground-truth radiance (after one global scale for the libraries with
other units), the largest difference between our fused merge and a float64 evaluation of Eq. (1),
and the load average before and after.
"""

from __future__ import annotations

import argparse
import json
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np

from omnispectral.imaging import merge_exposures, triangle_weight
from omnispectral.spectral.noise import CMV2000

PANORAMA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdr_envmaps" / "polyhaven_1k_hdr" / \
    "venice_sunset_1k.hdr"
TIMES_S = np.geomspace(252e-3, 0.015e-3, 15)
H, W = 1088, 2048


def ground_truth_radiance() -> np.ndarray:
    """A real HDR scene resized to the sensor (DN/s): peak at 2x full scale in the shortest exposure's..."""
    import cv2

    if PANORAMA.exists():
        pano = cv2.imread(str(PANORAMA), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32)
        img = cv2.resize(pano, (W, H), interpolation=cv2.INTER_CUBIC).clip(1e-4)
    else:  # no shared data: a log-uniform random scene of the same dynamic range
        img = np.exp(np.random.default_rng(0).uniform(np.log(1e-3), np.log(1e2), (H, W, 3))).astype(np.float32)
    # brightest pixel reaches 80 % of full scale at 0.05 ms: the bracket covers the scene
    return img * np.float32(0.8 * CMV2000.max_dn / (img.max() * 0.05e-3))


def simulate(truth: np.ndarray, rng) -> list[np.ndarray]:
    return [CMV2000.sample_dn(truth * t * CMV2000.gain_e_per_dn, rng).astype(np.uint16) for t in TIMES_S]


def eq1_reference(frames, times, bit_depth=12) -> np.ndarray:
    """Eq. (1) with the Eq. (2) weight in float64, one exposure at a time (the definition)."""
    num = np.zeros(frames[0].shape)
    den = np.zeros(frames[0].shape)
    sat = 0.99 * ((1 << bit_depth) - 1)
    for f, t in zip(frames, times, strict=True):
        z = f.astype(np.float64)
        w = triangle_weight(z, bit_depth).astype(np.float64) * ((z < sat) & (z > 0))
        num += w * z / t
        den += w
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def numpy_eq1_float32(frames, times, bit_depth=12) -> np.ndarray:
    """Eq. (1) with the Eq. (2) weight in plain NumPy float32, one exposure at a time (a peer)."""
    top = np.float32((1 << bit_depth) - 1)
    sat = np.float32(0.99 * top)
    num = np.zeros(frames[0].shape, np.float32)
    den = np.zeros(frames[0].shape, np.float32)
    for f, t in zip(frames, times, strict=True):
        z = f.astype(np.float32)
        w = np.minimum(z, top - z) * ((z < sat) & (z > 0))
        num += w * z * np.float32(1.0 / t)
        den += w
    with np.errstate(invalid="ignore", divide="ignore"):
        return num / den


def alternating_medians(methods: dict, repeat: int) -> dict[str, float]:
    """Median seconds of each method, the methods run in turn ``repeat`` times (round-robin)."""
    times = {name: [] for name in methods}
    for _ in range(repeat):
        for name, fn in methods.items():
            t0 = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t0)
    return {name: float(np.median(t)) for name, t in times.items()}


def rel_error(estimate, truth, mask, fit_scale=False):
    est = estimate[mask].astype(np.float64)
    tru = truth[mask].astype(np.float64)
    if fit_scale:
        est *= np.median(tru / np.maximum(est, 1e-30))
    rel = np.abs(est - tru) / tru
    return float(np.median(rel)), float(np.mean(rel))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--colour-hdri", action="store_true", help="also time colour-hdri once (~5 s)")
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args()
    import cv2

    load_before = os.getloadavg()
    rng = np.random.default_rng(0)
    truth = ground_truth_radiance()
    frames = simulate(truth, rng)
    mpx = H * W / 1e6
    f8 = [np.ascontiguousarray((f >> 4).astype(np.uint8)) for f in frames]
    t32 = TIMES_S.astype(np.float32)
    linear = np.repeat(np.linspace(0, 1, 256, dtype=np.float32)[:, None, None], 3, axis=2)
    linear[0] = linear[1]
    merge = cv2.createMergeDebevec()
    t0 = time.perf_counter()
    cv_out = merge.process(f8, t32, linear)  # the first call of the process: cold
    t_cv_cold = time.perf_counter() - t0

    # accuracy (once)
    tri = merge_exposures(frames, TIMES_S, 12, weight="triangle")
    noi = merge_exposures(frames, TIMES_S, 12, weight="noise")
    valid = tri.valid & (truth * TIMES_S[0] > 1)  # ground truth visible above 1 DN in the longest exposure
    errors = {"ours, triangle (Eq. 2)": rel_error(tri.radiance, truth, valid),
              "ours, noise-optimal": rel_error(noi.radiance, truth, valid),
              "OpenCV MergeDebevec (8-bit in)": rel_error(cv_out, truth, valid, fit_scale=True),
              "NumPy float32 Eq. (1)": rel_error(numpy_eq1_float32(frames, TIMES_S), truth, valid)}
    reference = eq1_reference(frames, TIMES_S)
    ok = np.isfinite(reference) & tri.valid
    eq1_diff = float(np.max(np.abs(tri.radiance[ok] - reference[ok]) / reference[ok]))
    tracemalloc.start()
    merge_exposures(frames, TIMES_S, 12)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    out_bytes = 2 * truth.nbytes + 2 * truth.size  # radiance + variance (float32) + two bool flags

    rows = []
    for threads in args.threads:
        cv2.setNumThreads(threads)
        for _ in range(3):  # warm-up: OpenCV's buffers allocated and reused from here on
            merge.process(f8, t32, linear, dst=cv_out)
        medians = alternating_medians({
            "ours, triangle (Eq. 2)": lambda t=threads: merge_exposures(frames, TIMES_S, 12, workers=t),
            "OpenCV MergeDebevec (8-bit in)": lambda: merge.process(f8, t32, linear, dst=cv_out),
            "ours, noise-optimal": lambda t=threads: merge_exposures(frames, TIMES_S, 12, weight="noise", workers=t),
            "NumPy float32 Eq. (1)": lambda: numpy_eq1_float32(frames, TIMES_S),
        }, args.repeat)
        t_cv = medians["OpenCV MergeDebevec (8-bit in)"]
        for name, t in medians.items():
            rows.append({"method": name, "threads": threads if "NumPy" not in name else 1, "time_s": t,
                         "mpx_s": mpx / t, "vs_warm_cv2": t_cv / t, "median_rel_err": errors[name][0],
                         "mean_rel_err": errors[name][1]})
    if args.colour_hdri:
        import warnings

        import colour_hdri

        stack = colour_hdri.ImageStack()
        for f, t in zip(frames, TIMES_S, strict=True):
            stack.append(colour_hdri.Image(data=f.astype(np.float64) / CMV2000.max_dn,
                                           metadata=colour_hdri.Metadata(f_number=1.0, exposure_time=float(t),
                                                                         iso=100.0)))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            col_out = colour_hdri.image_stack_to_HDRI(stack)
            t_col = time.perf_counter() - t0
        med, mean = rel_error(col_out, truth, valid, fit_scale=True)
        rows.append({"method": "colour-hdri image_stack_to_HDRI", "threads": 1, "time_s": t_col, "mpx_s": mpx / t_col,
                     "vs_warm_cv2": rows[1]["time_s"] / t_col, "median_rel_err": med, "mean_rel_err": mean})
    load_after = os.getloadavg()

    print(f"15 x {W}x{H}x3 uint16 (12 bit), bracket 252 ms -> 0.015 ms; errors on {valid.mean():.1%} of pixels; "
          f"medians of {args.repeat} alternating rounds; load {load_before[0]:.2f} -> {load_after[0]:.2f}")
    print(f"{'method':34s} {'thr':>3s} {'time s':>8s} {'Mpx/s':>7s} {'vs warm cv2':>11s} {'med rel':>8s} "
          f"{'mean rel':>9s}")
    for r in rows:
        print(f"{r['method']:34s} {r['threads']:3d} {r['time_s']:8.3f} {r['mpx_s']:7.2f} {r['vs_warm_cv2']:10.2f}x "
              f"{r['median_rel_err']:8.4f} {r['mean_rel_err']:9.4f}")
    print(f"OpenCV MergeDebevec cold (first call of the process): {t_cv_cold:.3f} s")
    print(f"fused merge vs float64 Eq. (1): max relative difference {eq1_diff:.2e}")
    print(f"peak memory allocated by the merge: {peak / 2**20:.0f} MiB (outputs {out_bytes / 2**20:.0f} MiB, "
          f"inputs {sum(f.nbytes for f in frames) / 2**20:.0f} MiB)")
    if args.json_out:
        data = {"rows": rows, "cv2_cold_s": t_cv_cold, "eq1_max_rel_diff": eq1_diff, "peak_alloc_mib": peak / 2**20,
                "load": [load_before[0], load_after[0]]}
        Path(args.json_out).write_text(json.dumps(data, indent=2))


if __name__ == "__main__":
    main()
