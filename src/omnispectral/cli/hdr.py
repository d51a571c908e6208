"""``omnispectral hdr merge``: an exposure bracket on disk into one linear HDR image (Eqs. (1)-(2))."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from rich.markup import escape

from omnispectral.capture.sourcefiles import RAW_SUFFIXES
from omnispectral.cli._common import console, err_console, print_json
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bracket import (
    auto_weight,
    exposure_time_mismatches,
    load_bracket,
    merge_bracket,
    write_float_image,
)
from omnispectral.imaging.response import CameraResponse
from omnispectral.limits import memory_budget

__all__ = ["cmd_hdr_merge"]


def cmd_hdr_merge(args) -> int:
    t0 = time.perf_counter()
    # outputs that are inputs are refused for every command (omnispectral.cli.main); here two outputs, one file
    if args.save_response and Path(args.save_response).resolve() == Path(args.output).resolve():
        raise ConfigurationError(f"{args.save_response}: is also the merged image's output; choose another file")
    _refuse_camera_raw(args.files)
    budget = memory_budget(args.memory_gb)  # the merge's memory is checked from the headers, before decoding
    response = args.response
    if response not in ("auto", "linear", "debevec"):
        response = CameraResponse.load(response)
    bracket = load_bracket(args.files, times=args.times, times_list=args.times_list, memory=budget,
                           response=response, deghost=args.deghost, with_variance=args.with_variance)
    weight = auto_weight(bracket, args.response) if args.weight == "auto" else args.weight
    result, resp, depth = merge_bracket(bracket, bit_depth=args.bit_depth, weight=weight, response=response,
                                        deghost=args.deghost, reference=args.reference)
    mismatches = [m.describe() for m in exposure_time_mismatches(bracket, resp, depth)]
    if mismatches:
        _warn_exposure_times(mismatches, bracket.time_sources)
    names = ["R", "G", "B"] if result.radiance.shape[2] == 3 else None
    image, channel_names = result.radiance, names
    if args.with_variance:
        c = image.shape[2]
        base = names or [f"C{i}" for i in range(c)]
        image = np.concatenate([image, result.variance, result.valid.all(axis=2, keepdims=True)], axis=2)
        channel_names = [*base, *(f"variance.{n}" for n in base), "valid"]
    attrs = {"omnispectral": "hdr merge", "units": "linear value per second of exposure",
             "weight": weight, "response": resp.kind}
    out = write_float_image(args.output, image, channel_names, attrs if Path(args.output).suffix == ".exr" else None)
    if args.save_response:
        resp.save(args.save_response)
    n = result.radiance[..., 0].size
    summary = {
        "output": str(out), "n_frames": len(bracket.frames), "bit_depth": depth, "weight": weight,
        "response": resp.kind, "exposure_s": bracket.exposure_s.tolist(), "time_sources": list(bracket.time_sources),
        "height": int(result.radiance.shape[0]), "width": int(result.radiance.shape[1]),
        "channels": int(result.radiance.shape[2]),
        "fraction_saturated": float(result.saturated.any(axis=2).sum() / n),
        "fraction_dark": float(result.dark.any(axis=2).sum() / n),
        "fraction_ghost": None if result.ghost is None else float(result.ghost.mean()),
        "radiance_min": float(result.radiance.min()), "radiance_max": float(result.radiance.max()),
        "response_file": args.save_response, "exposure_time_warnings": mismatches,
        "elapsed_s": round(time.perf_counter() - t0, 3),
    }
    if args.json:
        print_json(summary)
        return 0
    console.print(f"Merged {summary['n_frames']} frames ({depth}-bit, exposures {min(bracket.exposure_s):.4g}-"
                  f"{max(bracket.exposure_s):.4g} s from {', '.join(sorted(set(bracket.time_sources)))}) with the "
                  f"{weight} weight and a {resp.kind} response in {summary['elapsed_s']:.2f} s.")
    console.print(f"{summary['width']}x{summary['height']}x{summary['channels']}, radiance "
                  f"{summary['radiance_min']:.4g}-{summary['radiance_max']:.4g} per s; saturated everywhere "
                  f"{100 * summary['fraction_saturated']:.2f} %, dark everywhere {100 * summary['fraction_dark']:.2f} %"
                  + ("" if result.ghost is None else f", ghosts {100 * summary['fraction_ghost']:.2f} %") + ".")
    console.print(f"Wrote {out}" + (f" and {args.save_response}" if args.save_response else ""))
    return 0


def _refuse_camera_raw(files: list[str]) -> None:
    """Camera raw files (DNG, NEF, CR2…) are not frames ``hdr merge`` decodes: refused by name before any decoder
    parses them (``import`` reads them through LibRaw, its sizes checked from their metadata first)."""
    for f in files:
        if Path(f).suffix.lower() in RAW_SUFFIXES:
            raise InputFileError(f, "a camera raw file: hdr merge reads TIFF/PNG/JPEG frames (import raw files "
                                    "into a session with omnispectral import, or convert them to 16-bit TIFF)")


def _warn_exposure_times(mismatches: list[str], sources: tuple[str, ...]) -> None:
    """One warning line on standard error: which frames disagree with their exposure times, and where the
    times came from."""
    where = {"given": "--times (in file order)", "list": "the --times-list file", "exif": "the EXIF ExposureTime"}
    origin = " and ".join(where.get(s, s) for s in dict.fromkeys(sources))
    err_console.print(f"[bold yellow]warning:[/bold yellow] exposure times inconsistent with the frames: "
                      f"{escape('; '.join(mismatches))}; check {origin} (a wrong time shows as ghosts and a wrong "
                      "radiance)")
