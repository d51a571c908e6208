"""``omnispectral register A B``: sub-pixel shift of camera B's image relative to camera A's (paper Sec. 4.3)."""

from __future__ import annotations

import argparse

from omnispectral.cli._common import console, print_json
from omnispectral.imaging.imageio import read_image
from omnispectral.imaging.registration import (
    DEFAULT_BAND_LIMIT,
    DEFAULT_MIN_CONFIDENCE,
    DEFAULT_PREPROCESS,
    PREPROCESS,
    WINDOWS,
    phase_correlate,
    register_with_fallback,
)


def cmd_register(args) -> int:
    reference = read_image(args.reference)
    moving = read_image(args.moving)
    options = {"window": args.window, "band_limit": args.band_limit, "preprocess": args.preprocess}
    if args.calibrated_offset is not None:
        reg = register_with_fallback(reference, moving, tuple(args.calibrated_offset),
                                     min_confidence=args.min_confidence, **options)
    else:
        reg = phase_correlate(reference, moving, **options)
    low = reg.confidence < args.min_confidence
    out = {"dx": reg.dx, "dy": reg.dy, "confidence": reg.confidence, "min_confidence": args.min_confidence,
           "reliable": not low, "used_fallback": reg.used_fallback, "measured_dx": reg.measured_dx,
           "measured_dy": reg.measured_dy, "window": reg.window, "band_limit": reg.band_limit,
           "preprocess": reg.preprocess, "shape": list(reg.shape), "reference": str(args.reference),
           "moving": str(args.moving),
           "convention": "moving(x, y) ~= reference(x - dx, y - dy); x = column, y = row, pixels"}
    if args.json:
        print_json(out)
        return 0
    line = f"dx = {reg.dx:+.3f} px, dy = {reg.dy:+.3f} px, confidence {reg.confidence:.3f}"
    if reg.used_fallback:
        line += (f" [calibrated offset used: measured ({reg.measured_dx:+.3f}, {reg.measured_dy:+.3f}) "
                 f"has confidence below {args.min_confidence}]")
    elif low:
        line += f" [low confidence: below {args.min_confidence}; pass --calibrated-offset DX DY to fall back]"
    console.print(line, highlight=False)
    console.print("[dim]moving(x, y) ~= reference(x - dx, y - dy)[/dim]")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "register", help="sub-pixel shift of image B relative to image A (phase-only correlation)",
        description="Band-limited phase-only correlation with a sub-pixel peak model (paper Eq. (3); Takita et al. "
                    "2003). Prints dx, dy with moving(x, y) ~= reference(x - dx, y - dy) and the peak height as "
                    "confidence. Images: PNG, JPEG, TIFF, EXR, HDR; channels are averaged.")
    p.add_argument("reference", help="reference image (camera A)")
    p.add_argument("moving", help="image to register (camera B)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--min-confidence", type=float, default=DEFAULT_MIN_CONFIDENCE,
                   help=f"peak height below which the shift is not trusted (default {DEFAULT_MIN_CONFIDENCE})")
    p.add_argument("--calibrated-offset", type=float, nargs=2, metavar=("DX", "DY"), default=None,
                   help="rig offset to report instead when the confidence is below --min-confidence")
    p.add_argument("--window", choices=WINDOWS, default="hann", help="apodisation window (default hann)")
    p.add_argument("--band-limit", type=float, default=DEFAULT_BAND_LIMIT,
                   help=f"fraction of Nyquist used (default {DEFAULT_BAND_LIMIT})")
    p.add_argument("--preprocess", choices=PREPROCESS, default=DEFAULT_PREPROCESS,
                   help=f"intensity transform before correlation (default {DEFAULT_PREPROCESS}; 'gradient' for bands "
                        "with reversed contrast)")
    p.set_defaults(func=cmd_register)
