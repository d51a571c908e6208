"""``omnispectral spectral …``: six-band system, Wiener estimation, accuracy, filter selection."""

from __future__ import annotations

from rich.table import Table

from omnispectral.choices import DEFAULT_FILTERS
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.errors import ConfigurationError
from omnispectral.io import atomic_write_json
from omnispectral.spectral import library as lib
from omnispectral.spectral.evaluate import PAPER_FIGURES, Protocol, evaluate, public
from omnispectral.spectral.noise import CMV2000
from omnispectral.spectral.plots import plot_estimates
from omnispectral.spectral.select import select_filters

__all__ = ["cmd_spectral_evaluate", "cmd_spectral_list", "cmd_spectral_select"]


# --------------------------------------------------------------------------------- spectral
def _protocol_from_args(args):
    return Protocol(
        target=args.target, illuminant=args.illuminant, camera=args.camera, filters=tuple(args.filter),
        noise=CMV2000 if args.noise == "on" else None, patch_px=args.patch_px, seed=args.seed,
        normalized=not args.absolute, mixture=args.estimator == "mixture", nonnegative=args.nonnegative,
        noise_aware=args.noise_aware, sigma2=args.sigma2,
        **({"prior_reflectances": tuple(args.prior_set)} if args.prior_set else {}),
        **({"prior_illuminants": tuple(args.prior_illuminant)} if args.prior_illuminant else {}),
    )


def cmd_spectral_evaluate(args) -> int:
    if args.filter is None:
        args.filter = list(DEFAULT_FILTERS)
    if len(args.filter) != 2:
        raise ConfigurationError("--filter must be given twice (camera A's and camera B's filter) or not at all")
    result = evaluate(_protocol_from_args(args))
    plot_path = None if args.plot in (None, "none") else plot_estimates(result, args.plot)  # only when asked
    out = public(result)
    out["plot"] = None if plot_path is None else str(plot_path)
    if args.json_out:
        atomic_write_json(args.json_out, out)
    if args.json:
        print_json(out)
        return 0
    table = Table(title=f"Spectral accuracy: {out['n_targets']} {out['target']} targets under {out['illuminant']}")
    for col in ("system", "estimator", "NRMSE", "ΔE*ab", "ΔE00", "max ΔE*ab", "angle°", "paper NRMSE",
                "paper ΔE*ab"):
        table.add_column(col, justify="left" if col in ("system", "estimator") else "right")
    short = "mixture" if args.estimator == "mixture" else "Eq. (7)"
    rows = [("six-band", short, out["six_band"], PAPER_FIGURES["six_band"]),
            ("RGB", short, out["rgb"], PAPER_FIGURES["rgb"])]
    for key, label in (("six_band_pooled", "six-band"), ("rgb_pooled", "RGB")):
        if key in out["alternatives"]:
            rows.append((label, "Eq. (7)", out["alternatives"][key],
                         PAPER_FIGURES["six_band" if label == "six-band" else "rgb"]))
    for label, est, r, paper in rows:
        table.add_row(label, est, f"{r['nrmse']:.4f}", f"{r['delta_e_ab']:.2f}", f"{r['delta_e_2000']:.2f}",
                      f"{r['delta_e_ab_max']:.2f}", f"{r['spectral_angle_deg']:.2f}", f"{paper['nrmse']:.4f}",
                      f"{paper['delta_e_ab']:.2f}")
    console.print(table)
    console.print("[dim]Estimators: 'mixture' = Wiener with one prior component per light source, "
                  "weighted by posterior probability (ours); 'Eq. (7)' = Wiener with the pooled prior (paper).[/dim]")
    console.print(f"[dim]{out['definition']}[/dim]")
    console.print("[dim]Paper figures: Hirai et al. 2018 Sec. 5.2, real rig (Baumer HXG20, 34A + SP-18). "
                  f"Ours: simulated {out['camera']} behind {', '.join(out['filters'])}"
                  + ("" if out["noise"] is None else
                     f", {out['noise']['name']} noise, {out['noise']['patch_px']}² px patches")
                  + ".[/dim]")
    prior = out["six_band"]["prior"]
    console.print(f"[dim]Prior: {prior['n_reflectances']} reflectances x {prior['n_illuminants']} light sources "
                  f"({', '.join(prior['illuminants'])}); {prior['n_excluded_as_held_out']} near-copies of the target "
                  f"or calibration set excluded. sigma^2 tuned on the calibration set: six-band "
                  f"{out['six_band']['sigma2']:.3g}, RGB {out['rgb']['sigma2']:.3g}.[/dim]")
    if "sp18-standin" in [f.lower() for f in out["filters"]]:
        console.print("[yellow]Camera B's filter is a synthetic stand-in for the Fujifilm SP-18 (no published curve); "
                      "pass --filter wratten-34a --filter FILE.csv with a measured curve for real work.[/yellow]")
    if plot_path:
        console.print(f"Plot of six patches (paper Fig. 9 style): {plot_path}")
    if args.json_out:
        console.print(f"Results as JSON: {args.json_out}")
    return 0


def cmd_spectral_select(args) -> int:
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        result = select_filters(args.candidates, top=args.top, camera=args.camera, target=args.target,
                                illuminant=args.illuminant, reference=tuple(args.reference),
                                mixture=args.estimator == "mixture", progress=bars)
    if args.json:
        print_json(result)
        return 0
    console.print(f"[dim]{result['candidates']['note']}[/dim]")
    table = Table(title=f"Best filter pairs of {result['n_pairs']} ({result['candidates']['n_filters']} filters), "
                        f"{result['target']} under {result['illuminant']}")
    for col in ("rank", "filter A", "filter B", "NRMSE", "ΔE*ab"):
        table.add_column(col, justify="right" if col in ("rank", "NRMSE", "ΔE*ab") else "left")
    for r in result["top"]:
        table.add_row(str(r["rank"]), r["filter_a"], r["filter_b"], f"{r['nrmse']:.4f}", f"{r['delta_e_ab']:.2f}")
    ref = result["reference"]
    table.add_row(str(ref["rank"]), ref["filter_a"], ref["filter_b"], f"{ref['nrmse']:.4f}",
                  f"{ref['delta_e_ab']:.2f}", style="yellow")
    console.print(table)
    console.print(f"Reference pair {ref['filter_a']} + {ref['filter_b']} ranks {ref['rank']} of {result['n_pairs'] + 1}"
                  f" (the reference is scored with the same protocol). {result['elapsed_s']:.1f} s.")
    return 0


def cmd_spectral_list(args) -> int:
    data = {"cameras": lib.camera_names(), "filters": lib.filter_names(),
            "reflectance_sets": lib.reflectance_set_names(), "illuminants": lib.illuminant_names(),
            "prior_illuminants": list(lib.PRIOR_ILLUMINANTS),
            "prior_reflectance_sets": list(lib.PRIOR_REFLECTANCE_SETS)}
    if args.json:
        print_json(data)
    else:
        for k, v in data.items():
            console.print(f"[bold]{k}[/bold]: {', '.join(v)}")
    return 0
