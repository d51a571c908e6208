"""``omnispectral mosaic SESSION_OR_MERGED -o PANO.zarr``: the arguments; run by :mod:`omnispectral.cli.mosaic`."""

from __future__ import annotations

import argparse

from omnispectral.choices import BLEND_NAMES, DEFAULT_INTERP, DEFAULT_MULTIBAND_LEVELS, DEFAULT_TILE, INTERP_NAMES
from omnispectral.cli.parsers import positive_int_arg

__all__ = ["add_commands"]


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "mosaic", help="stitch a capture session or merged directions into a six-band panorama (Zarr)",
        description="One resampling per output pixel through the composed geometry (equirect pixel -> ray -> "
                    "head rotation -> lens model -> sensor pixel), linear blending of overlaps (paper Sec. 4.5), "
                    "tiles in parallel with Dask. A raw session is HDR-merged first, direction by direction, into "
                    "SESSION/merged (camera B at the calibrated offset 0). An interrupted run resumes.")
    p.add_argument("input", metavar="SESSION_OR_MERGED",
                   help="capture session directory (session.json) or merged directions (merged.json)")
    p.add_argument("-o", "--output", required=True, metavar="PANO.zarr", help="output Zarr store")
    p.add_argument("--width", type=int, default=None,
                   help="panorama width in px, height = width/2 (default: the sensor's resolution, 2*pi*f)")
    p.add_argument("--tile", type=int, default=DEFAULT_TILE, help=f"tile and chunk side in px (default {DEFAULT_TILE})")
    p.add_argument("--interp", choices=INTERP_NAMES, default=DEFAULT_INTERP,
                   help=f"interpolation (default {DEFAULT_INTERP}); spline = cubic B-spline, lanczos = Lanczos-3")
    p.add_argument("--blend", choices=BLEND_NAMES, default="linear", help="linear (paper, default) or multiband")
    p.add_argument("--levels", type=int, default=DEFAULT_MULTIBAND_LEVELS,
                   help=f"pyramid levels of multi-band blending (default {DEFAULT_MULTIBAND_LEVELS})")
    p.add_argument("--no-edge-model", dest="edge_model", action="store_false",
                   help="interpolate straight edges too, instead of giving each pixel its area on either side "
                        "(omnispectral.mosaic.edges)")
    p.add_argument("--gain-compensation", action="store_true",
                   help="equalise per-direction gains in the overlaps (Brown & Lowe 2007)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="Dask distributed scheduler address (default: local threads)")
    p.add_argument("--workers", type=positive_int_arg, default=None, help="local threads (default: all cores)")
    p.add_argument("--region", type=int, nargs=4, metavar=("ROW0", "ROW1", "COL0", "COL1"), default=None,
                   help="compute only the tiles meeting this pixel window")
    p.add_argument("--merged-dir", default=None, help="where a raw session is merged to (default SESSION/merged)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output instead of resuming it")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func="omnispectral.cli.mosaic:cmd_mosaic")
