"""Simulated chessboard views for the stereo calibration of camera B (``omnispectral simulate-chessboard``).

What a user does with a real rig before a campaign: hold a chessboard in front of the two cameras
at a dozen poses and trigger both at once (the head stays at pan = tilt = 0).  The simulator renders
those pairs with the same unknown mounting error of camera B as :func:`~omnispectral.capture.
simulate.simulate_session` draws for the same seed, so a calibration fitted on them
(:mod:`omnispectral.product.rigboard`) can be tested on the sessions of that seed.

Layout written (each file atomically)::

    DIR/rig.toml                 snapshot of the rig
    DIR/A/view_00.tif …          camera A, 16-bit RGB (DN), one exposure
    DIR/B/view_00.tif …          camera B, same names: a pair per name
    DIR/board.json               the board (inner corners, square size): what the user knows
    DIR/ground_truth/views.json  the poses and B's true mounting (processing never reads it)
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import tifffile

from omnispectral.capture.scenes.chessboard import ChessboardScene
from omnispectral.capture.simulate import DEFAULT_MOUNTING_ERROR_DEG, RigRenderer, raw_frame, true_mounting_error_deg
from omnispectral.errors import ConfigurationError
from omnispectral.io import atomic_path, atomic_write_json, atomic_write_text
from omnispectral.rig import Rig, rig_toml

BOARD_FORMAT = "omnispectral-chessboard-views"
#: Inner corners and square side of the simulated board (an A2-size print: 0.72 × 0.54 m with its margin).
DEFAULT_BOARD = (9, 6)
DEFAULT_SQUARE_MM = 60.0
#: The board's width (margin included) spans this share of camera A's horizontal field of view (poses whose
#: board does not fit both cameras are drawn again).
WIDTH_SHARE = (0.3, 0.6)
#: Largest tilt (deg) of the board away from facing the rig, per axis, and in-plane turn.
MAX_TILT_DEG, MAX_TURN_DEG = 35.0, 15.0


def random_board_pose(rng: np.random.Generator, model_a, board: tuple[int, int], square_m: float
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(centre_m, right, down)`` of a board somewhere in camera A's view (pan = tilt = 0), facing it roughly."""
    w, h = model_a.width, model_a.height
    px = np.array([rng.uniform(0.3, 0.7) * w, rng.uniform(0.35, 0.65) * h])
    ray = model_a.pixel_to_world(px, 0.0, 0.0)[0]
    width_m = (board[0] + 3) * square_m
    share = rng.uniform(*WIDTH_SHARE)
    distance_m = width_m / (2.0 * math.tan(math.radians(share * model_a.hfov_deg) / 2.0))
    cam = model_a.camera_to_world(0.0, 0.0)
    right = cam[:, 0] - np.dot(cam[:, 0], ray) * ray
    right /= np.linalg.norm(right)
    down = np.cross(ray, right)
    turn = _rotation(ray, rng.uniform(-MAX_TURN_DEG, MAX_TURN_DEG))
    tilt = _rotation(right, rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG)) @ _rotation(
        down, rng.uniform(-MAX_TILT_DEG, MAX_TILT_DEG))
    r = tilt @ turn
    return distance_m * ray, r @ right, r @ down


def _rotation(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rotation matrix by ``angle_deg`` about a unit ``axis`` (``cv2.Rodrigues``)."""
    return cv2.Rodrigues(np.asarray(axis, np.float64) * math.radians(angle_deg))[0]


def board_fully_seen(scene: ChessboardScene, models: dict, margin_squares: float = 1.5) -> bool:
    """Every camera sees all of the board's corners with ``margin_squares`` of room (its margin included)."""
    cols, rows = scene.board
    outer = ChessboardScene((cols + 2 * math.ceil(margin_squares), rows + 2 * math.ceil(margin_squares)),
                            scene.square_m, scene.centre_m, scene.right, scene.down)
    pts = outer.corners_m() * 1000.0
    for m in models.values():
        _, ok = m.world_points_to_pixel(pts, 0.0, 0.0, margin_px=-1.0)
        if not ok.all():
            return False
    return True


def simulate_board_views(output: str | Path, rig: Rig, *, seed: int = 0, n_views: int = 12,
                         board: tuple[int, int] = DEFAULT_BOARD, square_mm: float = DEFAULT_SQUARE_MM,
                         noise: bool = True, mounting_error_deg: float = DEFAULT_MOUNTING_ERROR_DEG,
                         supersample: int = 4, progress=None) -> dict:
    """Render ``n_views`` chessboard pairs (module docstring); returns a summary of what was written.

    Camera B carries :func:`~omnispectral.capture.simulate.true_mounting_error_deg` of ``seed`` (the
    same as a simulated session of that seed).  Each camera's exposure puts its brightest band on the
    white squares at 70 % of its full well; ``supersample`` rays per pixel side integrate the board's edges.
    """
    if "B" not in rig.camera_names:
        raise ConfigurationError(f"rig {rig.name!r} has one camera: there is no camera B to calibrate")
    if n_views < 1:
        raise ConfigurationError(f"n_views must be at least 1, got {n_views}")
    out = Path(output)
    rng = np.random.default_rng([int(seed), 0x43484553])
    square_m = float(square_mm) / 1000.0
    error = true_mounting_error_deg(seed, mounting_error_deg)
    scene = ChessboardScene(board, square_m, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
    renderer = RigRenderer(rig, scene, noise=noise, electrons_per_unit=1.0, b_mounting_error_deg=error,
                           supersample=supersample)
    # each camera exposed for its own brightest band on white (as a user sets each camera's exposure),
    # camera A for the bracket's middle exposure
    white = {c: float(np.max(renderer.band_matrix(c) @ scene.white_radiance())) for c in ("A", "B")}
    t_mid = float(np.exp(np.mean(np.log(rig.bracket.exposures_s))))
    renderer.electrons_per_unit = 0.7 * rig.cameras["A"].full_well_e / (white["A"] * t_mid)
    exposure_s = {c: 0.7 * rig.cameras[c].full_well_e / (white[c] * renderer.electrons_per_unit) for c in ("A", "B")}
    atomic_write_text(out / "rig.toml", rig_toml(rig))
    atomic_write_json(out / "board.json", {"format": BOARD_FORMAT, "board": list(board), "square_mm": float(square_mm)})
    views = []
    for k in range(n_views):
        for _ in range(200):
            centre, right, down = random_board_pose(rng, renderer.models["A"], board, square_m)
            scene = ChessboardScene(board, square_m, centre, right, down)
            if board_fully_seen(scene, renderer.models):
                break
        else:
            raise ConfigurationError(f"no pose of a {board[0]}x{board[1]} board with {square_mm:g} mm squares fits "
                                     f"both cameras of rig {rig.name!r}")
        renderer.set_scene(scene)
        name = f"view_{k:02d}.tif"
        for c in ("A", "B"):
            cam = replace(rig.cameras[c], raw=None)
            frame = raw_frame(cam, renderer.electrons_per_second(c, 0.0, 0.0), exposure_s[c], rng if noise else None)
            with atomic_path(out / c / name) as tmp:
                tifffile.imwrite(tmp, frame, photometric="rgb")
        views.append({"name": name, "centre_m": centre.tolist(), "right": right.tolist(), "down": down.tolist(),
                      "distance_m": float(np.linalg.norm(centre))})
        if progress is not None:
            progress(k + 1, n_views)
    truth = {"seed": int(seed), "mounting_error_deg": list(error), "camera_b_true": renderer.models["B"].to_dict(),
             "exposure_s": exposure_s, "views": views}
    atomic_write_json(out / "ground_truth" / "views.json", truth)
    return {"output": str(out), "n_views": n_views, "board": list(board), "square_mm": float(square_mm),
            "distance_m": [v["distance_m"] for v in views]}
