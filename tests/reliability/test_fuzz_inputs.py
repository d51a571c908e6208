"""Hypothesis fuzz of the readers of user files: the rig loader, the spectral CSV reader, the
journal reader and the TIFF frame reader end in a result or one :class:`OmnispectralError`, never in
another exception.  The budget is small for CI (``max_examples`` 150 each, no deadline)."""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tifffile

pytest.importorskip("hypothesis", reason="hypothesis is not installed (pip install 'omnispectral[test]')")

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omnispectral.capture.plan import make_plan
from omnispectral.capture.session import Session, read_journal, verify_session
from omnispectral.errors import OmnispectralError
from omnispectral.rig import load_preset, load_rig, rig_from_dict

#: CI budget; a longer, random search:
#: OMNISPECTRAL_FUZZ_EXAMPLES=2000 OMNISPECTRAL_FUZZ_RANDOM=1 pytest tests/reliability/test_fuzz_inputs.py
FUZZ = settings(max_examples=int(os.environ.get("OMNISPECTRAL_FUZZ_EXAMPLES", "150")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow],
                derandomize=not os.environ.get("OMNISPECTRAL_FUZZ_RANDOM"))
WORK = Path(tempfile.mkdtemp(prefix="omnispectral-fuzz-"))


def teardown_module(module):
    shutil.rmtree(WORK, ignore_errors=True)


def _rig_dict() -> dict:
    return tomllib.loads(load_preset("small").toml_text)


def _key_paths(d, prefix=()):
    for k, v in d.items():
        yield (*prefix, k)
        if isinstance(v, dict):
            yield from _key_paths(v, (*prefix, k))


RIG_PATHS = list(_key_paths(_rig_dict()))
VALUES = st.one_of(st.none(), st.booleans(), st.integers(min_value=-(1 << 70), max_value=1 << 70),
                   st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12),
                   st.lists(st.floats(allow_nan=True, allow_infinity=True) | st.integers(-5, 10**15), max_size=16),
                   st.dictionaries(st.text(max_size=5), st.integers(), max_size=3))


# ------------------------------------------------------------------ rig loader
@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(RIG_PATHS), VALUES, st.booleans()), min_size=1, max_size=4))
def test_rig_loader_never_raises_anything_but_a_clear_error(edits):
    data = _rig_dict()
    for path, value, delete in edits:
        node = data
        for k in path[:-1]:
            node = node.get(k) if isinstance(node, dict) else None
        if not isinstance(node, dict):
            continue
        if delete:
            node.pop(path[-1], None)
        else:
            node[path[-1]] = value
    try:
        rig = rig_from_dict(data, "fuzz.toml")
        plan = make_plan(rig)
    except OmnispectralError:
        return
    assert plan.n_directions >= 1 and all(math.isfinite(t) and t > 0 for t in plan.exposures_s)
    for cam in rig.cameras.values():
        assert all(math.isfinite(v) for v in cam.lens.distortion) and cam.width_px * cam.height_px <= 1 << 28
    assert all(math.isfinite(v) for v in rig.mounting.baseline_mm)


@FUZZ
@given(text=st.text(alphabet=st.sampled_from(list("[]=\".,#\n abcnpx_0123456789-+einf{}AB")), max_size=300))
def test_rig_file_of_random_text_gives_one_clear_error(text):
    p = WORK / "random-rig.toml"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(OmnispectralError):
        load_rig(p)


# ------------------------------------------------------------------ spectral CSV reader
CSV_CHARS = st.sampled_from(list("0123456789.,-+eE#\n \tnaifx%wavelength_nm\ufeff\x00"))


@FUZZ
@given(body=st.text(alphabet=CSV_CHARS, max_size=200), header=st.booleans(),
       kind=st.sampled_from(["transmittance", "reflectance", "sensitivity", "illuminant"]))
def test_csv_reader_never_raises_anything_but_a_clear_error(body, header, kind):
    from omnispectral.spectral.curves import read_spectral_csv

    p = WORK / "random.csv"
    p.write_text(("wavelength_nm,a\n" if header else "") + body, encoding="utf-8")
    try:
        s = read_spectral_csv(p, kind)
    except OmnispectralError:
        return
    assert np.all(np.isfinite(s.values)) and np.all(np.diff(s.wavelength_nm) > 0)
    if kind in ("transmittance", "reflectance"):
        assert s.values.max() <= 1.0 + 1e-6


@FUZZ
@given(data=st.binary(max_size=200))
def test_csv_reader_on_random_bytes(data):
    from omnispectral.spectral.curves import read_spectral_csv

    p = WORK / "random-bytes.csv"
    p.write_bytes(data)
    with pytest.raises(OmnispectralError):
        read_spectral_csv(p, "transmittance")


# ------------------------------------------------------------------ journal reader
def _frame_session() -> Path:
    """A session of the ``small`` plan with the first 6 frames (4 × 6 px) written."""
    root = WORK / "journal-session"
    if (root / "session.json").exists():
        return root
    rig = load_preset("small")
    s = Session.create(root, rig, make_plan(rig), kind="test")
    for k in range(3):
        for cam in ("A", "B"):
            s.write_frame(np.full((4, 6), 100 * k, np.uint16), direction=0, camera=cam, exposure_index=k,
                          exposure_s=0.01, pan_deg_commanded=0.0, tilt_deg_commanded=0.0, pan_deg_reported=0.0,
                          tilt_deg_reported=0.0, timestamp="2026-01-01T00:00:00", bit_depth=12)
    return root


LINE = st.one_of(
    st.binary(max_size=60),
    st.builds(lambda d, c, k, extra: json.dumps({"direction": d, "camera": c, "exposure_index": k, **extra}).encode(),
              st.one_of(st.integers(-3, 1 << 40), st.text(max_size=3), st.none(), st.floats()),
              st.one_of(st.sampled_from(["A", "B", "C"]), st.integers()),
              st.one_of(st.integers(-2, 20), st.lists(st.integers(), max_size=2)),
              st.dictionaries(st.sampled_from(["sha256", "bytes", "file", "exposure_s"]),
                              st.one_of(st.integers(), st.text(max_size=8), st.none()), max_size=3)))


@FUZZ
@given(lines=st.lists(LINE, max_size=12), keep=st.integers(0, 6), newline_at_end=st.booleans())
def test_journal_reader_and_verify_never_crash(lines, keep, newline_at_end):
    from omnispectral.capture.resume import repair_session

    root = _frame_session()
    original = (root / "journal.jsonl").read_bytes().splitlines(keepends=True)
    blob = b"".join(original[:keep]) + b"\n".join(lines) + (b"\n" if newline_at_end and lines else b"")
    (root / "journal.jsonl").write_bytes(blob)
    try:
        j = read_journal(root / "journal.jsonl")
        assert all(isinstance(k[0], int) and isinstance(k[2], int) for k in j.records)
        report = verify_session(root)
        assert report["n_ok"] + report["n_missing"] + report["n_damaged"] == report["n_planned"]
        rep = repair_session(root)  # dry run: the frames themselves are intact ...
        assert rep["n_frames"] + rep["n_quarantined"] == 6 and not rep["applied"]
        # ... but one whose journal line now holds another checksum is never given a new one
        assert all(d["problem"].startswith("checksum mismatch with its journal record") for d in rep["damaged_frames"])
    finally:
        (root / "journal.jsonl").write_bytes(b"".join(original))


# ------------------------------------------------------------------ TIFF frame reader
def _valid_frame_bytes() -> bytes:
    root = _frame_session()
    return (root / "frames/d0000/A_e01.tif").read_bytes()


@FUZZ
@given(edits=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), max_size=8),
       cut=st.one_of(st.none(), st.integers(0, 2000)))
def test_tiff_frame_reader_never_raises_anything_but_a_clear_error(edits, cut):
    from omnispectral.imaging.bracket import read_frame

    data = bytearray(_valid_frame_bytes())
    for pos, value in edits:
        if data:
            data[pos % len(data)] = value
    if cut is not None:
        data = data[:cut]
    root = WORK / "tiff-session"
    if not root.exists():
        shutil.copytree(_frame_session(), root)
    victim = root / "frames/d0000/A_e01.tif"
    victim.write_bytes(bytes(data))
    for read in (lambda: Session.open(root).read_frame(0, "A", 1), lambda: (read_frame(victim), None)):
        try:
            frame, _ = read()
        except OmnispectralError:
            continue
        assert frame.size <= 1 << 28
    report = verify_session(root, checksums=False, check_pixels=True)
    assert report["n_ok"] + report["n_damaged"] + report["n_missing"] == report["n_planned"]


def test_fuzz_targets_accept_valid_input():
    """The fuzzed readers do accept the valid inputs the fuzz starts from (so the fuzz is not vacuous)."""
    from omnispectral.imaging.bracket import read_frame

    assert rig_from_dict(_rig_dict(), "small").name == "small"
    root = _frame_session()
    assert len(read_journal(root / "journal.jsonl").records) == 6
    frame, meta = Session.open(root).read_frame(0, "A", 1)
    assert frame.shape == (4, 6) and int(frame.max()) == 100 and meta["exposure_index"] == 1
    p = WORK / "ok.tif"
    tifffile.imwrite(p, np.arange(24, dtype=np.uint16).reshape(4, 6))
    assert int(read_frame(p).sum()) == 276
