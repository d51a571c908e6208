"""``omnispectral calibrate lens …``: Zhang's lens calibration from chessboard images (paper Sec. 4.2)."""

from __future__ import annotations

from rich.table import Table

from omnispectral.cli._common import console, print_json
from omnispectral.imaging.lens import calibrate_lens
from omnispectral.io import atomic_write_json

__all__ = ["cmd_calibrate_lens"]


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
