"""``omnispectral register A B``: sub-pixel shift of camera B's image relative to camera A's (paper Sec. 4.3)."""

from __future__ import annotations

from omnispectral.cli._common import console, print_json
from omnispectral.imaging.imageio import read_image
from omnispectral.imaging.registration import (
    phase_correlate,
    register_with_fallback,
)

__all__ = ["cmd_register"]


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
