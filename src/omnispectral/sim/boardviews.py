"""Simulated chessboard views for the stereo calibration of camera B: board poses and their rendering.

What a user does with a real rig before a campaign: hold a chessboard in front of the two cameras
at a few poses and trigger both at once (the head stays at pan = tilt = 0).  The simulated rig does
the same through a :class:`~omnispectral.sim.simulate.RigRenderer` whose camera B carries the
session's unknown mounting error (:func:`~omnispectral.sim.simulate.simulate_session` records the
views into ``SESSION/calibration/``; ``omnispectral simulate-chessboard`` into any folder,
:func:`~omnispectral.sim.simulate.simulate_board_views`), so a calibration fitted on them
(:mod:`omnispectral.product.rigboard`) can be tested on the sessions of that seed.

Layout written (each file atomically; the layout of :mod:`omnispectral.capture.calviews`)::

    DIR/rig.toml                 snapshot of the rig
    DIR/A/view_00.tif …          camera A, 16-bit RGB (DN), one exposure
    DIR/B/view_00.tif …          camera B, same names: a pair per name
    DIR/board.json               the board (inner corners, square size): what the user knows
    DIR/ground_truth/views.json  the poses and B's true mounting (processing never reads it), written last

This module renders through any renderer with the :class:`~omnispectral.sim.simulate.RigRenderer`
interface (``rig``, ``models``, ``band_matrix``, ``set_scene``, ``electrons_per_unit``, called for a
frame), so the simulator can use it without a circular import.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import tifffile

from omnispectral.capture.calviews import clear_views, view_name, write_board_description
from omnispectral.choices import DEFAULT_BOARD, DEFAULT_SQUARE_MM
from omnispectral.errors import ConfigurationError
from omnispectral.io import atomic_path, atomic_write_json, atomic_write_text
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.rig import rig_toml
from omnispectral.sim.scenes.chessboard import ChessboardScene

__all__ = ["DEFAULT_BOARD", "DEFAULT_SQUARE_MM", "MIN_SQUARE_PX", "VIEWS_TRUTH", "WIDTH_SHARE", "board_fully_seen",
           "board_rng", "board_views_complete", "expose_for_board", "next_board_scene", "random_board_pose",
           "render_board_views", "square_px"]

#: The board's width (margin included) spans this share of camera A's horizontal field of view (poses whose
#: board does not fit both cameras are drawn again).
WIDTH_SHARE = (0.3, 0.6)
#: Largest tilt (deg) of the board away from facing the rig, per axis, and in-plane turn.
MAX_TILT_DEG, MAX_TURN_DEG = 35.0, 15.0
#: Smallest square (px of camera A, the board at the middle of :data:`WIDTH_SHARE`) OpenCV finds reliably: a
#: simulated rig with a smaller sensor (a test rig of 96 px) records no views.
MIN_SQUARE_PX = 6.0
#: The file a simulation's views are complete with (written last).
VIEWS_TRUTH = Path("ground_truth") / "views.json"


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


def square_px(model_a, board: tuple[int, int] = DEFAULT_BOARD) -> float:
    """Side (px of camera A) of the board's squares at the middle of :data:`WIDTH_SHARE` of its field of view."""
    return model_a.width * float(np.mean(WIDTH_SHARE)) / (board[0] + 3)


def next_board_scene(rng: np.random.Generator, models: dict, board: tuple[int, int], square_m: float
                     ) -> ChessboardScene:
    """A random pose of the board that both cameras see whole (:func:`random_board_pose`, drawn again until
    :func:`board_fully_seen`); a board that never fits is a :class:`ConfigurationError`."""
    for _ in range(200):
        centre, right, down = random_board_pose(rng, models["A"], board, square_m)
        scene = ChessboardScene(board, square_m, centre, right, down)
        if board_fully_seen(scene, models):
            return scene
    raise ConfigurationError(f"no pose of a {board[0]}x{board[1]} board with {square_m * 1000:g} mm squares fits "
                             "both cameras of the rig")


def board_rng(seed: int) -> np.random.Generator:
    """The random stream of a seed's board poses and view noise."""
    return np.random.default_rng([int(seed), 0x43484553])


def expose_for_board(renderer, scene: ChessboardScene) -> dict[str, float]:
    """Set ``renderer.electrons_per_unit`` and return each camera's exposure (s) so that its brightest band on
    the white squares reaches 70 % of full well, camera A at the bracket's middle exposure (as a user sets
    each camera's exposure)."""
    rig = renderer.rig
    white = {c: float(np.max(renderer.band_matrix(c) @ scene.white_radiance())) for c in ("A", "B")}
    t_mid = float(np.exp(np.mean(np.log(rig.bracket.exposures_s))))
    renderer.electrons_per_unit = 0.7 * rig.cameras["A"].full_well_e / (white["A"] * t_mid)
    return {c: 0.7 * rig.cameras[c].full_well_e / (white[c] * renderer.electrons_per_unit) for c in ("A", "B")}


def render_board_views(output: str | Path, renderer, *, seed: int = 0, n_views: int = 8,
                       board: tuple[int, int] = DEFAULT_BOARD, square_mm: float = DEFAULT_SQUARE_MM,
                       progress: ProgressCallback | None = None) -> dict:
    """Render ``n_views`` chessboard pairs through ``renderer`` into ``output`` (module docstring); returns a
    summary of what was written.  Frames come from ``renderer(camera, 0, 0, exposure_s, rng)`` (its rig's
    cameras must give RGB frames); poses and noise from ``seed``; ``progress("render", done, n_views)`` after
    each pair."""
    if "B" not in renderer.rig.camera_names:
        raise ConfigurationError(f"rig {renderer.rig.name!r} has one camera: there is no camera B to calibrate")
    if n_views < 1:
        raise ConfigurationError(f"n_views must be at least 1, got {n_views}")
    out = Path(output)
    rng = board_rng(seed)
    square_m = float(square_mm) / 1000.0
    scene = ChessboardScene(board, square_m, (0.0, 0.0, 2.0), (1.0, 0.0, 0.0), (0.0, -1.0, 0.0))
    renderer.set_scene(scene)
    exposure_s = expose_for_board(renderer, scene)
    clear_views(out)
    atomic_write_text(out / "rig.toml", rig_toml(renderer.rig))
    write_board_description(out, board, square_mm)
    views = []
    for k in range(n_views):
        scene = next_board_scene(rng, renderer.models, board, square_m)
        renderer.set_scene(scene)
        for c in ("A", "B"):
            frame = renderer(c, 0.0, 0.0, exposure_s[c], rng)
            with atomic_path(out / c / view_name(k)) as tmp:
                tifffile.imwrite(tmp, frame, photometric="rgb")
        views.append({"name": view_name(k), "centre_m": scene.centre_m.tolist(), "right": scene.right.tolist(),
                      "down": scene.down.tolist(), "distance_m": float(np.linalg.norm(scene.centre_m))})
        report_progress(progress, "render", k + 1, n_views)
    truth = {"seed": int(seed), "mounting_error_deg": list(renderer.b_mounting_error_deg),
             "camera_b_true": renderer.models["B"].to_dict(), "exposure_s": exposure_s, "views": views}
    atomic_write_json(out / VIEWS_TRUTH, truth)
    return {"output": str(out), "n_views": n_views, "board": list(board), "square_mm": float(square_mm),
            "distance_m": [v["distance_m"] for v in views]}


def board_views_complete(output: str | Path, seed: int, n_views: int, mounting_error_deg) -> bool:
    """``output`` already holds ``n_views`` views of ``seed`` with camera B mounted ``mounting_error_deg`` off
    the rig file (a resumed simulation, or the slots of a time-lapse, render them once)."""
    path = Path(output) / VIEWS_TRUTH
    try:
        truth = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (truth.get("seed") == int(seed) and len(truth.get("views", [])) == n_views
            and [float(x) for x in truth.get("mounting_error_deg", [])] == [float(x) for x in mounting_error_deg])
