"""Device drivers on their emulators and the GenTL simulated producer (run by hand; numbers go to docs/benchmarks.md).

    .venv/bin/python benchmarks/bench_devices.py [--repeat 5] [--json-out FILE]

Measured, medians of ``--repeat`` runs in one process:

* one position query (``p`` / ``:j1``) over a pseudo-terminal, RODEON and Merlin drivers;
* a 90 deg pan move at full speed through ``move_to`` + ``wait_settled`` against the emulator's
  travel time (emulator speeds 30 and 25 deg/s, time scaled 20x as in the tests): the overhead the
  driver's polling adds on arrival, and the read-back error in degrees;
* trigger + read of one 400 x 400 RGBa8 frame from the genicam package's simulated producer
  (free-running at 200 fps: the trigger discards queued frames, so this is ~one frame period).

There is no peer implementation of these protocols to compare against (the published ones are
GPL/CeCILL code we do not ship); the numbers bound what the drivers cost per direction.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

from omnispectral.capture.drivers.gentl import GenTLSystem, producer_paths
from omnispectral.capture.drivers.merlin import MerlinHead
from omnispectral.capture.drivers.rodeon import RodeonHead
from omnispectral.sim.emulators import MerlinEmulator, RodeonEmulator

SCALE = 20.0


def bench_head(emu_cls, head_cls, repeat: int) -> dict:
    queries, moves, errors, travel = [], [], [], 0.0
    with emu_cls(time_scale=SCALE) as emu:
        head = head_cls(emu.port, command_timeout_s=0.5, poll_s=0.01, tolerance_deg=0.01)
        speed = emu.motors[next(iter(emu.motors))].max_speed_deg_s * SCALE
        for i in range(repeat):
            t0 = time.perf_counter()
            for _ in range(20):
                head.position()
            queries.append((time.perf_counter() - t0) / 40)  # two axes per position()
            target = 90.0 * ((i + 1) % 2)  # 90, 0, 90, ...: 90 deg moves
            start = head.position()[0]
            travel = abs(target - start) / speed
            t0 = time.perf_counter()
            head.move_to(target, 0.0)
            pan, _ = head.wait_settled(5.0)
            moves.append(time.perf_counter() - t0 - travel)
            errors.append(abs(pan - target))
        head.close()
    return {"query_ms": 1e3 * statistics.median(queries), "arrival_overhead_ms": 1e3 * statistics.median(moves),
            "travel_ms": 1e3 * travel, "max_readback_error_deg": max(errors)}


def bench_camera(repeat: int) -> dict:
    system = GenTLSystem(producer_paths(["simulator"], environment=False))
    try:
        cam = system.open("A", serial="0", fixed_exposure=True, frame_rate_hz=200)
        times = []
        for _ in range(repeat * 4):
            t0 = time.perf_counter()
            cam.trigger()
            cam.read_frame(2.0)
            times.append(time.perf_counter() - t0)
        cam.close()
    finally:
        system.close()
    return {"trigger_read_ms": 1e3 * statistics.median(times), "frame_period_ms": 1e3 / 200}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args()
    out = {"load": os.getloadavg(), "rodeon": bench_head(RodeonEmulator, RodeonHead, args.repeat),
           "merlin": bench_head(MerlinEmulator, MerlinHead, args.repeat), "gentl": bench_camera(args.repeat)}
    print(json.dumps(out, indent=2))
    if args.json_out:
        with open(args.json_out, "w", encoding="utf-8") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
