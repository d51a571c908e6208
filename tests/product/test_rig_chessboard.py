"""Camera B's mounting from chessboard pairs (``calibrate rig --chessboard``), against the simulator's hidden truth."""

from __future__ import annotations

import json
import shutil
import tomllib

import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.lens import find_board, read_gray8
from omnispectral.product.direction_parallax import FAR_OFFSET_MIN_STD_PX, OFF_MODEL_WARNING_DEG
from omnispectral.product.pairgeometry import adjusted_model
from omnispectral.product.rigboard import calibrate_chessboard_folder
from omnispectral.product.rigfile import RigCalibration
from omnispectral.rig import load_preset, rig_from_dict
from omnispectral.sim.scenes.chessboard import ChessboardScene
from omnispectral.sim.simulate import simulate_board_views, true_mounting_error_deg
from tests.product.test_rig_registration import infinity_error_px

RIG = load_preset("small")


@pytest.fixture(scope="module")
def boards(tmp_path_factory):
    """Eight noisy chessboard pairs of the small rig, camera B mounted with seed 1's unknown error."""
    root = tmp_path_factory.mktemp("boards")
    simulate_board_views(root / "cb", RIG, seed=1, n_views=8)
    return root / "cb"


def test_rendered_board_corners_are_where_opencv_finds_them(boards):
    truth = json.loads((boards / "ground_truth" / "views.json").read_text())
    true_b = CameraModel.from_dict(truth["camera_b_true"])
    models = {"A": RIG.camera_model("A"), "B": true_b}
    errors = []
    for v in truth["views"]:
        corners_mm = ChessboardScene((9, 6), 0.06, v["centre_m"], v["right"], v["down"]).corners_m() * 1000.0
        for cam, model in models.items():
            found, _ = find_board(read_gray8(boards / cam / v["name"]), (9, 6))
            expected, _ = model.world_points_to_pixel(corners_mm, 0.0, 0.0, margin_px=None)
            errors.append(min(np.median(np.linalg.norm(found - expected, axis=1)),
                              np.median(np.linalg.norm(found[::-1] - expected, axis=1))))
    # the scene's corner layout and the renderer's geometry agree with OpenCV's detector to a fraction of a pixel
    assert max(errors) < 0.15


def test_chessboard_pairs_recover_b_mounting_at_infinity(boards, tmp_path):
    cal = calibrate_chessboard_folder(boards, tmp_path / "cal.json")
    truth = json.loads((boards / "ground_truth" / "views.json").read_text())
    true_b = CameraModel.from_dict(truth["camera_b_true"])
    nominal_b = RIG.camera_model("B")
    ma = RIG.camera_model("A")
    assert cal.method == "chessboard" and cal.chessboard["n_pairs"] == 8
    # the bound is 0.1 px over the whole sensor; the rig file itself is pixels off
    assert infinity_error_px(ma, cal.apply(nominal_b), true_b) < 0.05
    assert infinity_error_px(ma, nominal_b, true_b) > 0.5
    np.testing.assert_allclose(cal.delta_deg, true_mounting_error_deg(1), atol=0.012)
    assert cal.chessboard["std_deg"]["yaw"] < 0.01 and cal.chessboard["rms_b_px"] < 0.2
    assert not cal.warnings()
    # the uncertainty it states at infinity covers its actual error, and is far below what a per-direction
    # offset at infinity measures (process then does not apply those offsets)
    std_px = cal.infinity_std_px(nominal_b)
    assert 0.001 < std_px < FAR_OFFSET_MIN_STD_PX
    assert infinity_error_px(ma, cal.apply(nominal_b), true_b) < 5 * std_px
    # the file round-trips with its method and chessboard record
    again = RigCalibration.load(tmp_path / "cal.json")
    assert again.method == "chessboard" and again.chessboard["n_pairs"] == 8 and again.mounting == cal.mounting


def test_stated_uncertainty_at_infinity_follows_the_geometry():
    """``infinity_std_px`` against B's predicted positions at infinity moved by one standard deviation of
    each angle; a calibration fitted on a session's blocks states none."""
    mb, ma = RIG.camera_model("B"), RIG.camera_model("A")
    sigma = {"yaw": 0.01, "pitch": 0.004, "roll": 0.02}
    cal = RigCalibration("small", mb.mounting.to_dict(), (0.0, 0.0, 0.0), 1, 1, 0.0, {}, [], method="chessboard",
                         chessboard={"std_deg": sigma})
    moved = [infinity_error_px(ma, adjusted_model(mb, d), mb) for d in
             ((sigma["yaw"], 0, 0), (0, sigma["pitch"], 0), (0, 0, sigma["roll"]))]
    assert cal.infinity_std_px(mb) == pytest.approx(float(np.sqrt(np.sum(np.square(moved)))), rel=0.25)
    scene = RigCalibration("small", mb.mounting.to_dict(), (0.0, 0.0, 0.0), 1, 1, 0.0, {}, [])
    assert scene.infinity_std_px(mb) is None


def test_refined_baseline_finds_a_camera_mounted_off_the_rig_file(tmp_path):
    # camera B really sits 64 mm from A and 1.5 mm higher (head frame: y up); the rig file says 60 mm
    text = RIG.toml_text.replace("baseline_mm = [60.0, 0.0, 0.0]", "baseline_mm = [64.0, 1.5, 0.0]")
    true_rig = rig_from_dict(tomllib.loads(text), "moved", text)
    simulate_board_views(tmp_path / "cb", true_rig, seed=5, n_views=12)
    kept = calibrate_chessboard_folder(tmp_path / "cb", tmp_path / "kept.json", rig=RIG)
    refined = calibrate_chessboard_folder(tmp_path / "cb", tmp_path / "refined.json", rig=RIG, refine_baseline=True)
    np.testing.assert_allclose(refined.mounting["baseline_mm"], [64.0, 1.5, 0.0], atol=0.8)
    assert refined.chessboard["rms_b_px"] < kept.chessboard["rms_b_px"]
    assert kept.mounting["baseline_mm"] == [60.0, 0.0, 0.0]


def test_calibrate_rig_chessboard_cli_and_bad_input(boards, tmp_path, capsys):
    out = tmp_path / "cal.json"
    assert main(["calibrate", "rig", "--chessboard", str(boards), "-o", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "8 chessboard pairs" in printed and RigCalibration.load(out).method == "chessboard"
    # exactly one source
    assert main(["calibrate", "rig", "-o", str(out)]) == 2
    assert "either a SESSION" in capsys.readouterr().err
    # a folder without board.json needs the board on the command line
    bare = tmp_path / "bare"
    shutil.copytree(boards / "A", bare / "A")
    shutil.copytree(boards / "B", bare / "B")
    assert main(["calibrate", "rig", "--chessboard", str(bare), "--preset", "small", "-o", str(out)]) == 2
    assert "--board and --square-mm" in capsys.readouterr().err
    # a pair with B's image missing names the file
    (bare / "B" / "view_03.tif").unlink()
    assert main(["calibrate", "rig", "--chessboard", str(bare), "--preset", "small", "--board", "9x6",
                 "--square-mm", "60", "-o", str(out)]) == 1
    err = capsys.readouterr().err
    assert "view_03.tif" in err and len(err.strip().splitlines()) == 1
    # a pair whose B image shows another view is skipped and listed, the rest still calibrates
    shutil.copy(boards / "B" / "view_04.tif", bare / "B" / "view_03.tif")
    cal = calibrate_chessboard_folder(bare, tmp_path / "c2.json", board=(9, 6), square_mm=60.0, rig=RIG)
    assert cal.chessboard["n_pairs"] == 7 and [r["name"] for r in cal.chessboard["rejected"]] == ["view_03.tif"]


def few_directions_rig():
    """The small rig's cameras on a coarser grid (12 directions, 6 exposures): quick sessions, full-size blocks."""
    text = RIG.toml_text
    for old, new in (("count = 15", "count = 6"), ("shortest_s = 0.000015", "shortest_s = 0.0002"),
                     ("n_pan = 12", "n_pan = 6"), ("n_tilt = 3", "n_tilt = 2")):
        assert old in text
        text = text.replace(old, new)
    return rig_from_dict(tomllib.loads(text), "few", text)


def test_process_uses_a_chessboard_calibration_and_says_when_it_no_longer_fits(tmp_path, capsys, monkeypatch):
    from omnispectral.mosaic.sources import MergedDirections
    from omnispectral.product.parallax_ahead import ParallaxAhead
    from omnispectral.product.process import process, register_parallax
    from omnispectral.sim.scenes import ProceduralOutdoorScene
    from omnispectral.sim.simulate import simulate_session
    from tests.product.test_product import NOON

    rig = few_directions_rig()
    simulate_session(tmp_path / "s", rig, ProceduralOutdoorScene(time_hhmm="12:00"), start=NOON,
                     ground_truth_width=256, progress=False, seed=3)
    simulate_board_views(tmp_path / "cb", rig, seed=3, n_views=6)
    calibrate_chessboard_folder(tmp_path / "cb", tmp_path / "cal.json")
    measured_ahead = []
    finished = ParallaxAhead.finished
    monkeypatch.setattr(ParallaxAhead, "finished", lambda self: measured_ahead.append(finished(self)) or
                        measured_ahead[-1])
    index = process(tmp_path / "s", tmp_path / "p", progress=False, rig_calibration=tmp_path / "cal.json")
    # the mounting was known before the merge: directions were measured while it went on, and they are what
    # the stage after the merge measures from the same files
    assert len(measured_ahead) == 1 and len(measured_ahead[0]) >= 1
    again = tmp_path / "again"
    shutil.copytree(tmp_path / "p" / "merged", again)
    meta = json.loads((again / "merged.json").read_text())
    for d in meta["directions"]:
        d["images"]["B"].pop("parallax")
    meta.pop("rig_calibration")
    (again / "merged.json").write_text(json.dumps(meta))
    register_parallax(MergedDirections.open(again), RigCalibration.load(tmp_path / "p" / "rig-calibration.json"))
    first = json.loads((tmp_path / "p" / "merged" / "merged.json").read_text())["directions"]
    second = json.loads((again / "merged.json").read_text())["directions"]
    assert [d["images"]["B"] for d in first] == [d["images"]["B"] for d in second]  # stats, offsets, checksums
    for i in measured_ahead[0]:
        name = f"d{i:04d}_P.npy"
        assert (tmp_path / "p" / "merged" / name).read_bytes() == (again / name).read_bytes()
    reg = index["registration"]
    assert reg["method"] == "parallax" and reg["rig_calibration"]["method"] == "chessboard"
    truth = json.loads((tmp_path / "s" / "ground_truth" / "ground_truth.json").read_text())
    used = RigCalibration.load(tmp_path / "p" / "rig-calibration.json")
    assert infinity_error_px(rig.camera_model("A"), used.apply(rig.camera_model("B")),
                             CameraModel.from_dict(truth["camera_b_true"]["model"])) < 0.05
    assert not reg["warnings"]
    # the board's model is trusted at infinity: the directions' offsets there are measured, not applied
    assert all(d["far_offset_px"] == [0.0, 0.0] for d in reg["directions"])
    assert any(d["far_offset_measured_a_px"] != [0.0, 0.0] for d in reg["directions"])
    across = [d["median_across_deg"] for d in reg["directions"] if d["n_across_blocks"] >= 8]
    # a calibration that no longer fits (camera B knocked 2° in pitch since): process says so
    moved = json.loads((tmp_path / "cal.json").read_text())
    moved["camera_b_mounting"]["misalignment_deg"]["pitch"] += 2.0
    (tmp_path / "moved.json").write_text(json.dumps(moved))
    index = process(tmp_path / "s", tmp_path / "p2", progress=False, rig_calibration=tmp_path / "moved.json")
    warned = [w for w in index["registration"]["warnings"] if "does not fit this session" in w]
    moved_across = [d["median_across_deg"] for d in index["registration"]["directions"] if d["n_across_blocks"] >= 8]
    # the right model leaves a fraction of the bound; 2° of pitch (~5 px here) shows wherever blocks measure
    assert len(across) >= 6 and max(across) < 0.6 * OFF_MODEL_WARNING_DEG
    assert len(warned) >= 6 and min(moved_across) > 1.0, (moved_across, warned)
    # the session's own fit stays available and says what it cannot do
    assert main(["calibrate", "rig", str(tmp_path / "s"), "-o", str(tmp_path / "scene.json")]) == 0
    assert "calibrate rig --chessboard" in capsys.readouterr().out
    assert RigCalibration.load(tmp_path / "scene.json").method == "scene"
