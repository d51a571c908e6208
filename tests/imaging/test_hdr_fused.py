"""The compiled one-pass merge equals the NumPy evaluation of Eq. (1) bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.imaging import hdr, merge_exposures
from omnispectral.spectral.noise import CMV2000

TIMES_S = np.geomspace(252e-3, 0.015e-3, 15)


@pytest.fixture(scope="module")
def frames():
    """A log-uniform scene over 10^6 with a saturated-everywhere and a dark-everywhere corner."""
    rng = np.random.default_rng(3)
    truth = np.exp(rng.uniform(np.log(1e1), np.log(3e7), (70, 90, 3))).astype(np.float32)
    out = [CMV2000.sample_dn(truth * t * CMV2000.gain_e_per_dn, rng).astype(np.uint16) for t in TIMES_S]
    for f in out:
        f[:5, :5] = 4095  # saturated even in the shortest exposure
        f[-5:, -5:] = 0  # zero in every exposure
    return out


def numpy_path(monkeypatch):
    monkeypatch.setattr(hdr, "_fused_frames", lambda model, frames: None)


def assert_same(a, b):
    for name in ("radiance", "variance", "saturated", "dark", "ghost"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None
        else:
            np.testing.assert_array_equal(x, y, err_msg=name)


@pytest.mark.parametrize("weight", ["triangle", "noise"])
@pytest.mark.parametrize(("workers", "count"), [(1, 15), (2, 15), (1, 4), (2, 7)])
def test_fused_equals_numpy_path(frames, weight, workers, count, monkeypatch):
    """Brackets of 15, 4 and 7 exposures: the kernel takes five at a time, padding 4 and 7 with weightless
    exposures."""
    assert hdr._fused_kernel() is not None
    fused = merge_exposures(frames[-count:], TIMES_S[-count:], 12, weight=weight, chunk_rows=16, workers=workers)
    assert fused.saturated[:5, :5].all() and fused.dark[-5:, -5:].all()
    assert 0.0 < np.nanmean(fused.radiance) and np.isfinite(fused.radiance).all()
    numpy_path(monkeypatch)
    assert_same(fused, merge_exposures(frames[-count:], TIMES_S[-count:], 12, weight=weight, chunk_rows=16,
                                       workers=workers))


def test_fused_matches_float64_eq1(frames):
    """Eq. (1) unchanged: float64, one exposure at a time, the triangle weight of Eq. (2)."""
    res = merge_exposures(frames, TIMES_S, 12)
    sat = 0.99 * 4095
    num = np.zeros(frames[0].shape)
    den = np.zeros(frames[0].shape)
    for f, t in zip(frames, TIMES_S, strict=True):
        z = f.astype(np.float64)
        w = np.minimum(z, 4095 - z) * ((z < sat) & (z > 0))
        num += w * z / t
        den += w
    ok = (den > 0) & res.valid  # flagged pixels take the shortest or longest exposure instead
    assert np.max(np.abs(res.radiance[ok] - num[ok] / den[ok]) / (num[ok] / den[ok])) < 2e-6


def test_fused_with_deghost_2d_and_8_bit(frames, monkeypatch):
    eight = [(f >> 4).astype(np.uint8) for f in frames[5:]]
    gray = [f[..., 1] for f in frames]
    moved = [f.copy() for f in frames]
    moved[3][20:30, 20:30] = moved[3][40:50, 40:50]  # a ghost in one exposure
    runs = [lambda: merge_exposures(eight, TIMES_S[5:], 8, workers=2),
            lambda: merge_exposures(gray, TIMES_S, 12, weight="noise"),
            lambda: merge_exposures(moved, TIMES_S, 12, deghost=True, chunk_rows=8)]
    fused = [run() for run in runs]
    assert fused[2].ghost[20:30, 20:30].mean() > 0.5
    numpy_path(monkeypatch)
    for run, result in zip(runs, fused, strict=True):
        assert_same(result, run())


def test_mixed_dtypes_take_the_numpy_path(frames):
    mixed = [frames[0], frames[1].astype(np.uint32)]
    model = hdr._build_model(TIMES_S[:2], 12, "triangle", None, None, None, 3)
    assert hdr._fused_frames(model, mixed) is None
    assert hdr._fused_frames(model, frames[:2]) is not None
    res = merge_exposures(mixed, TIMES_S[:2], 12)
    assert np.isfinite(res.radiance[res.valid]).all()


def test_a_bracket_of_read_only_and_writable_frames_takes_the_compiled_path(frames, monkeypatch):
    """Frames mapped from the page cache are read-only, frames read past it writable: one bracket can hold both."""
    mixed = [f.copy() for f in frames]
    for f in mixed[::2]:
        f.flags.writeable = False
    fused = merge_exposures(mixed, TIMES_S, 12, weight="noise")
    assert all(f.flags.writeable for f in mixed[1::2]), "the caller's frames keep their flags"
    numpy_path(monkeypatch)
    assert_same(fused, merge_exposures(frames, TIMES_S, 12, weight="noise"))
