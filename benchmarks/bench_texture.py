"""Fine texture: a hyperspectral reflectance cube on a wall, camera A's and B's band errors and the spectral
error the pipeline adds, against the simulator's truth on the product's grid.

For each cube and distance the script simulates the ``small`` preset at noon with the cube hung on a wall
of the procedural scene, processes it the default way and compares, over the panel's pixels (2 px in from
its border):

- per camera, the median relative band error ``|P − T| / T`` (P the product, T the truth's bands);
- the spectral error the pipeline adds: unit-norm NRMSE between the spectra the product's estimator gives
  from P and from T, next to the estimator's own floor, the NRMSE between its spectra from T and the true
  spectra (the scene's radiance as the mean of 8 × 8 rays per pixel, the texture filtered over each ray's share
  of the pixel as the simulator renders it).

Cubes: ``--cube FILE`` (``.npz`` or ENVI, see ``omnispectral.sim.scenes.cube``; repeatable) or, by
default, one made here from a photograph (scikit-image's ``coffee``, a real scene's texture) whose linear
sRGB is lifted per pixel onto the first three principal components of the Vrhel et al. (1994) object
reflectances shipped with the package (mean plus three components fitted to the pixel's colour under
D65, clipped to 0..1): measured spectral shapes, a real scene's texture.

``--b-variant`` changes camera B step by step towards a twin of camera A (``B_VARIANTS``: B's mounting known
exactly, then A's filter, then no mounting angles, then no baseline), which tells registration, filter,
sampling phase and parallax apart; ``--interp`` processes the same frames with other interpolations.

    python benchmarks/bench_texture.py [--cube FILE ...] [--placement near-25 ...] [--noise on off]
        [--interp spline ...] [--b-variant rig a-twin ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import datetime as dt
import itertools
import json
import os
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

from omnispectral.choices import INTERP_NAMES
from omnispectral.imaging.geometry import lonlat_to_ray
from omnispectral.product.layout import open_product
from omnispectral.product.process import process
from omnispectral.rig import load_preset, rig_from_dict
from omnispectral.sim.antialias import REFINE_RAYS_PER_SIDE, subpixel_offsets
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.scenes.base import footprint_kwargs
from omnispectral.sim.scenes.cube import CubeOnWallScene
from omnispectral.sim.simulate import DEFAULT_MOUNTING_ERROR_DEG, simulate_session
from omnispectral.sim.truth import GroundTruth, equirect_ray_spread_rad
from omnispectral.spectral.colour import spectra_to_linear_srgb
from omnispectral.spectral.library import load_reflectances

NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)
#: Where the panel hangs: wall, longitude, latitude of its centre (deg) and width (m); the near wall's face is
#: 4.0 m south of the rig, so these put the panel 4.4-7.0 m away, each at another sampling phase of the cameras.
PLACEMENTS = {"near-25": ("near wall", -25.0, 5.0, 1.2), "near-33": ("near wall", -33.0, 4.0, 1.2),
              "near-41": ("near wall", -41.0, 6.0, 1.2), "near-55": ("near wall", -55.0, 5.0, 1.2)}


def photo_cube(size_px: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A ``(size, size, 31)`` reflectance cube (400–700 nm, 10 nm) from a photograph's texture (module docstring)."""
    import cv2
    from skimage.data import coffee

    refl = load_reflectances("vrhel-objects").resample(np.arange(400, 701, 10.0))
    r = np.asarray(refl.values, np.float64)
    mean = r.mean(axis=0)
    _, _, vt = np.linalg.svd(r - mean, full_matrices=False)
    basis = vt[:3]  # (3, 31)
    wl = np.arange(400, 701, 10.0)
    import colour

    d65 = np.asarray(colour.SDS_ILLUMINANTS["D65"].copy().align(colour.SpectralShape(400, 700, 10)).values)
    white = spectra_to_linear_srgb((d65)[None], wl)[0]
    to_rgb = spectra_to_linear_srgb(basis * d65, wl) / white  # (3, 3): rgb of each component
    rgb_mean = spectra_to_linear_srgb((mean * d65)[None], wl)[0] / white
    img = coffee()[:, 100:500]
    img = cv2.resize(img, (size_px, size_px), interpolation=cv2.INTER_AREA).astype(np.float64) / 255.0
    lin = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)
    weights = (lin.reshape(-1, 3) - rgb_mean) @ np.linalg.inv(to_rgb)
    cube = np.clip(mean + weights @ basis, 0.0, 1.0).reshape(size_px, size_px, -1)
    return cube.astype(np.float32), wl


def panel_mask(scene: CubeOnWallScene, base: ProceduralOutdoorScene, height: int, width: int,
               inset_px: int = 2) -> np.ndarray:
    """Pixels of the product's grid whose centre ray meets the panel, ``inset_px`` in from its border."""
    import cv2

    lat = 90 - (np.arange(height) + 0.5) / height * 180
    lon = (np.arange(width) + 0.5) / width * 360 - 180
    rays = lonlat_to_ray(*np.meshgrid(lon, lat)).reshape(-1, 3)
    one = np.ones((1, scene.wavelength_nm.size), np.float32)
    differs = np.abs(scene.band_radiance(rays, one, sun_disk=False) - base.band_radiance(rays, one))
    mask = (differs.reshape(height, width, -1).max(axis=-1) > 0).astype(np.uint8)
    return cv2.erode(mask, np.ones((2 * inset_px + 1, 2 * inset_px + 1), np.uint8)) > 0


def true_spectra(scene, rows: np.ndarray, cols: np.ndarray, height: int, width: int, scale: float) -> np.ndarray:
    """The scene's spectra as the mean of 8 × 8 rays per pixel (``REFINE_RAYS_PER_SIDE``: what the truth's bands
    take where a pixel's first rays disagree, as on most of a textured panel), each filtering the texture over
    its share of the pixel, in the truth's units."""
    n = REFINE_RAYS_PER_SIDE
    acc = 0.0
    for dy in subpixel_offsets(n) + 0.5:
        for dx in subpixel_offsets(n) + 0.5:
            lat = 90 - (rows + dy) / height * 180
            lon = (cols + dx) / width * 360 - 180
            acc = acc + scene.spectral_radiance(lonlat_to_ray(lon, lat), sun_disk=False, **footprint_kwargs(
                scene, equirect_ray_spread_rad(lat, width, height, n)))
    return acc / (n * n) * scale


def unit_nrmse(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-row RMS difference of the unit-norm spectra (scale removed)."""
    an = a / np.linalg.norm(a, axis=-1, keepdims=True)
    bn = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.sqrt(((an - bn) ** 2).mean(axis=-1)) / np.sqrt((bn ** 2).mean(axis=-1))


#: Camera B of the ``small`` preset changed to isolate what makes its error differ from A's (``--b-variant``):
#: the rig file's text replacements, and whether B carries the simulator's unknown mounting error (seed 0).
B_VARIANTS = {
    "rig": ((), True),
    "known-mounting": ((), False),
    "a-filter": ((('filter = "sp18-standin"', 'filter = "wratten-34a"'),), False),
    "a-filter-no-angles": ((('filter = "sp18-standin"', 'filter = "wratten-34a"'), ("yaw_deg = 0.15", "yaw_deg = 0.0"),
                            ("pitch_deg = -0.08", "pitch_deg = 0.0"), ("roll_deg = 0.05", "roll_deg = 0.0")), False),
    "a-twin": ((('filter = "sp18-standin"', 'filter = "wratten-34a"'), ("yaw_deg = 0.15", "yaw_deg = 0.0"),
                ("pitch_deg = -0.08", "pitch_deg = 0.0"), ("roll_deg = 0.05", "roll_deg = 0.0"),
                ("baseline_mm = [60.0, 0.0, 0.0]", "baseline_mm = [0.0, 0.0, 0.0]")), False),
}


def variant_rig(variant: str):
    """The ``small`` preset with camera B changed as :data:`B_VARIANTS` says, and B's mounting error (deg)."""
    replacements, unknown_error = B_VARIANTS[variant]
    rig = load_preset("small")
    if not replacements:
        return rig, (DEFAULT_MOUNTING_ERROR_DEG if unknown_error else 0.0)
    text = rig.toml_text
    for old, new in replacements:
        if old not in text:
            raise SystemExit(f"bench_texture: the small preset no longer has {old!r}; update B_VARIANTS")
        text = text.replace(old, new)
    return rig_from_dict(tomllib.loads(text), f"small ({variant})", text), 0.0


def simulate(out: Path, cube, placement: str, noise: bool, b_variant: str = "rig"):
    """Simulate the ``small`` preset (B as ``b_variant`` says) at noon with ``cube`` at ``placement``; (scene,
    base scene, seconds)."""
    base = ProceduralOutdoorScene(time_hhmm="12:00", day_of_year=172)
    wall, lon, lat, width_m = PLACEMENTS[placement]
    scene = CubeOnWallScene(cube, base=base, wall=wall, lon_deg=lon, lat_deg=lat, width_m=width_m)
    rig, mounting_error_deg = variant_rig(b_variant)
    t0 = time.perf_counter()
    simulate_session(out / "s", rig, scene, start=NOON, noise=noise, progress=False,
                     mounting_error_deg=mounting_error_deg)
    return scene, base, time.perf_counter() - t0


def measure(out: Path, scene, base, placement: str, noise: bool, interp: str | None = None) -> dict:
    """Process ``out/s`` (``interp``: the mosaic's interpolation, ``None`` the default) and measure the panel."""
    t1 = time.perf_counter()
    product = out / f"p-{interp or 'default'}"
    process(out / "s", product, interp=interp, truth=GroundTruth.of_session(out / "s"), progress=False)
    t2 = time.perf_counter()
    _, store, est = open_product(product)
    bands = store.read(0)
    truth = np.load(out / "s" / "ground_truth" / "bands.npy", mmap_mode="r")
    h, w = bands.shape[:2]
    mask = panel_mask(scene, base, h, w)
    rows, cols = np.nonzero(mask)
    p, t = bands[mask].astype(np.float64), np.asarray(truth[rows, cols], np.float64)
    rel = np.abs(p - t) / np.maximum(t, 1e-12)
    scale = json.loads((out / "s" / "ground_truth" / "ground_truth.json").read_text())["dn_per_second_per_unit"]
    spec_t = true_spectra(scene, rows, cols, h, w, scale)
    est_p, est_t = est.estimate(p.astype(np.float32)), est.estimate(t.astype(np.float32))
    added, floor = unit_nrmse(est_p, est_t), unit_nrmse(est_t, spec_t)
    a_err, b_err = float(np.median(rel[:, :3])), float(np.median(rel[:, 3:]))
    distance_m = round(float(np.linalg.norm(scene.centre_m)), 2)
    return {"placement": placement, "interp": interp or "default", "distance_m": distance_m, "noise": noise,
            "panel_px": int(mask.sum()),
            "a_band_error": a_err, "b_band_error": b_err, "b_over_a": b_err / a_err,
            "spectral_added_nrmse": float(np.median(added)), "estimator_floor_nrmse": float(np.median(floor)),
            "added_over_floor": float(np.median(added) / np.median(floor)),
            "holes": int((~np.isfinite(bands[mask])).any(axis=-1).sum()),
            "process_s": round(t2 - t1, 1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cube", action="append", default=None, help="reflectance cube file (repeatable)")
    ap.add_argument("--placement", nargs="+", default=list(PLACEMENTS), choices=list(PLACEMENTS))
    ap.add_argument("--noise", nargs="+", default=["on"], choices=["on", "off"])
    ap.add_argument("--interp", nargs="+", default=[None], choices=[None, *INTERP_NAMES],
                    help="the mosaic's interpolation(s), each on the same simulated frames (default: process's)")
    ap.add_argument("--b-variant", nargs="+", default=["rig"], choices=list(B_VARIANTS),
                    help="camera B as the preset has it, or changed towards A's (B_VARIANTS)")
    ap.add_argument("--out", default="/tmp/bench_texture")
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)
    cubes = [(c, c) for c in args.cube] if args.cube else [("coffee (photo texture, Vrhel PCs)", photo_cube())]
    print(f"load {os.getloadavg()[0]:.1f}", file=sys.stderr)
    rows = []
    for name, cube in cubes:
        for d in args.placement:
            for n, variant in itertools.product(args.noise, args.b_variant):
                out = Path(args.out) / f"{len(rows)}"
                scene, base, simulate_s = simulate(out, cube, d, n == "on", variant)
                for interp in args.interp:
                    res = {"cube": str(name), "b_variant": variant,
                           **measure(out, scene, base, d, n == "on", interp), "simulate_s": round(simulate_s, 1)}
                    rows.append(res)
                    print(json.dumps(res), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
