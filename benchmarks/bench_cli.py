"""How long ``omnispectral --help`` and ``omnispectral COMMAND --help`` take, each in a fresh process.

    .venv/bin/python benchmarks/bench_cli.py [--repeat 5] [--limit 1.0] [--json OUT.json]

Every command and sub-command of the parser (``omnispectral``, ``omnispectral process``, ``omnispectral calibrate
lens``…) is run with ``--help`` ``--repeat`` times through the installed ``omnispectral`` console script (or
``python -m omnispectral`` where there is none), interleaved so that a burst of load elsewhere spreads over all
commands; the table gives the median, fastest and slowest wall time of each.  The load average before and after is
printed with it: the bound is for an idle machine, and a loaded one (other builds, tests) is slower.  Exit status 1
when any median exceeds ``--limit`` seconds (the parsers import nothing heavy: see ``omnispectral.cli.parsers``).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from omnispectral.cli import build_parser

__all__ = ["help_commands", "launcher", "main", "time_help"]


def help_commands() -> list[list[str]]:
    """Every command path of the parser, the bare program first: ``[]``, ``["spectral"]``, ``["spectral",
    "evaluate"]``…"""

    def walk(parser: argparse.ArgumentParser, path: list[str]):
        yield path
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    yield from walk(sub, [*path, name])

    return list(walk(build_parser(), []))


def launcher(python_m: bool = False) -> list[str]:
    """The ``omnispectral`` console script beside this interpreter, else ``python -m omnispectral``."""
    script = Path(sys.executable).with_name("omnispectral")
    return [str(script)] if script.is_file() and not python_m else [sys.executable, "-m", "omnispectral"]


def time_help(command: list[str], words: list[str]) -> float:
    """Wall time of one ``COMMAND … --help`` in a new process (s); the help must be printed, exit status 0."""
    t0 = time.perf_counter()
    r = subprocess.run([*command, *words, "--help"], capture_output=True, text=True, timeout=120)
    elapsed = time.perf_counter() - t0
    if r.returncode != 0 or not r.stdout.startswith("usage: omnispectral"):
        raise SystemExit(f"{' '.join(['omnispectral', *words, '--help'])}: exit {r.returncode}\n{r.stderr}")
    return elapsed


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5, help="runs per command (at least 5; the median is reported)")
    ap.add_argument("--limit", type=float, default=1.0, help="largest median allowed, s (default 1.0)")
    ap.add_argument("--python-m", action="store_true", help="run 'python -m omnispectral' instead of the script")
    ap.add_argument("--json", default=None, metavar="OUT.json", help="also write the numbers as JSON")
    args = ap.parse_args()
    if args.repeat < 5:
        ap.error("--repeat must be at least 5")
    command = launcher(args.python_m)
    paths = help_commands()
    load_before = os.getloadavg()
    times: dict[str, list[float]] = {" ".join(["omnispectral", *p]): [] for p in paths}
    for _ in range(args.repeat):  # interleaved: every command once per round
        for p in paths:
            times[" ".join(["omnispectral", *p])].append(time_help(command, p))
    load_after = os.getloadavg()
    rows = {name: {"median_s": statistics.median(t), "min_s": min(t), "max_s": max(t)} for name, t in times.items()}
    width = max(map(len, rows)) + len(" --help")
    print(f"{' '.join(command)}; {args.repeat} runs per command; {os.cpu_count()} CPUs; load average (1, 5, 15 min) "
          f"{' '.join(f'{x:.2f}' for x in load_before)} before, {' '.join(f'{x:.2f}' for x in load_after)} after")
    print(f"{'command':<{width}}  median s   min s   max s")
    for name, r in rows.items():
        flag = "  > limit" if r["median_s"] > args.limit else ""
        print(f"{name + ' --help':<{width}}  {r['median_s']:8.3f}  {r['min_s']:6.3f}  {r['max_s']:6.3f}{flag}")
    worst = max(rows, key=lambda k: rows[k]["median_s"])
    over = [k for k, r in rows.items() if r["median_s"] > args.limit]
    print(f"slowest median: {worst} --help, {rows[worst]['median_s']:.3f} s (limit {args.limit:g} s); "
          f"{len(over)} of {len(rows)} over the limit")
    if args.json:
        Path(args.json).write_text(json.dumps({"command": command, "repeat": args.repeat, "limit_s": args.limit,
                                               "cpus": os.cpu_count(), "load_before": load_before,
                                               "load_after": load_after, "commands": rows}, indent=2) + "\n")
    return 1 if over else 0


if __name__ == "__main__":
    sys.exit(main())
