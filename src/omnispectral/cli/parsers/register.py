"""``omnispectral register A B``: the arguments; run by :mod:`omnispectral.cli.register`."""

from __future__ import annotations

import argparse

from omnispectral.choices import DEFAULT_BAND_LIMIT, DEFAULT_MIN_CONFIDENCE, DEFAULT_PREPROCESS, PREPROCESS, WINDOWS

__all__ = ["add_commands"]


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
    p.set_defaults(func="omnispectral.cli.register:cmd_register")
