"""The paper's Eq. (2): the triangle (hat) weight of a pixel code, for the HDR merge and the response recovery.

References
----------
.. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
   J. Imaging 4(4):53, 2018, Eq. (2).
.. [2] P. E. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997
   (the hat weight of the response recovery).
"""

from __future__ import annotations

import numpy as np

__all__ = ["triangle_weight"]


def triangle_weight(dn: np.ndarray, bit_depth: int) -> np.ndarray:
    """The paper's Eq. (2) generalised to ``bit_depth``: ``w(I) = min(I, M - I)``, ``M = 2^bits - 1``.

    Rises from 0 at code 0 to mid-range and falls to 0 at full scale; codes beyond full scale get 0.  This is
    the weight of :func:`~omnispectral.imaging.hdr.merge_exposures` ``(weight="triangle")``: its NumPy path
    calls this function, and its compiled kernel (``omnispectral.imaging.hdr._fused_kernel``) evaluates the same
    float32 operations inline (a compiled loop cannot call NumPy; the tests hold the two paths bit-identical);
    it is also the data term's weight of the response recovery
    (:func:`~omnispectral.imaging.response.solve_debevec`, Debevec & Malik's hat).

    Parameters
    ----------
    dn
        Codes (any real or integer dtype; float32 is used as it is, without a copy).
    bit_depth
        Bits per code.

    Returns
    -------
    numpy.ndarray
        float32 weights, the shape of ``dn``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Eq. (2) (``w(I) = I`` up to 127, ``255 - I`` above, for 8 bits).
    .. [2] P. E. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997
       (the hat weight of the response recovery).
    """
    top = float((1 << bit_depth) - 1)
    dn = np.asarray(dn).astype(np.float32, copy=False)
    w = np.minimum(dn, top - dn)
    return np.maximum(w, 0.0, out=w)
