"""Raw Bayer mosaics: colour filter array layouts, black level / dark frame correction and demosaicing.

A single-sensor colour camera delivers one value per photosite, filtered by the 2 × 2 colour filter
array (CFA) repeated over the sensor; the layout is named by its first two rows (``RGGB``: R G on
even rows, G B on odd rows; the SFNC pixel formats ``BayerRG12`` … of GenICam cameras).  Sessions
store these mosaics as the camera gave them (uint16, the code including the camera's black level);
processing subtracts the black level or a dark frame (:func:`correct_raw`) and demosaics with a
maintained implementation (:func:`demosaic`):

``menon2007``
    Menon, Andriani & Calvagno, "Demosaicing with directional filtering and a posteriori decision",
    IEEE TIP 16(1), 2007 (colour-demosaicing's implementation, with its refining step).
``malvar2004``
    Malvar, He & Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned colour
    images", ICASSP 2004 (colour-demosaicing).
``bilinear``
    Bilinear interpolation of each colour plane (colour-demosaicing).
``opencv-ea``
    OpenCV's edge-aware demosaicing (``COLOR_Bayer…2RGB_EA``); integer codes only, so it can demosaic
    frames before the HDR merge but not the merged (floating-point, high dynamic range) mosaic.

Whether frames are demosaiced before the HDR merge or the mosaic is merged first and demosaiced once
is the rig's choice (``[cameras.X.raw] order``); docs/benchmarks.md measures both on the simulator.
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np

with warnings.catch_warnings():  # colour-demosaicing 0.2.7 imports from scipy.ndimage.filters (deprecated)
    warnings.simplefilter("ignore", DeprecationWarning)
    from colour_demosaicing import (
        demosaicing_CFA_Bayer_bilinear,
        demosaicing_CFA_Bayer_Malvar2004,
        demosaicing_CFA_Bayer_Menon2007,
    )

from omnispectral.errors import ConfigurationError

__all__ = ["CFA_PATTERNS", "DEMOSAIC_METHODS", "ORDERS", "channel_index", "check_pattern", "correct_raw", "demosaic",
           "mosaic"]

CFA_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
DEMOSAIC_METHODS = ("menon2007", "malvar2004", "bilinear", "opencv-ea")
#: ``merge-first``: HDR merge on the mosaic, demosaic once; ``demosaic-first``: demosaic every frame, then merge.
ORDERS = ("merge-first", "demosaic-first")

# OpenCV names a Bayer layout by the second row's second and third pixels: RGGB is its "BG"
_OPENCV_EA = {"RGGB": cv2.COLOR_BayerBG2RGB_EA, "BGGR": cv2.COLOR_BayerRG2RGB_EA,
              "GRBG": cv2.COLOR_BayerGB2RGB_EA, "GBRG": cv2.COLOR_BayerGR2RGB_EA}


def check_pattern(pattern: str) -> str:
    """The CFA layout in upper case; :class:`ConfigurationError` unless it is one of :data:`CFA_PATTERNS`."""
    p = str(pattern).upper()
    if p not in CFA_PATTERNS:
        raise ConfigurationError(f"unknown CFA pattern {pattern!r}; expected one of {', '.join(CFA_PATTERNS)}")
    return p


def channel_index(shape: tuple[int, int], pattern: str) -> np.ndarray:
    """``(H, W)`` int8: the colour (0 = R, 1 = G, 2 = B) of every photosite of a ``pattern`` mosaic."""
    p = check_pattern(pattern)
    cell = np.array([["RGB".index(p[0]), "RGB".index(p[1])], ["RGB".index(p[2]), "RGB".index(p[3])]], np.int8)
    h, w = shape
    return np.tile(cell, ((h + 1) // 2, (w + 1) // 2))[:h, :w]


def mosaic(rgb: np.ndarray, pattern: str) -> np.ndarray:
    """The Bayer mosaic ``(H, W)`` a ``pattern`` sensor records of an ``(H, W, 3)`` image (same dtype)."""
    idx = channel_index(rgb.shape[:2], pattern)
    return np.take_along_axis(rgb, idx[..., None].astype(np.intp), axis=2)[..., 0]


def demosaic(cfa: np.ndarray, pattern: str, method: str = "menon2007") -> np.ndarray:
    """``(H, W, 3)`` float32 RGB of a Bayer mosaic (module docstring for the methods).

    ``cfa`` is linear (black level subtracted); floating point for the colour-demosaicing methods
    (any range: an HDR mosaic in DN/s works), integer codes for ``opencv-ea``.  Negative
    interpolation overshoot is clipped at 0.
    """
    p = check_pattern(pattern)
    cfa = np.asarray(cfa)
    if cfa.ndim == 3 and cfa.shape[2] == 1:
        cfa = cfa[..., 0]
    if cfa.ndim != 2:
        raise ConfigurationError(f"a Bayer mosaic is (H, W), got shape {cfa.shape}")
    if method == "opencv-ea":
        if cfa.dtype not in (np.uint8, np.uint16):
            raise ConfigurationError("opencv-ea demosaics integer codes only (8 or 16 bit), not a merged HDR "
                                     "mosaic; use order = \"demosaic-first\" or another method")
        return cv2.cvtColor(np.ascontiguousarray(cfa), _OPENCV_EA[p]).astype(np.float32)
    functions = {"menon2007": demosaicing_CFA_Bayer_Menon2007, "malvar2004": demosaicing_CFA_Bayer_Malvar2004,
                 "bilinear": demosaicing_CFA_Bayer_bilinear}
    if method not in functions:
        raise ConfigurationError(f"unknown demosaicing method {method!r}; expected one of "
                                 f"{', '.join(DEMOSAIC_METHODS)}")
    x = np.asarray(cfa, np.float64)
    # colour-demosaicing works in float64; the HDR mosaic's range (1e-2 … 1e7 DN/s) is kept as it is
    rgb = functions[method](x, p)
    return np.clip(rgb, 0, None).astype(np.float32)


def correct_raw(frame: np.ndarray, bit_depth: int, black_level_dn: float = 0.0,
                dark: np.ndarray | None = None) -> np.ndarray:
    """A raw frame with its black level, or its dark frame, subtracted: uint16 codes for the HDR merge.

    ``dark`` (the mean of dark frames at the same exposure, shape of ``frame``, including the black
    level) replaces ``black_level_dn`` where given.  Codes are rounded and clipped at 0 (the merge gives
    zero codes no weight); codes the sensor clipped (≥ 99 % of full scale) stay at full scale so the
    merge still sees them saturated (subtracting the dark frame would otherwise hide the clipping).
    """
    top = (1 << int(bit_depth)) - 1
    f = np.asarray(frame)
    offset = np.asarray(dark, np.float32) if dark is not None else np.float32(black_level_dn)
    if dark is not None and np.shape(dark) != f.shape:
        raise ConfigurationError(f"dark frame of shape {np.shape(dark)} for a frame of shape {f.shape}")
    out = np.clip(np.rint(f.astype(np.float32) - offset), 0, top).astype(np.uint16)
    out[f >= 0.99 * top] = top
    return out
