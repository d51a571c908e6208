"""Registration of camera B across conditions: times of day × seeds × chart distances, plus HDR panoramas.

Every run simulates a session of the ``small`` preset (camera B mounted with an unknown error of up
to 0.5° per axis drawn from the seed; the scene's materials and skyline drawn from the seed too),
then processes it with ``--registration parallax`` (rig calibration + per-pixel parallax, the
default) and ``--registration paper`` (one POC offset per direction).  Per run it records the
ColorChecker ΔE*ab (mean, max) and NRMSE, the six-band PSNR of both, the rig calibration's largest
error at infinity over the sensor (against the simulator's true mounting, which processing never
reads) and the chart's parallax error (median over chart pixels of |w_est − w_true| in px).

At 1.5 and 5 m the chart's patches are scaled with the distance (0.03 and 0.10 m) so that they keep
the angular size of the default 50 mm patches at 2.5 m: the matrix varies the parallax, not the
number of pixels per patch (a 50 mm patch at 5 m is 1.4 px wide on the 256-px sensor); at 5 m the chart
stands at latitude -10° instead of -15° so that it stays above the ground.

    python benchmarks/bench_registration_matrix.py --out /tmp/regmatrix            # the whole matrix
    python benchmarks/bench_registration_matrix.py --times 09:30 --seeds 5 --distances 2.5
    python benchmarks/bench_registration_matrix.py --calibration session chessboard --out /tmp/regmatrix
        # each session processed with B's mounting fitted on it and from chessboard pairs of its seed

Results: one JSON line per run and calibration in OUT/results.jsonl (resumable: finished runs are
skipped) and a Markdown table per calibration on stdout (also OUT/table-CAL.md).  Load average is
recorded per run.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.product.pairgeometry import predict_b_px
from omnispectral.product.process import process
from omnispectral.product.rigboard import calibrate_chessboard_folder
from omnispectral.product.rigfile import RigCalibration
from omnispectral.rig import load_preset
from omnispectral.sim.scenes import PanoramaScene, ProceduralOutdoorScene
from omnispectral.sim.simulate import simulate_board_views, simulate_session
from omnispectral.sim.truth import GroundTruth

TIMES = ("06:30", "08:00", "09:30", "11:00", "12:30", "14:00", "15:30", "17:00", "18:00")
SEEDS = (0, 1, 5)
DISTANCES_M = (1.5, 2.5, 5.0)
PANORAMAS = ("venice_sunset_1k.hdr", "royal_esplanade_1k.hdr")
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdr_envmaps" / "polyhaven_1k_hdr"


def infinity_error_px(product: Path, truth: dict) -> float:
    """Largest distance over A's sensor between B's predicted and true positions of points at infinity."""
    merged = MergedDirections.open(product / "merged")
    model_a = merged.cameras["A"]
    true_b = CameraModel.from_dict(truth["camera_b_true"]["model"])
    cal = RigCalibration.load(product / "rig-calibration.json")
    nominal = CameraModel.from_dict(merged.meta["rig_file_camera_b"])
    v, u = np.mgrid[0:model_a.height:2, 0:model_a.width:2]
    px = np.stack([u.ravel(), v.ravel()], axis=-1).astype(np.float64)
    err = np.linalg.norm(predict_b_px(model_a, cal.apply(nominal), px, 0.0) - predict_b_px(model_a, true_b, px, 0.0),
                         axis=1)
    return float(np.nanmax(err))


def chart_errors_px(product: Path, scene, truth: dict) -> dict | None:
    """On the chart's pixels, in every direction that sees the chart, medians over pixels of:

    - ``chart_parallax_error_px``: |w_est − w_true| · |e| (the parallax in px along the epipolar line; a
      yaw error of the rig model shows up here too, as a depth offset);
    - ``chart_registration_error_px``: the distance between where processing takes B's value for an A
      pixel (the calibrated model at the estimated inverse depth) and where B really saw that content
      (the true mounting at the true depth): the error that reaches the spectra.
    """
    from omnispectral.product.pairgeometry import cached_epipolar_field

    merged = MergedDirections.open(product / "merged")
    ma, mb = merged.cameras["A"], merged.cameras["B"]
    true_b = CameraModel.from_dict(truth["camera_b_true"]["model"])
    cal_b = RigCalibration.load(product / "rig-calibration.json").apply(
        CameraModel.from_dict(merged.meta["rig_file_camera_b"]))
    field = np.linalg.norm(cached_epipolar_field(ma, mb)[..., :2], axis=-1)
    v, u = np.mgrid[0:ma.height, 0:ma.width]
    px = np.stack([u, v], axis=-1).astype(np.float64)
    par_errs, reg_errs = [], []
    for d in merged.directions:
        par = d["images"]["B"].get("parallax")
        if not par:
            return None
        rays, _ = ma.pixel_to_world(px, d["pan_deg"], d["tilt_deg"])
        rec = scene.shade(np.nan_to_num(rays).reshape(-1, 3).astype(np.float32), np.zeros(3))
        chart = (rec.obj == scene._chart_id).reshape(ma.height, ma.width)
        if chart.sum() < 20:
            continue
        w_true = 1.0 / rec.t_m.reshape(ma.height, ma.width)[chart]
        w_est = np.load(product / "merged" / par["file"])[..., 0].astype(np.float32)[chart]
        par_errs.append(np.abs(w_est - w_true) * field[chart])
        q_est = predict_b_px(ma, cal_b, px[chart], w_est)
        q_true = predict_b_px(ma, true_b, px[chart], w_true)
        reg_errs.append(np.linalg.norm(q_est - q_true, axis=-1))
    if not par_errs:
        return None
    return {"chart_parallax_error_px": float(np.median(np.concatenate(par_errs))),
            "chart_registration_error_px": float(np.median(np.concatenate(reg_errs))),
            "chart_registration_error_p90_px": float(np.percentile(np.concatenate(reg_errs), 90))}


def accuracy(product: Path) -> dict:
    report = json.loads((product / "report" / "report.json").read_text())
    acc = report["accuracy"]
    cc = acc.get("colorchecker") or {}
    edges = ((acc.get("pixel_errors") or {}).get("depth_edges") or {})
    ratio = edges.get("ratio") or {}
    return {"psnr_db": acc["six_band_psnr_db"], "spectral_nrmse": acc["spectral_nrmse"],
            "cc_de_mean": cc.get("delta_e_ab"), "cc_de_max": cc.get("delta_e_ab_max"), "cc_nrmse": cc.get("nrmse"),
            "holes": (report.get("holes") or {}).get("n_pixels"),
            # what the user is told: "the rig calibration does not fit" and the like (false alarms show here)
            "registration_warnings": len(report.get("registration_warnings") or []),
            "edge_band_nrmse": (edges.get("edge") or {}).get("band_nrmse"),
            "edge_to_smooth_band_nrmse": ratio.get("band_nrmse"), "edge_to_smooth_delta_e": ratio.get("delta_e_ab")}


def truth_bands_delta_e(product: Path) -> dict | None:
    """ColorChecker ΔE*ab from the ground truth's own six bands on the product's panorama grid (the truth
    resampled as the report resamples it, patches read as the report reads them, the product's estimator):
    what a perfect registration would score at this panorama resolution.  A run whose chart patches are a
    few pixels wide can miss the bounds here already (the patch's central pixel mixes its neighbours and
    the gaps between them): such a run's failure is the evaluation's, not the registration's."""
    from omnispectral.product.layout import open_product
    from omnispectral.product.report import _resize_to, chart_scores, patch_bands
    from omnispectral.spectral.metrics import colour_differences

    index, store, estimator = open_product(product)
    gt = Path(index["session"]) / "ground_truth"
    patches = json.loads((gt / "ground_truth.json").read_text()).get("colorchecker_patches") or []
    if not patches:
        return None
    h, w = store.shapes[0]
    truth = _resize_to(np.load(gt / "bands.npy"), h, w)
    bands = np.array([patch_bands(truth, p["lon_deg"], p["lat_deg"], 0.5 * p["half_size_deg"]) for p in patches])
    de = colour_differences(estimator.estimate(bands), np.load(gt / "colorchecker_radiance.npy"),
                            np.load(gt / "colorchecker_white.npy"), np.asarray(estimator.wavelength_nm))["delta_e_ab"]
    # scored as the report scores them (patches crossed by a shadow edge left out)
    scores = chart_scores(patches, np.zeros(len(patches)), de, np.isfinite(de))
    worst = max((p for p in scores["per_patch"] if p["scored"]), key=lambda p: p["delta_e_ab"])
    return {"truth_bands_de_mean": scores["delta_e_ab"], "truth_bands_de_max": scores["delta_e_ab_max"],
            "truth_bands_de_max_patch": worst["name"]}


def chessboard_calibration(out: Path, seed: int) -> Path:
    """Camera B's mounting for ``seed`` from 12 simulated chessboard pairs (the rig of that seed), made once."""
    folder = out / "chessboards" / f"seed_{seed}"
    cal = folder / "rig-calibration.json"
    if not cal.is_file():
        simulate_board_views(folder, load_preset("small"), seed=seed)
        calibrate_chessboard_folder(folder, cal)
    return cal


def run_one(work: Path, key: dict, paper: dict | None = None,
            calibrations: dict[str, Path | None] | None = None) -> list[dict]:
    """Simulate one session and process it with the paper's registration once and with the parallax
    registration once per calibration (``calibrations``: name → camera B's mounting file, or ``None`` for
    the mounting fitted on the session (``"session"``) or from the chessboard views the simulation recorded
    with the session (``"views"``, the default path); default ``{"session": None}``); ``paper``: that method's result of
    an earlier run on the same frames, reused instead of processing again.  One row per calibration."""
    calibrations = calibrations or {"session": None}
    rig = load_preset("small")
    h, m = (int(x) for x in key["time"].split(":"))
    start = dt.datetime(2026, 3, 21, h, m, tzinfo=dt.UTC)
    if key["scene"] == "procedural":
        d = key["distance_m"]
        scene = ProceduralOutdoorScene(key["time"], seed=key["seed"], chart_distance_m=d, chart_patch_m=0.05 * d / 2.5,
                                       chart_lat_deg=-15.0 if d <= 2.5 else -10.0)
    else:
        scene = PanoramaScene(SHARED / key["scene"])
    session = work / "session"
    shutil.rmtree(work, ignore_errors=True)
    t0 = time.perf_counter()
    simulate_session(session, rig, scene, start=start, seed=key["seed"], progress=False)
    truth = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    common = {**key, "simulate_s": time.perf_counter() - t0, "load": os.getloadavg()[0]}
    if paper is not None:
        common["paper"] = {**paper, "reused": True}
    else:
        t1 = time.perf_counter()
        process(session, work / "paper", truth=GroundTruth.of_session(session), progress=False, registration="paper")
        common["paper"] = {**accuracy(work / "paper"), "process_s": time.perf_counter() - t1}
    rows = []
    for name, cal in calibrations.items():
        out = work / f"parallax-{name}"
        t1 = time.perf_counter()
        process(session, out, truth=GroundTruth.of_session(session),
                progress=False, registration="parallax", rig_calibration=cal,
                calibration_views=name == "views")
        row = {**common, "rig_calibration": name,
               "parallax": {**accuracy(out), "process_s": time.perf_counter() - t1,
                            "infinity_error_px": infinity_error_px(out, truth)}}
        if key["scene"] == "procedural":
            row["parallax"].update(chart_errors_px(out, scene, truth) or {})
            row["truth_bands"] = truth_bands_delta_e(out)
        rows.append(row)
    shutil.rmtree(work, ignore_errors=True)
    return rows


def fmt(x, spec=".2f") -> str:
    return "—" if x is None else format(x, spec)


def table(rows: list[dict]) -> str:
    lines = ["| scene | time | seed | chart m | ΔE mean / max (parallax) | ΔE mean / max (paper) | NRMSE par / paper | "
             "PSNR dB par / paper | ∞ error px | chart parallax err px | chart B position err px (p90) | "
             "holes par / paper | edge/smooth band NRMSE par / paper | registration warnings |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, q = r["parallax"], r["paper"]
        scene = r["scene"].split("_1k")[0]
        lines.append(f"| {scene} | {r['time']} | {r['seed']} | {fmt(r.get('distance_m'), '.1f')} | "
                     f"{fmt(p['cc_de_mean'])} / {fmt(p['cc_de_max'])} | "
                     f"{fmt(q['cc_de_mean'])} / {fmt(q['cc_de_max'])} | "
                     f"{fmt(p['cc_nrmse'], '.4f')} / {fmt(q['cc_nrmse'], '.4f')} | {fmt(p['psnr_db'], '.1f')} / "
                     f"{fmt(q['psnr_db'], '.1f')} | {fmt(p['infinity_error_px'], '.3f')} | "
                     f"{fmt(p.get('chart_parallax_error_px'), '.3f')} | "
                     f"{fmt(p.get('chart_registration_error_px'), '.3f')} "
                     f"({fmt(p.get('chart_registration_error_p90_px'), '.3f')}) | "
                     f"{fmt(p.get('holes'), 'd')} / {fmt(q.get('holes'), 'd')} | "
                     f"{fmt(p.get('edge_to_smooth_band_nrmse'), '.1f')} / "
                     f"{fmt(q.get('edge_to_smooth_band_nrmse'), '.1f')} | {fmt(p.get('registration_warnings'), 'd')} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    out = []
    for method in ("parallax", "paper"):
        de = [r[method]["cc_de_mean"] for r in rows if r[method]["cc_de_mean"] is not None]
        dmax = [r[method]["cc_de_max"] for r in rows if r[method]["cc_de_max"] is not None]
        ok = sum(1 for r in rows if r[method]["cc_de_mean"] is not None and r[method]["cc_de_mean"] <= 2.0
                 and r[method]["cc_de_max"] <= 6.0 and r[method]["cc_nrmse"] <= 0.02)
        if de:
            out.append(f"{method}: ΔE mean median {np.median(de):.2f}, worst {max(de):.2f}; ΔE max worst "
                       f"{max(dmax):.2f}; runs within ΔE ≤ 2 / max ≤ 6 / NRMSE ≤ 0.02: {ok} of {len(de)}")
    inf = [r["parallax"]["infinity_error_px"] for r in rows]
    out.append(f"rig calibration error at infinity: median {np.median(inf):.3f} px, worst {max(inf):.3f} px")
    par = [r["parallax"]["chart_parallax_error_px"] for r in rows
           if r["parallax"].get("chart_parallax_error_px") is not None]
    if par:
        out.append(f"chart parallax error (median over the chart's pixels): median {np.median(par):.3f} px, worst "
                   f"{max(par):.3f} px; runs ≤ 0.3 px: {sum(x <= 0.3 for x in par)} of {len(par)}")
    reg = [r["parallax"]["chart_registration_error_px"] for r in rows
           if r["parallax"].get("chart_registration_error_px") is not None]
    if reg:
        out.append(f"chart B-position error (median over the chart's pixels): median {np.median(reg):.3f} px, worst "
                   f"{max(reg):.3f} px; runs ≤ 0.3 px: {sum(x <= 0.3 for x in reg)} of {len(reg)}")
    warned = [r for r in rows if r["parallax"].get("registration_warnings")]
    out.append(f"runs with registration warnings: {len(warned)} of {len(rows)}")
    better = sum(1 for r in rows if r["parallax"]["psnr_db"] >= r["paper"]["psnr_db"])
    out.append(f"six-band PSNR parallax ≥ paper in {better} of {len(rows)} runs")
    # every local failure by name, with what a perfect registration scores on the same run
    for r in rows:
        p, name = r["parallax"], f"{r['scene']} {r['time']} seed {r['seed']} {r.get('distance_m') or ''}".rstrip()
        if p["cc_de_mean"] is not None and not (p["cc_de_mean"] <= 2.0 and p["cc_de_max"] <= 6.0
                                                 and p["cc_nrmse"] <= 0.02):
            tb = r.get("truth_bands") or {}
            ceiling = (f"; the truth's own bands: {tb['truth_bands_de_mean']:.2f} / {tb['truth_bands_de_max']:.2f} "
                       f"({tb['truth_bands_de_max_patch']})") if tb else ""
            out.append(f"  outside the ColorChecker bounds: {name}: ΔE {p['cc_de_mean']:.2f} / {p['cc_de_max']:.2f}, "
                       f"NRMSE {p['cc_nrmse']:.4f}{ceiling}")
        if p["psnr_db"] < r["paper"]["psnr_db"]:
            out.append(f"  PSNR below the paper's method: {name}: {p['psnr_db']:.2f} vs {r['paper']['psnr_db']:.2f} dB")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="/tmp/omnispectral-regmatrix")
    ap.add_argument("--times", nargs="*", default=list(TIMES))
    ap.add_argument("--seeds", nargs="*", type=int, default=list(SEEDS))
    ap.add_argument("--distances", nargs="*", type=float, default=list(DISTANCES_M))
    ap.add_argument("--panoramas", nargs="*", default=list(PANORAMAS))
    ap.add_argument("--reuse-paper", nargs="*", default=[], metavar="RESULTS",
                    help="results.jsonl of earlier runs whose '--registration paper' results are reused for the "
                         "same runs (the simulator and that method unchanged since: same frames, same result)")
    ap.add_argument("--calibration", nargs="+", choices=["session", "chessboard", "views"], default=["session"],
                    help="camera B's mounting: fitted on each session (default), and/or from 12 simulated chessboard "
                         "pairs of the run's seed (calibrate rig --chessboard), made once per seed under "
                         "OUT/chessboards, and/or from the session's own calibration views (SESSION/calibration/, "
                         "what a plain 'process' uses); several: each session is simulated once and processed with "
                         "each")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = out / "results.jsonl"

    def run_key(r: dict) -> str:
        return json.dumps({k: r.get(k) for k in ("scene", "time", "seed", "distance_m")}, sort_keys=True)

    done: dict[tuple[str, str], dict] = {}
    if results.exists():
        for line in results.read_text().splitlines():
            r = json.loads(line)
            done[(run_key(r), r.get("rig_calibration", "session"))] = r
    paper = {}
    for f in args.reuse_paper:
        for line in Path(f).read_text().splitlines():
            r = json.loads(line)
            paper[run_key(r)] = r["paper"]
    keys = [{"scene": "procedural", "time": t, "seed": s, "distance_m": d}
            for t in args.times for s in args.seeds for d in args.distances]
    keys += [{"scene": p, "time": "12:00", "seed": s, "distance_m": None} for p in args.panoramas
             for s in args.seeds[:1]] if SHARED.is_dir() else []
    for i, key in enumerate(keys):
        k = run_key(key)
        todo = [c for c in args.calibration if (k, c) not in done]
        if todo:
            print(f"[{i + 1}/{len(keys)}] {key} {todo}", file=sys.stderr, flush=True)
            cals = {c: chessboard_calibration(out, key["seed"]) if c == "chessboard" else None for c in todo}
            for row in run_one(out / "work", key, paper.get(k), cals):
                done[(k, row["rig_calibration"])] = row
                with open(results, "a") as fh:
                    fh.write(json.dumps(row) + "\n")
    texts = []
    for c in args.calibration:
        rows = [done[(run_key(key), c)] for key in keys]
        text = f"## B's mounting: {c}\n\n" + table(rows) + "\n\n" + summary(rows)
        (out / f"table-{c}.md").write_text(text + "\n")
        texts.append(text)
    print("\n\n".join(texts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
