"""Hostile inputs end in one line naming the file or the option, never a traceback or an unbounded allocation.

Issue "Nothing the user owns is ever destroyed, and no damage passes as good data", items 3 and 4: image sizes
checked from the header before decoding (PNG, JPEG, TIFF, in ``import``, ``hdr merge`` and every image reader),
command-line values outside their domain (exit 2), bad files (exit 1), the viewer on ``::1``, and disk full
naming the file being written.
"""

from __future__ import annotations

import asyncio
import errno
import io
import pathlib
import resource
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnispectral.cli import main
from omnispectral.errors import ConfigurationError, InputFileError, describe_os_error
from omnispectral.io import atomic_write_text, is_temp_name
from omnispectral.rig import load_rig

from .test_fault_injection import simulate_tiny, tiny_rig


# ------------------------------------------------------------------ hostile images
def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def bomb_png(path: Path, side: int = 30000, palette: bool = False) -> Path:
    """A valid 1-bit grey (or palette) PNG of ``side``² px, all zeros: ~110 kB on disk, 0.8 GiB decoded (and
    2.6 GiB as the float RGB a reader makes of it).  Written row block by row block: the test never holds it."""
    row = b"\0" * ((side + 7) // 8 + 1)
    z = zlib.compressobj(9)
    parts = [z.compress(row * min(1000, side - i)) for i in range(0, side, 1000)] + [z.flush()]
    ihdr = struct.pack(">IIBBBBB", side, side, 1, 3 if palette else 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + (_chunk(b"PLTE", b"\0\0\0\xff\xff\xff")
                     if palette else b"") + _chunk(b"IDAT", b"".join(parts)) + _chunk(b"IEND", b""))
    return path


def bomb_jpeg(path: Path, side: int = 15000) -> Path:
    """A 16² px JPEG whose frame header (SOF0) claims ``side``² px (Pillow's decompression-bomb error at 15000²)."""
    buf = io.BytesIO()
    Image.new("RGB", (16, 16), (128, 64, 32)).save(buf, "JPEG")
    data = bytearray(buf.getvalue())
    struct.pack_into(">HH", data, data.index(b"\xff\xc0") + 5, side, side)
    path.write_bytes(bytes(data))
    return path


def small_png(path: Path, value: int = 100) -> Path:
    Image.fromarray(np.full((20, 30, 3), value, np.uint8)).save(path)
    return path


def peak_rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def test_bomb_files_are_what_they_claim(tmp_path, monkeypatch):
    png = bomb_png(tmp_path / "b.png")
    assert png.stat().st_size < 1_300_000
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", None)
    with Image.open(png) as im:  # a valid PNG: Pillow parses it
        assert im.size == (30000, 30000)
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 1024 * 1024 * 1024 // 4 // 3)  # Pillow's default
    with pytest.raises(Image.DecompressionBombError):  # what used to escape as a traceback
        Image.open(bomb_jpeg(tmp_path / "b.jpg"))


@pytest.mark.parametrize("palette", [False, True], ids=["1-bit", "palette"])
def test_import_refuses_a_png_bomb_before_decoding(tmp_path, capsys, palette):
    bomb_png(tmp_path / "bomb.png", palette=palette)
    (tmp_path / "dirs.csv").write_text("file,pan_deg,tilt_deg,exposure_s\nbomb.png,0,0,0.01\n")
    before = peak_rss_kib()
    code = main(["import", "--preset", "small", "--directions", str(tmp_path / "dirs.csv"), "--images",
                 str(tmp_path), "-o", str(tmp_path.parent / f"{tmp_path.name}-session")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1
    assert "bomb.png: image of 30000x30000 px; camera A of the rig is 256x136" in err
    assert peak_rss_kib() - before < 200_000  # KiB: nothing near the 2.6 GiB it used to reach


def test_import_refuses_a_jpeg_bomb_before_decoding(tmp_path, capsys):
    bomb_jpeg(tmp_path / "bomb.jpg")
    (tmp_path / "dirs.csv").write_text("file,pan_deg,tilt_deg,exposure_s\nbomb.jpg,0,0,0.01\n")
    code = main(["import", "--preset", "small", "--directions", str(tmp_path / "dirs.csv"), "--images",
                 str(tmp_path), "-o", str(tmp_path.parent / f"{tmp_path.name}-session")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1
    assert "bomb.jpg: image of 15000x15000 px x 3; camera A of the rig is 256x136" in err


def test_hdr_merge_refuses_a_png_bomb_before_decoding(tmp_path, capsys):
    good = small_png(tmp_path / "good.png")
    evil = bomb_png(tmp_path / "evil.png")
    before = peak_rss_kib()
    code = main(["hdr", "merge", str(good), str(evil), "--times", "0.01", "0.04", "-o", str(tmp_path / "o.exr")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1
    assert "evil.png: claims 30000x30000 px" in err and "above the limit" in err
    assert peak_rss_kib() - before < 200_000
    assert not (tmp_path / "o.exr").exists()


def test_hdr_merge_refuses_a_bracket_of_mixed_sizes_from_the_headers(tmp_path, capsys):
    good = small_png(tmp_path / "good.png")
    evil = bomb_jpeg(tmp_path / "evil.jpg")  # 15000² is within the limits: refused as not matching, undecoded
    before = peak_rss_kib()
    code = main(["hdr", "merge", str(good), str(evil), "--times", "0.01", "0.04", "-o", str(tmp_path / "o.exr")])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and "DecompressionBomb" not in err
    assert "evil.jpg: is (15000, 15000, 3) uint8 but good.png is (20, 30, 3) uint8" in err
    assert peak_rss_kib() - before < 200_000


def test_every_image_reader_checks_the_header_first(tmp_path):
    from omnispectral.capture.sourcefiles import decode_source_image
    from omnispectral.imaging.bracket import exif_exposure_s, read_frame
    from omnispectral.imaging.imageio import read_image
    from omnispectral.imaging.lens import read_gray8

    png, jpg = bomb_png(tmp_path / "b.png"), bomb_jpeg(tmp_path / "b.jpg", side=40000)
    for reader in (read_image, read_frame, read_gray8, exif_exposure_s, lambda p: decode_source_image(p)):
        for path in (png, jpg):
            with pytest.raises(InputFileError, match=r"claims \d+x\d+ px .* above the limit"):
                reader(path)
    with pytest.raises(InputFileError, match="15000x15000 px, the rig's sensor is 136x256"):
        decode_source_image(bomb_jpeg(tmp_path / "c.jpg"), (256, 136))
    ok = small_png(tmp_path / "ok.png")  # an ordinary image still reads, with or without the sensor's size
    assert read_image(ok).shape == (20, 30, 3) and decode_source_image(ok, (20, 30))[0].shape == (20, 30, 3)


def test_radiance_hdr_header_is_checked(tmp_path):
    from omnispectral.imaging.imageio import read_image

    p = tmp_path / "big.hdr"
    p.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 40000 +X 80000\n" + b"\0" * 64)
    with pytest.raises(InputFileError, match=r"big.hdr: claims 80000x40000 px"):
        read_image(p)


# ------------------------------------------------------------------ command-line values outside their domain
@pytest.fixture(scope="module")
def tiny_session(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile")
    simulate_tiny(root / "s")
    return root / "s"


@pytest.mark.parametrize("command", ["process", "mosaic"])
def test_huge_tile_is_one_line(tiny_session, tmp_path, capsys, command):
    out = tmp_path / ("p" if command == "process" else "m.zarr")
    code = main([command, str(tiny_session), "-o", str(out), "--tile", "99999999999"])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err and err.count("\n") == 1
    assert "tile must be at most 8192 px, got 99999999999" in err


@pytest.mark.parametrize(("args", "message"), [
    (["--seed", "-1"], "argument --seed: -1 is outside 0-4294967295"),
    (["--seed", "99999999999999999999999"], "argument --seed: 99999999999999999999999 is outside"),
    (["--date", "2017-02-30"], "argument --date: '2017-02-30' is not a date YYYY-MM-DD (day is out of range"),
    (["--date", "yesterday"], "argument --date: 'yesterday' is not a date"),
])
def test_simulate_values_outside_their_domain_exit_2(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exc:
        main(["simulate", "--preset", "small", "-o", str(tmp_path / "s"), *args])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and message in err and "Traceback" not in err
    assert not (tmp_path / "s").exists()


# ------------------------------------------------------------------ bad files (exit 1)
def _filter_csv(path: Path, rows: str) -> Path:
    path.write_text("# units: fraction\nwavelength_nm,hostile\n" + rows)
    return path


def test_filter_csv_of_subnormal_values_is_one_line(tmp_path, capsys):
    from omnispectral.spectral.library import load_filter

    p = _filter_csv(tmp_path / "tiny.csv", "".join(f"{wl},1e-320\n" for wl in range(400, 701, 10)))
    with pytest.raises(InputFileError, match=r"tiny.csv: the filter's transmittance is zero at every wavelength"):
        load_filter(str(p))
    q = _filter_csv(tmp_path / "faint.csv", "".join(f"{wl},1e-300\n" for wl in range(400, 701, 10)))
    with pytest.raises(InputFileError, match=r"faint.csv: the filter's transmittance peaks at 1e-300"):
        load_filter(str(q))
    code = main(["spectral", "evaluate", "--filter", str(p), "--filter", "sp18-standin", "--plot", "none"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1 and "tiny.csv" in err


def test_csv_with_a_5_mb_field_is_one_line(tmp_path, capsys):
    from omnispectral.spectral.curves import read_spectral_csv

    p = _filter_csv(tmp_path / "big.csv", "400,0.5\n410," + "1" * 5_000_000 + "\n420,0.5\n")
    with pytest.raises(InputFileError, match=r"big.csv, line 4: not a readable CSV table \(field larger"):
        read_spectral_csv(p, "transmittance")
    code = main(["spectral", "evaluate", "--filter", str(p), "--filter", "sp18-standin", "--plot", "none"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" not in err and err.count("\n") == 1 and "big.csv, line 4" in err


def test_rig_distortion_1e308_is_one_line(tmp_path, capsys):
    text = tiny_rig().toml_text
    old = "distortion = [-0.28,"
    assert old in text
    p = tmp_path / "r.toml"
    p.write_text(text.replace(old, "distortion = [1e308,", 1))
    with pytest.raises(ConfigurationError, match=r"distortion: coefficient 1e\+308 is beyond ±1e\+06"):
        load_rig(p)
    assert main(["plan", "--rig", str(p)]) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.count("\n") == 1 and "r.toml" in err


# ------------------------------------------------------------------ the viewer on ::1
def _status(app, host: str | None) -> int:
    sent = []

    async def inner(scope, receive, send):
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    async def receive():
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message):
        sent.append(message)

    headers = [] if host is None else [(b"host", host.encode())]
    scope = {"type": "http", "method": "GET", "path": "/", "raw_path": b"/", "query_string": b"",
             "headers": headers, "http_version": "1.1", "scheme": "http", "server": ("::1", 8000),
             "client": ("::1", 5000), "root_path": ""}
    asyncio.run(app(inner)(scope, receive, send))
    return sent[0]["status"]


@pytest.mark.parametrize(("host", "status"), [
    ("[::1]:8000", 200), ("[::1]", 200), ("127.0.0.1:8000", 200), ("localhost:8000", 200), ("LOCALHOST", 200),
    ("attacker.example:8000", 400), ("[::2]:8000", 400), ("[::1", 400), ("", 400), (None, 400),
    ("localhost.attacker.example", 400),
])
def test_viewer_on_ipv6_loopback_accepts_bracketed_host(host, status):
    from omnispectral.view.server import LoopbackHostMiddleware, host_name

    assert host_name("[::1]:8000") == "::1" and host_name("localhost:80") == "localhost"
    assert _status(LoopbackHostMiddleware, host) == status


# ------------------------------------------------------------------ disk full names the file being written
@pytest.mark.parametrize("error", [
    OSError(errno.ENOSPC, "No space left on device"),  # what a failed write raises: no file name
    OSError(errno.ENOSPC),                             # errno given as the only argument
    OSError("[Errno 28] No space left on device"),     # re-raised by a library as text
], ids=["errno-strerror", "errno-only", "text"])
def test_disk_full_inside_atomic_path_names_the_output(tmp_path, monkeypatch, error):
    target = tmp_path / "out.json"
    target.write_text("old")

    def full(self, *args, **kwargs):
        raise error

    monkeypatch.setattr(pathlib.Path, "write_text", full)
    with pytest.raises(OSError) as exc:
        atomic_write_text(target, "new")
    assert describe_os_error(exc.value) == f"{target}: disk full"
    monkeypatch.undo()
    assert target.read_text() == "old" and not [p for p in tmp_path.iterdir() if is_temp_name(p.name)]


def test_disk_full_on_the_command_line_names_the_output(tmp_path, monkeypatch, capsys):
    def full(self, *args, **kwargs):
        raise OSError(errno.ENOSPC)

    monkeypatch.setattr(pathlib.Path, "write_text", full)
    code = main(["plan", "--preset", "small", "--tradeoff", str(tmp_path / "t.png")])
    monkeypatch.undo()
    err = capsys.readouterr().err
    assert code == 1 and f"{tmp_path / 't.json'}: disk full" in err.replace("\n", "")
    assert "(no file name)" not in err and "Traceback" not in err
    assert not (tmp_path / "t.json").exists() and not [p for p in tmp_path.iterdir() if is_temp_name(p.name)]


def test_disk_full_in_a_store_chunk_names_the_array(tmp_path, monkeypatch):
    from omnispectral.mosaic.store import ChannelLast

    class Full:
        shape, dtype = (2, 2, 1), np.float32
        metadata = None

        def __setitem__(self, key, value):
            raise OSError(errno.ENOSPC, "No space left on device")

    a = ChannelLast(Full(), tmp_path / "panorama.zarr" / "0")
    with pytest.raises(OSError) as exc:
        a[0:1, 0:1, :] = np.zeros((1, 1, 1), np.float32)
    assert describe_os_error(exc.value) == f"{tmp_path / 'panorama.zarr' / '0'}: disk full"


def test_exr_data_window_is_checked_before_reading(tmp_path):
    import OpenEXR

    from omnispectral.imaging.imageio import read_exr, read_image

    p = tmp_path / "big.exr"
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"R": np.ones((5, 7), np.float32), "G": np.ones((5, 7), np.float32)}).write(str(p))
    assert read_exr(p)[0].shape == (5, 7, 2)
    data = bytearray(p.read_bytes())
    at = data.index(b"dataWindow\0box2i\0") + len(b"dataWindow\0box2i\0") + 4
    struct.pack_into("<iiii", data, at, 0, 0, 99999, 99999)
    p.write_bytes(bytes(data))
    before = peak_rss_kib()
    with pytest.raises(InputFileError, match=r"big.exr: claims 100000x100000 px"):
        read_image(p)
    assert peak_rss_kib() - before < 200_000
