"""Raw Bayer frames: demosaicing method and order against the RGB-frame path (numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_bayer.py [--root DIR] [--chart-patch 0.15] [--seed 0] [--json-out FILE]

One simulated scene (procedural, 12:00, ``small`` rig) is captured twice with the same seed: as RGB
frames (every pixel has three channels: the reference) and as RGGB mosaics (``simulate --raw bayer``).
The Bayer session is processed once per variant (the session's rig snapshot rewritten with the
variant's ``[cameras.X.raw] demosaic`` and ``order``; the frames are the same):

* ``merge-first``: HDR merge on the mosaic, then one demosaic of the merged (float, HDR) mosaic;
* ``demosaic-first``: every frame demosaiced (codes), then the HDR merge of the RGB frames.

Reported per variant: ColorChecker ΔE*ab (mean, max) and chart NRMSE against the simulator's truth,
six-band PSNR, whole-panorama spectral NRMSE, and the HDR-merge stage time.  The ColorChecker's
patches are ``--chart-patch`` metres wide (0.15 m: ≈7 px on the small rig's 256 px sensor; at the
scene's default 0.05 m a patch is ≈2.5 px and no demosaicing can recover its colour).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import re
import shutil
from pathlib import Path

from omnispectral.product.process import process
from omnispectral.rig import load_preset
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.simulate import simulate_session
from omnispectral.sim.truth import GroundTruth

VARIANTS = [("menon2007", "merge-first"), ("menon2007", "demosaic-first"), ("malvar2004", "merge-first"),
            ("malvar2004", "demosaic-first"), ("bilinear", "merge-first"), ("opencv-ea", "demosaic-first")]
NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)


def accuracy(product: Path, index: dict) -> dict:
    acc = json.loads((product / "report" / "report.json").read_text())["accuracy"]
    cc = acc["colorchecker"]
    return {"delta_e_ab": cc["delta_e_ab"], "delta_e_ab_max": cc["delta_e_ab_max"], "chart_nrmse": cc["nrmse"],
            "six_band_psnr_db": acc["six_band_psnr_db"], "spectral_nrmse": acc["spectral_nrmse"],
            "hdr_merge_s": index["timings_s"]["hdr_merge"]}


def with_variant(bayer: Path, target: Path, method: str, order: str) -> Path:
    """A copy of the Bayer session whose rig snapshot asks for ``method`` and ``order``."""
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(bayer, target, ignore=shutil.ignore_patterns(".omnispectral.lock"))
    rig = (target / "rig.toml").read_text()
    rig = re.sub(r'(\[cameras\.[AB]\.raw\]\n)', rf'\1demosaic = "{method}"\norder = "{order}"\n', rig)
    (target / "rig.toml").write_text(rig)
    return target


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default="/tmp/bench_bayer")
    ap.add_argument("--chart-patch", type=float, default=0.15)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args()
    root = Path(args.root)
    scene = ProceduralOutdoorScene(time_hhmm="12:00", day_of_year=172, chart_patch_m=args.chart_patch)
    rows = {}
    for raw in ("rgb", "bayer"):
        simulate_session(root / raw, load_preset("small"), scene, start=NOON, progress=False, seed=args.seed,
                         raw=raw)
    shutil.rmtree(root / "p_rgb", ignore_errors=True)  # products are rebuilt: a resumed merge would time nothing
    index = process(root / "rgb", root / "p_rgb", truth=GroundTruth.of_session(root / "rgb"), progress=False)
    rows["rgb frames"] = accuracy(root / "p_rgb", index)
    print("rgb frames", json.dumps(rows["rgb frames"]), flush=True)
    for method, order in VARIANTS:
        name = f"{method} {order}"
        session = with_variant(root / "bayer", root / f"bayer_{method}_{order}", method, order)
        shutil.rmtree(root / f"p_{method}_{order}", ignore_errors=True)
        index = process(session, root / f"p_{method}_{order}", truth=GroundTruth.of_session(session), progress=False)
        rows[name] = accuracy(root / f"p_{method}_{order}", index)
        print(name, json.dumps(rows[name]), flush=True)
    print(f"{'variant':28s} {'dE mean':>8s} {'dE max':>7s} {'chart NRMSE':>11s} {'PSNR dB':>8s} {'merge s':>8s}")
    for name, r in rows.items():
        print(f"{name:28s} {r['delta_e_ab']:8.3f} {r['delta_e_ab_max']:7.2f} {r['chart_nrmse']:11.4f} "
              f"{r['six_band_psnr_db']:8.2f} {r['hdr_merge_s']:8.2f}")
    if args.json_out:
        Path(args.json_out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
