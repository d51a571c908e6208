"""The local linear score's compiled arithmetic gives the NumPy version's bits."""

from __future__ import annotations

import numpy as np
import pytest

import omnispectral.imaging.similarity as similarity
from omnispectral.imaging.similarity import LocalLinearScore
from omnispectral.imaging.similarity_kernel import compiled_score


@pytest.mark.skipif(compiled_score() is None, reason="Numba not installed")
def test_compiled_score_is_the_numpy_score_bit_for_bit(monkeypatch):
    """HDR-like A (four decades), B a varying mix of A plus noise, with a flat patch (var_b below the floor: 0),
    a patch where B is an exact mix (ratio clipped at 1) and a saturated-like constant row."""
    rng = np.random.default_rng(11)
    a = (10.0 ** rng.uniform(0, 4, (90, 130, 3))).astype(np.float32)
    mix = rng.uniform(-0.5, 1.0, (3, 3)).astype(np.float32)
    b = a @ mix.T + rng.normal(0, 20, a.shape).astype(np.float32)
    b[10:40, 10:50] = 5.0
    b[50:70, 60:100] = a[50:70, 60:100] @ mix.T
    b[80] = 1e4
    score = LocalLinearScore(a, 11)
    prepared = score.prepare_b(b)
    fast = score(prepared)
    monkeypatch.setattr(similarity, "compiled_score", lambda: None)
    slow = score(prepared)
    assert fast.dtype == slow.dtype == np.float32
    assert np.array_equal(fast.view(np.uint32), slow.view(np.uint32))
    assert (fast[21:29, 21:39] == 0).all() and fast.max() <= 1.0 and np.percentile(fast[52:68, 62:98], 5) > 0.99
