"""``omnispectral import``: the arguments; run by :mod:`omnispectral.cli.importer`."""

from __future__ import annotations

from omnispectral.choices import RESPONSES
from omnispectral.cli.parsers.capture import add_rig_args

__all__ = ["add_commands"]


def add_commands(sub) -> None:
    """Register ``import``."""
    p = sub.add_parser("import", help="build a session from images made elsewhere (Papywizard, Hugin, CSV)",
                       description="Build a capture session from existing images (TIFF, PNG, JPEG) of one camera of "
                                   "the rig: directions from a CSV (file,pan_deg,tilt_deg), a Papywizard XML or a "
                                   "Hugin .pto; exposure times from the CSV, a table or EXIF. Run once per camera "
                                   "into the same session (a rig with camera A only, or --one-camera, makes a "
                                   "three-band session); 'omnispectral process' works on it as on a capture.")
    add_rig_args(p)
    p.add_argument("--camera", default="A", choices=["A", "B"], help="the rig camera the images are from (default A)")
    p.add_argument("--directions", required=True, metavar="FILE.csv|FILE.xml|FILE.pto",
                   help="where each image looked: CSV file,pan_deg,tilt_deg; Papywizard XML; Hugin project")
    p.add_argument("--images", default=None, metavar="DIR",
                   help="the images (name order = Papywizard picture order; CSV names are looked up here)")
    p.add_argument("--exposures", default=None, metavar="TABLE",
                   help="exposure times: CSV file,exposure_s or 'name seconds' lines (default: EXIF ExposureTime)")
    p.add_argument("--response", default="auto", choices=list(RESPONSES),
                   help="how values relate to light: linear (raw, 16-bit), srgb (JPEG/PNG); auto: srgb for 8-bit")
    p.add_argument("--reference", action="store_true",
                   help="leave the images where they are: the journal records each file's absolute path, size, "
                        "modification time and SHA-256 (session verify names a moved or changed one) instead of "
                        "copying it into the session")
    p.add_argument("-o", "--output", required=True, metavar="SESSION", help="session directory (created or added to)")
    p.add_argument("--json", action="store_true", help="print a JSON summary")
    p.set_defaults(func="omnispectral.cli.importer:cmd_import")
