"""Image files made elsewhere, decoded as a session frame: TIFF/PNG/JPEG unchanged, camera raw as its Bayer mosaic.

Shared by ``omnispectral import`` (:mod:`omnispectral.capture.importer`), which copies such files into a session
or references them in place, and by :class:`~omnispectral.capture.session.Session`, which decodes referenced
files when ``process`` reads them.  Both therefore see the same pixels.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.imaging.bracket import read_frame
from omnispectral.limits import check_image_shape

__all__ = ["IMAGE_SUFFIXES", "RAW_SUFFIXES", "check_raw_sizes", "decode_source_image", "read_camera_raw"]

#: camera raw files, read through rawpy (LibRaw; the optional ``raw`` extra): DNG and the common makers' formats
RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".raf", ".rw2", ".pef")
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", *RAW_SUFFIXES)


def read_camera_raw(path: Path, expected_hw: tuple[int, int] | None = None) -> tuple[np.ndarray, dict]:
    """A camera raw file's Bayer mosaic as recorded (uint16 ``(H, W)``, visible area) and what the camera says
    about it: CFA layout (``RGGB`` …), black level, white level (LibRaw through rawpy).

    The sizes LibRaw read from the file's metadata are checked before it decodes anything
    (:func:`check_raw_sizes`): the raw area it would allocate against the limits, the visible area against the
    camera's sensor ``expected_hw`` (px) when given."""
    try:
        import rawpy  # optional dependency (extra "raw"): LibRaw's native library
    except ImportError:
        raise InputFileError(path, "camera raw files need rawpy (pip install 'omnispectral[raw]')") from None
    try:
        with rawpy.imread(str(path)) as raw:  # opens and parses the metadata; decoding waits for the first pixel read
            check_raw_sizes(path, raw.sizes, expected_hw)
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16)
            pattern, desc = np.asarray(raw.raw_pattern), raw.color_desc.decode("ascii", "replace")
            black = float(np.mean(raw.black_level_per_channel))
            white = int(raw.white_level)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        if isinstance(exc, InputFileError):
            raise
        raise InputFileError(path, f"not a readable camera raw file ({type(exc).__name__}: {exc})") from None
    cfa = "".join(desc[int(i)] for i in pattern.ravel()) if pattern.shape == (2, 2) else ""
    if sorted(cfa) != sorted("RGGB"):
        raise InputFileError(path, f"colour filter array {desc} {pattern.tolist()} is not a 2 x 2 Bayer pattern")
    return mosaic, {"cfa_pattern": cfa, "black_level": black, "white_level": white}


def check_raw_sizes(path: Path, sizes, expected_hw: tuple[int, int] | None = None) -> None:
    """Refuse a camera raw file from the sizes in its metadata (rawpy's ``ImageSizes``), before decoding: the raw
    area LibRaw allocates (``raw_height × raw_width`` 16-bit samples) within the limits
    (:func:`omnispectral.limits.check_image_shape`), the visible area (``height × width``) the sensor's when
    ``expected_hw`` is given."""
    check_image_shape(path, (int(sizes.raw_height), int(sizes.raw_width)), None, 2)
    check_image_shape(path, (int(sizes.height), int(sizes.width)), expected_hw, 2)


def decode_source_image(path: Path, expected_hw: tuple[int, int] | None = None) -> tuple[np.ndarray, dict]:
    """A file as a session frame: ``(H, W, 3)`` RGB (an alpha channel dropped) or an ``(H, W)`` Bayer mosaic of a
    camera raw file, in its own integer type, and the raw file's CFA metadata (empty for other images).

    ``expected_hw``: the camera's sensor (px); an image file whose header (a camera raw file: its metadata) says
    another size is refused before it is decoded (any image's header is checked against the limits,
    :func:`omnispectral.limits.check_image_header`; a camera raw file's sizes by :func:`check_raw_sizes`).
    """
    path = Path(path)
    if path.suffix.lower() in RAW_SUFFIXES:
        return read_camera_raw(path, expected_hw)
    frame = read_frame(path, expected_hw)
    if frame.ndim == 3 and frame.shape[2] == 4:
        frame = frame[..., :3]
    return frame, {}
