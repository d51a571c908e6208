"""Registration benchmark (run by hand; numbers go to docs/benchmarks.md, section "Registration").

    .venv/bin/python benchmarks/bench_registration.py [--n 40] [--n-large 16] [--protocol hdr single] [--json out.json]

Random crops of the four shared HDR panoramas (../shared/data/hdr_envmaps/polyhaven_1k_hdr), each
moved by a random sub-pixel shift in [-4, 4] px: a region is mirror-extended (periodic and
continuous) and Fourier-shifted, and both crops are cut from its interior, so the shift is exact
and the crops are not circular shifts.  256 px crops are at the panorama's resolution; 1024 px
crops come from the panorama upsampled 3x in the same Fourier step (the 1k panoramas are only
512 px high).  Exposure: one exposure per pair with the reference's mean at 18 % of full well
(clipped suns included), CMOSIS CMV2000 noise (shot, 13 e- read noise, 12 bit).  This is the
"single" protocol.  The "hdr" protocol is the rig's: each image is the HDR merge
(``merge_exposures``, triangle weights) of the paper's 15-exposure bracket (252 ms to 0.015 ms,
factor 2 apart) simulated with CMV2000 noise, with one radiance scale per panorama and band (median
at 18 % of full well at the middle exposure), so only the sun saturates even the shortest
exposure; ours gets the merge's saturated mask (``reference_valid`` / ``moving_valid``), cv2 and
skimage have no such input.

Pairs: same band (channel mean in both), cross band through filter-like mixes (camera A
0.45 R + 0.15 G + 0.40 B, camera B 0.20 R + 0.60 G + 0.20 B, each with its own exposure) and
red vs blue (the extreme, with contrast reversal between sky and buildings).

Methods: ours (``phase_correlate`` defaults, and ``preprocess="gradient"``), ``cv2.phaseCorrelate``
with a Hann window, ``skimage.registration.phase_cross_correlation(upsample_factor=100)`` without and
with the same Hann window (``skimage_hann``).  Times: every method on the same pair in turn, 5 rounds,
the median per pair, then the median over pairs; the machine's load average is recorded.
Errors are Euclidean (px), over all crops and over the crops whose confidence (ours, defaults)
passes ``DEFAULT_MIN_CONFIDENCE`` -- the same subset for every method.  Also: confidence of pure
noise and flat sky (for the threshold) and block-wise disparity throughput.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np
import scipy.fft as sfft

from omnispectral.imaging.blockpoc import block_disparity
from omnispectral.imaging.hdr import merge_exposures
from omnispectral.imaging.imageio import read_image
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE, phase_correlate
from omnispectral.spectral.noise import CMV2000

PANORAMAS = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdr_envmaps" / "polyhaven_1k_hdr"
FILTER_A = np.array([0.45, 0.15, 0.40])
FILTER_B = np.array([0.20, 0.60, 0.20])
MARGIN_PX = 32
PAIRS = ("same", "filters", "red_blue")
EXPOSURES_S = 0.252 * 0.5 ** np.arange(15)  # 252 ms ... 0.015 ms (paper Sec. 4.2)


def shifted_pair(region: np.ndarray, size: int, upsample: int, shift_xy) -> tuple[np.ndarray, np.ndarray]:
    """Crops ``size`` px of the ``upsample``x trigonometric interpolant of ``region`` (2-D), at 0 and ``shift_xy``."""
    ext = np.concatenate([region, region[::-1]], axis=0)
    ext = np.concatenate([ext, ext[:, ::-1]], axis=1)
    n0, n1 = ext.shape
    spec = sfft.fft2(ext, workers=-1)
    big0, big1 = n0 * upsample, n1 * upsample
    ky = sfft.fftfreq(n0, 1.0 / n0)
    kx = sfft.fftfreq(n1, 1.0 / n1)
    keep_y = np.abs(ky) < n0 / 2
    keep_x = np.abs(kx) < n1 / 2
    iy = np.where(ky >= 0, ky, ky + big0).astype(int)[keep_y]
    ix = np.where(kx >= 0, kx, kx + big1).astype(int)[keep_x]
    spec = spec[np.ix_(keep_y, keep_x)]
    out = []
    for dx, dy in ((0.0, 0.0), shift_xy):
        ramp = np.exp(-2j * np.pi * (ky[keep_y][:, None] * dy / big0 + kx[keep_x][None, :] * dx / big1))
        full = np.zeros((big0, big1), np.complex128)
        full[np.ix_(iy, ix)] = spec * ramp
        img = sfft.ifft2(full, workers=-1).real * upsample**2
        out.append(img[MARGIN_PX:MARGIN_PX + size, MARGIN_PX:MARGIN_PX + size])
    return out[0], out[1]


def hdr_capture(radiance_dn_s: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The 15-exposure bracket of a radiance map (DN/s) with CMV2000 noise, merged: (radiance, valid)."""
    frames = [CMV2000.sample_dn(radiance_dn_s * t * CMV2000.gain_e_per_dn, rng).astype(np.uint16)
              for t in EXPOSURES_S]
    res = merge_exposures(frames, EXPOSURES_S)
    return res.radiance[:, :, 0], ~res.saturated[:, :, 0]


def make_cases(panos, size: int, n: int, rng: np.random.Generator, protocol: str = "single") -> list[dict]:
    upsample = 1 if size <= 256 else 3
    need = int(np.ceil((size + 2 * MARGIN_PX) / upsample))
    t_mid = EXPOSURES_S[len(EXPOSURES_S) // 2]
    cases = []
    for i in range(n):
        pano = panos[i % len(panos)]
        y0 = int(rng.integers(40, pano.shape[0] - need - 40))
        x0 = int(rng.integers(0, pano.shape[1] - need))
        shift = tuple(rng.uniform(-4.0, 4.0, 2))
        region = pano[y0:y0 + need, x0:x0 + need]
        case = {"shift": shift}
        for key, wa, wb in (("same", np.full(3, 1 / 3), np.full(3, 1 / 3)), ("filters", FILTER_A, FILTER_B),
                            ("red_blue", np.array([1.0, 0, 0]), np.array([0, 0, 1.0]))):
            if key == "same":
                a, b = shifted_pair(region @ wa, size, upsample, shift)
            else:
                a, _ = shifted_pair(region @ wa, size, upsample, (0.0, 0.0))
                _, b = shifted_pair(region @ wb, size, upsample, shift)
            if protocol == "single":
                sa = 0.18 * CMV2000.full_well_e / a.mean()
                sb = sa if key == "same" else 0.18 * CMV2000.full_well_e / b.mean()
                case[key] = (CMV2000.sample_dn(a * sa, rng).astype(np.float32),
                             CMV2000.sample_dn(b * sb, rng).astype(np.float32), None, None)
            else:
                ra, va = hdr_capture(a * (0.18 * CMV2000.max_dn / (np.median(pano @ wa) * t_mid)), rng)
                rb, vb = hdr_capture(b * (0.18 * CMV2000.max_dn / (np.median(pano @ wb) * t_mid)), rng)
                case[key] = (ra, rb, va, vb)
        cases.append(case)
    return cases


def method_ours(preprocess="sqrt", use_mask=True, **kwargs):
    def run(a, b, va=None, vb=None):
        if use_mask:
            kwargs.update(reference_valid=va, moving_valid=vb)
        r = phase_correlate(a, b, preprocess=preprocess, **kwargs)
        return r.dx, r.dy, r.confidence
    return run


def method_cv2():
    import cv2

    windows = {}

    def run(a, b, va=None, vb=None):
        win = windows.setdefault(a.shape, cv2.createHanningWindow(a.shape[::-1], cv2.CV_32F))
        (dx, dy), resp = cv2.phaseCorrelate(a, b, win)
        return dx, dy, resp
    return run


def method_skimage():
    from skimage.registration import phase_cross_correlation

    def run(a, b, va=None, vb=None):
        shift, _, _ = phase_cross_correlation(a, b, upsample_factor=100)
        return -shift[1], -shift[0], np.nan
    return run


def method_skimage_hann():
    """skimage given the same Hann window as cv2 and ours (its documented remedy for non-periodic images)."""
    from skimage.filters import window
    from skimage.registration import phase_cross_correlation

    windows = {}

    def run(a, b, va=None, vb=None):
        win = windows.setdefault(a.shape, window("hann", a.shape).astype(np.float32))
        shift, _, _ = phase_cross_correlation(a * win, b * win, upsample_factor=100)
        return -shift[1], -shift[0], np.nan
    return run


def evaluate(cases, key: str, methods: dict, repeat_time: int = 5) -> dict:
    """Errors of every method; times interleaved (method by method on the same pair), median of repeats."""
    results = {name: {"errors": [], "time_s": [], "confidence": []} for name in methods}
    for c in cases:
        times = {name: [] for name in methods}
        for _ in range(repeat_time):
            for name, fn in methods.items():
                t = time.perf_counter()
                dx, dy, q = fn(*c[key])
                times[name].append(time.perf_counter() - t)
                last = results[name]
                if len(times[name]) == 1:
                    last["errors"].append(float(np.hypot(dx - c["shift"][0], dy - c["shift"][1])))
                    last["confidence"].append(float(q))
        for name in methods:
            results[name]["time_s"].append(float(np.median(times[name])))
    return {name: {k: np.array(v) for k, v in r.items()} for name, r in results.items()}


def summarise(results: dict, accepted: np.ndarray) -> dict:
    out = {}
    for name, r in results.items():
        e, ea = r["errors"], r["errors"][accepted]
        out[name] = {"mean_all": float(e.mean()), "median_all": float(np.median(e)),
                     "p95_all": float(np.percentile(e, 95)), "frac_over_0.1_all": float((e > 0.1).mean()),
                     "mean_accepted": float(ea.mean()), "p95_accepted": float(np.percentile(ea, 95)),
                     "frac_over_0.1_accepted": float((ea > 0.1).mean()),
                     "gross_failures_all": int((e > 1.0).sum()), "median_time_ms": float(np.median(r["time_s"]) * 1e3)}
    return out


def noise_confidence(rng: np.random.Generator, panos) -> dict:
    """Peak heights on pure sensor noise and on flat sky (the fallback threshold's evidence)."""
    out = {}
    for size in (256, 1024):
        peaks = [phase_correlate(CMV2000.sample_dn(np.full((size, size), 1500.0), rng),
                                 CMV2000.sample_dn(np.full((size, size), 1500.0), rng)).confidence for _ in range(20)]
        out[f"noise_{size}"] = {"max": float(np.max(peaks)), "median": float(np.median(peaks))}
    sky = []
    for pano, (y0, x0) in zip(panos, ((10, 100), (10, 400), (10, 800), (15, 600)), strict=True):
        region = pano[y0:y0 + 96 + 2 * MARGIN_PX, x0:x0 + 96 + 2 * MARGIN_PX].mean(axis=2)
        a, b = shifted_pair(region, 96, 1, (1.3, -0.4))
        s = 0.18 * CMV2000.full_well_e / a.mean()
        sky.append(phase_correlate(CMV2000.sample_dn(a * s, rng), CMV2000.sample_dn(b * s, rng)).confidence)
    out["top_rows_96px"] = [float(x) for x in sky]
    blocks = block_disparity(CMV2000.sample_dn(np.full((512, 512), 1500.0), rng),
                             CMV2000.sample_dn(np.full((512, 512), 1500.0), rng), block=32, step=32)
    out["noise_blocks_32"] = {"max": float(blocks.confidence.max()), "p99": float(np.percentile(blocks.confidence, 99))}
    return out


def block_throughput(rng) -> dict:
    img = rng.random((1024, 1024)).astype(np.float32)
    out = {}
    for block, step in ((32, 16), (64, 32)):
        best = np.inf
        for _ in range(3):
            t = time.perf_counter()
            dm = block_disparity(img, img, block=block, step=step)
            best = min(best, time.perf_counter() - t)
        out[f"{block}/{step}"] = {"time_s": best, "n_blocks": int(dm.dx.size)}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=40, help="crops at 256 px (default 40)")
    ap.add_argument("--n-large", type=int, default=16, help="crops at 1024 px (default 16)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 1024])
    ap.add_argument("--protocol", nargs="+", default=["hdr", "single"], choices=["hdr", "single"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write all numbers to this file")
    ap.add_argument("--methods", nargs="+", default=None, help="only these methods (the first must be 'ours')")
    ap.add_argument("--pairs", nargs="+", default=list(PAIRS), choices=PAIRS)
    ap.add_argument("--threads", type=int, default=None,
                    help="threads on both sides: OpenCV's (cv2.setNumThreads), BLAS and OMNISPECTRAL_THREADS "
                         "(default: the libraries' own)")
    ap.add_argument("--no-extras", action="store_true", help="skip the confidence and block-disparity measurements")
    args = ap.parse_args()
    if args.threads:
        import cv2
        from threadpoolctl import threadpool_limits

        cv2.setNumThreads(args.threads)
        os.environ["OMNISPECTRAL_THREADS"] = str(args.threads)
        threadpool_limits(args.threads)
    panos = [read_image(p).astype(np.float64) for p in sorted(PANORAMAS.glob("*.hdr"))]
    methods = {"ours": method_ours(), "ours_nomask": method_ours(use_mask=False),
               "ours_gradient": method_ours("gradient"), "ours_norefine": method_ours(use_mask=False, refine=0),
               "cv2": method_cv2(), "skimage_up100": method_skimage(), "skimage_hann": method_skimage_hann()}
    if args.methods:
        methods = {k: v for k, v in methods.items() if k in args.methods}
    report = {"load_before": os.getloadavg(), "threads": args.threads,
              "n": args.n, "n_large": args.n_large, "min_confidence": DEFAULT_MIN_CONFIDENCE, "protocols": {}}
    for protocol in args.protocol:
        rng = np.random.default_rng(args.seed)
        report["protocols"][protocol] = {}
        for size in args.sizes:
            n = args.n if size <= 256 else args.n_large
            t = time.perf_counter()
            cases = make_cases(panos, size, n, rng, protocol)
            print(f"\n{protocol}, {size} px: {n} crops generated in {time.perf_counter() - t:.1f} s")
            report["protocols"][protocol][size] = {}
            for key in args.pairs:
                res = evaluate(cases, key, methods)
                accepted = res["ours"]["confidence"] >= DEFAULT_MIN_CONFIDENCE
                summary = summarise(res, accepted)
                report["protocols"][protocol][size][key] = {"accepted_fraction": float(accepted.mean()),
                                                            "methods": summary}
                print(f"  {key}: accepted by confidence >= {DEFAULT_MIN_CONFIDENCE}: {accepted.mean():.0%}")
                cols = f"{'mean':>7s} {'median':>7s} {'p95':>7s} {'>0.1':>5s}"
                print(f"    {'method':15s} {cols} | {'mean':>7s} {'>0.1':>5s} {'>1px':>5s} {'time ms':>8s}"
                      "   (all | accepted)")
                for name, s in summary.items():
                    print(f"    {name:15s} {s['mean_all']:7.4f} {s['median_all']:7.4f} {s['p95_all']:7.4f} "
                          f"{s['frac_over_0.1_all']:5.2f} | {s['mean_accepted']:7.4f} "
                          f"{s['frac_over_0.1_accepted']:5.2f} {s['gross_failures_all']:5d} {s['median_time_ms']:8.2f}")
    report["load_after"] = os.getloadavg()
    if args.no_extras:
        _write(args.json, report)
        return
    rng = np.random.default_rng(args.seed + 1)
    report["confidence_without_texture"] = noise_confidence(rng, panos)
    print("\nconfidence without texture:", json.dumps(report["confidence_without_texture"]))
    report["block_disparity_1024"] = block_throughput(rng)
    print("block_disparity 1024 px:", json.dumps(report["block_disparity_1024"]))
    _write(args.json, report)


def _write(path, report: dict) -> None:
    if path:
        from omnispectral.io import atomic_write_json

        atomic_write_json(path, report)


if __name__ == "__main__":
    main()
