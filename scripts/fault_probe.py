"""A fault probe: omnispectral's command line tried as a hostile or unlucky user would, each case classified.

Run ``python scripts/fault_probe.py [--out probe.json] [--only SUBSTRING]``.  It simulates one tiny session and
processes it (about a minute), then runs every case below against copies of them through the installed
``omnispectral`` command, each in its own process with a 4 GiB address-space limit, and classifies the outcome:

``held``        what docs/reliability.md promises happened (a result, or one error line with the right exit code)
``held-weakly`` nothing was lost, but the message was not one line, or the exit code not the promised one
``destroyed``   a file the user owned, or an input, was deleted or changed
``wrong-data``  the command exited 0 with wrong or damaged data
``traceback``   a Python traceback reached the user
``unbounded``   the memory limit or the time limit was hit

The families: ownership, damage, hostile files, values outside their domain, kills and concurrency, the viewer,
the disk.  The counts per outcome end the output; ``--out`` keeps every case's detail as JSON.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import time
import urllib.request
import zlib
from collections import Counter
from pathlib import Path

BIN = Path(sys.executable).parent / "omnispectral"
MEMORY_LIMIT_BYTES = 4 << 30
TIMEOUT_S = 300
CASES: list[tuple[str, str, object]] = []


def case(family: str):
    def register(fn):
        CASES.append((family, fn.__name__, fn))
        return fn
    return register


class Outcome(Exception):
    def __init__(self, kind: str, detail: str = ""):
        super().__init__(f"{kind}: {detail}")
        self.kind, self.detail = kind, detail


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT_BYTES, MEMORY_LIMIT_BYTES))


def run(*argv, timeout: float = TIMEOUT_S, preexec=_limit_memory, cwd=None) -> subprocess.CompletedProcess:
    """Run ``omnispectral ARGV`` (memory-limited); a traceback or the limits end the case."""
    try:
        out = subprocess.run([str(BIN), "-q", *map(str, argv)], capture_output=True, text=True, timeout=timeout,
                             preexec_fn=preexec, cwd=cwd)
    except subprocess.TimeoutExpired:
        raise Outcome("unbounded", f"still running after {timeout} s") from None
    if "MemoryError" in out.stderr or "Cannot allocate memory" in out.stderr:
        raise Outcome("unbounded", "hit the 4 GiB memory limit")
    if "Traceback (most recent call last)" in out.stderr:
        raise Outcome("traceback", out.stderr.strip().splitlines()[-1][:200])
    return out


def one_line_error(out: subprocess.CompletedProcess, code: int = 1, *words: str) -> None:
    """The command failed with ``code`` and one error line containing every word."""
    lines = [x for x in out.stderr.strip().splitlines() if x.strip()]
    if code == 2 and lines and lines[0].startswith("usage:"):  # argparse: its usage, then one error line
        lines = [x for x in lines if "error:" in x]
    if out.returncode == 0:
        raise Outcome("wrong-data", "exit 0 where an error was due")
    if out.returncode != code or len(lines) != 1 or not all(w in lines[0] for w in words):
        raise Outcome("held-weakly", f"exit {out.returncode}: {out.stderr.strip()[:300]}")


def digest(root: Path) -> dict[str, str]:
    root = Path(root)
    files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
    return {str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in files if ".omnispectral.lock" not in p.name}


def unchanged(before: dict, root: Path, what: str) -> None:
    after = digest(root)
    lost = [k for k in before if k not in after or after[k] != before[k]]
    if lost:
        raise Outcome("destroyed", f"{what}: {len(lost)} file(s) changed or removed, e.g. {lost[0]}")


# ------------------------------------------------------------------------------------------------- fixtures
class Work:
    """The probe's folder: a tiny rig, one session and its product (made once), copies per case."""

    def __init__(self, root: Path):
        self.root = root
        self.rig = root / "tiny.toml"
        self.session = root / "base-session"
        self.product = root / "base-product"
        self.n = 0

    def prepare(self) -> None:
        from omnispectral.rig import load_preset

        text = load_preset("small").toml_text
        for old, new in (("width_px = 256", "width_px = 96"), ("height_px = 136", "height_px = 52"),
                         ("count = 15", "count = 6"), ("shortest_s = 0.000015", "shortest_s = 0.0002"),
                         ("n_pan = 12", "n_pan = 6"), ("n_tilt = 3", "n_tilt = 2"),
                         ("hfov_deg = 95.0", "hfov_deg = 120.0")):
            text = text.replace(old, new)
        self.rig.write_text(text)
        print("preparing a tiny session and its product …", file=sys.stderr, flush=True)
        for argv in (["simulate", "--rig", self.rig, "--gt-width", "64", "--no-calibration-views", "-o",
                      self.session],
                     ["process", self.session, "-o", self.product, "--width", "256"]):
            out = subprocess.run([str(BIN), "-q", *map(str, argv)], capture_output=True, text=True)
            if out.returncode:
                sys.exit(f"fault probe: could not prepare ({' '.join(map(str, argv))}): {out.stderr.strip()}")

    def fresh(self, name: str) -> Path:
        self.n += 1
        return self.root / f"c{self.n:03d}-{name}"

    def session_copy(self) -> Path:
        dst = self.fresh("session")
        shutil.copytree(self.session, dst)
        return dst

    def product_copy(self) -> Path:
        dst = self.fresh("product")
        shutil.copytree(self.product, dst)
        return dst

    def user_dir(self) -> Path:
        d = self.fresh("users-folder")
        (d / "A").mkdir(parents=True)
        (d / "A" / "holiday.png").write_bytes(b"\x89PNG the user's photo")
        (d / "notes.txt").write_text("the user's notes")
        (d / "report").mkdir()
        (d / "report" / "index.html").write_text("the user's page")
        return d


def first_chunk(product: Path) -> Path:
    return next(p for p in sorted((product / "panorama.zarr" / "0" / "c").rglob("*")) if p.is_file())


def flip_bytes(path: Path, at: int | None = None) -> None:
    data = bytearray(path.read_bytes())
    k = len(data) // 2 if at is None else at
    data[k] ^= 0xFF
    data[k + 1] ^= 0x5A
    path.write_bytes(bytes(data))


def png_with_header(path: Path, width: int, height: int, bit_depth: int = 8, colour: int = 2) -> Path:
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, 0)
    raw = zlib.compress(b"\0" * 4096)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", raw) + chunk(b"IEND", b""))
    return path


def jpeg_with_header(path: Path, width: int, height: int) -> Path:
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, height, width, 3) + b"\x01\x11\x00\x02\x11\x01\x03\x11\x01"
    path.write_bytes(b"\xff\xd8" + sof + b"\xff\xd9")
    return path


def small_png(path: Path, value: int = 100) -> Path:
    import cv2
    import numpy as np

    cv2.imwrite(str(path), np.full((40, 60, 3), value, np.uint8))
    return path


# ------------------------------------------------------------------------------------------------ ownership
@case("ownership")
def mosaic_overwrite_onto_a_users_folder(w: Work):
    d = w.user_dir()
    before = digest(d)
    one_line_error(run("mosaic", w.session, "-o", d, "--overwrite"), 1)
    unchanged(before, d, "the user's folder")


@case("ownership")
def mosaic_overwrite_onto_its_session(w: Work):
    s = w.session_copy()
    before = digest(s)
    one_line_error(run("mosaic", s, "-o", s, "--overwrite"), 2, "input")
    unchanged(before, s, "the session")


@case("ownership")
def process_into_a_users_folder(w: Work):
    d = w.user_dir()
    before = digest(d)
    one_line_error(run("process", w.session, "-o", d), 1, "did not write")
    unchanged(before, d, "the user's folder")


@case("ownership")
def process_overwrite_with_a_users_file_in_merged(w: Work):
    p = w.product_copy()
    (p / "merged" / "my-notes.txt").write_text("mine")
    one_line_error(run("process", w.session, "-o", p, "--overwrite", "--hdr-weight", "triangle", "--width", "256"),
                   1, "my-notes.txt")
    if (p / "merged" / "my-notes.txt").read_text() != "mine":
        raise Outcome("destroyed", "the user's file in merged/")


@case("ownership")
def process_overwrite_with_a_users_file_in_the_store(w: Work):
    p = w.product_copy()
    (p / "panorama.zarr" / "table.csv").write_text("mine")
    one_line_error(run("process", w.session, "-o", p, "--overwrite", "--hdr-weight", "triangle", "--width", "256"),
                   1, "table.csv")
    if not (p / "panorama.zarr" / "table.csv").exists():
        raise Outcome("destroyed", "the user's file in panorama.zarr/")


@case("ownership")
def calibrate_rig_onto_the_sessions_rig(w: Work):
    s = w.session_copy()
    before = digest(s)
    one_line_error(run("calibrate", "rig", s, "-o", s / "rig.toml"), 2, "input")
    unchanged(before, s, "the session")


@case("ownership")
def calibrate_rig_onto_the_sessions_index(w: Work):
    s = w.session_copy()
    before = digest(s)
    one_line_error(run("calibrate", "rig", s, "-o", s / "session.json"), 2, "input")
    unchanged(before, s, "the session")


@case("ownership")
def export_onto_the_products_index(w: Work):
    p = w.product_copy()
    before = digest(p)
    one_line_error(run("export", p, "--format", "png", "-o", p / "product.json"), 2)
    unchanged(before, p, "the product")


@case("ownership")
def relight_into_its_product(w: Work):
    p = w.product_copy()
    before = digest(p)
    one_line_error(run("relight", p, "--white=0,-30", "--to", "A", "-o", p), 2, "input")
    unchanged(before, p, "the product")


@case("ownership")
def chessboard_views_into_a_users_folder(w: Work):
    d = w.user_dir()
    before = digest(d)
    one_line_error(run("simulate-chessboard", "--rig", w.rig, "--views", "1", "-o", d), 1, "did not write")
    unchanged(before, d, "the user's folder")


@case("ownership")
def hdr_merge_onto_one_of_its_frames(w: Work):
    d = w.fresh("bracket")
    d.mkdir()
    frames = [small_png(d / f"f{k}.png", 40 * (k + 1)) for k in range(3)]
    before = digest(d)
    one_line_error(run("hdr", "merge", *frames, "--times", "0.01", "0.02", "0.04", "-o", frames[1]), 2, "input")
    unchanged(before, d, "the bracket")


@case("ownership")
def process_series_into_its_series(w: Work):
    s = w.fresh("series")
    s.mkdir()
    (s / "series.json").write_text(json.dumps({"format": "omnispectral-series", "slots": []}))
    one_line_error(run("process-series", s, "-o", s / "out"), 2, "input")


# --------------------------------------------------------------------------------------------------- damage
@case("damage")
def repair_never_blesses_damaged_pixels(w: Work):
    import tifffile

    s = w.session_copy()
    frame = sorted((s / "frames").rglob("*.tif"))[5]
    with tifffile.TiffFile(frame) as tf:
        data, desc = tf.pages[0].asarray(), tf.pages[0].description
    data = data.copy()
    data[3, 3] = (data[3, 3] + 1000) % 4096
    tifffile.imwrite(frame, data, description=desc, metadata=None)
    run("session", "repair", s, "--apply")
    out = run("session", "verify", s, "--json")
    report = json.loads(out.stdout)
    if out.returncode == 0 and report.get("n_ok") == report.get("n_planned", -1):
        raise Outcome("wrong-data", "the damaged frame passes verify after repair")


@case("damage")
def product_verify_names_a_flipped_chunk(w: Work):
    p = w.product_copy()
    flip_bytes(first_chunk(p))
    out = run("product", "verify", p)
    if out.returncode != 1 or "c/" not in (out.stdout + out.stderr):
        raise Outcome("wrong-data", f"verify exit {out.returncode}")


@case("damage")
def export_refuses_a_flipped_chunk(w: Work):
    p = w.product_copy()
    flip_bytes(first_chunk(p))
    one_line_error(run("export", p, "--format", "rgb-exr", "-o", w.fresh("x").with_suffix(".exr")), 1)


@case("damage")
def spectrum_refuses_a_flipped_chunk(w: Work):
    p = w.product_copy()
    for c in sorted((p / "panorama.zarr" / "0" / "c").rglob("*")):
        if c.is_file():
            flip_bytes(c)
    one_line_error(run("spectrum", p, "--lon", "0", "--lat", "0"), 1)


@case("damage")
def rerun_repairs_a_flipped_chunk(w: Work):
    p = w.product_copy()
    chunk = first_chunk(p)
    good = chunk.read_bytes()
    flip_bytes(chunk)
    out = run("process", w.session, "-o", p, "--width", "256")
    if out.returncode != 0 or chunk.read_bytes() != good:
        raise Outcome("wrong-data", f"exit {out.returncode}; chunk repaired: {chunk.read_bytes() == good}")


@case("damage")
def rerun_repairs_a_deleted_chunk(w: Work):
    p = w.product_copy()
    chunk = first_chunk(p)
    good = chunk.read_bytes()
    chunk.unlink()
    out = run("process", w.session, "-o", p, "--width", "256")
    if out.returncode != 0 or not chunk.exists() or chunk.read_bytes() != good:
        raise Outcome("wrong-data", "the deleted chunk is not rebuilt")


@case("damage")
def rerun_remerges_a_damaged_merged_file(w: Work):
    p = w.product_copy()
    f = sorted((p / "merged").glob("d*_A.npy"))[3]
    good = f.read_bytes()
    flip_bytes(f, len(good) - 64)
    out = run("process", w.session, "-o", p, "--width", "256")
    if out.returncode != 0 or f.read_bytes() != good:
        raise Outcome("wrong-data", "the damaged merged file is kept")


@case("damage")
def garbage_product_index(w: Work):
    p = w.product_copy()
    (p / "product.json").write_text("{not json")
    one_line_error(run("export", p, "--format", "png", "-o", w.fresh("x").with_suffix(".png")), 1, "product.json")


@case("damage")
def damaged_ground_truth_does_not_stop_process(w: Work):
    s = w.session_copy()
    for f in (s / "ground_truth").glob("*"):
        if f.is_file() and f.suffix != ".json":
            f.write_bytes(b"garbage")
    out = run("process", s, "-o", w.fresh("p"), "--width", "256")
    if out.returncode != 0:
        raise Outcome("held-weakly", f"exit {out.returncode}: {out.stderr.strip()[:200]}")


@case("damage")
def garbage_journal_lines_are_repaired(w: Work):
    s = w.session_copy()
    with open(s / "journal.jsonl", "a") as fh:
        fh.write("garbage line\n{\"half\": \n")
    run("session", "repair", s, "--apply")
    out = run("session", "verify", s, "--json")
    if out.returncode != 0:
        raise Outcome("held-weakly", f"verify after repair: exit {out.returncode}")


@case("damage")
def truncated_frame_is_damaged(w: Work):
    s = w.session_copy()
    f = sorted((s / "frames").rglob("*.tif"))[7]
    f.write_bytes(f.read_bytes()[:500])
    out = run("process", s, "-o", w.fresh("p"), "--width", "256")
    one_line_error(out, 1)


# ------------------------------------------------------------------------------------------- hostile files
@case("hostile files")
def png_bomb_in_hdr_merge(w: Work):
    d = w.fresh("bomb")
    d.mkdir()
    files = [png_with_header(d / f"b{k}.png", 30000, 30000) for k in range(2)]
    one_line_error(run("hdr", "merge", *files, "--times", "0.01", "0.02", "-o", d / "out.exr"), 1)


@case("hostile files")
def jpeg_bomb_in_hdr_merge(w: Work):
    d = w.fresh("jbomb")
    d.mkdir()
    files = [jpeg_with_header(d / f"b{k}.jpg", 15000, 15000) for k in range(2)]
    one_line_error(run("hdr", "merge", *files, "--times", "0.01", "0.02", "-o", d / "out.exr"), 1)


@case("hostile files")
def tiff_claiming_65535_squared(w: Work):
    d = w.fresh("tiff")
    d.mkdir()
    ifd = struct.pack("<H", 4) + b"".join(struct.pack("<HHII", tag, 4, 1, v) for tag, v in
                                          ((256, 65535), (257, 65535), (258, 16), (277, 3))) + b"\0\0\0\0"
    files = []
    for k in range(2):
        (d / f"t{k}.tif").write_bytes(b"II*\0" + struct.pack("<I", 8) + ifd + b"\0" * 1024)
        files.append(d / f"t{k}.tif")
    one_line_error(run("hdr", "merge", *files, "--times", "0.01", "0.02", "-o", d / "out.exr"), 1)


@case("hostile files")
def png_with_a_lying_chunk_length(w: Work):
    d = w.fresh("png")
    d.mkdir()
    f = small_png(d / "a.png")
    data = bytearray(f.read_bytes())
    data[33:37] = struct.pack(">I", 0x7FFFFFF0)
    f.write_bytes(bytes(data))
    g = small_png(d / "b.png", 200)
    one_line_error(run("hdr", "merge", f, g, "--times", "0.01", "0.02", "-o", d / "out.exr"), 1)


@case("hostile files")
def truncated_png(w: Work):
    d = w.fresh("png")
    d.mkdir()
    f = small_png(d / "a.png")
    f.write_bytes(f.read_bytes()[:60])
    g = small_png(d / "b.png", 200)
    one_line_error(run("hdr", "merge", f, g, "--times", "0.01", "0.02", "-o", d / "out.exr"), 1)


@case("hostile files")
def exr_of_garbage(w: Work):
    d = w.fresh("exr")
    d.mkdir()
    (d / "env.exr").write_bytes(b"v/1\x01" + os.urandom(2000))
    one_line_error(run("simulate", "--rig", w.rig, "--scene", d / "env.exr", "-o", d / "s"), 1)


@case("hostile files")
def filter_csv_of_subnormals(w: Work):
    d = w.fresh("csv")
    d.mkdir()
    rows = "\n".join(f"{wl},1e-320" for wl in range(400, 701, 10))
    (d / "f.csv").write_text("wavelength_nm,transmittance\n" + rows + "\n")
    text = w.rig.read_text().replace('filter = "wratten-34a"', f'filter = "{d / "f.csv"}"', 1)
    (d / "rig.toml").write_text(text)
    one_line_error(run("simulate", "--rig", d / "rig.toml", "-o", d / "s"), 1)


@case("hostile files")
def csv_with_a_5_mb_field(w: Work):
    d = w.fresh("csv")
    d.mkdir()
    (d / "prior.csv").write_text("wavelength_nm,a\n400," + "9" * 5_000_000 + "\n")
    one_line_error(run("spectral", "evaluate", "--prior-set", d / "prior.csv", "--plot", "none"), 1)


@case("hostile files")
def rig_with_distortion_1e308(w: Work):
    d = w.fresh("rig")
    d.mkdir()
    (d / "rig.toml").write_text(w.rig.read_text().replace("distortion = [-0.28", "distortion = [1e308", 1))
    one_line_error(run("plan", "--rig", d / "rig.toml"), 1)


@case("hostile files")
def rig_at_the_sensor_limit(w: Work):
    d = w.fresh("rig")
    d.mkdir()
    (d / "rig.toml").write_text(w.rig.read_text().replace("width_px = 96", "width_px = 32768")
                                .replace("height_px = 52", "height_px = 32768"))
    out = run("simulate", "--rig", d / "rig.toml", "-o", d / "s", timeout=120)
    one_line_error(out, 1)


@case("hostile files")
def rig_of_binary_garbage(w: Work):
    d = w.fresh("rig")
    d.mkdir()
    (d / "rig.toml").write_bytes(os.urandom(3000))
    one_line_error(run("plan", "--rig", d / "rig.toml"), 1)


@case("hostile files")
def rig_with_a_trillion_directions(w: Work):
    d = w.fresh("rig")
    d.mkdir()
    (d / "rig.toml").write_text(w.rig.read_text().replace("n_pan = 6", "n_pan = 1000000000000"))
    one_line_error(run("plan", "--rig", d / "rig.toml"), 1)


@case("hostile files")
def pto_of_garbage_for_import(w: Work):
    d = w.fresh("import")
    d.mkdir()
    (d / "a.pto").write_bytes(b"i w9999999999 h-1 n\"../../etc/passwd\"\n" + os.urandom(500))
    one_line_error(run("import", "--rig", w.rig, "--camera", "A", "--directions", d / "a.pto", "-o", d / "s"), 1)


@case("hostile files")
def times_list_of_garbage(w: Work):
    d = w.fresh("bracket")
    d.mkdir()
    frames = [small_png(d / f"f{k}.png", 40 * (k + 1)) for k in range(2)]
    (d / "list.txt").write_text("f0.png nan\nf1.png -3\n")
    one_line_error(run("hdr", "merge", *frames, "--times-list", d / "list.txt", "-o", d / "o.exr"), 1)


# ------------------------------------------------------------------------------------------ value domains
def _usage(*argv, code: int = 2):
    one_line_error(run(*argv), code)


@case("domains")
def tile_of_eleven_digits(w: Work):
    _usage("process", w.session, "-o", w.fresh("p"), "--tile", "99999999999")


@case("domains")
def negative_seed(w: Work):
    _usage("simulate", "--rig", w.rig, "--seed", "-1", "-o", w.fresh("s"))


@case("domains")
def february_30th(w: Work):
    _usage("simulate", "--rig", w.rig, "--date", "2017-02-30", "-o", w.fresh("s"))


@case("domains")
def width_of_two_million(w: Work):
    _usage("process", w.session, "-o", w.fresh("p"), "--width", "2000000")


@case("domains")
def port_99999(w: Work):
    _usage("view", w.product, "--port", "99999")


@case("domains")
def latitude_999(w: Work):
    _usage("spectrum", w.product, "--lon", "0", "--lat", "999")


@case("domains")
def negative_exposure_time(w: Work):
    d = w.fresh("bracket")
    d.mkdir()
    frames = [small_png(d / f"f{k}.png", 40 * (k + 1)) for k in range(2)]
    _usage("hdr", "merge", *frames, "--times", "-0.01", "0.02", "-o", d / "o.exr")


@case("domains")
def zero_workers(w: Work):
    _usage("mosaic", w.product / "merged", "-o", w.fresh("pano").with_suffix(".zarr"), "--workers", "0")


@case("domains")
def export_level_99(w: Work):
    _usage("export", w.product, "--format", "png", "--level", "99", "-o", w.fresh("x").with_suffix(".png"))


@case("domains")
def zero_board_views(w: Work):
    _usage("simulate-chessboard", "--rig", w.rig, "--views", "0", "-o", w.fresh("b"))


@case("domains")
def timelapse_ending_before_it_starts(w: Work):
    _usage("timelapse", "--rig", w.rig, "--from", "10:00", "--to", "09:00", "-o", w.fresh("series"))


# -------------------------------------------------------------------------------------- kills, concurrency
def _kill_after(argv, seconds: float, sig=signal.SIGKILL) -> None:
    p = subprocess.Popen([str(BIN), "-q", *map(str, argv)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                         preexec_fn=_limit_memory)
    time.sleep(seconds)
    p.send_signal(sig)
    p.wait(timeout=120)


@case("kills")
def simulate_killed_then_resumed_is_complete(w: Work):
    s = w.fresh("s")
    _kill_after(["simulate", "--rig", w.rig, "--gt-width", "64", "--no-calibration-views", "-o", s], 4.0)
    out = run("simulate", "--rig", w.rig, "--gt-width", "64", "--no-calibration-views", "-o", s)
    ver = run("session", "verify", s, "--pixels", "--json")
    if out.returncode or ver.returncode:
        raise Outcome("wrong-data", f"resume exit {out.returncode}, verify exit {ver.returncode}")
    a = {p.relative_to(s): p.read_bytes() for p in (s / "frames").rglob("*.tif")}
    b = {p.relative_to(w.session): p.read_bytes() for p in (w.session / "frames").rglob("*.tif")}
    if set(a) != set(b) or any(_pixels(s / k) != _pixels(w.session / k) for k in list(a)[:20]):
        raise Outcome("wrong-data", "the resumed session differs from an uninterrupted one")


def _pixels(path: Path) -> bytes:
    import tifffile

    return tifffile.imread(path).tobytes()


@case("kills")
def process_killed_then_resumed_gives_the_same_panorama(w: Work):
    p = w.fresh("p")
    _kill_after(["process", w.session, "-o", p, "--width", "256"], 6.0)
    out = run("process", w.session, "-o", p, "--width", "256")
    if out.returncode:
        raise Outcome("wrong-data", f"resume exit {out.returncode}: {out.stderr[:200]}")
    _same_panorama(p, w.product)


def _same_panorama(a: Path, b: Path) -> None:
    import numpy as np
    import zarr

    x = zarr.open_array(str(a / "panorama.zarr" / "0"), mode="r")[:]
    y = zarr.open_array(str(b / "panorama.zarr" / "0"), mode="r")[:]
    if x.shape != y.shape or not np.array_equal(np.nan_to_num(x, nan=-1), np.nan_to_num(y, nan=-1)):
        raise Outcome("wrong-data", "the resumed panorama differs from an uninterrupted one")


@case("kills")
def process_interrupted_exits_130_then_resumes(w: Work):
    p = w.fresh("p")
    proc = subprocess.Popen([str(BIN), "-q", "process", str(w.session), "-o", str(p), "--width", "256"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, preexec_fn=_limit_memory)
    time.sleep(5.0)
    proc.send_signal(signal.SIGINT)
    err = proc.communicate(timeout=120)[1]
    if "Traceback" in err:
        raise Outcome("traceback", err.strip().splitlines()[-1])
    out = run("process", w.session, "-o", p, "--width", "256")
    if out.returncode:
        raise Outcome("wrong-data", f"resume exit {out.returncode}")
    _same_panorama(p, w.product)


@case("concurrency")
def two_processes_on_one_product(w: Work):
    p = w.fresh("p")
    first = subprocess.Popen([str(BIN), "-q", "process", str(w.session), "-o", str(p), "--width", "256"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    second = run("process", w.session, "-o", p, "--width", "256")
    first.wait(timeout=300)
    one_line_error(second, 1, "in use")
    _same_panorama(p, w.product)


@case("concurrency")
def mosaic_while_process_holds_the_product(w: Work):
    p = w.fresh("p")
    first = subprocess.Popen([str(BIN), "-q", "process", str(w.session), "-o", str(p), "--width", "256"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)
    second = run("mosaic", p / "merged", "-o", p / "panorama.zarr", "--overwrite")
    first.wait(timeout=300)
    one_line_error(second, 1, "in use")


@case("concurrency")
def two_simulations_into_one_session(w: Work):
    s = w.fresh("s")
    argv = [str(BIN), "-q", "simulate", "--rig", str(w.rig), "--gt-width", "64", "--no-calibration-views", "-o",
            str(s)]
    a = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(1.0)
    b = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    a.wait(timeout=300)
    if "Traceback" in b.stderr + a.stderr.read():
        raise Outcome("traceback", "one of the two simulations")
    ver = run("session", "verify", s, "--json")
    if ver.returncode and a.returncode == 0:
        raise Outcome("wrong-data", "the session is not complete after both ended")


# ----------------------------------------------------------------------------------------------- the viewer
def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _viewer(w: Work, host: str = "127.0.0.1"):
    port = _free_port()
    proc = subprocess.Popen([str(BIN), "-q", "view", str(w.product), "--port", str(port), "--host", host],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    base = f"http://{'[' + host + ']' if ':' in host else host}:{port}"
    for _ in range(100):
        try:
            urllib.request.urlopen(base + "/", timeout=1).read()
            return proc, base
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise Outcome("held-weakly", "the viewer did not start")


def _status(url: str, headers: dict | None = None) -> int:
    try:
        return urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=10).status
    except urllib.error.HTTPError as exc:
        return exc.code


def _with_viewer(w: Work, check, host: str = "127.0.0.1") -> None:
    proc, base = _viewer(w, host)
    try:
        check(base)
    finally:
        proc.terminate()
        err = proc.communicate(timeout=30)[1]
        if "Traceback" in err:
            raise Outcome("traceback", err.strip().splitlines()[-1][:200])


@case("viewer")
def viewer_path_traversal(w: Work):
    def check(base):
        for path in ("/static/../../../../etc/passwd", "/static/%2e%2e/%2e%2e/etc/passwd", "/tiles/../product.json"):
            if _status(base + path) == 200:
                raise Outcome("wrong-data", f"{path} served")
    _with_viewer(w, check)


@case("viewer")
def viewer_foreign_host_header(w: Work):
    def check(base):
        if _status(base + "/", {"Host": "evil.example"}) == 200:
            raise Outcome("wrong-data", "a foreign Host header is served (DNS rebinding)")
    _with_viewer(w, check)


@case("viewer")
def viewer_on_ipv6_loopback(w: Work):
    def check(base):
        if _status(base + "/") != 200:
            raise Outcome("wrong-data", "the viewer on ::1 refuses its own browser")
    _with_viewer(w, check, "::1")


@case("viewer")
def viewer_tile_out_of_range(w: Work):
    def check(base):
        for path in ("/tile/99/0/0.png", "/tile/0/99999/99999.png", "/spectrum?lon=abc&lat=0",
                     "/spectrum?lon=0&lat=1e400"):
            code = _status(base + path)
            if code >= 500:
                raise Outcome("traceback", f"{path}: HTTP {code}")
    _with_viewer(w, check)


@case("viewer")
def viewer_of_a_folder_that_is_not_a_product(w: Work):
    d = w.user_dir()
    one_line_error(run("view", d, "--port", str(_free_port())), 1)


# --------------------------------------------------------------------------------------------------- disk
def _file_size_limit(n_bytes: int):
    def limit():
        _limit_memory()
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes fail with EFBIG, as on a full disk
        resource.setrlimit(resource.RLIMIT_FSIZE, (n_bytes, n_bytes))
    return limit


@case("disk")
def process_on_a_full_disk_names_the_file(w: Work):
    p = w.fresh("p")
    out = run("process", w.session, "-o", p, "--width", "256", preexec=_file_size_limit(20_000))
    one_line_error(out, 1)
    if ".omnitmp" in out.stderr:
        raise Outcome("held-weakly", "the message names a temporary file")


@case("disk")
def export_on_a_full_disk_leaves_no_half_file(w: Work):
    x = w.fresh("x").with_suffix(".exr")
    out = run("export", w.product, "--format", "spectral-exr", "-o", x, preexec=_file_size_limit(10_000))
    one_line_error(out, 1, str(x.name))
    if x.exists() or list(x.parent.glob(f".{x.name}*")):
        raise Outcome("wrong-data", "a half-written export is left")


@case("disk")
def export_into_a_read_only_folder(w: Work):
    d = w.fresh("ro")
    d.mkdir()
    d.chmod(0o555)
    try:
        if os.access(d, os.W_OK):  # root ignores the mode: nothing to probe here
            return
        one_line_error(run("export", w.product, "--format", "png", "-o", d / "x.png"), 1)
    finally:
        d.chmod(0o755)


@case("disk")
def simulate_into_a_file(w: Work):
    f = w.fresh("file")
    f.write_text("a file of the user's")
    one_line_error(run("simulate", "--rig", w.rig, "-o", f), 1)
    if f.read_text() != "a file of the user's":
        raise Outcome("destroyed", "the user's file")


# -------------------------------------------------------------------------------------------------- runner
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=None, help="write every case's outcome here (JSON)")
    ap.add_argument("--only", default=None, help="run the cases whose name contains this")
    ap.add_argument("--keep", action="store_true", help="keep the work folder")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="omnispectral-probe-"))
    work = Work(root)
    work.prepare()
    results = []
    for family, name, fn in CASES:
        if args.only and args.only not in name:
            continue
        t0 = time.perf_counter()
        try:
            fn(work)
            kind, detail = "held", ""
        except Outcome as exc:
            kind, detail = exc.kind, exc.detail
        except Exception as exc:  # the probe's own failure is reported, not hidden
            kind, detail = "probe-error", f"{type(exc).__name__}: {exc}"
        results.append({"family": family, "case": name, "outcome": kind, "detail": detail,
                        "seconds": round(time.perf_counter() - t0, 1)})
        print(f"{kind:12s} {family:14s} {name}" + (f" — {detail}" if detail else ""), flush=True)
    counts = Counter(r["outcome"] for r in results)
    print(f"\n{len(results)} cases: " + ", ".join(f"{n} {k}" for k, n in counts.most_common()))
    if args.out:
        Path(args.out).write_text(json.dumps({"cases": results, "counts": counts}, indent=1))
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if set(counts) <= {"held"} else 1


if __name__ == "__main__":
    sys.exit(main())
