"""``omnispectral process | spectrum | export | report | product verify | demo``: from a session to a spectral
panorama and files."""

from __future__ import annotations

import sys
from pathlib import Path

from rich.markup import escape
from rich.table import Table

from omnispectral.apps.demo import run_demo
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.cli.capture import rig_from_args
from omnispectral.errors import ConfigurationError
from omnispectral.product.exports import export_product
from omnispectral.product.layout import read_index
from omnispectral.product.process import process
from omnispectral.product.report import calibration_basis, write_report
from omnispectral.product.rigboard import calibrate_chessboard_folder
from omnispectral.product.rigsession import calibrate_session
from omnispectral.product.series import DEFAULT_REGIONS, parse_region, process_series
from omnispectral.product.spectra import spectrum_at
from omnispectral.product.sun_reference import parse_sun_reference
from omnispectral.product.verify import verify_product
from omnispectral.sim.truth import GroundTruth

__all__ = ["cmd_calibrate_rig", "cmd_demo", "cmd_export", "cmd_process", "cmd_process_series", "cmd_product_verify",
           "cmd_report", "cmd_spectrum"]


def cmd_process(args) -> int:
    with ProgressBars(enabled=not args.json) as bars:
        index = process(args.session, args.output, width=args.width, tile=args.tile, interp=args.interp,
                        scheduler=args.scheduler, skip_bad=args.skip_bad, min_confidence=args.min_confidence,
                        hdr_weight=args.hdr_weight, progress=bars, verify_checksums=not args.sizes_only,
                        registration=args.registration, rig_calibration=args.rig_calibration,
                        overwrite=args.overwrite, sun=args.sun, calibration_views=not args.no_calibration_views,
                        sun_reference=parse_sun_reference(args.sun_reference) if args.sun_reference else None,
                        truth=GroundTruth.of_session(args.session))
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


def _print_repaired(repaired: dict) -> None:
    """One line per kind of file a resumed run found missing or damaged (checksums) and made again."""
    for kind, noun, what in (("merged", "merged file", "merged again"), ("chunks", "panorama chunk", "rendered again")):
        items = repaired.get(kind) or []
        if items:
            names = ", ".join(Path(i["file"]).name if kind == "merged" else i["file"] for i in items[:5])
            more = f" and {len(items) - 5} more" if len(items) > 5 else ""
            plural = "s" if len(items) > 1 else ""
            console.print(f"[yellow]repaired:[/yellow] {len(items)} {noun}{plural} {what} ({escape(names)}{more}: "
                          f"{escape(items[0]['problem'])})", soft_wrap=True)
    if repaired.get("panorama_rebuilt"):
        console.print("[yellow]repaired:[/yellow] a merged file came out different: the panorama was rebuilt")


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
        basis = f": {calibration_basis(registration['rig_calibration'])}" if registration.get("rig_calibration") else ""
        console.print(f"Calibration: {escape(source['description'])}{escape(basis)}.")
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
    _print_repaired(index.get("repaired") or {})
    _print_accuracy_warnings(index.get("accuracy_warnings") or [])
    if far_warning:  # the last line (README): how far off far content may be
        console.print(f"[bold yellow]warning:[/bold yellow] {escape(far_warning)}")


def _print_accuracy_warnings(warnings: list[dict]) -> None:
    """One line per accuracy limit of the run (product.expectations): what is off, how much, what to do."""
    for w in warnings:
        console.print(f"[bold yellow]accuracy:[/bold yellow] {escape(w['message'])}")


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
    rep = write_report(args.product, truth=GroundTruth.of_session(read_index(args.product)["session"]))
    if args.json:
        print_json(rep["report"])
    else:
        _print_accuracy(rep["report"].get("accuracy"), rep["report"].get("holes"))
        console.print(f"Report: {rep['files']['html']} and {rep['files']['json']}")
        _print_accuracy_warnings(rep["report"].get("accuracy_warnings") or [])
    return 0


def _print_accuracy(acc: dict | None, holes: dict | None = None) -> None:
    if not acc:
        console.print("No readable ground truth: accuracy not measured (a real capture, or its truth is damaged).")
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

        def num(v, fmt: str) -> str:  # a region with no scored pixel has no figure
            return "–" if v is None else format(v, fmt)

        t.add_row("band NRMSE at depth edges / smooth", f"{num(e['band_nrmse'], '.3f')} / "
                  f"{num(s_['band_nrmse'], '.4f')}", f"within {edges['radius_px']:g} px of a depth step")
        t.add_row("ΔE*ab at depth edges / smooth", f"{num(e['delta_e_ab'], '.2f')} / {num(s_['delta_e_ab'], '.2f')}",
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
        out = process_series(args.series, args.output, regions, progress=bars, rig_calibration=args.rig_calibration,
                             truth_of=GroundTruth.of_session)
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


def cmd_product_verify(args) -> int:
    """``product verify``: one line per missing or damaged file, then a summary; exit 1 when there is any."""
    report = verify_product(args.product)
    if args.json:
        print_json(report)
    else:
        for problem in report["problems"]:
            console.print(escape(f"{problem['file']}: {problem['problem']}"), soft_wrap=True)
        state = "[green]all good[/green]" if report["ok"] else f"[red]{len(report['problems'])} problems[/red]"
        console.print(f"{escape(report['product'])}: {state}: {report['n_merged_files']} merged files and "
                      f"{report['n_chunks']} chunks checked ({report['bytes_checked'] / 1e6:.1f} MB in "
                      f"{report['seconds']:.2f} s)" + ("" if report["ok"] else
                                                       "; 'omnispectral process' on the product repairs them"),
                      soft_wrap=True)
    return 0 if report["ok"] else 1
