"""The recovered sun across the day: irradiance, spectrum and direction against the simulator's truth.

Every run simulates a session of the ``small`` preset with the procedural scene (its times of day and
seeds are the registration matrix's, benchmarks/bench_registration_matrix.py: sun elevations from about
5° to 75°), processes it once per sun method (default: the attenuated bracket) and records:

- the product's horizontal irradiance per band against the truth's (``ground_truth/bands.npy`` on the
  same grid, both integrated by :func:`omnispectral.product.irradiance.irradiance`), worst band;
- the sun's spectrum (unit-norm NRMSE) against the truth's sun spectrum (the scene's CIE D-series sun);
- the angle between the recovered and the true sun direction;
- the sun stage's time and the whole processing time;
- with ``--render``, Fig. 16's mirror ball on a grey plate lit by the product against the same scene lit
  by the truth's environment (the plate's worst block ratio per band).

    python benchmarks/bench_sun.py --out /tmp/sun                      # 9 times x 3 seeds, the ND bracket
    python benchmarks/bench_sun.py --sun nd-bracket diffuse-reference sky-model --seeds 0 --out /tmp/sun
        # every method on the same frames (the white target's place from the scene, as a user would note it)

One JSON line per run in OUT/results.jsonl (resumable), a Markdown table on stdout and in OUT/table.md,
with the machine's load average per run.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import shutil
import time
from pathlib import Path

import numpy as np

from omnispectral.mosaic.store import PanoramaStore
from omnispectral.product.irradiance import irradiance
from omnispectral.product.process import process
from omnispectral.product.sun_reference import SunReference
from omnispectral.rig import load_preset
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.scenes.sky import unit_luminance_daylight
from omnispectral.sim.simulate import simulate_session
from omnispectral.sim.truth import GroundTruth
from omnispectral.spectral.metrics import nrmse

TIMES = ("06:30", "08:00", "09:30", "11:00", "12:30", "14:00", "15:30", "17:00", "18:00")
SEEDS = (0, 1, 5)


def angle_deg(lon1: float, lat1: float, lon2: float, lat2: float) -> float:
    """Great-circle angle between two directions (degrees)."""
    a1, b1, a2, b2 = map(math.radians, (lon1, lat1, lon2, lat2))
    c = math.sin(b1) * math.sin(b2) + math.cos(b1) * math.cos(b2) * math.cos(a1 - a2)
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def score(session: Path, product: Path) -> dict:
    """Irradiance ratios, spectrum NRMSE and direction error of one product against its truth."""
    gt = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    daylight = gt["scene"]["daylight"]
    truth_h = irradiance(np.load(session / "ground_truth" / "bands.npy", mmap_mode="r")).band_irradiance_dn_s_sr
    prod_h = irradiance(PanoramaStore.open(product / "panorama.zarr")).band_irradiance_dn_s_sr
    ratio = np.asarray(prod_h) / np.asarray(truth_h)
    sun = json.loads((product / "sun.json").read_text())
    out = {"sun_elevation_deg": daylight["sun_elevation_deg"], "method": sun["method"],
           "recovered": bool(sun.get("recovered")), "irradiance_ratio": ratio.tolist(),
           "worst_ratio": float(ratio[np.argmax(np.abs(ratio - 1))])}
    if sun.get("recovered"):
        wl = np.asarray(sun["wavelength_nm"])
        true_spd = unit_luminance_daylight(daylight["cct_sun_K"], wl)
        out["spectrum_nrmse"] = float(nrmse(np.asarray(sun["spectral_radiance"])[None], true_spd[None])[0])
        out["direction_error_deg"] = angle_deg(sun["lon_deg"], sun["lat_deg"], daylight["sun_lon_deg"],
                                               daylight["sun_lat_deg"])
    return out


def plate_ratio(session: Path, product: Path, size: int = 64, spp: int = 128) -> list[float]:
    """Fig. 16's mirror ball on a grey plate lit by the product against the same scene lit by the truth's
    environment: the worst (furthest from 1) ratio per band of the plate's block medians (four blocks)."""
    from omnispectral.apps.environment import environment_from_bands, environment_from_product
    from omnispectral.apps.render import MirrorBallScene, render_fast

    env, est = environment_from_product(product)
    truth_env = environment_from_bands(np.load(session / "ground_truth" / "bands.npy"), est, env.units)
    ours = render_fast(env, est, MirrorBallScene(), size, size, spp=spp).bands
    theirs = render_fast(truth_env, est, MirrorBallScene(), size, size, spp=spp).bands
    plate = slice(int(0.8 * size), size)
    ratios = np.array([np.median(ours[plate, c:c + size // 4].reshape(-1, ours.shape[2]), axis=0)
                       / np.median(theirs[plate, c:c + size // 4].reshape(-1, ours.shape[2]), axis=0)
                       for c in range(0, size, size // 4)])
    return ratios[np.argmax(np.abs(ratios - 1), axis=0), np.arange(ratios.shape[1])].tolist()


def run_one(work: Path, time_hhmm: str, seed: int, methods: list[str], render: bool = False) -> list[dict]:
    """Simulate one session, process it once per sun method, score each product."""
    shutil.rmtree(work, ignore_errors=True)
    h, m = (int(x) for x in time_hhmm.split(":"))
    start = dt.datetime(2026, 3, 21, h, m, tzinfo=dt.UTC)
    scene = ProceduralOutdoorScene(time_hhmm, seed=seed)
    t0 = time.perf_counter()
    simulate_session(work / "session", load_preset("small"), scene, start=start, seed=seed, progress=False)
    simulate_s = time.perf_counter() - t0
    # where the user put the white target (the scene's description stands in for the user's notes)
    reference = SunReference.from_dict(scene.describe()["reference"])
    rows = []
    for method in methods:
        t1 = time.perf_counter()
        index = process(work / "session", work / method, truth=GroundTruth.of_session(work / "session"),
                        progress=False, sun=method,
                        sun_reference=reference if method == "diffuse-reference" else None)
        extra = {"render_plate_ratio": plate_ratio(work / "session", work / method)} if render else {}
        rows.append({"time": time_hhmm, "seed": seed, "sun_method": method, **extra,
                     **score(work / "session", work / method), "sun_s": index["timings_s"].get("sun"),
                     "process_s": time.perf_counter() - t1, "simulate_s": simulate_s,
                     "load_avg": os.getloadavg()[0]})
    shutil.rmtree(work, ignore_errors=True)
    return rows


def table(rows: list[dict]) -> str:
    """Markdown table of the runs, worst cases last."""
    lines = ["| time | seed | sun elev. (°) | method | worst band ratio | spectrum NRMSE | direction (°) "
             "| sun stage (s) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['time']} | {r['seed']} | {r['sun_elevation_deg']:.1f} | {r['method']} | "
                     f"{r['worst_ratio']:.4f} | {r.get('spectrum_nrmse', float('nan')):.4f} | "
                     f"{r.get('direction_error_deg', float('nan')):.3f} | {r['sun_s'] or 0:.2f} |")
    rec = [r for r in rows if r["recovered"]]
    if rec:
        worst = max(rec, key=lambda r: abs(r["worst_ratio"] - 1))
        lines.append(f"\nRecovered in {len(rec)}/{len(rows)} runs; worst band ratio {worst['worst_ratio']:.4f} "
                     f"({worst['time']} seed {worst['seed']}); worst spectrum NRMSE "
                     f"{max(r['spectrum_nrmse'] for r in rec):.4f}; worst direction "
                     f"{max(r['direction_error_deg'] for r in rec):.3f}°.")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--times", nargs="+", default=list(TIMES))
    ap.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    ap.add_argument("--sun", nargs="+", default=["nd-bracket"], help="process --sun methods (each on the same frames)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/omnispectral-bench-sun"))
    ap.add_argument("--render", action="store_true", help="also render the mirror ball against the truth's")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    results = args.out / "results.jsonl"
    done = {(r["time"], r["seed"], r["sun_method"]): r for r in map(json.loads, results.read_text().splitlines())} \
        if results.exists() else {}
    for t in args.times:
        for s in args.seeds:
            todo = [m for m in args.sun if (t, s, m) not in done]
            if not todo:
                continue
            for row in run_one(args.out / "work", t, s, todo, args.render):
                done[(t, s, row["sun_method"])] = row
                with open(results, "a", encoding="utf-8") as fh:
                    fh.write(json.dumps(row) + "\n")
                print(f"{t} seed {s} {row['sun_method']}: worst ratio {row['worst_ratio']:.4f}"
                      + (f", plate {row['render_plate_ratio']}" if "render_plate_ratio" in row else ""), flush=True)
    texts = []
    for m in args.sun:
        rows = [done[(t, s, m)] for t in args.times for s in args.seeds if (t, s, m) in done]
        texts.append(f"### {m}\n\n{table(rows)}\n")
    text = "\n".join(texts)
    (args.out / "table.md").write_text(text, encoding="utf-8")
    print(text)


if __name__ == "__main__":
    main()
