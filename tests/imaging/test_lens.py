"""Lens calibration: synthetic ground truth, OpenCV's sample boards, CLI and bad input."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from omnispectral.cli import main
from omnispectral.errors import InputFileError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.lens import CalibrationError, board_object_points, calibrate_lens, parse_board

BOARD = (9, 6)
SQUARE_MM = 25.0
#: Ground truth of the synthetic views: a wide lens with strong barrel distortion and slight decentring.
TRUTH = CameraModel(800, 600, 610.0, 612.5, 404.3, 297.6, (-0.28, 0.09, 0.0008, -0.0005, -0.012))


def _rotation(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    rx, _ = cv2.Rodrigues(np.array([np.radians(pitch_deg), 0.0, 0.0]))
    ry, _ = cv2.Rodrigues(np.array([0.0, np.radians(yaw_deg), 0.0]))
    rz, _ = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(roll_deg)]))
    return ry @ rx @ rz


def render_board(cam: CameraModel, rot: np.ndarray, t_mm: np.ndarray, rays: np.ndarray, seed: int,
                 board=BOARD, square_mm=SQUARE_MM) -> np.ndarray:
    """8-bit image of a chessboard (pose ``rot``, ``t_mm``: board → camera) seen through ``cam``.

    Each pixel's ray (from ``cam.unproject``) is intersected with the board plane; the checker is
    box-filtered over the pixel footprint (separable ramps across square edges), so corners are
    rendered without aliasing bias.  White paper margin of one square, grey background, noise.
    """
    n = rot[:, 2]
    s = (n @ t_mm) / (rays @ n)
    pts = (rays * s[..., None] - t_mm) @ rot  # board coordinates (mm); corner (i, j) at (i, j) * square
    a = pts[..., 0] / square_mm + 1.0  # in squares from the board's outer corner
    b = pts[..., 1] / square_mm + 1.0
    footprint = np.sqrt(np.abs(np.gradient(a, axis=1) * np.gradient(b, axis=0)
                               - np.gradient(a, axis=0) * np.gradient(b, axis=1)))

    def soft_sign(x):
        edge = np.round(x)
        left = np.where(np.mod(edge - 1, 2) == 0, 1.0, -1.0)  # sign of the square left of the nearest edge
        return left * np.clip((edge - x) / (0.5 * footprint), -1.0, 1.0)

    cols, rows = board
    checker = soft_sign(a) * soft_sign(b)  # +1 = black
    on_board = (a > 0) & (a < cols + 1) & (b > 0) & (b < rows + 1)
    on_paper = (a > -1) & (a < cols + 2) & (b > -1) & (b < rows + 2) & (s > 0)
    img = np.where(on_paper, 225.0, 90.0)
    img = np.where(on_board, 125.0 - 100.0 * checker, img)
    img += np.random.default_rng(seed).normal(0.0, 1.5, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def synthetic_views(cam: CameraModel, tmp_path, n_views: int = 12):
    """Write ``n_views`` PNGs of the board at varied poses covering the image; return paths and poses."""
    rng = np.random.default_rng(7)
    px = np.stack(np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float)), axis=-1)
    rays, ok = cam.unproject(px)
    assert ok.all()
    centre = np.array([(BOARD[0] - 1) / 2 * SQUARE_MM, (BOARD[1] - 1) / 2 * SQUARE_MM, 0.0])
    paths, poses = [], []
    targets = [(0.0, 0.0), (-0.4, -0.3), (0.4, -0.3), (-0.4, 0.3), (0.4, 0.3), (0.0, -0.3), (0.0, 0.3),
               (-0.45, 0.0), (0.45, 0.0), (-0.25, 0.15), (0.25, -0.15), (0.1, 0.25)]
    cols, rows = BOARD
    paper = np.array([[-2, -2, 0], [cols + 1, -2, 0], [-2, rows + 1, 0], [cols + 1, rows + 1, 0]]) * SQUARE_MM
    for k in range(n_views):
        while True:  # a random pose near the target direction with the whole board (and margin) in view
            xn, yn = np.array(targets[k % len(targets)]) + rng.uniform(-0.05, 0.05, 2)
            rot = _rotation(rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-25, 25))
            z = rng.uniform(420.0, 560.0)
            t = np.array([xn * z, yn * z, z]) - rot @ centre
            if cam.project(paper @ rot.T + t, margin_px=-5.0)[1].all():
                break
        img = render_board(cam, rot, t, rays, seed=k)
        path = tmp_path / f"view{k:02d}.png"
        cv2.imwrite(str(path), img)
        paths.append(path)
        poses.append((rot, t))
    return paths, poses


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("synthetic_boards")
    return synthetic_views(TRUTH, tmp)


# ------------------------------------------------------------------------------------------ ground truth
def test_rendered_corners_are_where_the_model_puts_them(synthetic):
    """The renderer and CameraModel.project agree: detected corners sit on the projected board corners."""
    paths, poses = synthetic
    from omnispectral.imaging.lens import find_board, read_gray8

    obj = board_object_points(BOARD, SQUARE_MM).astype(np.float64)
    errors = []
    for path, (rot, t) in zip(paths, poses, strict=True):
        corners, _ = find_board(read_gray8(path), BOARD)
        truth, ok = TRUTH.project(obj @ rot.T + t)
        assert ok.all()
        # The detector may start at either end of the symmetric-looking grid.
        err = min(np.abs(corners - truth).max(), np.abs(corners[::-1] - truth).max())
        errors.append(err)
    assert max(errors) < 0.2, errors


def test_synthetic_distortion_recovered(synthetic):
    paths, _ = synthetic
    result = calibrate_lens(paths, BOARD, SQUARE_MM)
    cam = result.camera
    assert len(result.views) == len(paths) and not result.rejected and not result.warnings
    assert result.rms_px < 0.1
    assert abs(cam.fx - TRUTH.fx) < 0.3 and abs(cam.fy - TRUTH.fy) < 0.3  # measured 0.10, 0.13 px
    assert abs(cam.cx - TRUTH.cx) < 0.6 and abs(cam.cy - TRUTH.cy) < 0.6  # measured 0.24, 0.38 px
    np.testing.assert_allclose(cam.dist, TRUTH.dist, atol=0.003)
    # The distortion itself, where it matters: where rays land across the image.  A small principal point
    # error trades off against the board poses like a small camera rotation, so the bundles of rays are
    # aligned by the best rotation (Kabsch) before comparing pixels.
    px = np.stack(np.meshgrid(np.linspace(0, 799, 41), np.linspace(0, 599, 31)), axis=-1).reshape(-1, 2)
    true_rays, _ = TRUTH.unproject(px)
    fit_rays, _ = cam.unproject(px)
    u, _, vt = np.linalg.svd(fit_rays.T @ true_rays)
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    uv, ok = cam.project(true_rays @ rot.T, margin_px=5.0)
    assert ok.all()
    err = np.linalg.norm(uv - px, axis=-1)
    # (largest in the extreme image corners, which no board view reaches)
    assert err.max() < 0.75 and np.sqrt(np.mean(err**2)) < 0.1, (err.max(), np.sqrt(np.mean(err**2)))
    # Without the alignment the pixels still agree to about half a pixel.
    uv, _ = cam.project(true_rays, margin_px=5.0)
    assert np.linalg.norm(uv - px, axis=-1).max() < 1.0


def test_fixed_opencv_window_fails_on_small_squares(synthetic):
    """Why the corner window adapts: OpenCV's 23 px window merges corners of the oblique views (squares of
    17-24 px here) and the calibration goes wrong by tens of pixels."""
    paths, _ = synthetic
    result = calibrate_lens(paths, BOARD, SQUARE_MM, subpix_window_px=11)
    assert result.rms_px > 0.5
    assert abs(result.camera.cx - TRUTH.cx) > 10.0


# ------------------------------------------------------------------------------------------ real boards
def _opencv_reference(paths):
    """OpenCV's own calibration of its sample boards, as in its tutorial."""
    obj = np.zeros((54, 3), np.float32)
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * SQUARE_MM
    objs, imgs = [], []
    for p in paths:
        gray = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        found, corners = cv2.findChessboardCorners(gray, (9, 6), None)
        if found:
            corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1),
                                       (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001))
            objs.append(obj)
            imgs.append(corners)
    rms, k, dist, _, _ = cv2.calibrateCamera(objs, imgs, gray.shape[::-1], None, None)
    return rms, k, dist.ravel(), len(objs)


def test_real_chessboards_match_opencv(shared_data):
    """With OpenCV's corner window our pipeline is OpenCV's; the adapted default fixes its one bad view."""
    paths = sorted((shared_data / "calibration_chessboard").glob("left*.jpg"))
    if not paths:
        pytest.skip("no left*.jpg chessboards in the shared data")
    ref_rms, ref_k, ref_dist, n_ref = _opencv_reference(paths)
    result = calibrate_lens(paths, (9, 6), SQUARE_MM, subpix_window_px=11)
    cam = result.camera
    assert len(result.views) == n_ref == 13
    assert result.rms_px == pytest.approx(ref_rms, abs=1e-6)
    assert result.rms_px == pytest.approx(0.409, abs=0.002)
    assert cam.fx == pytest.approx(536.07, abs=0.05) and cam.fy == pytest.approx(536.02, abs=0.05)
    np.testing.assert_allclose([cam.fx, cam.fy, cam.cx, cam.cy],
                               [ref_k[0, 0], ref_k[1, 1], ref_k[0, 2], ref_k[1, 2]], atol=1e-4)
    np.testing.assert_allclose(cam.dist, ref_dist, atol=1e-6)
    # Per-image errors combine to the overall RMS (54 corners per view).
    per_view = np.array([v.rms_px for v in result.views])
    assert np.sqrt(np.mean(per_view**2)) == pytest.approx(result.rms_px, rel=1e-6)
    assert per_view[1] == pytest.approx(1.22, abs=0.01)  # left02: 22 px squares under a 23 px window
    # The default window adapted to the corner spacing fixes left02.
    adapted = calibrate_lens(paths, (9, 6), SQUARE_MM)
    assert adapted.rms_px == pytest.approx(0.181, abs=0.002)
    assert adapted.camera.fx == pytest.approx(533.30, abs=0.05)
    assert max(v.rms_px for v in adapted.views) < 0.3


# ------------------------------------------------------------------------------------------ CLI
def test_cli_writes_lens_json(synthetic, tmp_path, capsys):
    paths, _ = synthetic
    out = tmp_path / "lens.json"
    assert main(["calibrate", "lens", *map(str, paths[:8]), "--board", "9x6", "--square-mm", "25",
                 "-o", str(out), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    saved = json.loads(out.read_text())
    assert printed["output"] == str(out)
    for key in ("rms_px", "fx", "fy", "cx", "cy", "distortion", "image_size", "images_used", "images_rejected"):
        assert key in saved
    assert set(saved["distortion"]) == {"k1", "k2", "p1", "p2", "k3"}
    assert saved["image_size"] == {"width": 800, "height": 600}
    assert len(saved["images_used"]) == 8 and all("rms_px" in v for v in saved["images_used"])
    cam = CameraModel.from_json(out)
    assert cam.fx == saved["fx"] and cam.dist == tuple(saved["distortion"].values())
    assert abs(cam.fx - TRUTH.fx) < 2.0


def test_cli_table_lists_rejected_images(synthetic, tmp_path, capsys):
    paths, _ = synthetic
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((600, 800), 128, np.uint8))
    out = tmp_path / "sub" / "lens.json"
    assert main(["calibrate", "lens", *map(str, paths[:5]), str(blank), "--board", "9x6", "--square-mm", "25",
                 "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "RMS reprojection error" in text and "not found" in text and "written to" in text
    saved = json.loads(out.read_text())
    assert saved["images_rejected"] == [{"path": str(blank), "reason": "9x6 board not found"}]


# ------------------------------------------------------------------------------------------ bad input
@pytest.fixture(autouse=True)
def _unwrapped_errors(monkeypatch):
    """Keep the one-line CLI errors on one line whatever the terminal width."""
    from omnispectral.cli._common import err_console

    monkeypatch.setattr(err_console, "_width", 10_000)


def _run_error(argv, capsys, status: int = 1) -> str:
    """Run the CLI expecting an error: 1 for bad inputs, 2 for a bad command line (README)."""
    assert main(argv) == status
    return capsys.readouterr().err


def test_unreadable_and_truncated_files(synthetic, tmp_path, capsys):
    paths, _ = synthetic
    args = ["--board", "9x6", "--square-mm", "25", "-o", str(tmp_path / "lens.json")]
    text = tmp_path / "notes.jpg"
    text.write_text("this is not an image\n")
    err = _run_error(["calibrate", "lens", *map(str, paths[:4]), str(text), *args], capsys)
    assert "notes.jpg" in err and "not a readable image" in err
    jpg = tmp_path / "board.jpg"
    cv2.imwrite(str(jpg), cv2.imread(str(paths[0])))
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(jpg.read_bytes()[: jpg.stat().st_size // 2])
    err = _run_error(["calibrate", "lens", *map(str, paths[:4]), str(cut), *args], capsys)
    assert "cut.jpg" in err and "truncated" in err
    err = _run_error(["calibrate", "lens", str(tmp_path / "nowhere.png"), *args], capsys)
    assert "nowhere.png: file not found" in err
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(InputFileError, match="empty"):
        calibrate_lens([empty], BOARD, SQUARE_MM)
    assert not (tmp_path / "lens.json").exists()


def test_too_few_boards(synthetic, tmp_path, capsys):
    paths, _ = synthetic
    blanks = []
    for k in range(3):
        blank = tmp_path / f"blank{k}.png"
        cv2.imwrite(str(blank), np.full((600, 800), 40 * k + 60, np.uint8))
        blanks.append(str(blank))
    err = _run_error(["calibrate", "lens", *map(str, paths[:2]), *blanks, "--board", "9x6", "--square-mm", "25",
                      "-o", str(tmp_path / "lens.json")], capsys)
    assert "board found in 2 of 5 images" in err and "at least 3" in err and "blank2.png" in err
    with pytest.raises(CalibrationError):
        calibrate_lens(paths[:3], (8, 6), SQUARE_MM)  # wrong board size: found nowhere


def test_mixed_image_sizes(synthetic, tmp_path):
    paths, _ = synthetic
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(paths[0])), (640, 480)))
    with pytest.raises(InputFileError, match=r"small\.png: image is 640x480 but .*view00\.png is 800x600"):
        calibrate_lens([*paths[:3], small], BOARD, SQUARE_MM)


@pytest.mark.parametrize("board", ["9by6", "9x", "2x6", "x"])
def test_bad_board_syntax(board, tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "lens", "a.png", "--board", board, "--square-mm", "25", "-o", str(tmp_path / "l.json")])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--board" in err


def test_parse_board_and_square():
    assert parse_board("9x6") == (9, 6) and parse_board(" 7 X 5 ") == (7, 5)
    with pytest.raises(Exception, match="COLSxROWS"):
        parse_board("9*6")


def test_colour_and_16_bit_images(synthetic, tmp_path):
    """Colour and 16-bit files give the same corners as the 8-bit grey original."""
    paths, _ = synthetic
    from omnispectral.imaging.lens import find_board, read_gray8

    grey = read_gray8(paths[0])
    colour = tmp_path / "colour.png"
    cv2.imwrite(str(colour), cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    deep = tmp_path / "deep.png"
    cv2.imwrite(str(deep), (grey.astype(np.uint16) * 257))
    ref, _ = find_board(grey, BOARD)
    for path in (colour, deep):
        corners, _ = find_board(read_gray8(path), BOARD)
        np.testing.assert_allclose(corners, ref, atol=0.01)


def test_copied_real_board_with_sb_detector(shared_data, tmp_path):
    paths = sorted((shared_data / "calibration_chessboard").glob("left*.jpg"))[:4]
    if len(paths) < 4:
        pytest.skip("shared chessboards missing")
    copies = []
    for p in paths:
        shutil.copy(p, tmp_path / p.name)
        copies.append(tmp_path / p.name)
    result = calibrate_lens(copies, (9, 6), SQUARE_MM, detector="sb", min_images=3)
    assert {v.detector for v in result.views} == {"sb"} and len(result.views) >= 3
    assert result.rms_px < 0.5
