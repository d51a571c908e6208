"""Registration of camera B to A through the geometry, on simulated captures with a known mounting error."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omnispectral.imaging.geometry import Mounting
from omnispectral.product.align import align_direction
from omnispectral.rig import load_preset
from omnispectral.sim.simulate import RigRenderer


@pytest.fixture(scope="module")
def setup(shared_data):
    from omnispectral.sim.scenes import PanoramaScene

    scene = PanoramaScene(shared_data / "hdr_envmaps" / "polyhaven_1k_hdr" / "venice_sunset_1k.hdr")
    return RigRenderer(load_preset("small"), scene, noise=False)


@pytest.mark.parametrize(("extra_yaw", "extra_pitch"), [(0.0, 0.0), (0.12, -0.07)])
def test_b_offset_recovers_an_uncalibrated_mounting_error(setup, extra_yaw, extra_pitch):
    r = setup
    nominal_b = r.models["B"]
    m = nominal_b.mounting
    true_b = replace(nominal_b, mounting=Mounting(m.roll_deg, (m.misalignment_deg[0] + extra_yaw,
                                                               m.misalignment_deg[1] + extra_pitch,
                                                               m.misalignment_deg[2]), m.baseline_mm))
    pan, tilt = -15.0, 0.0
    img_a = r.electrons_per_second("A", pan, tilt)
    r.models["B"] = true_b
    r._last.pop("B", None)
    try:
        img_b = r.electrons_per_second("B", pan, tilt)
    finally:
        r.models["B"] = nominal_b
        r._last.pop("B", None)
    res = align_direction(3, img_a, img_b, r.models["A"], nominal_b, pan, tilt)
    centre = r.models["A"].pixel_to_world(np.array([[r.models["A"].cx, r.models["A"].cy]]), pan, tilt)[0]
    expected = true_b.world_to_pixel(centre, pan, tilt)[0][0] - nominal_b.world_to_pixel(centre, pan, tilt)[0][0]
    assert not res.used_fallback and res.confidence > 0.3
    # the offset of a small rotation varies slightly across a distorted field; it is compared at the centre
    np.testing.assert_allclose(res.offset_px, expected, atol=0.1)


def test_textureless_direction_falls_back_to_the_calibrated_offset(setup):
    r = setup
    flat = np.full((136, 256, 3), 100.0, np.float32)
    noise = np.random.default_rng(0).normal(0, 1, flat.shape).astype(np.float32)
    res = align_direction(0, flat + noise, flat - noise, r.models["A"], r.models["B"], 0.0, 60.0,
                          calibrated_offset_px=(0.3, -0.2))
    assert res.used_fallback and res.offset_px == (0.3, -0.2)


def test_b_onto_a_map_does_not_depend_on_the_head_direction(setup):
    from omnispectral.product.pairgeometry import b_onto_a_maps

    a, b = setup.models["A"], setup.models["B"]
    m0 = b_onto_a_maps(a, b, 0.0, 0.0, step=4)
    m1 = b_onto_a_maps(a, b, 75.0, -40.0, step=4)
    ok = m0[0] > -1e5
    np.testing.assert_allclose(m1[0][ok], m0[0][ok], atol=1e-3)
    np.testing.assert_allclose(m1[1][ok], m0[1][ok], atol=1e-3)


def test_an_implausibly_large_offset_is_rejected(setup):
    r = setup
    pan, tilt = -15.0, 0.0
    img_a = r.electrons_per_second("A", pan, tilt)
    img_b = np.roll(r.electrons_per_second("B", pan, tilt), 9, axis=1)  # a 9 px "offset": a false peak
    res = align_direction(1, img_a, img_b, r.models["A"], r.models["B"], pan, tilt, max_offset_px=4.0)
    assert res.used_fallback and res.offset_px == (0.0, 0.0) and abs(res.measured_px[0]) > 5
