"""``capture --dry-run`` checks what it can without talking to any device: GenTL producers, serial numbers, the
head's port, the cameras' device tables; a rig it finds unusable exits 1 with its problems listed."""

from __future__ import annotations

import importlib.util
import json
from importlib import resources

import pytest

from omnispectral.capture import drivers
from omnispectral.cli import main

SIMULATED = 'device = { driver = "simulated" }'


def _rig(tmp_path, device_a: str, device_b: str, head: str | None = None) -> str:
    """The ``small`` preset with these camera device tables (and a serial head on ``head`` when given)."""
    text = resources.files("omnispectral").joinpath("data/rigs/small.toml").read_text()
    assert text.count(SIMULATED) == 2
    text = text.replace(SIMULATED, f"device = {{ {device_a} }}", 1).replace(SIMULATED, f"device = {{ {device_b} }}", 1)
    if head is not None:
        text = text.replace('driver = "simulated"\nmodel = "Dr. Clauss', 'driver = "rodeon"\nmodel = "Dr. Clauss', 1)
        text = text.replace('port = ""', f'port = "{head}"', 1)
    path = tmp_path / "rig" / "rig.toml"
    path.parent.mkdir(exist_ok=True)
    path.write_text(text)
    return str(path)


@pytest.fixture
def no_devices(monkeypatch):
    """A dry run must not open any device: opening one fails the test."""
    def refuse(*_args, **_kwargs):
        raise AssertionError("a dry run opened a device")

    monkeypatch.setattr(drivers, "open_cameras", refuse)
    monkeypatch.setattr(drivers, "open_head", refuse)
    monkeypatch.delenv("GENICAM_GENTL64_PATH", raising=False)


def _dry_run(capsys, rig: str, tmp_path, *extra: str) -> tuple[int, str]:
    status = main(["capture", "--rig", rig, "-o", str(tmp_path / "session"), "--dry-run", *extra])
    return status, capsys.readouterr().out


def test_dry_run_flags_a_missing_producer_and_one_serial_on_two_cameras(tmp_path, capsys, no_devices):
    cam = 'driver = "genicam", cti = "producers/maker.cti", serial = "700123"'
    rig = _rig(tmp_path, cam, cam)
    status, text = _dry_run(capsys, rig, tmp_path, "--json")
    out = json.loads(text)
    assert status == 1
    missing = str(tmp_path / "rig" / "producers" / "maker.cti")  # relative to the rig file's folder
    cti_problems = [p for p in out["problems"] if missing in p]
    serial_problems = [p for p in out["problems"] if "700123" in p]
    assert len(cti_problems) == 1 and "does not exist" in cti_problems[0]
    assert "[cameras.A]" in cti_problems[0] and "[cameras.B]" in cti_problems[0]
    assert len(serial_problems) == 1 and "[cameras.A]" in serial_problems[0] and "[cameras.B]" in serial_problems[0]
    assert len(out["problems"]) == 2
    assert not (tmp_path / "session").exists()

    status, text = _dry_run(capsys, rig, tmp_path)
    assert status == 1
    assert "2 problems" in text and missing in text.replace("\n", "") and "700123" in text


def test_dry_run_of_a_usable_rig_has_no_problems(tmp_path, capsys, no_devices):
    (tmp_path / "rig" / "producers").mkdir(parents=True)
    (tmp_path / "rig" / "producers" / "maker.cti").write_bytes(b"")  # never loaded by a dry run
    rig = _rig(tmp_path, 'driver = "genicam", cti = "producers/maker.cti", serial = "700123"',
               'driver = "genicam", cti = "producers/maker.cti", serial = "700124"')
    status, text = _dry_run(capsys, rig, tmp_path, "--json")
    assert status == 0 and json.loads(text)["problems"] == []
    status, text = _dry_run(capsys, rig, tmp_path)
    assert status == 0 and "No problems found" in text


def test_dry_run_of_the_simulated_rig_has_no_problems(tmp_path, capsys, no_devices):
    status, text = _dry_run(capsys, _rig(tmp_path, 'driver = "simulated"', 'driver = "simulated"'), tmp_path, "--json")
    assert status == 0 and json.loads(text)["problems"] == []


@pytest.mark.skipif(importlib.util.find_spec("genicam") is None, reason="genicam is not installed "
                    "(pip install 'omnispectral[devices]')")
def test_dry_run_finds_the_simulator_alias(tmp_path, capsys, no_devices):
    rig = _rig(tmp_path, 'driver = "genicam", cti = "simulator", serial = "0"',
               'driver = "genicam", cti = "simulator", serial = "1"')
    status, text = _dry_run(capsys, rig, tmp_path, "--json")
    assert status == 0 and json.loads(text)["problems"] == []


def test_dry_run_without_any_producer_or_port_or_serial(tmp_path, capsys, no_devices, monkeypatch):
    port = tmp_path / "ttyNOTHERE"
    rig = _rig(tmp_path, 'driver = "genicam", user_id = "left"', 'driver = "genicam", exposure_mode = 1',
               head=str(port))
    status, text = _dry_run(capsys, rig, tmp_path, "--json")
    problems = json.loads(text)["problems"]
    assert status == 1
    assert any("no GenTL producer" in p and "GENICAM_GENTL64_PATH" in p for p in problems)
    assert any("[head]" in p and str(port) in p for p in problems)
    assert any("[cameras.B]" in p and "exposure_mode" in p for p in problems)
    assert len(problems) == 3
    # a producer from GENICAM_GENTL64_PATH and the port present: only B's device table is left
    (tmp_path / "gentl").mkdir()
    (tmp_path / "gentl" / "maker.cti").write_bytes(b"")
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(tmp_path / "gentl"))
    port.write_text("")
    status, text = _dry_run(capsys, rig, tmp_path, "--json")
    problems = json.loads(text)["problems"]
    assert status == 1 and len(problems) == 1 and "exposure_mode" in problems[0]
