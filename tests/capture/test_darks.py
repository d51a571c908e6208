"""Black level and dark frames: ``capture darks`` on the simulated rig, ``process`` subtracting them (ground truth)."""

from __future__ import annotations

import datetime as dt
import json
import shutil

import numpy as np
import pytest

from omnispectral.capture.darks import dark_frames, load_darks
from omnispectral.capture.session import Session
from omnispectral.cli import main
from omnispectral.errors import InputFileError
from omnispectral.product.merge import RawSettings, merge_direction
from omnispectral.product.process import process
from omnispectral.rig import rig_with_camera_settings
from omnispectral.sim.simulate import RigRenderer, dark_signal_map, simulate_session, true_mounting_error_deg
from tests.reliability.test_fault_injection import tiny_rig

NOON = dt.datetime(2017, 6, 21, 12, 0, tzinfo=dt.UTC)
BLACK_DN, DARK_E_S, DSNU = 64.0, 400.0, 0.8


def dark_rig():
    """The tiny test rig with a black level of 64 DN and a strong, non-uniform dark signal (hot pixels)."""
    return rig_with_camera_settings(tiny_rig(), {c: {"black_level_dn": BLACK_DN, "noise": {
        "dark_current_e_s": DARK_E_S, "dark_signal_nonuniformity": DSNU}} for c in "AB"})


@pytest.fixture(scope="module")
def dark_session(tmp_path_factory):
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    root = tmp_path_factory.mktemp("darks")
    rig, scene = dark_rig(), ProceduralOutdoorScene(time_hhmm="12:00")
    simulate_session(root / "s", rig, scene, start=NOON, ground_truth_width=64, progress=False)
    return root / "s", rig, scene


def test_capture_darks_records_the_dark_signal_per_exposure(dark_session, capsys):
    path, rig, _ = dark_session
    assert main(["capture", "darks", "-o", str(path), "--dark-frames", "16", "--json"]) == 0
    index = json.loads(capsys.readouterr().out)
    plan = Session.open(path).plan()
    exposures = plan.exposures_s
    # the bracket and the dark extension's longer exposures (indices from DARK_EXPOSURE_BASE)
    assert len(index["frames"]) == 2 * (len(exposures) + len(plan.dark_extension["exposures_s"]))
    darks = load_darks(path)
    cam = rig.camera_a
    dmap = dark_signal_map(cam, (cam.height_px, cam.width_px, 3))
    gain = cam.noise_model().gain_e_per_dn
    for k, t in enumerate(exposures):
        truth = BLACK_DN + dmap * DARK_E_S * t / gain
        err = darks[("A", k)] - truth
        # mean of 16 frames: read noise 13 e- = 3.9 DN per frame -> ~1 DN; hot pixels add their shot noise
        assert abs(err.mean()) < 0.3 and np.sqrt(np.mean(err ** 2)) < 1.6, (k, err.mean(), np.sqrt(np.mean(err ** 2)))
    # the longest exposure's dark frame: hot pixels far above the black level
    assert darks[("A", 0)].max() > BLACK_DN + 60 and np.percentile(darks[("A", 0)], 50) > BLACK_DN + 15


def test_process_subtracts_dark_frames_against_the_ground_truth(dark_session, capsys):
    path, rig, scene = dark_session
    if not load_darks(path):
        assert main(["capture", "darks", "-o", str(path), "--dark-frames", "16", "--json"]) == 0
        capsys.readouterr()
    s = Session.open(path)
    plan = s.plan()
    renderer = RigRenderer(rig, scene, b_mounting_error_deg=true_mounting_error_deg(0))
    gain = rig.camera_a.noise_model().gain_e_per_dn
    darks = {k: v for (c, k), v in dark_frames(path).items() if c == "A"}
    errors = {"darks": [], "black level": []}
    for d in plan.directions[:6]:
        truth = renderer.electrons_per_second("A", d.pan_deg, d.tilt_deg) / gain
        ok = renderer.pixel_valid("A")[..., None] & (truth * min(plan.exposures_s) < 3000) & (truth > 0)
        for name, settings in (("darks", RawSettings(BLACK_DN, darks)), ("black level", RawSettings(BLACK_DN))):
            radiance, _ = merge_direction(s, d.index, "A", len(plan.exposures_s), settings, weight="noise")
            errors[name].append(radiance[ok] / truth[ok] - 1)
    rel = {k: np.concatenate(v) for k, v in errors.items()}
    med = {k: float(np.median(np.abs(v))) for k, v in rel.items()}
    bias = {k: float(np.median(v)) for k, v in rel.items()}
    # with the dark frames the merge is unbiased to noise level (measured -0.02 %); the black level alone
    # leaves the dark signal: +0.8 % on a noon scene whose median pixel reaches ~2800 DN in 0.25 s
    assert abs(bias["darks"]) < 0.002 and med["darks"] < 0.01, (bias, med)
    assert bias["black level"] > 0.005 and med["black level"] > med["darks"], (bias, med)
    # hot pixels: the worst 1 % of pixels (measured 4.8 % with the dark frames, 23 % without)
    p99 = {k: float(np.percentile(np.abs(v), 99)) for k, v in rel.items()}
    assert p99["black level"] > 3 * p99["darks"] and p99["darks"] < 0.08, p99


def test_recording_darks_changes_the_product_fingerprint_and_damage_is_named(dark_session, tmp_path, capsys):
    path, _, _ = dark_session
    copy = tmp_path / "s"
    shutil.copytree(path, copy, ignore=shutil.ignore_patterns(".omnispectral.lock"))
    if not load_darks(copy):
        assert main(["capture", "darks", "-o", str(copy), "--dark-frames", "2", "--json"]) == 0
        capsys.readouterr()
    (copy / "darks" / "A_e03.tif").write_bytes(b"II*\x00garbage")
    with pytest.raises(InputFileError, match=r"darks/A_e03.tif: (damaged dark frame|shape \[0\])"):
        load_darks(copy)
    assert main(["process", str(copy), "-o", str(tmp_path / "p"), "--registration", "paper"]) != 0  # bad input
    err = capsys.readouterr().err
    assert "A_e03.tif" in err and len(err.strip().splitlines()) == 1
    (copy / "darks" / "darks.json").unlink()
    # the refused run had started merged/ for the session with darks: without them it is another product
    with pytest.raises(InputFileError, match="darks_sha256"):
        process(copy, tmp_path / "p", progress=False, registration="paper", report=False)
    index = process(copy, tmp_path / "p", progress=False, registration="paper", report=False, overwrite=True)
    assert "darks_sha256" not in index["fingerprint"]


def test_capture_darks_through_the_genicam_driver(tmp_path, capsys):
    """The real-device path: the rig's GenICam cameras (genicam's simulated GenTL producer, real harvesters
    calls) are opened, set to each exposure of the bracket, read and averaged; the head is not touched."""
    from omnispectral.capture.plan import make_plan
    from omnispectral.rig import load_rig
    from tests.capture.test_real_capture import _rig

    rig = load_rig(_rig(tmp_path / "rig.toml", "/dev/null-no-head"))
    Session.create(tmp_path / "s", rig, make_plan(rig), kind="capture")
    assert main(["capture", "darks", "-o", str(tmp_path / "s"), "--dark-frames", "3", "--json"]) == 0
    index = json.loads(capsys.readouterr().out)
    assert [(e["camera"], e["exposure_index"]) for e in index["frames"]] == [("A", 0), ("B", 0), ("A", 1), ("B", 1)]
    assert all(e["n_frames"] == 3 and e["shape"] == [100, 120, 3] for e in index["frames"])
    assert [e["exposure_s"] for e in index["frames"]] == pytest.approx([0.01, 0.01, 0.001, 0.001], rel=0.01)
    darks = load_darks(tmp_path / "s")
    # the producer's frames are a test pattern, not darkness: the average is what the camera gave
    assert darks[("A", 0)].shape == (100, 120, 3) and darks[("A", 0)].max() > 0
