"""Compiled occlusion z-buffer (Numba).

:func:`~omnispectral.imaging.blockpoc.occlusion_zbuffer` forward-warps every pixel of camera A's image
along its parallax and marks those a nearer pixel lands on.  At full resolution (2.2 Mpx per direction) its
NumPy version makes about fifteen float64 whole-image passes and a scattered ``np.maximum.at``; the kernel
here does the same float64 operations in two passes (scatter the nearest, then compare), so the result is
the NumPy version's (``tests/imaging/test_zbuffer_kernel.py``).  Numba is imported on first use;
``compiled_zbuffer()`` returns ``None`` without it and the caller runs the NumPy version.  The kernel
releases the GIL and starts no threads.
"""

from __future__ import annotations

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["compiled_zbuffer"]


@built_on_first_use
def compiled_zbuffer(numba):
    """``zbuffer(dx_px, dy_px, nearness, tol_px, out)`` (module docstring), or ``None`` without Numba."""

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def zbuffer(dx_px, dy_px, nearness, tol_px, out):  # pragma: no cover - compiled
        """Reference pixels whose rounded target ``p + d(p)`` a pixel nearer by more than ``tol_px`` also
        lands on (``out``, bool ``(H, W)``); only pixels more than ``tol_px`` nearer than the farthest finite
        one are scattered."""
        h, w = dx_px.shape
        farthest, any_finite = np.inf, False
        for y in range(h):
            for x in range(w):
                v = nearness[y, x]
                if np.isfinite(v):
                    any_finite = True
                    if v < farthest:
                        farthest = v
        threshold = (farthest if any_finite else 0.0) + tol_px
        top = np.full(h * w, -np.inf)
        target = np.empty((h, w), np.int64)
        for y in range(h):
            for x in range(w):
                tx, ty = np.rint(np.float64(x) + dx_px[y, x]), np.rint(np.float64(y) + dy_px[y, x])
                key = -1
                if tx >= 0 and tx < w and ty >= 0 and ty < h:  # False for NaN
                    key = np.int64(ty) * w + np.int64(tx)
                target[y, x] = key
                v = nearness[y, x]
                if key >= 0 and np.isfinite(v) and v > threshold and v > top[key]:
                    top[key] = v
        for y in range(h):
            for x in range(w):
                key = target[y, x]
                out[y, x] = key >= 0 and nearness[y, x] < top[key] - tol_px

    return zbuffer
