"""Spectral image-based rendering (paper Sec. 6.1): each check against an independent computation."""

from __future__ import annotations

import json

import colour
import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="mitsuba is not installed (pip install 'omnispectral[render]')")

from omnispectral.apps.environment import (
    EnvironmentMap,
    environment_from_bands,
    environment_from_product,
    fill_uncovered,
    uniform_environment,
)
from omnispectral.apps.materials import Conductor, Diffuse, conductor_reflectance, load_metal
from omnispectral.apps.render import MirrorBallScene, XmlScene, render_fast, render_spectral, write_render
from omnispectral.imaging.geometry import lonlat_to_ray
from omnispectral.product.estimator import estimator_params, rig_estimator
from omnispectral.product.layout import write_band_product
from omnispectral.rig import load_preset, rig_toml
from omnispectral.spectral.colour import spectra_to_xyz
from omnispectral.spectral.library import load_illuminant, load_reflectances

WL = np.arange(400.0, 701.0, 5.0)


def _sphere_hit(scene: MirrorBallScene, ray: np.ndarray):
    o = scene.camera_position_m - scene.ball_centre_m
    b = ray @ o
    disc = b * b - (o @ o - scene.ball_radius_m ** 2)
    if disc < 0:
        return None
    return scene.camera_position_m + (-b - np.sqrt(disc)) * ray


def test_uniform_environment_plate_is_albedo_times_radiance_minus_ball_occlusion():
    """Plate pixel = ρ(λ) L(λ) (1 − F), F = r³/D³ the view factor of the ball (a black occluder) from the plate
    point (sphere resting on the plane; D = distance to its centre)."""
    orange = load_reflectances("colorchecker").select(["orange"]).resample(WL)
    plate = Diffuse("orange", WL, orange.values[0])
    scene = MirrorBallScene(ball=Diffuse.constant("black", 0.0), plate=plate, elevation_deg=35.0)
    d65 = load_illuminant("D65").resample(WL).values[0] / 100.0
    env = uniform_environment(d65, WL)
    w = h = 48
    res = render_spectral(env, scene, w, h, spp=64, wavelength_step_nm=10.0)
    wl = res.wavelength_nm
    rho_l = np.interp(wl, WL, plate.values * d65)
    r = scene.ball_radius_m
    near, far = [], []
    for row in range(h):
        for col in range(w):
            ray = scene.camera_ray(col + 0.5, row + 0.5, w, h)
            if ray[1] >= 0 or _sphere_hit(scene, ray) is not None:
                continue
            p = scene.camera_position_m + (-scene.camera_position_m[1] / ray[1]) * ray
            if max(abs(p[0]), abs(p[2])) > scene.plate_half_size_m - 0.05:
                continue
            dist = np.linalg.norm(p - scene.ball_centre_m)
            expected = rho_l * (1 - (r / dist) ** 3)
            (near if dist < 2.5 * r else far).append((res.spectra[row, col], expected, (r / dist) ** 3))
    assert len(near) > 30 and len(far) > 100
    for group, tol in ((near, 0.02), (far, 0.01)):
        got = np.sum([g for g, _, _ in group], axis=0)
        exp = np.sum([e for _, e, _ in group], axis=0)
        assert np.max(np.abs(got / exp - 1)) < tol
    # the occlusion is what the check resolves: near the ball it removes 5-35 % of the light
    assert np.mean([f for _, _, f in near]) > 0.08


def _smooth_env(h: int = 64):
    w = 2 * h
    lon = (np.arange(w) + 0.5) / w * 360 - 180
    lat = 90 - (np.arange(h) + 0.5) / h * 180
    d = lonlat_to_ray(lon[None, :], lat[:, None])

    def radiance(dirs):
        a, b, c = 1.0 + 0 * WL, (WL - 400) / 300, 1 - (WL - 400) / 300
        return a + b * (0.5 + 0.5 * dirs[..., 1:2]) + c * (0.5 + 0.5 * dirs[..., 0:1])

    return EnvironmentMap(radiance(d).astype(np.float32), WL, "relative"), radiance


def test_mirror_ball_pixel_is_environment_in_reflected_direction_times_silver_fresnel():
    env, radiance = _smooth_env()
    scene = MirrorBallScene(view_lon_deg=40.0)
    size = 65
    res = render_spectral(env, scene, size, size, spp=16, wavelength_step_nm=25.0)
    n, k = scene.ball.eta_k(res.wavelength_nm)
    checked = 0
    for col, row in ((32, 32), (36, 30), (28, 35), (33, 26), (25, 31)):
        ray = scene.camera_ray(col + 0.5, row + 0.5, size, size)
        p = _sphere_hit(scene, ray)
        assert p is not None
        nrm = (p - scene.ball_centre_m) / scene.ball_radius_m
        cos = -(ray @ nrm)
        refl = ray + 2 * cos * nrm
        expected = np.interp(res.wavelength_nm, WL, radiance(refl)) * conductor_reflectance(cos, n, k)
        assert np.max(np.abs(res.spectra[row, col] / expected - 1)) < 0.01
        checked += 1
    # a background pixel is the environment itself
    ray = scene.camera_ray(3.5, 3.5, size, size)
    assert _sphere_hit(scene, ray) is None and ray[1] > 0
    assert np.max(np.abs(res.spectra[3, 3] / np.interp(res.wavelength_nm, WL, radiance(ray)) - 1)) < 0.01
    assert checked == 5
    # silver's reflectance rises from ~0.86 at 400 nm to ~0.96 at 700 nm (Palik): the ball is not grey
    r400, r700 = load_metal("silver").reflectance(np.array([400.0, 700.0]))
    assert 0.8 < r400 < 0.9 < 0.95 < r700 < 0.99


def _chart_xml(tmp_path, names, values) -> str:
    shapes = []
    for i, (_name, v) in enumerate(zip(names, values, strict=True)):
        csv = tmp_path / f"patch{i:02d}.csv"
        csv.write_text("wavelength_nm,reflectance\n" + "".join(f"{w:g},{x:.6f}\n" for w, x in zip(WL, v, strict=True)))
        r, c = divmod(i, 6)
        shapes.append(f"""
  <shape type="rectangle">
    <transform name="to_world"><scale value="0.4"/><translate x="{-2.5 + c}" y="{1.5 - r}" z="0"/></transform>
    <bsdf type="diffuse"><spectrum name="reflectance" filename="{csv.name}"/></bsdf>
  </shape>""")
    xml = f"""<scene version="3.0.0">
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <float name="fov" value="{2 * np.degrees(np.arctan(3.5 / 10)):.9f}"/><string name="fov_axis" value="x"/>
    <transform name="to_world"><lookat origin="0, 0, 10" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
      <rfilter type="box"/></film>
  </sensor>{"".join(shapes)}
</scene>"""
    path = tmp_path / "chart.xml"
    path.write_text(xml)
    return path


def test_rendered_colorchecker_under_d65_matches_colour_science(tmp_path):
    """An XML scene with CSV reflectances (the FILE.xml route), uniform D65 sky: every patch's XYZ equals
    colour-science's ``sd_to_XYZ(patch, D65)``."""
    cc = load_reflectances("colorchecker").resample(WL)
    scene = XmlScene(_chart_xml(tmp_path, cc.names, cc.values))
    assert len(scene.materials) == 24
    d65 = load_illuminant("D65").resample(WL).values[0]
    env = uniform_environment(d65, WL)
    w, h = 112, 64  # 16 px per unit: patch centres at ((x + 3.5)·16, (2 − y)·16)
    res = render_spectral(env, scene, w, h, spp=64)
    white_y = spectra_to_xyz(d65[None], WL)[0, 1]
    shape = colour.SpectralShape(400, 700, 5)
    d65_sd = colour.SpectralDistribution(dict(zip(WL, d65, strict=True)))
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    white_xy = colour.XYZ_to_xy(colour.sd_to_XYZ(colour.sd_ones(shape), cmfs, d65_sd, method="Integration") / 100)
    de = []
    for i in range(24):
        r, c = divmod(i, 6)
        col, row = int((-2.5 + c + 3.5) * 16), int((2 - (1.5 - r)) * 16)
        got = res.spectra[row - 4:row + 4, col - 4:col + 4].reshape(-1, WL.size).mean(axis=0)
        xyz_got = spectra_to_xyz(got[None], WL)[0] / white_y
        sd = colour.SpectralDistribution(dict(zip(WL, cc.values[i], strict=True)))
        xyz_ref = colour.sd_to_XYZ(sd, cmfs, d65_sd, method="Integration") / 100
        de.append(colour.delta_E(colour.XYZ_to_Lab(xyz_got, white_xy), colour.XYZ_to_Lab(xyz_ref, white_xy)))
    assert max(de) < 0.3, de


@pytest.fixture(scope="module")
def small_estimator():
    return rig_estimator(load_preset("small"))[0]


def _band_env(estimator, h=64):
    """Six bands of a smooth sky: daylight D65 overhead, illuminant A towards lon -90° near the horizon."""
    w = 2 * h
    lon = np.radians((np.arange(w) + 0.5) / w * 360 - 180)
    lat = np.radians(90 - (np.arange(h) + 0.5) / h * 180)
    d65 = load_illuminant("D65").resample(WL).values[0] / 100
    ill_a = load_illuminant("A").resample(WL).values[0] / 100
    sky = 1.0 + 0.5 * np.sin(lat)[:, None] + 0 * lon[None, :]
    warm = 0.8 * (1 + np.sin(-lon))[None, :] * np.cos(lat)[:, None]
    spectra = sky[..., None] * d65 + warm[..., None] * ill_a
    return (1000 * spectra @ estimator.system_matrix.T).astype(np.float32)


def test_fast_path_agrees_with_band_packed_for_flat_materials(small_estimator):
    est = small_estimator
    lin = est.linear_map(est.weights)
    bands = _band_env(est)
    assert (bands @ lin[0].T).min() > 0  # nothing clipped: the estimate stays linear in the bands
    env = environment_from_bands(bands, est, "DN/s", linear_map=lin)
    metal = Conductor("flat metal", np.array([300.0, 900.0]), np.array([0.2, 0.2]), np.array([3.0, 3.0]))
    scene = MirrorBallScene(ball=metal, plate=Diffuse.constant("grey", 0.3))
    size = 48
    spec = render_spectral(env, scene, size, size, spp=32)
    fast = render_fast(env, est, scene, size, size, spp=32, linear_map=lin)
    assert fast.info["exact"] and spec.spectra.shape == fast.spectra.shape
    ball = np.zeros((size, size), bool)
    plate = np.zeros((size, size), bool)
    for row in range(size):
        for col in range(size):
            ray = scene.camera_ray(col + 0.5, row + 0.5, size, size)
            hit = _sphere_hit(scene, ray)
            if hit is not None:
                nrm = (hit - scene.ball_centre_m) / scene.ball_radius_m
                cos = -(ray @ nrm)
                ball[row, col] = cos > 0.4 and (ray + 2 * cos * nrm)[1] > 0.05  # mirror image of the sky
            elif ray[1] < 0 and hit is None:
                plate[row, col] = True
    # camera → ball → sky is purely specular: the same rays in every pass, agreement to float precision
    rel = np.abs(fast.spectra[ball] - spec.spectra[ball]).max() / spec.spectra[ball].max()
    assert ball.sum() > 60 and rel < 2e-4
    # diffuse paths differ by Monte Carlo noise only (different importance sampling per pass)
    ratio = fast.spectra[plate].mean(axis=0) / spec.spectra[plate].mean(axis=0)
    assert np.max(np.abs(ratio - 1)) < 0.02
    # a coloured material is where the fast path is approximate: orange ball differs clearly
    orange = load_reflectances("colorchecker").select(["orange"]).resample(WL)
    scene_c = MirrorBallScene(ball=Diffuse("orange", WL, orange.values[0]), plate=Diffuse.constant("grey", 0.3))
    assert not render_fast(env, est, scene_c, 8, 8, spp=1, linear_map=lin).info["exact"]


def test_environment_from_product_flags_saturation_fills_holes_never_negative(tmp_path, small_estimator):
    rig = load_preset("small")
    clip = 0.99 * rig.camera_a.max_dn / min(rig.bracket.exposures_s)
    h = 128
    bands = _band_env(small_estimator, h)
    bands[10:12, 100:102] = 1.2 * clip  # a sun: 2 × 2 px saturated at level 0
    bands[h - 6:, :] = np.nan  # below the head: never seen
    bands[60, 10] = -50.0  # dark noise
    write_band_product(tmp_path / "p", bands, {"bands": list(small_estimator.band_names), "units": "DN/s",
                                               "estimator": {"params": estimator_params(rig)}},
                       attrs={"bands": list(small_estimator.band_names), "rig": {"toml": rig_toml(rig)}}, tile=64)
    env, _ = environment_from_product(tmp_path / "p", level=1)
    assert env.spectra.shape == (64, 128, 61) and env.spectra.min() >= 0
    assert np.array_equal(np.argwhere(env.saturated), [[5, 50]])
    assert env.filled[-3:].all() and not env.filled[:-3].any()
    d = env.describe()
    assert d["saturated_pixels"] == 1 and 0 < d["saturated_energy_fraction"] < 1
    filled, mask = fill_uncovered(np.array([[[1.0]], [[np.nan]], [[np.nan]], [[np.nan]], [[4.0]]]))
    assert filled[:, 0, 0].tolist() == [1.0, 1.0, 1.0, 4.0, 4.0] and mask.sum() == 3


def test_write_render_outputs_round_trip(tmp_path):
    env = uniform_environment(np.linspace(1, 2, WL.size), WL)
    res = render_spectral(env, MirrorBallScene(), 16, 16, spp=2, wavelength_step_nm=50.0)
    files = write_render(res, tmp_path, "ball")
    sd = colour.io.read_spectral_image_Fichet2021(files["spectral_exr"])
    wl_read = np.array(sorted(float(k) for k in sd.S0.keys())) if hasattr(sd, "S0") else None
    meta = json.loads(open(files["json"]).read())
    assert meta["passes"] == 3 and meta["wavelength_nm"] == [400.0, 450.0, 500.0, 550.0, 600.0, 650.0, 700.0]
    assert wl_read is None or wl_read.size == 7
    from omnispectral.imaging.imageio import read_image

    rgb = read_image(files["srgb_exr"])
    assert rgb.shape == (16, 16, 3) and np.isfinite(rgb).all()
    assert np.allclose(rgb, res.linear_srgb(), rtol=1e-5, atol=1e-6)


def test_cli_render_render_series_and_relight(tmp_path, small_estimator):
    from omnispectral.cli import main

    est = small_estimator
    for k, scale in enumerate((0.3, 1.0)):
        write_band_product(tmp_path / "series" / f"slot_{k}", scale * _band_env(est, 32),
                           {"bands": list(est.band_names), "units": "DN/s",
                            "estimator": {"params": estimator_params(load_preset("small"))}}, tile=32)
    rc = main(["render", str(tmp_path / "series" / "slot_1"), "-o", str(tmp_path / "r"), "--width", "24",
               "--height", "16", "--spp", "2", "--wavelength-step", "50", "--json"])
    assert rc == 0
    meta = json.loads((tmp_path / "r" / "render.json").read_text())
    assert meta["passes"] == 3 and meta["environment"]["width"] == 64
    rc = main(["render-series", str(tmp_path / "series"), "-o", str(tmp_path / "s"), "--width", "16", "--height", "16",
               "--spp", "1", "--fast", "--exposure", "common", "--json"])
    assert rc == 0 and len(list((tmp_path / "s" / "frames").glob("frame_*.png"))) == 2
    import cv2

    sheet = cv2.imread(str(tmp_path / "s" / "contact_sheet.png"))
    assert sheet.shape == (16, 32, 3)
    # with one exposure for both, the dimmer slot's frame is darker
    f0, f1 = (cv2.imread(str(tmp_path / "s" / "frames" / f"frame_000{i}.png")).mean() for i in (0, 1))
    assert f0 < f1
    rc = main(["relight", str(tmp_path / "series" / "slot_1"), "--white", "0,45,5", "--to", "D65", "-o",
               str(tmp_path / "rl"), "--json"])
    assert rc == 0 and (tmp_path / "rl" / "preview_relit.png").is_file()
    assert main(["relight", str(tmp_path / "series" / "slot_1"), "--white", "0,95", "-o", str(tmp_path / "x")]) == 2


def test_colour_weights_match_colour_science_integration():
    s = np.random.default_rng(1).random((5, WL.size))
    shape = colour.SpectralShape(400, 700, 5)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    ref = np.array([colour.sd_to_XYZ(colour.SpectralDistribution(dict(zip(WL, x, strict=True))), cmfs,
                                     colour.sd_ones(shape), k=1, method="Integration") for x in s])
    assert np.allclose(spectra_to_xyz(s, WL), 100 * ref, rtol=1e-10)  # colour-science returns k Σ … / 100


def test_xml_conductor_from_csv_and_series_from_time_stack(tmp_path, small_estimator):
    """A metal given as a CSV (n, k) in a scene file: the sphere's centre pixel under a uniform sky is
    L(λ) · R(0°, n, k); and render-series finds its slots through a process-series time stack."""
    import shutil

    import zarr

    from omnispectral.apps.series import series_slots

    metal_csv = tmp_path / "silver.csv"
    from omnispectral.apps import materials

    shutil.copyfile(materials._DATA / "silver.csv", metal_csv)
    (tmp_path / "ball.xml").write_text("""<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective"><float name="fov" value="10"/>
    <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    <film type="hdrfilm"><integer name="width" value="9"/><integer name="height" value="9"/><rfilter type="box"/></film>
  </sensor>
  <shape type="sphere"><float name="radius" value="0.3"/>
    <bsdf type="conductor"><spectrum name="eta" filename="silver.csv"/><spectrum name="k" filename="silver.csv"/></bsdf>
  </shape>
</scene>""")
    scene = XmlScene(tmp_path / "ball.xml")
    env = uniform_environment(np.linspace(1.0, 2.0, WL.size), WL)
    res = render_spectral(env, scene, 9, 9, spp=4, wavelength_step_nm=20.0)
    n, k = load_metal("silver").eta_k(res.wavelength_nm)
    expected = np.interp(res.wavelength_nm, WL, np.linspace(1.0, 2.0, WL.size)) * conductor_reflectance(1.0, n, k)
    assert np.max(np.abs(res.spectra[4, 4] / expected - 1)) < 2e-3
    # a process-series output: slots listed by its time stack, in time order
    for name in ("slot_0630", "slot_1000"):
        write_band_product(tmp_path / "series" / name, _band_env(small_estimator, 16),
                           {"bands": list(small_estimator.band_names), "units": "DN/s",
                            "estimator": {"params": estimator_params(load_preset("small"))}}, tile=16)
    g = zarr.open_group(str(tmp_path / "series" / "timestack.zarr"), mode="w", zarr_format=3)
    g.attrs.update({"times": ["2017-06-21T06:30:00+00:00", "2017-06-21T10:00:00+00:00"],
                    "products": ["slot_0630", "slot_1000"]})
    assert [p.name for _, p in series_slots(tmp_path / "series")] == ["slot_0630", "slot_1000"]


def test_bad_inputs_name_the_file(tmp_path):
    from omnispectral.errors import ConfigurationError, InputFileError

    (tmp_path / "broken.xml").write_text("<scene><sensor>")
    with pytest.raises(InputFileError, match=r"broken\.xml: not valid XML"):
        XmlScene(tmp_path / "broken.xml")
    (tmp_path / "nosensor.xml").write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    with pytest.raises(InputFileError, match="has no <sensor>"):
        XmlScene(tmp_path / "nosensor.xml")
    with pytest.raises(ConfigurationError, match="unknown metal"):
        load_metal("unobtainium")
    (tmp_path / "nk.csv").write_text("wavelength_nm,n,k\n400,0.1\n")
    with pytest.raises(InputFileError, match=r"nk\.csv"):
        load_metal(str(tmp_path / "nk.csv"))
    with pytest.raises(ConfigurationError, match="is tabulated on"):
        load_metal("silver").eta_k(np.array([300.0]))


@pytest.mark.slow
def test_render_series_on_a_simulated_time_lapse(tmp_path):
    """Four times of day simulated with a tiny rig (``timelapse``), processed (``process-series``) and rendered
    (``render-series``): one frame per slot in time order, each slot's render equal to rendering its product
    alone, and the mirror-ball scene brighter at 13:00 than at 07:00 (frames on one common exposure)."""
    import cv2

    from omnispectral.apps.render import render_product
    from omnispectral.capture.timelapse import slot_times
    from omnispectral.cli import main
    from omnispectral.imaging.imageio import read_image
    from tests.product.test_product import NOON, simulate_series, tiny_rig

    slots = slot_times(NOON.replace(hour=7), NOON.replace(hour=16), 3 * 3600)
    simulate_series(tmp_path / "series", tiny_rig(), slots)
    assert main(["process-series", str(tmp_path / "series"), "-o", str(tmp_path / "processed")]) == 0
    opts = {"width": 24, "height": 24, "spp": 4, "wavelength_step_nm": 50.0}
    assert main(["render-series", str(tmp_path / "processed"), "-o", str(tmp_path / "render"), "--width", "24",
                 "--height", "24", "--spp", "4", "--wavelength-step", "50", "--exposure", "common"]) == 0
    summary = json.loads((tmp_path / "render" / "render_series.json").read_text())
    labels = [s["label"] for s in summary["slots"]]
    assert [lab[11:16] for lab in labels] == ["07:00", "10:00", "13:00", "16:00"]
    assert sorted((tmp_path / "render" / "frames").glob("frame_*.png"))[-1].name == "frame_0003.png"
    assert cv2.imread(str(tmp_path / "render" / "contact_sheet.png")).shape == (24, 96, 3)
    rgb = [read_image(s["files"]["srgb_exr"]) for s in summary["slots"]]
    alone = render_product(summary["slots"][2]["environment"]["source"], tmp_path / "alone", **opts)
    assert np.allclose(read_image(alone["files"]["srgb_exr"]), rgb[2], rtol=1e-5, atol=1e-7)
    assert rgb[2].mean() > 1.5 * rgb[0].mean()
    frames = [cv2.imread(str(tmp_path / "render" / "frames" / f"frame_000{k}.png")).mean() for k in range(4)]
    assert frames[2] > frames[0]


def test_variant_choice_avoids_an_llvm_too_old_for_mitsuba():
    """LLVM 15 aborts the process compiling Mitsuba's kernels (X86 ``fminimum``): only 17+ picks llvm_ad_rgb."""
    from omnispectral.apps.render import auto_variant

    both = ["scalar_rgb", "llvm_ad_rgb", "scalar_spectral"]
    assert auto_variant(both, (19, 1, 7)) == "llvm_ad_rgb"
    assert auto_variant(both, (17, 0, 0)) == "llvm_ad_rgb"
    assert auto_variant(both, (15, 0, 6)) == "scalar_rgb"
    assert auto_variant(both, None) == "scalar_rgb"
    assert auto_variant(["scalar_rgb"], (19, 1, 7)) == "scalar_rgb"


def test_render_scene_file_film_size_and_sample_count_unless_given(tmp_path, small_estimator):
    """``render --scene FILE.xml`` renders at the scene file's film size and sample count (``$param`` read
    from its ``<default>``); ``--width``/``--height``/``--spp`` given on the command line win."""
    from omnispectral.cli import main

    write_band_product(tmp_path / "p", _band_env(small_estimator, 16),
                       {"bands": list(small_estimator.band_names), "units": "DN/s",
                        "estimator": {"params": estimator_params(load_preset("small"))}}, tile=16)
    grey = "".join(f"{w},0.5\n" for w in range(400, 701, 50))
    (tmp_path / "grey.csv").write_text("wavelength_nm,reflectance\n" + grey)
    (tmp_path / "plate.xml").write_text("""<scene version="3.0.0">
  <default name="spp" value="3"/>
  <sensor type="perspective"><float name="fov" value="30"/>
    <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler>
    <film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="5"/></film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"><spectrum name="reflectance" filename="grey.csv"/></bsdf></shape>
</scene>""")
    base = ["render", str(tmp_path / "p"), "--scene", str(tmp_path / "plate.xml"), "--wavelength-step", "60",
            "--json"]
    assert main([*base, "-o", str(tmp_path / "a")]) == 0
    meta = json.loads((tmp_path / "a" / "render.json").read_text())
    assert (meta["width"], meta["height"], meta["spp"]) == (12, 5, 3)
    assert main([*base, "-o", str(tmp_path / "b"), "--width", "7", "--spp", "2"]) == 0
    meta = json.loads((tmp_path / "b" / "render.json").read_text())
    assert (meta["width"], meta["height"], meta["spp"]) == (7, 5, 2)
    import cv2

    assert cv2.imread(str(tmp_path / "b" / "render.png")).shape == (5, 7, 3)
    # a grid too coarse for the render's colour is a usage error, not a traceback
    assert main([*base[:-2], "100", "-o", str(tmp_path / "c")]) == 2
