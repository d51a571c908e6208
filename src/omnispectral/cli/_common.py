"""Shared helpers of the command-line front end."""

from __future__ import annotations

import json
import sys

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

console = Console(stderr=False)
err_console = Console(stderr=True, soft_wrap=True)  # one-line errors stay one line


def print_json(data) -> None:
    """Print ``data`` as indented JSON on standard output (nothing else goes to stdout with ``--json``)."""
    sys.stdout.write(json.dumps(data, indent=2) + "\n")


class ProgressBars:
    """Rich progress bars on standard error for the library's ``progress(stage, done, total)`` callbacks.

    Use as a context manager and pass the object itself as the callback; one bar per stage, created
    on the stage's first report.  ``enabled=False`` draws nothing (e.g. with ``--json``).
    """

    def __init__(self, enabled: bool = True, transient: bool = False):
        self.bar = Progress(TextColumn("{task.description:>16}"), BarColumn(), MofNCompleteColumn(),
                            TimeElapsedColumn(), console=err_console, disable=not enabled, transient=transient)
        self.tasks: dict[str, int] = {}

    def __enter__(self) -> ProgressBars:
        self.bar.start()
        return self

    def __exit__(self, *exc) -> None:
        self.bar.stop()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if stage not in self.tasks:
            self.tasks[stage] = self.bar.add_task(stage, total=total)
        self.bar.update(self.tasks[stage], completed=done, total=total)
