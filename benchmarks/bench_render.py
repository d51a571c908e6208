"""Spectral rendering cost: band-packed spectral path vs six-band fast path (numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_render.py [--size 512] [--spp 64] [--variant llvm_ad_rgb] [--json-out FILE]

The mirror ball on a grey plate (silver ball, ColorChecker neutral 5 plate) lit by a synthetic 1024 × 512
six-band product (a D65 sky brightening upwards, an illuminant-A glow towards lon −90°, a saturated sun of
4 × 4 px).  Each path runs in a fresh subprocess: wall time of the render call (environment estimate
excluded, it is shared) and the child's peak resident memory (``ru_maxrss``).  The spectral path renders
61 wavelengths in 21 RGB passes, the fast path the six bands in 2 passes plus the per-pixel estimator.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

CHILD = r"""
import json, sys, time
from omnispectral.apps.environment import environment_from_product
from omnispectral.apps.render import MirrorBallScene, render_fast, render_spectral, mitsuba
product, path, size, spp, variant = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), sys.argv[5]
mitsuba(variant)
env, est = environment_from_product(product, level=0)
scene = MirrorBallScene(view_lon_deg=180.0)
t = time.perf_counter()
if path == "spectral":
    res = render_spectral(env, scene, size, size, spp)
else:
    res = render_fast(env, est, scene, size, size, spp)
print(json.dumps({"seconds": time.perf_counter() - t, "passes": res.info["passes"], "variant": res.info["variant"],
                  "mean": float(res.spectra.mean())}))
"""


def make_product(root: Path) -> None:
    from omnispectral.product.estimator import estimator_params, rig_estimator
    from omnispectral.product.layout import write_band_product
    from omnispectral.rig import load_preset, rig_toml
    from omnispectral.spectral.library import load_illuminant

    rig = load_preset("small")
    est = rig_estimator(rig)[0]
    wl = np.asarray(est.wavelength_nm)
    h, w = 512, 1024
    lon = np.radians((np.arange(w) + 0.5) / w * 360 - 180)
    lat = np.radians(90 - (np.arange(h) + 0.5) / h * 180)
    d65 = load_illuminant("D65").resample(wl).values[0] / 100
    ill_a = load_illuminant("A").resample(wl).values[0] / 100
    sky = (1.0 + 0.5 * np.sin(lat))[:, None] + 0 * lon[None, :]
    warm = 0.8 * (1 + np.sin(-lon))[None, :] * np.cos(lat)[:, None]
    bands = (100 * (sky[..., None] * d65 + warm[..., None] * ill_a) @ est.system_matrix.T).astype(np.float32)
    clip = 0.99 * rig.camera_a.max_dn / min(rig.bracket.exposures_s)
    bands[100:104, 700:704] = clip
    write_band_product(root, bands, {"bands": list(est.band_names), "units": "DN/s",
                                     "estimator": {"params": estimator_params(rig)}},
                       attrs={"bands": list(est.band_names), "rig": {"toml": rig_toml(rig)}}, tile=256)


def run(product: Path, path: str, size: int, spp: int, variant: str) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    out = subprocess.run([sys.executable, "-c", CHILD, str(product), path, str(size), str(spp), variant],
                         check=True, capture_output=True, text=True)
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res["peak_rss_mib"] = max(rss, before) / 1024  # ru_maxrss of the largest child so far (KiB on Linux)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--json-out", default=None)
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        product = Path(tmp) / "product"
        make_product(product)
        fast = run(product, "fast", a.size, a.spp, a.variant)  # smaller child first: ru_maxrss is a running maximum
        spectral = run(product, "spectral", a.size, a.spp, a.variant)
    out = {"size": a.size, "spp": a.spp, "variant": a.variant, "load": os.getloadavg(), "fast": fast,
           "spectral": spectral, "ratio_time": spectral["seconds"] / fast["seconds"]}
    print(json.dumps(out, indent=2))
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
