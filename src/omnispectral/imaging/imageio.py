"""Reading images from files into ``(H, W, C)`` float32 arrays.

Formats: PNG, JPEG, TIFF, BMP, PNM and Radiance HDR through OpenCV (``cv2.imread`` with
``IMREAD_UNCHANGED``, so 16-bit and float data keep their depth), TIFF through ``tifffile`` when
OpenCV cannot read it (float or many-channel TIFF), and OpenEXR through the ``OpenEXR`` package
(the OpenCV wheels are built without EXR support).

Values are not rescaled: an 8- or 16-bit file gives its digital numbers (DN) as float32, a float
file its values as they are.  Colour files come out in R, G, B(, A) order (OpenCV's BGR is
reversed).  Anything that is not a readable image raises
:class:`~omnispectral.errors.InputFileError` naming the file.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import OpenEXR
import tifffile

from omnispectral.errors import InputFileError
from omnispectral.limits import check_image_header, check_image_shape

__all__ = ["decode_with_opencv", "read_exr", "read_image"]

#: Channel order used when an EXR file stores named channels.
_EXR_ORDER = ("R", "G", "B", "A", "Y")


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as ``(H, W, C)`` float32 (DN for integer files, values as stored for float files).

    Raises
    ------
    InputFileError
        The file does not exist, is not a file, cannot be decoded as an image, or its header claims a size
        above the limits (:func:`omnispectral.limits.check_image_header`, checked before decoding).
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(path, "no such file")
    if not path.is_file():
        raise InputFileError(path, "not a regular file")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        image, _ = read_exr(path)
    else:
        check_image_header(path)  # the size from the header, before OpenCV (which is not lazy) decodes it
        image = decode_with_opencv(path)
        if image is None and suffix in (".tif", ".tiff"):
            image = _read_tiff(path)
        if image is None:
            raise InputFileError(path, "cannot be read as an image (unsupported format or corrupt file)")
    return _as_hwc_float32(image, path)


def decode_with_opencv(path: Path) -> np.ndarray | None:
    """The file's pixels as stored (any depth), channels in R, G, B(, A) order; ``None`` if OpenCV cannot."""

    # np.fromfile + imdecode copes with non-ASCII paths, which cv2.imread does not on every platform.
    data = np.fromfile(str(path), dtype=np.uint8)
    if data.size == 0:
        return None
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if image is None:
        return None
    if image.ndim == 3 and image.shape[2] in (3, 4):
        order = [2, 1, 0] + ([3] if image.shape[2] == 4 else [])
        image = image[:, :, order]
    return image


def _read_tiff(path: Path) -> np.ndarray | None:
    try:
        image = tifffile.imread(path)
    except Exception:  # tifffile raises many types for corrupt files; all mean "not readable"
        return None
    if image.ndim == 3 and image.shape[0] in (1, 3, 4) and image.shape[2] not in (1, 3, 4):
        image = np.moveaxis(image, 0, -1)  # planar (C, H, W) storage
    return image


def read_exr(path: str | Path) -> tuple[np.ndarray, list[str]]:
    """Every channel of a single-part OpenEXR file, ``(H, W, C)`` float32, and the channel names
    (R, G, B, A, Y first when present, then the rest alphabetically)."""

    path = Path(path)

    try:  # the size from the header first: a hostile data window is refused before any pixel is read
        with OpenEXR.File(str(path), header_only=True) as exr:  # the header is valid only while the file is open
            header = exr.header()
            (x0, y0), (x1, y1) = (np.asarray(v, dtype=np.int64) for v in header["dataWindow"])
            n_channels = max(1, len(header.get("channels") or ()))
    except Exception as exc:  # the OpenEXR binding raises RuntimeError/OSError/ValueError; a damaged window
        raise InputFileError(path, f"cannot be read as an OpenEXR image ({exc})") from exc
    check_image_shape(path, (int(y1 - y0 + 1), int(x1 - x0 + 1), n_channels), bytes_per_sample=4)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = {name: np.asarray(ch.pixels) for name, ch in exr.channels().items()}
    except Exception as exc:  # the OpenEXR binding raises RuntimeError/OSError/ValueError
        raise InputFileError(path, f"cannot be read as an OpenEXR image ({exc})") from exc
    if not channels:
        raise InputFileError(path, "OpenEXR file has no channels")
    names = [n for n in _EXR_ORDER if n in channels] + sorted(n for n in channels if n not in _EXR_ORDER)
    shapes = {channels[n].shape for n in names}
    if len(shapes) != 1:
        raise InputFileError(path, f"OpenEXR channels have different sizes {sorted(shapes)} (subsampled channels "
                                   "are not supported)")
    return np.stack([channels[n] for n in names], axis=-1).astype(np.float32, copy=False), names


def _as_hwc_float32(image: np.ndarray, path: Path) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[:, :, None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0:
        raise InputFileError(path, f"unexpected image array shape {image.shape}")
    if image.dtype.kind not in "uif":
        raise InputFileError(path, f"unsupported pixel type {image.dtype}")
    return np.ascontiguousarray(image, dtype=np.float32)
