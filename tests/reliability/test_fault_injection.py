"""Fault injection: every case of the fault probe reproduced — kills at each kind of rename (``os.replace``
intercepted in a child process that SIGKILLs itself), concurrent runs, parameter changes on resume,
corrupted frames, hostile sizes — and what must happen instead (docs/reliability.md)."""

from __future__ import annotations

import datetime as dt
import errno
import hashlib
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tifffile

from omnispectral.capture.session import Session, dark_extensions, read_journal, verify_session
from omnispectral.cli import main
from omnispectral.errors import ConfigurationError, InputFileError, OmnispectralError
from omnispectral.io import TEMP_MARK, atomic_write_text, is_temp_name
from omnispectral.locking import LOCK_NAME, LockedError, directory_lock, read_holder
from omnispectral.rig import load_preset, load_rig, rig_from_dict
from omnispectral.sim.simulate import simulate_session

NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)
TESTS = os.path.dirname(os.path.abspath(__file__))
SRC = str(Path(TESTS).parents[1] / "src")


#: Frames of a tiny session at noon: 12 directions x 6 exposures x 2 cameras, one sun bracket of 4 attenuated
#: exposures x 2 cameras, and the dark extension of 4 directions whose darkest pixels the bracket leaves noisy
#: (2 longer exposures x 2 cameras each).
TINY_FRAMES = 144 + 8 + 16


def tiny_rig(width_px: int = 96, height_px: int = 52):
    """The ``small`` preset reduced to 12 directions × 6 exposures of 96 × 52 px (144 regular frames)."""
    text = load_preset("small").toml_text
    for old, new in (("width_px = 256", f"width_px = {width_px}"), ("height_px = 136", f"height_px = {height_px}"),
                     ("count = 15", "count = 6"), ("shortest_s = 0.000015", "shortest_s = 0.0002"),
                     ("n_pan = 12", "n_pan = 6"), ("n_tilt = 3", "n_tilt = 2"),
                     ("hfov_deg = 95.0", "hfov_deg = 120.0")):
        text = text.replace(old, new)
    return rig_from_dict(tomllib.loads(text), "tiny", text)


def tiny_scene(time_hhmm: str = "12:00"):
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    return ProceduralOutdoorScene(time_hhmm=time_hhmm)


def simulate_tiny(path, seed: int = 0, time_hhmm: str = "12:00", rig=None) -> dict:
    return simulate_session(path, rig or tiny_rig(), tiny_scene(time_hhmm), start=NOON, seed=seed,
                            ground_truth_width=64, progress=False)


def tree_digest(root: Path, sub: str) -> dict[str, str]:
    """SHA-256 of every file under ``root/sub`` (relative names)."""
    base = root / sub
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(base.rglob("*")) if p.is_file()}


def temp_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if is_temp_name(p.name)]


@pytest.fixture(scope="module")
def session(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fault")
    simulate_tiny(root / "s")
    return root / "s"


@pytest.fixture(scope="module")
def product(session, tmp_path_factory) -> Path:
    from omnispectral.product.process import process

    out = tmp_path_factory.mktemp("fault-product") / "p"
    process(session, out, progress=False, report=False)
    return out


# ------------------------------------------------------------------ the kill helper
KILL_RUNNER = textwrap.dedent("""
    import json, os, signal, sys
    sys.path[:0] = [{tests!r}, {src!r}]
    kill = json.loads(sys.argv[1])
    real_replace, seen = os.replace, [0]

    def replace(src, dst, *a, **k):
        d = str(dst)
        if kill["match"] in d and d.endswith(kill.get("suffix", "")):
            seen[0] += 1
            if seen[0] == kill["n"]:
                if kill["when"] == "after":
                    real_replace(src, dst, *a, **k)
                os.kill(os.getpid(), signal.SIGKILL)  # as a power cut or kill -9 at this very point
        return real_replace(src, dst, *a, **k)

    os.replace = replace
    import test_fault_injection as t
    if kill["job"] == "simulate":
        t.simulate_tiny(kill["out"])
    else:
        from omnispectral.product.process import process
        process(kill["session"], kill["out"], progress=False, report=False)
    print("finished without being killed")
""")


def run_killed(tmp_path: Path, **kill) -> subprocess.CompletedProcess:
    """Run ``kill["job"]`` in a child that SIGKILLs itself at the ``n``-th ``os.replace`` onto a matching path."""
    script = tmp_path / "kill_runner.py"
    script.write_text(KILL_RUNNER.format(tests=TESTS, src=SRC))
    proc = subprocess.run([sys.executable, str(script), json.dumps({"match": "", **kill})], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stdout + proc.stderr[-2000:]
    return proc


# ------------------------------------------------------------------ 1. merged/ reused for other inputs
@pytest.mark.slow
def test_case01_process_refuses_intermediates_of_another_session_or_weight(session, product, tmp_path):
    from omnispectral.mosaic.store import PanoramaStore
    from omnispectral.product.fingerprint import session_identity
    from omnispectral.product.process import process

    other = tmp_path / "s2"
    simulate_tiny(other, seed=1)
    p = tmp_path / "p"
    shutil.copytree(product, p)
    before = PanoramaStore.open(p / "panorama.zarr").read()
    with pytest.raises(InputFileError, match=r"merged: was made from other inputs or settings: session\.created_utc"):
        process(other, p, progress=False, report=False)
    with pytest.raises(InputFileError, match=r'hdr_weight: "noise" → "triangle".*--overwrite'):
        process(session, p, progress=False, report=False, hdr_weight="triangle")
    with pytest.raises(InputFileError, match=r'registration\.method: "parallax" → "paper"'):
        process(session, p, progress=False, report=False, registration="paper")
    index = process(other, p, progress=False, report=False, overwrite=True)
    assert index["fingerprint"]["session"]["frames_sha256"] == session_identity(other)["frames_sha256"]
    merged = json.loads((p / "merged" / "merged.json").read_text())
    assert merged["session"]["path"] == str(other.resolve())
    after = PanoramaStore.open(p / "panorama.zarr").read()
    # another seed's noise: the panorama was really recomputed (not relabelled)
    assert np.nanmax(np.abs(after - before)) > 0
    # and a rerun with exactly the same inputs resumes instead of refusing
    again = process(other, p, progress=False, report=False)
    assert again["mosaic"]["tiles_computed"] == 0 and again["timings_s"]["hdr_merge"] == 0


def test_case01_fingerprint_names_every_difference(session, tmp_path):
    from omnispectral.fingerprint import differences
    from omnispectral.product.fingerprint import product_fingerprint

    a = product_fingerprint(session, hdr_weight="noise", registration="parallax")
    cal = tmp_path / "cal.json"
    cal.write_text('{"x": 1}')
    b = product_fingerprint(session, hdr_weight="noise", registration="parallax", rig_calibration=cal,
                            skipped_directions=[3])
    diffs = differences(a, b)
    assert len(diffs) == 2 and diffs[1].startswith("registration.rig_calibration_sha256: null → ")
    assert diffs[0] == "skipped_directions: [] → [3]"
    assert product_fingerprint(session, hdr_weight="noise", registration="parallax") == a


# ------------------------------------------------------------------ 2. resume with other parameters
@pytest.mark.parametrize(("change", "message"), [
    ({"time_hhmm": "18:00"}, r"mix frames: scene_parameters\.time_hhmm: \"12:00\" → \"18:00\""),
    ({"seed": 7}, r"seed: 0 → 7"),
    ({"rig": "half"}, r"rig cameras\.A\.width_px: 96 → 48"),
])
def test_case02_resume_with_other_parameters_is_refused(session, change, message):
    kwargs = dict(change)
    if kwargs.get("rig") == "half":
        kwargs["rig"] = tiny_rig(48, 26)
    n_before = len(read_journal(session / "journal.jsonl").records)
    with pytest.raises(InputFileError, match=message):
        simulate_tiny(session, **kwargs)
    assert len(read_journal(session / "journal.jsonl").records) == n_before == TINY_FRAMES


# ------------------------------------------------------------------ 3. concurrent runs
HOLD_LOCK = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {src!r})
    from omnispectral.locking import directory_lock
    with directory_lock(sys.argv[1], "test holder"):
        print("locked", flush=True)
        time.sleep(120)
""")


def _hold_lock(tmp_path: Path, directory: Path) -> subprocess.Popen:
    script = tmp_path / "hold.py"
    script.write_text(HOLD_LOCK.format(src=SRC))
    proc = subprocess.Popen([sys.executable, str(script), str(directory)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_case03_second_run_is_refused_and_a_dead_holders_lock_is_stale(tmp_path):
    target = tmp_path / "s"
    holder = _hold_lock(tmp_path, target)
    try:
        with pytest.raises(LockedError, match=rf"in use by pid {holder.pid} on .*test holder"):
            simulate_tiny(target)
        assert not (target / "session.json").exists()
    finally:
        holder.kill()
        holder.wait()
    record = read_holder(target)
    assert record["pid"] == holder.pid  # SIGKILL left the lock file behind ...
    with directory_lock(target) as lock:  # ... but the kernel released the lock: it is taken over as stale
        assert lock.stale_holder["pid"] == holder.pid
    assert not (target / LOCK_NAME).exists()


def test_case03_product_lock_refuses_a_second_process(session, tmp_path):
    from omnispectral.product.process import process

    holder = _hold_lock(tmp_path, tmp_path / "p")
    try:
        with pytest.raises(LockedError, match=rf"p: in use by pid {holder.pid}"):
            process(session, tmp_path / "p", progress=False)
    finally:
        holder.kill()
        holder.wait()


@pytest.mark.slow
def test_case03_two_simultaneous_simulations_never_duplicate_frames(tmp_path):
    rig_file = tmp_path / "tiny.toml"
    rig_file.write_text(tiny_rig().toml_text)
    cmd = [sys.executable, "-m", "omnispectral.cli", "simulate", "--rig", str(rig_file), "-o", str(tmp_path / "s"),
           "--gt-width", "64", "--json"]
    env = {**os.environ, "PYTHONPATH": SRC}
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for _ in range(2)]
    outs = [p.communicate(timeout=300) for p in procs]
    codes = [p.returncode for p in procs]
    written = sum(json.loads(o)["n_written"] for (o, _), c in zip(outs, codes, strict=True) if c == 0)
    refused = [e for (_, e), c in zip(outs, codes, strict=True) if c != 0]
    s = Session.open(tmp_path / "s")
    # the regular frames and the sun bracket's (TINY_FRAMES less the noon session's dark extension), and the
    # dark extension this start time needed
    expected = 144 + 8 + 2 * sum(dark_extensions(s, s.plan()).values())
    assert written == expected  # every frame written exactly once, by one of them
    assert all("in use by pid" in e and "Traceback" not in e for e in refused)
    lines = (tmp_path / "s" / "journal.jsonl").read_text().splitlines()
    keys = [(r["direction"], r["camera"], r["exposure_index"]) for r in map(json.loads, lines)]
    assert len(keys) == len(set(keys)) == expected
    assert verify_session(tmp_path / "s")["complete"]


# ------------------------------------------------------------------ 4, 7, 8. kills at renames, bit-identical resume
@pytest.fixture(scope="module")
def reference_simulation(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ref")
    simulate_tiny(root / "s")
    return root / "s"


@pytest.mark.slow
@pytest.mark.parametrize(("n", "when", "what"), [
    (1, "before", "rig.toml: a half-created session"),
    (3, "after", "session.json written, no frame yet"),
    (50, "after", "a frame renamed, its journal line not written"),
    (77, "before", "camera B of an exposure whose A frame is written"),
    (149, "before", "the ground truth"),
])
def test_case04_kill_at_a_rename_then_resume_is_bit_identical(reference_simulation, tmp_path, n, when, what):
    out = tmp_path / "s"
    run_killed(tmp_path, job="simulate", out=str(out), n=n, when=when)
    simulate_tiny(out)  # resume
    assert tree_digest(out, "frames") == tree_digest(reference_simulation, "frames"), what
    assert (out / "journal.jsonl").read_bytes() == (reference_simulation / "journal.jsonl").read_bytes(), what
    assert tree_digest(out, "ground_truth") == tree_digest(reference_simulation, "ground_truth")
    assert not temp_files(out) and not (out / LOCK_NAME).exists()
    stamps = [dt.datetime.fromisoformat(json.loads(x)["timestamp"])
              for x in (out / "journal.jsonl").read_text().splitlines()]
    assert all(b >= a for a, b in itertools.pairwise(stamps))  # time never goes backwards


def test_case04_frame_noise_does_not_depend_on_what_was_rendered_before():
    from omnispectral.sim.devices import frame_rng

    a = frame_rng(3, "A", 30.0, -15.0, 0.01).standard_normal(4)
    frame_rng(3, "A", 60.0, -15.0, 0.01).standard_normal(100)  # another frame in between
    assert np.array_equal(a, frame_rng(3, "A", 30.0, -15.0, 0.01).standard_normal(4))
    assert not np.array_equal(a, frame_rng(3, "B", 30.0, -15.0, 0.01).standard_normal(4))
    assert not np.array_equal(a, frame_rng(3, "A", 30.0, -15.0, 0.02).standard_normal(4))
    assert not np.array_equal(a, frame_rng(4, "A", 30.0, -15.0, 0.01).standard_normal(4))


@pytest.fixture(scope="module")
def reference_product(session, tmp_path_factory) -> Path:
    from omnispectral.product.process import process

    out = tmp_path_factory.mktemp("refp") / "p"
    process(session, out, progress=False, report=False)
    return out


@pytest.mark.slow
@pytest.mark.parametrize(("kill", "what"), [
    ({"match": "/merged/d", "n": 5, "when": "before"}, "merging: an image's temporary file left in merged/"),
    ({"match": "", "suffix": "panorama.zarr", "n": 1, "when": "before"}, "creating the store: a half-made store"),
    ({"match": "/.done/", "n": 1, "when": "before"}, "a chunk marker's temporary file left in .done/"),
    ({"match": "product.json", "n": 1, "when": "before"}, "everything but the index written"),
])
def test_case07_08_process_killed_at_a_rename_resumes_to_the_same_panorama(session, reference_product, tmp_path,
                                                                          kill, what):
    from omnispectral.mosaic.store import PanoramaStore
    from omnispectral.product.process import process

    out = tmp_path / "p"
    run_killed(tmp_path, job="process", session=str(session), out=str(out), **kill)
    assert temp_files(out) or kill["match"] == "product.json", what  # the kill left its temporary file
    process(session, out, progress=False, report=False)
    got = PanoramaStore.open(out / "panorama.zarr").read()
    want = PanoramaStore.open(reference_product / "panorama.zarr").read()
    np.testing.assert_array_equal(got, want)
    assert not temp_files(out), what


def test_case07_temporary_marker_never_read_as_a_marker(tmp_path):
    from omnispectral.mosaic.store import PanoramaStore

    store = PanoramaStore.create(tmp_path / "x.zarr", 32, 64, 6, 16, {}, {"a": 1})
    store.write_chunk(0, 0, 1, np.ones((16, 16, 6), np.float32), {"holes": 2})
    done = store.path / "0" / ".done"
    (done / f".0_0.json{TEMP_MARK}k1ll3d.json").write_text('{"half": ')  # a kill before the rename
    assert store.done_markers(0) == {(0, 1): {"level": 0, "ty": 0, "tx": 1, "holes": 2}}


def test_case08_half_created_session_is_created_again(tmp_path):
    rig = tiny_rig()
    from omnispectral.capture.plan import make_plan

    s = tmp_path / "s"
    (s / "frames").mkdir(parents=True)
    atomic_write_text(s / "rig.toml", "half")  # killed before plan.json and session.json
    (s / f".plan.json{TEMP_MARK}abc.json").write_text("{")
    Session.create(s, rig, make_plan(rig))
    assert Session.open(s).plan().n_directions == 12 and not temp_files(s)
    (tmp_path / "t").mkdir()
    (tmp_path / "t" / "notes.txt").write_text("mine")
    with pytest.raises(InputFileError, match="not an omnispectral session"):
        Session.create(tmp_path / "t", rig, make_plan(rig))
    assert (tmp_path / "t" / "notes.txt").read_text() == "mine"


# ------------------------------------------------------------------ 5. corrupted frames
@pytest.mark.slow
def test_case05_corrupted_same_size_frames_count_as_damaged_and_are_skippable(session, tmp_path):
    from omnispectral.product.process import process

    bad = tmp_path / "bad"
    shutil.copytree(session, bad)
    garbled = bad / "frames/d0004/A_e02.tif"
    data = bytearray(garbled.read_bytes())
    data[-600:-500] = np.random.default_rng(1).integers(0, 256, 100, dtype=np.uint8).tobytes()  # pixels only
    garbled.write_bytes(bytes(data))
    noise = bad / "frames/d0007/B_e05.tif"
    noise.write_bytes(np.random.default_rng(2).integers(0, 256, noise.stat().st_size, dtype=np.uint8).tobytes())
    # sizes alone see nothing; decoding sees both (the random file does not decode, the garbled one fails the
    # pixel checksum its description embeds); checksums (the default) see both
    fast = verify_session(bad, checksums=False)
    assert fast["n_damaged"] == 0
    decoded = verify_session(bad, checksums=False, check_pixels=True)
    assert [d["file"] for d in decoded["damaged"]] == ["frames/d0004/A_e02.tif", "frames/d0007/B_e05.tif"]
    assert decoded["damaged"][0]["problem"].startswith("pixel checksum mismatch")
    with pytest.raises(InputFileError, match=r"d0004/A_e02.tif: checksum mismatch.*--skip-bad"):
        process(bad, tmp_path / "p", progress=False, report=False)
    index = process(bad, tmp_path / "p2", progress=False, report=False, skip_bad=True)
    assert [d["direction"] for d in index["skipped_directions"]] == [4, 7]
    assert index["session_check"]["n_damaged"] == 2 and index["session_check"]["n_ok"] == TINY_FRAMES - 2


# ------------------------------------------------------------------ 6. absurd exposure times, CSV scales
def _bracket(tmp_path: Path) -> list[Path]:
    paths = []
    for k, level in enumerate((200, 800, 3200)):
        p = tmp_path / f"f{k}.tif"
        tifffile.imwrite(p, np.full((8, 10), level, np.uint16))
        paths.append(p)
    return paths


@pytest.mark.parametrize("times", [["1e-300", "0.01", "0.04"], ["1e300", "0.01", "0.04"], ["0.01", "0.01", "-2"]])
def test_case06_absurd_exposure_times_are_refused(tmp_path, capsys, times):
    files = _bracket(tmp_path)
    out = tmp_path / "o.exr"
    code = main(["hdr", "merge", *map(str, files), "--times", *times, "-o", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and not out.exists() and err.count("\n") == 1
    assert ("outside 1e-07-3600 s" in err or "not positive" in err) and "Traceback" not in err


def test_case06_merge_exposures_refuses_subnormal_times():
    from omnispectral.imaging import merge_exposures

    frames = [np.full((4, 4), v, np.uint16) for v in (100, 400)]
    with pytest.raises(ConfigurationError, match="outside"):
        merge_exposures(frames, [1e-300, 0.01])
    ok = merge_exposures(frames, [0.0025, 0.01])
    assert np.allclose(ok.radiance, 40000.0, rtol=1e-3)


@pytest.mark.parametrize(("rows", "header", "message", "peak"), [
    ("400,1.2\n500,0.8\n700,0.3", "", "neither a fraction", None),          # percent peaking at 1.2 %
    ("400,1.26\n500,0.8\n700,0.3", "", "neither a fraction", None),         # a fraction above 1
    ("400,1.26\n500,0.8\n700,0.3", "# units: fraction\n", "exceeds 1", None),
    ("400,1.2\n500,0.8\n700,0.3", "# units: percent\n", None, 0.012),
    ("400,12\n500,80\n700,30", "", None, 0.8),
])
def test_case06_ambiguous_csv_scales_are_refused(tmp_path, rows, header, message, peak):
    from omnispectral.spectral.curves import read_spectral_csv

    p = tmp_path / "t.csv"
    p.write_text(f"{header}wavelength_nm,t\n{rows}\n")
    if message:
        with pytest.raises(InputFileError, match=message):
            read_spectral_csv(p, "transmittance")
    else:
        assert read_spectral_csv(p, "transmittance").values.max() == pytest.approx(peak)


# ------------------------------------------------------------------ 9. garbage in the journal, session repair
def test_case09_garbage_journal_line_is_repaired_from_the_frames(session, tmp_path, capsys):
    from omnispectral.product.process import process

    s = tmp_path / "s"
    shutil.copytree(session, s)
    original = read_journal(s / "journal.jsonl").records
    lines = (s / "journal.jsonl").read_text().splitlines(keepends=True)
    lines[40] = "\x00\x00garbage from a disk error\n"
    lines.pop(90)  # and one line lost
    (s / "journal.jsonl").write_text("".join(lines))
    damaged_bytes = (s / "journal.jsonl").read_bytes()
    with pytest.raises(InputFileError, match=r"journal.jsonl: line 41: not a frame record.*session repair"):
        process(s, tmp_path / "p", progress=False)
    assert main(["session", "repair", str(s), "--json"]) == 0  # dry run
    report = json.loads(capsys.readouterr().out)
    assert report["journal_bad_lines"] == [41] and report["n_recovered"] == 2 and not report["applied"]
    assert (s / "journal.jsonl").read_bytes() == damaged_bytes  # a dry run changes nothing
    assert main(["session", "repair", str(s), "--apply"]) == 0
    capsys.readouterr()
    assert read_journal(s / "journal.jsonl").records == original  # every record back, byte for byte
    assert verify_session(s, check_pixels=True)["complete"]
    assert next(iter(s.glob("journal.jsonl.bak-*"))).read_bytes() == damaged_bytes


# ------------------------------------------------------------------ 10. markup in user text
def test_case10_rich_markup_in_user_text_is_printed_verbatim(tmp_path, capsys):
    assert main(["session", "verify", "q[/x]"]) == 1
    err = capsys.readouterr().err
    assert "q[/x]: not found" in err and "MarkupError" not in err and err.count("\n") == 1


# ------------------------------------------------------------------ 11. absurd rig values
@pytest.mark.parametrize(("old", "new", "message"), [
    ("count = 6", "exposures_s = [inf, 0.01]", "exposures_s: inf s is outside"),
    ("count = 6", "exposures_s = [1e300, 0.01]", "exposures_s: 1e.300 s is outside"),
    ("distortion = [", "distortion = [nan, ", r"distortion: expected 4, 5, 8, 12 or 14 numbers"),
    ("baseline_mm = [", "baseline_mm = [nan, ", r"baseline_mm: expected \[x, y, z\]"),
    ("n_pan = 6", "n_pan = 1000000000000", r"1000000000000 x 2 directions is above the limit"),
    ("hfov_deg = 120.0", "hfov_deg = 1e-9", r"fields of view must be at least 0.1 deg"),
    ("width_px = 96", "width_px = 2000000", r"2000000 px is above the limit"),
])
def test_case11_absurd_rig_values_are_refused(tmp_path, capsys, old, new, message):
    text = tiny_rig().toml_text
    assert old in text
    p = tmp_path / "r.toml"
    p.write_text(text.replace(old, new, 1))
    with pytest.raises(ConfigurationError, match=message):
        load_rig(p)
    assert main(["plan", "--rig", str(p)]) == 1
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize("depth", ["-1", "64", "0"])
def test_case11_hdr_bit_depth_out_of_range(tmp_path, capsys, depth):
    files = _bracket(tmp_path)
    assert main(["hdr", "merge", *map(str, files), "--times", "0.0025", "0.01", "0.04", "--bit-depth", depth,
                 "-o", str(tmp_path / "o.exr")]) == 2
    assert f"--bit-depth: {depth} is not a sensor bit depth" in capsys.readouterr().err


def test_case11_all_zero_filter_names_its_file(tmp_path):
    from omnispectral.spectral.library import load_filter

    p = tmp_path / "zero.csv"
    p.write_text("wavelength_nm,f\n400,0\n550,0\n700,0\n")
    with pytest.raises(InputFileError, match=r"zero.csv: the filter's transmittance is zero at every wavelength"):
        load_filter(str(p))


# ------------------------------------------------------------------ 12. export outputs, disk full, read-only
@pytest.mark.parametrize(("fmt", "name", "message"), [
    ("png", ".", "is a directory"), ("png", "x.json", r"a png export is written as \.png, not \.json"),
    ("spectral-exr", "x.png", r"written as \.exr"),
])
def test_case12_export_to_a_directory_or_wrong_extension(product, tmp_path, capsys, fmt, name, message):
    out = tmp_path / name
    assert main(["export", str(product), "--format", fmt, "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cv2.error" not in err and err.count("\n") == 1
    import re

    assert re.search(message, err)


@pytest.mark.parametrize(("code", "words"), [(errno.ENOSPC, "disk full"), (errno.EACCES, "permission denied"),
                                             (errno.EROFS, "read-only file system")])
def test_case12_disk_full_or_unwritable_output_is_one_line_and_nothing_half_written(product, tmp_path, capsys,
                                                                                  monkeypatch, code, words):
    out = tmp_path / "pano.png"

    def failing_replace(src, dst, *a, **k):
        raise OSError(code, os.strerror(code), str(dst))

    monkeypatch.setattr(os, "replace", failing_replace)
    assert main(["export", str(product), "--format", "png", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert f"{out}: {words}" in err and "Traceback" not in err and err.count("\n") == 1
    assert not out.exists() and not temp_files(tmp_path)


# ------------------------------------------------------------------ 13. hostile sizes
def hostile_tiff(path: Path, width: int = 65535, height: int = 65535) -> Path:
    """A valid 2 × 2 RGB TIFF whose header is patched to claim ``width`` × ``height`` pixels."""
    tifffile.imwrite(path, np.zeros((2, 2, 3), np.uint16), photometric="rgb")
    with tifffile.TiffFile(path) as tf:
        tags = tf.pages[0].tags
        offsets = {n: tags[n].valueoffset for n in ("ImageWidth", "ImageLength")}
        dtypes = {n: tags[n].dtype for n in ("ImageWidth", "ImageLength")}
    data = bytearray(path.read_bytes())
    for name, value in (("ImageWidth", width), ("ImageLength", height)):
        fmt = "<H" if int(dtypes[name]) == 3 else "<I"
        import struct

        struct.pack_into(fmt, data, offsets[name], value)
    path.write_bytes(bytes(data))
    return path


def test_case13_hostile_tiff_header_is_refused_before_decoding(tmp_path, capsys):
    files = _bracket(tmp_path)
    evil = hostile_tiff(tmp_path / "evil.tif")
    assert evil.stat().st_size < 2000
    import resource

    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    code = main(["hdr", "merge", str(files[0]), str(evil), "--times", "0.01", "0.04", "-o", str(tmp_path / "o.exr")])
    err = capsys.readouterr().err
    assert code == 1 and "evil.tif: claims 65535x65535 px (24.0 GiB decoded)" in err
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 200_000  # KiB: nothing near 24 GiB


def test_case13_hostile_frame_in_a_session_is_damaged_not_allocated(session, tmp_path):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    hostile_tiff(s / "frames/d0002/B_e01.tif")
    with pytest.raises(InputFileError, match=r"B_e01.tif: claims 65535x65535 px"):
        Session.open(s).read_frame(2, "B", 1)
    report = verify_session(s, checksums=False, check_pixels=True)
    assert [d["file"] for d in report["damaged"]] == ["frames/d0002/B_e01.tif"]


def test_case13_huge_panorama_width_is_refused_up_front(session, tmp_path, capsys):
    assert main(["process", str(session), "-o", str(tmp_path / "p"), "--width", "2000000"]) == 2
    err = capsys.readouterr().err
    assert "a 2000000x1000000 px panorama needs about 59604.6 GiB of disk" in err
    assert not (tmp_path / "p").exists()


# ------------------------------------------------------------------ 14. writing over inputs
def test_case14_hdr_merge_refuses_to_overwrite_an_input(tmp_path, capsys):
    files = _bracket(tmp_path)
    before = files[1].read_bytes()
    assert main(["hdr", "merge", *map(str, files), "--times", "0.0025", "0.01", "0.04", "-o", str(files[1])]) == 2
    assert "is the input" in capsys.readouterr().err
    assert files[1].read_bytes() == before


def test_case14_export_refuses_to_write_into_the_product(product, capsys):
    index = product / "product.json"
    before = index.read_bytes()
    assert main(["export", str(product), "--format", "rgb-exr", "-o", str(product / "product.exr")]) == 2
    assert "lies inside the input" in capsys.readouterr().err
    assert main(["export", str(product), "--format", "png", "-o", str(index)]) == 2
    assert index.read_bytes() == before


def test_case14_process_refuses_to_write_into_its_session(session, capsys):
    assert main(["process", str(session), "-o", str(session / "product")]) == 2
    assert "lies inside the input" in capsys.readouterr().err
    assert not (session / "product").exists()


def test_errors_are_omnispectral_errors():
    assert issubclass(LockedError, OmnispectralError)


def test_case13_frame_of_another_size_than_recorded_is_damaged(session, tmp_path):
    s = tmp_path / "s"
    shutil.copytree(session, s)
    frame, meta = Session.open(s).read_frame(5, "A", 3)
    victim = s / "frames/d0005/A_e03.tif"
    size = victim.stat().st_size
    tifffile.imwrite(victim, frame.reshape(104, 48, 3), photometric="rgb", description=json.dumps(meta),
                     metadata=None)  # same bytes, same size, another shape
    assert victim.stat().st_size == size
    report = verify_session(s, checksums=False, check_pixels=True)
    assert report["damaged"][0]["problem"] == "shape [104, 48, 3], the journal recorded [52, 96, 3]"
