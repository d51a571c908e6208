"""Command-line interface: thin argument parsing over the library.

Every command has ``--help``; commands that report numbers have ``--json``.  Errors derived from
:class:`~omnispectral.errors.OmnispectralError` are printed as one line.  Exit status (README): 0 success;
2 the command line is wrong (argparse's usage errors, and :class:`~omnispectral.errors.ConfigurationError`:
a value or combination of options that makes no sense); 1 the work failed (a missing, unreadable or
invalid file, a device, a lock, the disk); 130 interrupted.  Progress bars go to standard error, only when
it is a terminal and ``--quiet`` is not given.  ``--version`` answers before any command module (and
colour-science, NumPy…) is imported.

Each area of the package registers its commands from a light module of :mod:`omnispectral.cli.parsers`
(``add_commands(subparsers)``: argparse and :mod:`omnispectral.choices` only), so ``omnispectral --help`` and
``omnispectral COMMAND --help`` import nothing heavy.  A command's ``func`` default names the function that runs it,
``"omnispectral.cli.AREA:cmd_NAME"``; :func:`main` imports that module (and with it the library) only to run the
command, inside its error handling: a missing optional dependency (:mod:`omnispectral.extras`) is one line, exit 1.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Callable

from rich.markup import escape

from omnispectral import __version__
from omnispectral.cli import _common
from omnispectral.errors import ConfigurationError, InputFileError, OmnispectralError, describe_os_error
from omnispectral.extras import missing_extra_message
from omnispectral.ownership import check_output_outside_inputs

#: Exit status of a command line that is wrong (argparse uses it too) and of work that failed.
EXIT_USAGE, EXIT_FAILURE = 2, 1

#: Modules of ``omnispectral.cli.parsers`` that register sub-commands, in the order ``--help`` lists them (each
#: command runs in the module of ``omnispectral.cli`` of the same name).
COMMAND_MODULES = ("spectral", "hdr", "lens", "capture", "register", "simulate", "devices", "importer", "mosaic",
                   "product", "view", "apps")


#: Argument names (argparse ``dest``) of what a command writes and of what it reads: no output may be, or lie
#: inside, an input (:mod:`omnispectral.ownership`).  Values that are not existing paths (a scene's name) are
#: ignored on the input side.
OUTPUT_DESTS = ("output", "out", "json_out", "save_response", "tradeoff", "plot")
INPUT_DESTS = ("session", "product", "series", "rig", "rig_calibration", "chessboard", "reference", "moving",
               "input", "images", "files", "scene", "times_list", "response", "directions", "exposures",
               "dark_frames", "cube", "prior_set", "cti")


def paths_of(args: argparse.Namespace, dests: tuple[str, ...]) -> list:
    """The values of ``args`` under ``dests``, lists flattened (non-path values are left to the caller)."""
    out = []
    for dest in dests:
        value = getattr(args, dest, None)
        out.extend(value if isinstance(value, list | tuple) else [value])
    return out


def exit_status(exc: OmnispectralError) -> int:
    """1 for a bad input (file, device, lock…), 2 for a command line that makes no sense (module docstring)."""
    usage = isinstance(exc, ConfigurationError) and not isinstance(exc, InputFileError)
    return EXIT_USAGE if usage else EXIT_FAILURE


def build_parser() -> argparse.ArgumentParser:
    """The full ``omnispectral`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="omnispectral",
        description="HDR spectral imaging of omnidirectional scenes with a six-band two-camera rig "
                    "(Hirai et al. 2018).")
    parser.add_argument("--version", action="version", version=f"omnispectral {__version__}")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(f"omnispectral.cli.parsers.{name}").add_commands(sub)
    return parser


def command_function(target: str) -> Callable[[argparse.Namespace], int]:
    """The function a command's ``func`` default names, ``"module:function"``; its module is imported now."""
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def main(argv: list[str] | None = None) -> int:
    words = sys.argv[1:] if argv is None else list(argv)
    if words[:1] == ["--version"]:  # fast path: no command module (colour-science, NumPy, …) imported
        sys.stdout.write(f"omnispectral {__version__}\n")
        return 0
    parser = build_parser()
    args = parser.parse_args(words)
    _common.QUIET = bool(getattr(args, "quiet", False))
    try:
        check_output_outside_inputs(paths_of(args, OUTPUT_DESTS), paths_of(args, INPUT_DESTS))
        return command_function(args.func)(args)  # the command's module is imported here, inside the handlers
    except OmnispectralError as exc:
        _common.err_console.print(f"[bold red]error:[/bold red] {escape(str(exc))}")  # user text is not markup
        return exit_status(exc)
    except OSError as exc:  # disk full, read-only or unwritable output, vanished input: one line, no traceback
        _common.err_console.print(f"[bold red]error:[/bold red] {escape(describe_os_error(exc))}")
        return EXIT_FAILURE
    except ModuleNotFoundError as exc:  # an optional dependency (omnispectral.extras) that is not installed
        message = missing_extra_message(exc)
        if message is None:
            raise
        _common.err_console.print(f"[bold red]error:[/bold red] omnispectral {args.command}: {escape(message)}")
        return EXIT_FAILURE
    except KeyboardInterrupt:
        _common.err_console.print("interrupted")
        return 130
