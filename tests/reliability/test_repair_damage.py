"""``session repair`` never blesses damaged pixels (docs/reliability.md, "Resume"): a frame that fails its journal
checksum, the pixel checksum its TIFF description embeds, or holds a value above the camera's full scale is
quarantined (``SESSION/quarantine/frames/…``), left out of the journal and shot again by a resume."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import tifffile

from omnispectral.capture.resume import repair_session
from omnispectral.capture.session import Session, pixels_sha256, read_journal, verify_session
from omnispectral.checksums import file_sha256
from omnispectral.cli import main
from omnispectral.sim.simulate import simulate_session
from tests.reliability.test_fault_injection import NOON, tiny_rig, tiny_scene

#: The frame the tests damage, its key and where a repair moves it.
VICTIM = "frames/d0003/A_e02.tif"
VICTIM_KEY = (3, "A", 2)
QUARANTINED = "quarantine/frames/d0003/A_e02.tif"


def simulate_small(path: Path) -> dict:
    """12 directions x 6 exposures x 2 cameras of 48 x 26 px (and a sun bracket), no calibration views."""
    return simulate_session(path, tiny_rig(48, 26), tiny_scene(), start=NOON, ground_truth_width=64,
                            progress=False, calibration_views=False)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("repair-damage")
    simulate_small(root / "s")
    return root / "s"


@pytest.fixture
def session(pristine, tmp_path) -> Path:
    shutil.copytree(pristine, tmp_path / "s")
    return tmp_path / "s"


def rewrite_frame(path: Path, pixels: np.ndarray, description: str) -> None:
    """Write ``pixels`` into the frame TIFF at ``path`` as :meth:`Session.write_frame` does, with ``description``."""
    tifffile.imwrite(path, pixels, photometric="rgb" if pixels.ndim == 3 else "minisblack",
                     description=description, metadata=None)


def damage_one_pixel(path: Path, value: int | None = None) -> None:
    """Change one pixel of a frame (to ``value``, else by one code), keeping its description and its size."""
    with tifffile.TiffFile(path) as tf:
        pixels, description = tf.pages[0].asarray(), tf.pages[0].description
    size = path.stat().st_size
    pixels[5, 7, 1] = value if value is not None else pixels[5, 7, 1] ^ 1
    rewrite_frame(path, pixels, description)
    assert path.stat().st_size == size


def journal_lines(session: Path) -> list[str]:
    return (session / "journal.jsonl").read_text().splitlines(keepends=True)


def key_of(line: str) -> tuple[int, str, int]:
    rec = json.loads(line)
    return rec["direction"], rec["camera"], rec["exposure_index"]


def line_of(lines: list[str], key: tuple[int, str, int]) -> int:
    return next(i for i, line in enumerate(lines) if key_of(line) == key)


def repair_json(session: Path, capsys, *options: str) -> dict:
    assert main(["session", "repair", str(session), "--json", *options]) == 0
    return json.loads(capsys.readouterr().out)


def test_damaged_frame_is_quarantined_and_shot_again(session, pristine, capsys):
    journal = (session / "journal.jsonl").read_bytes()
    damage_one_pixel(session / VICTIM)
    damaged_bytes = (session / VICTIM).read_bytes()
    assert main(["session", "verify", str(session)]) == 1
    assert f"{VICTIM}: checksum mismatch" in capsys.readouterr().out
    # the dry run names it and changes nothing
    dry = repair_json(session, capsys)
    assert [(d["file"], d["quarantine"]) for d in dry["damaged_frames"]] == [(VICTIM, QUARANTINED)]
    assert "checksum mismatch" in dry["damaged_frames"][0]["problem"] and dry["quarantined"] == [QUARANTINED]
    assert dry["n_changed"] == 0 and dry["n_dropped"] == 1 and not dry["applied"]
    assert (session / "journal.jsonl").read_bytes() == journal and (session / VICTIM).read_bytes() == damaged_bytes
    assert not (session / "quarantine").exists()
    # --apply moves it aside (bytes kept), drops its record, says so and logs it
    assert main(["session", "repair", str(session), "--apply"]) == 0
    printed = capsys.readouterr().out
    assert VICTIM in printed and QUARANTINED in printed and "1 damaged frames quarantined" in printed
    assert not (session / VICTIM).exists() and (session / QUARANTINED).read_bytes() == damaged_bytes
    records = read_journal(session / "journal.jsonl").records
    assert set(records) == set(read_journal(next(session.glob("journal.jsonl.bak-*"))).records) - {VICTIM_KEY}
    event = [e for e in Session.open(session).events() if e["event"] == "repair"][-1]
    assert event["quarantined"] == [QUARANTINED] and event["dropped"] == 1
    report = verify_session(session)
    assert not report["complete"] and report["n_damaged"] == 0
    assert [(m["file"], m["problem"]) for m in report["missing"]] == [(VICTIM, "not in the journal")]
    # a resume shoots exactly that frame again; then every frame is good, pixels included
    again = simulate_small(session)
    assert again["n_written"] == 1 and again["complete"]
    assert VICTIM_KEY in Session.open(session).completed()
    assert np.array_equal(tifffile.imread(session / VICTIM), tifffile.imread(pristine / VICTIM))  # its own noise
    assert verify_session(session, check_pixels=True)["complete"]
    assert main(["session", "verify", str(session), "--pixels"]) == 0
    capsys.readouterr()


def test_lost_line_and_garbage_lines_still_refuse_the_damaged_frame(session, capsys):
    lines = journal_lines(session)
    lost = lines.pop(line_of(lines, VICTIM_KEY))  # the damaged frame's line is lost ...
    other = lines.pop(line_of(lines, (5, "B", 4)))  # ... and an intact frame's
    garbled = sorted(key_of(lines[i]) for i in (20, 60))
    lines[20] = "\x00\x00garbage from a disk error\n"
    lines[60] = '{"direction": 2, "camera"\n'
    (session / "journal.jsonl").write_text("".join(lines))
    damage_one_pixel(session / VICTIM)
    report = repair_json(session, capsys)
    assert report["journal_bad_lines"] == [21, 61]
    assert [(d["file"], d["problem"]) for d in report["damaged_frames"]] == [
        (VICTIM, "pixel checksum mismatch (the pixels changed after the capture)")]
    assert report["recovered"] == [list(k) for k in sorted([*garbled, (5, "B", 4)])]  # not the damaged frame
    applied = repair_json(session, capsys, "--apply")
    assert applied["applied"] and applied["quarantined"] == [QUARANTINED]
    records = read_journal(session / "journal.jsonl").records
    assert VICTIM_KEY not in records and records[(5, "B", 4)] == json.loads(other)
    assert json.loads(lost)["sha256"] != file_sha256(session / QUARANTINED)
    missing = verify_session(session, check_pixels=True)["missing"]
    assert [m["file"] for m in missing] == [VICTIM]


def test_value_above_full_scale_is_refused(session, capsys):
    # an older frame (no pixel checksum in its description) holding 24480 DN in a 12-bit camera, its journal
    # line rewritten to the damaged file: only the full scale tells
    path = session / VICTIM
    with tifffile.TiffFile(path) as tf:
        pixels, record = tf.pages[0].asarray(), json.loads(tf.pages[0].description)
    record.pop("pixels_sha256", None)
    pixels[5, 7, 1] = 24480
    rewrite_frame(path, pixels, json.dumps(record))
    lines = journal_lines(session)
    i = line_of(lines, VICTIM_KEY)
    lines[i] = json.dumps({**record, "sha256": file_sha256(path), "bytes": path.stat().st_size},
                          separators=(",", ":")) + "\n"
    (session / "journal.jsonl").write_text("".join(lines))
    assert verify_session(session)["complete"]  # checksums alone see nothing
    pixels_check = verify_session(session, check_pixels=True)
    assert [d["file"] for d in pixels_check["damaged"]] == [VICTIM]
    assert "24480 DN, above the camera's full scale of 4095 DN" in pixels_check["damaged"][0]["problem"]
    report = repair_json(session, capsys)
    assert [d["file"] for d in report["damaged_frames"]] == [VICTIM] and report["needed"]
    assert "above the camera's full scale" in report["damaged_frames"][0]["problem"]
    repair_session(session, apply=True)
    assert (session / QUARANTINED).is_file() and VICTIM_KEY not in Session.open(session).completed()


def test_undamaged_session_is_left_alone(session, capsys):
    # every frame embeds the checksum of its pixels
    with tifffile.TiffFile(session / VICTIM) as tf:
        assert json.loads(tf.pages[0].description)["pixels_sha256"] == pixels_sha256(tf.pages[0].asarray())
    # an older frame without it (its journal line agrees with the file) is still good
    older = session / "frames/d0001/B_e00.tif"
    with tifffile.TiffFile(older) as tf:
        pixels, record = tf.pages[0].asarray(), json.loads(tf.pages[0].description)
    record.pop("pixels_sha256", None)
    rewrite_frame(older, pixels, json.dumps(record))
    lines = journal_lines(session)
    i = line_of(lines, (1, "B", 0))
    lines[i] = json.dumps({**record, "sha256": file_sha256(older), "bytes": older.stat().st_size},
                          separators=(",", ":")) + "\n"
    (session / "journal.jsonl").write_text("".join(lines))
    before = {p.relative_to(session).as_posix(): p.read_bytes() for p in session.rglob("*") if p.is_file()}
    report = repair_json(session, capsys)
    assert not report["needed"] and report["damaged_frames"] == [] and report["n_quarantined"] == 0
    applied = repair_json(session, capsys, "--apply")
    assert not applied["applied"] and applied["quarantined"] == []
    after = {p.relative_to(session).as_posix(): p.read_bytes() for p in session.rglob("*") if p.is_file()}
    assert after == before and not (session / "quarantine").exists()
    assert verify_session(session, check_pixels=True)["complete"]
