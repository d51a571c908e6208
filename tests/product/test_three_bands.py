"""Products with three bands (one RGB camera): a one-camera rig through capture, ``process``, the
estimator, exports, report, ``spectrum``, viewer and relighting, measured against the simulator's truth and
against the six-band rig on the same scene."""

from __future__ import annotations

import json
import tomllib

import numpy as np
import pytest

from omnispectral.capture.session import Session, dark_extensions, verify_session
from omnispectral.cli import main
from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.sources import MergedDirections
from omnispectral.product.process import process
from omnispectral.product.report import accuracy
from omnispectral.rig import load_preset, one_camera_rig, rig_from_dict, rig_with_camera_settings
from omnispectral.sim.scenes import ProceduralOutdoorScene
from omnispectral.sim.simulate import simulate_session
from omnispectral.sim.truth import GroundTruth
from tests.reliability.test_fault_injection import NOON, tiny_rig

BANDS3 = ["A:R", "A:G", "A:B"]


def six_band_rig():
    """The tiny rig (12 directions x 6 exposures of 96 x 52 px) with 80° across pan: no gaps between directions."""
    text = tiny_rig().toml_text.replace("vfov_deg = 61.0", "vfov_deg = 80.0")
    return rig_from_dict(tomllib.loads(text), "tiny-80", text)


def rgb_rig():
    """That rig's camera A alone and without its filter: one plain RGB camera (three bands)."""
    return rig_with_camera_settings(one_camera_rig(six_band_rig()), {"A": {"filter": "none"}})


def chart_scene():
    """The procedural scene with a chart large enough to be measured on the tiny rig's ~2°/px panorama."""
    return ProceduralOutdoorScene(time_hhmm="12:00", chart_lat_deg=0.0, chart_patch_m=0.3)


@pytest.fixture(scope="module")
def products(tmp_path_factory):
    """The same scene captured by a one-camera RGB rig and by the six-band rig, both processed."""
    root = tmp_path_factory.mktemp("threeband")
    scene = chart_scene()
    out = {}
    for name, rig in (("rgb", rgb_rig()), ("six", six_band_rig())):
        simulate_session(root / name, rig, scene, start=NOON, ground_truth_width=128, progress=False)
        index = process(root / name, root / f"p_{name}", truth=GroundTruth.of_session(root / name), progress=False)
        report = json.loads((root / f"p_{name}" / "report" / "report.json").read_text())
        out[name] = (root / name, root / f"p_{name}", index, report)
    return out


def test_one_camera_rig_is_three_bands_and_camera_b_is_refused_by_name():
    rig = rgb_rig()
    assert rig.camera_names == ("A",) and rig.n_bands == 3
    system = rig.system()
    assert system.band_names == tuple(BANDS3) and system.matrix.shape[0] == 3
    # camera A alone keeps its own filter: the six-band rig's first three bands
    assert np.array_equal(one_camera_rig(tiny_rig()).system().matrix, tiny_rig().system().matrix[:3])
    with pytest.raises(ConfigurationError, match="has one camera"):
        rig.camera_b  # noqa: B018
    # a rig file with [cameras.B] alone names what is missing
    data = tomllib.loads(load_preset("small").toml_text)
    del data["cameras"]["A"]
    with pytest.raises(ConfigurationError, match=r"\[cameras\] A: missing table"):
        rig_from_dict(data, "b-only.toml")


def test_one_camera_session_processes_and_six_bands_beat_three(products):
    session, product, index, report = products["rgb"]
    assert Session.open(session).cameras() == ("A",)
    v = verify_session(session)
    # 12 directions x 6 exposures x one camera, the sun bracket's 4 attenuated exposures, the dark extension's
    s = Session.open(session)
    assert v["complete"] and v["n_planned"] == 12 * 6 + 4 + sum(dark_extensions(s, s.plan()).values())
    assert index["bands"] == BANDS3 and index["registration"]["method"] == "none"
    merged = MergedDirections.open(product / "merged")
    assert merged.n_bands == 3 and not list((product / "merged").glob("*_B.npy"))
    assert "sensitivity_b" not in index["estimator"]["params"]
    acc3, acc6 = report["accuracy"], products["six"][3]["accuracy"]
    assert acc3["n_bands"] == 3 and "six_band_psnr_db" not in acc3 and acc6["six_band_psnr_db"] == acc6["band_psnr_db"]
    # the three bands against the truth's three bands: as good radiometrically as the six (measured 36.1 / 40.0 dB)
    assert acc3["band_psnr_db"] > 33
    cc3, cc6 = acc3["colorchecker"], acc6["colorchecker"]
    assert cc3["n_patches_seen"] == cc6["n_patches_seen"] == 24
    # spectrally an RGB camera is the paper's "RGB" row (chart level 0.0255 / 5.7; measured here 0.0255 / 5.8) ...
    assert np.isfinite(cc3["delta_e_ab"]) and 1.0 < cc3["delta_e_ab"] < 10.0 and cc3["nrmse"] < 0.04
    # ... and the six-band rig on the same scene is far better (measured 0.0134 / 1.1; whole panorama 0.0135 vs 0.0246)
    assert cc6["delta_e_ab"] < 0.4 * cc3["delta_e_ab"] and cc6["nrmse"] < 0.75 * cc3["nrmse"]
    assert acc6["spectral_nrmse"] < 0.75 * acc3["spectral_nrmse"]


def test_three_band_exports_spectrum_viewer_and_relighting(products, tmp_path, capsys):
    from omnispectral.apps.relight import WhiteReference, relight_product
    from omnispectral.imaging.imageio import read_exr
    from omnispectral.mosaic.store import PanoramaStore
    from omnispectral.product.exports import export_product
    from omnispectral.product.layout import open_product
    from omnispectral.spectral.colour import spectrum_cct_K
    from omnispectral.view.tiles import Display, SlotRenderer

    session, product, index, _ = products["rgb"]
    patches = json.loads((session / "ground_truth" / "ground_truth.json").read_text())["colorchecker_patches"]
    white = max(patches, key=lambda p: np.mean(p["reflectance"]))
    # spectrum: three bands in, a 61-sample spectrum out
    assert main(["spectrum", str(product), "--lon", str(white["lon_deg"]), "--lat", str(white["lat_deg"]),
                 "--json"]) == 0
    spec = json.loads(capsys.readouterr().out)
    assert list(spec["bands"]) == BANDS3 and len(spec["spectrum"]) == 61 and min(spec["spectrum"]) > 0
    # the store: OME-Zarr with three channels, read as (band, lat, lon)
    store = PanoramaStore.open(product / "panorama.zarr")
    da = store.to_xarray()
    assert da.shape[0] == 3 and list(da.coords["band"].values) == BANDS3
    # spectral EXR: one channel per wavelength, values the estimator's spectra of the bands
    out = export_product(product, "spectral-exr", tmp_path / "s.exr")
    exr, names = read_exr(out["output"])
    _, _, est = open_product(product)
    assert sum(n.startswith("S0.") for n in names) == 61 and est.n_bands == 3 and np.isfinite(exr).all()
    assert export_product(product, "png", tmp_path / "p.png")["width"] == index["width"]
    # viewer: every band can be shown, a fourth does not exist
    viewer = SlotRenderer(product)
    assert viewer.render(Display("band", 2), 0, 1, 0, 1, 64, 32).shape == (32, 64, 3)
    with pytest.raises(ConfigurationError, match=r"band 3 does not exist \(0-2\)"):
        viewer.render(Display("band", 3), 0, 1, 0, 1, 64, 32)
    # relighting on the white patch to illuminant A: the relit white is A's colour (2856 K)
    ref = WhiteReference(white["lon_deg"], white["lat_deg"], 0.5 * white["half_size_deg"])
    relight_product(product, tmp_path / "relit", [ref], to="A")
    relit = PanoramaStore.open(tmp_path / "relit" / "panorama.zarr")
    assert relit.n_bands == 3
    from omnispectral.apps.relight import disk_mean_bands

    relit_white = est.estimate(disk_mean_bands(relit, 0, ref)[None])[0]
    assert abs(spectrum_cct_K(est.wavelength_nm, relit_white) - 2856) < 250


def test_accuracy_compares_the_truth_bands_of_the_product_by_name(tmp_path):
    """A one-camera product against the truth of a six-band simulation: the truth's A bands are compared."""
    from omnispectral.sim.simulate import RigRenderer
    from omnispectral.sim.truth import GroundTruth, write_ground_truth

    renderer = RigRenderer(tiny_rig(), chart_scene(), noise=False)
    meta = write_ground_truth(tmp_path / "gt", renderer, 64, spectral_width=32)
    assert meta["bands"]["names"][:3] == BANDS3 and meta["bands"]["shape"][2] == 6
    truth = np.load(tmp_path / "gt" / "bands.npy")
    from omnispectral.product.estimator import rig_estimator

    est, _ = rig_estimator(rgb_rig())
    never = 1e-12  # a shortest exposure no pixel saturates: every pixel is compared
    exact = accuracy(truth[..., :3].copy(), est, GroundTruth.open(tmp_path / "gt"), never, 4095, BANDS3)
    assert exact["band_psnr_db"] == float("inf") and exact["n_bands"] == 3
    assert exact["pixels_compared_fraction"] == 1.0
    b = truth[..., 3:].astype(np.float64)
    off = accuracy((1.1 * b).astype(np.float32), est, GroundTruth.open(tmp_path / "gt"), never, 4095,
                   ["B:R", "B:G", "B:B"])
    expected = 10 * np.log10(b.max() ** 2 / np.mean((0.1 * b) ** 2))  # B's bands, 10 % too bright
    assert off["band_psnr_db"] == pytest.approx(expected, abs=0.01)
    with pytest.raises(ConfigurationError, match="ground truth has bands"):
        accuracy(truth[..., :3].copy(), est, GroundTruth.open(tmp_path / "gt"), never, 4095, ["X", "Y", "Z"])


def test_cli_one_camera_dry_run_plans_one_camera(tmp_path, capsys):
    rig = tiny_rig()
    (tmp_path / "tiny.toml").write_text(rig.toml_text)
    assert main(["capture", "--rig", str(tmp_path / "tiny.toml"), "--one-camera", "--dry-run", "--json",
                 "-o", str(tmp_path / "s")]) == 0
    plan = json.loads(capsys.readouterr().out)
    assert plan["n_frames"] == 12 * 6 and list(plan["cameras"]) == ["A"]


def test_cli_simulate_one_camera_writes_a_three_band_session_and_truth(tmp_path, capsys):
    (tmp_path / "tiny.toml").write_text(tiny_rig().toml_text)
    assert main(["simulate", "--rig", str(tmp_path / "tiny.toml"), "--one-camera", "--gt-width", "64",
                 "-o", str(tmp_path / "s"), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    s = Session.open(tmp_path / "s")
    # + the sun bracket's 4 exposures and the dark extension's
    assert out["n_written"] == 12 * 6 + 4 + sum(dark_extensions(s, s.plan()).values()) and out["rig"] == "small-A"
    assert s.cameras() == ("A",) and not list((tmp_path / "s" / "frames").rglob("B_*.tif"))
    gt = json.loads((tmp_path / "s" / "ground_truth" / "ground_truth.json").read_text())
    assert gt["bands"]["names"] == BANDS3 and "camera_b_true" not in gt
    # --one-camera drops camera A's filter (34A) too: a plain RGB camera, the truth through it alone
    wl = np.asarray(np.load(tmp_path / "s" / "ground_truth" / "wavelength_nm.npy"), float)
    matrix = np.load(tmp_path / "s" / "ground_truth" / "system_matrix.npy")
    plain = rig_with_camera_settings(one_camera_rig(tiny_rig()), {"A": {"filter": "none"}})
    assert np.allclose(matrix, plain.system(wl).matrix, rtol=1e-6)
    assert not np.allclose(matrix, tiny_rig().system(wl).matrix[:3], rtol=1e-2)
    assert "wratten-34a" not in (tmp_path / "s" / "rig.toml").read_text()


def test_a_three_band_product_never_calls_itself_six_band(products, capsys):
    from omnispectral.cli.product import _print_summary

    _print_summary(products["rgb"][2])
    first = capsys.readouterr().out.splitlines()[0]
    assert "3-band panorama" in first and "six-band" not in first and "camera B" not in first


def test_calibrate_rig_refuses_a_one_camera_session(products, capsys):
    session = products["rgb"][0]
    assert main(["calibrate", "rig", str(session), "-o", str(session.parent / "cal.json")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "no camera B to calibrate" in err and str(session) in err
