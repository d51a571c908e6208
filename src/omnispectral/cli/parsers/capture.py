"""``omnispectral plan | session verify | session repair``: the arguments, and the rig options other commands
share (:func:`add_rig_args`); run by :mod:`omnispectral.cli.capture`."""

from __future__ import annotations

from omnispectral.choices import PRESETS

__all__ = ["add_commands", "add_rig_args"]


def add_rig_args(p) -> None:
    g = p.add_mutually_exclusive_group()
    g.add_argument("--preset", choices=PRESETS, default=None, help="built-in rig of the paper (or 'small')")
    g.add_argument("--rig", default=None, metavar="FILE.toml", help="rig description file")
    p.add_argument("--one-camera", action="store_true",
                   help="use the rig's camera A alone and without its filter: one plain RGB camera, three bands "
                        "(take the filter off the lens; for a filtered one-camera rig write a rig file with only "
                        "[cameras.A], which is one-camera already)")


def add_commands(sub) -> None:
    """Register ``plan`` and ``session verify``."""
    p = sub.add_parser("plan", help="direction grid, overlap and acquisition time of a rig",
                       description="Plan a capture: the pan/tilt direction grid (serpentine order), its overlap and "
                                   "the estimated acquisition time (paper Table 2, Sec. 5.5).")
    add_rig_args(p)
    p.add_argument("--overlap", type=float, default=None, metavar="F",
                   help="per-side overlap fraction (0-0.5); default: the rig's own grid")
    p.add_argument("--tradeoff", default=None, metavar="OUT.png",
                   help="also write the overlap / directions / time curve (paper Fig. 15a) as PNG and JSON")
    p.add_argument("--json", action="store_true", help="print the plan as JSON")
    p.set_defaults(func="omnispectral.cli.capture:cmd_plan")

    s = sub.add_parser("session", help="inspect capture sessions", description="Inspect capture sessions.")
    ssub = s.add_subparsers(dest="session_command", metavar="SUBCOMMAND", required=True)
    v = ssub.add_parser("verify", help="check a session against its plan and checksums",
                        description="Check completeness against the plan and every frame's SHA-256; name every "
                                    "missing or damaged frame. Exit status 1 when the session is incomplete.")
    v.add_argument("session", metavar="SESSION")
    v.add_argument("--pixels", action="store_true",
                   help="also decode every frame and check its pixels (the pixel checksum it embeds, the camera's "
                        "full scale)")
    v.add_argument("--json", action="store_true", help="print the report as JSON")
    v.set_defaults(func="omnispectral.cli.capture:cmd_session_verify")
    r = ssub.add_parser("repair", help="rebuild a session's journal from its frames (dry run by default)",
                        description="Every raw frame embeds its journal record: rebuild journal.jsonl from the frames "
                                    "that decode (garbage lines, lost or cut lines). Damaged frames (a checksum "
                                    "mismatch, pixels above full scale) are never given a new checksum: --apply moves "
                                    "them to SESSION/quarantine/ and a resume captures them again. Reports what would "
                                    "change; "
                                    "--apply writes it (the old journal is kept as journal.jsonl.bak-TIME).")
    r.add_argument("session", metavar="SESSION")
    r.add_argument("--apply", action="store_true", help="write the rebuilt journal and quarantine damaged "
                                                      "frames (default: dry run)")
    r.add_argument("--json", action="store_true", help="print the report as JSON")
    r.set_defaults(func="omnispectral.cli.capture:cmd_session_repair")
