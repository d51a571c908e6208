"""Compiled per-pixel arithmetic of the local linear score (Numba), around OpenCV's box filters.

:class:`~omnispectral.imaging.similarity.LocalLinearScore` is called once per inverse-depth level of the
parallax sweep (up to 48 times per direction).  Between its box filters the NumPy version makes about
thirty whole-image temporaries (the window products before the filters; the covariances, the quadratic
form, the ratio and the channel mean after them); the two kernels here do the same float32 operations in
the same order, one pass each, so the scores are the NumPy version's bits (``tests/imaging/
test_similarity.py``) at about half its time.  Numba is imported on first use; ``compiled_score()``
returns ``None`` without it and the caller runs the NumPy version.  The kernels release the GIL and start
no threads.

References
----------
.. [1] K. He, J. Sun and X. Tang, "Guided Image Filtering", IEEE TPAMI 35(6):1397-1409, 2013 (the local
   linear model and its window statistics).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["compiled_score"]


@built_on_first_use
def compiled_score(numba) -> SimpleNamespace | None:
    """The kernels ``window_products`` and ``score_from_moments`` (module docstring), or ``None`` without
    Numba."""

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def window_products(a0, a1, a2, b, bb, ab0, ab1, ab2):  # pragma: no cover - compiled
        """``b·b`` and ``a_i·b`` per channel of ``b`` ``(H, W, 3)``, with A's centred channels ``a_i`` ``(H, W)``."""
        for y in range(b.shape[0]):
            for x in range(b.shape[1]):
                p, q, r = a0[y, x], a1[y, x], a2[y, x]
                for c in range(3):
                    v = b[y, x, c]
                    bb[y, x, c] = v * v
                    ab0[y, x, c] = p * v
                    ab1[y, x, c] = q * v
                    ab2[y, x, c] = r * v

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def score_from_moments(mb, bb, ab0, ab1, ab2, m0, m1, m2, f00, f01, f02, f11, f12, f22, var_floor,
                           out):  # pragma: no cover - compiled
        """The multiple correlation per channel of B from the window means (``mb``, ``bb``, ``ab_i``: box
        filtered; ``m_i``: A's means; ``f_ij``: the quadratic form), averaged over B's three channels."""
        zero, one, three = np.float32(0.0), np.float32(1.0), np.float32(3.0)
        for y in range(mb.shape[0]):
            for x in range(mb.shape[1]):
                total = zero
                for c in range(3):
                    mbc = mb[y, x, c]
                    var_b = bb[y, x, c] - mbc * mbc
                    c0 = ab0[y, x, c] - m0[y, x] * mbc
                    c1 = ab1[y, x, c] - m1[y, x] * mbc
                    c2 = ab2[y, x, c] - m2[y, x] * mbc
                    explained = zero
                    explained += f00[y, x] * c0 * c0
                    explained += f01[y, x] * c0 * c1
                    explained += f02[y, x] * c0 * c2
                    explained += f11[y, x] * c1 * c1
                    explained += f12[y, x] * c1 * c2
                    explained += f22[y, x] * c2 * c2
                    r = zero
                    if var_b > var_floor:
                        ratio = explained / var_b
                        if ratio < zero:  # np.clip's: NaN stays NaN
                            ratio = zero
                        elif ratio > one:
                            ratio = one
                        r = np.sqrt(ratio)
                    total = r if c == 0 else total + r
                out[y, x] = total / three

    return SimpleNamespace(window_products=window_products, score_from_moments=score_from_moments)
