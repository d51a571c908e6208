"""Camera B's mounting fitted to a session's block correspondences: a robust least-squares fit of its rotation.

A rig file states B's mounting (a small rotation and the baseline) only as well as it was measured;
a fraction of a degree of error moves B's image by pixels (11 px per 0.5° on the paper's 2048-px
sensor).  The paper registers B to A by one POC offset per direction (Hirai et al. 2018, Sec. 4.3); here
B's rotation is estimated once per session from every direction's block correspondences together
(:mod:`omnispectral.product.rigmeasure`), and depth is left to the per-pixel parallax
(:mod:`omnispectral.product.direction_parallax`).

Model.  ``q = π_B(R(δ)ᵀ (r_A(p) − w c))`` (:func:`~omnispectral.product.pairgeometry.predict_b_px`): A's ray
``r_A(p)``, B's optical centre ``c`` (the rig file's baseline, metres), the block's inverse depth ``w ≥ 0``
(1/m) and the unknown rotation change ``δ`` (yaw, pitch, roll in degrees, added to the rig file's
misalignment: :func:`~omnispectral.product.pairgeometry.adjusted_model`).  Depth moves ``q`` along the
epipolar direction ``g = ∂q/∂w`` only.  With the block's structure tensor ``J`` as the information of its
measured shift and ``r = q_measured − q̂(w = 0)``, the block's depth is ``w = gᵀJr / gᵀJg`` and its
perpendicular residual, which no depth explains, ``±√((r − w g)ᵀ J (r − w g))``.  Then

1. the perpendicular residuals fix ``δ`` whatever the depths (robust least squares, soft-L1 loss of scale
   :data:`ROBUST_SCALE_PX`, weighted by √confidence, so near objects' mismatches and false matches do not
   pull);
2. along ``g``, a rotation and a common depth are nearly indistinguishable; real points are never
   beyond infinity, so the farthest dense cluster of blocks is taken to be at infinity (``w = 0``):
   ``δ`` is corrected along ``g`` until that cluster's median sits at zero (a scene with nothing far,
   e.g. indoors, cannot anchor this: calibrate on an outdoor session and pass the file);
3. 1 and 2 alternate until ``δ`` changes by less than 10⁻⁴°.

Residuals per direction (median perpendicular residual, number of blocks) are kept in the
:class:`~omnispectral.product.rigfile.RigCalibration`; a direction whose perpendicular residual exceeds its
bound (:data:`~omnispectral.product.rigfile.DIRECTION_WARNING_PX`) is reported.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from omnispectral.imaging.geometry import CameraModel
from omnispectral.product.pairgeometry import adjusted_model, predict_b_px
from omnispectral.product.rigfile import RigCalibration
from omnispectral.product.rigmeasure import RigMeasurements

__all__ = ["ALONG_MIN_WEIGHT", "FAR_MIN_FRACTION", "FAR_WINDOW_PX", "MAX_DELTA_DEG", "MAX_INV_DEPTH_PER_M",
           "ROBUST_SCALE_PX", "fit_b_mounting"]

#: Soft-L1 scale of the perpendicular residuals (px).
ROBUST_SCALE_PX = 0.15
#: Half-width (px along the epipolar line) of the window that finds the far cluster.
FAR_WINDOW_PX = 0.25
#: Nearest plausible content (1/m): nothing the cameras register is closer than 0.33 m.
MAX_INV_DEPTH_PER_M = 3.0
#: Blocks whose structure measures the along-line shift at least this well (``gᵀJg/|g|²``) anchor infinity.
ALONG_MIN_WEIGHT = 0.3
#: Smallest share of the usable blocks that makes a cluster.
FAR_MIN_FRACTION = 0.15
#: Largest correction of the rig file's mounting, per angle (degrees): a rig file wrong by more is a wrong
#: rig file, and a fit on a scene that cannot anchor it (flat frames, a test pattern) stays inside this box.
MAX_DELTA_DEG = 5.0
#: Residual (px) given to a block the model cannot project into B during the fit (beyond the soft-L1 knee,
#: so it pulls as little as an outlier).
UNPROJECTABLE_RESIDUAL_PX = 10.0


def _epipolar(model_a, model_b, a_px, w) -> tuple[np.ndarray, np.ndarray]:
    """Predicted B pixel at ``w`` and the epipolar direction there (px per unit of inverse depth)."""
    q = predict_b_px(model_a, model_b, a_px, w)
    q2 = predict_b_px(model_a, model_b, a_px, w + 0.01)
    g = (q2 - q) / 0.01
    return q, g


def _split(meas: RigMeasurements, model_a, model_b) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per block, with the structure tensor ``J`` as the information of the measured shift:

    - ``w``: the inverse depth that best explains the residual ``r = q − q̂(w = 0)`` along the epipolar
      direction ``g`` in the ``J`` metric, ``w = gᵀJr / gᵀJg`` (unclamped);
    - ``along``: ``w · |g|``, the along-line residual in pixels;
    - ``perp``: the residual no depth can explain, ``±√((r − w g)ᵀ J (r − w g))`` (depth-independent;
      for an edge parallel to the line it is the shift across the edge, for an edge across the line 0);
    - ``along_weight``: ``gᵀJg / |g|²``, how well the block measures the along-line shift (0 for an edge
      parallel to the epipolar line).
    """
    q0, g = _epipolar(model_a, model_b, meas.a_px, 0.0)
    jxx, jxy, jyy = meas.tensor[:, 0], meas.tensor[:, 1], meas.tensor[:, 2]

    def jdot(x, y):
        return x[:, 0] * (jxx * y[:, 0] + jxy * y[:, 1]) + x[:, 1] * (jxy * y[:, 0] + jyy * y[:, 1])

    r = meas.b_px - q0
    gjg = jdot(g, g)
    # an edge almost parallel to the line would need an absurd depth to explain a shift across it
    w = np.clip(jdot(g, r) / np.maximum(gjg, 1e-12), -MAX_INV_DEPTH_PER_M, MAX_INV_DEPTH_PER_M)
    # second pass at the block's own depth (the line curves slightly over large parallax)
    qw, gw = _epipolar(model_a, model_b, meas.a_px, w)
    rw = meas.b_px - qw
    gjgw = jdot(gw, gw)
    w2 = np.clip(jdot(gw, rw) / np.maximum(gjgw, 1e-12), -MAX_INV_DEPTH_PER_M - w,
                 MAX_INV_DEPTH_PER_M - w)
    res = rw - w2[:, None] * gw
    gp = np.stack([-gw[:, 1], gw[:, 0]], axis=1)
    perp = np.sign(np.sum(res * gp, axis=1)) * np.sqrt(np.maximum(jdot(res, res), 0.0))
    glen2 = np.maximum(np.sum(g * g, axis=1), 1e-12)
    return w + w2, (w + w2) * np.sqrt(glen2), perp, gjg / glen2


def _far_cluster(along_px: np.ndarray, half_px: float, min_count: int) -> tuple[float, np.ndarray]:
    """Median of the lowest dense cluster of along-line residuals (the scene's farthest content)."""
    order = np.argsort(along_px)
    s = along_px[order]
    hi = np.searchsorted(s, s + 2 * half_px, side="right")
    counts = hi - np.arange(s.size)
    dense = np.flatnonzero(counts >= min_count)
    if dense.size == 0:
        return float("nan"), np.zeros(along_px.size, bool)
    i = int(dense[0])
    # centre the window on the cluster: take the densest window starting within the first one
    j = i + int(np.argmax(counts[i:hi[i]]))
    members = order[j:hi[j]]
    mask = np.zeros(along_px.size, bool)
    mask[members] = True
    return float(np.median(along_px[members])), mask


def _finite_blocks(meas: RigMeasurements, model_a: CameraModel, model_b: CameraModel) -> RigMeasurements:
    """The blocks whose residuals are finite under the rig file's mounting (all of them, the same object, when
    every one is): a flat or saturated image pair can give blocks the fit cannot use."""
    with np.errstate(invalid="ignore", divide="ignore"):
        _, along, perp, along_weight = _split(meas, model_a, model_b)
    ok = (np.isfinite(perp) & np.isfinite(along) & np.isfinite(along_weight) & np.isfinite(meas.confidence)
          & np.isfinite(meas.tensor).all(axis=1))
    return meas if ok.all() else meas.subset(ok)


def fit_b_mounting(meas: RigMeasurements, model_a: CameraModel, model_b: CameraModel, *, rig_name: str = "",
                   max_iter: int = 6) -> RigCalibration:
    """Estimate camera B's rotation change ``δ`` from pooled block correspondences (module docstring).

    Parameters
    ----------
    meas
        Every direction's block correspondences (:func:`~omnispectral.product.rigmeasure.measure_direction`).
    model_a, model_b
        Camera A's and camera B's models (B: the rig file's, which ``δ`` is added to).
    rig_name
        The rig's name, recorded in the result.
    max_iter
        Most alternations of the perpendicular fit and the far anchor (steps 1 and 2).

    Returns
    -------
    RigCalibration
        ``method = "scene"``: B's absolute mounting, ``δ`` in degrees, the inliers' RMS perpendicular
        residual (px), the far anchor and the per-direction residuals.  Blocks whose residual cannot be
        evaluated (a non-finite position or confidence, a point the rig model cannot project into B) are left
        out; fewer than 12 blocks leave ``δ = 0``.
    """
    delta = np.zeros(3)
    meas = _finite_blocks(meas, model_a, model_b)
    n = meas.a_px.shape[0]
    anchor = {"n_blocks": 0}
    if n < 12:
        return _result(meas, model_a, model_b, delta, np.ones(n, bool), anchor, rig_name)
    for _ in range(max_iter):
        previous = delta.copy()
        # 1. perpendicular residuals fix the rotation whatever the depths; yaw is held near its value
        yaw0 = delta[0]

        def residuals(x, yaw0=yaw0):
            with np.errstate(invalid="ignore", divide="ignore"):
                _, _, perp, _ = _split(meas, model_a, adjusted_model(model_b, x))
            perp = np.where(np.isfinite(perp), perp, UNPROJECTABLE_RESIDUAL_PX)
            return np.concatenate([perp * np.sqrt(meas.confidence), [10.0 * (x[0] - yaw0)]])

        sol = least_squares(residuals, delta, loss="soft_l1", f_scale=ROBUST_SCALE_PX, x_scale=0.05,
                            diff_step=1e-4, bounds=(-MAX_DELTA_DEG, MAX_DELTA_DEG))
        delta = sol.x
        # 2. the farthest dense cluster is at infinity: move the yaw along the lines until it sits at 0
        mb = adjusted_model(model_b, delta)
        _, along, perp, along_weight = _split(meas, model_a, mb)
        sigma = _robust_sigma(perp)
        usable = (along_weight >= ALONG_MIN_WEIGHT) & (np.abs(perp) <= max(3 * sigma, 0.2))
        # the window follows the measurement noise (estimated across the lines, where depth plays no part)
        far, members = _far_cluster(along[usable], max(FAR_WINDOW_PX, sigma),
                                    max(5, int(FAR_MIN_FRACTION * usable.sum())))
        if np.isfinite(far):
            idx = np.flatnonzero(usable)[members]
            eps = 1e-3
            nudged = adjusted_model(model_b, delta + np.array([eps, 0.0, 0.0]))
            _, along_eps, _, _ = _split(meas.subset(idx), model_a, nudged)
            slope = float(np.median((along_eps - along[idx]) / eps))  # px per degree of yaw
            if abs(slope) > 1e-6 and np.isfinite(slope):
                delta[0] = float(np.clip(delta[0] - far / slope, -MAX_DELTA_DEG, MAX_DELTA_DEG))
            anchor = {"n_blocks": int(idx.size), "offset_px_before": far,
                      "directions": sorted({int(d) for d in meas.direction[idx]})}
        if np.max(np.abs(delta - previous)) < 1e-4:
            break
    _, _, perp, _ = _split(meas, model_a, adjusted_model(model_b, delta))
    inlier = np.abs(perp) < max(3 * _robust_sigma(perp), 0.2)
    return _result(meas, model_a, model_b, delta, inlier, anchor, rig_name)


def _robust_sigma(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def _result(meas, model_a, model_b, delta, inlier, anchor, rig_name) -> RigCalibration:
    mb = adjusted_model(model_b, delta)
    perp = _split(meas, model_a, mb)[2] if meas.a_px.shape[0] else np.zeros(0)
    has = np.isfinite(perp)
    directions = []
    for d in sorted({int(x) for x in meas.direction}):
        sel = (meas.direction == d) & has
        directions.append({"direction": d, "n_blocks": int((meas.direction == d).sum()),
                           "n_inliers": int((sel & inlier).sum()),
                           "median_perpendicular_px": float(np.median(np.abs(perp[sel]))) if sel.any() else None})
    inlier = inlier & has
    rms = float(np.sqrt(np.mean(perp[inlier] ** 2))) if inlier.any() else float("nan")
    return RigCalibration(rig_name, mb.mounting.to_dict(), tuple(float(x) for x in delta), int(meas.a_px.shape[0]),
                          int(inlier.sum()), rms, anchor, directions)
