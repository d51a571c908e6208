"""``omnispectral simulate | capture | timelapse``: run the capture loop on the simulated rig (or a rig's devices)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from rich.markup import escape

from omnispectral.capture.boardviews import DEFAULT_BOARD, DEFAULT_SQUARE_MM
from omnispectral.capture.calviews import DEFAULT_N_VIEWS, calibration_folder
from omnispectral.capture.devices import FakeClock
from omnispectral.capture.drivers import rig_device_kind
from omnispectral.capture.hardware import capture_calibration_views, capture_darks, capture_with_devices, dry_run
from omnispectral.capture.scenes import DEFAULT_DATE, build_scene
from omnispectral.capture.simulate import simulate_board_views, simulate_session
from omnispectral.capture.timelapse import parse_hhmm, parse_interval_s, run_timelapse, slot_times
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.cli.capture import add_rig_args, rig_from_args
from omnispectral.cli.lens import board_arg, positive_mm_arg


def _start_time(text: str, date: str | None) -> _dt.datetime:
    day = _dt.date.fromisoformat(date) if date else DEFAULT_DATE
    return parse_hhmm(text, day, _dt.UTC)


def cmd_simulate(args) -> int:
    rig = rig_from_args(args, default_preset="small")
    start = _start_time(args.time, args.date)
    scene = build_scene(args.scene, args.cube, start, seed=args.seed, chart_distance_m=args.chart_distance,
                        chart_patch_m=args.chart_patch, light=args.light)
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = simulate_session(args.output, rig, scene, start=start, noise=args.noise == "on", seed=args.seed,
                               ground_truth_width=args.gt_width, progress=bars, mounting_error_deg=args.mounting_error,
                               raw=args.raw, calibration_views=not args.no_calibration_views)
    out["rig"] = rig.name
    if args.json:
        print_json(out)
    else:
        console.print(f"Simulated {out['n_written']} frames ({out['n_already_done']} already there) of {rig.name} "
                      f"in {out['wall_s']:.1f} s; the capture itself would take {out['simulated_s']:.0f} s.")
        console.print(f"Session: {args.output}  (verify: omnispectral session verify {args.output})")
        console.print(f"Ground truth: {out['ground_truth']} (bands.npy in DN/s, spectral.npy, ground_truth.json)")
        _print_calibration_views(out)
    return 0 if out["complete"] else 1


def _print_calibration_views(out: dict) -> None:
    """Where the session's chessboard views are (process fits camera B's mounting from them), or that there are none."""
    if out.get("calibration_views"):
        took = f" in {out['calibration_views_s']:.1f} s" if out.get("calibration_views_s") else ""
        console.print(f"Calibration views: {out['calibration_views']} (chessboard pairs{took}; 'omnispectral "
                      "process' fits camera B's mounting from them)")
    elif out.get("complete") and out.get("calibration_views_note"):
        console.print(f"[yellow]No calibration views[/yellow] ({escape(out['calibration_views_note'])}): process "
                      "will fit camera B's mounting from the session's own images and warn how far off far content "
                      "may be")


def cmd_simulate_chessboard(args) -> int:
    rig = rig_from_args(args, default_preset="small")
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = simulate_board_views(args.output, rig, seed=args.seed, n_views=args.views, board=args.board,
                                   square_mm=args.square_mm, noise=args.noise == "on",
                                   mounting_error_deg=args.mounting_error,
                                   progress=lambda i, n: bars("render", i, n))
    if args.json:
        print_json(out)
    else:
        dist, folder = out["distance_m"], Path(args.output)
        console.print(f"Simulated {out['n_views']} chessboard pairs ({out['board'][0]}x{out['board'][1]} inner "
                      f"corners, {out['square_mm']:g} mm squares, {min(dist):.2f}-{max(dist):.2f} m) of {rig.name} "
                      f"into {folder / 'A'} and {folder / 'B'} (truth: {folder / 'ground_truth' / 'views.json'}).")
        console.print(f"Calibrate: omnispectral calibrate rig --chessboard {args.output} -o rig-calibration.json")
    return 0


def cmd_capture_darks(args) -> int:
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        index = capture_darks(args.output, args.dark_frames, seed=args.seed, noise=args.noise == "on", progress=bars)
    if args.json:
        print_json(index)
    else:
        worst = max(index["frames"], key=lambda e: e["mean_dn"])
        console.print(f"Recorded {len(index['frames'])} dark frames (mean of {args.dark_frames} each) into "
                      f"{Path(args.output) / 'darks'}; largest mean {worst['mean_dn']:.1f} DN (camera "
                      f"{worst['camera']}, {worst['exposure_s']:g} s). 'omnispectral process' subtracts them.")
    return 0


def cmd_capture_calibration_views(args) -> int:
    rig = _calibration_rig(args)
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = capture_calibration_views(args.output, rig, n_views=args.views, board=args.board,
                                        square_mm=args.square_mm, interval_s=args.interval, seed=args.seed,
                                        noise=args.noise == "on", mounting_error_deg=args.mounting_error,
                                        say=lambda m: console.print(escape(m)), progress=bars)
    if args.json:
        print_json(out)
    else:
        console.print(f"Recorded {out['n_views']} chessboard pairs ({out['board'][0]}x{out['board'][1]}, "
                      f"{out['square_mm']:g} mm squares; {len(out['rejected'])} shots not kept) into "
                      f"{out['folder']}: 'omnispectral process' fits camera B's mounting from them.")
    return 0


def _calibration_rig(args):
    """The rig of ``capture calibration-views``: --preset/--rig, else the session's snapshot at -o."""
    snapshot = Path(args.output) / "rig.toml"
    if args.preset is None and args.rig is None and snapshot.is_file():
        args.rig = str(snapshot)
    return rig_from_args(args)


def cmd_capture(args) -> int:
    if args.what == "darks":
        return cmd_capture_darks(args)
    if args.what == "calibration-views":
        return cmd_capture_calibration_views(args)
    rig = rig_from_args(args)
    kind = rig_device_kind(rig)
    if args.dry_run:
        out = dry_run(rig, args.output)
        if args.json:
            print_json(out)
            return 0
        h = out["head"]
        console.print(f"[bold]{rig.name}[/bold] (dry run, nothing moves): {out['n_directions']} directions x "
                      f"{len(out['exposures_s'])} exposures x {len(out['cameras'])} camera(s) = "
                      f"{out['n_frames']} frames, "
                      f"{out['n_already_done']} already in {args.output}; estimated {out['estimated']}")
        port = f" on {h['port']} ({'present' if h['port_exists'] else 'NOT FOUND'})" if h["port"] else ""
        console.print(f"head: {h['driver']}{port}")
        for name, dev in out["cameras"].items():
            console.print(f"camera {name}: " + escape(", ".join(f"{k} {v}" for k, v in dev.items())))
        for m in out["moves"][:8]:
            console.print(f"  direction {m['direction']}: pan {m['pan_deg']:.3f} deg, tilt {m['tilt_deg']:.3f} deg")
        if len(out["moves"]) > 8:
            console.print(f"  … {len(out['moves']) - 8} more directions")
        return 0
    if kind == "simulated":
        return cmd_simulate(args)
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = capture_with_devices(args.output, rig, progress=bars)
    if args.json:
        print_json(out)
    else:
        console.print(f"Captured {out['n_written']} frames ({out['n_already_done']} already there) of "
                      f"{out['n_planned']} into {out['session']}"
                      + ("" if out["complete"] else f"; stopped: {escape(str(out['stopped_reason']))} "
                                                    "(run the same command again to resume)"))
    return 0 if out["complete"] else 1


def cmd_timelapse(args) -> int:
    rig = rig_from_args(args, default_preset="small")
    start = _start_time(args.start, args.date)
    end = _start_time(args.end, args.date)
    slots = slot_times(start, end, parse_interval_s(args.every))
    clock = FakeClock(start)  # simulated devices: simulated time
    # one mounting of the cameras for the whole series: its views once, in SERIES/calibration/ (the first slot)
    views = False if args.no_calibration_views else calibration_folder(args.output)

    def capture(session_dir: Path, t: _dt.datetime) -> dict:
        scene = build_scene(args.scene, args.cube, t, seed=args.seed, chart_distance_m=args.chart_distance,
                            chart_patch_m=args.chart_patch, light=args.light)
        res = simulate_session(session_dir, rig, scene, start=clock.now(), noise=args.noise == "on",
                               seed=args.seed, ground_truth_width=args.gt_width, progress=False,
                               mounting_error_deg=args.mounting_error, raw=args.raw, calibration_views=views)
        clock.sleep(res["simulated_s"])
        return res

    def report(entry: dict) -> None:
        if not args.json:
            console.print(f"{entry['time'][11:16]} {entry['session']}: {entry['status']}"
                          + (f" ({entry['reason']})" if entry.get("reason") else ""))

    index = run_timelapse(args.output, slots, clock, capture, {"rig": rig.name, "every_s": parse_interval_s(args.every),
                                                                "scene": args.scene}, on_slot=report)
    if args.json:
        print_json(index)
    else:
        console.print(f"Series {args.output}: {index['n_complete']} sessions, {index['n_skipped']} slots skipped "
                      f"(index: {Path(args.output) / 'series.json'})"
                      + (f"; calibration views for every slot: {views}" if views else ""))
    return 0


def _add_scene_args(p) -> None:
    p.add_argument("--scene", default="procedural", metavar="procedural|indoor|FILE.hdr|FILE.exr",
                   help="procedural outdoor scene (default), an indoor room with a chart and a white reference "
                        "(relighting ground truth), or an HDR equirectangular panorama")
    p.add_argument("--light", default=None, metavar="FL11|LED-B3|D65|A|FILE.csv",
                   help="light source of --scene indoor (default FL11)")
    p.add_argument("--cube", default=None, metavar="FILE.npz|FILE.hdr",
                   help="hyperspectral reflectance cube mounted on a wall of the procedural scene, or the "
                        "painting of --scene indoor")
    p.add_argument("--date", default=None, metavar="YYYY-MM-DD", help=f"day of the capture (default {DEFAULT_DATE})")
    p.add_argument("--noise", choices=["on", "off"], default="on", help="CMV2000 sensor noise")
    p.add_argument("--seed", type=int, default=0,
                   help="random seed of the noise, of camera B's unknown mounting error and of the scene's materials")
    p.add_argument("--mounting-error", type=float, default=0.5, metavar="DEG",
                   help="camera B is mounted up to this far (per axis) from what the rig file says, drawn from the "
                        "seed and recorded only in the ground truth (default 0.5; 0 = exactly as the rig file)")
    p.add_argument("--chart-distance", type=float, default=None, metavar="M",
                   help="distance of the ColorChecker from the rig (procedural scene; default 2.5 m)")
    p.add_argument("--chart-patch", type=float, default=None, metavar="M",
                   help="ColorChecker patch size (procedural scene; default 0.05 m)")
    p.add_argument("--raw", choices=["rgb", "bayer"], default="rgb",
                   help="frames as RGB (default) or as the raw RGGB Bayer mosaics of single-sensor cameras "
                        "(CFA layout in the rig snapshot and the journal; process demosaics)")
    p.add_argument("--gt-width", type=int, default=None, metavar="W",
                   help="width of the ground-truth panorama (default: the width process gives the panorama, "
                        "camera A's native width)")
    p.add_argument("--no-calibration-views", action="store_true",
                   help=f"do not record the rig's calibration views (by default {DEFAULT_N_VIEWS} chessboard pairs "
                        "into SESSION/calibration/, or SERIES/calibration/ once for a time-lapse; process fits camera "
                        "B's mounting from them to ~0.03 px at infinity). Without them process fits it from the "
                        "session's own images and warns, per direction, how far off far content may be")


def _add_session_args(p) -> None:
    add_rig_args(p)
    _add_scene_args(p)
    p.add_argument("--time", default="12:00", metavar="HH:MM",
                   help="time of day of the capture (sun position and daylight of the simulated scene)")
    p.add_argument("-o", "--output", required=True, metavar="SESSION", help="session directory (resumed if it exists)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")


def add_commands(sub) -> None:
    """Register ``simulate``, ``simulate-chessboard``, ``capture`` and ``timelapse``."""
    s = sub.add_parser("simulate", help="capture a simulated scene with the simulated rig (plus ground truth)",
                       description="Run the capture loop on the simulated rig: every sensor pixel through the rig's "
                                   "camera model, CMV2000 noise, frames and journal as from real hardware, and the "
                                   "ground truth (the rig's bands in DN/s and spectral radiance, equirectangular), "
                                   "then the rig's calibration views (chessboard pairs in SESSION/calibration/, from "
                                   "which process fits camera B's mounting; --no-calibration-views opts out). "
                                   "Resumable.")
    _add_session_args(s)
    s.set_defaults(func=cmd_simulate)

    b = sub.add_parser("simulate-chessboard", help="simulated chessboard pairs for 'calibrate rig --chessboard'",
                       description="Render a chessboard at random poses in front of the simulated rig (head at pan = "
                                   "tilt = 0), both cameras at once, camera B with the same unknown mounting error as "
                                   "'simulate' draws for the same --seed: DIR/A/view_NN.tif and DIR/B/view_NN.tif "
                                   "(16-bit RGB), DIR/board.json, DIR/rig.toml.")
    add_rig_args(b)
    b.add_argument("--views", type=int, default=12, metavar="N", help="board poses (default 12)")
    b.add_argument("--board", type=board_arg, default=DEFAULT_BOARD, metavar="COLSxROWS",
                   help="inner corners (default 9x6)")
    b.add_argument("--square-mm", type=positive_mm_arg, default=DEFAULT_SQUARE_MM, metavar="S",
                   help=f"square side in mm (default {DEFAULT_SQUARE_MM:g})")
    b.add_argument("--noise", choices=["on", "off"], default="on", help="CMV2000 sensor noise")
    b.add_argument("--seed", type=int, default=0, help="random seed of the poses, the noise and camera B's mounting "
                                                       "error (the same error as 'simulate --seed')")
    b.add_argument("--mounting-error", type=float, default=0.5, metavar="DEG",
                   help="largest error of camera B's mounting per axis, as for 'simulate' (default 0.5)")
    b.add_argument("-o", "--output", required=True, metavar="DIR")
    b.add_argument("--json", action="store_true", help="print a JSON summary")
    b.set_defaults(func=cmd_simulate_chessboard)

    c = sub.add_parser("capture", help="capture a session with the devices a rig file names",
                       description="Run the capture loop on the devices named in the rig file (GenICam cameras, "
                                   "RODEON or Merlin head; an all-simulated rig runs the simulator); resumes an "
                                   "incomplete session in the same directory.")
    c.add_argument("what", nargs="?", choices=["frames", "darks", "calibration-views"], default="frames",
                   help="frames (default): the capture; darks: dark frames (lenses capped) for every exposure of "
                        "the bracket of the existing session -o SESSION, subtracted by process; calibration-views: "
                        "chessboard pairs both cameras take at once, once per mounting of the cameras, into "
                        "-o SESSION/calibration/ (or a time-lapse's SERIES/calibration/), from which process fits "
                        "camera B's mounting; the operator is asked to move the board between shots (or --interval); "
                        "an all-simulated rig shoots a simulated board")
    _add_session_args(c)
    c.add_argument("--dry-run", action="store_true", help="print the plan and the devices named; move nothing")
    c.add_argument("--dark-frames", type=int, default=8, metavar="N",
                   help="capture darks: frames averaged per camera and exposure (default 8)")
    c.add_argument("--views", type=int, default=DEFAULT_N_VIEWS, metavar="N",
                   help=f"capture calibration-views: chessboard pairs (default {DEFAULT_N_VIEWS})")
    c.add_argument("--board", type=board_arg, default=DEFAULT_BOARD, metavar="COLSxROWS",
                   help="capture calibration-views: inner corners of the chessboard (default 9x6)")
    c.add_argument("--square-mm", type=positive_mm_arg, default=DEFAULT_SQUARE_MM, metavar="S",
                   help=f"capture calibration-views: square side in mm (default {DEFAULT_SQUARE_MM:g})")
    c.add_argument("--interval", type=float, default=None, metavar="S",
                   help="capture calibration-views: shoot every S seconds instead of asking for Enter")
    c.set_defaults(func=cmd_capture)

    t = sub.add_parser("timelapse", help="one capture every N minutes into a series directory",
                       description="Time-lapse (paper Sec. 5.3): one session per slot from --from to --to every "
                                   "--every; a capture that overruns its slot skips to the next slot and records it.")
    add_rig_args(t)
    _add_scene_args(t)
    t.add_argument("--every", default="5min", help="interval, e.g. 5min, 300s, 1h")
    t.add_argument("--from", dest="start", default="06:00", metavar="HH:MM")
    t.add_argument("--to", dest="end", default="17:00", metavar="HH:MM")
    t.add_argument("-o", "--output", required=True, metavar="SERIES", help="series directory")
    t.add_argument("--json", action="store_true", help="print the series index as JSON")
    t.set_defaults(func=cmd_timelapse)
