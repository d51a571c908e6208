"""Calibration views once per mounting of the cameras: the simulated rig and ``capture``
record chessboard pairs, ``process`` finds them (file > views > the session's own images), says which it
used, and a product made without them says per direction how far off its far content may be."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil

import numpy as np
import pytest

from omnispectral.capture.calviews import find_calibration_views, operator_next_view, record_calibration_views
from omnispectral.capture.plan import make_plan
from omnispectral.capture.session import Session, verify_session
from omnispectral.cli import main
from omnispectral.imaging.geometry import CameraModel
from omnispectral.product.far_content import FAR_CONTENT_TARGET_PX
from omnispectral.product.fingerprint import product_fingerprint
from omnispectral.product.pairgeometry import adjusted_model
from omnispectral.product.rigboard import calibrate_chessboard_folder
from omnispectral.product.rigfile import RigCalibration
from omnispectral.product.rigsource import CACHE_FILE, choose_rig_calibration
from omnispectral.rig import load_preset
from omnispectral.sim.scenes.chessboard import ChessboardScene
from omnispectral.sim.simulate import simulate_session, simulated_board_cameras, true_mounting_error_deg
from tests.product.test_product import NOON
from tests.product.test_rig_chessboard import few_directions_rig
from tests.product.test_rig_registration import infinity_error_px
from tests.reliability.test_fault_injection import tiny_rig

SMALL = load_preset("small")


def _scene(time_hhmm: str = "12:00"):
    from omnispectral.sim.scenes import ProceduralOutdoorScene

    return ProceduralOutdoorScene(time_hhmm=time_hhmm)


def _b_at_infinity_px(product, session) -> float:
    """B's largest error at infinity over A's sensor: the product's calibration against the simulator's truth."""
    truth = json.loads((session / "ground_truth" / "ground_truth.json").read_text())
    rig = Session.open(session).rig()
    used = RigCalibration.load(product / "rig-calibration.json")
    return infinity_error_px(rig.camera_model("A"), used.apply(rig.camera_model("B")),
                             CameraModel.from_dict(truth["camera_b_true"]["model"]))


@pytest.fixture(scope="module")
def views_session(tmp_path_factory):
    """A 12-direction session of the small rig's cameras (seed 3), with the calibration views simulate records."""
    root = tmp_path_factory.mktemp("views")
    out = simulate_session(root / "s", few_directions_rig(), _scene(), start=NOON, ground_truth_width=256,
                           progress=False, seed=3)
    return root / "s", out


def test_simulate_records_views_once_and_process_fits_them(views_session, tmp_path, capsys):
    session, out = views_session
    views = session / "calibration"
    assert out["calibration_views"] == str(views) and out["calibration_views_s"] > 0
    assert sorted(p.name for p in (views / "A").iterdir()) == [f"view_{k:02d}.tif" for k in range(6)]
    assert sorted(p.name for p in (views / "B").iterdir()) == [f"view_{k:02d}.tif" for k in range(6)]
    # the views carry the session's unknown mounting of camera B (the same seed)
    truth = json.loads((views / "ground_truth" / "views.json").read_text())
    assert truth["mounting_error_deg"] == list(true_mounting_error_deg(3))
    # the session stays a valid session: verify and repair ignore the folder
    assert verify_session(session)["complete"]
    assert main(["session", "repair", str(session)]) == 0
    assert "nothing to do" in capsys.readouterr().out
    # resumed: the views are not rendered again
    stamp = (views / "A" / "view_00.tif").stat().st_mtime_ns
    again = simulate_session(session, few_directions_rig(), _scene(), start=NOON, ground_truth_width=256,
                             progress=False, seed=3)
    assert again["calibration_views_s"] == 0.0 and (views / "A" / "view_00.tif").stat().st_mtime_ns == stamp
    # a plain process finds them, says so, and B at infinity is within the bound
    assert main(["process", str(session), "-o", str(tmp_path / "p")]) == 0
    printed = capsys.readouterr().out
    assert f"Calibration: camera B's mounting from 6 chessboard views in {views}" in printed
    assert "far content may be off" not in printed
    reg = json.loads((tmp_path / "p" / "product.json").read_text())["registration"]
    assert reg["rig_calibration_source"]["kind"] == "chessboard-views"
    assert reg["rig_calibration"]["method"] == "chessboard"
    assert all(d["far_content_error_px"] < FAR_CONTENT_TARGET_PX for d in reg["directions"])
    assert _b_at_infinity_px(tmp_path / "p", session) <= 0.1
    # the fit is cached beside the views, fingerprinted by them
    cached = RigCalibration.load(views / CACHE_FILE)
    assert cached.chessboard["views_sha256"] == reg["rig_calibration_source"]["views_sha256"]
    assert choose_rig_calibration(session, few_directions_rig()).cached


def test_a_changed_views_folder_is_fitted_again(views_session, tmp_path):
    session, _ = views_session
    copy = tmp_path / "s"
    shutil.copytree(session, copy, ignore=shutil.ignore_patterns("frames", "ground_truth"))
    rig = few_directions_rig()
    first = choose_rig_calibration(copy, rig)
    assert first.kind == "chessboard-views" and first.calibration.chessboard["n_pairs"] == 6
    # one pair taken away: another fingerprint, fitted again (and cached again)
    for cam in ("A", "B"):
        (copy / "calibration" / cam / "view_05.tif").unlink()
    second = choose_rig_calibration(copy, rig)
    assert not second.cached and second.views_sha256 != first.views_sha256
    assert second.calibration.chessboard["n_pairs"] == 5
    assert choose_rig_calibration(copy, rig).cached
    # the product's fingerprint follows the views: a product of the old views is not resumed silently
    old = product_fingerprint(session, hdr_weight="noise", registration="parallax",
                              calibration_views_sha256=first.views_sha256)
    new = product_fingerprint(session, hdr_weight="noise", registration="parallax",
                              calibration_views_sha256=second.views_sha256)
    assert old["registration"]["calibration_views_sha256"] != new["registration"]["calibration_views_sha256"]
    # a file given on the command line comes first
    cal_file = tmp_path / "cal.json"
    second.calibration.save(cal_file)
    assert choose_rig_calibration(copy, rig, cal_file).kind == "file"
    # views that cannot be fitted leave the session's own fit, and say why
    (copy / "calibration" / "board.json").write_text(json.dumps({"format": "omnispectral-chessboard-views",
                                                                 "board": [7, 4], "square_mm": 60.0}))
    fallback = choose_rig_calibration(copy, rig)
    assert fallback.kind == "session" and "could not be fitted" in fallback.notes[0]


def test_without_views_process_warns_per_direction(tmp_path, capsys):
    rig_file = tmp_path / "tiny.toml"
    rig_file.write_text(tiny_rig().toml_text)
    assert main(["simulate", "--rig", str(rig_file), "--gt-width", "64", "--no-calibration-views", "-o",
                 str(tmp_path / "s")]) == 0
    assert "No calibration views (--no-calibration-views given)" in capsys.readouterr().out
    assert not (tmp_path / "s" / "calibration").exists()
    assert main(["process", str(tmp_path / "s"), "-o", str(tmp_path / "p")]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "Calibration: camera B's mounting fitted from this session's own images" in "\n".join(lines)
    # the last line: how far off far content may be, per direction, and how to fix it
    assert lines[-1].startswith("warning: far content may be off by up to")
    reg = json.loads((tmp_path / "p" / "product.json").read_text())["registration"]
    assert reg["rig_calibration_source"]["kind"] == "session"
    per = [d["far_content_error_px"] for d in reg["directions"]]
    assert len(per) == 12 and all(v > 0 for v in per) and max(per) > FAR_CONTENT_TARGET_PX
    assert reg["far_content"]["warning"] in reg["warnings"]  # the report lists it too
    assert "capture calibration-views" in reg["far_content"]["warning"]
    report = json.loads((tmp_path / "p" / "report" / "report.json").read_text())
    assert reg["far_content"]["warning"] in report["registration_warnings"]
    assert all("far_content_error_px" in d for d in report["registration"])


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """A two-slot time-lapse (``timelapse`` command) of the 12-direction rig, and what the command printed."""
    root = tmp_path_factory.mktemp("series")
    rig_file = root / "few.toml"
    rig_file.write_text(few_directions_rig().toml_text)
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        assert main(["timelapse", "--rig", str(rig_file), "--from", "12:00", "--to", "12:05", "--every", "5min",
                     "--gt-width", "64", "-o", str(root / "series")]) == 0
    return root / "series", printed.getvalue()


def test_timelapse_records_the_views_once_for_the_series(series):
    series, printed = series
    assert f"calibration views for every slot: {series / 'calibration'}" in printed
    slots = sorted(p for p in series.iterdir() if p.name.startswith("slot_"))
    assert [p.name for p in slots] == ["slot_1200", "slot_1205"]
    assert not any((p / "calibration").exists() for p in slots)
    assert all(find_calibration_views(p) == series / "calibration" for p in slots)
    first, second = (choose_rig_calibration(p, few_directions_rig()) for p in slots)
    assert first.kind == second.kind == "chessboard-views" and not first.cached and second.cached
    assert first.calibration.mounting == second.calibration.mounting


@pytest.mark.slow
def test_process_series_uses_the_series_views_for_every_slot(series, tmp_path, capsys):
    series, _ = series
    assert main(["process-series", str(series), "-o", str(tmp_path / "out")]) == 0
    printed = capsys.readouterr().out
    assert f"Calibration (first slot): camera B's mounting from 6 chessboard views in {series / 'calibration'}" \
        in printed and "warning" not in printed
    for slot in ("slot_1200", "slot_1205"):
        reg = json.loads((tmp_path / "out" / slot / "product.json").read_text())["registration"]
        assert reg["rig_calibration_source"]["path"] == str(series / "calibration")
        assert _b_at_infinity_px(tmp_path / "out" / slot, series / slot) <= 0.1


def test_capture_calibration_views_with_the_simulated_devices(tmp_path, capsys):
    assert main(["capture", "calibration-views", "--preset", "small", "--views", "4", "--seed", "1", "-o",
                 str(tmp_path / "s")]) == 0
    assert "Recorded 4 chessboard pairs" in capsys.readouterr().out
    views = tmp_path / "s" / "calibration"
    summary = json.loads((views / "capture.json").read_text())
    assert summary["n_views"] == 4 and summary["rig"] == "small"
    cal = calibrate_chessboard_folder(views, tmp_path / "cal.json")
    true_b = adjusted_model(SMALL.camera_model("B"), true_mounting_error_deg(1))
    assert infinity_error_px(SMALL.camera_model("A"), cal.apply(SMALL.camera_model("B")), true_b) <= 0.1
    # views taken before the capture do not stop the session from being created there, and stay
    Session.create(tmp_path / "s", SMALL, make_plan(SMALL), kind="capture")
    assert find_calibration_views(tmp_path / "s") == views
    # taken again (the cameras mounted again; the rig from the session's snapshot): the old pairs are gone
    assert main(["capture", "calibration-views", "--views", "2", "-o", str(tmp_path / "s")]) == 0
    assert sorted(p.name for p in (views / "B").iterdir()) == ["view_00.tif", "view_01.tif"]


def test_the_operator_is_asked_again_when_a_camera_misses_the_board(tmp_path):
    cams, board = simulated_board_cameras(SMALL, seed=2)
    asked = []

    def next_view(k, n, problem):
        asked.append((k, problem))
        if len(asked) == 1:  # first pose: the board held far to the side, out of both cameras' view
            board.renderer.set_scene(ChessboardScene((9, 6), 0.06, (30.0, 0.0, 2.0), (1, 0, 0), (0, -1, 0)))
        else:
            board(k, n, problem)

    out = record_calibration_views(tmp_path, SMALL, cams, next_view, n_views=2)
    assert out["n_views"] == 2 and len(out["rejected"]) == 1
    assert asked[1] == (0, "camera A does not see the whole 9x6 board")
    # the terminal's words, and an interval instead of Enter
    messages = []
    operator_next_view(ask=messages.append)(0, 6, None)
    operator_next_view(ask=messages.append)(2, 6, "camera B does not see the whole 9x6 board")
    assert "pose 1 of 6" in messages[0] and messages[0].endswith("press Enter")
    assert messages[1].startswith("not kept (camera B does not see")
    slept = []

    class Clock:
        def sleep(self, s):
            slept.append(s)

    operator_next_view(interval_s=3.0, clock=Clock(), say=messages.append)(1, 6, None)
    assert slept == [3.0] and "shooting in 3 s" in messages[-1]


def test_the_simulator_records_no_views_it_cannot_use(tmp_path):
    out = simulate_session(tmp_path / "s", tiny_rig(), _scene(), start=NOON, ground_truth_width=64, progress=False)
    assert out["calibration_views"] is None and "too few" in out["calibration_views_note"]
    assert not (tmp_path / "s" / "calibration").exists()
    assert np.isfinite(out["wall_s"]) and os.path.isdir(tmp_path / "s" / "frames")
