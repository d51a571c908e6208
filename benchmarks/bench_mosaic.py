"""Mosaic engine benchmarks (run by hand, one case at a time; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_mosaic.py CASE [--work DIR] [--json-out FILE]

Cases:

``quality``
    Noise-free simulated captures of a real HDR panorama (``venice_sunset_1k.hdr``, six bands via
    :func:`omnispectral.mosaic.synthetic.six_band_panorama`) through the time-lapse geometry (12 × 3
    directions, 95° × 61° portrait, camera B misaligned as in the rig presets) with a sensor whose
    native panorama width equals the panorama's (1024 px), so pixel-scale detail matters.  Stitched
    back by our engine (each interpolation) and by Hugin's ``nona`` (spline36 ``m i2``, and spline16
    / bilinear for reference; two 3-band runs), PSNR against the panorama.
``speed``
    Six bands, 7260 × 3630, 36 directions of 2048 × 1088 (the paper's time-lapse configuration),
    rendered from the panorama upsampled to 7260 px.  Wall time of our engine (default
    interpolation, 2 threads) against ``nona`` doing the same (two 3-band runs, spline36); PSNR of both.
``versus``
    The ``speed`` job with ours and ``nona`` alternating in fresh processes, ``--repeat`` rounds: medians of
    wall and CPU time (``getrusage`` of the children), load average before each run, PSNR;
    ``--baseline-src DIR`` adds our engine from another source tree (a previous commit) to the rounds.
``memory``
    Peak RSS of the engine at 7260 × 3630, 4× and 16× the pixel count (same 36 directions), each in
    a fresh process.
``gigapixel``
    The paper's gigapixel configuration (60 × 21 = 1260 directions, 14.5° × 10.8°, 2048 × 1088):
    a 60000 × 30000 canvas of which a window of ≥ 1/8 of 60000 × 32000 pixels is stitched from the
    directions that overlap it (merged float16 images, one exposure each); throughput and peak RSS.

``nona`` (Debian ``hugin-tools``; ``make bench-deps`` installs it) gets the same images as float
TIFF and the same poses: yaw/pitch/roll decomposed from our camera-to-world rotation
(``Rt1`` so float input is not clipped).  The comparison uses distortion-free lenses so both
programs see exactly the same geometry (Hugin's lens polynomial is not OpenCV's).
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

import numpy as np

from omnispectral.capture.plan import direction_grid
from omnispectral.imaging.geometry import HEAD_TO_WORLD_AT_ZERO, CameraModel, Mounting
from omnispectral.mosaic import PanoramaStore, mosaic
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.mosaic.synthetic import six_band_panorama, write_synthetic_merged

PANORAMA = Path(__file__).resolve().parents[2] / "shared" / "data" / "hdr_envmaps" / "polyhaven_1k_hdr" / \
    "venice_sunset_1k.hdr"
MISALIGNMENT_B_DEG = (0.15, -0.08, 0.05)  # the rig presets' camera B mounting error
OFFSET_B_PX = (0.37, -0.21)


# ------------------------------------------------------------------------------------------ inputs
def load_panorama(width: int) -> np.ndarray:
    """Six-band panorama at ``width`` × ``width / 2`` (the 1k panorama, resized with area/cubic)."""
    import cv2

    rgb = cv2.imread(str(PANORAMA), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float32)
    if rgb.shape[1] != width:
        interp = cv2.INTER_AREA if width < rgb.shape[1] else cv2.INTER_CUBIC
        rgb = np.maximum(cv2.resize(rgb, (width, width // 2), interpolation=interp), 0.0)
    return six_band_panorama(rgb)


def timelapse_cameras(width_px: int, height_px: int, hfov_deg: float = 95.0) -> dict[str, CameraModel]:
    """The time-lapse lens without distortion, portrait; camera B with the presets' misalignment."""
    return {"A": CameraModel.from_fov(width_px, height_px, hfov_deg, (), Mounting(roll_deg=90.0)),
            "B": CameraModel.from_fov(width_px, height_px, hfov_deg, (), Mounting(roll_deg=90.0,
                                                                                  misalignment_deg=MISALIGNMENT_B_DEG))}


def gigapixel_cameras() -> dict[str, CameraModel]:
    """The gigapixel telephoto as the paper states it: 14.5° × 10.8° on 2048 × 1088 px (landscape, k1 = -0.02).

    Square pixels would give 14.5° × 7.7°, less than the 60 × 21 grid's 8.6° tilt step (gaps between
    rows); the stated angles need ``fy / fx = 0.71``, so the model takes them as they are.
    """
    fx = 1024.0 / np.tan(np.radians(14.5 / 2))
    fy = 544.0 / np.tan(np.radians(10.8 / 2))
    dist = (-0.02, 0.0, 0.0, 0.0, 0.0)
    return {c: CameraModel(2048, 1088, fx, fy, 1023.5, 543.5, dist,
                           Mounting(misalignment_deg=MISALIGNMENT_B_DEG if c == "B" else (0.0, 0.0, 0.0)))
            for c in ("A", "B")}


def grid(n_pan: int, n_tilt: int) -> list[tuple[float, float]]:
    return [(d.pan_deg, d.tilt_deg) for d in direction_grid(n_pan, n_tilt)]


# ------------------------------------------------------------------------------------------ metrics
def psnr(estimate: np.ndarray, truth: np.ndarray) -> dict:
    """PSNR (peak = the truth's maximum), PSNR at the 99.9th percentile as peak, and log-domain PSNR."""
    ok = np.isfinite(estimate).all(axis=-1)
    e, t = estimate[ok].astype(np.float64), truth[ok].astype(np.float64)
    mse = float(np.mean((e - t) ** 2))
    p999 = float(np.percentile(t, 99.9))
    floor = 1e-3 * float(np.mean(t))
    log_mse = float(np.mean((np.log(np.maximum(e, 0) + floor) - np.log(t + floor)) ** 2))
    log_range = float(np.log(t.max() + floor) - np.log(floor))
    return {"psnr_db": 10 * np.log10(t.max() ** 2 / mse), "psnr_p999_db": 10 * np.log10(p999 ** 2 / mse),
            "log_psnr_db": 10 * np.log10(log_range ** 2 / log_mse), "covered": float(ok.mean()),
            "median_rel_err": float(np.median(np.abs(e - t) / (t + floor)))}


# ------------------------------------------------------------------------------------------ nona
def hugin_angles(model: CameraModel, pan_deg: float, tilt_deg: float) -> tuple[float, float, float]:
    """Hugin's yaw, pitch, roll of a camera: ``camera_to_world = R_Y(-y) R_X(-p) R_Z(r) diag(-1, -1, 1)``."""
    m = model.camera_to_world(pan_deg, tilt_deg) @ np.linalg.inv(HEAD_TO_WORLD_AT_ZERO)
    a = np.arctan2(m[0, 2], m[2, 2])
    b = np.arcsin(np.clip(-m[1, 2], -1.0, 1.0))
    c = np.arctan2(m[1, 0], m[1, 1])
    return -float(np.degrees(a)), -float(np.degrees(b)), float(np.degrees(c))


def write_nona_inputs(merged: MergedDirections, work: Path, width: int, interpolator: int = 2) -> list[Path]:
    """Float TIFFs of every source and one project per camera (``nona`` takes at most 4 channels)."""
    import tifffile

    work.mkdir(parents=True, exist_ok=True)
    projects = []
    for cam in ("A", "B"):
        lines = [f'p f2 w{width} h{width // 2} v360 E0 R0 n"TIFF c:NONE"', f"m i{interpolator}"]
        model = merged.cameras[cam]
        for s in merged.sources():
            if s.camera != cam:
                continue
            name = f"d{s.direction:04d}_{cam}.tif"
            if not (work / name).exists():
                tifffile.imwrite(work / name, s.read(), photometric="rgb")
            if s.offset_px != (0.0, 0.0):
                raise ValueError("nona inputs are written for zero registration offsets")
            y, p, r = hugin_angles(model, s.pan_deg, s.tilt_deg)
            lines.append(f"i w{model.width} h{model.height} f0 v{model.hfov_deg!r} Rt1 y{y!r} p{p!r} r{r!r} "
                         "a0 b0 c0 d0 e0 g0 t0 Eev0 Er1 Eb1 Ra0 Rb0 Rc0 Rd0 Re0 Va1 Vb0 Vc0 Vd0 Vx0 Vy0 Vm0 "
                         f'n"{name}"')
        project = work / f"{cam}_i{interpolator}.pto"
        project.write_text("\n".join(lines) + "\n")
        projects.append(project)
    return projects


def run_nona(projects: list[Path], out_prefix: Path) -> dict:
    """Run ``nona`` on each project (sequentially, as a user would); wall time and the largest peak RSS."""
    seconds, rss = 0.0, 0.0
    outputs = []
    for project in projects:
        out = out_prefix.with_name(f"{out_prefix.name}_{project.stem}")
        t0 = time.perf_counter()
        r = subprocess.run(["/usr/bin/time", "-f", "%M", "nona", "-m", "TIFF", "-o", str(out), str(project)],
                           capture_output=True, text=True, cwd=project.parent)
        seconds += time.perf_counter() - t0
        if r.returncode != 0:
            raise RuntimeError(f"nona failed: {r.stderr[-500:]}")
        rss = max(rss, float(r.stderr.strip().splitlines()[-1]) / 1024.0)
        outputs.append(out.with_suffix(".tif"))
    return {"seconds": seconds, "peak_rss_mb": rss, "outputs": outputs}


def read_nona_six_bands(outputs: list[Path]) -> np.ndarray:
    """Six bands from the two nona outputs (RGBA float TIFF; alpha 0 = not covered → NaN)."""
    import tifffile

    parts = []
    for path in outputs:
        img = tifffile.imread(path).astype(np.float32)
        rgb = img[..., :3].copy()
        if img.shape[-1] > 3:
            rgb[img[..., 3] <= 0] = np.nan
        parts.append(rgb)
        path.unlink()
    return np.concatenate(parts, axis=-1)


# ------------------------------------------------------------------------------------------ cases
def ensure_merged(path: Path, truth: np.ndarray, cameras, directions, dtype: str,
                  offset=(0.0, 0.0)) -> MergedDirections:
    if (path / "merged.json").exists():
        md = MergedDirections.open(path, require_complete=False)
        if md.meta.get("complete"):
            return md
    t0 = time.perf_counter()
    md = write_synthetic_merged(path, truth, cameras, directions, offset, dtype=dtype)
    print(f"  rendered {len(directions)} directions in {time.perf_counter() - t0:.1f} s", flush=True)
    return md


def case_quality(work: Path) -> dict:
    width = 1024
    truth = load_panorama(width)
    # sensor sized so that 2 pi f = 1024 px for the 95 deg x 61 deg lens (portrait)
    f = width / (2 * np.pi)
    w_px = 2 * round(f * np.tan(np.radians(47.5)))
    h_px = 2 * round(f * np.tan(np.radians(30.5)))
    merged = ensure_merged(work / "quality_merged", truth, timelapse_cameras(w_px, h_px), grid(12, 3), "float32")
    rows = {}
    for interp in ("linear", "cubic", "spline", "lanczos"):
        summary = mosaic(merged, work / "quality.zarr", width=width, interp=interp, workers=2, overwrite=True)
        est = PanoramaStore.open(work / "quality.zarr").read(0)
        rows[f"ours {interp}"] = {**psnr(est, truth), "seconds": summary["seconds"]["tiles"]}
        print(f"  ours {interp}: {rows[f'ours {interp}']}", flush=True)
    for i, name in ((2, "spline36"), (1, "spline16"), (5, "bilinear")) if shutil.which("nona") else ():
        nona = run_nona(write_nona_inputs(merged, work / "quality_nona", width, i), work / "quality_nona" / "out")
        est = read_nona_six_bands(nona["outputs"])
        rows[f"nona {name}"] = {**psnr(est, truth), "seconds": nona["seconds"]}
        print(f"  nona {name}: {rows[f'nona {name}']}", flush=True)
    return {"case": "quality", "width": width, "sensor": [w_px, h_px], "directions": 36, "results": rows}


def case_speed(work: Path, interps=("cubic", "spline")) -> dict:
    width = 7260
    truth = load_panorama(width)
    merged = ensure_merged(work / "speed_merged", truth, timelapse_cameras(2048, 1088), grid(12, 3), "float32")
    rows = {}
    for interp in interps:
        summary = mosaic(merged, work / "speed.zarr", width=width, interp=interp, workers=2, overwrite=True)
        est = PanoramaStore.open(work / "speed.zarr").read(0)
        rows[f"ours {interp}"] = {**psnr(est, truth), "seconds": summary["seconds"]["total"],
                                  "tile_seconds": summary["seconds"]["tiles"], "summary": summary}
        del est
        print(f"  ours {interp}: {rows[f'ours {interp}']['seconds']:.1f} s", flush=True)
    if shutil.which("nona"):
        nona = run_nona(write_nona_inputs(merged, work / "speed_nona", width, 2), work / "speed_nona" / "out")
        est = read_nona_six_bands(nona["outputs"])
        rows["nona spline36"] = {**psnr(est, truth), "seconds": nona["seconds"], "peak_rss_mb": nona["peak_rss_mb"]}
        print(f"  nona: {nona['seconds']:.1f} s", flush=True)
    return {"case": "speed", "width": width, "directions": 36, "results": rows}


def run_one(merged: Path, out: Path, width: int, region=None, env: dict | None = None) -> dict:
    """One engine run in a fresh process under ``/usr/bin/time`` (its peak RSS: a child forked from this
    process would inherit this process's high-water mark in ``ru_maxrss``)."""
    cmd = ["/usr/bin/time", "-f", "MAXRSS_KB %M", sys.executable, __file__, "_one", str(merged), str(out), str(width)]
    r = subprocess.run(cmd + ([json.dumps(region)] if region else []), capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    kb = [line for line in r.stderr.splitlines() if line.startswith("MAXRSS_KB")][-1].split()[1]
    summary["peak_rss_mb"] = round(float(kb) / 1024.0, 1)
    return summary


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def case_versus(work: Path, repeat: int = 3, baseline_src: Path | None = None) -> dict:
    """The ``speed`` job, ours and ``nona`` alternating in fresh processes: wall and CPU time (user + system of
    the children, ``getrusage``), medians of ``repeat`` rounds, the load average before each run; PSNR of each
    contender's first output.  ``baseline_src``: also run our engine from another source tree (a previous
    commit's ``src``) in the same rounds, and compare its panorama with ours."""
    width = 7260
    truth = load_panorama(width)
    merged = ensure_merged(work / "speed_merged", truth, timelapse_cameras(2048, 1088), grid(12, 3), "float32")
    projects = write_nona_inputs(merged, work / "speed_nona", width, 2) if shutil.which("nona") else []
    contenders = {"ours": None}
    if projects:
        contenders["nona spline36"] = "nona"
    if baseline_src is not None:
        contenders["ours, baseline"] = Path(baseline_src).absolute()
    runs: dict[str, list[dict]] = {name: [] for name in contenders}
    quality: dict[str, dict] = {}
    for rnd in range(repeat):
        for name, how in contenders.items():
            load = os.getloadavg()
            cpu0, t0 = _children_cpu_s(), time.perf_counter()
            if how == "nona":
                nona = run_nona(projects, work / "speed_nona" / "out")
                rss = nona["peak_rss_mb"]
            else:
                out = work / ("versus_baseline.zarr" if how else "versus.zarr")
                env = dict(os.environ, PYTHONPATH=str(how)) if how else None
                summary = run_one(merged.path, out, width, env=env)
                rss = summary["peak_rss_mb"]
            wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
            runs[name].append({"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "peak_rss_mb": rss,
                               "load_before": [round(x, 2) for x in load]})
            print(f"  round {rnd + 1} {name}: wall {wall:.1f} s, CPU {cpu:.1f} s, load {load[0]:.2f}", flush=True)
            if name not in quality:
                est = read_nona_six_bands(nona["outputs"]) if how == "nona" else PanoramaStore.open(out).read(0)
                quality[name] = psnr(est, truth)
                if how == "nona":
                    quality[name]["seconds"] = None
                del est
            elif how == "nona":
                for path in nona["outputs"]:
                    path.unlink()
    rows = {}
    for name, rs in runs.items():
        wall = statistics.median(r["wall_s"] for r in rs)
        cpu = statistics.median(r["cpu_s"] for r in rs)
        rows[name] = {"wall_median_s": wall, "cpu_median_s": cpu, "runs": rs, **quality[name]}
    if "nona spline36" in rows:
        for name in rows:
            rows[name]["nona_cpu_over_ours"] = rows["nona spline36"]["cpu_median_s"] / rows[name]["cpu_median_s"]
            rows[name]["nona_wall_over_ours"] = rows["nona spline36"]["wall_median_s"] / rows[name]["wall_median_s"]
    if baseline_src is not None:
        a, b = PanoramaStore.open(work / "versus.zarr"), PanoramaStore.open(work / "versus_baseline.zarr")
        x, y = a.read(0), b.read(0)
        fin = np.isfinite(x) & np.isfinite(y)
        diff = np.abs(x - y)[fin]
        rel = diff / np.maximum(np.abs(y[fin]), 1e-30)
        rows["ours vs baseline"] = {"same_coverage": bool(np.array_equal(np.isfinite(x), np.isfinite(y))),
                                    "max_abs_over_peak": float(diff.max() / np.abs(y[fin]).max()),
                                    "rel_p99_99": float(np.percentile(rel, 99.99)), "rel_median": float(np.median(rel))}
    return {"case": "versus", "width": width, "directions": 36, "repeat": repeat, "results": rows}


def case_memory(work: Path, scales=(1, 2, 4)) -> dict:
    if not (work / "speed_merged" / "merged.json").exists():
        ensure_merged(work / "speed_merged", load_panorama(7260), timelapse_cameras(2048, 1088), grid(12, 3),
                      "float32")
    rows = {}
    for s in scales:
        width = 7260 * s
        rows[f"{s * s}x"] = run_one(work / "speed_merged", work / "memory.zarr", width)
        print(f"  {s * s}x ({width} px): {rows[f'{s * s}x']['peak_rss_mb']} MB, "
              f"{rows[f'{s * s}x']['seconds']['total']} s", flush=True)
        shutil.rmtree(work / "memory.zarr", ignore_errors=True)
    return {"case": "memory", "results": rows}


def case_gigapixel(work: Path) -> dict:
    width, height = 60000, 30000
    cameras = gigapixel_cameras()
    directions = grid(60, 21)
    # window: >= 1/8 of 60000 x 32000 = 240 Mpx; 15000 x 16000 around the horizon facing lon 0
    win_w, win_h = 15000, 16000
    col0, row0 = width // 2 - win_w // 2, height // 2 - win_h // 2
    region = (row0, row0 + win_h, col0, col0 + win_w)
    lon0, lon1 = col0 * 360 / width - 180, (col0 + win_w) * 360 / width - 180
    lat1, lat0 = 90 - row0 * 180 / height, 90 - (row0 + win_h) * 180 / height
    share = [(p, t) for p, t in directions if lon0 - 9 <= p <= lon1 + 9 and lat0 - 7 <= t <= lat1 + 7]
    print(f"  window {win_w} x {win_h} px ({win_w * win_h / 1e6:.0f} Mpx, lon {lon0:.1f}..{lon1:.1f}, "
          f"lat {lat0:.1f}..{lat1:.1f}), {len(share)} of 1260 directions", flush=True)
    truth = load_panorama(1024)
    merged = ensure_merged(work / "giga_merged", truth, cameras, share, "float16")
    del truth
    summary = run_one(work / "giga_merged", work / "giga.zarr", width, region)
    size = sum(p.stat().st_size for p in (work / "giga.zarr").rglob("*") if p.is_file())
    merged_size = sum(p.stat().st_size for p in merged.path.glob("*.npy"))
    return {"case": "gigapixel", "window": [win_w, win_h], "n_directions": len(share), "summary": summary,
            "store_bytes": size, "merged_bytes": merged_size}


def _one(merged: str, out: str, width: str, region: str | None = None) -> None:
    """A single engine run in this process; prints its summary as JSON (used for peak RSS per run)."""
    kw = {"region": tuple(json.loads(region))} if region else {}
    summary = mosaic(merged, out, width=int(width), workers=2, overwrite=True, **kw)
    print(json.dumps(summary))


CASES = {"quality": case_quality, "speed": case_speed, "versus": case_versus, "memory": case_memory,
         "gigapixel": case_gigapixel}


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "_one":
        _one(*sys.argv[2:])
        return
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", nargs="?", default="all", choices=[*CASES, "all"])
    ap.add_argument("--work", type=Path, default=Path(os.environ.get("TMPDIR", "/tmp")) / "omnispectral-bench-mosaic")
    ap.add_argument("--json-out", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="versus: rounds (medians)")
    ap.add_argument("--baseline-src", type=Path, help="versus: also run the engine from this source tree")
    args = ap.parse_args()
    if shutil.which("nona") is None and args.case in ("quality", "speed", "all"):
        print("nona not found: its rows are skipped (make bench-deps installs Debian's hugin-tools)", flush=True)
    args.work.mkdir(parents=True, exist_ok=True)
    results = []
    for name in (CASES if args.case == "all" else [args.case]):
        print(f"{name}:", flush=True)
        kw = {"repeat": args.repeat, "baseline_src": args.baseline_src} if name == "versus" else {}
        results.append(CASES[name](args.work, **kw))
    text = json.dumps(results, indent=2, default=str)
    if args.json_out:
        args.json_out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
