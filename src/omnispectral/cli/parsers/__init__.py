"""The command line's argument parsers: one light module per area, importing only argparse, the standard library,
:mod:`omnispectral.errors` and :mod:`omnispectral.choices` (names and defaults the library owns), never NumPy,
colour-science, OpenCV, SciPy or Zarr, so ``omnispectral --help`` and ``omnispectral COMMAND --help`` answer at once.

Each module's ``add_commands(subparsers)`` registers its commands, and each command's ``func`` default names the
function that runs it as ``"omnispectral.cli.AREA:cmd_NAME"``; :func:`omnispectral.cli.main` imports that module (and
with it the library) only when the command runs.
"""

import argparse as _argparse
import datetime as _dt

#: Largest ``--seed``: seeds reach NumPy's ``SeedSequence`` and renderers that take an unsigned 32-bit seed.
MAX_SEED = 2**32 - 1


def seed_arg(text: str) -> int:
    """argparse type: a random seed, an integer in 0 – 2³² − 1 (a negative seed used to end in NumPy's traceback)."""
    try:
        value = int(text)
    except ValueError:
        raise _argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value <= MAX_SEED:
        raise _argparse.ArgumentTypeError(f"{value} is outside 0-{MAX_SEED}")
    return value


def positive_int_arg(text: str) -> int:
    """argparse type: an integer ≥ 1 (a count: threads, workers)."""
    try:
        value = int(text)
    except ValueError:
        raise _argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise _argparse.ArgumentTypeError(f"{value} is not a count (at least 1)")
    return value


def date_arg(text: str) -> str:
    """argparse type: a calendar date ``YYYY-MM-DD`` that exists (``2017-02-30`` is refused), returned as given."""
    try:
        _dt.date.fromisoformat(text)
    except ValueError as exc:
        raise _argparse.ArgumentTypeError(f"{text!r} is not a date YYYY-MM-DD ({exc})") from None
    return text
