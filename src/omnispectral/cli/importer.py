"""``omnispectral import``: a session from images made elsewhere (:mod:`omnispectral.capture.importer`)."""

from __future__ import annotations

from omnispectral.capture.importer import import_images, list_images, read_directions, read_exposure_table
from omnispectral.cli._common import ProgressBars, console, print_json
from omnispectral.cli.capture import rig_from_args

__all__ = ["cmd_import"]


def cmd_import(args) -> int:
    rig = rig_from_args(args)
    images = list_images(args.images) if args.images else None
    entries = read_directions(args.directions, images)
    table = read_exposure_table(args.exposures) if args.exposures else None
    with ProgressBars(enabled=not args.json, transient=True) as bars:
        out = import_images(args.output, rig, args.camera, entries, exposure_table=table, response=args.response,
                            reference=args.reference, progress=bars)
    if args.json:
        print_json(out)
    else:
        console.print(f"{'Referenced' if out['referenced'] else 'Imported'} {out['n_images']} images of camera "
                      f"{out['camera']} ({out['n_directions']} "
                      f"directions x {out['n_exposures']} exposures) into {out['session']}; cameras in the session: "
                      f"{', '.join(out['cameras_imported'])}"
                      + ("" if len(out["cameras_imported"]) == len(rig.cameras) else
                         " (import the other camera with --camera before 'omnispectral process')"))
    return 0
