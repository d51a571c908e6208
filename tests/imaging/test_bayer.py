"""Raw Bayer frames: CFA layouts, demosaicing, the simulator's mosaics and process's demosaicing vs ground truth."""

from __future__ import annotations

import datetime as dt
import json
import tomllib

import numpy as np
import pytest

from omnispectral.capture.session import Session, dark_extensions
from omnispectral.cli import main
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.bayer import CFA_PATTERNS, channel_index, correct_raw, demosaic, mosaic
from omnispectral.product.merge import RawSettings, merge_direction
from omnispectral.rig import load_preset, rig_from_dict, rig_with_camera_settings
from omnispectral.sim.simulate import RigRenderer, bayer_rig, simulate_session, true_mounting_error_deg
from omnispectral.sim.truth import GroundTruth
from tests.reliability.test_fault_injection import tiny_rig

NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)



def smooth_image(h=48, w=64):
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([1000 + 20 * x + 3 * y, 2000 + 7 * y - 4 * x, 500 + 5 * x + 9 * y], axis=-1)


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
def test_mosaic_layout_matches_colour_demosaicing(pattern):
    from colour_demosaicing import masks_CFA_Bayer  # after omnispectral.imaging.bayer silenced its import warnings

    idx = channel_index((6, 8), pattern)
    masks = masks_CFA_Bayer((6, 8), pattern)  # the peer library's R, G, B masks
    for c in range(3):
        assert np.array_equal(idx == c, masks[c])
    rgb = smooth_image()
    m = mosaic(rgb, pattern)
    assert m[0, 0] == rgb[0, 0, "RGB".index(pattern[0])] and m[1, 1] == rgb[1, 1, "RGB".index(pattern[3])]


@pytest.mark.parametrize("pattern", CFA_PATTERNS)
@pytest.mark.parametrize("method", ["menon2007", "malvar2004", "bilinear", "opencv-ea"])
def test_demosaic_recovers_a_smooth_image(pattern, method):
    rgb = smooth_image()
    m = mosaic(rgb, pattern)
    out = demosaic(m.astype(np.uint16) if method == "opencv-ea" else m, pattern, method)
    # interior of a linear image: every method is (nearly) exact; a wrong layout is off by hundreds of DN
    err = np.abs(out[4:-4, 4:-4] - rgb[4:-4, 4:-4]).max()
    assert err < (1.0 if method == "opencv-ea" else 0.05 * 1000 / 100), (method, pattern, err)


def test_demosaic_rejects_bad_input():
    with pytest.raises(ConfigurationError, match="unknown CFA pattern"):
        demosaic(np.zeros((4, 4)), "RGBG")
    with pytest.raises(ConfigurationError, match="integer codes only"):
        demosaic(np.zeros((4, 4), np.float32), "RGGB", "opencv-ea")
    with pytest.raises(ConfigurationError, match="unknown demosaicing method"):
        demosaic(np.zeros((4, 4)), "RGGB", "ahd")


def test_correct_raw_subtracts_dark_and_keeps_clipping_visible():
    frame = np.array([[100, 4095], [70, 60]], np.uint16)
    dark = np.array([[64.4, 80.0], [64.0, 64.0]], np.float32)
    out = correct_raw(frame, 12, dark=dark)
    assert out.tolist() == [[36, 4095], [6, 0]]  # clipped stays clipped; below the dark level: 0 (no weight)
    assert correct_raw(frame, 12, black_level_dn=64).tolist() == [[36, 4095], [6, 0]]


def test_rig_raw_table_is_validated():
    text = load_preset("small").toml_text
    bad = text.replace("[cameras.B]", '[cameras.A.raw]\ncfa_pattern = "RGBX"\n\n[cameras.B]')
    with pytest.raises(ConfigurationError, match=r"bad.toml: \[cameras.A.raw\] cfa_pattern: expected one of"):
        rig_from_dict(tomllib.loads(bad), "bad.toml", bad)
    bad = text.replace("[cameras.B]", '[cameras.A.raw]\ndemosaic = "opencv-ea"\n\n[cameras.B]')
    with pytest.raises(ConfigurationError, match="opencv-ea demosaics integer codes only"):
        rig_from_dict(tomllib.loads(bad), "bad.toml", bad)
    rig = rig_with_camera_settings(load_preset("small"), {"B": {"raw": {"cfa_pattern": "gbrg", "order":
                                                                        "demosaic-first"}, "black_level_dn": 32.0}})
    assert rig.camera_b.raw.cfa_pattern == "GBRG" and rig.camera_b.raw.order == "demosaic-first"
    assert rig.camera_b.black_level_dn == 32.0 and rig.camera_a.raw is None
    assert rig_from_dict(tomllib.loads(rig.toml_text), "x", rig.toml_text).camera_b == rig.camera_b


@pytest.fixture(scope="module")
def bayer_session(tmp_path_factory):
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    root = tmp_path_factory.mktemp("bayer")
    rig = rig_with_camera_settings(bayer_rig(tiny_rig()), {c: {"black_level_dn": 48.0} for c in "AB"})
    scene = ProceduralOutdoorScene(time_hhmm="12:00")
    simulate_session(root / "s", rig, scene, start=NOON, ground_truth_width=64, progress=False)
    return root / "s", rig, scene


def test_simulated_bayer_frames_are_mosaics_with_their_layout_in_the_journal(bayer_session):
    path, rig, scene = bayer_session
    s = Session.open(path)
    frame, meta = s.read_frame(3, "A", 2)
    assert frame.dtype == np.uint16 and frame.shape == (52, 96)
    assert meta["camera_metadata"]["cfa_pattern"] == "RGGB" and meta["camera_metadata"]["black_level"] == 48.0
    assert s.rig().camera_a.raw.cfa_pattern == "RGGB"
    # the mosaic is the noise-free RGB rendering sampled through the CFA (plus black level): compare the means
    d = s.plan().directions[3]
    renderer = RigRenderer(rig, scene, b_mounting_error_deg=true_mounting_error_deg(0))
    expected = mosaic(renderer.electrons_per_second("A", d.pan_deg, d.tilt_deg) * meta["exposure_s"]
                      / rig.camera_a.noise_model().gain_e_per_dn, "RGGB") + 48.0
    ok = (expected < 3500) & (expected > 100)
    assert abs(np.median(frame[ok] / expected[ok]) - 1) < 0.01


@pytest.mark.parametrize(("method", "order"), [("menon2007", "merge-first"), ("malvar2004", "demosaic-first"),
                                                ("opencv-ea", "demosaic-first")])
def test_merged_bayer_direction_against_the_noise_free_truth(bayer_session, method, order):
    path, rig, scene = bayer_session
    s = Session.open(path)
    plan = s.plan()
    d = plan.directions[4]
    spec = rig_with_camera_settings(rig, {"A": {"raw": {"demosaic": method, "order": order}}}).camera_a.raw
    radiance, _ = merge_direction(s, d.index, "A", len(plan.exposures_s), RawSettings(48.0, {}, spec),
                                  weight="noise")
    renderer = RigRenderer(rig, scene, b_mounting_error_deg=true_mounting_error_deg(0))
    truth = renderer.electrons_per_second("A", d.pan_deg, d.tilt_deg) / rig.camera_a.noise_model().gain_e_per_dn
    ok = renderer.pixel_valid("A")[..., None] & (truth * min(plan.exposures_s) < 3000) & (truth > 0)
    ok[:3], ok[-3:], ok[:, :3], ok[:, -3:] = False, False, False, False
    rel = np.abs(radiance[ok] / truth[ok] - 1)
    # demosaicing a 96 x 52 px view of a detailed scene: most pixels within a few %, edges worse
    assert np.median(rel) < 0.05, np.median(rel)
    # without the black level subtracted the dark pixels would be far off: the correction is applied
    rgb_mean = np.median(radiance[ok] / truth[ok])
    assert abs(rgb_mean - 1) < 0.02


def test_cli_simulate_raw_bayer_then_process(tmp_path, capsys):
    rig = tiny_rig()
    (tmp_path / "tiny.toml").write_text(rig.toml_text)
    assert main(["simulate", "--rig", str(tmp_path / "tiny.toml"), "--raw", "bayer", "--gt-width", "64",
                 "-o", str(tmp_path / "s"), "--json"]) == 0
    capsys.readouterr()
    rec = json.loads((tmp_path / "s" / "journal.jsonl").read_text().splitlines()[0])
    assert rec["shape"] == [52, 96] and rec["camera_metadata"]["cfa_pattern"] == "RGGB"
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p"), "--registration", "paper",
                 "--json"]) == 0
    index = json.loads(capsys.readouterr().out)
    # 144 regular frames, the sun bracket's 8 and the dark extension's (2 cameras each)
    s = Session.open(tmp_path / "s")
    n_dark = 2 * sum(dark_extensions(s, s.plan()).values())
    assert index["bands"] == ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"] and n_dark > 0
    assert index["session_check"]["n_ok"] == 152 + n_dark


@pytest.mark.slow
def test_bayer_session_colorchecker_within_0_3_of_the_rgb_path(tmp_path):
    """simulator Bayer session → process → ColorChecker ΔE*ab within 0.3 of RGB frames."""
    from omnispectral.product.process import process
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    scene = ProceduralOutdoorScene(time_hhmm="12:00", day_of_year=172, chart_patch_m=0.15)
    de = {}
    for raw in ("rgb", "bayer"):
        simulate_session(tmp_path / raw, load_preset("small"), scene, start=NOON, progress=False, raw=raw)
        process(tmp_path / raw, tmp_path / f"p_{raw}", truth=GroundTruth.of_session(tmp_path / raw), progress=False)
        acc = json.loads((tmp_path / f"p_{raw}" / "report" / "report.json").read_text())["accuracy"]
        de[raw] = acc["colorchecker"]["delta_e_ab"]
    assert de["rgb"] < 1.5
    assert abs(de["bayer"] - de["rgb"]) <= 0.3, de
