"""``omnispectral devices list | probe``: the arguments; run by :mod:`omnispectral.cli.devices`."""

from __future__ import annotations

__all__ = ["add_commands"]


def add_commands(sub) -> None:
    """Register ``devices list`` and ``devices probe``."""
    d = sub.add_parser("devices", help="cameras and serial ports found; probe a rig's devices",
                       description="Find GenICam cameras (through GenTL producers) and serial ports, or talk to "
                                   "the devices a rig file names.")
    dsub = d.add_subparsers(dest="devices_command", metavar="SUBCOMMAND", required=True)
    lst = dsub.add_parser("list", help="GenTL cameras and serial ports found",
                          description="List the cameras the GenTL producers offer (from --cti and "
                                      "GENICAM_GENTL64_PATH) and the serial ports of this computer.")
    lst.add_argument("--cti", action="append", default=[], metavar="FILE.cti|simulator",
                     help="GenTL producer to load (repeatable); 'simulator' is the one shipped in the genicam package")
    lst.add_argument("--json", action="store_true", help="print the lists as JSON")
    lst.set_defaults(func="omnispectral.cli.devices:cmd_devices_list")
    p = dsub.add_parser("probe", help="talk to each device of a rig and print what it answered",
                        description="Open the head and the cameras the rig names, read their identity, resolution "
                                    "and position (nothing moves), and close them. Exit status 1 if one fails.")
    p.add_argument("--rig", required=True, metavar="FILE.toml", help="rig description file")
    p.add_argument("--json", action="store_true", help="print the answers as JSON")
    p.set_defaults(func="omnispectral.cli.devices:cmd_devices_probe", preset=None)
