"""Exports: spectral OpenEXR read back by colour-science, ENVI, RGB against colour-science, previews."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.errors import ConfigurationError
from omnispectral.product.exports import (
    spectral_channel_name,
    tone_map_srgb,
    write_envi,
    write_preview,
    write_radiance_hdr,
    write_spectral_exr,
)
from omnispectral.spectral.colour import spectra_to_linear_srgb

WL = np.arange(400.0, 701.0, 5.0)


def _cube(h=20, w=24, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.1, 2.0, (h, w, 1)) * (1 + 0.5 * np.sin(WL / rng.uniform(20, 60, (h, w, 1))))
    return base.astype(np.float32)


def test_channel_names_follow_fichet2021():
    assert spectral_channel_name(550) == "S0.550,0nm" and spectral_channel_name(402.5) == "S0.402,5nm"


def test_spectral_exr_reads_back_with_colour_science(tmp_path):
    from colour.io import read_spectral_image_Fichet2021

    cube = _cube()
    write_spectral_exr(tmp_path / "s.exr", cube, WL, units="W.m^-2.sr^-1", attributes={"omnispectral": "test"})
    components, spec = read_spectral_image_Fichet2021(tmp_path / "s.exr", additional_data=True)
    wl, values = components["S0"]
    np.testing.assert_allclose(wl, WL)
    np.testing.assert_allclose(values, cube, rtol=1e-6)
    assert spec.is_emissive
    names = {a.name: a.value for a in spec.attributes}
    assert names["spectralLayoutVersion"] == "1.0" and names["emissiveUnits"] == "W.m^-2.sr^-1"
    with pytest.raises(ConfigurationError, match="do not match"):
        write_spectral_exr(tmp_path / "bad.exr", cube[..., :10], WL, units="x")
    assert not (tmp_path / "bad.exr").exists()


def test_rgb_matches_colour_science():
    import colour

    cube = _cube(3, 4)
    ours = spectra_to_linear_srgb(cube, WL)
    for y, x in ((0, 0), (2, 3)):
        sd = colour.SpectralDistribution(dict(zip(WL, cube[y, x], strict=True)))
        xyz = colour.sd_to_XYZ(sd, method="Integration", k=1.0, shape=colour.SpectralShape(400, 700, 5))
        rgb = colour.XYZ_to_RGB(xyz, "sRGB")
        np.testing.assert_allclose(ours[y, x], rgb, rtol=2e-3)


def test_envi_round_trip(tmp_path):
    import spectral.io.envi as envi

    cube = _cube()
    write_envi(tmp_path / "pano.hdr", cube, WL, description="test")
    img = envi.open(str(tmp_path / "pano.hdr"))
    np.testing.assert_allclose(np.asarray(img.load()), cube)
    np.testing.assert_allclose([float(w) for w in img.metadata["wavelength"]], WL)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pano.hdr", "pano.img"]
    # band-sequential as the docstring says, band names from the wavelengths, no ignore value without holes
    assert img.metadata["interleave"] == "bsq" and img.metadata["band names"][0] == f"{WL[0]:g} nm"
    assert "data ignore value" not in img.metadata
    # pixels nothing covers carry the declared ignore value; every other pixel its light
    ignore = np.zeros(cube.shape[:2], bool)
    ignore[0, :3] = True
    write_envi(tmp_path / "holes.hdr", cube, WL, ignore=ignore)
    img = envi.open(str(tmp_path / "holes.hdr"))
    data = np.asarray(img.load())
    value = float(img.metadata["data ignore value"])
    assert value < 0 and np.all(data[ignore] == value) and np.allclose(data[~ignore], cube[~ignore])


def test_preview_and_radiance_hdr(tmp_path):
    import cv2

    rgb = spectra_to_linear_srgb(_cube(), WL)
    rgb[0, 0] = np.nan
    write_preview(tmp_path / "p.png", rgb)
    png = cv2.imread(str(tmp_path / "p.png"))
    assert png.shape == (20, 24, 3) and png.max() > 128
    write_radiance_hdr(tmp_path / "p.hdr", rgb)
    back = cv2.imread(str(tmp_path / "p.hdr"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    expected = np.clip(rgb[1:, 1:], 0, None)
    # RGBE: 8-bit mantissas with a shared exponent, so errors scale with each pixel's largest channel
    assert np.all(np.abs(back[1:, 1:] - expected) <= expected.max(axis=2, keepdims=True) / 100)
    # brighter input never gives a darker preview pixel (monotone tone curve, same exposure)
    ramp = np.linspace(0, 5, 50, dtype=np.float32)[None, :, None].repeat(3, axis=2)
    assert np.all(np.diff(tone_map_srgb(ramp)[0, :, 1].astype(int)) >= 0)


def test_radiance_hdr_declares_rec709_primaries_and_d65_and_stays_readable(tmp_path):
    """The ``.hdr`` header says which RGB it holds (``PRIMARIES=``, before ``FORMAT=`` for rgbe.c readers);
    OpenCV and OpenImageIO still read the same pixels."""
    import cv2

    rgb = np.random.default_rng(3).uniform(0.01, 5.0, (6, 8, 3)).astype(np.float32)
    path = write_radiance_hdr(tmp_path / "p.hdr", rgb)
    header = path.read_bytes().split(b"\n\n", 1)[0].decode("ascii").splitlines()
    assert header == ["#?RADIANCE", "PRIMARIES= 0.640 0.330 0.300 0.600 0.150 0.060 0.3127 0.3290",
                      "FORMAT=32-bit_rle_rgbe"]
    assert [p.name for p in tmp_path.iterdir()] == ["p.hdr"]
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]
    tol = rgb.max(axis=2, keepdims=True) / 100  # RGBE: 8-bit mantissas with a shared exponent
    assert np.all(np.abs(back - rgb) <= tol)
    oiio = pytest.importorskip("OpenImageIO", reason="OpenImageIO is not installed (pip install 'omnispectral[test]')")
    buf = oiio.ImageBuf(str(path))
    assert buf.spec().format == oiio.FLOAT and np.all(np.abs(buf.get_pixels(oiio.FLOAT) - rgb) <= tol)
