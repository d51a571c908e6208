"""Compiled per-level bookkeeping of the parallax sweep (Numba).

:func:`~omnispectral.imaging.parallax.sweep_inverse_depth` visits up to 48 inverse-depth levels per
direction.  At each level its NumPy version makes about twenty whole-image passes: the moved positions
(``x + w e + w² h``), and after the score the running best level, its neighbours for the parabola, the
scores at infinity and at the block's own depth, and the two highest local maxima of the score curve.  The
two kernels here do the same operations (float32 where NumPy's are float32, float64 where they are float64,
in the same order, without fused multiply-adds) in one pass each, so the sweep gives the NumPy version's
bits (``tests/imaging/test_sweep_kernel.py``).  Numba is imported on first use; ``compiled_sweep()`` returns
``None`` without it and the sweep runs its NumPy version.  The kernels release the GIL and start no
threads.

References
----------
.. [1] R. T. Collins, "A space-sweep approach to true multi-image matching", CVPR 1996 (the plane sweep).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["compiled_sweep"]


@built_on_first_use
def compiled_sweep(numba) -> SimpleNamespace | None:
    """The kernels ``moved_positions`` and ``level_update`` (module docstring), or ``None`` without Numba."""

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def moved_positions(wk, wk2, fx, fy, hx, hy, map_x, map_y):  # pragma: no cover - compiled
        """``x + wk·fx + wk2·hx`` and ``y + wk·fy + wk2·hy`` (float32) at every pixel ``(y, x)``."""
        for y in range(fx.shape[0]):
            yf = np.float32(y)
            for x in range(fx.shape[1]):
                map_x[y, x] = (np.float32(x) + wk * fx[y, x]) + wk2 * hx[y, x]
                map_y[y, x] = (yf + wk * fy[y, x]) + wk2 * hy[y, x]

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def maximum(a, b):  # pragma: no cover - compiled
        """``np.maximum``: NaN when either is NaN."""
        if a != a or b != b:
            return a + b
        return a if a >= b else b

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def level_update(k, wk, half_dw, at_zero, raw, score, lo, hi, own, best, best_raw, best_k, left, right,
                     prev, score_zero, score_own, top1, rival, prev_sel, prev2_sel):  # pragma: no cover - compiled
        """One level ``k`` (inverse depth ``wk``) of the sweep's bookkeeping, in place (the NumPy version:
        :func:`omnispectral.imaging.parallax._sweep_level_numpy`)."""
        bonus, none = 0.01, np.float32(-np.inf)
        for y in range(raw.shape[0]):
            for x in range(raw.shape[1]):
                r, s = raw[y, x], score[y, x]
                if best_k[y, x] == k - 1:
                    right[y, x] = r
                if at_zero:
                    score_zero[y, x] = s
                at_own = abs(wk - own[y, x]) <= half_dw
                if at_own:
                    score_own[y, x] = maximum(score_own[y, x], s)
                sel = none
                if wk >= lo[y, x] and wk <= hi[y, x]:
                    sel = np.float32(np.float64(s) + (bonus if at_own else 0.0))
                if k >= 1:
                    p, p2 = prev_sel[y, x], prev2_sel[y, x]
                    peak = p if (p >= p2 and p >= sel) else none
                    t1, t2 = top1[y, x], rival[y, x]
                    rival[y, x] = maximum(t2, t1) if peak > t1 else maximum(t2, peak)
                    top1[y, x] = maximum(t1, peak)
                prev2_sel[y, x] = prev_sel[y, x]
                prev_sel[y, x] = sel
                if sel > best[y, x]:
                    left[y, x] = prev[y, x]
                    right[y, x] = np.nan
                    best[y, x] = sel
                    best_raw[y, x] = r
                    best_k[y, x] = k
                prev[y, x] = r

    return SimpleNamespace(moved_positions=moved_positions, level_update=level_update)
