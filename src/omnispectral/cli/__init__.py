"""Command-line interface: thin argument parsing over the library.

Every command has ``--help``; commands that report numbers have ``--json``.  Errors derived from
:class:`~omnispectral.errors.OmnispectralError` are printed as one line (exit status 2).  Each area
of the package registers its commands from its own module (``add_commands(subparsers)``).
"""

from __future__ import annotations

import argparse
import importlib

from rich.markup import escape

from omnispectral import __version__
from omnispectral.cli._common import err_console
from omnispectral.errors import OmnispectralError, describe_os_error

#: Modules of ``omnispectral.cli`` that register sub-commands, in the order ``--help`` lists them.
COMMAND_MODULES = ("spectral", "hdr", "lens", "capture", "register", "simulate", "devices", "importer", "mosaic",
                   "product", "view", "apps")


def build_parser() -> argparse.ArgumentParser:
    """The full ``omnispectral`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="omnispectral",
        description="HDR spectral imaging of omnidirectional scenes with a six-band two-camera rig "
                    "(Hirai et al. 2018).")
    parser.add_argument("--version", action="version", version=f"omnispectral {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"omnispectral.cli.{name}").add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except OmnispectralError as exc:
        err_console.print(f"[bold red]error:[/bold red] {escape(str(exc))}")  # user text is not markup
        return 2
    except OSError as exc:  # disk full, read-only or unwritable output, vanished input: one line, no traceback
        err_console.print(f"[bold red]error:[/bold red] {escape(describe_os_error(exc))}")
        return 1
    except KeyboardInterrupt:
        err_console.print("interrupted")
        return 130
