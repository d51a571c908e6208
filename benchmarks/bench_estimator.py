"""Wiener estimator throughput: the fast stacked kernels against the reference, alternating in one process.

    .venv/bin/python benchmarks/bench_estimator.py [--repeat 3] [--rows 1088] [--ref-rows 128] [--json-out FILE]
    .venv/bin/python benchmarks/bench_estimator.py --versus-matmul [--threads 1 2] [--repeat 5]

A CMV2000 frame of six bands (``--rows`` x 2048 x 6 float32 -> 61 wavelengths) of realistic values:
the prior's colour signals (nine lights x reflectances) through the six-band system, brightness
spanning 10^4, 1 % noise.  For each case the fast path (the public ``WienerEstimator`` methods)
and the reference (``_estimate_reference`` etc., one component at a time, NumPy/LAPACK with BLAS
held to one thread) run alternately, ``--repeat`` times each; reported: median seconds, Mpx/s, the
speed-up, and the largest difference relative to each pixel's peak.  The reference runs on the
first ``--ref-rows`` rows only (it is 10-40x slower); Mpx/s are per its own pixel count.  Fast
paths use ``omnispectral.threads.kernel_threads()`` threads (``OMNISPECTRAL_THREADS``); the load
average before and after is printed.

``--versus-matmul``: the default mixture estimate (9 components, float32 out) of the whole frame against
its peer, one plain ``(N, 6) @ (6, 61)`` float32 matmul of the same pixels into a reused output (what a
linear estimator costs), alternating in this process, for each ``--threads`` count on both sides (ours:
``OMNISPECTRAL_THREADS``; the matmul: BLAS threads), medians of ``--repeat``; ours twice, into a fresh
output (a plain call) and into a reused one (``estimate(..., out=)``, the matmul's footing).  Every timed call
starts after a pause of ``PAUSE_S`` (the BLAS workers' spinning, :func:`alternate`).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from omnispectral.spectral.prior import build_prior
from omnispectral.spectral.system import six_band_system
from omnispectral.spectral.wiener import WienerEstimator, apply_linear_map
from omnispectral.threads import kernel_threads


def realistic_frame(rows: int, cols: int = 2048, seed: int = 0) -> np.ndarray:
    """Six-band values of the prior's colour signals at brightness 0.01-100 with 1 % noise, float32."""
    system, prior = six_band_system(), build_prior()
    rng = np.random.default_rng(seed)
    n = rows * cols
    pick = rng.integers(0, len(prior.signals), n)
    bands = system.response(prior.signals)[pick] * np.exp(rng.uniform(np.log(0.01), np.log(100), n))[:, None]
    bands *= 1 + 0.01 * rng.standard_normal(bands.shape)
    return bands.astype(np.float32).reshape(rows, cols, 6)


def peak_relative_error(fast, ref) -> float:
    fast = np.asarray(fast, np.float64).reshape(-1, fast.shape[-1])
    ref = np.asarray(ref, np.float64).reshape(-1, ref.shape[-1])
    return float((np.abs(fast - ref).max(axis=1) / np.abs(ref).max(axis=1)).max())


PAUSE_S = 0.25  # before each timed call: OpenBLAS's idle workers spin 2^28 TSC cycles (~0.1 s) after a call


def alternate(fast, reference, repeat: int):
    """Median seconds of ``fast`` and ``reference`` run alternately ``repeat`` times (after one warm-up of each).

    Each timed call starts ``PAUSE_S`` after the previous one ended: OpenBLAS's worker threads busy-wait
    ``2**THREAD_TIMEOUT`` cycles (28 by default, ~0.1 s) for more work after a multi-threaded call, and would
    take a core from whatever runs next (measured in one process, medians of 7: ours on two threads 0.219 s right
    after a two-thread matmul, 0.163-0.170 s after nothing, a one-thread matmul, a pause, or the matmul then a pause).
    """
    out_fast, out_ref = fast(), reference()
    t_fast, t_ref = [], []
    for _ in range(repeat):
        time.sleep(PAUSE_S)
        t0 = time.perf_counter()
        out_fast = fast()
        t_fast.append(time.perf_counter() - t0)
        del out_fast
        time.sleep(PAUSE_S)
        t0 = time.perf_counter()
        out_ref = reference()
        t_ref.append(time.perf_counter() - t0)
    return float(np.median(t_fast)), float(np.median(t_ref)), fast(), out_ref


def versus_matmul(frame: np.ndarray, threads: list[int], repeat: int) -> list[dict]:
    """The mixture estimate against one plain float32 matmul of the same pixels, alternating, per thread count:
    ours into a fresh output (a plain call) and into a reused one (``out=``, as the matmul's)."""
    system, prior = six_band_system(), build_prior()
    mixture = WienerEstimator.fit(system, prior, 1e-5, mixture=True)
    flat = np.ascontiguousarray(frame.reshape(-1, 6))
    matrix = np.ascontiguousarray(mixture.linear_map(np.full(mixture.n_components, 1 / mixture.n_components))[0]
                                  .T.astype(np.float32))  # (6, 61): any linear estimator's cost
    product = np.empty((flat.shape[0], matrix.shape[1]), np.float32)
    spectra = np.empty((*frame.shape[:-1], matrix.shape[1]), np.float32)
    rows = []
    for t in threads:
        os.environ["OMNISPECTRAL_THREADS"] = str(t)

        def ours():
            return mixture.estimate(frame)

        def ours_reused():
            return mixture.estimate(frame, out=spectra)

        def matmul(t=t):
            with threadpool_limits(t, user_api="blas"):
                return np.matmul(flat, matrix, out=product)

        t_ours, t_peer, _, _ = alternate(ours, matmul, repeat)
        t_reused, t_peer2, _, _ = alternate(ours_reused, matmul, repeat)
        rows.append({"threads": t, "ours_s": t_ours, "ours_out_reused_s": t_reused, "matmul_s": t_peer,
                     "matmul_s_second": t_peer2, "ratio": t_ours / t_peer, "ratio_out_reused": t_reused / t_peer2,
                     "load": os.getloadavg()[0]})
        print(f"{t} thread(s): mixture estimate {t_ours:.3f} s (output reused: {t_reused:.3f} s), plain matmul "
              f"{t_peer:.3f} / {t_peer2:.3f} s: {t_ours / t_peer:.2f}x ({t_reused / t_peer2:.2f}x with the output "
              f"reused; load {os.getloadavg()[0]:.2f})", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rows", type=int, default=1088)
    ap.add_argument("--ref-rows", type=int, default=128)
    ap.add_argument("--json-out", default=None)
    ap.add_argument("--versus-matmul", action="store_true", help="the mixture estimate against a plain matmul")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, len(os.sched_getaffinity(0))])
    args = ap.parse_args()
    load_before = os.getloadavg()
    if args.versus_matmul:
        rows = versus_matmul(realistic_frame(args.rows), args.threads, args.repeat)
        print(f"medians of {args.repeat}; load {load_before[0]:.2f} -> {os.getloadavg()[0]:.2f}")
        if args.json_out:
            Path(args.json_out).write_text(json.dumps({"versus_matmul": rows}, indent=2))
        return
    system, prior = six_band_system(), build_prior()
    mixture = WienerEstimator.fit(system, prior, 1e-5, mixture=True)
    pooled = WienerEstimator.fit(system, prior, 1e-5)
    frame = realistic_frame(args.rows)
    sub = np.ascontiguousarray(frame[:args.ref_rows])
    noise = 1e-4 * np.abs(frame) + 1e-8
    sub_noise = np.ascontiguousarray(noise[:args.ref_rows])
    mpx, sub_mpx = frame.shape[0] * frame.shape[1] / 1e6, sub.shape[0] * sub.shape[1] / 1e6
    weights = mixture.component_posterior(sub[::8, ::8]).mean(axis=(0, 1))
    M, b = mixture.linear_map(weights)

    def ref(fn):
        def run():
            with threadpool_limits(1):
                return fn()
        return run

    cases = [
        ("mixture estimate (9 components)", lambda: mixture.estimate(frame),
         ref(lambda: mixture._estimate_reference(sub)), mpx),
        ("mixture posterior std", lambda: mixture.posterior_std(frame),
         ref(lambda: mixture._posterior_std_reference(sub)), mpx),
        ("mixture component posterior", lambda: mixture.component_posterior(frame),
         ref(lambda: mixture._component_posterior_reference(sub)), mpx),
        ("linear map, fixed weights (61x6)", lambda: apply_linear_map(frame, M, b),
         ref(lambda: (sub.reshape(-1, 6) @ M.T.astype(np.float32)).reshape(*sub.shape[:2], -1)), mpx),
        ("pooled estimate (one linear map)", lambda: pooled.estimate(frame),
         ref(lambda: pooled._estimate_reference(sub)), mpx),
        ("mixture estimate, per-pixel noise", lambda: mixture.estimate(sub, noise_variance=sub_noise),
         ref(lambda: mixture._estimate_reference(sub, noise_variance=sub_noise)), sub_mpx),
        ("mixture posterior std, per-pixel noise", lambda: mixture.posterior_std(sub, noise_variance=sub_noise),
         ref(lambda: mixture._posterior_std_reference(sub, noise_variance=sub_noise)), sub_mpx),
    ]
    rows = []
    for name, fast, reference, fast_mpx in cases:
        t_fast, t_ref, out_fast, out_ref = alternate(fast, reference, args.repeat)
        err = peak_relative_error(out_fast[:args.ref_rows], out_ref)
        rows.append({"case": name, "fast_s": t_fast, "fast_mpx_s": fast_mpx / t_fast, "fast_mpx": fast_mpx,
                     "reference_s": t_ref, "reference_mpx_s": sub_mpx / t_ref,
                     "speedup": (fast_mpx / t_fast) / (sub_mpx / t_ref), "max_peak_rel_diff": err})
        print(f"{name:42s} fast {t_fast:7.3f} s {fast_mpx / t_fast:6.2f} Mpx/s | reference {t_ref:7.3f} s "
              f"{sub_mpx / t_ref:6.2f} Mpx/s | x{rows[-1]['speedup']:5.1f} | max diff {err:.1e}", flush=True)
    load_after = os.getloadavg()
    print(f"frame {frame.shape[1]}x{frame.shape[0]}x6 float32 ({mpx:.2f} Mpx), reference on {sub_mpx:.2f} Mpx; "
          f"{kernel_threads()} kernel threads; medians of {args.repeat}; load {load_before[0]:.2f} -> "
          f"{load_after[0]:.2f}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps({"rows": rows, "threads": kernel_threads(),
                                                   "load": [load_before[0], load_after[0]]}, indent=2))


if __name__ == "__main__":
    main()
