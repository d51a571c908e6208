"""A short mutation fuzz of the readers that check headers: valid small PNG, JPEG, TIFF, EXR, spectral CSV and rig
TOML files with random bytes changed (fixed seeds, ~50 cases per reader) end either in a result or in one
:class:`~omnispectral.errors.InputFileError` / :class:`~omnispectral.errors.ConfigurationError` line, never in
another exception type, and never allocate much (the peak RSS of the whole run rises by less than 200 MB).

Unlike ``test_fuzz_inputs.py`` (hypothesis, structured edits), the inputs here are real encoder outputs with
bytes flipped, inserted or cut anywhere — the header fields (sizes, offsets, counts) included.
"""

from __future__ import annotations

import io
import resource
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import tifffile
from PIL import Image

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bracket import exif_exposure_s, read_frame
from omnispectral.imaging.imageio import read_exr, read_image
from omnispectral.limits import check_image_header
from omnispectral.rig import load_preset, load_rig
from omnispectral.spectral.curves import read_spectral_csv

#: Mutated cases per reader and the bound on the run's peak-RSS rise (KiB).
N_CASES = 50
MAX_RSS_RISE_KIB = 200_000

#: a reader's library warning (Pillow's "Tag data larger than file") would print ahead of the one error line
pytestmark = pytest.mark.filterwarnings("error::UserWarning")


def _png() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(1).integers(0, 65535, (12, 17, 3), dtype=np.uint16).astype(np.uint8)).save(
        buf, "PNG")
    return buf.getvalue()


def _jpeg() -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.random.default_rng(2).integers(0, 255, (16, 24, 3), dtype=np.uint8)).save(buf, "JPEG")
    return buf.getvalue()


def _tiff() -> bytes:
    buf = io.BytesIO()
    tifffile.imwrite(buf, np.random.default_rng(3).integers(0, 4095, (10, 14), dtype=np.uint16),
                     description='{"exposure_s": 0.01}')
    return buf.getvalue()


def _exr(tmp: Path) -> bytes:
    p = tmp / "seed.exr"
    pixels = np.random.default_rng(4).random((6, 9)).astype(np.float32)
    OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage},
                 {"R": pixels, "G": pixels * 2, "B": pixels * 3}).write(str(p))
    return p.read_bytes()


def _csv() -> bytes:
    rows = "\n".join(f"{w},{0.1 + 0.8 * (w - 400) / 300:.4f}" for w in range(400, 701, 10))
    return f"# units: fraction\nwavelength_nm,filter\n{rows}\n".encode()


def _toml() -> bytes:
    return load_preset("small").toml_text.encode()


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """Flip 1-8 bytes (half of the cases within the first 64 bytes, where the headers are), and sometimes insert
    bytes or cut the file."""
    out = bytearray(data)
    head = int(rng.integers(0, 2)) == 0
    for _ in range(int(rng.integers(1, 9))):
        at = int(rng.integers(0, min(64, len(out)) if head else len(out)))
        out[at] = int(rng.integers(0, 256))
    what = int(rng.integers(0, 6))
    if what == 0:
        out = out[:int(rng.integers(1, len(out)))]
    elif what == 1:
        at = int(rng.integers(0, len(out)))
        out[at:at] = rng.integers(0, 256, int(rng.integers(1, 16)), dtype=np.uint8).tobytes()
    return bytes(out)


def _image_readers(path: Path) -> None:
    check_image_header(path)
    read_image(path)
    read_frame(path)
    exif_exposure_s(path)


READERS: dict[str, tuple[Callable, str, Callable[[Path], object]]] = {
    "png": (lambda tmp: _png(), ".png", _image_readers),
    "jpeg": (lambda tmp: _jpeg(), ".jpg", _image_readers),
    "tiff": (lambda tmp: _tiff(), ".tif", _image_readers),
    "exr": (_exr, ".exr", lambda p: (read_exr(p), read_image(p))),
    "csv": (lambda tmp: _csv(), ".csv", lambda p: read_spectral_csv(p, "transmittance")),
    "toml": (lambda tmp: _toml(), ".toml", load_rig),
}


def peak_rss_kib() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


@pytest.mark.parametrize("kind", list(READERS))
def test_seed_inputs_are_valid(kind, tmp_path):
    make, suffix, read = READERS[kind]
    p = tmp_path / f"seed{suffix}"
    p.write_bytes(make(tmp_path))
    read(p)  # the unmutated file reads without an error


@pytest.mark.parametrize("kind", list(READERS))
def test_mutated_inputs_end_in_a_result_or_one_clear_error(kind, tmp_path):
    make, suffix, read = READERS[kind]
    seed = make(tmp_path)
    rng = np.random.default_rng(sum(map(ord, kind)))  # fixed seed per reader
    before, t0 = peak_rss_kib(), time.perf_counter()
    outcomes = {"result": 0, "error": 0}
    for case in range(N_CASES):
        p = tmp_path / f"case{case:02d}{suffix}"
        p.write_bytes(mutate(seed, rng))
        try:
            read(p)
        except (InputFileError, ConfigurationError) as exc:
            assert "\n" not in str(exc), (case, str(exc))
            outcomes["error"] += 1
        except Exception as exc:  # anything else is a bug: name the case to reproduce it
            raise AssertionError(f"{kind} case {case}: {type(exc).__name__}: {exc}") from exc
        else:
            outcomes["result"] += 1
    assert peak_rss_kib() - before < MAX_RSS_RISE_KIB, outcomes
    assert time.perf_counter() - t0 < 20, outcomes
