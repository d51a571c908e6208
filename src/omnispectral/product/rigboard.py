"""Camera B's mounting from chessboard views that both cameras see: a stereo calibration with the lenses fixed.

Why.  Calibrated from a session's own images (:mod:`omnispectral.product.rigcal`), B's pitch and
roll come out to a few thousandths of a degree, but its yaw cannot: along the epipolar lines a yaw
and a common depth move B's image alike, and the session fixes the yaw only as well as its farthest
content with edges across those lines is far (trees 30 m away leave 0.1° on the small rig; a clear
sky and a horizontal skyline give nothing).  A chessboard of known square size fixes the distance
of every corner, so yaw and depth separate: the approach of OpenCV's ``stereoCalibrate`` (Zhang
2000; Bouguet's Camera Calibration Toolbox), with both lenses held at the rig file's calibration and
B's rotation written as the rig's mounting (yaw, pitch, roll on top of the rig file's), optionally
its baseline too.

Fit.  Per view ``k``, the board's pose ``(r_k, t_k)`` in camera A's frame starts from
``cv2.solvePnP`` on A's corners; then one robust least-squares problem (soft-L1, 0.5 px) over B's
rotation change ``δ`` (and the baseline ``c``) and every pose reprojects the board into both cameras
through their own models (:meth:`~omnispectral.imaging.geometry.CameraModel.world_points_to_pixel`,
head at pan = tilt = 0).  The standard deviations come from the Jacobian at the solution
(``σ² (JᵀJ)⁻¹``, ``σ²`` the residual variance).

Input.  Pairs of images with the same file name in two folders (``A/`` and ``B/``), taken at the same
moment with the head still; any format :func:`~omnispectral.imaging.lens.read_gray8` reads.  A pair
where either camera misses the board is listed and skipped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from omnispectral.capture.calviews import IMAGE_SUFFIXES
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import CameraModel, head_rotation
from omnispectral.imaging.lens import CalibrationError, board_object_points, check_board, find_board, read_gray8
from omnispectral.io import read_text_file
from omnispectral.product.rigcal import RigCalibration, adjusted_model
from omnispectral.rig import Rig, load_rig

#: Soft-L1 scale of the corner residuals (px).
CORNER_SCALE_PX = 0.5
#: A view whose B corners lie farther than this share of the board's size from where A's pose and the
#: rig file put them (in either corner order) is not the same board: rejected.
MAX_ORDER_MISMATCH = 0.25
#: Fewest pairs a calibration accepts.
MIN_PAIRS = 1


@dataclass(frozen=True)
class BoardPair:
    """One view: the board's inner corners ``(N, 2)`` found in camera A's and in camera B's image."""

    name: str
    corners_a_px: np.ndarray
    corners_b_px: np.ndarray


def pair_files(folder_a: str | Path, folder_b: str | Path) -> list[tuple[Path, Path]]:
    """Image files of ``folder_a`` paired with the file of the same name in ``folder_b``, sorted by name."""
    fa, fb = Path(folder_a), Path(folder_b)
    for f in (fa, fb):
        if not f.is_dir():
            raise InputFileError(f, "not a folder of chessboard images")
    names_a = sorted(p.name for p in fa.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not names_a:
        raise InputFileError(fa, "no images (tif, png, jpg, ...)")
    missing = [n for n in names_a if not (fb / n).is_file()]
    if missing:
        raise InputFileError(fb / missing[0], f"camera B has no image of this name for camera A's {fa / missing[0]}")
    return [(fa / n, fb / n) for n in names_a]


def find_board_pairs(pairs: list[tuple[Path, Path]], board: tuple[int, int], detector: str = "auto"
                     ) -> tuple[list[BoardPair], list[tuple[str, str]]]:
    """The board's corners in both images of every pair; ``(found, rejected (name, why))``."""
    found, rejected = [], []
    for pa, pb in pairs:
        hit_a = find_board(read_gray8(pa), board, detector)
        hit_b = find_board(read_gray8(pb), board, detector)
        if hit_a is None or hit_b is None:
            rejected.append((pa.name, f"{board[0]}x{board[1]} board not found in camera "
                                      f"{'A' if hit_a is None else 'B'}'s image"))
            continue
        found.append(BoardPair(pa.name, hit_a[0], hit_b[0]))
    return found, rejected


def _pose_in_a(model_a: CameraModel, obj_mm: np.ndarray, corners_px: np.ndarray) -> np.ndarray:
    """``(rvec, tvec_mm)`` of the board in camera A's frame from its corners (``cv2.solvePnP``)."""
    k, dist, _ = model_a.to_opencv()
    ok, rvec, tvec = cv2.solvePnP(obj_mm, corners_px.astype(np.float64), k, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("cv2.solvePnP found no pose of the board in camera A's image")
    return np.concatenate([rvec.ravel(), tvec.ravel()])


def board_points_world_mm(model_a: CameraModel, obj_mm: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Board corners ``(V, N, 3)`` in the world frame at pan = tilt = 0 (mm) for poses ``(V, 6)`` in A's frame."""
    rot = np.stack([cv2.Rodrigues(p[:3])[0] for p in poses])
    cam = np.einsum("vij,nj->vni", rot, obj_mm) + poses[:, None, 3:]
    # the inverse of CameraModel.world_points_to_pixel: camera frame -> head frame -> world
    head = cam @ model_a.mounting.rotation().T + np.asarray(model_a.mounting.baseline_mm)
    return head @ head_rotation(0.0, 0.0).T


def _with_baseline(model_b: CameraModel, baseline_mm) -> CameraModel:
    return replace(model_b, mounting=replace(model_b.mounting, baseline_mm=tuple(float(x) for x in baseline_mm)))


def _order_b(pair: BoardPair, predicted_b: np.ndarray, board_px: float) -> np.ndarray | None:
    """B's corners in A's order: OpenCV may start a board from either end; ``None`` if neither order fits."""
    straight = float(np.nanmedian(np.linalg.norm(pair.corners_b_px - predicted_b, axis=1)))
    flipped = float(np.nanmedian(np.linalg.norm(pair.corners_b_px[::-1] - predicted_b, axis=1)))
    if min(straight, flipped) > MAX_ORDER_MISMATCH * board_px:
        return None
    return pair.corners_b_px if straight <= flipped else pair.corners_b_px[::-1]


def fit_b_mounting_to_boards(pairs: list[BoardPair], model_a: CameraModel, model_b: CameraModel,
                             board: tuple[int, int], square_mm: float, *, refine_baseline: bool = False,
                             rig_name: str = "") -> RigCalibration:
    """B's rotation change (and baseline) that reprojects every board into both cameras (module docstring)."""
    obj = board_object_points(board, square_mm).astype(np.float64)
    poses, used, cb, rejected = [], [], [], []
    for pair in pairs:
        pose = _pose_in_a(model_a, obj, pair.corners_a_px)
        world = board_points_world_mm(model_a, obj, pose[None])[0]
        pred, _ = model_b.world_points_to_pixel(world, 0.0, 0.0, margin_px=None)
        size = float(np.linalg.norm(np.ptp(pair.corners_a_px, axis=0)))
        ordered = _order_b(pair, pred, size)
        if ordered is None:
            rejected.append((pair.name, "camera B's corners do not match camera A's board (another board, or a "
                                        "rig file far from the rig)"))
            continue
        poses.append(pose)
        used.append(pair)
        cb.append(ordered)
    if len(used) < MIN_PAIRS:
        raise CalibrationError("no chessboard pair left to fit camera B's mounting"
                               + "".join(f"; {n}: {why}" for n, why in rejected))
    ca = np.stack([p.corners_a_px for p in used])
    cb = np.stack(cb)
    nb = 3 if refine_baseline else 0
    base0 = np.asarray(model_b.mounting.baseline_mm, np.float64)

    def unpack(x):
        delta, base = x[:3], (x[3:3 + nb] if nb else base0)
        return delta, base, x[3 + nb:].reshape(-1, 6)

    def residuals(x):
        delta, base, p = unpack(x)
        world = board_points_world_mm(model_a, obj, p)
        qa, _ = model_a.world_points_to_pixel(world, 0.0, 0.0, margin_px=None)
        mb = _with_baseline(adjusted_model(model_b, delta), base)
        qb, _ = mb.world_points_to_pixel(world, 0.0, 0.0, margin_px=None)
        return np.nan_to_num(np.concatenate([(qa - ca).ravel(), (qb - cb).ravel()]), nan=1e3)

    x0 = np.concatenate([np.zeros(3), base0 if nb else [], np.concatenate(poses)])
    scale = np.concatenate([np.full(3, 0.05), np.full(nb, 1.0), np.tile([0.01, 0.01, 0.01, 10.0, 10.0, 10.0],
                                                                         len(used))])
    sol = least_squares(residuals, x0, loss="soft_l1", f_scale=CORNER_SCALE_PX, x_scale=scale)
    delta, base, p = unpack(sol.x)
    r = residuals(sol.x).reshape(2, len(used), -1, 2)
    n_par = sol.x.size
    dof = max(r.size - n_par, 1)
    sigma2 = float(np.sum(r ** 2) / dof)
    jtj = sol.jac.T @ sol.jac
    cov = sigma2 * np.linalg.pinv(jtj)
    std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    centres_m = board_points_world_mm(model_a, obj, p).mean(axis=1) / 1000.0
    per_view = []
    for k, pair in enumerate(used):
        per_view.append({"name": pair.name, "distance_m": float(np.linalg.norm(centres_m[k])),
                         "rms_a_px": float(np.sqrt(np.mean(np.sum(r[0, k] ** 2, axis=-1)))),
                         "rms_b_px": float(np.sqrt(np.mean(np.sum(r[1, k] ** 2, axis=-1))))})
    rms_b = float(np.sqrt(np.mean(np.sum(r[1] ** 2, axis=-1))))
    mb = _with_baseline(adjusted_model(model_b, delta), base)
    n_corners = int(cb.shape[0] * cb.shape[1])
    chessboard = {"board": [int(board[0]), int(board[1])], "square_mm": float(square_mm), "n_pairs": len(used),
                  "rms_a_px": float(np.sqrt(np.mean(np.sum(r[0] ** 2, axis=-1)))), "rms_b_px": rms_b,
                  "std_deg": dict(zip(("yaw", "pitch", "roll"), (float(s) for s in std[:3]), strict=True)),
                  "baseline_refined": bool(refine_baseline),
                  **({"baseline_std_mm": [float(s) for s in std[3:6]]} if nb else {}),
                  "views": per_view, "rejected": [{"name": n, "why": w} for n, w in rejected]}
    return RigCalibration(rig_name, mb.mounting.to_dict(), tuple(float(x) for x in delta), n_corners, n_corners,
                          rms_b, {}, [], method="chessboard", chessboard=chessboard)


def calibrate_rig_from_boards(folder: str | Path, model_a: CameraModel, model_b: CameraModel,
                              board: tuple[int, int], square_mm: float, *, refine_baseline: bool = False,
                              detector: str = "auto", rig_name: str = "") -> RigCalibration:
    """Find the board in every pair of ``folder/A`` and ``folder/B`` and fit B's mounting to them."""
    check_board(tuple(board))
    if not square_mm > 0:
        raise ConfigurationError(f"square size must be positive, got {square_mm} mm")
    folder = Path(folder)
    found, rejected = find_board_pairs(pair_files(folder / "A", folder / "B"), board, detector)
    if len(found) < MIN_PAIRS:
        raise CalibrationError(f"{board[0]}x{board[1]} board found in both cameras in none of the pairs in "
                               f"{folder}" + "".join(f"; {n}: {why}" for n, why in rejected[:5]))
    cal = fit_b_mounting_to_boards(found, model_a, model_b, board, square_mm, refine_baseline=refine_baseline,
                                   rig_name=rig_name)
    cal.chessboard["rejected"] = [{"name": n, "why": w} for n, w in rejected] + cal.chessboard["rejected"]
    cal.source = str(folder.resolve())
    return cal


def calibrate_chessboard_folder(folder: str | Path, output: str | Path, *, board: tuple[int, int] | None = None,
                                square_mm: float | None = None, rig: Rig | None = None,
                                refine_baseline: bool = False, detector: str = "auto") -> RigCalibration:
    """``calibrate rig --chessboard``: pairs in ``folder/A`` and ``folder/B``; the rig from ``rig`` or
    ``folder/rig.toml``, the board from ``board``/``square_mm`` or ``folder/board.json`` (as
    ``simulate-chessboard`` writes); the calibration saved to ``output`` (JSON) for ``process --rig-calibration``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputFileError(folder, "not a folder of chessboard pairs (A/ and B/)")
    if board is None or square_mm is None:
        spec_path = folder / "board.json"
        if not spec_path.is_file():
            raise ConfigurationError(f"give --board and --square-mm (no {spec_path} to read them from)")
        try:
            spec = json.loads(read_text_file(spec_path, "board description"))
            board = board or (int(spec["board"][0]), int(spec["board"][1]))
            square_mm = square_mm or float(spec["square_mm"])
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            raise InputFileError(spec_path, f"not a board description ({exc})") from None
    if rig is None:
        rig = load_rig(folder / "rig.toml")
    if "B" not in rig.camera_names:
        raise InputFileError(folder / "rig.toml", "a one-camera rig: there is no camera B to calibrate")
    cal = calibrate_rig_from_boards(folder, rig.camera_model("A"), rig.camera_model("B"), board, square_mm,
                                    refine_baseline=refine_baseline, detector=detector, rig_name=rig.name)
    cal.save(output)
    return cal
