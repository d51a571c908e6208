"""Accuracy limits a run states about itself (product.expectations): from the rig, the settings and the session's own
measurements, recorded in product.json, shown by the report and printed at the end of ``process``.

The end-to-end cases are the measured ones (docs/benchmarks.md): Bayer frames on the ``small`` preset's default
chart (~3 px patches), the paper's registration with the chart at 1.5 m, an indoor session whose self-fitted yaw
rests on one wall; against them an RGB session with calibration views processed by the default path.
"""

from __future__ import annotations

import json

import pytest

from omnispectral.cli import main
from omnispectral.cli.product import _print_summary
from omnispectral.product.expectations import (
    ANCHOR_MIN_SPAN_DEG,
    PAPER_PARALLAX_PX,
    accuracy_warnings,
    anchor_span_deg,
    product_accuracy_warnings,
)
from omnispectral.product.process import process
from omnispectral.product.report import calibration_basis
from omnispectral.rig import load_preset, rig_with_camera_settings

SMALL = load_preset("small")
#: the ``small`` preset's plan: 12 pans every 30° from -165°, three tilts (direction index -> pan)
SMALL_PANS = {i: p for i, p in enumerate([-165.0 + 30 * k for k in range(12)] + [165.0 - 30 * k for k in range(12)]
                                         + [-165.0 + 30 * k for k in range(12)])}


def _bayer(rig):
    raw = {"cfa_pattern": "RGGB", "demosaic": "menon2007", "order": "merge-first"}
    return rig_with_camera_settings(rig, {c: {"raw": raw} for c in rig.camera_names})


def _kinds(warnings: list[dict]) -> list[str]:
    return [w["kind"] for w in warnings]


# ------------------------------------------------------------------------------------------ the rules
def test_bayer_frames_warn_when_a_chart_patch_is_below_four_pixels():
    warned = accuracy_warnings({}, _bayer(SMALL))
    assert _kinds(warned) == ["bayer"]
    figures = warned[0]["figures"]
    assert figures["px_per_deg"] == pytest.approx(2.645, abs=0.01) and figures["min_feature_deg"] > 1.0
    text = warned[0]["message"]
    assert "Raw Bayer frames" in text and "Raw Bayer frames)" in text and "record RGB frames" in text
    assert accuracy_warnings({}, SMALL) == []  # RGB frames
    # the paper's sensor: 21 px per degree, 4 px = 0.19°
    assert accuracy_warnings({}, _bayer(load_preset("paper-timelapse"))) == []


def _paper_index(offsets, fallback=()):
    return {"registration": {"method": "paper", "directions": [
        {"direction": i, "offset_dx_px": dx, "offset_dy_px": dy, "used_fallback": i in fallback, "confidence": 0.5}
        for i, (dx, dy) in enumerate(offsets)]}}


def test_paper_registration_warns_on_the_spread_of_its_offsets():
    far = [(0.3 + 0.05 * (k % 3), -0.2 + 0.04 * (k % 4)) for k in range(24)]  # one offset at infinity, POC noise
    assert accuracy_warnings(_paper_index(far), SMALL) == []
    near = [*far, (0.3, 4.5), (0.1, 5.5)]  # the ground 1.5 m below in two directions
    warned = accuracy_warnings(_paper_index(near), SMALL)
    assert _kinds(warned) == ["paper-registration"]
    f = warned[0]["figures"]
    assert f["spread_px"] > PAPER_PARALLAX_PX and 1.3 < f["distance_m"] < 2.2
    assert "--registration parallax" in warned[0]["message"]
    # a direction that kept the calibrated offset measured nothing
    assert accuracy_warnings(_paper_index([*far, (0.0, 40.0)], fallback={24}), SMALL) == []
    # the parallax registration is never judged by this rule
    assert accuracy_warnings({"registration": {"method": "parallax", "directions": []}}, SMALL) == []


def test_anchor_span_wraps_around():
    assert anchor_span_deg([-15.0, 15.0]) == pytest.approx(30.0)
    assert anchor_span_deg([-165.0, 165.0]) == pytest.approx(30.0)
    assert anchor_span_deg([45.0]) == 0.0
    assert anchor_span_deg(SMALL_PANS.values()) == pytest.approx(330.0)


def _scene_fit_index(anchor_blocks, anchor_directions, method="scene"):
    cal = {"method": method, "far_anchor": {"n_blocks": anchor_blocks, "directions": anchor_directions},
           "camera_b_mounting": {"baseline_mm": [60.0, 0.0, 0.0]}}
    return {"registration": {"method": "parallax", "rig_calibration": cal,
                             "rig_calibration_source": {"kind": "session" if method == "scene" else "chessboard-views"},
                             "directions": []}}


def test_a_session_fit_anchored_on_one_wall_warns_about_the_yaw():
    wall = accuracy_warnings(_scene_fit_index(7, [17, 18]), SMALL, SMALL_PANS)
    assert _kinds(wall) == ["session-yaw"]
    f = wall[0]["figures"]
    assert f["anchor_span_deg"] == pytest.approx(30.0) and f["anchor_span_deg"] < ANCHOR_MIN_SPAN_DEG
    assert f["yaw_error_deg"][0] == pytest.approx(0.344, abs=0.01)  # 60 mm at 10 m
    assert f["yaw_error_deg"][1] == pytest.approx(1.146, abs=0.01)  # at 3 m
    assert "capture calibration-views" in wall[0]["message"]
    # the horizon all around the rig pins it
    around = [15, 16, 17, 18, 19, 21, 22, 23, 25, 27, 28, 31, 32, 35]
    assert accuracy_warnings(_scene_fit_index(34, around), SMALL, SMALL_PANS) == []
    # too few far blocks: the rig file's yaw was kept
    few = accuracy_warnings(_scene_fit_index(3, around), SMALL, SMALL_PANS)
    assert _kinds(few) == ["session-yaw"] and "could not be fixed" in few[0]["message"]
    # a chessboard fit states its own uncertainty (product.far_content)
    assert accuracy_warnings(_scene_fit_index(0, [], method="chessboard"), SMALL, SMALL_PANS) == []


def test_calibration_basis_names_chessboard_corners_or_session_blocks():
    board = {"method": "chessboard", "n_blocks": 324, "n_inliers": 324, "rms_perpendicular_px": 0.03,
             "chessboard": {"n_pairs": 6, "rms_b_px": 0.031, "std_deg": {"yaw": 0.002, "pitch": 0.002, "roll": 0.007}}}
    text = calibration_basis(board)
    assert text.startswith("324 chessboard corners of 6 views") and "block" not in text
    scene = {"method": "scene", "n_blocks": 222, "n_inliers": 208, "rms_perpendicular_px": 0.041,
             "far_anchor": {"n_blocks": 7, "directions": [17, 18]}}
    text = calibration_basis(scene)
    assert text.startswith("208 of 222 blocks of the session's images") and "7 blocks in 2 directions" in text


def test_process_summary_prints_the_limits_at_the_end_and_keeps_its_lines(capsys):
    warning = accuracy_warnings({}, _bayer(SMALL))
    index = {"width": 952, "height": 476, "rig": "small", "bands": ["A:R", "A:G", "A:B", "B:R", "B:G", "B:B"],
             "registration": {"method": "paper", "directions": [], "warnings": []},
             "skipped_directions": [{"direction": 3, "problems": ["A_e00.tif: missing"]}],
             "timings_s": {"total": 1.0}, "sun": {}, "accuracy_warnings": warning}
    _print_summary(index)
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert lines[0].startswith("952×476 six-band panorama of small")
    assert lines[-2].startswith("skipped direction 3:") and lines[-1] == f"accuracy: {warning[0]['message']}"
    # the far-content warning stays the last line (README), the limits just before it
    far = "far content may be off by up to 0.98 px (direction 15)"
    index["registration"] = {**index["registration"], "far_content": {"warning": far}, "warnings": [far]}
    _print_summary(index)
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert lines[-2] == f"accuracy: {warning[0]['message']}" and lines[-1] == f"warning: {far}"


# ------------------------------------------------------------------------------------------ end to end
def _simulate(root, *args) -> str:
    assert main(["simulate", "--preset", "small", "--gt-width", "476", "--json", "-o", str(root), *args]) == 0
    return str(root)


@pytest.fixture(scope="module")
def chart_products(tmp_path_factory):
    """An RGB session with the chart at 1.5 m and its calibration views: the default path and the paper's."""
    root = tmp_path_factory.mktemp("near-chart")
    session = _simulate(root / "session", "--chart-distance", "1.5")
    parallax = process(session, root / "parallax")
    paper = process(session, root / "paper", registration="paper", report=False)
    return root, parallax, paper


@pytest.mark.slow
def test_rgb_session_with_calibration_views_states_no_limit(chart_products):
    root, parallax, _ = chart_products
    assert parallax["registration"]["rig_calibration_source"]["kind"] == "chessboard-views"
    assert parallax["accuracy_warnings"] == []
    report = json.loads((root / "parallax" / "report" / "report.json").read_text())
    assert report["accuracy_warnings"] == []
    html = (root / "parallax" / "report" / "report.html").read_text()
    assert "Accuracy limits of this run</h2><p>None found" in html


@pytest.mark.slow
def test_paper_registration_with_a_near_chart_warns_parallax_does_not(chart_products):
    root, parallax, paper = chart_products
    assert _kinds(paper["accuracy_warnings"]) == ["paper-registration"]
    figures = paper["accuracy_warnings"][0]["figures"]
    assert figures["spread_px"] > 3.0 and figures["distance_m"] < 3.0  # the ground 1.5 m below the head
    assert json.loads((root / "paper" / "product.json").read_text())["accuracy_warnings"] == paper["accuracy_warnings"]
    assert "paper-registration" not in _kinds(parallax["accuracy_warnings"])


@pytest.mark.slow
def test_chessboard_calibration_is_worded_as_corners_of_views(chart_products, capsys):
    root, parallax, _ = chart_products
    html = (root / "parallax" / "report" / "report.html").read_text()
    assert "fitted from 324 chessboard corners of 6 views" in html and "block measurements" not in html
    _print_summary(parallax)
    out = capsys.readouterr().out
    calibration = next(line for line in out.splitlines() if line.startswith("Calibration:"))
    assert "chessboard corners of 6 views" in calibration and "blocks" not in calibration


@pytest.mark.slow
def test_bayer_session_warns_at_the_end_of_process(tmp_path, capsys):
    session = _simulate(tmp_path / "session", "--raw", "bayer")
    capsys.readouterr()
    assert main(["process", session, "-o", str(tmp_path / "product")]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert lines[-1].startswith("accuracy: Raw Bayer frames on camera A and B at 2.6 px per degree")
    index = json.loads((tmp_path / "product" / "product.json").read_text())
    assert _kinds(index["accuracy_warnings"]) == ["bayer"]
    report = json.loads((tmp_path / "product" / "report" / "report.json").read_text())
    assert _kinds(report["accuracy_warnings"]) == ["bayer"]
    assert "Raw Bayer frames on camera A and B" in (tmp_path / "product" / "report" / "report.html").read_text()
    # a product made before the warnings were recorded gets them from its session's rig
    del index["accuracy_warnings"]
    assert _kinds(product_accuracy_warnings(index)) == ["bayer"]


@pytest.mark.slow
def test_indoor_session_fit_warns_about_the_yaw(tmp_path):
    session = _simulate(tmp_path / "session", "--scene", "indoor", "--no-calibration-views")
    index = process(session, tmp_path / "product")
    cal = index["registration"]["rig_calibration"]
    assert index["registration"]["rig_calibration_source"]["kind"] == "session" and cal["method"] == "scene"
    assert _kinds(index["accuracy_warnings"]) == ["session-yaw"]
    figures = index["accuracy_warnings"][0]["figures"]
    assert figures["anchor_span_deg"] < ANCHOR_MIN_SPAN_DEG
    html = (tmp_path / "product" / "report" / "report.html").read_text()
    assert "blocks of the session&#x27;s images" in html and "Camera B&#x27;s yaw was fitted" in html
