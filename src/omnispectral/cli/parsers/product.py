"""``omnispectral process | process-series | spectrum | export | report | product verify | demo | calibrate rig``: the
arguments;
run by :mod:`omnispectral.cli.product`."""

from __future__ import annotations

import argparse
import math

from omnispectral.choices import (
    DEFAULT_HDR_WEIGHT,
    DEFAULT_INTERP,
    DEFAULT_REGISTRATION,
    FORMATS,
    HDR_WEIGHT_NAMES,
    INTERP_NAMES,
    PRESETS,
    REGISTRATION_NAMES,
    SUN_METHOD_NAMES,
)
from omnispectral.cli.parsers import seed_arg
from omnispectral.cli.parsers.lens import board_arg, calibrate_group, positive_mm_arg

__all__ = ["add_commands", "degrees_in"]


def degrees_in(low: float, high: float):
    """argparse type: a finite angle in ``[low, high]`` degrees (out of range is a usage error, never wrapped)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number of degrees") from None
        if not (math.isfinite(value) and low <= value <= high):
            raise argparse.ArgumentTypeError(f"{text} is outside {low:g}..{high:g} degrees")
        return value

    return parse


def add_commands(sub) -> None:
    """Register ``process``, ``process-series``, ``spectrum``, ``export``, ``report``, ``product verify``, ``demo``
    and ``calibrate rig``."""

    c = calibrate_group(sub).add_parser(
        "rig", help="camera B's mounting relative to camera A, from a session's images or from chessboard pairs",
        description="Fits camera B's rotation relative to A. From a SESSION: block correspondences of every "
                    "direction (residuals across the epipolar lines; the farthest content taken to be at infinity, "
                    "so B's yaw is only as good as that content is far). From --chessboard DIR: pairs of images of "
                    "a chessboard both cameras saw at once (DIR/A/NAME and DIR/B/NAME; stereo calibration with the "
                    "rig file's lenses), which fixes the yaw too. The file is reused with "
                    "'process --rig-calibration'.")
    c.add_argument("session", metavar="SESSION", nargs="?", default=None)
    c.add_argument("-o", "--output", required=True, metavar="FILE.json")
    c.add_argument("--work", default=None, metavar="DIR", help="keep the merged directions here (default: temporary)")
    c.add_argument("--chessboard", default=None, metavar="DIR",
                   help="chessboard pairs in DIR/A and DIR/B (same file names), e.g. from simulate-chessboard")
    c.add_argument("--board", type=board_arg, default=None, metavar="COLSxROWS",
                   help="inner corners of the chessboard (default: DIR/board.json)")
    c.add_argument("--square-mm", type=positive_mm_arg, default=None, metavar="S",
                   help="square side in mm (default: DIR/board.json)")
    c.add_argument("--refine-baseline", action="store_true",
                   help="fit B's baseline too (default: the rig file's; the fit's spread grows)")
    g = c.add_mutually_exclusive_group()
    g.add_argument("--preset", choices=PRESETS, default=None, help="with --chessboard: a built-in rig (default: "
                                                                   "DIR/rig.toml)")
    g.add_argument("--rig", default=None, metavar="FILE.toml", help="with --chessboard: the rig file (default: "
                                                                   "DIR/rig.toml)")
    c.add_argument("--json", action="store_true", help="print the calibration as JSON")
    c.set_defaults(func="omnispectral.cli.product:cmd_calibrate_rig")

    p = sub.add_parser("process", help="a capture session into an HDR six-band panorama with its estimator",
                       description="HDR merge per direction and camera; camera B's mounting from --rig-calibration, "
                                   "else the chessboard views recorded with the session (SESSION/calibration/), else "
                                   "fitted from the session's own images (then a warning says, per direction, how "
                                   "far off far content may be), and per-pixel parallax (or the paper's one POC "
                                   "offset per direction); mosaic into a six-band Zarr panorama with a "
                                   "registration-quality layer; Wiener estimator attached; report. Resumable: a rerun "
                                   "re-checks the merged files and the panorama's chunks against their checksums "
                                   "and makes again what is missing or damaged ('product verify' checks without "
                                   "repairing).")
    p.add_argument("session", metavar="SESSION")
    p.add_argument("-o", "--output", required=True, metavar="PRODUCT", help="product directory")
    p.add_argument("--width", type=int, default=None, help="panorama width in px (default: the sensor's resolution)")
    p.add_argument("--tile", type=int, default=None, help="tile side in px")
    p.add_argument("--interp", default=DEFAULT_INTERP, choices=INTERP_NAMES,
                   help=f"interpolation (default {DEFAULT_INTERP}: no overshoot on small targets; also the "
                        f"default of 'mosaic')")
    p.add_argument("--hdr-weight", default=DEFAULT_HDR_WEIGHT, choices=HDR_WEIGHT_NAMES,
                   help="HDR weight (default inverse variance; 'triangle' is the paper's Eq. (2))")
    p.add_argument("--registration", default=DEFAULT_REGISTRATION, choices=REGISTRATION_NAMES,
                   help="camera B to A: rig calibration + per-pixel parallax (default), or the paper's one POC "
                        "offset per direction")
    p.add_argument("--rig-calibration", default=None, metavar="FILE.json",
                   help="camera B's mounting from 'omnispectral calibrate rig' (default: from the chessboard views "
                        "in SESSION/calibration/, or the series' for a time-lapse slot, fitted once and cached there; "
                        "without views, fitted from this session's own images)")
    p.add_argument("--no-calibration-views", action="store_true",
                   help="fit camera B's mounting from this session's own images even where chessboard views are")
    p.add_argument("--sun", default="auto", choices=list(SUN_METHOD_NAMES),
                   help="how the saturated sun is recovered: auto (the attenuated bracket when the session has "
                        "one, else the diffuse reference if given, else the clear-sky model), nd-bracket, "
                        "diffuse-reference, sky-model (a model estimate fitted to the sky), or none (keep the "
                        "lower bound)")
    p.add_argument("--sun-reference", default=None, metavar="LON,LAT[,normal=AZ/EL][,reflectance=R|FILE.csv]",
                   help="a white or grey target lit by the sun, where it is in the panorama (degrees; a negative "
                        "longitude as --sun-reference=-20,-45); default a horizontal target of reflectance 0.95")
    p.add_argument("--min-confidence", type=float, default=None, help="with --registration paper: POC confidence "
                                                                      "below which the calibrated offset is used")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="Dask distributed scheduler address")
    p.add_argument("--skip-bad", action="store_true",
                   help="leave out directions with missing or damaged frames instead of stopping")
    p.add_argument("--sizes-only", action="store_true",
                   help="check frame sizes against the journal only (faster; a same-size corrupted frame is missed)")
    p.add_argument("--overwrite", action="store_true",
                   help="rebuild a product whose intermediates were made from other inputs or settings")
    p.add_argument("--json", action="store_true", help="print the product index as JSON")
    p.set_defaults(func="omnispectral.cli.product:cmd_process")

    ps = sub.add_parser("process-series", help="process a time-lapse series; region spectra over the day",
                        description="Process every complete slot of a time-lapse series, stack the panoramas in "
                                    "time and estimate the spectral power distribution of regions (sky, a wall) at "
                                    "every time (paper Fig. 13) as JSON and PNG.")
    ps.add_argument("series", metavar="SERIES")
    ps.add_argument("-o", "--output", required=True, metavar="OUT")
    ps.add_argument("--rig-calibration", default=None, metavar="FILE.json",
                    help="camera B's mounting for every slot (default: the series' chessboard views in "
                         "SERIES/calibration/, else fitted on the first slot and reused)")
    ps.add_argument("--region", action="append", default=None, metavar="NAME:LON0,LON1,LAT0,LAT1",
                    help="region to analyse (repeat; default: sky 45-75° and ground -75 to -45° all around)")
    ps.add_argument("--json", action="store_true")
    ps.set_defaults(func="omnispectral.cli.product:cmd_process_series")

    s = sub.add_parser("spectrum", help="the estimated spectrum at a direction of a product",
                       description="Six bands, Wiener spectrum and its posterior std at a longitude/latitude.")
    s.add_argument("product", metavar="PRODUCT")
    s.add_argument("--lon", type=degrees_in(-180, 180), required=True, help="longitude in degrees (-180..180, 0 = +Z)")
    s.add_argument("--lat", type=degrees_in(-90, 90), required=True, help="latitude in degrees (-90..90)")
    s.add_argument("--level", type=int, default=0, help="pyramid level")
    fmt = s.add_mutually_exclusive_group()
    fmt.add_argument("--json", action="store_true")
    fmt.add_argument("--csv", action="store_true",
                     help="print CSV: one row per wavelength (wavelength_nm, spectrum, std: the posterior σ)")
    s.set_defaults(func="omnispectral.cli.product:cmd_spectrum")

    e = sub.add_parser("export", help="standard files from a product",
                       description="Spectral OpenEXR (Fichet 2021), ENVI, linear RGB EXR / Radiance HDR for "
                                   "image-based lighting, sRGB PNG/JPEG preview, uncertainty map; by region or level.")
    e.add_argument("product", metavar="PRODUCT")
    e.add_argument("--format", required=True, choices=FORMATS)
    e.add_argument("-o", "--output", required=True, metavar="FILE")
    e.add_argument("--region", type=int, nargs=4, default=None, metavar=("ROW0", "ROW1", "COL0", "COL1"),
                   help="pixel window of the chosen level")
    e.add_argument("--level", type=int, default=0, help="pyramid level (0 = full size)")
    e.add_argument("--half", action="store_true", help="spectral EXR in 16-bit floats (half the size)")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func="omnispectral.cli.product:cmd_export")

    r = sub.add_parser("report", help="(re)write the report of a product",
                       description="Preview, timings, registration per direction and, for simulated sessions, "
                                   "accuracy against the ground truth (JSON + HTML).")
    r.add_argument("product", metavar="PRODUCT")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func="omnispectral.cli.product:cmd_report")

    pr = sub.add_parser("product", help="check products", description="Check products.")
    prsub = pr.add_subparsers(dest="product_command", metavar="SUBCOMMAND", required=True)
    v = prsub.add_parser("verify", help="check every panorama chunk and merged file of a product against its checksum",
                         description="Checks every merged image and parallax map and every chunk of every level of "
                                     "the panorama (and its quality layer) for presence and against the size and "
                                     "CRC-32 recorded when it was written; prints one line per problem and a "
                                     "summary. Cost: one read of every file, about 1 s per GB from the page cache "
                                     "(measured on a 40 MB product), bounded by the disk's read speed otherwise. "
                                     "'process' on the product repairs what it finds. Exit status 1 when anything "
                                     "is missing or damaged.")
    v.add_argument("product", metavar="PRODUCT")
    v.add_argument("--json", action="store_true", help="print the report as JSON")
    v.set_defaults(func="omnispectral.cli.product:cmd_product_verify")

    d = sub.add_parser("demo", help="simulate, process, export and report in one go",
                       description="Simulate the paper's time-lapse geometry on the procedural scene (reduced "
                                   "sensor unless --full), process it, export, and print the accuracy table.")
    d.add_argument("-o", "--output", "--out", dest="out", default="demo-output",
                   help="output directory (default demo-output/)")
    d.add_argument("--full", action="store_true", help="the paper's full scale (2048×1088 sensors)")
    d.add_argument("--time", default="12:00", metavar="HH:MM", help="time of day of the scene")
    d.add_argument("--seed", type=seed_arg, default=0, help="the simulation's seed (0 to 2^32 - 1)")
    d.set_defaults(func="omnispectral.cli.product:cmd_demo")
