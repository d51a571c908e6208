"""Limits that turn absurd inputs into one clear error before any work or allocation.

Numbers here are far outside anything the paper's rigs need (Table 2: 2048 × 1088 sensors, 7260-px
panoramas, exposures 15 µs – 3.9 s) but small enough that a hostile or mistyped value cannot make
a command allocate tens of GiB or run for days:

* exposure times in [``MIN_EXPOSURE_S``, ``MAX_EXPOSURE_S``] and finite;
* a raw frame or bracket image at most ``MAX_IMAGE_SIDE_PX`` per side and ``MAX_IMAGE_PIXELS`` pixels,
  checked from the file's header *before* decoding (:func:`check_image_header`);
* a lens's distortion coefficients at most ``MAX_DISTORTION_COEFFICIENT`` in magnitude;
* a plan of at most ``MAX_DIRECTIONS`` directions;
* a panorama at most ``MAX_PANORAMA_WIDTH_PX`` wide, and never larger than the free disk space of its
  output (:func:`check_panorama_size`);
* work whose memory is known from headers (``hdr merge``) within a budget: ``MEMORY_FRACTION`` of the memory
  available (psutil, else ``/proc/meminfo``), or what the user states (:func:`memory_budget`,
  :func:`check_memory`).
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import struct
import threading
from dataclasses import dataclass
from pathlib import Path

import tifffile
from PIL import Image, UnidentifiedImageError

from omnispectral.errors import ConfigurationError, InputFileError

try:  # optional (any platform); without it the available memory comes from Linux's /proc/meminfo
    import psutil
except ImportError:  # pragma: no cover - psutil is installed with the test extras
    psutil = None

__all__ = [
    "MAX_DIRECTIONS",
    "MAX_DISTORTION_COEFFICIENT",
    "MAX_EXPOSURE_S",
    "MAX_IMAGE_PIXELS",
    "MAX_IMAGE_SIDE_PX",
    "MAX_PANORAMA_WIDTH_PX",
    "MEMORY_FRACTION",
    "MIN_EXPOSURE_S",
    "MIN_FOV_DEG",
    "PANORAMA_BYTES_PER_PX",
    "MemoryBudget",
    "available_memory_bytes",
    "check_bit_depth",
    "check_directions",
    "check_exposure_times",
    "check_image_header",
    "check_image_shape",
    "check_memory",
    "check_panorama_size",
    "check_png_chunks",
    "gib",
    "guard_product_output",
    "image_header",
    "memory_budget",
    "sensor_memory_bytes",
]

MIN_EXPOSURE_S = 1e-7
MAX_EXPOSURE_S = 3600.0
MAX_IMAGE_SIDE_PX = 32768
MAX_IMAGE_PIXELS = 1 << 28  # 268 Mpx: a 16-bit RGB frame of this size is 1.5 GiB
MAX_DIRECTIONS = 100_000
#: |OpenCV distortion coefficient| of a rig file's lens: real lenses (rational models included) stay far below.
MAX_DISTORTION_COEFFICIENT = 1e6
MIN_FOV_DEG = 0.1  # a 0.1° lens needs 1.3 million directions for the sphere
MAX_PANORAMA_WIDTH_PX = 131_072
PANORAMA_BYTES_PER_PX = 6 * 4 * 4 / 3  # six float32 bands, pyramid levels add a third
#: Share of the available memory one command may plan to use (the rest: the system, other programs, estimates' slack).
MEMORY_FRACTION = 0.5

# tifffile reports a damaged tag on its logger; without a handler Python's last resort prints it to stderr ahead
# of the one line our readers give for the same file.  A handler here keeps those lines off the terminal (an
# application's own logging configuration still receives them).
logging.getLogger("tifffile").addHandler(logging.NullHandler())


def gib(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.1f} GiB"


def check_exposure_times(times_s, where: str = "exposure times") -> list[float]:
    """Finite exposure times within the limits (seconds); the error names ``where`` and the bad value."""
    out = []
    for t in times_s:
        try:
            v = float(t)
        except (TypeError, ValueError):
            raise ConfigurationError(f"{where}: {t!r} is not a number of seconds") from None
        if not math.isfinite(v) or not MIN_EXPOSURE_S <= v <= MAX_EXPOSURE_S:
            raise ConfigurationError(f"{where}: {t!r} s is outside {MIN_EXPOSURE_S:g}-{MAX_EXPOSURE_S:g} s")
        out.append(v)
    return out


def check_bit_depth(bit_depth: int, where: str = "bit depth") -> int:
    if isinstance(bit_depth, bool) or not isinstance(bit_depth, int) or not 1 <= bit_depth <= 16:
        raise ConfigurationError(f"{where}: {bit_depth!r} is not a sensor bit depth (1-16)")
    return bit_depth


def check_image_shape(path: str | Path, shape: tuple[int, ...], expected_hw: tuple[int, int] | None = None,
                      bytes_per_sample: int = 2) -> None:
    """Refuse an image whose header claims an absurd size (or not the rig's sensor size) before decoding."""
    try:
        dims = [int(x) for x in shape]
    except (TypeError, ValueError):
        raise InputFileError(path, f"damaged image header (shape {shape!r})") from None
    if len(dims) < 2 or min(dims) < 1:
        raise InputFileError(path, f"not an image (shape {tuple(dims)})")
    h, w = dims[0], dims[1]
    n = math.prod(dims)
    if expected_hw is not None and (h, w) != tuple(expected_hw):
        raise InputFileError(path, f"{w}x{h} px, the rig's sensor is {expected_hw[1]}x{expected_hw[0]}")
    if h > MAX_IMAGE_SIDE_PX or w > MAX_IMAGE_SIDE_PX or h * w > MAX_IMAGE_PIXELS:
        raise InputFileError(path, f"claims {w}x{h} px ({gib(n * bytes_per_sample)} decoded), above the limit of "
                                   f"{MAX_IMAGE_SIDE_PX} px per side and {MAX_IMAGE_PIXELS / 1e6:.0f} Mpx")


def check_image_header(path: str | Path, expected_hw: tuple[int, int] | None = None) -> tuple[int, ...] | None:
    """Read only an image file's header and check its size (against ``expected_hw``, the rig's sensor, when known;
    else against the limits) before anything decodes it; return the shape it claims (``None`` if unknown).

    TIFF through tifffile's first page; PNG, JPEG, BMP, PNM and the other formats Pillow identifies through
    Pillow's lazy ``Image.open`` (which reads the header only); Radiance HDR from its resolution line.  A file no
    header reader identifies is left to its decoder, which then refuses it as unreadable.
    """
    path = Path(path)
    header = image_header(path)
    if header is None:
        return None
    shape, itemsize = header
    check_image_shape(path, shape, expected_hw, itemsize)
    return tuple(int(x) for x in shape)


def image_header(path: str | Path) -> tuple[tuple[int, ...], int] | None:
    """``(shape, bytes per sample)`` an image file's header claims, read without decoding; ``None`` for a format
    no header reader here knows."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in (".tif", ".tiff"):
        try:
            with tifffile.TiffFile(path) as tf:
                page = tf.pages[0]
                return page.shape, int(page.dtype.itemsize) if page.dtype is not None else 2
        except Exception as exc:  # tifffile raises several types for damaged headers
            raise InputFileError(path, f"damaged TIFF ({type(exc).__name__}: {exc})") from None
    if suffix in (".hdr", ".pic"):
        shape = _radiance_shape(path)
        return None if shape is None else (shape, 4)
    check_png_chunks(path)
    return _pillow_header(path)


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png_chunks(path: str | Path) -> None:
    """Refuse a PNG file one of whose chunks claims more bytes than the file holds, reading only the chunks'
    8-byte length and type fields (nothing is decoded).

    libpng (under OpenCV) allocates a chunk's stated length before reading it: one damaged length field made a
    700-byte file allocate 256 MiB.  A file that is not a PNG is left alone.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != PNG_SIGNATURE:
                return
            size = os.fstat(fh.fileno()).st_size
            at = 8
            while at + 8 <= size:
                fh.seek(at)
                length, kind = struct.unpack(">I4s", fh.read(8))
                if at + 12 + length > size:
                    name = kind.decode("latin-1") if kind.isalpha() else kind.hex()
                    raise InputFileError(path, f"damaged PNG: chunk {name!r} at byte {at} claims {length} bytes, "
                                               f"the file has {size}")
                if kind == b"IEND":
                    return
                at += 12 + length
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None


_PILLOW_LIMIT_LOCK = threading.Lock()
# Pillow's own decompression-bomb limit (a warning above it, an error above twice it) is at least ours: an image
# this module let through is never refused by Pillow with a traceback half-way through decoding it.
if Image.MAX_IMAGE_PIXELS is not None and Image.MAX_IMAGE_PIXELS < MAX_IMAGE_PIXELS:
    Image.MAX_IMAGE_PIXELS = MAX_IMAGE_PIXELS


def _pillow_header(path: Path) -> tuple[tuple[int, int, int], int] | None:
    """``((h, w, channels), bytes per sample)`` from Pillow's header parse, ``None`` when Pillow does not know the
    format.  Pillow's own decompression-bomb check is switched off here: :func:`check_image_shape` is the check."""
    try:
        with _PILLOW_LIMIT_LOCK:  # the limit is global: threads checking headers at once restore it in turn
            saved = Image.MAX_IMAGE_PIXELS
            Image.MAX_IMAGE_PIXELS = None
            try:
                with Image.open(path) as im:  # lazy: reads the header, decodes nothing
                    w, h = im.size
                    bands = len(im.getbands())
                    itemsize = 2 if im.mode.startswith("I;16") or im.mode in ("I", "F") else 1
            finally:
                Image.MAX_IMAGE_PIXELS = saved
    except UnidentifiedImageError:
        return None
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    except OSError as exc:  # a damaged header of a known format
        if exc.errno is not None:
            raise
        raise InputFileError(path, f"damaged image header ({exc})") from None
    except (SyntaxError, ValueError, struct.error, EOFError) as exc:
        raise InputFileError(path, f"damaged image header ({type(exc).__name__}: {exc})") from None
    return (h, w, bands), itemsize


def _radiance_shape(path: Path) -> tuple[int, int, int] | None:
    """``(h, w, 3)`` from a Radiance HDR file's resolution line (``-Y H +X W``), ``None`` if it has none."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
    except FileNotFoundError:
        raise InputFileError(path, "file not found") from None
    if not head.startswith(b"#?"):
        return None
    m = re.search(rb"\n\n([-+][YX]) (\d{1,12}) ([-+][YX]) (\d{1,12})\n", head)
    if m is None:
        return None
    a, b = int(m.group(2)), int(m.group(4))
    return (a, b, 3) if m.group(1).endswith(b"Y") else (b, a, 3)


def check_panorama_size(width: int, output: str | Path) -> None:
    """Refuse a panorama width beyond the limit or needing more disk than is free at ``output``."""
    if isinstance(width, bool) or not isinstance(width, int) or width < 8:
        raise ConfigurationError(f"panorama width must be an even number >= 8, got {width!r}")
    need = (width // 2) * width * PANORAMA_BYTES_PER_PX
    if width > MAX_PANORAMA_WIDTH_PX:
        raise ConfigurationError(f"a {width}x{width // 2} px panorama needs about {gib(need)} of disk "
                                 f"(limit {MAX_PANORAMA_WIDTH_PX} px wide)")
    probe = Path(output)
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need > free:
        raise ConfigurationError(f"a {width}x{width // 2} px panorama needs about {gib(need)} of disk "
                                 f"(uncompressed); {gib(free)} free at {probe}")


def check_directions(n_pan: int, n_tilt: int, where: str = "plan") -> None:
    n = int(n_pan) * int(n_tilt)
    if n > MAX_DIRECTIONS:
        raise ConfigurationError(f"{where}: {n_pan} x {n_tilt} = {n} directions is above the limit of "
                                 f"{MAX_DIRECTIONS} (check the field of view and the grid)")


def guard_product_output(product: str | Path, width: int | None = None) -> None:
    """``process``: the product directory is not a session, and the width is sane (that it lies outside the
    session: :func:`omnispectral.ownership.check_output_outside_inputs`)."""
    p = Path(product).resolve()
    if (p / "session.json").exists():
        raise ConfigurationError(f"{product}: is a capture session, not a product directory")
    if width is not None:
        check_panorama_size(int(width) if not isinstance(width, bool) else width, product)


@dataclass(frozen=True)
class MemoryBudget:
    """How many bytes a command may plan to hold in memory, and where that number comes from (for messages)."""

    bytes: float
    source: str


def available_memory_bytes() -> int | None:
    """Memory available to a new allocation without swapping (bytes): psutil's ``available`` when psutil is
    installed, else ``MemAvailable`` of ``/proc/meminfo``; ``None`` when neither says."""
    if psutil is not None:
        return int(psutil.virtual_memory().available)
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def memory_budget(memory_gb: float | None = None, fraction: float = MEMORY_FRACTION) -> MemoryBudget | None:
    """The memory budget: ``memory_gb`` GiB when the user states it (``--memory-gb``), else ``fraction`` of the
    available memory (:func:`available_memory_bytes`); ``None`` when the available memory is unknown.

    Raises
    ------
    ConfigurationError
        For a stated budget that is not a positive, finite number of GiB.
    """
    if memory_gb is not None:
        try:
            value = float(memory_gb)
        except (TypeError, ValueError):
            raise ConfigurationError(f"--memory-gb {memory_gb!r} is not a number of GiB") from None
        if not math.isfinite(value) or value <= 0:
            raise ConfigurationError(f"--memory-gb {memory_gb!r} must be a positive number of GiB")
        return MemoryBudget(value * 2**30, f"--memory-gb {value:g}")
    available = available_memory_bytes()
    if available is None:
        return None
    return MemoryBudget(fraction * available, f"{fraction:.0%} of the {gib(available)} available; --memory-gb "
                                              "states another budget")


def sensor_memory_bytes(sensor_px: int, bytes_per_px: float, base_bytes: float = 0.0) -> float:
    """Working memory of a job that holds a few frames of a ``sensor_px``-pixel camera at a time: its measured
    peak per sensor pixel (``bytes_per_px``) times the pixels, plus its fixed part."""
    return float(base_bytes) + float(bytes_per_px) * int(sensor_px)


def check_memory(path: str | Path, need_bytes: float, budget: MemoryBudget | None, what: str) -> None:
    """Refuse work on ``path`` that needs more memory than ``budget`` (no check without a budget).

    Raises
    ------
    InputFileError
        ``PATH: WHAT needs about N GiB of memory, more than the budget of M GiB (its source)``.
    """
    if budget is not None and need_bytes > budget.bytes:
        raise InputFileError(path, f"{what} needs about {gib(need_bytes)} of memory, more than the budget of "
                                   f"{gib(budget.bytes)} ({budget.source})")
