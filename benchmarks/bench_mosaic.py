"""Mosaic engine benchmarks (run by hand, one case at a time; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_mosaic.py CASE [--work DIR] [--json-out FILE]

Cases:

``quality``
    Noise-free simulated captures of a real HDR panorama (``venice_sunset_1k.hdr``, six bands via
    :func:`omnispectral.sim.synthetic.six_band_panorama`) through the time-lapse geometry (12 × 3
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
    ``--whole``: the whole 60000 × 30000 canvas from all 1260 directions × 2 cameras, with no holes
    expected and PSNR against the truth on 32 sampled windows of 512² (both poles among them; median
    and worst); ``--sensor-scale 2`` renders 1024 × 544 sensors with the same field of view (the inputs
    take a quarter of the disk).

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
from omnispectral.sim.synthetic import six_band_panorama, write_synthetic_merged

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


def gigapixel_cameras(scale: int = 1) -> dict[str, CameraModel]:
    """The gigapixel telephoto as the paper states it: 14.5° × 10.8° on 2048 × 1088 px (landscape, k1 = -0.02).

    Square pixels would give 14.5° × 7.7°, less than the 60 × 21 grid's 8.6° tilt step (gaps between
    rows); the stated angles need ``fy / fx = 0.71``, so the model takes them as they are.  ``scale``
    divides the sensor (``2``: 1024 × 544) with the same field of view, so the same directions cover the
    same canvas with fewer source pixels.
    """
    w, h = 2048 // scale, 1088 // scale
    fx = (w / 2) / np.tan(np.radians(14.5 / 2))
    fy = (h / 2) / np.tan(np.radians(10.8 / 2))
    dist = (-0.02, 0.0, 0.0, 0.0, 0.0)
    return {c: CameraModel(w, h, fx, fy, (w - 1) / 2, (h - 1) / 2, dist,
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


def run_one(merged: Path, out: Path, width: int, region=None, env: dict | None = None, processes: int = 0) -> dict:
    """One engine run in a fresh process under ``/usr/bin/time`` (its peak RSS: a child forked from this
    process would inherit this process's high-water mark in ``ru_maxrss``).  ``processes``: on a cluster of
    that many separate one-thread worker processes (:func:`omnispectral.mosaic.cluster.process_cluster`)
    instead of two local threads; the summary then also has the process tree's peak RSS (sampled)."""
    cmd = ["/usr/bin/time", "-f", "MAXRSS_KB %M", sys.executable, __file__, "_one", str(merged), str(out), str(width),
           json.dumps(region), str(processes)]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    kb = [line for line in r.stderr.splitlines() if line.startswith("MAXRSS_KB")][-1].split()[1]
    summary["peak_rss_mb"] = round(float(kb) / 1024.0, 1)
    return summary


class TreeRSS:
    """Peak of the summed RSS of this process and all its descendants, sampled every ``interval_s``."""

    def __init__(self, interval_s: float = 0.5):
        import threading

        self.interval_s, self.peak_mb, self._stop = interval_s, 0.0, threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _sample(self) -> float:
        import psutil

        me = psutil.Process()
        total = 0
        for p in [me, *me.children(recursive=True)]:
            try:
                total += p.memory_info().rss
            except psutil.Error:
                pass
        return total / 2**20

    def _run(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.peak_mb = max(self.peak_mb, self._sample())

    def __enter__(self) -> TreeRSS:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


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


def case_gigapixel(work: Path, whole: bool = False, sensor_scale: int = 1, processes: int = 0,
                   windows: int = 32) -> dict:
    """A 240 Mpx share of the gigapixel canvas, or (``whole``) the whole 60000 × 30000 canvas from all 1260
    directions × 2 cameras; ``sensor_scale`` divides the sensor (same field of view).  The whole run is
    checked against the truth on ``windows`` sampled windows of 512² (the two poles among them).  ``processes``:
    the mosaic on that many worker processes (:func:`run_one`) instead of two threads."""
    width, height = 60000, 30000
    cameras = gigapixel_cameras(sensor_scale)
    directions = grid(60, 21)
    region = None
    share = directions
    if not whole:
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
    name = "giga_whole" if whole else "giga"
    suffix = f"_s{sensor_scale}" if sensor_scale != 1 else ""
    t0 = time.perf_counter()
    merged = ensure_merged(work / f"{name}_merged{suffix}", truth, cameras, share, "float16")
    render_s = time.perf_counter() - t0
    merged_size = sum(p.stat().st_size for p in merged.path.glob("*.npy"))
    print(f"  inputs: {len(share)} directions x 2 of {cameras['A'].width} x {cameras['A'].height}, "
          f"{merged_size / 1e9:.2f} GB", flush=True)
    out = work / f"{name}{suffix}.zarr"
    load_before = os.getloadavg()
    summary = run_one(merged.path, out, width, region, processes=processes)
    load_after = os.getloadavg()
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    result = {"case": "gigapixel", "whole": whole, "sensor": [cameras["A"].width, cameras["A"].height],
              "n_directions": len(share), "processes": processes, "summary": summary, "store_bytes": size,
              "merged_bytes": merged_size,
              "render_s": round(render_s, 1), "load_before": [round(x, 2) for x in load_before],
              "load_after": [round(x, 2) for x in load_after]}
    if region is not None:
        result["window"] = [region[3] - region[2], region[1] - region[0]]
    if whole:
        result["windows"] = window_psnr(PanoramaStore.open(out), truth, windows)
    print(f"  mosaic {summary['seconds']['total']:.0f} s, {summary['megapixels_per_s']} Mpx/s (tiles), "
          f"peak RSS {summary['peak_rss_mb']} MB, store {size / 1e9:.2f} GB, holes {summary['holes_px']}", flush=True)
    return result


def window_psnr(store: PanoramaStore, truth: np.ndarray, n: int, size: int = 512, seed: int = 0) -> dict:
    """PSNR (:func:`psnr`, the window's own peak) of ``n`` windows of ``size``² of the level-0 panorama against
    the truth looked up along the same rays; the two polar windows plus ``n - 2`` at random (seeded)."""
    from omnispectral.mosaic.maps import Canvas
    from omnispectral.sim.synthetic import lookup, pad_over_poles

    h, w = store.shapes[0]
    canvas, padded = Canvas(w, h), pad_over_poles(np.asarray(truth, np.float32))
    rng = np.random.default_rng(seed)
    corners = [(0, int(rng.integers(0, w - size))), (h - size, int(rng.integers(0, w - size)))]
    corners += [(int(rng.integers(0, h - size)), int(rng.integers(0, w - size))) for _ in range(n - 2)]
    rows = []
    for r0, c0 in corners:
        est = store.read(0, slice(r0, r0 + size), slice(c0, c0 + size))
        ref = lookup(padded, canvas.rays(np.arange(r0, r0 + size), np.arange(c0, c0 + size)), truth.shape[1],
                     truth.shape[0])
        rows.append({"row0": r0, "col0": c0, "holes": int((~np.isfinite(est)).any(axis=-1).sum()), **psnr(est, ref)})
    worst = min(rows, key=lambda r: r["psnr_db"])
    return {"n": len(rows), "size": size, "psnr_db_median": float(np.median([r["psnr_db"] for r in rows])),
            "psnr_db_min": worst["psnr_db"], "worst": worst, "holes": sum(r["holes"] for r in rows), "rows": rows}


def _one(merged: str, out: str, width: str, region: str = "null", processes: str = "0") -> None:
    """A single engine run in this process (two threads, or a cluster of ``processes`` worker processes); prints
    its summary as JSON (used for peak RSS per run)."""
    region = json.loads(region)
    kw = {"region": tuple(region)} if region else {}
    if int(processes):
        import signal

        from omnispectral.mosaic.cluster import process_cluster

        signal.signal(signal.SIGTERM, lambda *_: sys.exit(1))  # a killed run still stops its cluster (finally)

        t0 = time.perf_counter()
        with process_cluster(int(processes), directory=Path(out).parent / "cluster") as address, TreeRSS() as tree:
            started = time.perf_counter() - t0
            summary = mosaic(merged, out, width=int(width), scheduler=address, overwrite=True, **kw)
        summary.update(cluster_start_s=round(started, 2), processes=int(processes),
                       tree_peak_rss_mb=round(tree.peak_mb, 1))
    else:
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
    ap.add_argument("--whole", action="store_true", help="gigapixel: the whole canvas from all 1260 directions")
    ap.add_argument("--sensor-scale", type=int, default=1, help="gigapixel: sensor divided by this (same FOV)")
    ap.add_argument("--processes", type=int, default=0,
                    help="gigapixel: mosaic on this many Dask worker processes (default: two local threads)")
    args = ap.parse_args()
    if shutil.which("nona") is None and args.case in ("quality", "speed", "all"):
        print("nona not found: its rows are skipped (make bench-deps installs Debian's hugin-tools)", flush=True)
    args.work.mkdir(parents=True, exist_ok=True)
    results = []
    for name in (CASES if args.case == "all" else [args.case]):
        print(f"{name}:", flush=True)
        kw = {"repeat": args.repeat, "baseline_src": args.baseline_src} if name == "versus" else {}
        if name == "gigapixel":
            kw = {"whole": args.whole, "sensor_scale": args.sensor_scale, "processes": args.processes}
        results.append(CASES[name](args.work, **kw))
    text = json.dumps(results, indent=2, default=str)
    if args.json_out:
        args.json_out.write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
