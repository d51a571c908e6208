"""``omnispectral plan | session verify``: acquisition planning and session checks (paper Sec. 4.5, 5.5)."""

from __future__ import annotations

from rich.markup import escape
from rich.table import Table

from omnispectral.capture.plan import format_duration, make_plan, plot_tradeoff, tradeoff
from omnispectral.capture.resume import repair_session
from omnispectral.capture.session import verify_session
from omnispectral.cli._common import console, print_json
from omnispectral.io import atomic_write_json
from omnispectral.rig import one_camera_rig, resolve_rig, rig_with_camera_settings

__all__ = ["cmd_plan", "cmd_session_repair", "cmd_session_verify", "rig_from_args"]


def rig_from_args(args, default_preset: str | None = None):
    preset = args.preset if args.preset or args.rig else default_preset
    rig = resolve_rig(preset, args.rig)
    if not getattr(args, "one_camera", False) or rig.camera_names == ("A",):
        return rig
    return rig_with_camera_settings(one_camera_rig(rig), {"A": {"filter": "none"}})


def cmd_plan(args) -> int:
    rig = rig_from_args(args)
    plan = make_plan(rig, overlap=args.overlap)
    out = plan.to_dict()
    if args.tradeoff:
        rows = tradeoff(rig)
        png = args.tradeoff if args.tradeoff.endswith(".png") else args.tradeoff + ".png"
        plot_tradeoff(rig, rows, png)
        js = png[:-4] + ".json"
        ref = make_plan(rig)  # the rig's own grid (marked on the plot), whatever --overlap asked for
        atomic_write_json(js, {"rig": rig.name,
                               "reference": {"overlap": ref.overlap, "overlap_pan": ref.overlap_pan,
                                             "overlap_tilt": ref.overlap_tilt, "n_directions": ref.n_directions,
                                             "estimated_s": ref.estimated_s},
                               "curve": rows})
        out["tradeoff"] = {"png": png, "json": js}
    if args.json:
        print_json(out)
        return 0
    t = out["timing_s"]
    console.print(f"[bold]{escape(rig.name)}[/bold]: {plan.n_pan} x {plan.n_tilt} = {plan.n_directions} directions, "
                  f"overlap {100 * plan.overlap_pan:.1f} % (pan) / {100 * plan.overlap_tilt:.1f} % (tilt) per side, "
                  f"{len(plan.exposures_s)} exposures {max(plan.exposures_s) * 1e3:.4g} ms -> "
                  f"{min(plan.exposures_s) * 1e3:.4g} ms")
    table = Table(title=f"Estimated acquisition time: {format_duration(plan.estimated_s)}")
    columns = [("head moves", "moves"), ("settling", "settle"), ("exposures", "exposures"), ("read-out", "readout"),
               *([("sun bracket", "sun_bracket")] if "sun_bracket" in t else []), ("per direction", "per_direction"),
               ("total", "total")]
    for col, _ in columns:
        table.add_column(col, justify="right")
    table.add_row(*(format_duration(t[k]) for _, k in columns))
    console.print(table)
    if plan.sun_bracket:
        console.print(f"sun bracket: through {plan.sun_bracket['filter']} "
                      f"({len(plan.sun_bracket['exposures_s'])} exposures), aimed at the sun once a direction's "
                      f"shortest exposure clips; filter changer: {plan.sun_bracket['changer']}")
    if plan.dark_extension:
        dark = plan.dark_extension
        console.print(f"dark extension: {', '.join(f'{t * 1e3:.4g}' for t in dark['exposures_s'])} ms on both "
                      f"cameras where the darkest {dark['percentile']:g} % of a direction's pixels stay below a "
                      f"signal-to-noise ratio of {dark['snr']:g} in the longest exposure; at most "
                      f"+{format_duration(dark['max_s_per_direction'])} per such direction, not in the total "
                      f"({format_duration(plan.estimated_max_s)} if every direction needs it)")
    if args.tradeoff:
        console.print(f"Overlap trade-off (paper Fig. 15a; the rig's own grid marked at "
                      f"{100 * make_plan(rig).overlap:.1f} %): {out['tradeoff']['png']} and {out['tradeoff']['json']}")
    return 0


def cmd_session_verify(args) -> int:
    report = verify_session(args.session, check_pixels=args.pixels)
    if args.json:
        print_json(report)
    else:
        state = "[green]complete[/green]" if report["complete"] else "[red]incomplete[/red]"
        console.print(f"{escape(report['session'])}: {state}, {report['n_ok']} of {report['n_planned']} frames good, "
                      f"{report['n_missing']} missing, {report['n_damaged']} damaged"
                      + (", journal cut mid-line (repaired on resume)" if report["journal_partial_last_line"] else ""))
        for item in report["damaged"] + report["missing"][:50]:
            console.print(escape(f"  {item['file']}: {item['problem']}"))
        if report["n_missing"] > 50:
            console.print(f"  … and {report['n_missing'] - 50} more missing")
        for bad in report["journal_bad_lines"]:
            console.print(f"  journal.jsonl line {bad['line']}: {escape(bad['problem'])}")
        if report["journal_bad_lines"]:
            console.print(f"  (omnispectral session repair {escape(report['session'])} rebuilds the journal from "
                          f"the frames)")
        if any(item["file"].startswith("frames/") for item in report["damaged"]):
            console.print(f"  (omnispectral session repair {escape(report['session'])} --apply quarantines damaged "
                          f"frames; a resume captures them again)")
    return 0 if report["complete"] else 1


def cmd_session_repair(args) -> int:

    out = repair_session(args.session, apply=args.apply)
    if args.json:
        print_json(out)
        return 0
    s = escape(out["session"])
    moved = "quarantined" if out["applied"] else "to be quarantined"
    console.print(f"{s}: {out['n_frames']} frames decode with their records; the journal lists "
                  f"{out['n_journal_records']} ({len(out['journal_bad_lines'])} bad lines"
                  + (", cut last line" if out["journal_partial_last_line"] else "") + f"); "
                  f"{out['n_recovered']} frames would be added, {out['n_dropped']} records dropped, "
                  f"{out['n_changed']} changed, {out['n_quarantined']} damaged frames {moved}")
    for d in out["damaged_frames"][:20]:
        console.print(escape(f"  {d['file']}: {d['problem']} ({moved} as {d['quarantine']}; "
                             "captured again on resume)"))
    if out["n_quarantined"] > 20:
        console.print(f"  … and {out['n_quarantined'] - 20} more damaged frames {moved}")
    if not out["needed"]:
        console.print("The journal already matches the frames; nothing to do.")
    elif out["applied"]:
        console.print(f"Journal rebuilt (old one kept as {escape(out.get('backup', '-'))}).")
    else:
        console.print(f"Dry run: nothing changed. Apply with: omnispectral session repair {s} --apply")
    return 0
