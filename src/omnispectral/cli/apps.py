"""``omnispectral render | render-series | relight``: the paper's applications (Sec. 6)."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape

from omnispectral.apps.materials import load_metal
from omnispectral.apps.relight import parse_white, relight_product
from omnispectral.apps.render import render_product
from omnispectral.apps.series import render_series
from omnispectral.cli._common import console, err_console, print_json


def _progress(enabled: bool):
    return (lambda msg: err_console.print(f"[dim]{escape(msg)}[/dim]")) if enabled else None


def _render_kwargs(args) -> dict:
    kw = {"scene": args.scene, "width": args.width, "height": args.height, "spp": args.spp, "level": args.level,
          "max_env_width": args.env_width, "wavelength_step_nm": args.wavelength_step, "fast": args.fast,
          "seed": args.seed, "variant": args.variant}
    if args.scene in (None, "mirror-ball"):
        kw.update(view_lon_deg=args.view_lon, elevation_deg=args.elevation)
        if args.metal:

            kw["ball"] = load_metal(args.metal)
    return kw


def _print_environment_sun(env: dict) -> None:
    """What the environment holds of the sun: recovered (how), a model estimate, or a lower bound."""
    sun = env.get("sun") or {}
    if sun.get("recovered"):
        console.print(f"lit by the recovered sun ({sun.get('method')}).")
        if sun.get("model_estimate"):
            console.print("[yellow]warning:[/yellow] the sun is a model estimate, not a measurement "
                          "(product's sun.json)")
    if env.get("saturated_pixels"):
        console.print(f"[yellow]warning:[/yellow] {env['saturated_pixels']} saturated environment pixels (the sun) "
                      f"hold a lower bound only: {100 * env['saturated_energy_fraction']:.1f} % of the map's energy")


def cmd_render(args) -> int:

    out = render_product(args.product, args.output, progress=_progress(not args.json), **_render_kwargs(args))
    if args.json:
        print_json(out)
        return 0
    env = out["environment"]
    console.print(f"{out['path']} render, {out['width']}×{out['height']} px, {out['spp']} spp, {out['passes']} "
                  f"Mitsuba passes ({out['variant']}) in {out['seconds']:.1f} s; environment "
                  f"{env['width']}×{env['height']} (level {env.get('level')}).")
    if out.get("note"):
        console.print(f"[yellow]note:[/yellow] {escape(out['note'])}")
    _print_environment_sun(env)
    for k, v in out["files"].items():
        console.print(f"  {k}: {v}")
    return 0


def cmd_render_series(args) -> int:

    out = render_series(args.series, args.output, exposure=args.exposure, progress=_progress(not args.json),
                        **_render_kwargs(args))
    if args.json:
        print_json(out)
        return 0
    console.print(f"{out['n_slots']} slots rendered into {Path(args.output)}: contact sheet {out['contact_sheet']}, "
                  f"frames {Path(out['frames']) / 'frame_%04d.png'}")
    return 0


def cmd_relight(args) -> int:

    whites = [parse_white(w) for w in args.white]
    out = relight_product(args.product, args.output, whites, to=args.to, reflectance=args.white_reflectance,
                          sources=args.sources, method=args.method, source_factor=args.source_factor,
                          progress=_progress(not args.json))
    if args.json:
        print_json(out)
        return 0
    console.print(f"Relit {out['width']}×{out['height']} px to {escape(args.to)} from {len(whites)} white "
                  f"reference(s) in {out['seconds']:.1f} s ({out['tiles']} tiles); {out['light_source_pixels']} "
                  f"pixels brighter than {args.source_factor:g}× the lit white (light sources, sky) "
                  f"{'kept' if args.sources == 'keep' else 'relit'} and flagged.")
    console.print(f"Product: {out['output']} (export / view / render it like any product)")
    for k, v in out["previews"].items():
        console.print(f"  preview {k}: {v}")
    return 0


def _add_render_args(p) -> None:
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output directory")
    p.add_argument("--scene", default="mirror-ball", metavar="mirror-ball|FILE.xml",
                   help="the paper's mirror ball on a grey plate (default) or a Mitsuba scene file whose spectral "
                        "parameters are CSV files (<spectrum name=\"reflectance\" filename=\"paint.csv\"/>); the "
                        "file's film width/height and sampler sample_count are used unless --width, --height or "
                        "--spp is given")
    p.add_argument("--width", type=int, default=None, metavar="PX",
                   help="image width (default: a --scene file's film width, else 256; this option wins over the "
                        "scene file)")
    p.add_argument("--height", type=int, default=None, metavar="PX",
                   help="image height (default: a --scene file's film height, else 256; this option wins over the "
                        "scene file)")
    p.add_argument("--spp", type=int, default=None, metavar="N",
                   help="samples per pixel (default: a --scene file's sampler sample_count, else 64; this option "
                        "wins over the scene file)")
    p.add_argument("--level", type=int, default=None, help="pyramid level of the environment (default: the finest "
                                                            "at most --env-width wide)")
    p.add_argument("--env-width", type=int, default=1024, metavar="PX")
    p.add_argument("--wavelength-step", type=float, default=None, metavar="NM",
                   help="coarser spectral grid (default: the estimator's 5 nm, 61 wavelengths = 21 passes)")
    p.add_argument("--fast", action="store_true", help="six-band fast path (2 passes; exact only for "
                                                       "wavelength-flat materials)")
    p.add_argument("--view-lon", type=float, default=0.0, metavar="DEG", help="mirror ball: longitude the camera faces")
    p.add_argument("--elevation", type=float, default=15.0, metavar="DEG", help="mirror ball: camera elevation")
    p.add_argument("--metal", default=None, metavar="silver|aluminium|FILE.csv", help="mirror ball: the metal "
                                                                                       "(default silver)")
    p.add_argument("--variant", default=None, choices=["scalar_rgb", "llvm_ad_rgb"],
                   help="Mitsuba variant (default: llvm_ad_rgb when an LLVM library is installed)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", action="store_true")


def add_commands(sub) -> None:
    """Register ``render``, ``render-series`` and ``relight``."""
    r = sub.add_parser("render", help="spectral rendering lit by a product's panorama (Mitsuba 3)",
                       description="Image-based spectral rendering (paper Sec. 6.1): the product's spectral radiance "
                                   "as environment map, rendered by Mitsuba 3 three wavelengths per pass; writes a "
                                   "spectral EXR (Fichet 2021 layout), a linear sRGB EXR and a tone-mapped PNG.")
    r.add_argument("product", metavar="PRODUCT")
    _add_render_args(r)
    r.set_defaults(func=cmd_render)

    s = sub.add_parser("render-series", help="render every slot of a processed time-lapse (Fig. 16)",
                       description="Render each slot of a process-series output with the same scene; a frame "
                                   "sequence (frames/frame_0000.png …) and a labelled contact sheet.")
    s.add_argument("series", metavar="SERIES")
    _add_render_args(s)
    s.add_argument("--exposure", choices=["auto", "common"], default="auto",
                   help="tone-map each frame for itself, or all with the brightest slot's exposure")
    s.set_defaults(func=cmd_render_series)

    e = sub.add_parser("relight", help="relight a product to another illuminant from a white reference",
                       description="Spectral relighting (paper Sec. 6.2): the illuminant measured on white "
                                   "reference(s) in the scene, reflectance estimated per pixel under it, colour "
                                   "signals under the new illuminant; tile by tile into a product-like directory.")
    e.add_argument("product", metavar="PRODUCT")
    e.add_argument("--white", action="append", required=True, metavar="LON,LAT[,RADIUS_DEG]",
                   help="a white reference's direction (repeat for several; interpolated between them); write "
                        "--white=-30,0 when the longitude is negative")
    e.add_argument("--to", default="A", metavar="A|D65|FILE.csv", help="the new illuminant (default A)")
    e.add_argument("--white-reflectance", default=None, metavar="0.95|FILE.csv",
                   help="the white reference's reflectance (default flat 0.95)")
    e.add_argument("--sources", choices=["keep", "relight"], default="keep",
                   help="pixels brighter than the lit white (lamps, sky): keep as captured (default) or relight")
    e.add_argument("--source-factor", type=float, default=2.0, metavar="FACTOR",
                   help="a pixel is a light source above FACTOR times a perfect white's luminance under its light "
                        "(default 2: the illuminance varies over a room)")
    e.add_argument("--method", choices=["wiener", "ratio"], default="wiener",
                   help="reflectance by Wiener estimation under the measured light (default) or the paper's signal / "
                        "illuminant ratio")
    e.add_argument("-o", "--output", required=True, metavar="OUT")
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=cmd_relight)
