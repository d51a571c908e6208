"""``omnispectral devices list | probe``: the cameras and serial ports found, and what a rig's devices answer."""

from __future__ import annotations

from rich.markup import escape
from rich.table import Table

from omnispectral.capture.drivers import list_serial_ports
from omnispectral.capture.hardware import probe_rig
from omnispectral.cli._common import console, print_json
from omnispectral.cli.capture import rig_from_args

__all__ = ["cmd_devices_list", "cmd_devices_probe"]


def cmd_devices_list(args) -> int:
    # lazy: harvesters and genicam load the GenTL native libraries, only wanted when cameras are listed
    from omnispectral.capture.drivers.gentl import GenTLSystem, producer_paths

    ports = list_serial_ports()
    producers = producer_paths(args.cti)
    cameras = []
    if producers:
        system = GenTLSystem(producers)
        try:
            cameras = system.devices()
        finally:
            system.close()
    out = {"serial_ports": ports, "gentl_producers": [str(p) for p in producers], "cameras": cameras}
    if args.json:
        print_json(out)
        return 0
    if not producers:
        console.print("GenTL cameras: no producer (give --cti FILE.cti or --cti simulator, or set "
                      "GENICAM_GENTL64_PATH)")
    else:
        t = Table(title=f"GenTL cameras ({len(cameras)}) from {', '.join(out['gentl_producers'])}")
        for col in ("vendor", "model", "serial", "user id", "GenTL id"):
            t.add_column(col)
        for c in cameras:
            t.add_row(c["vendor"], c["model"], c["serial"], c["user_id"], c["id"])
        console.print(t)
    t = Table(title=f"Serial ports ({len(ports)})")
    for col in ("device", "description", "hardware id"):
        t.add_column(col)
    for p in ports:
        t.add_row(p["device"], p["description"], p["hwid"])
    console.print(t)
    return 0


def cmd_devices_probe(args) -> int:
    rig = rig_from_args(args)
    report = probe_rig(rig)
    if args.json:
        print_json(report)
    elif not report:
        console.print(f"{rig.name}: every device is simulated; nothing to probe")
    for entry in report if not args.json else ():
        if not entry["ok"]:
            console.print(f"[red]{escape(entry['device'])}: {escape(entry['error'])}[/red]", soft_wrap=True)
            continue
        details = ", ".join(f"{k} {v}" for k, v in entry.items() if k not in ("device", "ok") and v not in (None, ""))
        console.print(f"[green]{escape(entry['device'])}[/green]: {escape(details)}", soft_wrap=True)
    return 0 if all(e["ok"] for e in report) else 1
