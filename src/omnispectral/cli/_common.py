"""Shared helpers of the command-line front end."""

from __future__ import annotations

import json
import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

__all__ = ["PIPE_WIDTH", "QUIET", "ProgressBars", "console", "err_console", "print_json", "progress_wanted"]

#: Set by ``main`` from ``--quiet``: no progress bars.
QUIET = False
#: Width of tables and text when standard output is not a terminal (a pipe, a file): wide enough that
#: nothing is cut or wrapped at Rich's default of 80 columns; a table takes only the width it needs.
PIPE_WIDTH = 4000


def _stdout_console() -> Console:
    return Console(stderr=False) if sys.stdout.isatty() else Console(stderr=False, width=PIPE_WIDTH)


console = _stdout_console()
err_console = Console(stderr=True, soft_wrap=True)  # one-line errors stay one line


def print_json(data) -> None:
    """Print ``data`` as indented JSON on standard output (nothing else goes to stdout with ``--json``)."""
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


def progress_wanted(enabled: bool = True) -> bool:
    """Whether to draw progress: asked for, no ``--quiet``, and standard error is a terminal."""
    return enabled and not QUIET and err_console.is_terminal


class ProgressBars:
    """Rich progress bars on standard error for the library's ``progress(stage, done, total)`` callbacks.

    Use as a context manager and pass the object itself as the callback; one bar per stage, created
    on the stage's first report, and started again (its elapsed time too) when the stage reports fewer units
    done than before (a stage run once per slot of a series).  Nothing is drawn with ``enabled=False`` (e.g.
    with ``--json``), with ``--quiet``, or when standard error is not a terminal (a log file gets no bar frames).
    """

    def __init__(self, enabled: bool = True, transient: bool = False):
        self.enabled = progress_wanted(enabled)
        self.bar = Progress(TextColumn("{task.description:>16}"), BarColumn(), MofNCompleteColumn(),
                            TimeElapsedColumn(), console=err_console, disable=not self.enabled, transient=transient)
        self.tasks: dict[str, int] = {}
        self.done: dict[str, int] = {}  # the last report's units done, per stage

    def __enter__(self) -> ProgressBars:
        self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.stop()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.bar.add_task(stage, total=total)
        elif done < self.done[stage]:  # the stage starts again (the next slot's frames): its clock too
            self.bar.reset(self.tasks[stage], total=total, completed=done)
        self.done[stage] = done
        self.bar.update(self.tasks[stage], completed=done, total=total)
