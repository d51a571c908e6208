"""``omnispectral simulate | capture | timelapse``: run the capture loop on the simulated rig (or a rig's devices)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

from rich.markup import escape

from omnispectral.capture.calviews import calibration_folder
from omnispectral.capture.drivers import rig_device_kind
from omnispectral.capture.hardware import capture_calibration_views, capture_darks, capture_with_devices, dry_run
from omnispectral.capture.plan import format_duration, make_plan
from omnispectral.capture.session import Session
from omnispectral.capture.timelapse import parse_hhmm, parse_interval_s, run_timelapse, slot_times
from omnispectral.choices import DEFAULT_DATE
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.cli.capture import rig_from_args
from omnispectral.sim.devices import FakeClock, stand_in_head
from omnispectral.sim.scenes import build_scene
from omnispectral.sim.simulate import (
    simulate_board_views,
    simulate_session,
    simulated_board_cameras,
    simulated_dark_cameras,
)

__all__ = ["cmd_capture", "cmd_capture_calibration_views", "cmd_capture_darks", "cmd_simulate",
           "cmd_simulate_chessboard", "cmd_timelapse"]


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
                                   progress=bars)
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
        index = capture_darks(args.output, args.dark_frames, cameras=_simulated_dark_cameras(args), progress=bars)
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
                                        square_mm=args.square_mm, interval_s=args.interval,
                                        devices=_simulated_board(args, rig), say=lambda m: console.print(escape(m)),
                                        progress=bars)
    if args.json:
        print_json(out)
    else:
        console.print(f"Recorded {out['n_views']} chessboard pairs ({out['board'][0]}x{out['board'][1]}, "
                      f"{out['square_mm']:g} mm squares; {len(out['rejected'])} shots not kept) into "
                      f"{out['folder']}: 'omnispectral process' fits camera B's mounting from them.")
    return 0


def _simulated_dark_cameras(args) -> dict | None:
    """The capped sensors of an all-simulated session's rig for ``capture darks`` (None: the rig's real cameras)."""
    rig = Session.open(args.output).rig()
    if any(rig.cameras[c].device.get("driver", "simulated") != "simulated" for c in rig.camera_names):
        return None
    return simulated_dark_cameras(rig, seed=args.seed, noise=args.noise == "on")


def _simulated_board(args, rig):
    """``(cameras, next_view)`` in front of a simulated board for an all-simulated rig (None: the real cameras),
    camera B with the unknown mounting of a session of ``--seed``."""
    if rig_device_kind(rig) != "simulated":
        return None
    return simulated_board_cameras(rig, seed=args.seed, noise=args.noise == "on",
                                   mounting_error_deg=args.mounting_error, board=args.board, square_mm=args.square_mm)


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
        status = 1 if out["problems"] else 0  # a rig the capture could not use: the dry run fails too
        if args.json:
            print_json(out)
            return status
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
        _print_problems(rig, out["problems"])
        return status
    if kind == "simulated":
        return cmd_simulate(args)
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = capture_with_devices(args.output, rig, progress=bars,
                                   head=stand_in_head(rig) if rig.head.driver == "simulated" else None)
    if args.json:
        print_json(out)
    else:
        console.print(f"Captured {out['n_written']} frames ({out['n_already_done']} already there) of "
                      f"{out['n_planned']} into {out['session']}"
                      + ("" if out["complete"] else f"; stopped: {escape(str(out['stopped_reason']))} "
                                                    "(run the same command again to resume)"))
        _print_exposures_set_otherwise(out.get("exposures_set_otherwise") or [])
    return 0 if out["complete"] else 1


def _print_exposures_set_otherwise(entries: list[dict]) -> None:
    """One line per camera and exposure the camera set otherwise than planned (out of its range)."""
    for e in entries:
        console.print(f"[yellow]camera {escape(str(e['camera']))} set {e['set_s']:.6g} s for the planned "
                      f"{e['requested_s']:.6g} s (exposure {e['exposure_index']}, {e['n_frames']} frames)[/yellow]: "
                      "the frames record the exposure set, and the merge uses it")


def _print_problems(rig, problems: list[str]) -> None:
    """The dry run's problems, one per line under the rig file's name, or that it found none."""
    if not problems:
        console.print("No problems found (the devices were not contacted: 'omnispectral devices probe' talks to them)")
        return
    n = len(problems)
    console.print(f"[bold red]{n} problem{'s' if n > 1 else ''}[/bold red] in {escape(str(rig.source or rig.name))}: "
                  "a capture would stop before its first frame")
    for p in problems:
        console.print(f"  - {escape(p)}")


def cmd_timelapse(args) -> int:
    rig = rig_from_args(args, default_preset="small")
    start = _start_time(args.start, args.date)
    end = _start_time(args.end, args.date)
    every_s = parse_interval_s(args.every)
    slots = slot_times(start, end, every_s)
    plan = make_plan(rig)
    if plan.estimated_max_s > every_s and not args.json:
        console.print(f"[yellow]A capture takes {format_duration(plan.estimated_s)}, "
                      f"{format_duration(plan.estimated_max_s)} with the dark extension in every direction: longer "
                      f"than the {format_duration(every_s)} between slots[/yellow], so a slot may start late and the "
                      "slots it overruns are skipped")
    clock = FakeClock(start)  # simulated devices: simulated time
    # one mounting of the cameras for the whole series: its views once, in SERIES/calibration/ (the first slot)
    views = False if args.no_calibration_views else calibration_folder(args.output)

    def capture(session_dir: Path, t: _dt.datetime) -> dict:
        scene = build_scene(args.scene, args.cube, t, seed=args.seed, chart_distance_m=args.chart_distance,
                            chart_patch_m=args.chart_patch, light=args.light)
        res = simulate_session(session_dir, rig, scene, start=clock.now(), noise=args.noise == "on",
                               seed=args.seed, ground_truth_width=args.gt_width, progress=bars,
                               mounting_error_deg=args.mounting_error, raw=args.raw, calibration_views=views)
        # the series' clock goes on to where the slot's (resumed) session ends: the capture time of all its frames,
        # an interrupted run's included (this run's simulated_s alone would lose that run's time)
        clock.sleep(res.get("capture_s", res["simulated_s"]))
        return res

    def report(entry: dict) -> None:
        if not args.json:
            console.print(f"{entry['time'][11:16]} {entry['session']}: {entry['status']}"
                          + (f" ({entry['reason']})" if entry.get("reason") else ""))

    # one bar for the slots (drawn from the start, before the first slot's capture), one for the frames of each
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        index = run_timelapse(args.output, slots, clock, capture,
                              {"rig": rig.name, "every_s": every_s, "scene": args.scene},
                              on_slot=report, progress=bars)
    if args.json:
        print_json(index)
    else:
        console.print(f"Series {args.output}: {index['n_complete']} sessions, {index['n_skipped']} slots skipped "
                      f"(index: {Path(args.output) / 'series.json'})"
                      + (f"; calibration views for every slot: {views}" if views else ""))
    return 0
