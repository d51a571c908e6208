"""Camera B's mounting fitted to chessboard corners that both cameras see: a stereo calibration with the lenses fixed.

Why.  Calibrated from a session's own images (:mod:`omnispectral.product.rigfit`), B's pitch and
roll come out to a few thousandths of a degree, but its yaw cannot: along the epipolar lines a yaw
and a common depth move B's image alike, and the session fixes the yaw only as well as its farthest
content with edges across those lines is far (trees 30 m away leave 0.1° on the small rig; a clear
sky and a horizontal skyline give nothing).  A chessboard of known square size fixes the distance
of every corner, so yaw and depth separate: the approach of OpenCV's ``stereoCalibrate`` (Zhang
2000; Bouguet's Camera Calibration Toolbox), with both lenses held at the rig file's calibration and
B's rotation written as the rig's mounting (yaw, pitch, roll on top of the rig file's), optionally
its baseline too.  (The paper, Hirai et al. 2018, Sec. 4.3, registers B to A by one POC offset per
direction instead.)

Fit.  Per view ``k``, the board's pose ``(r_k, t_k)`` (Rodrigues vector, mm) in camera A's frame starts
from ``cv2.solvePnP`` on A's corners; then one robust least-squares problem (soft-L1, scale
:data:`CORNER_SCALE_PX`) over B's rotation change ``δ`` (and the baseline ``c``) and every pose minimises

.. math:: \\sum \\rho(r^2) \\text{ over every coordinate } r \\text{ of }
          \\pi_A(X_{kn}) - a_{kn} \\text{ and } \\pi_B(X_{kn}; \\delta, c) - b_{kn},
          \\qquad X_{kn} = H_0\\big(M_A\\,(R(r_k)\\,P_n + t_k) + c_A\\big),

``ρ`` the soft-L1 loss, ``P_n`` the board's corners (mm, :func:`~omnispectral.imaging.lens.board_object_points`),
``M_A`` and ``c_A`` camera A's mounting rotation and baseline (mm), ``H_0`` the head at pan = tilt = 0, ``a_kn``,
``b_kn`` the corners found (:mod:`omnispectral.product.boardcorners`), each camera projecting through its
own model (:meth:`~omnispectral.imaging.geometry.CameraModel.world_points_to_pixel`, head at
pan = tilt = 0; :func:`board_points_world_mm`).  OpenCV may number a board's corners from either end:
B's corners are taken in the order that fits A's pose (a view where neither is within
:data:`MAX_ORDER_MISMATCH` of the board's size is rejected).  The standard deviations come from the
Jacobian at the solution (``σ² (JᵀJ)⁻¹``, ``σ²`` the residual variance).
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from scipy.optimize import least_squares

from omnispectral.imaging.geometry import CameraModel, head_rotation
from omnispectral.imaging.lens import CalibrationError, board_object_points
from omnispectral.product.boardcorners import BoardPair
from omnispectral.product.pairgeometry import adjusted_model
from omnispectral.product.rigfile import RigCalibration

__all__ = ["CORNER_SCALE_PX", "MAX_ORDER_MISMATCH", "MIN_PAIRS", "board_points_world_mm",
           "fit_b_mounting_to_boards"]

#: Soft-L1 scale of the corner residuals (px).
CORNER_SCALE_PX = 0.5
#: A view whose B corners lie farther than this share of the board's size from where A's pose and the
#: rig file put them (in either corner order) is not the same board: rejected.
MAX_ORDER_MISMATCH = 0.25
#: Fewest pairs a calibration accepts.
MIN_PAIRS = 1


def _pose_in_a(model_a: CameraModel, obj_mm: np.ndarray, corners_px: np.ndarray) -> np.ndarray:
    """``(rvec, tvec_mm)`` of the board in camera A's frame from its corners (``cv2.solvePnP``)."""
    k, dist, _ = model_a.to_opencv()
    ok, rvec, tvec = cv2.solvePnP(obj_mm, corners_px.astype(np.float64), k, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise CalibrationError("cv2.solvePnP found no pose of the board in camera A's image")
    return np.concatenate([rvec.ravel(), tvec.ravel()])


def board_points_world_mm(model_a: CameraModel, obj_mm: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Board corners in the world frame at pan = tilt = 0 for board poses in camera A's frame.

    Parameters
    ----------
    model_a
        Camera A's model (its mounting on the head).
    obj_mm
        ``(N, 3)`` the board's corners in the board's frame (mm).
    poses
        ``(V, 6)`` per view the Rodrigues rotation vector (rad) and translation (mm) in A's frame.

    Returns
    -------
    numpy.ndarray
        ``(V, N, 3)`` corners in the world frame (mm).
    """
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
    """B's rotation change (and baseline) that reprojects every board into both cameras (module docstring).

    Parameters
    ----------
    pairs
        The views' corners in both cameras (:func:`~omnispectral.product.boardcorners.find_board_pairs`).
    model_a, model_b
        Camera A's and camera B's models (B: the rig file's, which ``δ`` is added to).
    board
        Inner corners ``(columns, rows)``.
    square_mm
        The board's square size (mm).
    refine_baseline
        Fit B's baseline (mm) too.
    rig_name
        The rig's name, recorded in the result.

    Returns
    -------
    RigCalibration
        ``method = "chessboard"``: B's absolute mounting, ``δ`` in degrees, B's corner RMS (px) and
        ``chessboard`` (board, views with their distance in m and RMS in px, ``std_deg``, rejected views).

    Raises
    ------
    CalibrationError
        No view left (fewer than :data:`MIN_PAIRS`), or no pose of the board in A's image.
    """
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
