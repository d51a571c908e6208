"""``omnispectral mosaic SESSION_OR_MERGED -o PANO.zarr``: stitch the six-band panorama (paper Sec. 4.4–4.5)."""

from __future__ import annotations

from pathlib import Path

from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from omnispectral.capture.session import Session
from omnispectral.cli._common import console, err_console, print_json, progress_wanted
from omnispectral.errors import InputFileError
from omnispectral.mosaic import mosaic
from omnispectral.product.estimator import b_predictor, rig_estimator
from omnispectral.product.merge import merge_session

__all__ = ["cmd_mosaic"]


def cmd_mosaic(args) -> int:
    region = tuple(args.region) if args.region else None
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
               TimeRemainingColumn())
    with Progress(*columns, console=err_console, disable=not progress_wanted(not args.no_progress),
                  transient=False) as bar:
        tasks = {}
        labels = {"merge": "HDR merge (directions)", "tiles": "tiles", "pyramid": "pyramid chunks"}

        def progress(stage, done, total):
            if stage not in tasks:
                tasks[stage] = bar.add_task(labels[stage], total=total)
            bar.update(tasks[stage], completed=done, total=total)

        source = Path(args.input)
        if not source.exists():
            raise InputFileError(source, "not found")
        predictor = None
        if (source / "session.json").is_file():  # a raw session: merge it into directions first
            merged_dir = Path(args.merged_dir) if args.merged_dir is not None else source / "merged"
            predictor = b_predictor(rig_estimator(Session.open(source).rig())[0])
            source = merge_session(source, merged_dir, progress=progress)
        summary = mosaic(source, args.output, width=args.width, tile=args.tile, interp=args.interp,
                         blend=args.blend, multiband_levels=args.levels, gain_compensation=args.gain_compensation,
                         scheduler=args.scheduler, workers=args.workers, overwrite=args.overwrite,
                         region=region, b_predictor=predictor, edge_model=args.edge_model,
                         progress=progress)
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
