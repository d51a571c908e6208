"""Relighting throughput and memory on a large synthetic product (numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_relight_scale.py [--width 4096] [--tile 512] [--work DIR] [--repeat N]

A product of ``width × width/2`` six-band pixels is written tile by tile (never whole in memory: ColorChecker
reflectances in a repeating pattern under FL11, a white reference, 1 % noise per pixel so that it
compresses like a capture), then ``relight`` runs in a fresh subprocess (``--repeat`` times: the median
time, the peak memory over the runs); its wall time, pixels per second, peak resident memory
(``ru_maxrss``) and the disk used by the input and the relit product are reported.
Memory should follow the tile size and the workers, not the panorama.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_product(root: Path, width: int, tile: int, noise: float = 0.01) -> None:
    from omnispectral.product.estimator import estimator_params, rig_estimator
    from omnispectral.product.layout import create_band_product, fill_pyramid, write_level0
    from omnispectral.rig import load_preset
    from omnispectral.spectral.library import load_illuminant, load_reflectances

    rig = load_preset("small")
    est = rig_estimator(rig)[0]
    wl = np.asarray(est.wavelength_nm)
    cc = load_reflectances("colorchecker").resample(wl).values
    fl11 = load_illuminant("FL11").resample(wl).values[0]
    patch_bands = (1000 * (cc * fl11 / fl11.mean()) @ est.system_matrix.T).astype(np.float32)  # (24, 6)
    h = width // 2
    store = create_band_product(root, h, width, {"bands": list(est.band_names), "units": "DN/s",
                                                 "estimator": {"params": estimator_params(rig)}},
                                {"bands": list(est.band_names)}, tile=tile)

    def tile_fn(r0, r1, c0, c1):
        rr, cc_ = np.mgrid[r0:r1, c0:c1]
        x = patch_bands[((rr // 16) * 7 + cc_ // 16) % 24]
        if noise > 0:  # relative noise per pixel and band: compresses like a capture, not like a flat pattern
            x *= 1 + noise * np.random.default_rng((r0, c0)).standard_normal(x.shape, dtype=np.float32)
        return x

    write_level0(store, tile_fn)
    fill_pyramid(store)


def disk_bytes(root: Path) -> int:
    """Bytes on disk under ``root`` (allocated blocks, as ``du``)."""
    return sum(p.stat().st_blocks * 512 for p in root.rglob("*") if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--width", type=int, default=4096)
    ap.add_argument("--tile", type=int, default=512)
    ap.add_argument("--work", default=None)
    ap.add_argument("--noise", type=float, default=0.01, help="relative noise of the synthetic bands")
    ap.add_argument("--repeat", type=int, default=1, help="relight runs on the one product (median reported)")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=a.work) as tmp:
        product = Path(tmp) / "product"
        t = time.perf_counter()
        make_product(product, a.width, a.tile, a.noise)
        t_make = time.perf_counter() - t
        # the white patch (index 18) first appears at rows 32-47, columns 64-79 (pattern (r//16)*7 + c//16 = 18)
        h = a.width // 2
        lon = (72 + 0.5) / a.width * 360 - 180
        lat = 90 - (40 + 0.5) / h * 180
        runs, loads = [], []
        for _ in range(a.repeat):
            t = time.perf_counter()
            subprocess.run([str(Path(sys.executable).with_name("omnispectral")), "relight", str(product),
                            f"--white={lon},{lat},{2 * 360 / a.width}", "--to", "A", "-o", str(Path(tmp) / "relit")],
                           check=True, stdout=subprocess.DEVNULL)
            runs.append(time.perf_counter() - t)
            loads.append(os.getloadavg()[0])
        t_relight = float(np.median(runs))
        rss_mib = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
        disk = {name: disk_bytes(Path(tmp) / name) / 2**30 for name in ("product", "relit")}
    px = a.width * (a.width // 2)
    out = {"width": a.width, "height": a.width // 2, "megapixels": px / 1e6, "tile": a.tile, "noise": a.noise,
           "write_product_s": t_make, "relight_s": t_relight, "relight_runs_s": runs, "load_after_runs": loads,
           "megapixels_per_s": px / 1e6 / t_relight,
           "relight_peak_rss_mib": rss_mib, "disk_gib": disk, "load": os.getloadavg()}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
