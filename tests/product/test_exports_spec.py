"""Exports as their specifications say: spectral EXR per Fichet et al. 2021 read by colour-science and
OpenEXR, half floats read by OpenImageIO, RGB EXR with chromaticities/latlong that Mitsuba 3 renders cleanly,
a saturation mask beside a spectral export, no absolute paths."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import OpenEXR
import pytest

from omnispectral.product.estimator import estimator_params
from omnispectral.product.exports import (
    FICHET_EMISSIVE_UNITS,
    REC709_CHROMATICITIES,
    export_product,
    write_rgb_exr,
    write_spectral_exr,
)
from omnispectral.product.layout import write_band_product
from omnispectral.product.saturation import saturation_level_dn_s
from omnispectral.rig import load_preset

WL = np.arange(400.0, 701.0, 5.0)


def _hostile_cube(h=16, w=20):
    """Spectra as a bad estimate gives them: NaN (uncovered), negative undershoot, huge values (the sun)."""
    rng = np.random.default_rng(3)
    cube = rng.uniform(0.5, 3.0, (h, w, WL.size)).astype(np.float32)
    cube[0, 0] = np.nan
    cube[1, :4, 10:30] = -1.6e8
    cube[2, 2] = 9.6e7
    cube[3, 3, 5] = np.inf
    return cube


def _header(path):
    with OpenEXR.File(str(path)) as f:
        return dict(f.header())  # the File's own dict is emptied when it closes


def test_spectral_exr_follows_fichet2021_and_holds_light(tmp_path):
    from colour.io import read_spectral_image_Fichet2021

    cube = _hostile_cube()
    units = "DN per second of exposure per unit of the system matrix"
    write_spectral_exr(tmp_path / "s.exr", cube, WL, units=units, attributes={"omnispectral_region": "all"})
    header = _header(tmp_path / "s.exr")
    assert header["emissiveUnits"] == FICHET_EMISSIVE_UNITS == "W.m^-2.sr^-1"
    assert "polarisationHandedness" not in header  # unpolarised: only S0 channels
    assert header["omnispectral_units"] == units
    components = read_spectral_image_Fichet2021(tmp_path / "s.exr")
    wl, values = components["S0"]
    np.testing.assert_allclose(wl, WL)
    expected = np.nan_to_num(cube, nan=0.0, posinf=0.0, neginf=0.0).clip(0)
    assert np.isfinite(values).all() and values.min() >= 0
    np.testing.assert_allclose(values, expected, rtol=1e-6)
    assert values[2, 2].max() == pytest.approx(9.6e7)  # the sun keeps its (lower-bound) value
    assert set(components) == {"S0", "RGB"} or "S1" not in components


def test_half_spectral_exr_scales_into_range_and_reads_with_openimageio(tmp_path):
    oiio = pytest.importorskip("OpenImageIO", reason="OpenImageIO is not installed (pip install 'omnispectral[test]')")

    cube = _hostile_cube()
    write_spectral_exr(tmp_path / "h.exr", cube, WL, units="x", half=True)
    inp = oiio.ImageInput.open(str(tmp_path / "h.exr"))
    spec = inp.spec()
    assert spec.format == oiio.HALF
    scale = float(spec.getattribute("omnispectral_scale"))
    assert scale > 1 and np.log2(scale) == int(np.log2(scale))  # a power of two: exact in any float
    data = inp.read_image(oiio.FLOAT)
    inp.close()
    names = list(spec.channelnames)
    s0 = np.stack([data[..., names.index(f"S0.{repr(float(w)).replace('.', ',')}nm")] for w in WL], axis=-1)
    assert np.isfinite(s0).all() and s0.min() >= 0
    expected = np.nan_to_num(cube, nan=0.0, posinf=0.0, neginf=0.0).clip(0)
    assert s0.max() <= 65504 and s0.max() * scale == pytest.approx(9.6e7, rel=1e-3)  # in range, nothing inf
    np.testing.assert_allclose(s0 * scale, expected, rtol=1e-3, atol=scale * 6e-8)
    assert (tmp_path / "h.exr").stat().st_size < 0.7 * _float_size(tmp_path, cube)


def _float_size(tmp_path, cube):
    write_spectral_exr(tmp_path / "f.exr", cube, WL, units="x")
    return (tmp_path / "f.exr").stat().st_size


MITSUBA_SCRIPT = textwrap.dedent("""
    import sys
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    messages = []
    class Collect(mi.Appender):
        def append(self, level, text):
            messages.append(text)
        def log_progress(self, *args):
            pass
    logger = mi.logger()
    logger.clear_appenders()
    logger.add_appender(Collect())
    logger.set_log_level(mi.LogLevel.Warn)
    T = mi.ScalarTransform4f()
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "emitter": {"type": "envmap", "filename": sys.argv[1]},
        "ball": {"type": "sphere", "bsdf": {"type": "diffuse"}},
        "sensor": {"type": "perspective", "fov": 60, "to_world": T.look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32},
                   "sampler": {"type": "independent", "sample_count": 16}}})
    mi.render(scene)
    print(sum("Invalid sample value" in m for m in messages))
""")


def _mitsuba_invalid_samples(exr) -> int:
    pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install 'omnispectral[render]')")
    out = subprocess.run([sys.executable, "-c", MITSUBA_SCRIPT, str(exr)], capture_output=True, text=True,
                         timeout=120, check=True)
    return int(out.stdout.strip().splitlines()[-1])


def test_rgb_exr_declares_rec709_latlong_and_mitsuba_renders_it_cleanly(tmp_path):
    oiio = pytest.importorskip("OpenImageIO", reason="OpenImageIO is not installed (pip install 'omnispectral[test]')")

    rgb = np.random.default_rng(1).uniform(0, 2, (16, 32, 3)).astype(np.float32)
    rgb[3:12, 3:20, 0] = -0.5  # out-of-gamut colours: a negative channel, as 0.41 % of the demo's pixels
    rgb[10, 10] = np.nan
    write_rgb_exr(tmp_path / "env.exr", rgb)
    inp = oiio.ImageInput.open(str(tmp_path / "env.exr"))
    spec, back = inp.spec(), inp.read_image(oiio.FLOAT)
    inp.close()
    np.testing.assert_allclose(spec.getattribute("chromaticities"), REC709_CHROMATICITIES, atol=1e-7)
    assert spec.getattribute("textureformat") == "LatLong Environment"  # OpenEXR envmap = latlong
    assert np.isfinite(back).all() and back.min() == 0.0
    np.testing.assert_array_equal(back[0, 0], rgb[0, 0])
    assert _mitsuba_invalid_samples(tmp_path / "env.exr") == 0
    # the same pixels written as before (negatives kept): Mitsuba complains, so the check above can fail
    with OpenEXR.File({"type": OpenEXR.scanlineimage}, {c: np.ascontiguousarray(rgb[..., i])
                                                        for i, c in enumerate("RGB")}) as f:
        f.write(str(tmp_path / "raw.exr"))
    assert _mitsuba_invalid_samples(tmp_path / "raw.exr") > 0


@pytest.fixture(scope="module")
def sun_product(tmp_path_factory):
    """A product whose rig snapshot says where clipping starts, with a saturated 'sun' of inconsistent bands."""
    rig = load_preset("small")
    clip = 0.99 * rig.camera_a.max_dn / min(rig.bracket.exposures_s)
    h, w = 64, 128
    grey = rig.system(WL).matrix @ np.ones(WL.size)  # a flat spectrum seen by the six bands
    bands = np.broadcast_to((200.0 * grey / grey.mean()).astype(np.float32), (h, w, 6)).copy()
    bands[20:24, 40:46, :3] = clip  # camera A clipped in every exposure, camera B not: a wild estimate
    bands[20:24, 40:46, 3:] = 0.02 * clip
    bands[60:, :10] = np.nan
    bands[40, 60, :3], bands[40, 60, 3:] = 5000.0, 1.0  # bands no spectrum explains, far below clipping
    root = tmp_path_factory.mktemp("sun") / "product"
    write_band_product(root, bands, {"bands": ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"], "units": "DN/s",
                                     "estimator": {"params": estimator_params(rig)}},
                       attrs={"bands": ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"],
                              "rig": {"name": rig.name, "toml": rig.toml_text}}, tile=32)
    return root, clip


def test_spectral_export_of_the_sun_is_finite_non_negative_with_its_mask_and_no_paths(sun_product, tmp_path):
    import cv2
    from colour.io import read_spectral_image_Fichet2021

    from omnispectral.mosaic.store import PanoramaStore

    root, clip = sun_product
    store = PanoramaStore.open(root / "panorama.zarr")
    assert saturation_level_dn_s(store.attrs()) == pytest.approx(clip)
    out = export_product(root, "spectral-exr", tmp_path / "pano.exr", region=(16, 48, 32, 96))
    values = read_spectral_image_Fichet2021(tmp_path / "pano.exr")["S0"][1]
    assert np.isfinite(values).all() and values.min() >= 0
    mask = cv2.imread(str(tmp_path / "pano_saturated.png"), cv2.IMREAD_UNCHANGED)
    expected = np.zeros((32, 64), np.uint8)
    expected[4:8, 8:14] = 255  # rows 20-24, cols 40-46 of level 0, in the region's frame
    expected[24, 28] = 128  # row 40, col 60: not saturated, but its estimate was clipped
    np.testing.assert_array_equal(mask, expected)
    assert out["saturation"]["saturated_px"] == 24 and out["saturation"]["clipped_estimate_px"] == 1
    # at level 1 a pixel is saturated when a level-0 pixel under it is: rows 10-12, cols 20-23
    export_product(root, "envi", tmp_path / "coarse.hdr", level=1)
    coarse = cv2.imread(str(tmp_path / "coarse_saturated.png"), cv2.IMREAD_UNCHANGED)
    sat = np.argwhere(coarse == 255)
    assert sat.min(axis=0).tolist() == [10, 20] and sat.max(axis=0).tolist() == [11, 22]
    for value in _header(tmp_path / "pano.exr").values():
        assert str(tmp_path.parent) not in str(value) and str(root.parent) not in str(value)
