"""RODEON and Merlin drivers against their pseudo-terminal emulators: moves, read-back, speeds, faults."""

from __future__ import annotations

import re
import time

import pytest

from omnispectral.capture.devices import (
    DeviceDisconnected,
    DeviceError,
    DeviceProtocolError,
    DeviceTimeout,
    PanTiltHead,
)
from omnispectral.capture.drivers.merlin import MerlinHead, decode_u24, encode_u24
from omnispectral.capture.drivers.rodeon import RodeonHead, parse_rodeon_reply, rodeon_request
from omnispectral.capture.plan import Direction
from omnispectral.capture.run import RetryPolicy, goto_direction
from omnispectral.errors import OmnispectralError
from omnispectral.sim.emulators import EmulatorFaults, MerlinEmulator, RodeonEmulator

SCALE = 20.0  # emulated motors run 20x faster than the real ones so the tests stay fast
HEADS = {"rodeon": (RodeonEmulator, RodeonHead, "RODEON head"), "merlin": (MerlinEmulator, MerlinHead, "Merlin head")}
FAST = {"command_timeout_s": 0.1, "retries": 2, "poll_s": 0.005, "stall_s": 0.15, "tolerance_deg": 0.01}


@pytest.fixture(params=sorted(HEADS))
def rig(request):
    emu_cls, head_cls, label = HEADS[request.param]
    emu = emu_cls(time_scale=SCALE)
    head = head_cls(emu.port, **FAST)
    yield emu, head, label
    head.close()
    emu.close()


def _truth_deg(emu, axis: str) -> float:
    key = {"pan": 1, "tilt": 2} if isinstance(emu, RodeonEmulator) else {"pan": "1", "tilt": "2"}
    m = emu.motors[key[axis]]
    return m.steps(emu.now()) * 360.0 / m.steps_per_turn


def test_drivers_implement_the_head_protocol(rig):
    emu, head, _ = rig
    assert isinstance(head, PanTiltHead)
    assert head.steps_per_turn["pan"] == emu.motors[next(iter(emu.motors))].steps_per_turn


@pytest.mark.parametrize("pan,tilt", [(30.0, -20.0), (345.0, 60.0), (12.3456, -89.5), (180.0, 0.0)])
def test_move_and_read_back_within_tolerance(rig, pan, tilt):
    emu, head, _ = rig
    head.move_to(pan, tilt)
    got_pan, got_tilt = head.wait_settled(timeout_s=3.0)
    step = 360.0 / head.steps_per_turn["pan"]
    assert abs(got_pan - pan) <= step / 2 + 1e-9
    assert abs(got_tilt - tilt) <= step / 2 + 1e-9
    # what the driver reports is where the emulated motors are (Merlin wraps pan into one turn)
    assert abs((got_pan - _truth_deg(emu, "pan") + 180) % 360 - 180) < 1e-9
    assert abs(got_tilt - _truth_deg(emu, "tilt")) < 1e-9


@pytest.mark.parametrize("name", sorted(HEADS))
def test_move_speed_follows_the_speed_setting(name):
    """A 90 deg pan move takes travel / speed (emulated), and twice as long at half speed."""
    emu_cls, head_cls, _ = HEADS[name]
    durations = {}
    for fraction in (1.0, 0.5):
        with emu_cls(time_scale=SCALE) as emu:
            head = head_cls(emu.port, speed_fraction=fraction, **FAST)
            t0 = time.monotonic()
            head.move_to(90.0, 0.0)
            head.wait_settled(timeout_s=3.0)
            durations[fraction] = time.monotonic() - t0
            expected = 90.0 / (emu.motors[next(iter(emu.motors))].max_speed_deg_s * fraction * SCALE)
            head.close()
        # the lower bound is what shows the speed is obeyed: at half speed the move cannot be faster than travel/speed
        assert expected <= durations[fraction] <= expected + 0.4, (fraction, durations, expected)
    assert durations[0.5] / durations[1.0] > 1.2


def _one_line_error(exc: BaseException, label: str) -> str:
    msg = str(exc)
    assert isinstance(exc, OmnispectralError) and "\n" not in msg
    assert msg.startswith(f"{label} on /dev/")
    return msg


def test_no_answer_times_out_in_bounded_time(rig):
    emu, head, label = rig
    emu.faults.no_answer = 1000
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout) as ei:
        head.position()
    elapsed = time.monotonic() - t0
    msg = _one_line_error(ei.value, label)
    assert "no answer within 0.1 s" in msg and "3 attempts" in msg and "position" in msg
    assert elapsed < 3 * 0.1 + 0.3


def test_one_lost_reply_is_retried(rig):
    emu, head, _ = rig
    emu.faults.no_answer = 1
    head.move_to(10.0, 5.0)
    assert abs(head.wait_settled(3.0)[0] - 10.0) < 0.01


def test_garbage_is_retried_then_reported(rig):
    emu, head, label = rig
    emu.faults.garbage = 1
    head.move_to(-10.0, 5.0)
    assert abs(head.wait_settled(3.0)[1] - 5.0) < 0.01
    emu.faults.garbage = 1000
    with pytest.raises(DeviceProtocolError) as ei:
        head.position()
    msg = _one_line_error(ei.value, label)
    assert "answered '\\x15\\x7f#?" in msg and "3 attempts" in msg


def test_error_replies_are_reported_with_their_meaning(rig):
    emu, head, label = rig
    emu.faults.error_replies = 1000
    with pytest.raises(DeviceProtocolError) as ei:
        head.move_to(20.0, 0.0)
    msg = _one_line_error(ei.value, label)
    if isinstance(head, MerlinHead):
        assert "error !2 (motor not stopped)" in msg
    else:
        assert "echoed '?' instead of 'S'" in msg


def test_move_that_never_arrives_times_out_and_the_loop_retries(rig):
    emu, head, label = rig
    emu.faults.stall_moves = 1
    head.move_to(60.0, 0.0)
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout) as ei:
        head.wait_settled(timeout_s=3.0)
    assert time.monotonic() - t0 < 1.0  # detected as a stall, not at the timeout
    msg = _one_line_error(ei.value, label)
    stopped = float(re.search(r"pan axis stopped for [\d.]+ s at ([-\d.]+) deg", msg).group(1))
    assert abs(stopped - 30.0) < 0.5  # stall_fraction 0.5 of the way from 0 to 60 deg
    assert "target 60.000 deg" in msg
    # the capture loop's bounded retry: the first attempt stalls, the second arrives
    emu.faults.stall_moves = 1
    pan, tilt = goto_direction(head, Direction(7, 0, 0, 100.0, 10.0), RetryPolicy(2, 3.0, 0.01))
    assert abs(pan - 100.0) < 0.01 and abs(tilt - 10.0) < 0.01
    emu.faults.stall_moves = 1000
    with pytest.raises(DeviceError, match=r"head could not reach direction 8 .* after 3 attempts: .*pan axis stopped"):
        goto_direction(head, Direction(8, 0, 0, 200.0, 10.0), RetryPolicy(2, 3.0, 0.01))


def test_cable_pulled_mid_move(rig):
    emu, head, label = rig
    emu.faults.pull_cable_on_move = emu.moves + 1
    emu.faults.pull_cable_after_s = 0.05
    t0 = time.monotonic()
    with pytest.raises(DeviceDisconnected) as ei:
        # the line goes 50 ms into the move: while the driver waits for it, or (on a slow machine) while it
        # is still sending the second axis's command; either way the move stops with the one clear error
        head.move_to(300.0, 45.0)
        head.wait_settled(timeout_s=5.0)
    assert time.monotonic() - t0 < 0.6
    msg = _one_line_error(ei.value, label)
    assert "serial port lost" in msg and "cable pulled" in msg
    assert emu.cable_pulled
    head.close()  # closing a head whose line is gone does not raise


@pytest.mark.parametrize("name", sorted(HEADS))
def test_missing_port_is_named(name, tmp_path):
    _, head_cls, label = HEADS[name]
    with pytest.raises(DeviceDisconnected, match=rf"^{label}: cannot open serial port {tmp_path}/ttyUSB9 "):
        head_cls(str(tmp_path / "ttyUSB9"), **FAST)


def test_rodeon_empty_position_answer_on_arrival_is_tolerated():
    with RodeonEmulator(time_scale=SCALE, faults=EmulatorFaults(empty_position_on_arrival=True)) as emu:
        head = RodeonHead(emu.port, **FAST)
        head.move_to(45.0, -30.0)
        pan, tilt = head.wait_settled(3.0)
        assert abs(pan - 45.0) < 0.01 and abs(tilt + 30.0) < 0.01
        assert any(r == rodeon_request(1, "p")[:-1] for r in emu.requests)
        head.close()


def test_rodeon_reply_parsing():
    assert parse_rodeon_reply(b"\xa1\xa1p+0012000\r", 1, "p") == ["+0012000"]
    assert parse_rodeon_reply(b"\xa0vV2.10\rHD\r", 0, "v") == ["V2.10", "HD"]
    assert parse_rodeon_reply(b"\xa2G\r", 2, "G") == []
    assert rodeon_request(1, "S", f"{12000:+08d}") == b"\xc1S+0012000\r"
    with pytest.raises(ValueError, match="address byte 0xA1"):
        parse_rodeon_reply(b"\xa2p+1\r", 1, "p")


def test_merlin_24bit_numbers_are_lsb_first():
    assert encode_u24(0x123456) == "563412"
    assert decode_u24("563412") == 0x123456
    for v in (0, 1, 0x800000, 0xFFFFFF, 9024000):
        assert decode_u24(encode_u24(v)) == v
    with pytest.raises(ValueError):
        encode_u24(1 << 24)


def test_a_pulled_cable_seen_by_tcdrain_is_a_disconnection():
    """pyserial's POSIX flush raises ``termios.error`` (EIO), not an OSError, once the other end of the line
    is gone (seen in CI on the Merlin emulator): the link reports a disconnection naming the device."""
    termios = pytest.importorskip("termios")
    from omnispectral.capture.devices import DeviceDisconnected
    from omnispectral.capture.drivers.serial_link import SerialLink

    link = SerialLink("merlin", "loop://", timeout_s=0.05, retries=0)

    def flush():
        raise termios.error(5, "Input/output error")

    link.ser.flush = flush
    with pytest.raises(DeviceDisconnected, match="merlin"):
        link.exchange(b":e1\r", lambda reply: reply)
    link.close()
