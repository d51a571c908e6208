"""Sizes checked before decoding: an ``hdr merge`` whose working memory exceeds the budget is refused from the
headers, and camera raw files are refused from their metadata before LibRaw decodes them."""

from __future__ import annotations

import struct
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from omnispectral import limits
from omnispectral.cli import main
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bracket import merge_memory_bytes

from .test_fault_injection import tiny_rig
from .test_hostile_inputs import bomb_jpeg, peak_rss_kib, small_png

GIB = 2**30


# ------------------------------------------------------------------ hdr merge: the memory budget
def _bracket(tmp_path: Path, side: int = 15000) -> list[str]:
    return [str(bomb_jpeg(tmp_path / f"big_{k}.jpg", side=side)) for k in range(3)]


def test_merge_memory_counts_frames_and_output():
    shape = (15000, 15000, 3)
    px = 15000 * 15000
    base = merge_memory_bytes(shape, 1, 3)
    assert base == 4 * px * 3 + px * 3 * 10 + px * 3 * 4 * 2  # frames (+ one decoding), output, written copies
    assert merge_memory_bytes(shape, 1, 3, recover_response=True) == base + 3 * px * 3
    assert merge_memory_bytes(shape, 2, 3) > base
    assert merge_memory_bytes(shape, 1, 3, with_variance=True) > merge_memory_bytes(shape, 1, 3)


def test_hdr_merge_of_huge_jpegs_is_refused_before_decoding_with_a_stated_budget(tmp_path, capsys):
    files = _bracket(tmp_path)
    before = peak_rss_kib()
    code = main(["hdr", "merge", *files, "--times", "0.01", "0.04", "0.16", "--memory-gb", "4",
                 "-o", str(tmp_path / "o.exr")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1, err
    need = merge_memory_bytes((15000, 15000, 3), 1, 3, recover_response=True) / GIB
    assert f"big_0.jpg: merging 3 frames of 15000x15000 px x 3 (uint8) needs about {need:.1f} GiB" in err
    assert "budget of 4.0 GiB (--memory-gb 4)" in err
    assert peak_rss_kib() - before < 200_000 and not (tmp_path / "o.exr").exists()


def test_hdr_merge_budget_is_a_share_of_the_available_memory(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 8 * GIB)
    files = _bracket(tmp_path)
    assert main(["hdr", "merge", *files, "--times", "0.01", "0.04", "0.16", "-o", str(tmp_path / "o.exr")]) == 1
    err = capsys.readouterr().err
    assert "more than the budget of 4.0 GiB (50% of the 8.0 GiB available; --memory-gb states another budget)" in err
    # a bracket within the budget is merged as before
    small = [str(small_png(tmp_path / f"s{k}.png", 40 * (k + 1))) for k in range(3)]
    assert main(["hdr", "merge", *small, "--times", "0.01", "0.02", "0.04", "--response", "linear",
                 "-o", str(tmp_path / "ok.exr")]) == 0
    assert (tmp_path / "ok.exr").is_file()


def test_available_memory_falls_back_to_proc_meminfo(monkeypatch):
    if not Path("/proc/meminfo").is_file():
        pytest.skip("no /proc/meminfo")
    monkeypatch.setattr(limits, "psutil", None)
    assert limits.available_memory_bytes() > 0


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_memory_budget_must_be_positive(tmp_path, capsys, value):
    small = [str(small_png(tmp_path / f"s{k}.png", 40 * (k + 1))) for k in range(2)]
    assert main(["hdr", "merge", *small, "--times", "0.01", "0.02", "--memory-gb", value,
                 "-o", str(tmp_path / "o.exr")]) == 2
    assert "--memory-gb" in capsys.readouterr().err
    with pytest.raises(ConfigurationError):
        limits.memory_budget(float(value))


# ------------------------------------------------------------------ camera raw files: sizes from the metadata
def _dng(tmp_path: Path, name: str = "a.dng", claim_side: int | None = None) -> Path:
    import tifffile

    from tests.capture.test_import import write_dng

    p = tmp_path / name
    write_dng(p, (np.arange(52 * 96).reshape(52, 96) % 4000).astype(np.uint16), 64, 4095)
    if claim_side is not None:  # the metadata claims another size; the pixel data stays 52 x 96
        data = bytearray(p.read_bytes())
        with tifffile.TiffFile(p) as tf:
            for tag in ("ImageWidth", "ImageLength"):
                t = tf.pages[0].tags[tag]
                struct.pack_into("<H" if t.dtype == 3 else "<I", data, t.valueoffset, claim_side)
        p.write_bytes(bytes(data))
    return p


class _FakeRaw:
    """A rawpy object whose metadata claims ``side``² px; reading its pixels (decoding) is recorded."""

    decoded = False

    def __init__(self, side: int):
        self.sizes = SimpleNamespace(raw_height=side, raw_width=side, height=side, width=side)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    @property
    def raw_image_visible(self):
        _FakeRaw.decoded = True
        return np.zeros((4, 4), np.uint16)


def test_camera_raw_sizes_are_checked_before_decoding(monkeypatch, tmp_path):
    rawpy = pytest.importorskip("rawpy")
    from omnispectral.capture.sourcefiles import read_camera_raw

    monkeypatch.setattr(rawpy, "imread", lambda path: _FakeRaw(60000))
    _FakeRaw.decoded = False
    with pytest.raises(InputFileError, match=r"x.dng: claims 60000x60000 px .* above the limit"):
        read_camera_raw(tmp_path / "x.dng")
    assert not _FakeRaw.decoded
    monkeypatch.setattr(rawpy, "imread", lambda path: _FakeRaw(52))
    with pytest.raises(InputFileError, match=r"x.dng: 52x52 px, the rig's sensor is 96x52"):
        read_camera_raw(tmp_path / "x.dng", (52, 96))
    assert not _FakeRaw.decoded


def test_real_dng_claiming_a_huge_size_is_refused_from_its_metadata(tmp_path):
    pytest.importorskip("rawpy")
    from omnispectral.capture.sourcefiles import decode_source_image

    mosaic, meta = decode_source_image(_dng(tmp_path), (52, 96))
    assert mosaic.shape == (52, 96) and meta["cfa_pattern"] == "RGGB"
    with pytest.raises(InputFileError, match=r"big.dng: claims 30000x30000 px .* above the limit"):
        decode_source_image(_dng(tmp_path, "big.dng", claim_side=30000))
    with pytest.raises(InputFileError, match=r"other.dng: 96x52 px, the rig's sensor is 256x136"):
        decode_source_image(_dng(tmp_path, "other.dng"), (136, 256))


def test_import_refuses_a_raw_file_of_another_sensor_before_decoding(tmp_path, capsys, monkeypatch):
    rawpy = pytest.importorskip("rawpy")
    real = rawpy.imread
    opened = []

    def spy(path):
        raw = real(path)
        opened.append(raw)
        return raw

    monkeypatch.setattr(rawpy, "imread", spy)
    (tmp_path / "raw").mkdir()
    _dng(tmp_path / "raw", "IMG_0.dng")
    (tmp_path / "dirs.csv").write_text("file,pan_deg,tilt_deg,exposure_s\nIMG_0.dng,0,0,0.01\n")
    code = main(["import", "--preset", "small", "--directions", str(tmp_path / "dirs.csv"), "--images",
                 str(tmp_path / "raw"), "-o", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and "IMG_0.dng: 96x52 px, the rig's sensor is 256x136" in err, err
    assert opened


def test_hdr_merge_names_camera_raw_files_it_does_not_read(tmp_path, capsys):
    pytest.importorskip("tifffile")
    files = [str(_dng(tmp_path, f"IMG_{k}.dng", claim_side=30000)) for k in range(2)]
    assert main(["hdr", "merge", *files, "--times", "0.01", "0.02", "-o", str(tmp_path / "o.exr")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "IMG_0.dng: a camera raw file: hdr merge reads TIFF/PNG/JPEG frames" in err


def _rig_file(tmp_path: Path, width_px: int, height_px: int) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(tiny_rig(width_px, height_px).toml_text)
    return path


def test_simulate_at_the_sensor_limit_is_refused_before_rendering(tmp_path, capsys):
    """A rig at the documented sensor limit (32768² px) needs ~2.6 TiB of working memory: refused in one line
    naming the need and the budget, before anything is allocated (was: 32 GiB allocated, then killed)."""
    rig = _rig_file(tmp_path, 32768, 32768)
    before = peak_rss_kib()
    assert main(["simulate", "--rig", str(rig), "-o", str(tmp_path / "s")]) == 1
    err = capsys.readouterr().err
    assert "needs about" in err and "budget" in err and len(err.strip().splitlines()) == 1, err
    assert peak_rss_kib() - before < 200_000
    assert not (tmp_path / "s").exists()


def test_process_checks_its_memory_against_the_machine(tmp_path, monkeypatch):
    """``process`` estimates its working memory from the session's sensor before the merge: with 100 MB
    available (half of it the budget) a 48 × 26 px session is refused naming its rig file."""
    import datetime as dt

    from omnispectral.product.process import process
    from omnispectral.rig import load_rig
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.simulate import simulate_session

    rig = load_rig(_rig_file(tmp_path, 48, 26))
    simulate_session(tmp_path / "s", rig, ProceduralOutdoorScene("12:00"),
                     start=dt.datetime(2017, 6, 21, 12, tzinfo=dt.UTC), ground_truth_width=32, progress=False,
                     calibration_views=False)
    monkeypatch.setattr(limits, "available_memory_bytes", lambda: 100_000_000)
    with pytest.raises(InputFileError, match=r"rig\.toml: processing 48 × 26 frames needs about 0\.3 GiB"):
        process(tmp_path / "s", tmp_path / "p", progress=False, report=False)
    assert not (tmp_path / "p" / "merged").exists()
