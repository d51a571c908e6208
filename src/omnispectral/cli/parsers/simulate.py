"""``omnispectral simulate | simulate-chessboard | capture | timelapse``: the arguments; run by
:mod:`omnispectral.cli.simulate`."""

from __future__ import annotations

from omnispectral.choices import DEFAULT_BOARD, DEFAULT_DATE, DEFAULT_N_VIEWS, DEFAULT_SQUARE_MM
from omnispectral.cli.parsers import date_arg, seed_arg
from omnispectral.cli.parsers.capture import add_rig_args
from omnispectral.cli.parsers.lens import board_arg, positive_mm_arg

__all__ = ["add_commands"]


def _add_scene_args(p) -> None:
    p.add_argument("--scene", default="procedural", metavar="procedural|indoor|FILE.hdr|FILE.exr",
                   help="procedural outdoor scene (default), an indoor room with a chart and a white reference "
                        "(relighting ground truth), or an HDR equirectangular panorama")
    p.add_argument("--light", default=None, metavar="FL11|LED-B3|D65|A|FILE.csv",
                   help="light source of --scene indoor (default FL11)")
    p.add_argument("--cube", default=None, metavar="FILE.npz|FILE.hdr",
                   help="hyperspectral reflectance cube mounted on a wall of the procedural scene, or the "
                        "painting of --scene indoor")
    p.add_argument("--date", type=date_arg, default=None, metavar="YYYY-MM-DD",
                   help=f"day of the capture (default {DEFAULT_DATE})")
    p.add_argument("--noise", choices=["on", "off"], default="on", help="CMV2000 sensor noise")
    p.add_argument("--seed", type=seed_arg, default=0,
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
    s.set_defaults(func="omnispectral.cli.simulate:cmd_simulate")

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
    b.add_argument("--seed", type=seed_arg, default=0,
                   help="random seed of the poses, the noise and camera B's mounting error (the same error as "
                        "'simulate --seed')")
    b.add_argument("--mounting-error", type=float, default=0.5, metavar="DEG",
                   help="largest error of camera B's mounting per axis, as for 'simulate' (default 0.5)")
    b.add_argument("-o", "--output", required=True, metavar="DIR")
    b.add_argument("--json", action="store_true", help="print a JSON summary")
    b.set_defaults(func="omnispectral.cli.simulate:cmd_simulate_chessboard")

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
    c.set_defaults(func="omnispectral.cli.simulate:cmd_capture")

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
    t.set_defaults(func="omnispectral.cli.simulate:cmd_timelapse")
