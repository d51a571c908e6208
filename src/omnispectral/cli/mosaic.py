"""``omnispectral mosaic SESSION_OR_MERGED -o PANO.zarr``: stitch the six-band panorama (paper Sec. 4.4–4.5)."""

from __future__ import annotations

import argparse
from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from omnispectral.capture.session import Session
from omnispectral.cli._common import console, err_console, print_json, progress_wanted
from omnispectral.errors import InputFileError
from omnispectral.mosaic import mosaic
from omnispectral.mosaic.blending import BLENDS, DEFAULT_MULTIBAND_LEVELS
from omnispectral.mosaic.engine import DEFAULT_TILE
from omnispectral.mosaic.interp import METHODS
from omnispectral.product.estimator import b_predictor, rig_estimator
from omnispectral.product.merge import merge_session
from omnispectral.product.process import DEFAULT_INTERP


def cmd_mosaic(args) -> int:
    region = tuple(args.region) if args.region else None
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn())
    with Progress(*columns, console=err_console, disable=not progress_wanted(not args.no_progress),
                  transient=False) as bar:
        tasks = {}
        labels = {"merge": "HDR merge (directions)", "tiles": "tiles", "pyramid": "pyramid chunks"}

        def progress(stage, result, done, total):
            if stage not in tasks:
                tasks[stage] = bar.add_task(labels[stage], total=total)
            description = labels[stage]
            if stage == "tiles" and result:
                description = f"tiles (last: {result.get('n_sources', 0)} sources, {result.get('seconds', 0):.2f} s)"
            bar.update(tasks[stage], completed=done, total=total, description=description)

        source = Path(args.input)
        if not source.exists():
            raise InputFileError(source, "not found")
        predictor = None
        if (source / "session.json").is_file():  # a raw session: merge it into directions first
            merged_dir = Path(args.merged_dir) if args.merged_dir is not None else source / "merged"
            predictor = b_predictor(rig_estimator(Session.open(source).rig())[0])
            source = merge_session(source, merged_dir, progress=lambda d, n: progress("merge", {}, d, n))
        summary = mosaic(source, args.output, width=args.width, tile=args.tile, interp=args.interp,
                         blend=args.blend, multiband_levels=args.levels, gain_compensation=args.gain_compensation,
                         scheduler=args.scheduler, workers=args.workers, overwrite=args.overwrite,
                         region=region, b_predictor=predictor, progress=progress)
    if args.json:
        print_json(summary)
        return 0
    s = summary
    console.print(f"[bold]{s['output']}[/bold]: {s['width']} x {s['height']} x {s['bands']} float32 (DN/s), "
                  f"{len(s['levels'])} levels, tile {s['tile']}, {s['interp']} interpolation, {s['blend']} blending",
                  highlight=False)
    console.print(f"  {s['n_sources']} source images; tiles: {s['tiles_computed']} computed, {s['tiles_skipped']} "
                  f"already done of {s['tiles']}; {s['sources_per_tile_mean']:.1f} sources per tile on average "
                  f"(max {s['sources_per_tile_max']})", highlight=False)
    rate = f", {s['megapixels_per_s']} Mpx/s" if s["megapixels_per_s"] else ""
    console.print(f"  {s['seconds']['total']:.1f} s (tiles {s['seconds']['tiles']:.1f} s{rate}), "
                  f"peak RSS {s['peak_rss_mb']:.0f} MB, largest map error {s['max_map_error_px']:.1e} px",
                  highlight=False)
    if s["holes_px"]:
        console.print(f"  [yellow]{s['holes_px']} pixels are not covered by any direction (NaN)[/yellow]")
    return 0


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
    p.add_argument("--interp", choices=METHODS, default=DEFAULT_INTERP,
                   help=f"interpolation (default {DEFAULT_INTERP}); spline = cubic B-spline, lanczos = Lanczos-3")
    p.add_argument("--blend", choices=BLENDS, default="linear", help="linear (paper, default) or multiband")
    p.add_argument("--levels", type=int, default=DEFAULT_MULTIBAND_LEVELS,
                   help=f"pyramid levels of multi-band blending (default {DEFAULT_MULTIBAND_LEVELS})")
    p.add_argument("--gain-compensation", action="store_true",
                   help="equalise per-direction gains in the overlaps (Brown & Lowe 2007)")
    p.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="Dask distributed scheduler address (default: local threads)")
    p.add_argument("--workers", type=int, default=None, help="local threads (default: all cores)")
    p.add_argument("--region", type=int, nargs=4, metavar=("ROW0", "ROW1", "COL0", "COL1"), default=None,
                   help="compute only the tiles meeting this pixel window")
    p.add_argument("--merged-dir", default=None, help="where a raw session is merged to (default SESSION/merged)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output instead of resuming it")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_mosaic)
