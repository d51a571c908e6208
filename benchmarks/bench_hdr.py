"""HDR merge throughput and accuracy (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_hdr.py [--repeat 3] [--json-out FILE]

A bracket of the paper (15 exposures, 252 ms -> 0.015 ms) of one CMV2000 frame, 2048 x 1088 x 3,
12 bits in uint16, simulated from a real HDR panorama (scaled so the sky saturates the longest
exposures) with the CMV2000 noise model.  Compared in the same run:

* ours: ``merge_exposures`` (Eq. (1), triangle weight of Eq. (2); and the noise-optimal weight);
* OpenCV ``cv2.createMergeDebevec`` with a linear response: it merges 8-bit frames only, so it gets
  the frames shifted to 8 bits (its result is judged against the same ground truth);
* colour-hdri ``image_stack_to_HDRI`` (float frames in 0..1, Debevec weighting).

Reported: median wall time, output megapixels per second, the median/mean relative error against
the ground-truth radiance (after one global scale for the libraries with other units), and the
largest difference between our fused merge and a float64 reference evaluation of Eq. (1).
"""

from __future__ import annotations

import argparse
import json
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


def timed(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def rel_error(estimate, truth, mask, fit_scale=False):
    est = estimate[mask].astype(np.float64)
    tru = truth[mask].astype(np.float64)
    if fit_scale:
        est *= np.median(tru / np.maximum(est, 1e-30))
    rel = np.abs(est - tru) / tru
    return float(np.median(rel)), float(np.mean(rel))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args()
    import colour_hdri
    import cv2

    rng = np.random.default_rng(0)
    truth = ground_truth_radiance()
    frames = simulate(truth, rng)
    mpx = H * W / 1e6
    rows = []

    t_tri, tri = timed(lambda: merge_exposures(frames, TIMES_S, 12, weight="triangle"), args.repeat)
    valid = tri.valid & (truth * TIMES_S[0] > 1)  # ground truth visible above 1 DN in the longest exposure
    rows.append(("ours, triangle (Eq. 2)", t_tri, *rel_error(tri.radiance, truth, valid)))
    t_noi, noi = timed(lambda: merge_exposures(frames, TIMES_S, 12, weight="noise"), args.repeat)
    rows.append(("ours, noise-optimal", t_noi, *rel_error(noi.radiance, truth, valid)))
    tracemalloc.start()
    merge_exposures(frames, TIMES_S, 12)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    out_bytes = 2 * truth.nbytes + 2 * truth.size  # radiance + variance (float32) + two bool flags
    reference = eq1_reference(frames, TIMES_S)
    ok = np.isfinite(reference) & tri.valid
    eq1_diff = float(np.max(np.abs(tri.radiance[ok] - reference[ok]) / reference[ok]))

    f8 = [np.ascontiguousarray((f >> 4).astype(np.uint8)) for f in frames]
    t32 = TIMES_S.astype(np.float32)
    linear = np.repeat(np.linspace(0, 1, 256, dtype=np.float32)[:, None, None], 3, axis=2)
    linear[0] = linear[1]
    merge = cv2.createMergeDebevec()
    t_cv, cv_out = timed(lambda: merge.process(f8, t32, linear), args.repeat)
    rows.append(("OpenCV MergeDebevec (8-bit in)", t_cv, *rel_error(cv_out, truth, valid, fit_scale=True)))

    def colour_merge():
        stack = colour_hdri.ImageStack()
        for f, t in zip(frames, TIMES_S, strict=True):
            stack.append(colour_hdri.Image(data=f.astype(np.float64) / CMV2000.max_dn,
                                           metadata=colour_hdri.Metadata(f_number=1.0, exposure_time=float(t),
                                                                         iso=100.0)))
        return colour_hdri.image_stack_to_HDRI(stack)

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t_col, col_out = timed(colour_merge, max(1, args.repeat - 2))
    rows.append(("colour-hdri image_stack_to_HDRI", t_col, *rel_error(col_out, truth, valid, fit_scale=True)))

    print(f"15 x {W}x{H}x3 uint16 (12 bit), bracket 252 ms -> 0.015 ms; errors on {valid.mean():.1%} of pixels")
    print(f"{'method':34s} {'time s':>8s} {'Mpx/s':>8s} {'vs cv2':>7s} {'med rel':>8s} {'mean rel':>9s}")
    for name, t, med, mean in rows:
        print(f"{name:34s} {t:8.3f} {mpx / t:8.2f} {t_cv / t:6.2f}x {med:8.4f} {mean:9.4f}")
    print(f"fused merge vs float64 Eq. (1): max relative difference {eq1_diff:.2e}")
    print(f"peak memory allocated by the merge: {peak / 2**20:.0f} MiB (outputs {out_bytes / 2**20:.0f} MiB, "
          f"inputs {sum(f.nbytes for f in frames) / 2**20:.0f} MiB)")
    if args.json_out:
        data = {"rows": [dict(zip(("method", "time_s", "median_rel_err", "mean_rel_err"), r, strict=True))
                         for r in rows], "eq1_max_rel_diff": eq1_diff, "peak_alloc_mib": peak / 2**20,
                "speedup_vs_cv2_triangle": t_cv / t_tri}
        Path(args.json_out).write_text(json.dumps(data, indent=2))


if __name__ == "__main__":
    main()
