"""Rig files, planning (paper Table 2 / Sec. 5.5), sessions, devices with faults, resume after SIGKILL."""

from __future__ import annotations

import datetime as dt
import itertools
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace

import numpy as np
import pytest

from omnispectral.capture.plan import direction_grid, grid_counts, make_plan, tradeoff
from omnispectral.capture.run import RetryPolicy, run_capture
from omnispectral.capture.session import Session, content_matches, read_journal, verify_session
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.rig import load_preset, load_rig, rig_toml
from omnispectral.sim.devices import CameraFaults, FakeClock, HeadFaults, SimulatedCamera, SimulatedHead


# ------------------------------------------------------------------ planning
def test_paper_timelapse_plan_reproduces_table2():
    p = make_plan(load_preset("paper-timelapse"))
    assert (p.n_pan, p.n_tilt, p.n_directions) == (12, 3, 36)
    # Table 2: ~180 s, ~5 s per direction; the sun bracket (tests/product/test_sun.py) comes on top
    assert p.estimated_s - p.timing_s["sun_bracket"] == pytest.approx(180, rel=0.03)
    assert (p.estimated_s - p.timing_s["sun_bracket"]) / p.n_directions == pytest.approx(5.0, rel=0.03)


@pytest.mark.parametrize(("overlap", "n", "seconds"), [(None, 1260, 2 * 3600 + 17 * 60), (0.0, 425, 46 * 60),
                                                        (0.12, 726, 3600 + 19 * 60)])
def test_paper_gigapixel_plans_reproduce_sec_5_5(overlap, n, seconds):
    p = make_plan(load_preset("paper-gigapixel"), overlap=overlap)
    assert p.n_directions == n
    assert p.estimated_s - p.timing_s["sun_bracket"] == pytest.approx(seconds, rel=0.04)


def test_grid_is_serpentine_and_covers_the_sphere():
    dirs = direction_grid(12, 3)
    tilts = sorted({d.tilt_deg for d in dirs})
    assert tilts == pytest.approx([-60.0, 0.0, 60.0])
    pans = [d.pan_deg for d in dirs]
    assert pans[:12] == sorted(pans[:12]) and pans[12:24] == sorted(pans[12:24], reverse=True)
    assert max(abs(np.diff(pans[:12]))) == pytest.approx(30.0)
    # consecutive directions never jump across the circle
    assert max(abs(a.pan_deg - b.pan_deg) for a, b in itertools.pairwise(dirs)) <= 30.0 + 1e-9


def test_overlap_counts_and_tradeoff_monotonic():
    assert grid_counts(14.5, 10.8, 0.0) == (25, 17)
    rows = tradeoff(load_preset("paper-gigapixel"), overlaps=[0.0, 0.1, 0.2, 0.3])
    assert [r["n_directions"] for r in rows] == sorted(r["n_directions"] for r in rows)
    with pytest.raises(ConfigurationError, match="overlap"):
        grid_counts(10, 10, 0.6)


# ------------------------------------------------------------------ rig files
def _write_rig(tmp_path, old, new):
    text = load_preset("small").toml_text
    assert old in text
    p = tmp_path / "rig.toml"
    p.write_text(text.replace(old, new))
    return p


@pytest.mark.parametrize(("old", "new", "msg"), [
    ("width_px = 256", "width_px = -4", r"\[cameras.A\] width_px: must be positive"),
    ("bit_depth = 12", "bit_depth = 40", r"bit_depth: must be 8-16"),
    ('orientation = "portrait"      #', 'orientation = "sideways"      #', "orientation: expected one of"),
    ("hfov_deg = 95.0", "hfov_deg = 200.0", "below 180 deg"),
    ("count = 15", "count = 0", r"\[bracket\] count: must be positive"),
    ('driver = "simulated"\nmodel', 'driver = "rodeon"\nmodel', r"\[head\] port: the rodeon driver needs"),
    ("yaw_deg = 0.15", "yaw_deg = 45.0", "not a small misalignment"),
    ("count = 15", 'count = "fifteen"', r"rig.toml: \[bracket\] count: expected an integer, got 'fifteen'$"),
])
def test_rig_errors_name_the_key(tmp_path, old, new, msg):
    with pytest.raises(ConfigurationError, match=msg):
        load_rig(_write_rig(tmp_path, old, new))


def test_rig_file_errors(tmp_path):
    with pytest.raises(InputFileError, match="rig file not found"):
        load_rig(tmp_path / "nope.toml")
    (tmp_path / "bad.toml").write_text("name = [unclosed")
    with pytest.raises(InputFileError, match=r"bad.toml: not valid TOML"):
        load_rig(tmp_path / "bad.toml")


def test_rig_snapshot_round_trip(tmp_path):
    import tomllib

    from omnispectral.rig import rig_from_dict

    rig = load_preset("paper-gigapixel")
    again = rig_from_dict(tomllib.loads(rig_toml(replace(rig, toml_text=""))))
    assert again.bracket.exposures_s == pytest.approx(rig.bracket.exposures_s)
    assert again.camera_b.filter == rig.camera_b.filter and again.head == rig.head
    assert make_plan(again).n_directions == 1260


# ------------------------------------------------------------------ capture on simulated devices
def ramp_renderer(shape):
    """Deterministic frames that encode where the head pointed and the exposure (for checking)."""

    def render(camera, pan_deg, tilt_deg, exposure_s, rng):
        base = (pan_deg + 180) * 10 + (tilt_deg + 90) + (0 if camera == "A" else 5000)
        img = np.full(shape, min(4095.0, base * exposure_s * 10), np.float64)
        return (img + rng.integers(0, 3, shape)).clip(0, 4095).astype(np.uint16)

    return render


def small_session(tmp_path, name="s", dark=False):
    """A session of the ``small`` preset; without its dark extension unless ``dark`` (the ramp's dim directions
    would trigger it, and these tests count frames: tests/capture/test_dark_extension.py tests it)."""
    rig = load_preset("small")
    if not dark:
        rig = replace(rig, dark=None, toml_text="")
    plan = make_plan(rig)
    return rig, Session.create(tmp_path / name, rig, plan, kind="test")


def devices(rig, clock, head_faults=None, cam_faults=None, shape=(8, 6)):
    head = SimulatedHead(clock, rig.head.pan_speed_deg_s, rig.head.tilt_speed_deg_s, rig.head.settle_s, head_faults)
    cams = {c: SimulatedCamera(c, head, ramp_renderer(shape), clock, 12, rig.cameras[c].readout_s,
                               faults=(cam_faults or {}).get(c, CameraFaults())) for c in ("A", "B")}
    return head, cams


def test_capture_writes_every_frame_and_simulated_time_follows_the_timing_model(tmp_path):
    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    head, cams = devices(rig, clock)
    res = run_capture(s, head, cams, clock, progress=False)
    assert res.complete and res.n_written == 36 * 2 * 15
    plan = make_plan(rig)  # no filter changer given: no sun bracket
    assert res.simulated_s == pytest.approx(plan.estimated_s - plan.timing_s["sun_bracket"], rel=1e-6)
    report = verify_session(s.path)
    assert report["complete"] and report["n_ok"] == 1080
    frame, meta = s.read_frame(3, "B", 7)
    assert frame.dtype == np.uint16 and meta["exposure_s"] == pytest.approx(make_plan(rig).exposures_s[7])
    assert meta["pan_deg_commanded"] == make_plan(rig).directions[3].pan_deg


def test_verify_names_missing_and_damaged_frames(tmp_path):
    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    run_capture(s, *devices(rig, clock), clock, progress=False)
    victim = s.path / "frames/d0005/A_e03.tif"
    victim.write_bytes(victim.read_bytes()[:100])
    (s.path / "frames/d0010/B_e14.tif").unlink()
    with open(s.journal_path, "a") as fh:
        fh.write('{"direction": 1, "camera"')
    r = verify_session(s.path, check_pixels=True)
    assert not r["complete"] and r["n_damaged"] == 1 and r["journal_partial_last_line"]
    problems = {d["file"]: d["problem"] for d in r["damaged"]}
    assert "checksum mismatch" in problems["frames/d0005/A_e03.tif"]
    # a deleted frame is missing, not damaged
    assert r["n_missing"] == 1 and r["missing"][0]["file"] == "frames/d0010/B_e14.tif"
    assert r["missing"][0]["problem"] == "file missing"


def test_a_same_size_bit_flip_fails_the_fast_and_the_cryptographic_checksum(tmp_path):
    import hashlib

    import xxhash

    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    run_capture(s, *devices(rig, clock), clock, progress=False)
    key, victim = (7, "B", 4), s.path / "frames/d0007/B_e04.tif"
    rec = read_journal(s.journal_path).records[key]
    content = victim.read_bytes()
    # the journal holds both checksums of the file's bytes (peers' digests computed here)
    assert rec["sha256"] == hashlib.sha256(content).hexdigest()
    assert rec["xxh3_128"] == xxhash.xxh3_128(content).hexdigest() and rec["bytes"] == len(content)
    flipped = bytearray(content)
    flipped[-7] ^= 0x10  # one bit near the end of the file: the size stays
    victim.write_bytes(bytes(flipped))
    for cryptographic in (True, False):
        r = verify_session(s.path, check_pixels=True, cryptographic=cryptographic)
        assert r["n_damaged"] == 1 and "checksum mismatch" in r["damaged"][0]["problem"]
    with pytest.raises(InputFileError, match="checksum mismatch"):
        s.check_frames_on_read().read_frame(*key)
    # which digest each check compares: the fast one where recorded, the SHA-256 when asked or when it is absent
    forged = {**rec, "sha256": "0" * 64}
    assert content_matches(content, forged, cryptographic=False)
    assert not content_matches(content, forged, cryptographic=True)
    older = {k: v for k, v in rec.items() if k != "xxh3_128"}
    assert content_matches(content, older, cryptographic=False)
    assert not content_matches(bytes(flipped), older, cryptographic=False)


def test_head_that_stops_answering_stops_cleanly_and_resumes(tmp_path):
    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    head, cams = devices(rig, clock, head_faults=HeadFaults(dead_after_moves=4))
    res = run_capture(s, head, cams, clock, RetryPolicy(retries=2), progress=False)
    assert not res.complete and "head could not reach direction" in res.stopped_reason
    assert res.n_written == 4 * 30  # four directions done, nothing half-written
    assert s.events()[-1]["event"] == "stop"
    head2, cams2 = devices(rig, clock)
    res2 = run_capture(s, head2, cams2, clock, progress=False)
    assert res2.complete and res2.n_already_done == 120 and res2.n_written == 960
    assert verify_session(s.path)["complete"]


def test_transient_faults_are_retried(tmp_path):
    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    head, cams = devices(rig, clock, head_faults=HeadFaults(silent_calls=2),
                         cam_faults={"B": CameraFaults(timeouts=2)})
    res = run_capture(s, head, cams, clock, RetryPolicy(retries=3), progress=False)
    assert res.complete


def test_head_reporting_off_target_stops_with_the_numbers(tmp_path):
    rig, s = small_session(tmp_path)
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    head, cams = devices(rig, clock, head_faults=HeadFaults(offset_deg=(0.5, 0.0)))
    res = run_capture(s, head, cams, clock, RetryPolicy(retries=1, tolerance_deg=0.05), progress=False)
    assert res.n_written == 0 and "0.500 deg off target (tolerance 0.05 deg)" in res.stopped_reason
    assert verify_session(s.path)["n_missing"] == 1080


def test_session_refuses_a_foreign_directory(tmp_path):
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "photo.jpg").write_bytes(b"1")
    rig = load_preset("small")
    with pytest.raises(InputFileError, match="not an omnispectral session"):
        Session.create(tmp_path / "x", rig, make_plan(rig))
    Session.create(tmp_path / "y", rig, make_plan(rig))
    with pytest.raises(InputFileError, match="different plan"):
        Session.create(tmp_path / "y", rig, make_plan(rig, overlap=0.3))


KILL_SCRIPT = textwrap.dedent("""
    import datetime as dt, sys
    sys.path.insert(0, {tests!r})
    from test_capture import devices, small_session
    from omnispectral.sim.devices import FakeClock
    from omnispectral.capture.run import run_capture
    from pathlib import Path
    rig, s = small_session(Path({tmp!r}))
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    head, cams = devices(rig, clock, shape=(136, 256, 3))
    print("ready", flush=True)
    run_capture(s, head, cams, clock, progress=False)
""")


def test_resume_after_sigkill_loses_at_most_the_frame_in_flight(tmp_path):
    script = tmp_path / "cap.py"
    script.write_text(KILL_SCRIPT.format(tests=os.path.dirname(__file__), tmp=str(tmp_path)))
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    journal = tmp_path / "s" / "journal.jsonl"
    deadline = time.time() + 60
    while time.time() < deadline and (not journal.exists() or journal.stat().st_size < 20_000):
        time.sleep(0.02)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = verify_session(tmp_path / "s")
    assert 0 < before["n_ok"] < 1080 and before["n_damaged"] == 0  # nothing written was corrupted
    kept = {json.dumps(r, sort_keys=True) for r in Session(tmp_path / "s").completed().values()}
    rig = load_preset("small")
    s = Session.open(tmp_path / "s")
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    res = run_capture(s, *devices(rig, clock, shape=(136, 256, 3)), clock, progress=False)
    assert res.complete and res.n_already_done == before["n_ok"]
    assert res.n_written == 1080 - before["n_ok"]
    after = {json.dumps(r, sort_keys=True) for r in s.completed().values()}
    assert kept <= after  # every frame recorded before the kill is still there, unchanged
    assert verify_session(s.path, check_pixels=True)["complete"]


# ------------------------------------------------------------------ time-lapse on a fake clock
def test_timelapse_skips_slots_overrun_by_a_long_capture(tmp_path):
    from omnispectral.capture.timelapse import parse_hhmm, parse_interval_s, run_timelapse, slot_times

    tz = dt.UTC
    clock = FakeClock(dt.datetime(2026, 6, 21, 5, 58, tzinfo=tz))
    slots = slot_times(parse_hhmm("06:00", dt.date(2026, 6, 21), tz), parse_hhmm("06:30", dt.date(2026, 6, 21), tz),
                       parse_interval_s("5min"))
    durations = iter([180.0, 700.0, 180.0, 180.0, 180.0])  # the 06:05 capture runs ~11.7 min

    def capture(session_dir, t):
        assert clock.now() == t  # started exactly on the slot
        session_dir.mkdir()
        clock.sleep(next(durations))
        return {"complete": True}

    index = run_timelapse(tmp_path / "series", slots, clock, capture, {"rig": "small"})
    status = [(e["session"], e["status"]) for e in index["slots"]]
    assert status == [("slot_0600", "complete"), ("slot_0605", "complete"), ("slot_0610", "skipped"),
                      ("slot_0615", "skipped"), ("slot_0620", "complete"), ("slot_0625", "complete"),
                      ("slot_0630", "complete")]
    assert "overran until 06:16:40" in index["slots"][2]["reason"]
    assert clock.now() == dt.datetime(2026, 6, 21, 6, 33, tzinfo=tz)  # no real sleeping happened
    on_disk = json.loads((tmp_path / "series" / "series.json").read_text())
    assert on_disk["n_complete"] == 5 and on_disk["n_skipped"] == 2
    # resuming later: complete slots are kept, nothing is captured again
    again = run_timelapse(tmp_path / "series", slots, clock, lambda *a: pytest.fail("captured twice"))
    assert again["n_complete"] == 5


def test_interval_parsing():
    from omnispectral.capture.timelapse import parse_interval_s

    assert parse_interval_s("5min") == 300 and parse_interval_s("1h") == 3600 and parse_interval_s("90") == 90
    with pytest.raises(ConfigurationError, match="interval"):
        parse_interval_s("soon")


def test_cli_plan_json_and_tradeoff(tmp_path, capsys):
    from omnispectral.cli import main

    assert main(["plan", "--preset", "paper-gigapixel", "--overlap", "0", "--json",
                 "--tradeoff", str(tmp_path / "t.png")]) == 0
    out = json.loads(capsys.readouterr().out)
    for key in ("n_directions", "n_pan", "n_tilt", "overlap", "estimated_s", "directions"):
        assert key in out
    assert out["n_directions"] == 425 and set(out["directions"][0]) >= {"pan_deg", "tilt_deg"}
    curve = json.loads((tmp_path / "t.json").read_text())["curve"]
    assert curve[0]["overlap"] == 0 and curve[0]["n_directions"] == 425
    assert (tmp_path / "t.png").stat().st_size > 10_000


def test_cli_session_verify_exit_codes(tmp_path, capsys):
    from omnispectral.cli import main

    rig, s = small_session(tmp_path)
    assert main(["session", "verify", str(s.path), "--json"]) == 1
    assert json.loads(capsys.readouterr().out)["n_missing"] == 1080
    clock = FakeClock(dt.datetime(2026, 6, 21, 9, 0, tzinfo=dt.UTC))
    run_capture(s, *devices(rig, clock), clock, progress=False)
    assert main(["session", "verify", str(s.path)]) == 0
    assert main(["session", "verify", str(tmp_path / "nothing")]) == 1


@pytest.mark.parametrize("layout", [dict(), dict(byteorder=">"), dict(compression="zlib"), dict(rowsperstrip=7)])
def test_frame_pixels_read_from_its_bytes_are_tifffiles(tmp_path, layout):
    """A plainly stored frame is viewed in the bytes just read (no second copy); any other layout (big-endian,
    compressed) is decoded by tifffile; both give tifffile's pixels.  A truncated file is named, not viewed."""
    import tifffile

    from omnispectral.capture.session import decode_frame

    pixels = np.random.default_rng(3).integers(0, 4096, (24, 40, 3), dtype=np.uint16)
    p = tmp_path / "f.tif"
    tifffile.imwrite(p, pixels, description=json.dumps({"shape": [24, 40, 3]}), photometric="rgb", **layout)
    content = p.read_bytes()
    data, meta = decode_frame(p, content)
    assert np.array_equal(data, pixels) and meta == {"shape": [24, 40, 3]}
    plain = not layout or "rowsperstrip" in layout  # strips written one after the other are one run
    assert (not data.flags.writeable) == plain  # a view of the bytes exactly when stored plainly
    with pytest.raises(InputFileError, match=r"f\.tif"):
        decode_frame(p, content[: len(content) - 100])
