"""``omnispectral render | render-series | relight``: the paper's applications (Sec. 6)."""

from __future__ import annotations

from pathlib import Path

from rich.markup import escape

from omnispectral.apps.materials import load_metal
from omnispectral.apps.relight import parse_white, relight_product
from omnispectral.apps.render import render_product
from omnispectral.apps.series import render_series
from omnispectral.cli._common import ProgressBars, console, print_json

__all__ = ["cmd_relight", "cmd_render", "cmd_render_series"]


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

    with ProgressBars(enabled=not args.json, transient=True) as bars:  # from the start: reading the product
        out = render_product(args.product, args.output, progress=bars, **_render_kwargs(args))
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

    with ProgressBars(enabled=not args.json, transient=True) as bars:  # slots, and each slot's passes
        out = render_series(args.series, args.output, exposure=args.exposure, progress=bars,
                            **_render_kwargs(args))
    if args.json:
        print_json(out)
        return 0
    folders = [Path(s["folder"]).name for s in out["slots"]]
    console.print(f"{out['n_slots']} slots rendered into {Path(args.output)}: contact sheet {out['contact_sheet']}, "
                  f"frames {Path(out['frames']) / 'frame_%04d.png'}")
    console.print("slot folders: " + escape(", ".join(folders) if len(folders) <= 4
                                            else f"{folders[0]}, {folders[1]} … {folders[-1]}"))
    return 0


def cmd_relight(args) -> int:

    whites = [parse_white(w) for w in args.white]
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = relight_product(args.product, args.output, whites, to=args.to, reflectance=args.white_reflectance,
                              sources=args.sources, method=args.method, source_factor=args.source_factor,
                              progress=bars)
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
