from __future__ import annotations

import numpy as np
import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.imaging import merge_exposures, triangle_weight
from omnispectral.spectral.noise import CMV2000

# the paper's bracket: 15 exposures from 252 ms down to 0.015 ms
PAPER_TIMES_S = np.geomspace(252e-3, 0.015e-3, 15)


def bracket(radiance_dn_s, times, rng, noise=CMV2000):
    """Raw 12-bit frames of a radiance map (DN/s) through the CMV2000 noise model."""
    return [noise.sample_dn(radiance_dn_s * t * noise.gain_e_per_dn, rng).astype(np.uint16) for t in times]


def test_triangle_weight_matches_eq2_for_8_bit():
    dn = np.arange(256)
    expected = np.where(dn <= 127, dn, 255 - dn)
    np.testing.assert_array_equal(triangle_weight(dn, 8), expected)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(0)
    truth = np.exp(rng.uniform(np.log(1e2), np.log(1e7), (96, 128, 3))).astype(np.float32)
    return truth, bracket(truth, PAPER_TIMES_S, rng)


@pytest.mark.parametrize(("weight", "median_rel"), [("triangle", 0.02), ("noise", 0.01)])
def test_merge_recovers_radiance(scene, weight, median_rel):
    truth, frames = scene
    res = merge_exposures(frames, PAPER_TIMES_S, 12, weight=weight)
    assert res.radiance.dtype == np.float32 and res.radiance.shape == truth.shape
    rel = np.abs(res.radiance - truth) / truth
    assert res.valid.all()
    assert np.median(rel) < median_rel
    # the predicted variance matches the actual error scale (z-scores ~ unit variance)
    z = (res.radiance - truth) / np.sqrt(res.variance)
    assert 0.7 < z.std() < 1.4


def test_noise_weight_beats_triangle_in_dark_regions():
    rng = np.random.default_rng(1)
    truth = np.full((64, 64, 1), 30.0, np.float32)  # 7.6 DN in the longest exposure, 0 in short ones
    frames = bracket(truth, PAPER_TIMES_S, rng)
    tri = merge_exposures(frames, PAPER_TIMES_S, 12, weight="triangle").radiance
    noi = merge_exposures(frames, PAPER_TIMES_S, 12, weight="noise").radiance
    rmse = lambda x: float(np.sqrt(np.mean((x - truth) ** 2)))  # noqa: E731
    assert rmse(noi) < rmse(tri)


def test_saturated_everywhere_and_dark_everywhere_are_flagged():
    frames = [np.full((4, 4), 4095, np.uint16), np.full((4, 4), 4095, np.uint16)]
    res = merge_exposures(frames, [1e-3, 1e-2], 12)
    assert res.saturated.all() and not res.valid.any()
    np.testing.assert_allclose(res.radiance, 4095 / 1e-3)  # shortest exposure's value
    dark = merge_exposures([np.zeros((4, 4), np.uint16)] * 2, [1e-3, 1e-2], 12)
    assert dark.dark.all()
    np.testing.assert_allclose(dark.radiance, 0.0)


@pytest.mark.parametrize(
    ("frames", "times", "msg"),
    [
        ([np.zeros((4, 4), np.uint16), np.zeros((4, 5), np.uint16)], [1, 2], "exposure 1 has shape"),
        ([np.zeros((4, 4), np.uint16)] * 2, [1], "2 frames but 1 exposure times"),
        ([np.zeros((4, 4), np.uint16)] * 2, [1, 0], "exposure 1: exposure time 0.0 s is not positive"),
        ([np.zeros((4, 4), np.float32)], [1], "expected uint8 or uint16"),
    ],
)
def test_bad_input(frames, times, msg):
    with pytest.raises(ConfigurationError, match=msg):
        merge_exposures(frames, times, 12)


def test_fused_merge_equals_eq1_in_float64(scene):
    """The chunked float32 merge is Eq. (1) with the Eq. (2) weight (saturated and zero codes excluded)."""
    _, frames = scene
    num = np.zeros(frames[0].shape)
    den = np.zeros(frames[0].shape)
    for f, t in zip(frames, PAPER_TIMES_S, strict=True):
        z = f.astype(np.float64)
        w = np.minimum(z, 4095 - z) * ((z < 0.99 * 4095) & (z > 0))
        num += w * z / t
        den += w
    ok = den > 0
    fused = merge_exposures(frames, PAPER_TIMES_S, 12, chunk_rows=7, workers=2).radiance
    np.testing.assert_allclose(fused[ok], (num / np.where(ok, den, 1))[ok], rtol=2e-6)
