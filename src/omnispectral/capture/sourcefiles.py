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

__all__ = ["IMAGE_SUFFIXES", "RAW_SUFFIXES", "decode_source_image", "read_camera_raw"]

#: camera raw files, read through rawpy (LibRaw; the optional ``raw`` extra): DNG and the common makers' formats
RAW_SUFFIXES = (".dng", ".nef", ".cr2", ".cr3", ".arw", ".orf", ".raf", ".rw2", ".pef")
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", *RAW_SUFFIXES)


def read_camera_raw(path: Path) -> tuple[np.ndarray, dict]:
    """A camera raw file's Bayer mosaic as recorded (uint16 ``(H, W)``, visible area) and what the camera says
    about it: CFA layout (``RGGB`` …), black level, white level (LibRaw through rawpy)."""
    try:
        import rawpy  # optional dependency (extra "raw"): LibRaw's native library
    except ImportError:
        raise InputFileError(path, "camera raw files need rawpy (pip install 'omnispectral[raw]')") from None
    try:
        with rawpy.imread(str(path)) as raw:
            mosaic = np.array(raw.raw_image_visible, dtype=np.uint16)
            pattern, desc = np.asarray(raw.raw_pattern), raw.color_desc.decode("ascii", "replace")
            black = float(np.mean(raw.black_level_per_channel))
            white = int(raw.white_level)
    except (rawpy.LibRawError, OSError, ValueError) as exc:
        raise InputFileError(path, f"not a readable camera raw file ({type(exc).__name__}: {exc})") from None
    cfa = "".join(desc[int(i)] for i in pattern.ravel()) if pattern.shape == (2, 2) else ""
    if sorted(cfa) != sorted("RGGB"):
        raise InputFileError(path, f"colour filter array {desc} {pattern.tolist()} is not a 2 x 2 Bayer pattern")
    return mosaic, {"cfa_pattern": cfa, "black_level": black, "white_level": white}


def decode_source_image(path: Path, expected_hw: tuple[int, int] | None = None) -> tuple[np.ndarray, dict]:
    """A file as a session frame: ``(H, W, 3)`` RGB (an alpha channel dropped) or an ``(H, W)`` Bayer mosaic of a
    camera raw file, in its own integer type, and the raw file's CFA metadata (empty for other images).

    ``expected_hw``: the camera's sensor (px); an image file whose header says another size is refused before it
    is decoded (any image's header is checked against the limits, :func:`omnispectral.limits.check_image_header`).
    """
    path = Path(path)
    if path.suffix.lower() in RAW_SUFFIXES:
        return read_camera_raw(path)
    frame = read_frame(path, expected_hw)
    if frame.ndim == 3 and frame.shape[2] == 4:
        frame = frame[..., :3]
    return frame, {}
