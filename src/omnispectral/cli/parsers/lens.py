"""``omnispectral calibrate lens``: the arguments, the ``calibrate`` group and the chessboard arguments other
commands share; run by :mod:`omnispectral.cli.lens`."""

from __future__ import annotations

import argparse
import importlib

from omnispectral.choices import DEFAULT_SUBPIX_WINDOW, DETECTORS, LENS_MODEL_NAMES, MIN_IMAGES
from omnispectral.cli.parsers import positive_int_arg
from omnispectral.errors import ConfigurationError

__all__ = ["add_commands", "board_arg", "calibrate_group", "positive_mm_arg"]


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
    """argparse type: ``COLSxROWS`` inner corners (:func:`omnispectral.imaging.lens.parse_board`, whose module, with
    OpenCV, is imported only when a value is given)."""
    parse_board = importlib.import_module("omnispectral.imaging.lens").parse_board
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
    """argparse type of ``--subpix-window``: ``auto`` or a count of pixels."""
    return text if text == "auto" else positive_int_arg(text)


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
    lens.add_argument("--model", choices=list(LENS_MODEL_NAMES), default="standard",
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
    lens.set_defaults(func="omnispectral.cli.lens:cmd_calibrate_lens")
