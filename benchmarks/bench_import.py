"""Imported photographs vs the simulator's own session, on a real HDR panorama (numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_import.py --hdr PANORAMA.hdr [--preset small] [--root DIR]

The rig's two cameras photograph a :class:`PanoramaScene` of ``--hdr`` (e.g. Poly Haven's
``venice_sunset_1k.hdr`` in /work/shared/data/hdr_envmaps) three ways, same seed and noise:

* ``simulate``: the simulator's session (12-bit raw RGB frames, journal written by the capture loop);
* ``import tiff``: the same frames written as 16-bit TIFFs with a Papywizard XML and an exposure table,
  then ``omnispectral import``;
* ``import jpeg``: the frames as 8-bit sRGB JPEGs (quality 95, 4:4:4) with EXIF ExposureTime and a Hugin
  ``.pto``, then ``omnispectral import``.

Each session is processed (``--registration paper``: the scene is at infinity) and its six-band panorama
compared with the scene's ground truth (PSNR over unsaturated pixels, as the report computes it).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import shutil
import time
from pathlib import Path

from omnispectral.capture.importer import import_images, list_images, read_directions, read_exposure_table
from omnispectral.product.process import process
from omnispectral.rig import load_preset
from omnispectral.sim.photographs import write_photographs
from omnispectral.sim.scenes import PanoramaScene
from omnispectral.sim.simulate import RigRenderer, simulate_session, true_mounting_error_deg
from omnispectral.sim.truth import GroundTruth


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hdr", required=True)
    ap.add_argument("--preset", default="small")
    ap.add_argument("--root", default="/tmp/bench_import")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    root = Path(args.root)
    shutil.rmtree(root, ignore_errors=True)
    rig = load_preset(args.preset)
    scene = PanoramaScene(args.hdr, scale=1000.0)
    start = dt.datetime(2017, 6, 21, 12, tzinfo=dt.UTC)
    rows = {}
    t0 = time.perf_counter()
    simulate_session(root / "simulate", rig, scene, start=start, seed=args.seed, progress=False)
    gt = root / "simulate" / "ground_truth"
    renderer = RigRenderer(rig, scene, b_mounting_error_deg=true_mounting_error_deg(args.seed))
    sessions = {"simulate": root / "simulate"}
    for fmt in ("tiff", "jpeg"):
        s = root / f"import_{fmt}"
        for c in ("A", "B"):
            files = write_photographs(root / f"{fmt}_{c}", rig, scene, c, fmt=fmt, seed=args.seed, renderer=renderer)
            if fmt == "tiff":
                entries = read_directions(Path(files["papywizard"]), list_images(root / f"{fmt}_{c}"))
                table = read_exposure_table(files["exposures"])
            else:
                entries, table = read_directions(Path(files["pto"])), None
            import_images(s, rig, c, entries, exposure_table=table)
        shutil.copytree(gt, s / "ground_truth")
        sessions[f"import {fmt}"] = s
    print(f"sessions ready in {time.perf_counter() - t0:.0f} s", flush=True)
    for name, s in sessions.items():
        product = root / f"p_{name.replace(' ', '_')}"
        index = process(s, product, truth=GroundTruth.of_session(s), progress=False, registration="paper")
        acc = json.loads((product / "report" / "report.json").read_text())["accuracy"]
        rows[name] = {"six_band_psnr_db": acc["six_band_psnr_db"], "spectral_nrmse": acc["spectral_nrmse"],
                      "hdr_merge_s": index["timings_s"]["hdr_merge"]}
        print(name, json.dumps(rows[name]), flush=True)


if __name__ == "__main__":
    main()
