"""``omnispectral calibrate lens …``: Zhang's lens calibration from chessboard images (paper Sec. 4.2)."""

from __future__ import annotations

import argparse

from rich.table import Table

from omnispectral.cli._common import console, print_json
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.lens import DEFAULT_SUBPIX_WINDOW, DETECTORS, MIN_IMAGES, MODELS, calibrate_lens, parse_board
from omnispectral.io import atomic_write_json


def calibrate_group(sub) -> argparse._SubParsersAction:
    """The sub-commands of ``omnispectral calibrate``, created on first use.

    Other modules register further calibrations (``calibrate <what>``) through this function, so
    the group exists once whichever module comes first.
    """
    parser = sub.choices.get("calibrate")
    if parser is None:
        parser = sub.add_parser("calibrate", help="calibrate the rig: lens, …",
                                description="Calibrations measured in advance (paper Sec. 4).")
        parser.set_defaults(calibrate_sub=parser.add_subparsers(dest="calibration", metavar="WHAT", required=True))
    return parser.get_default("calibrate_sub")


def board_arg(text: str) -> tuple[int, int]:
    try:
        return parse_board(text)
    except ConfigurationError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def positive_mm_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def _subpix(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive integer or 'auto', got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer or 'auto', got {text!r}")
    return value


def cmd_calibrate_lens(args) -> int:
    result = calibrate_lens(args.images, board=args.board, square_mm=args.square_mm, model=args.model,
                            detector=args.detector, min_images=args.min_images,
                            subpix_window_px=args.subpix_window)
    out = result.to_dict()
    atomic_write_json(args.output, out)
    if args.json:
        print_json({**out, "output": str(args.output)})
        return 0
    cam = result.camera
    table = Table(title=f"Lens calibration: {len(result.views)} of {len(args.images)} images, "
                        f"{result.board[0]}x{result.board[1]} board, {result.square_mm:g} mm squares")
    for col, justify in (("image", "left"), ("board", "left"), ("RMS px", "right")):
        table.add_column(col, justify=justify)
    for v in result.views:
        table.add_row(str(v.path), f"found ({v.detector})", f"{v.rms_px:.3f}")
    for path, why in result.rejected:
        table.add_row(str(path), f"[yellow]{why}[/yellow]", "-")
    console.print(table)
    dist = "  ".join(f"{k}={v:.5g}" for k, v in cam.distortion.items())
    console.print(f"RMS reprojection error [bold]{result.rms_px:.3f} px[/bold]   "
                  f"fx={cam.fx:.2f} fy={cam.fy:.2f} cx={cam.cx:.2f} cy={cam.cy:.2f} px   "
                  f"image {cam.width}x{cam.height}   FOV {cam.hfov_deg:.1f}° x {cam.vfov_deg:.1f}°")
    console.print(f"Distortion ({result.model}): {dist}")
    for warning in result.warnings:
        console.print(f"[yellow]warning: {warning}[/yellow]")
    console.print(f"Camera model written to {args.output}")
    return 0


def add_commands(sub) -> None:
    """Register ``calibrate lens``."""

    lens = calibrate_group(sub).add_parser(
        "lens", help="lens intrinsics and distortion from chessboard images (Zhang's method)",
        description="Calibrate a lens from chessboard images with Zhang's method via OpenCV (paper Sec. 4.2): "
                    "focal lengths, principal point and OpenCV distortion coefficients. Images where the board "
                    "is not found are listed; too few boards is an error.")
    lens.add_argument("images", nargs="+", metavar="IMAGE", help="chessboard images from one camera")
    lens.add_argument("--board", type=board_arg, required=True, metavar="COLSxROWS",
                      help="inner corners per row x per column, e.g. 9x6")
    lens.add_argument("--square-mm", type=positive_mm_arg, required=True, metavar="S", help="square side in mm")
    lens.add_argument("-o", "--output", required=True, metavar="LENS.json", help="camera model to write (JSON)")
    lens.add_argument("--model", choices=list(MODELS), default="standard",
                      help="distortion model: standard k1 k2 p1 p2 k3 (default), rational (+k4..k6), "
                           "thin-prism (+s1..s4)")
    lens.add_argument("--detector", choices=list(DETECTORS), default="auto",
                      help="corner detector: classic findChessboardCorners, sb (sector-based) or auto "
                           "(classic, sb as fallback; default)")
    lens.add_argument("--subpix-window", type=_subpix, default=DEFAULT_SUBPIX_WINDOW, metavar="PX|auto",
                      help=f"cornerSubPix half-window: 'auto' = min(11, 40%% of the corner spacing) per image, or "
                           f"pixels; 11 is OpenCV's tutorial pipeline exactly (default {DEFAULT_SUBPIX_WINDOW})")
    lens.add_argument("--min-images", type=int, default=MIN_IMAGES,
                      help=f"fewest images with a found board (default {MIN_IMAGES})")
    lens.add_argument("--json", action="store_true", help="print the result as JSON")
    lens.set_defaults(func=cmd_calibrate_lens)
