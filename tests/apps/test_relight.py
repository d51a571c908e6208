"""Relighting from white references (paper Sec. 6.2): ground truth from spectra the bands were made of."""

from __future__ import annotations

import numpy as np
import pytest

from omnispectral.apps.relight import Relighter, WhiteReference, parse_white, relight_block, relight_product
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import equirect_pixel_to_lonlat
from omnispectral.product.estimator import estimator_params, rig_estimator
from omnispectral.product.layout import read_index, write_band_product
from omnispectral.product.spectra import open_product
from omnispectral.rig import load_preset
from omnispectral.spectral.colour import delta_e_ab
from omnispectral.spectral.colour import signal_to_Lab as signals_to_lab
from omnispectral.spectral.library import load_illuminant, load_reflectances

H, W = 128, 256
WL = np.arange(400.0, 701.0, 5.0)


@pytest.fixture(scope="module")
def est():
    return rig_estimator(load_preset("small"))[0]


def _layout():
    """Reflectance per pixel: grey wall, 24 ColorChecker patches (8×8 px) twice (west and east), white references
    (0.95) beside each set; a lamp (emitter) on top."""
    cc = load_reflectances("colorchecker").resample(WL).values
    refl = np.full((H, W, WL.size), 0.3)
    boxes = {}
    for half, c_off in (("west", 16), ("east", 144)):
        for i in range(24):
            r, c = divmod(i, 6)
            r0, c0 = 56 + 10 * r, c_off + 10 * c
            refl[r0:r0 + 8, c0:c0 + 8] = cc[i]
            boxes[(half, i)] = (r0, c0)
        refl[40:48, c_off + 20:c_off + 28] = 0.95
        boxes[(half, "white")] = (40, c_off + 20)
    return refl, cc, boxes


def _centre_lonlat(r0, c0):
    lon, lat = equirect_pixel_to_lonlat(np.array(c0 + 3.5), np.array(r0 + 3.5), W, H)
    return float(lon), float(lat)


def _product(tmp_path, est, light_west: str, light_east: str, name: str):
    refl, cc, boxes = _layout()
    e_w = load_illuminant(light_west).resample(WL).values[0]
    e_e = load_illuminant(light_east).resample(WL).values[0]
    e_w, e_e = e_w / e_w.mean(), e_e / e_e.mean()
    signal = refl * np.where(np.arange(W)[None, :, None] < W // 2, e_w, e_e)
    signal[:6, :, :] = 40 * e_w  # a lamp: far brighter than any white under it
    bands = 1000 * signal @ est.system_matrix.T
    write_band_product(tmp_path / name, bands.astype(np.float32),
                       {"bands": list(est.band_names), "units": "DN/s",
                        "estimator": {"params": estimator_params(load_preset("small"))}}, tile=64)
    return tmp_path / name, cc, boxes


def _patch_lab(product, boxes, half, white_signal_fn):
    _, store, est = open_product(product)
    bands = store.read(0)
    sig = np.array([est.estimate(bands[r0 + 2:r0 + 6, c0 + 2:c0 + 6].reshape(-1, 6).mean(axis=0)[None])[0]
                    for (h, i), (r0, c0) in sorted(boxes.items(), key=str) if h == half and i != "white"])
    r0, c0 = boxes[(half, "white")]
    white = est.estimate(bands[r0 + 2:r0 + 6, c0 + 2:c0 + 6].reshape(-1, 6).mean(axis=0)[None])[0] / 0.95
    return signals_to_lab(sig, white_signal_fn(white), WL)


def test_relight_fl11_to_a_matches_capture_under_a(tmp_path, est):
    src, _, boxes = _product(tmp_path, est, "FL11", "FL11", "fl11")
    ref, _, _ = _product(tmp_path, est, "A", "A", "a")
    white = WhiteReference(*_centre_lonlat(*boxes[("west", "white")]), radius_deg=3.0)
    out = relight_product(src, tmp_path / "relit", [white], to="A")
    assert out["tiles"] == 8 and (tmp_path / "relit" / "preview_relit.png").is_file()
    assert read_index(tmp_path / "relit")["relighting"]["to"] == "A"
    lab_relit = _patch_lab(tmp_path / "relit", boxes, "west", lambda w: w)
    lab_a = _patch_lab(ref, boxes, "west", lambda w: w)
    lab_src = _patch_lab(src, boxes, "west", lambda w: w)
    de = delta_e_ab(lab_relit, lab_a)
    assert de.mean() < 2.0, de
    # not relit, the FL11 capture's colours (each against its own white) differ from A's far more
    assert delta_e_ab(lab_src, lab_a).mean() > 2 * de.mean()
    # the paper's ratio s/E · E_new of two six-band estimates does worse under a spiky light
    relight_product(src, tmp_path / "ratio", [white], to="A", method="ratio")
    de_ratio = delta_e_ab(_patch_lab(tmp_path / "ratio", boxes, "west", lambda w: w), lab_a)
    assert de_ratio.mean() > 1.5 * de.mean()
    print(f"FL11 -> A on exact bands: Wiener reflectance {de.mean():.2f}, ratio {de_ratio.mean():.2f}")
    # the lamp is kept (brighter than the lit white) and counted
    assert out["light_source_pixels"] >= 6 * W
    _, store_r, _ = open_product(tmp_path / "relit")
    _, store_s, _ = open_product(src)
    assert np.allclose(store_r.read(0, slice(0, 6)), store_s.read(0, slice(0, 6)), rtol=2e-3)


def test_tiled_relighting_equals_whole_image(tmp_path, est):
    src, _, boxes = _product(tmp_path, est, "FL11", "FL11", "src")
    white = WhiteReference(*_centre_lonlat(*boxes[("west", "white")]), radius_deg=3.0)
    relight_product(src, tmp_path / "relit", [white], to="D65", sources="relight")
    _, store, e = open_product(src)
    from omnispectral.apps.relight import measure_relighter

    rl = measure_relighter(store, e, [white], "D65", sources="relight")
    whole, _, flag = relight_block(store.read(0), e, rl, slice(0, H), slice(0, W), (H, W))
    _, out, _ = open_product(tmp_path / "relit")
    assert np.allclose(out.read(0), whole @ e.system_matrix.T.astype(np.float32), rtol=1e-4, atol=1e-3)
    assert flag[:6].all()  # flagged even when relit


def test_two_white_references_relight_mixed_lighting(tmp_path, est):
    """West half under FL11, east half under D65; one white per half. With both references the east half relights
    as well as the west; with the west reference only it does not."""
    src, _, boxes = _product(tmp_path, est, "FL11", "D65", "mixed")
    ref, _, _ = _product(tmp_path, est, "A", "A", "a")
    whites = [WhiteReference(*_centre_lonlat(*boxes[(h, "white")]), radius_deg=3.0) for h in ("west", "east")]
    relight_product(src, tmp_path / "both", whites, to="A")
    relight_product(src, tmp_path / "one", whites[:1], to="A")
    lab_a = _patch_lab(ref, boxes, "east", lambda w: w)
    de_both = delta_e_ab(_patch_lab(tmp_path / "both", boxes, "east", lambda w: w), lab_a).mean()
    de_one = delta_e_ab(_patch_lab(tmp_path / "one", boxes, "east", lambda w: w), lab_a).mean()
    assert de_both < 2.5 and de_one > 2 * de_both, (de_both, de_one)


def test_bad_input(tmp_path):
    assert parse_white("10,-20") == WhiteReference(10.0, -20.0, 1.0)
    assert parse_white("10,-20,2.5").radius_deg == 2.5
    for bad in ("10", "a,b", "0,95", "0,0,-1"):
        with pytest.raises(ConfigurationError):
            parse_white(bad)
    (tmp_path / "product").mkdir()
    with pytest.raises(ConfigurationError, match="is the input"):
        relight_product(tmp_path / "product", tmp_path / "product" / ".", [WhiteReference(0, 0)])
    with pytest.raises(ConfigurationError, match="no light"):
        Relighter(WL, np.zeros((1, 3)), np.zeros((1, WL.size)), np.ones(WL.size), method="ratio")


def _indoor_product(tmp_path, est, light):
    from omnispectral.sim.scenes import IndoorScene

    scene = IndoorScene(light)
    w, h = 1024, 512
    bands = np.empty((h, w, 6), np.float32)
    for r0, block in scene.ground_truth_bands(w, h, est.system_matrix):
        bands[r0:r0 + block.shape[0]] = block
    write_band_product(tmp_path / light, 1e4 * bands, {"bands": list(est.band_names), "units": "DN/s",
                                                       "estimator": {"params": estimator_params(load_preset("small"))}},
                       tile=256)
    return tmp_path / light, scene


def test_indoor_scene_radiometry(est):
    from omnispectral.sim.scenes import IndoorScene, lonlat_to_direction
    from omnispectral.spectral.colour import spectra_to_xyz

    scene = IndoorScene("FL11")
    s = scene.spectrum
    lamp = scene.spectral_radiance(np.array([[-1.2, 1.7, 0.5]]))[0]  # at the west panel's centre
    assert 683 * spectra_to_xyz(lamp[None], WL)[0, 1] == pytest.approx(scene.lamp_cd_m2, rel=1e-3)
    wref = scene.white_reference()
    white = scene.spectral_radiance(lonlat_to_direction(wref["lon_deg"], wref["lat_deg"])[None])[0]
    ratio = white / (0.95 * s / np.pi)
    assert np.ptp(ratio) / ratio.mean() < 1e-5  # one spectrum lights the room
    # illuminance at the white from the two panels + ambient, computed here from the geometry
    p = np.array([0.9, 0.0, 3.5])
    e = scene.ambient_lx
    for cx, cz in ((-1.2, 0.5), (1.2, 0.5)):
        v = np.array([cx, 1.7, cz]) - p
        d = np.linalg.norm(v)
        e += scene.lamp_cd_m2 * 0.72 * (v @ [0, 0, -1] / d) * (v[1] / d) / d**2
    assert ratio.mean() == pytest.approx(e, rel=1e-4)
    d = np.random.default_rng(0).normal(size=(500, 3))
    assert np.allclose(scene.band_radiance(d, est.system_matrix), scene.spectral_radiance(d) @ est.system_matrix.T,
                       rtol=1e-4, atol=1e-9)


@pytest.mark.slow
def test_indoor_ground_truth_fl11_to_a(tmp_path, est):
    """The indoor scene's exact bands under FL11, relit to A from its white reference, against its bands under A."""
    src, scene = _indoor_product(tmp_path, est, "FL11")
    ref, _ = _indoor_product(tmp_path, est, "A")
    wref = scene.white_reference()
    white = WhiteReference(wref["lon_deg"], wref["lat_deg"], 0.6 * wref["half_size_deg"])
    out = relight_product(src, tmp_path / "relit", [white], to="A")
    assert out["light_source_pixels"] > 0  # the ceiling panels

    def lab(product, patches):
        from omnispectral.apps.relight import disk_mean_bands

        _, store, e = open_product(product)
        sig = e.estimate(np.array([disk_mean_bands(store, 0, WhiteReference(p["lon_deg"], p["lat_deg"],
                                                                             0.6 * p["half_size_deg"]))
                                   for p in patches]))
        w = e.estimate(disk_mean_bands(store, 0, white)[None])[0] / 0.95
        return signals_to_lab(sig, w, WL)

    for what, patches, bound in (("chart", scene.colorchecker_patches(), 2.0), ("painting", scene.painting_cells(),
                                                                                  2.0)):
        de = delta_e_ab(lab(tmp_path / "relit", patches), lab(ref, patches))
        de_src = delta_e_ab(lab(src, patches), lab(ref, patches))
        print(f"indoor FL11 -> A, exact bands, {what}: mean {de.mean():.2f}, max {de.max():.2f} "
              f"(not relit {de_src.mean():.2f})")
        assert de.mean() < bound and de_src.mean() > 2 * de.mean()


def test_simulate_scene_choice():
    import datetime as dt

    from omnispectral.cli.simulate import build_scene
    from omnispectral.sim.scenes import IndoorScene

    when = dt.datetime(2017, 6, 21, 12, tzinfo=dt.UTC)
    scene = build_scene("indoor", None, when, light="LED-B3")
    assert isinstance(scene, IndoorScene) and scene.describe()["light"] == "LED-B3"
    assert build_scene("indoor", None, when).light == "FL11"
    with pytest.raises(ConfigurationError, match="--light"):
        build_scene("procedural", None, when, light="A")
    with pytest.raises(ConfigurationError, match="unknown illuminant"):
        build_scene("indoor", None, when, light="no-such-light")


def test_indoor_painting_from_a_reflectance_cube(tmp_path, est):
    """``simulate --scene indoor --cube FILE``: the cube is the painting; a texel's radiance is its reflectance
    (resampled from the cube's 10 nm grid) × the illuminance there × S(λ)/π, computed here from the geometry."""
    import datetime as dt

    from omnispectral.errors import InputFileError
    from omnispectral.sim.scenes import IndoorScene, lonlat_to_direction
    from omnispectral.sim.scenes.build import build_scene

    wl10 = np.arange(400.0, 701.0, 10.0)
    rng = np.random.default_rng(3)
    cube = rng.uniform(0.05, 0.9, (3, 4, wl10.size)).astype(np.float32)
    np.savez(tmp_path / "paint.npz", cube=cube, wavelength_nm=wl10)
    scene = build_scene("indoor", str(tmp_path / "paint.npz"), dt.datetime(2017, 6, 21, tzinfo=dt.UTC), light="A")
    assert isinstance(scene, IndoorScene) and scene.describe()["painting"]["texels"] == [3, 4]
    cells = scene.painting_cells(rows=3, cols=4)
    for cell in (cells[0], cells[6], cells[11]):  # top-left, middle, bottom-right texels
        r, c = divmod(cell["index"], 4)
        p = np.array(cell["centre_m"])
        e = scene.irradiance_lx(p[None], np.array([[0.0, 0.0, -1.0]]))[0]
        expected = np.interp(WL, wl10, cube[r, c]) * e * scene.spectrum / np.pi
        got = scene.spectral_radiance(lonlat_to_direction(cell["lon_deg"], cell["lat_deg"])[None])[0]
        assert np.allclose(got, expected, rtol=1e-5), cell["name"]
        assert np.allclose(cell["reflectance"], np.interp(WL, wl10, cube[r, c]))
    # the top-left texel is up and to the right of the chart's centre as seen from the rig (longitude grows right)
    assert cells[0]["lon_deg"] > 0 and cells[0]["lat_deg"] > cells[11]["lat_deg"] and cells[11]["lon_deg"] > cells[0][
        "lon_deg"]
    # the built-in painting: reflectances in 0..1, varied (many distinct colours), and its bands through the scene
    default = IndoorScene("FL11")
    refl = default.painting_reflectance
    assert refl.shape == (48, 64, WL.size) and refl.min() >= 0 and refl.max() <= 1
    assert np.ptp(refl.reshape(-1, WL.size) @ est.system_matrix.T, axis=0).min() > 0.05 * np.abs(
        est.system_matrix).sum(axis=1).min()
    np.savez(tmp_path / "short.npz", cube=cube[..., :10], wavelength_nm=wl10[:10])
    with pytest.raises(InputFileError, match=r"short\.npz.*do not cover"):
        IndoorScene("A", painting=str(tmp_path / "short.npz"))


def test_band_path_equals_spectral_path_with_two_references(tmp_path, est):
    """Level 0 is relit on the bands (one 6 × 6 map per illuminant); that equals relighting the spectra and
    projecting them on the bands, for every mix of the two references, and kept light sources keep their bands."""
    from omnispectral.apps.relight import measure_relighter, pixel_rays

    src, _, boxes = _product(tmp_path, est, "FL11", "D65", "mixed")
    whites = [WhiteReference(*_centre_lonlat(*boxes[(h, "white")]), radius_deg=3.0) for h in ("west", "east")]
    _, store, e = open_product(src)
    bands = store.read(0).reshape(-1, 6)
    rays = pixel_rays(slice(0, H), slice(0, W), H, W)
    for sources in ("relight", "keep"):
        rl = measure_relighter(store, e, whites, "A", sources=sources)
        relit_bands, flag = rl.relight_bands(bands, rays)
        relit_spectra, flag2 = rl.relight(e.estimate(bands), rays, bands)
        assert np.array_equal(flag, flag2) and flag[:6 * W].all() and flag.sum() < 7 * W
        lit = ~flag
        assert np.allclose(relit_bands[lit], relit_spectra[lit] @ e.system_matrix.T, rtol=1e-4, atol=1e-3)
        if sources == "keep":
            assert np.array_equal(relit_bands[flag], bands[flag])
    assert len({tuple(np.round(rl.weights_at(rays[k:k + 1])[0], 2)) for k in range(0, H * W, 97)}) > 5


def test_bright_reflections_are_relit_and_emitters_kept(est):
    """A grey wall lit 1.6× more than the white reference (luminance factor 1.12) is a reflection and is relit;
    a lamp (40×) is kept. With ``source_factor=1`` the bright wall would be taken for a light source."""
    from omnispectral.apps.relight import luminance, target_illuminant

    wl = np.asarray(est.wavelength_nm)
    R = np.asarray(est.system_matrix, float)
    fl11 = load_illuminant("FL11").resample(wl).values[0]
    e = fl11 / fl11.mean()
    signals = np.array([0.7 * 1.6 * e, 40 * e, 0.3 * e])
    bands = signals @ R.T
    a = target_illuminant("A", wl)
    new = a * luminance(e[None], wl)[0] / luminance(a[None], wl)[0]
    rl = Relighter(wl, np.array([[0.0, 0.0, 1.0]]), e[None], a, R)
    relit, flag = rl.relight_bands(bands, None)
    assert flag.tolist() == [False, True, False]
    assert np.allclose(relit[0], (0.7 * 1.6 * new) @ R.T, rtol=0.03)  # Wiener reflectance of a grey: <= 2.5 %
    assert np.allclose(relit[2], (0.3 * new) @ R.T, rtol=0.03)
    assert np.array_equal(relit[1], bands[1].astype(np.float32))
    strict = Relighter(wl, np.array([[0.0, 0.0, 1.0]]), e[None], a, R, source_factor=1.0)
    assert strict.relight_bands(bands, None)[1].tolist() == [True, True, False]
    with pytest.raises(ConfigurationError, match="source_factor"):
        Relighter(wl, np.array([[0.0, 0.0, 1.0]]), e[None], a, R, source_factor=0.0)
