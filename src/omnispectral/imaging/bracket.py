"""Exposure brackets on disk: reading frames and exposure times, writing float images.

Frames are read unchanged (8- or 16-bit integers, RGB channel order) with OpenCV, or tifffile for
TIFF; a truncated or unreadable file is an :class:`~omnispectral.errors.InputFileError` naming it.
Exposure times come, in this order of precedence, from the caller (``--times``), from a list file
(Debevec's ``hdr_image_list.txt`` format: ``name seconds`` per line, ``1/1024`` allowed), or from
the EXIF ``ExposureTime`` tag.  Float results are written atomically as OpenEXR (float32, any
channel count), Radiance ``.hdr`` (3 channels), float TIFF or ``.npy``; ``read_exr`` (from
:mod:`omnispectral.imaging.imageio`) reads EXR back.
"""

from __future__ import annotations

import itertools
import re
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import tifffile
from PIL import Image, UnidentifiedImageError

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.hdr import merge_exposures
from omnispectral.imaging.imageio import decode_with_opencv, read_exr  # noqa: F401  (read_exr: re-exported)
from omnispectral.imaging.response import CameraResponse, recover_response
from omnispectral.io import atomic_path
from omnispectral.limits import (
    MemoryBudget,
    check_bit_depth,
    check_exposure_times,
    check_image_header,
    check_memory,
    image_header,
)

__all__ = ["EXIF_EXPOSURE_TIME", "EXIF_IFD_POINTER", "EXPOSURE_RATIO_TOLERANCE", "FLOAT_IMAGE_SUFFIXES", "Bracket",
           "ExposureMismatch", "auto_weight", "bracket_headers", "check_bracket_memory", "exif_exposure_s",
           "exposure_time_mismatches", "exposure_times_for", "guess_bit_depth", "load_bracket",
           "measured_exposure_ratio", "merge_bracket", "merge_memory_bytes", "parse_exposure_s", "read_frame",
           "read_times_list", "write_float_image"]

#: EXIF tag numbers (EXIF 2.32, CIPA DC-008): the Exif sub-IFD pointer and ExposureTime in it.
EXIF_IFD_POINTER = 0x8769
EXIF_EXPOSURE_TIME = 0x829A

FLOAT_IMAGE_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff", ".npy")


@dataclass(frozen=True)
class Bracket:
    """Frames of one exposure bracket with their exposure times and where each time came from."""

    paths: tuple[Path, ...]
    frames: tuple[np.ndarray, ...]
    exposure_s: np.ndarray
    time_sources: tuple[str, ...]

    @property
    def dtype(self) -> np.dtype:
        return self.frames[0].dtype


def parse_exposure_s(text: str) -> float:
    """Seconds from ``"0.004"``, ``"1/250"``, ``"1/250s"`` or ``"32"``; positive, finite."""
    t = str(text).strip().lower().removesuffix("s").strip()
    try:
        value = float(Fraction(t))
    except (ValueError, ZeroDivisionError):
        raise ConfigurationError(f"exposure time {text!r} is not a number of seconds (e.g. 0.004 or 1/250)") from None
    if not np.isfinite(value) or value <= 0:
        raise ConfigurationError(f"exposure time {text!r} is not positive")
    return check_exposure_times([value], f"exposure time {text!r}")[0]


def read_frame(path: str | Path, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """One raw or LDR frame, unchanged: ``(H, W)`` or ``(H, W, C)`` uint8/uint16 in RGB(A) order.

    The header's size is checked before decoding (:func:`omnispectral.limits.check_image_header`): against
    ``expected_hw`` (the sensor, in px) when given, else against the limits."""
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "file not found")
    suffix = path.suffix.lower()
    check_image_header(path, expected_hw)  # a hostile header claiming gigapixels is refused before any allocation
    if suffix in (".tif", ".tiff"):
        try:
            img = tifffile.imread(path)
        except Exception as exc:  # tifffile raises many types for damaged files
            raise InputFileError(path, f"cannot read TIFF ({exc})") from None
    else:
        if suffix in (".jpg", ".jpeg"):
            _check_jpeg_complete(path)
        img = decode_with_opencv(path)
        if img is None:
            raise InputFileError(path, "not a readable image (truncated or unknown format)")
    if not np.issubdtype(img.dtype, np.integer) or img.dtype.itemsize > 2:
        raise InputFileError(path, f"pixel type {img.dtype} is not an 8- or 16-bit integer frame")
    return np.ascontiguousarray(img)


def _check_jpeg_complete(path: Path) -> None:
    """OpenCV decodes a truncated JPEG with a warning; Pillow's strict loader refuses it."""

    try:
        with Image.open(path) as im:
            im.load()
    except OSError as exc:
        raise InputFileError(path, f"damaged JPEG ({exc})") from None


def exif_exposure_s(path: str | Path) -> float | None:
    """EXIF ``ExposureTime`` in seconds, or ``None`` when the file has none (a header claiming a size beyond the
    limits is refused first: Pillow would raise its decompression-bomb error)."""

    if Path(path).suffix.lower() in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        check_image_header(path)
    try:
        # a damaged tag makes Pillow warn ("Tag data larger than file") and skip it: no time is no time, and the
        # warning would print ahead of the command's own line
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            with Image.open(path) as im:
                exif = im.getexif()
                value = exif.get_ifd(EXIF_IFD_POINTER).get(EXIF_EXPOSURE_TIME, exif.get(EXIF_EXPOSURE_TIME))
    except (OSError, UnidentifiedImageError):
        return None
    if value is None:
        return None
    try:
        seconds = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return seconds if np.isfinite(seconds) and seconds > 0 else None


def read_times_list(path: str | Path) -> dict[str, float]:
    """Exposure times by file stem from a list file (``name seconds`` per line, ``#`` comments).

    This is the format of Debevec's ``hdr_image_list.txt``; a first line holding only the image
    count is accepted.  Stems are matched, so ``memorial0061.ppm`` in the list matches a PNG.
    """
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise InputFileError(path, f"cannot read ({exc.strerror})") from None
    times: dict[str, float] = {}
    for n, line in enumerate(lines, 1):
        text = line.split("#", 1)[0].strip()
        if not text or re.fullmatch(r"\d+", text):
            continue
        parts = text.split()
        if len(parts) < 2:
            raise InputFileError(path, f"expected 'filename seconds', got {line.strip()!r}", line=n)
        try:
            times[Path(parts[0]).stem] = parse_exposure_s(parts[1])
        except ConfigurationError as exc:
            raise InputFileError(path, str(exc), line=n) from None
    if not times:
        raise InputFileError(path, "no 'filename seconds' lines")
    return times


def exposure_times_for(paths: Sequence[Path], times: Sequence[str | float] | None = None,
                       times_list: Mapping[str, float] | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """Exposure time of each path (explicit > list file > EXIF) and where each came from."""
    if times is not None:
        if len(times) != len(paths):
            raise ConfigurationError(f"{len(paths)} files but {len(times)} exposure times")
        return np.array([parse_exposure_s(str(t)) for t in times]), ("given",) * len(paths)
    values, sources, missing = [], [], []
    for p in paths:
        t = None if times_list is None else times_list.get(p.stem)
        src = "list"
        if t is None:
            t, src = exif_exposure_s(p), "exif"
        if t is None:
            missing.append(p.name)
        values.append(t)
        sources.append(src)
    if missing:
        raise ConfigurationError(f"no exposure time for {', '.join(missing)}: no EXIF ExposureTime"
                                 + ("" if times_list is None else " and not in the list file")
                                 + "; pass --times or --times-list")
    for p, t, src in zip(paths, values, sources, strict=True):
        check_exposure_times([t], f"{p}: exposure time ({src})")
    return np.array(values, dtype=np.float64), tuple(sources)


def _sample_type(itemsize: int) -> str:
    return {1: "uint8", 2: "uint16", 4: "float32"}.get(int(itemsize), f"{itemsize}-byte samples")


def merge_memory_bytes(shape: tuple[int, ...], bytes_per_sample: int, n_frames: int, recover_response: bool = False,
                       deghost: bool = False, with_variance: bool = False) -> int:
    """The memory (bytes) ``hdr merge`` holds at its peak for a bracket of ``n_frames`` frames of ``shape``.

    The decoded frames (``n_frames × pixels × channels × bytes_per_sample``, held through the merge) and one more
    frame while the next is decoded; their stacked copy when the response is recovered (8-bit frames,
    :func:`~omnispectral.imaging.response.recover_response`); the merge's output (float32 radiance and variance,
    saturated and dark flags: 10 bytes per pixel and channel; the ghost mask and its scores with ``deghost``); the
    image written (float32, with ``with_variance`` the variances and a validity channel too) and its per-channel
    copies for the writer.

    Parameters
    ----------
    shape : tuple of int
        ``(H, W)`` or ``(H, W, C)`` of one frame, from its header.
    bytes_per_sample : int
        Bytes of one decoded sample (1 for 8-bit frames, 2 for 16-bit).
    n_frames : int
        Frames in the bracket.
    recover_response, deghost, with_variance : bool
        The merge's options that add memory.

    Returns
    -------
    int
        Bytes.
    """
    px = int(shape[0]) * int(shape[1])
    c = int(shape[2]) if len(shape) > 2 else 1
    frame = px * c * int(bytes_per_sample)
    frames = (n_frames + 1) * frame + (n_frames * frame if recover_response else 0)
    merged = px * c * (4 + 4 + 1 + 1) + (px * (1 + 4 + 1) if deghost else 0)
    written = px * ((2 * c + 1) if with_variance else c) * 4 * 2
    return frames + merged + written


def bracket_headers(paths: Sequence[Path]) -> list[tuple[tuple[int, ...], int] | None]:
    """Every frame's ``(shape, bytes per sample)`` from its header (``None`` for a format without a header reader),
    each checked against the limits, and all of one size: refused naming the first frame that differs."""
    headers = []
    for p in paths:
        check_image_header(p)
        headers.append(image_header(p))
    for p, header in zip(paths, headers, strict=True):
        if header is not None and headers[0] is not None and tuple(header[0][:2]) != tuple(headers[0][0][:2]):
            (shape, size), (shape0, size0) = header, headers[0]
            raise InputFileError(p, f"is {tuple(shape)} {_sample_type(size)} but {paths[0].name} is {tuple(shape0)} "
                                    f"{_sample_type(size0)}; a bracket must match")
    return headers


def check_bracket_memory(paths: Sequence[Path], headers: Sequence[tuple[tuple[int, ...], int] | None],
                         budget: MemoryBudget | None, response: str | CameraResponse = "auto", deghost: bool = False,
                         with_variance: bool = False) -> None:
    """Refuse a bracket whose merge (:func:`merge_memory_bytes`, from the headers) needs more than ``budget``,
    naming its first frame and the memory; frames whose headers say nothing are not checked."""
    known = [h for h in headers if h is not None]
    if budget is None or not known:
        return
    shape, itemsize = max(known, key=lambda h: int(np.prod(h[0])) * h[1])
    recover = isinstance(response, str) and response in ("auto", "debevec") and (itemsize == 1 or response == "debevec")
    need = merge_memory_bytes(shape, itemsize, len(paths), recover, deghost, with_variance)
    size = f"{shape[1]}x{shape[0]} px" + (f" x {shape[2]}" if len(shape) > 2 else "")
    check_memory(paths[0], need, budget, f"merging {len(paths)} frames of {size} ({_sample_type(itemsize)})")


def load_bracket(paths: Sequence[str | Path], times: Sequence[str | float] | None = None,
                 times_list: str | Path | None = None, memory: MemoryBudget | None = None,
                 response: str | CameraResponse = "auto", deghost: bool = False,
                 with_variance: bool = False) -> Bracket:
    """Read a bracket: every frame (same size, type and channels) and its exposure time.

    Sizes come from the headers first (:func:`bracket_headers`); with a ``memory`` budget
    (:func:`omnispectral.limits.memory_budget`) the merge's memory is checked from them too
    (:func:`check_bracket_memory`, with the merge's ``response``, ``deghost`` and ``with_variance``), all before
    any frame is decoded.
    """
    paths = tuple(Path(p) for p in paths)
    if len(paths) < 2:
        raise ConfigurationError("an exposure bracket needs at least two frames")
    for p in paths:  # the first thing wrong is said first: a missing frame, not its missing EXIF
        if not p.is_file():
            raise InputFileError(p, "file not found" if not p.exists() else "is not a file")
    table = read_times_list(times_list) if times_list is not None else None
    exposure_s, sources = exposure_times_for(paths, times, table)
    headers = bracket_headers(paths)  # every size from its header, checked before any frame is decoded
    check_bracket_memory(paths, headers, memory, response, deghost, with_variance)
    frames = []
    for p in paths:
        f = read_frame(p)
        if frames and (f.shape != frames[0].shape or f.dtype != frames[0].dtype):
            raise InputFileError(p, f"is {f.shape} {f.dtype} but {paths[0].name} is "
                                    f"{frames[0].shape} {frames[0].dtype}; a bracket must match")
        frames.append(f)
    if np.unique(exposure_s).size < 2:
        raise ConfigurationError("all frames have the same exposure time; nothing to merge")
    return Bracket(paths, tuple(frames), exposure_s, sources)


def write_float_image(path: str | Path, image: np.ndarray, channel_names: Sequence[str] | None = None,
                      attributes: Mapping[str, str] | None = None) -> Path:
    """Write a float32 ``(H, W[, C])`` image atomically; the format follows the suffix.

    ``.exr``: OpenEXR float32, ZIP, one part, channels ``R,G,B`` (3 channels), ``Y`` (1) or
    ``channel_names``; ``attributes`` become string header attributes.  ``.hdr``: Radiance RGBE
    (3 channels only).  ``.tif``: float32 TIFF (tifffile).  ``.npy``: NumPy.
    """
    path = Path(path)
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 2:
        img = img[..., None]
    suffix = path.suffix.lower()
    if suffix not in FLOAT_IMAGE_SUFFIXES:
        raise ConfigurationError(f"{path}: unknown output format; use one of {', '.join(FLOAT_IMAGE_SUFFIXES)}")
    c = img.shape[2]
    with atomic_path(path) as tmp:
        if suffix == ".exr":
            _write_exr(tmp, img, channel_names, attributes)
        elif suffix == ".hdr":
            if c != 3:
                raise ConfigurationError(f"{path}: Radiance .hdr holds 3 channels, the image has {c}")
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(img[..., ::-1])):
                raise InputFileError(path, "OpenCV could not write the Radiance file")
        elif suffix in (".tif", ".tiff"):
            tifffile.imwrite(tmp, img, photometric="rgb" if c == 3 else "minisblack",
                             compression="zlib", metadata=None)
        else:
            np.save(tmp, img)
    return path


def _default_channel_names(c: int) -> list[str]:
    return {1: ["Y"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}.get(c, [f"C{i}" for i in range(c)])


def _write_exr(path: Path, img: np.ndarray, names: Sequence[str] | None, attributes) -> None:
    names = list(names) if names is not None else _default_channel_names(img.shape[2])
    if len(names) != img.shape[2]:
        raise ConfigurationError(f"{len(names)} channel names for {img.shape[2]} channels")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for k, v in (attributes or {}).items():
        header[k] = str(v)
    channels = {n: np.ascontiguousarray(img[..., i]) for i, n in enumerate(names)}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def guess_bit_depth(frames: Sequence[np.ndarray]) -> int:
    """8 for uint8; for uint16 the smallest of 10, 12, 14, 16 bits that holds the largest value."""
    if frames[0].dtype == np.uint8:
        return 8
    top = max(int(np.max(f)) for f in frames)
    return next(b for b in (10, 12, 14, 16) if top < (1 << b))


def auto_weight(bracket: Bracket, response: str | CameraResponse) -> str:
    """The HDR weight that ``auto`` stands for: the paper's triangle (Eq. (2)) for linear raw frames, and the
    inverse-variance weight (``noise``) for 8-bit frames that go through a recovered or given response.

    Parameters
    ----------
    bracket : Bracket
        The frames; their dtype decides (8-bit codes, or raw frames of more bits).
    response : str or CameraResponse
        ``"linear"``, another response name (e.g. ``"auto"``: recovered for 8-bit frames), or a response.

    Returns
    -------
    str
        ``"noise"`` for 8-bit frames with a response other than ``"linear"``, else ``"triangle"``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eqs. (1)-(2) (the HDR merge and its triangle weight).
    .. [2] M. Granados et al., "Optimal HDR reconstruction with linear digital cameras", CVPR 2010 (the
       inverse-variance weight).
    .. [3] P. E. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997
       (the response of 8-bit frames).
    """
    linear = isinstance(response, str) and response == "linear"
    return "noise" if bracket.dtype.itemsize == 1 and not linear else "triangle"


#: Consecutive frames (by exposure time) whose brightness ratio differs from the ratio of their stated times by
#: more than this factor have a wrong time: noise and a response error move the median ratio by a few per cent,
#: a time off by one bracket step (usually 2× or more) moves it by the step.
EXPOSURE_RATIO_TOLERANCE = 1.5
#: Values that measure a ratio, as fractions of full scale: the brighter frame's code above a quarter of full
#: scale and below clipping (well above a dark floor of noise, black level and flare, which would pull the ratio
#: towards 1: codes 13-19 of 255 in Debevec's memorial bracket), the darker's above ``RATIO_DARKER_FLOOR`` and
#: below clipping.
RATIO_BRIGHTER_RANGE, RATIO_DARKER_FLOOR, RATIO_CLIP = (0.25, 0.9), 0.02, 0.9
#: Fewest values usable in both frames of a pair for its ratio to be measured; at most ``RATIO_MAX_SAMPLES``
#: (a regular subsample) are used.
RATIO_MIN_SAMPLES, RATIO_MAX_SAMPLES = 100, 1_000_000


@dataclass(frozen=True)
class ExposureMismatch:
    """Two consecutive frames whose brightness ratio disagrees with their stated exposure times."""

    shorter: Path
    longer: Path
    stated_ratio: float
    measured_ratio: float

    def describe(self) -> str:
        return (f"{self.longer.name} is {self.measured_ratio:.3g}x as bright as {self.shorter.name} but their "
                f"exposure times say {self.stated_ratio:.3g}x")


def measured_exposure_ratio(shorter: np.ndarray, longer: np.ndarray, response: CameraResponse,
                            bit_depth: int) -> float | None:
    """Median of ``longer / shorter`` in the response's linear units over the values usable in both frames:
    the frame that is brighter in fact (whatever the times say) in :data:`RATIO_BRIGHTER_RANGE`, the other above
    :data:`RATIO_DARKER_FLOOR`, both below :data:`RATIO_CLIP`; ``None`` when fewer than :data:`RATIO_MIN_SAMPLES`
    are usable."""
    index = np.arange(0, shorter.size, max(1, shorter.size // RATIO_MAX_SAMPLES))
    a, b = shorter.reshape(-1)[index].astype(np.intp), longer.reshape(-1)[index].astype(np.intp)
    bright, dark = (b, a) if b.mean() >= a.mean() else (a, b)
    top = (1 << bit_depth) - 1
    usable = ((bright > RATIO_BRIGHTER_RANGE[0] * top) & (bright < RATIO_BRIGHTER_RANGE[1] * top)
              & (dark > RATIO_DARKER_FLOOR * top) & (dark < RATIO_CLIP * top))
    if int(usable.sum()) < RATIO_MIN_SAMPLES:
        return None
    channels = shorter.shape[2] if shorter.ndim == 3 else 1
    lin = np.asarray(response.linear, np.float64)
    col = (index % channels) % lin.shape[1]  # one curve for all channels, or one per channel
    la, lb = lin[a[usable], col[usable]], lin[b[usable], col[usable]]
    ok = (la > 0) & (lb > 0)
    return float(np.median(lb[ok] / la[ok])) if int(ok.sum()) >= RATIO_MIN_SAMPLES else None


def exposure_time_mismatches(bracket: Bracket, response: CameraResponse, bit_depth: int,
                             tolerance: float = EXPOSURE_RATIO_TOLERANCE) -> list[ExposureMismatch]:
    """Pairs of consecutive frames (by exposure time) whose measured brightness ratio
    (:func:`measured_exposure_ratio`) differs from the ratio of their exposure times by more than ``tolerance``
    either way: a wrong ``--times``, list file or EXIF time, which the merge would otherwise only show as
    ghosts everywhere."""
    if response.n_codes != 1 << bit_depth:
        return []
    order = np.argsort(bracket.exposure_s, kind="stable")
    found = []
    for i, j in itertools.pairwise(order):
        stated = float(bracket.exposure_s[j] / bracket.exposure_s[i])
        measured = measured_exposure_ratio(bracket.frames[i], bracket.frames[j], response, bit_depth)
        if measured is not None and measured > 0 and max(measured / stated, stated / measured) > tolerance:
            found.append(ExposureMismatch(bracket.paths[i], bracket.paths[j], stated, measured))
    return found


def merge_bracket(bracket: Bracket, bit_depth: int | None = None, weight: str = "triangle",
                  response: str | CameraResponse = "auto", deghost: bool = False,
                  reference: int | None = None, samples: int = 400, smoothness: float = 50.0):
    """Merge a bracket read from disk: choose the bit depth and the response, then Eqs. (1)-(2).

    ``response``: ``"auto"`` (Debevec-Malik recovery for 8-bit frames, linear otherwise),
    ``"linear"``, ``"debevec"`` or a :class:`CameraResponse`.  Returns ``(HDRResult, response, bit_depth)``.
    """

    depth = check_bit_depth(bit_depth, "--bit-depth") if bit_depth is not None else guess_bit_depth(bracket.frames)
    top = (1 << depth) - 1
    for p, f in zip(bracket.paths, bracket.frames, strict=True):
        if int(f.max()) > top:
            raise InputFileError(p, f"holds values up to {int(f.max())}, more than {depth} bits allow")
    if isinstance(response, str):
        if response not in ("auto", "linear", "debevec"):
            raise ConfigurationError(f"unknown response {response!r}; expected auto, linear, debevec or a file")
        if response == "debevec" or (response == "auto" and depth == 8):
            response = recover_response(bracket.frames, bracket.exposure_s, samples, smoothness)
        else:
            response = CameraResponse.identity(depth)
    result = merge_exposures(bracket.frames, bracket.exposure_s, depth, weight=weight, response=response,
                             deghost=deghost, reference=reference)
    return result, response, depth
