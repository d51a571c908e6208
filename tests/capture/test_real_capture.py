"""A whole ``capture`` with real protocols: emulated RODEON head on a pseudo-terminal + GenTL simulated cameras."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("harvesters", reason="harvesters is not installed (pip install 'omnispectral[devices]')")

from omnispectral.capture.drivers.rodeon import rodeon_request
from omnispectral.capture.session import Session
from omnispectral.cli import main
from omnispectral.sim.emulators import EmulatorFaults, RodeonEmulator

SCALE = 20.0
N_PAN, N_TILT, N_EXPOSURES = 4, 2, 2


def _rig(path, port: str) -> str:
    cams = ""
    for name, serial in (("A", "0"), ("B", "1")):
        cams += f"""
[cameras.{name}]
model = "Viky (GenTL simulator)"
width_px = 120
height_px = 100
bit_depth = 8
orientation = "landscape"
lens = {{ hfov_deg = 120.0, vfov_deg = 100.0 }}
device = {{ driver = "genicam", cti = "simulator", serial = "{serial}", fixed_exposure = true, frame_rate_hz = 200 }}
"""
    path.write_text(f"""name = "emulated-rodeon"
{cams}
[head]
driver = "rodeon"
model = "RODEON emulator"
port = "{port}"
pan_speed_deg_s = {30 * SCALE}
tilt_speed_deg_s = {30 * SCALE}
settle_s = 0.0
position_tolerance_deg = 0.05
timeout_s = 5.0
retries = 1
command_timeout_s = 0.2
poll_s = 0.01

[bracket]
exposures_s = [0.01, 0.001]

[grid]
n_pan = {N_PAN}
n_tilt = {N_TILT}
""")
    return str(path)


def _json_of(capsys) -> dict:
    return json.loads(capsys.readouterr().out)


def _pan_targets(emu) -> list[int]:
    prefix = rodeon_request(1, "S")[:2]
    return [int(r[2:]) for r in emu.requests if r.startswith(prefix)]


def test_dry_run_and_probe_talk_as_promised(tmp_path, capsys):
    with RodeonEmulator(time_scale=SCALE, link=tmp_path / "ttyRODEON") as emu:
        rig = _rig(tmp_path / "rig.toml", emu.path)
        assert main(["capture", "--rig", rig, "-o", str(tmp_path / "s"), "--dry-run", "--json"]) == 0
        plan = _json_of(capsys)
        assert plan["n_frames"] == N_PAN * N_TILT * N_EXPOSURES * 2 and len(plan["moves"]) == N_PAN * N_TILT
        assert plan["head"] == {"driver": "rodeon", "port": emu.path, "port_exists": True}
        assert emu.requests == []  # a dry run does not talk to the head
        assert not (tmp_path / "s").exists()
        assert main(["devices", "probe", "--rig", rig, "--json"]) == 0
        report = {e["device"]: e for e in _json_of(capsys)}
    head = report["head (rodeon)"]
    assert head["info"]["brand"] == "CLAUSS" and head["steps_per_turn"] == {"pan": 172800, "tilt": 172800}
    assert abs(head["pan_deg"]) < 1e-9 and abs(head["tilt_deg"]) < 1e-9  # zeroed at factory zero by the init
    assert report["camera A"]["serial"] == "0" and report["camera B"]["serial"] == "1"
    assert report["camera A"]["exposure_feature"] is False and report["camera A"]["pixel_format"] == "RGBa8"


@pytest.mark.slow
def test_capture_with_emulated_rodeon_and_gentl_cameras_resumes_after_a_pulled_cable(tmp_path, capsys):
    link = tmp_path / "ttyRODEON"
    session = tmp_path / "session"
    n_frames = N_PAN * N_TILT * N_EXPOSURES * 2
    # first run: the cable is pulled while the head travels to the third direction
    faults = EmulatorFaults(pull_cable_on_move=3, pull_cable_after_s=0.005)
    with RodeonEmulator(time_scale=SCALE, link=link, faults=faults) as emu:
        rig = _rig(tmp_path / "rig.toml", str(link))
        assert main(["capture", "--rig", rig, "-o", str(session), "--json"]) == 1
        first = _json_of(capsys)
        assert emu.cable_pulled
    assert first["complete"] is False and first["n_written"] == 2 * N_EXPOSURES * 2
    assert first["stopped_reason"].startswith(f"RODEON head on {link}: serial port lost")
    assert main(["session", "verify", str(session), "--json"]) == 1
    assert _json_of(capsys)["n_missing"] == n_frames - first["n_written"]
    # the cable is plugged back in (a new emulator behind the same link): the same command resumes
    with RodeonEmulator(time_scale=SCALE, link=link) as emu2:
        assert main(["capture", "--rig", rig, "-o", str(session), "--json"]) == 0
        second = _json_of(capsys)
        targets = _pan_targets(emu2)
    assert second["complete"] is True and second["n_already_done"] == first["n_written"]
    assert second["n_written"] == n_frames - first["n_written"]
    assert main(["session", "verify", str(session), "--pixels", "--json"]) == 0
    report = _json_of(capsys)
    assert report["n_ok"] == n_frames and report["complete"]

    s = Session.open(session)
    plan = s.plan()
    # the resumed run only went to the directions not yet captured, in plan order
    expected = [round(d.pan_deg / 360 * 172800) for d in plan.directions[2:]]
    assert targets == expected
    records = s.completed()
    for (direction, camera, _k), rec in records.items():
        d = plan.directions[direction]
        assert abs(rec["pan_deg_reported"] - d.pan_deg) <= 0.05 and abs(rec["tilt_deg_reported"] - d.tilt_deg) <= 0.05
        meta = rec["camera_metadata"]
        assert meta["serial"] == {"A": "0", "B": "1"}[camera] and meta["pixel_format"] == "RGBa8"
    frame, _ = s.read_frame(5, "B", 1)
    assert frame.shape == (100, 120, 3) and frame.dtype == np.uint16
    assert np.all(frame[..., 1] == 255)  # camera B is the producer's "green" device
    stops = [e for e in s.events() if e["event"] == "stop"]
    assert len(stops) == 1 and "cable pulled" in stops[0]["reason"]
    # and the product pipeline takes the session as it is (the test pattern: the check is the path)
    assert main(["process", str(session), "-o", str(tmp_path / "product"), "--width", "128", "--json"]) == 0
    product = _json_of(capsys)
    assert product["session_kind"] == "capture" and product["rig"] == "emulated-rodeon"
    assert (product["width"], product["height"]) == (128, 64) and len(product["bands"]) == 6


def test_merlin_rig_probes_through_the_rig_file(tmp_path, capsys):
    from omnispectral.sim.emulators import MerlinEmulator

    with MerlinEmulator(time_scale=SCALE) as emu:
        text = open(_rig(tmp_path / "rig.toml", emu.port)).read().replace('driver = "rodeon"', 'driver = "merlin"')
        (tmp_path / "merlin.toml").write_text(text)
        assert main(["devices", "probe", "--rig", str(tmp_path / "merlin.toml"), "--json"]) == 0
        head = _json_of(capsys)[0]
    assert head["device"] == "head (merlin)" and head["steps_per_turn"] == {"pan": 9024000, "tilt": 9024000}
    assert head["info"]["pan_firmware"] == "020C01" and abs(head["resolution_deg"]["pan"] - 360 / 9024000) < 1e-15


def test_devices_list_finds_the_simulated_producer_cameras(capsys):
    assert main(["devices", "list", "--cti", "simulator", "--json"]) == 0
    out = _json_of(capsys)
    assert [c["serial"] for c in out["cameras"]] == ["0", "1", "2"]
    assert out["gentl_producers"][0].endswith("genicam/viky.cti")
    assert all("device" in p for p in out["serial_ports"])


def test_rig_device_errors_name_the_rig(tmp_path, capsys):
    with RodeonEmulator(time_scale=SCALE) as emu:
        text = open(_rig(tmp_path / "rig.toml", emu.port)).read()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("fixed_exposure = true", "exposure_mode = 1", 1))
    # the dry run talks to no device, but it reads the device tables: an unknown key is a problem (exit 1)
    assert main(["capture", "--rig", str(bad), "-o", str(tmp_path / "s"), "--dry-run"]) == 1
    assert "[cameras.A] device: unknown keys ['exposure_mode']" in capsys.readouterr().out
    assert main(["devices", "probe", "--rig", str(bad)]) == 1
    out = capsys.readouterr().out
    assert f"cameras (genicam): {bad}: [cameras.A] device: unknown keys ['exposure_mode']" in out
    mixed = tmp_path / "mixed.toml"
    mixed.write_text(text.replace('driver = "genicam"', 'driver = "simulated"'))
    assert main(["capture", "--rig", str(mixed), "-o", str(tmp_path / "m")]) == 2
    assert "simulated cameras render what the simulated head points at" in capsys.readouterr().err
