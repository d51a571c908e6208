"""``omnispectral process | spectrum | export | report | demo``: from a session to a spectral panorama and files."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from rich.markup import escape
from rich.table import Table

from omnispectral.apps.demo import run_demo
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.cli.capture import rig_from_args
from omnispectral.cli.lens import board_arg, calibrate_group, positive_mm_arg
from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.interp import METHODS
from omnispectral.product.exports import FORMATS, export_product
from omnispectral.product.process import DEFAULT_INTERP, process
from omnispectral.product.report import write_report
from omnispectral.product.rigboard import calibrate_chessboard_folder
from omnispectral.product.rigcal import calibrate_session
from omnispectral.product.series import DEFAULT_REGIONS, parse_region, process_series
from omnispectral.product.spectra import spectrum_at
from omnispectral.product.sun_methods import SUN_METHODS
from omnispectral.product.sun_reference import parse_sun_reference
from omnispectral.rig import PRESETS


def cmd_process(args) -> int:
    with ProgressBars(enabled=not args.json) as bars:
        index = process(args.session, args.output, width=args.width, tile=args.tile, interp=args.interp,
                        scheduler=args.scheduler, skip_bad=args.skip_bad, min_confidence=args.min_confidence,
                        hdr_weight=args.hdr_weight, progress=bars, verify_checksums=not args.sizes_only,
                        registration=args.registration, rig_calibration=args.rig_calibration,
                        overwrite=args.overwrite, sun=args.sun, calibration_views=not args.no_calibration_views,
                        sun_reference=parse_sun_reference(args.sun_reference) if args.sun_reference else None)
    if args.json:
        print_json(index)
        return 0
    _print_summary(index)
    return 0


def _registration_summary(registration: dict) -> str:
    """How camera B was registered, in a few words."""
    if registration.get("method") == "parallax":
        d = registration["rig_calibration"]["delta_from_rig_file_deg"]
        return (f"camera B {d['yaw']:+.3f}° yaw, {d['pitch']:+.3f}° pitch, {d['roll']:+.3f}° roll from the rig "
                "file, per-pixel parallax")
    reg = registration["directions"]
    n_fb = sum(a["used_fallback"] for a in reg)
    return f"camera B registered by POC in {len(reg) - n_fb}, calibrated offset in {n_fb}"


def _print_summary(index: dict) -> None:
    registration = index["registration"]
    reg = registration["directions"]
    n_bands = len(index.get("bands") or ()) or 6
    skipped = f"{len(index['skipped_directions'])} directions skipped as bad"
    if n_bands != 6:
        what = f"{n_bands}-band panorama of {index['rig']} (one camera: nothing to register; {skipped})"
    else:
        what = f"six-band panorama of {index['rig']} ({len(reg)} directions; {_registration_summary(registration)}; "
        what += f"{skipped})"
    console.print(f"[bold]{index['width']}×{index['height']}[/bold] {what}.")
    source = registration.get("rig_calibration_source")
    if source:
        console.print(f"Calibration: {escape(source['description'])}.")
    far_warning = (registration.get("far_content") or {}).get("warning")
    for w in registration.get("warnings", []):
        if w != far_warning:  # said last, below
            console.print(f"[yellow]warning:[/yellow] {escape(w)}")
    _print_sun(index.get("sun") or {})
    t = Table(title="Timings")
    for k in index["timings_s"]:
        t.add_column(k, justify="right")
    t.add_row(*(f"{v:.1f} s" for v in index["timings_s"].values()))
    console.print(t)
    for d in index["skipped_directions"]:
        console.print(f"[yellow]skipped direction {d['direction']}:[/yellow] {'; '.join(d['problems'][:3])}")
    if far_warning:
        console.print(f"[bold yellow]warning:[/bold yellow] {escape(far_warning)}")


def _print_sun(sun: dict) -> None:
    """One line on the sun: how it was recovered and where, or that the panorama holds a lower bound."""
    if sun.get("recovered"):
        how = f"{sun['method']}, {sun['filter']}" if sun.get("filter") else sun["method"]
        console.print(f"sun recovered ({how}): lon {sun['lon_deg']:.2f}°, lat {sun['lat_deg']:.2f}°, "
                      f"{sun.get('n_pixels_painted', 0)} panorama pixels hold it ({sun['file']}).")
        if sun.get("model_estimate"):
            console.print(f"[yellow]warning:[/yellow] the sun is a model estimate, not a measurement: "
                          f"{escape(sun.get('note', ''))}")
    elif sun.get("method") is not None and sun.get("note"):
        console.print(f"[yellow]sun:[/yellow] {escape(sun['note'])}")


def _print_irradiance(irr: dict) -> None:
    """The panorama's horizontal irradiance against the truth's (simulated sessions), and the sun's share."""
    ratio = irr.get("ratio_to_truth")
    if not ratio:
        return
    worst = irr["worst_band"]
    share = irr.get("sun_fraction")
    console.print(f"Horizontal irradiance of the panorama / the truth's: {min(ratio):.3f}–{max(ratio):.3f} over the "
                  f"bands (worst {worst['name']} {worst['ratio_to_truth']:.3f})"
                  + (f"; the sun carries {100 * min(share):.0f}–{100 * max(share):.0f} % of it." if share else "."))


def cmd_spectrum(args) -> int:
    out = spectrum_at(args.product, args.lon, args.lat, level=args.level)
    if args.json:
        print_json(out)
        return 0
    if args.csv:
        sys.stdout.write("wavelength_nm,spectrum,std\n")
        for wl, v, s in zip(out["wavelength_nm"], out["spectrum"], out["std"], strict=True):
            sys.stdout.write(f"{wl:g},{v:.9g},{s:.9g}\n")
        return 0
    console.print(f"lon {out['lon_deg']:.3f}°, lat {out['lat_deg']:.3f}° (pixel {out['pixel'][0]:.1f}, "
                  f"{out['pixel'][1]:.1f} of level {out['level']}); bands "
                  + ", ".join(f"{k} {v:.4g}" for k, v in out["bands"].items()))
    if out.get("warning"):
        console.print(f"[yellow]warning:[/yellow] {escape(out['warning'])}")
    t = Table(title=f"Estimated spectrum ({out['units']})")
    for col in ("λ (nm)", "value", "± std"):
        t.add_column(col, justify="right")
    for wl, v, s in list(zip(out["wavelength_nm"], out["spectrum"], out["std"], strict=True))[::4]:
        t.add_row(f"{wl:.0f}", f"{v:.4g}", f"{s:.2g}")
    console.print(t)
    return 0


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


def cmd_export(args) -> int:
    out = export_product(args.product, args.format, args.output,
                         tuple(args.region) if args.region else None, args.level, half=args.half)
    if args.json:
        print_json(out)
    else:
        console.print(f"Wrote {out['output']} ({out['format']}, {out['width']}×{out['height']} px of level "
                      f"{out['level']})")
        sat = out.get("saturation")
        if sat:
            console.print(f"{sat['saturated_px'] if sat['known'] else 'unknown:'} px saturated in every exposure "
                          f"(lower bounds), {sat['clipped_estimate_px']} px more whose estimate was clipped at 0: "
                          f"{sat['mask']}")
    return 0


def cmd_report(args) -> int:
    rep = write_report(args.product)
    if args.json:
        print_json(rep["report"])
    else:
        _print_accuracy(rep["report"].get("accuracy"), rep["report"].get("holes"))
        console.print(f"Report: {rep['files']['html']} and {rep['files']['json']}")
    return 0


def _print_accuracy(acc: dict | None, holes: dict | None = None) -> None:
    if not acc:
        console.print("No ground truth: accuracy not measured (not a simulated session).")
        return
    t = Table(title="Accuracy against the simulator's ground truth")
    for col in ("measure", "value", "spectral core (chart level)"):
        t.add_column(col, justify="right" if col != "measure" else "left")
    t.add_row(f"{acc['n_bands']}-band PSNR", f"{acc['band_psnr_db']:.2f} dB", "")
    t.add_row("spectral NRMSE (whole panorama)", f"{acc['spectral_nrmse']:.4f}", "")
    cc = acc.get("colorchecker")
    if cc:  # the spectral core's chart-level figures (README): six bands, or an unfiltered RGB camera
        six = acc["n_bands"] == 6
        t.add_row("ColorChecker NRMSE", f"{cc['nrmse']:.4f}", "0.0128 (paper 0.0148)" if six else
                  "RGB 0.0255 (paper 0.0530)")
        t.add_row("ColorChecker ΔE*ab mean / max", f"{cc['delta_e_ab']:.2f} / {cc['delta_e_ab_max']:.2f}",
                  "0.87 / 2.56 (paper 1.49)" if six else "RGB 5.67 (paper 6.12)")
        for x in cc.get("not_uniformly_lit", []):
            t.add_row(f"  not scored: {x['name']}", f"ΔE*ab {x['delta_e_ab']:.2f}",
                      f"shadow edge across the patch (radiance spread {x['radiance_spread']:.0%})")
    edges = (acc.get("pixel_errors") or {}).get("depth_edges")
    if edges:  # where the aggregates do not look (product.report_edges)
        e, s_ = edges["edge"], edges["smooth"]
        t.add_row("band NRMSE at depth edges / smooth", f"{e['band_nrmse']:.3f} / {s_['band_nrmse']:.4f}",
                  f"within {edges['radius_px']:g} px of a depth step")
        t.add_row("ΔE*ab at depth edges / smooth", f"{e['delta_e_ab']:.2f} / {s_['delta_e_ab']:.2f}",
                  "the pipeline's, same estimator")
    if holes is not None:
        t.add_row("holes (covered, a band missing)", f"{holes['n_pixels']}", "")
    console.print(t)


def cmd_demo(args) -> int:
    out = Path(args.out)

    def step(k: int, n: int, text: str) -> None:
        verb, _, rest = text.partition(" ")
        console.print(f"[bold]{k}/{n} {verb}[/bold]" + (f" {rest}" if rest else ""))

    with ProgressBars() as bars:
        summary = run_demo(out, full=args.full, time_hhmm=args.time, seed=args.seed, on_step=step, progress=bars)
    _print_accuracy(summary["accuracy"], summary.get("holes"))
    cal = summary.get("rig_calibration") or {}
    if cal.get("source"):
        console.print(f"Calibration: {escape(cal['source'])}; far content may be off by up to "
                      f"{cal['far_content_max_px']:.2f} px (worst direction)." if cal.get("far_content_max_px")
                      is not None else
                      f"Calibration: {escape(cal['source'])}.")
    if cal.get("warning"):
        console.print(f"[bold yellow]warning:[/bold yellow] {escape(cal['warning'])}")
    _print_sun(summary.get("sun") or {})
    _print_irradiance(summary.get("irradiance") or {})
    console.print(f"Done in {summary['total_s']:.0f} s. Everything is in {out}/:")
    for label, path in (("session (raw frames, journal, ground truth)", summary["session"]),
                        ("product (six-band Zarr panorama + estimator)", summary["product"]),
                        ("report (HTML)", summary["report_html"]),
                        ("report (JSON)", out / "report.json"), *summary["exports"].items()):
        console.print(f"  {label}: {path}")
    return 0


def cmd_process_series(args) -> int:
    regions = dict(parse_region(r) for r in args.region) if args.region else dict(DEFAULT_REGIONS)
    with ProgressBars(enabled=not args.json) as bars:
        out = process_series(args.series, args.output, regions, progress=bars, rig_calibration=args.rig_calibration)
    if args.json:
        print_json(out)
    else:
        console.print(f"{out['n_slots']} time slots processed into {out['output']}; time stack {out['timestack']} "
                      f"{tuple(out['stack_shape'])}; region spectra (Fig. 13) {out['region_spectra']} and "
                      f"{out['plot']}")
        source = out.get("rig_calibration_source")
        if source:
            console.print(f"Calibration (first slot): {escape(source['description'])}.")
        for slot, line in out.get("far_content_warnings", {}).items():
            console.print(f"[bold yellow]warning:[/bold yellow] {escape(slot)}: {escape(line)}")
    return 0


def cmd_calibrate_rig(args) -> int:
    if (args.session is None) == (args.chessboard is None):
        raise ConfigurationError("give either a SESSION (fit from its images) or --chessboard DIR (chessboard "
                                 "pairs)")
    if args.chessboard is not None:
        rig = rig_from_args(args) if (args.preset or args.rig) else None
        cal = calibrate_chessboard_folder(args.chessboard, args.output, board=args.board, square_mm=args.square_mm,
                                          rig=rig, refine_baseline=args.refine_baseline)
    else:
        cal = calibrate_session(args.session, args.output, args.work)
    if args.json:
        print_json(cal.to_dict())
        return 0
    d = cal.delta_deg
    change = f"yaw {d[0]:+.4f}°, pitch {d[1]:+.4f}°, roll {d[2]:+.4f}° from the rig file"
    if cal.method == "chessboard":
        cb = cal.chessboard
        sd = cb["std_deg"]
        console.print(f"Camera B's mounting from {cb['n_pairs']} chessboard pairs ({cal.n_blocks} corners): {change} "
                      f"(± {sd['yaw']:.4f}°, {sd['pitch']:.4f}°, {sd['roll']:.4f}°); corner residual RMS "
                      f"A {cb['rms_a_px']:.3f} px, B {cb['rms_b_px']:.3f} px; baseline "
                      f"{', '.join(f'{x:.2f}' for x in cal.mounting['baseline_mm'])} mm"
                      f"{' (refined)' if cb['baseline_refined'] else ' (rig file)'}.")
        for r in cb["rejected"]:
            console.print(f"[yellow]skipped:[/yellow] {escape(r['name'])}: {escape(r['why'])}")
    else:
        console.print(f"Camera B's mounting from {cal.n_inliers} of {cal.n_blocks} block measurements: {change}; "
                      f"RMS residual across the epipolar lines {cal.rms_perpendicular_px:.3f} px; infinity anchored on "
                      f"{cal.far_anchor.get('n_blocks', 0)} blocks (the yaw is only as good as that content is far: "
                      "chessboard pairs fix it, 'calibrate rig --chessboard').")
    for w in cal.warnings():
        console.print(f"[yellow]warning:[/yellow] {escape(w)}")
    console.print(f"Written: {args.output} (use: omnispectral process SESSION -o PRODUCT --rig-calibration "
                  f"{args.output})")
    return 0


def add_commands(sub) -> None:
    """Register ``process``, ``process-series``, ``spectrum``, ``export``, ``report``, ``demo`` and
    ``calibrate rig``."""

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
    c.set_defaults(func=cmd_calibrate_rig)

    p = sub.add_parser("process", help="a capture session into an HDR six-band panorama with its estimator",
                       description="HDR merge per direction and camera; camera B's mounting from --rig-calibration, "
                                   "else the chessboard views recorded with the session (SESSION/calibration/), else "
                                   "fitted from the session's own images (then a warning says, per direction, how "
                                   "far off far content may be), and per-pixel parallax (or the paper's one POC "
                                   "offset per direction); mosaic into a six-band Zarr panorama with a "
                                   "registration-quality layer; Wiener estimator attached; report. Resumable.")
    p.add_argument("session", metavar="SESSION")
    p.add_argument("-o", "--output", required=True, metavar="PRODUCT", help="product directory")
    p.add_argument("--width", type=int, default=None, help="panorama width in px (default: the sensor's resolution)")
    p.add_argument("--tile", type=int, default=None, help="tile side in px")
    p.add_argument("--interp", default=DEFAULT_INTERP, choices=METHODS,
                   help=f"interpolation (default {DEFAULT_INTERP}: no overshoot on small targets; also the "
                        f"default of 'mosaic')")
    p.add_argument("--hdr-weight", default="noise", choices=["noise", "triangle"],
                   help="HDR weight (default inverse variance; 'triangle' is the paper's Eq. (2))")
    p.add_argument("--registration", default="parallax", choices=["parallax", "paper"],
                   help="camera B to A: rig calibration + per-pixel parallax (default), or the paper's one POC "
                        "offset per direction")
    p.add_argument("--rig-calibration", default=None, metavar="FILE.json",
                   help="camera B's mounting from 'omnispectral calibrate rig' (default: from the chessboard views "
                        "in SESSION/calibration/, or the series' for a time-lapse slot, fitted once and cached there; "
                        "without views, fitted from this session's own images)")
    p.add_argument("--no-calibration-views", action="store_true",
                   help="fit camera B's mounting from this session's own images even where chessboard views are")
    p.add_argument("--sun", default="auto", choices=list(SUN_METHODS),
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
    p.add_argument("--verify-checksums", action="store_true",
                   help="check every frame's SHA-256 and decode it first (the default; kept for old scripts)")
    p.add_argument("--sizes-only", action="store_true",
                   help="check frame sizes against the journal only (faster; a same-size corrupted frame is missed)")
    p.add_argument("--overwrite", action="store_true",
                   help="rebuild a product whose intermediates were made from other inputs or settings")
    p.add_argument("--json", action="store_true", help="print the product index as JSON")
    p.set_defaults(func=cmd_process)

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
    ps.set_defaults(func=cmd_process_series)

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
    s.set_defaults(func=cmd_spectrum)

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
    e.set_defaults(func=cmd_export)

    r = sub.add_parser("report", help="(re)write the report of a product",
                       description="Preview, timings, registration per direction and, for simulated sessions, "
                                   "accuracy against the ground truth (JSON + HTML).")
    r.add_argument("product", metavar="PRODUCT")
    r.add_argument("--json", action="store_true")
    r.set_defaults(func=cmd_report)

    d = sub.add_parser("demo", help="simulate, process, export and report in one go",
                       description="Simulate the paper's time-lapse geometry on the procedural scene (reduced "
                                   "sensor unless --full), process it, export, and print the accuracy table.")
    d.add_argument("-o", "--output", "--out", dest="out", default="demo-output",
                   help="output directory (default demo-output/)")
    d.add_argument("--full", action="store_true", help="the paper's full scale (2048×1088 sensors)")
    d.add_argument("--time", default="12:00", metavar="HH:MM", help="time of day of the scene")
    d.add_argument("--seed", type=int, default=0)
    d.set_defaults(func=cmd_demo)
