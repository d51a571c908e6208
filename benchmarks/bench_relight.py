"""Relighting against ground truth: the indoor scene captured under FL11, relit to A, vs its capture under A.

    .venv/bin/python benchmarks/bench_relight.py [--work DIR] [--json-out FILE]

Simulates the small rig in the indoor scene (``simulate --scene indoor``) under FL11 and under A, processes
both (``process``, default settings), relights the FL11 product to A from the white reference
(``relight``), and compares the 24 ColorChecker patches and the painting's 48 cells (mean bands over 60 % of
each patch's or cell's angular half-size) with the capture under A, each relative to its own white reference
(CIELAB, ΔE*ab):

* six-band, reflectance by Wiener estimation under the measured light (the default);
* six-band, the paper's ratio ``s/E · E_new``;
* RGB only: the rig's camera without its filter (the paper's RGB comparison) looking at the same scene under
  FL11 (noise-free patch radiance from the scene), von Kries gains from the white reference to the camera's
  response to 0.95 × A, then a 3 × 3 matrix to XYZ fitted by least squares on the prior's reflectances
  under A (ColorChecker excluded), against the same A capture seen through its six bands.

Each is also compared with the truth: the scene's noise-free radiance under A averaged over the same disks,
relative to its white reference.

Camera B's mounting is calibrated once on an outdoor session of the same rig (a room has nothing far away to
anchor its yaw) and reused for both indoor sessions (``process --rig-calibration``).

Existing sessions and products in ``--work`` are reused (both stages resume).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def omnispectral(*args: str) -> None:
    """Run the command-line tool of this environment (the commands a user would type)."""
    subprocess.run([str(Path(sys.executable).with_name("omnispectral")), *args], check=True, stdout=subprocess.DEVNULL)


def patch_bands(product: Path, patches: list[dict]) -> np.ndarray:
    from omnispectral.apps.relight import WhiteReference, disk_mean_bands
    from omnispectral.product.spectra import open_product

    _, store, _ = open_product(product)
    return np.array([disk_mean_bands(store, 0, WhiteReference(p["lon_deg"], p["lat_deg"], 0.6 * p["half_size_deg"]))
                     for p in patches])


def disk_radiance(scene, patch: dict, n: int = 9) -> np.ndarray:
    """Mean spectral radiance over the disk that :func:`patch_bands` averages (an ``n × n`` grid of directions
    inside 60 % of the patch's angular half-size)."""
    from omnispectral.imaging.geometry import lonlat_to_ray

    r = 0.6 * patch["half_size_deg"]
    off = np.linspace(-r, r, n)
    dlon, dlat = np.meshgrid(off, off)
    inside = dlon ** 2 + dlat ** 2 <= r * r
    lat = patch["lat_deg"] + dlat[inside]
    lon = patch["lon_deg"] + dlon[inside] / max(math.cos(math.radians(patch["lat_deg"])), 0.05)
    return scene.spectral_radiance(lonlat_to_ray(lon, lat)).mean(axis=0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default="bench-relight")
    ap.add_argument("--json-out", default=None)
    a = ap.parse_args()
    from omnispectral.apps.relight import WhiteReference, reflectance_prior
    from omnispectral.imaging.geometry import lonlat_to_ray
    from omnispectral.product.spectra import open_product
    from omnispectral.sim.scenes import IndoorScene
    from omnispectral.spectral.colour import delta_e_ab, spectra_to_xyz
    from omnispectral.spectral.colour import signal_to_Lab as signals_to_lab
    from omnispectral.spectral.library import load_illuminant

    work = Path(a.work)
    timings = {}
    # a room has nothing far away to anchor camera B's yaw (docs/architecture.md, "Camera B"): calibrate the rig
    # on an outdoor session of the same rig (same seed: the same mounting error) and reuse it indoors
    t = time.perf_counter()
    omnispectral("simulate", "--scene", "procedural", "-o", str(work / "session_outdoor"))
    if not (work / "rig-calibration.json").is_file():
        omnispectral("calibrate", "rig", str(work / "session_outdoor"), "-o", str(work / "rig-calibration.json"))
    timings["rig_calibration_s"] = time.perf_counter() - t
    for light in ("FL11", "A"):
        t = time.perf_counter()
        omnispectral("simulate", "--scene", "indoor", "--light", light, "-o", str(work / f"session_{light}"))
        omnispectral("process", str(work / f"session_{light}"), "-o", str(work / f"product_{light}"),
                     "--rig-calibration", str(work / "rig-calibration.json"))
        timings[f"simulate_process_{light}_s"] = time.perf_counter() - t
    scene = IndoorScene("FL11")
    patches = scene.colorchecker_patches()
    wref = scene.white_reference()
    white = WhiteReference(wref["lon_deg"], wref["lat_deg"], 0.6 * wref["half_size_deg"])
    for method in ("wiener", "ratio"):
        t = time.perf_counter()
        omnispectral("relight", str(work / "product_FL11"), f"--white={white.lon_deg},{white.lat_deg},"
                     f"{white.radius_deg}", "--to", "A", "--method", method, "-o", str(work / f"relit_{method}"))
        timings[f"relight_{method}_s"] = time.perf_counter() - t
    _, _, est = open_product(work / "product_A")
    wl = np.asarray(est.wavelength_nm)

    def lab_of(product: Path, targets: list[dict]) -> np.ndarray:
        b = patch_bands(product, targets)
        wb = patch_bands(product, [{"lon_deg": white.lon_deg, "lat_deg": white.lat_deg,
                                    "half_size_deg": white.radius_deg / 0.6}])[0]
        return signals_to_lab(est.estimate(b), est.estimate(wb[None])[0] / 0.95, wl)

    # RGB only: the rig's camera without its filter (the paper's RGB comparison), seeing the same scene under FL11
    # (noise-free radiance from the scene, averaged over the same disks), von Kries to the camera's response to
    # 0.95 A, then a 3x3 matrix to XYZ fitted on the prior's reflectances under A
    import colour

    from omnispectral.rig import load_preset
    from omnispectral.spectral.system import rgb_system

    r3 = rgb_system(load_preset("small").camera_a.sensitivity, wl).matrix
    ill_a = load_illuminant("A").resample(wl).values[0]
    mu, cov = reflectance_prior(tuple(wl.tolist()))
    train = np.clip(np.random.default_rng(0).multivariate_normal(mu, cov, 2000), 0, 1)
    m, *_ = np.linalg.lstsq((train * ill_a) @ r3.T, spectra_to_xyz(train * ill_a, wl), rcond=None)
    w_fl = scene.spectral_radiance(lonlat_to_ray(white.lon_deg, white.lat_deg)[None])[0] @ r3.T
    w_a = r3 @ (0.95 * ill_a)
    white_xyz = (w_a / 0.95) @ m

    scene_a = IndoorScene("A")
    white_a = disk_radiance(scene_a, {"lon_deg": white.lon_deg, "lat_deg": white.lat_deg,
                                      "half_size_deg": white.radius_deg / 0.6})

    def evaluate(targets: list[dict]) -> dict:
        res = {}
        lab_a = lab_of(work / "product_A", targets)
        for method in ("wiener", "ratio"):
            de = delta_e_ab(lab_of(work / f"relit_{method}", targets), lab_a)
            res[f"six_band_{method}"] = {"mean": float(de.mean()), "median": float(np.median(de)),
                                         "max": float(de.max())}
        de = delta_e_ab(lab_of(work / "product_FL11", targets), lab_a)
        res["not_relit"] = {"mean": float(de.mean()), "max": float(de.max())}
        rgb_fl = np.array([disk_radiance(scene, p) for p in targets]) @ r3.T
        lab_rgb = colour.XYZ_to_Lab((rgb_fl * (w_a / w_fl)) @ m / white_xyz[1], colour.XYZ_to_xy(white_xyz))
        de = delta_e_ab(lab_rgb, lab_a)
        res["rgb_only_von_kries_noise_free"] = {"mean": float(de.mean()), "median": float(np.median(de)),
                                                "max": float(de.max())}
        # and each against the truth: the scene's noise-free radiance under A over the same disks, relative to
        # its white reference (no camera at all)
        lab_true = signals_to_lab(np.array([disk_radiance(scene_a, p) for p in targets]), white_a / 0.95, wl)
        res["capture_under_A_vs_truth"] = {"mean": float(delta_e_ab(lab_a, lab_true).mean())}
        res["six_band_wiener_vs_truth"] = {
            "mean": float(delta_e_ab(lab_of(work / "relit_wiener", targets), lab_true).mean())}
        res["rgb_only_vs_truth"] = {"mean": float(delta_e_ab(lab_rgb, lab_true).mean())}
        return res

    results = evaluate(patches)
    painting = evaluate(scene.painting_cells())
    out = {"colorchecker_delta_e_ab_vs_capture_under_A": results,
           "painting_cells_delta_e_ab_vs_capture_under_A": painting, "timings_s": timings, "load": os.getloadavg(),
           "relight_summary": json.loads((work / "relit_wiener" / "relight.json").read_text())["light_source_pixels"]}
    print(json.dumps(out, indent=2))
    if a.json_out:
        Path(a.json_out).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
