"""Analysis at a reduced resolution: integer box binning of images and the way back to full-resolution pixels.

Large sensors are analysed binned (the rig calibration's block measurements, camera B's per-pixel
parallax, the direction's far offset).  A ``f × f`` box average is area integration: a binned pixel is
the mean of the ``f²`` pixels it covers, and with pixel centres at integer coordinates the binned
pixel ``x_b`` is centred at the full-resolution coordinate

.. math::  x = (x_b + \\tfrac{1}{2})\\, f - \\tfrac{1}{2}.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["CALIBRATION_ANALYSIS_PX", "analysis_factor", "bin_image", "binned_to_full_px"]

#: Long side (px) at which the rig calibration's block measurements (and the direction's far offset) are
#: analysed; larger images are binned.  (Camera B's parallax:
#: :data:`omnispectral.imaging.parallax.PARALLAX_ANALYSIS_PX`.)
CALIBRATION_ANALYSIS_PX = 1024


def analysis_factor(width: int, height: int, target_px: int) -> int:
    """Integer binning that brings an image's long side to about ``target_px`` (1 for small images).

    Parameters
    ----------
    width, height
        Image size (px).
    target_px
        Wanted long side (px) of the binned image.

    Returns
    -------
    int
        ``max(1, round(max(width, height) / target_px))``.
    """
    return max(1, round(max(width, height) / target_px))


def bin_image(image: np.ndarray, factor: int) -> np.ndarray:
    """``factor × factor`` box average (area integration: a binned pixel is the mean of the pixels it covers).

    Parameters
    ----------
    image
        ``(H, W)`` or ``(H, W, C)`` image.
    factor
        Integer binning factor (1: no binning).

    Returns
    -------
    numpy.ndarray
        float32, ``(H // factor, W // factor[, C])`` (for a size that is not a multiple of ``factor``,
        OpenCV's area resampling spreads the remainder over the image); for ``factor == 1`` the image
        itself as float32.
    """
    if factor == 1:
        return np.asarray(image, np.float32)
    h, w = image.shape[:2]
    return cv2.resize(np.asarray(image, np.float32), (w // factor, h // factor), interpolation=cv2.INTER_AREA)


def binned_to_full_px(x, factor: int):
    """Pixel coordinates of a binned image → full-resolution coordinates (pixel centres at integers).

    Parameters
    ----------
    x
        Coordinates (px of the binned image), any shape.
    factor
        The binning factor.

    Returns
    -------
    numpy.ndarray
        float64, ``(x + 0.5) · factor − 0.5`` (px of the full-resolution image).
    """
    return (np.asarray(x, np.float64) + 0.5) * factor - 0.5
