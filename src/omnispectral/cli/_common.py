"""Shared helpers of the command-line front end."""

from __future__ import annotations

import json
import sys

from rich.console import Console

console = Console(stderr=False)
err_console = Console(stderr=True, soft_wrap=True)  # one-line errors stay one line


def print_json(data) -> None:
    """Print ``data`` as indented JSON on standard output (nothing else goes to stdout with ``--json``)."""
    sys.stdout.write(json.dumps(data, indent=2) + "\n")
