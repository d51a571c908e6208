"""Rig calibration: camera B's mounting relative to camera A, estimated from a session's own images.

A rig file states B's mounting (a small rotation and the baseline) only as well as it was measured;
a fraction of a degree of error moves B's image by pixels (11 px per 0.5° on the paper's 2048-px
sensor).  The paper registers B to A by one POC offset per direction (Sec. 4.3); here B's rotation
is estimated once per session from every direction together, and depth is left to the per-pixel
parallax (:mod:`omnispectral.imaging.disparity`).

Measurements.  Per direction, B's merged image is resampled onto A's grid for points at infinity with
the rig file's mounting (:func:`~omnispectral.product.align.warp_b_onto_a`) and registered block by
block (POC, :func:`~omnispectral.imaging.disparity.block_disparity`); a reliable block at A's
pixel ``p`` gives the B pixel ``q`` where B saw the same content.

Model.  ``q = π_B(R(δ)ᵀ (r_A(p) − w c))``: A's ray ``r_A(p)``, B's optical centre ``c`` (the rig file's
baseline, metres), the block's inverse depth ``w ≥ 0`` (1/m) and the unknown rotation change ``δ``
(yaw, pitch, roll in degrees, added to the rig file's misalignment).  Depth moves ``q`` along the
epipolar direction ``g = ∂q/∂w`` only, so

1. the parts of the residuals perpendicular to ``g`` fix ``δ`` whatever the depths (robust least
   squares, soft-L1 loss, so near objects' mismatches and false matches do not pull);
2. along ``g``, a rotation and a common depth are nearly indistinguishable; real points are never
   beyond infinity, so the farthest dense cluster of blocks is taken to be at infinity (``w = 0``):
   ``δ`` is corrected along ``g`` until that cluster's median sits at zero (a scene with nothing far,
   e.g. indoors, cannot anchor this: calibrate on an outdoor session and pass the file);
3. 1 and 2 alternate until ``δ`` changes by less than 10⁻⁴°.

Residuals per direction (median perpendicular residual, number of blocks) are kept; a direction
whose perpendicular residual exceeds its bound (:data:`DIRECTION_WARNING_PX`) is reported.
"""

from __future__ import annotations

import datetime as _dt
import json
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares

from omnispectral.capture.session import Session
from omnispectral.errors import InputFileError
from omnispectral.imaging.disparity import (
    CALIBRATION_ANALYSIS_PX,
    PARALLAX_MIN_CONFIDENCE,
    analysis_factor,
    bin_image,
    binned_to_full_px,
    block_size_for,
    measure_blocks,
)
from omnispectral.imaging.geometry import CameraModel, Mounting
from omnispectral.imaging.registration import as_gray
from omnispectral.io import atomic_write_json, read_text_file
from omnispectral.product.align import baseline_m, cached_maps, warp_b_onto_a
from omnispectral.product.merge import merge_session
from omnispectral.threads import ordered_thread_map

CALIBRATION_FORMAT = "omnispectral-rig-calibration"
#: A direction whose median perpendicular residual exceeds this (px) disagrees with the rig model.
DIRECTION_WARNING_PX = 0.5
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
#: A chessboard calibration whose B corners miss the fit by more than this RMS (px) is reported.
CHESSBOARD_WARNING_PX = 0.5


def predict_b_px(model_a: CameraModel, model_b: CameraModel, a_px: np.ndarray, inv_depth_per_m) -> np.ndarray:
    """Where B sees the content of A's pixels at inverse depth ``w`` (1/m; 0 = infinity), ``(n, 2)``."""
    rays, _ = model_a.pixel_to_world(a_px, 0.0, 0.0)
    w = np.broadcast_to(np.asarray(inv_depth_per_m, np.float64), rays.shape[:-1])
    px, _ = model_b.world_to_pixel(rays - w[..., None] * baseline_m(model_b), 0.0, 0.0, margin_px=None)
    return px


def adjusted_model(model_b: CameraModel, delta_deg) -> CameraModel:
    """Camera B with ``delta_deg`` (yaw, pitch, roll) added to its mounting's misalignment."""
    return replace(model_b, mounting=model_b.mounting.with_misalignment_change(delta_deg))


# ------------------------------------------------------------------------------------------ measurements
@dataclass
class RigMeasurements:
    """Block correspondences of all directions: A pixel, B pixel, confidence, direction index."""

    a_px: np.ndarray
    b_px: np.ndarray
    confidence: np.ndarray
    direction: np.ndarray
    #: the block's normalised structure tensor ``(jxx, jxy, jyy)``: how well each direction of the shift is
    #: measured (an edge measures only the shift across it: the aperture problem)
    tensor: np.ndarray

    @classmethod
    def empty(cls) -> RigMeasurements:
        return cls(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0, int), np.zeros((0, 3)))

    def extend(self, other: RigMeasurements) -> None:
        for name in ("a_px", "b_px", "confidence", "direction", "tensor"):
            setattr(self, name, np.concatenate([getattr(self, name), getattr(other, name)]))

    def subset(self, idx) -> RigMeasurements:
        return RigMeasurements(*(getattr(self, n)[idx] for n in ("a_px", "b_px", "confidence", "direction",
                                                                   "tensor")))


def measure_direction(direction: int, image_a: np.ndarray, image_b: np.ndarray, model_a: CameraModel,
                      model_b: CameraModel, min_confidence: float = PARALLAX_MIN_CONFIDENCE) -> RigMeasurements:
    """Reliable block correspondences (A pixel → B pixel) of one direction (module docstring)."""

    maps = cached_maps(model_a, model_b)
    warped, seen = warp_b_onto_a(image_b, maps)
    # large sensors are measured binned (a 2048-px image in 2 x 2 bins): the blocks then see as much of the
    # scene as on a 1024-px sensor, at a quarter of the cost; positions are brought back to full pixels
    f = analysis_factor(model_a.width, model_a.height, CALIBRATION_ANALYSIS_PX)
    block = block_size_for(model_a.width // f, model_a.height // f)
    # whole-vector outliers: the fit's far anchor is tuned on the blocks this rule keeps (the edge-aware
    # rule of the per-pixel parallax adds edge blocks that moved the anchor by pixels on one session)
    bs = measure_blocks(as_gray(bin_image(image_a, f)), as_gray(bin_image(warped, f)), block, min_confidence,
                        edge_aware=False)
    conf = bs.confidence
    gy, gx = np.meshgrid(binned_to_full_px(bs.y_px, f), binned_to_full_px(bs.x_px, f), indexing="ij")
    tx, ty = gx + bs.dx * f, gy + bs.dy * f
    ok = bs.reliable & _inside(seen, gx, gy, block * f) & _inside(seen, tx, ty, block * f)
    if not ok.any():
        return RigMeasurements.empty()
    a_px = np.stack([gx[ok], gy[ok]], axis=-1)
    tx, ty = tx[ok].astype(np.float32)[:, None], ty[ok].astype(np.float32)[:, None]
    mx = cv2.remap(maps[0], tx, ty, cv2.INTER_LINEAR).reshape(-1)
    my = cv2.remap(maps[1], tx, ty, cv2.INTER_LINEAR).reshape(-1)
    b_px = np.stack([mx, my], axis=-1).astype(np.float64)
    good = np.isfinite(b_px).all(axis=1) & (b_px > -1e5).all(axis=1)
    return RigMeasurements(a_px[good], b_px[good], conf[ok][good].astype(np.float64),
                           np.full(int(good.sum()), int(direction)), bs.tensor[ok][good])


def _inside(seen: np.ndarray, x: np.ndarray, y: np.ndarray, block: int) -> np.ndarray:
    h, w = seen.shape
    half = block / 2
    ok = (x - half >= 0) & (x + half <= w - 1) & (y - half >= 0) & (y + half <= h - 1)
    xi = np.clip(np.rint(x).astype(int), 0, w - 1)
    yi = np.clip(np.rint(y).astype(int), 0, h - 1)
    return ok & seen[yi, xi]


# ------------------------------------------------------------------------------------------ the fit
@dataclass
class RigCalibration:
    """The fitted mounting of camera B (absolute misalignment) and how well it fits."""

    rig_name: str
    mounting: dict
    delta_deg: tuple[float, float, float]
    n_blocks: int
    n_inliers: int
    rms_perpendicular_px: float
    far_anchor: dict
    directions: list[dict]
    source: str = ""
    created_utc: str = field(default_factory=lambda: _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"))
    #: ``"scene"`` (fitted from a session's blocks, this module) or ``"chessboard"`` (:mod:`.rigboard`)
    method: str = "scene"
    #: the chessboard fit's board, views, residuals and standard deviations (``method == "chessboard"``)
    chessboard: dict | None = None

    def apply(self, model_b: CameraModel) -> CameraModel:
        """Camera B's model with the calibrated mounting (lens unchanged)."""
        return replace(model_b, mounting=Mounting.from_dict(self.mounting))

    def infinity_std_px(self, model_b: CameraModel) -> float | None:
        """The standard deviation (px) of B's predicted position of points at infinity that the calibration
        states for itself (a chessboard fit's covariance, :mod:`.rigboard`): yaw and pitch move B's image
        by ``f · σ``, roll by up to the half-diagonal ``· σ``.  ``None`` when it states none (a session's
        blocks fix the yaw along the epipolar lines only to a few tenths of a pixel: module docstring)."""
        std = (self.chessboard or {}).get("std_deg")
        if not std:
            return None
        s = np.radians([float(std[k]) for k in ("yaw", "pitch", "roll")])
        half_diagonal_px = 0.5 * np.hypot(model_b.width, model_b.height)
        return float(np.hypot(model_b.fx * np.hypot(s[0], s[1]), half_diagonal_px * s[2]))

    def warnings(self) -> list[str]:
        out = [f"direction {d['direction']}: camera B disagrees with the rig model by "
               f"{d['median_perpendicular_px']:.2f} px across the epipolar lines (bound {DIRECTION_WARNING_PX} px)"
               for d in self.directions if d["median_perpendicular_px"] is not None
               and d["median_perpendicular_px"] > DIRECTION_WARNING_PX]
        if self.method == "scene" and self.far_anchor.get("n_blocks", 0) < 5:
            out.append("too few far blocks to fix camera B's yaw at infinity; the rig file's yaw was kept")
        if self.chessboard is not None and self.chessboard["rms_b_px"] > CHESSBOARD_WARNING_PX:
            out.append(f"camera B's chessboard corners miss the fitted rig by {self.chessboard['rms_b_px']:.2f} px RMS "
                       f"(bound {CHESSBOARD_WARNING_PX} px): check the pairs were taken at the same moment")
        return out

    def to_dict(self) -> dict:
        return {"format": CALIBRATION_FORMAT, "format_version": 1, "rig": self.rig_name,
                "created_utc": self.created_utc, "source": self.source, "method": self.method,
                **({"chessboard": self.chessboard} if self.chessboard is not None else {}),
                "camera_b_mounting": self.mounting, "delta_from_rig_file_deg":
                    dict(zip(("yaw", "pitch", "roll"), self.delta_deg, strict=True)),
                "n_blocks": self.n_blocks, "n_inliers": self.n_inliers,
                "rms_perpendicular_px": self.rms_perpendicular_px, "far_anchor": self.far_anchor,
                "directions": self.directions, "warnings": self.warnings()}

    def save(self, path: str | Path) -> Path:
        atomic_write_json(Path(path), self.to_dict())
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> RigCalibration:
        p = Path(path)
        try:
            data = json.loads(read_text_file(p, "rig calibration"))
        except ValueError as exc:
            raise InputFileError(p, f"not JSON ({exc})") from None
        if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
            found = data.get("format") if isinstance(data, dict) else None
            raise InputFileError(p, f"not a rig calibration (format {found!r})")
        try:
            return cls.from_dict(data, str(p))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputFileError(p, f"rig calibration is missing or has a bad {exc}") from None

    @classmethod
    def from_dict(cls, data: dict, source: str = "") -> RigCalibration:
        d = data["delta_from_rig_file_deg"]
        delta = (float(d["yaw"]), float(d["pitch"]), float(d["roll"]))
        return cls(data.get("rig", ""), data["camera_b_mounting"], delta,
                   int(data["n_blocks"]), int(data["n_inliers"]), float(data["rms_perpendicular_px"]),
                   data.get("far_anchor", {}), data.get("directions", []), source or data.get("source", ""),
                   data.get("created_utc", ""), data.get("method", "scene"), data.get("chessboard"))


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


def fit_b_mounting(meas: RigMeasurements, model_a: CameraModel, model_b: CameraModel, *, rig_name: str = "",
                   max_iter: int = 6) -> RigCalibration:
    """Estimate camera B's rotation change ``δ`` from pooled block correspondences (module docstring)."""
    n = meas.a_px.shape[0]
    delta = np.zeros(3)
    anchor = {"n_blocks": 0}
    if n < 12:
        return _result(meas, model_a, model_b, delta, np.ones(n, bool), anchor, rig_name)
    for _ in range(max_iter):
        previous = delta.copy()
        # 1. perpendicular residuals fix the rotation whatever the depths; yaw is held near its value
        yaw0 = delta[0]

        def residuals(x, yaw0=yaw0):
            _, _, perp, _ = _split(meas, model_a, adjusted_model(model_b, x))
            return np.concatenate([perp * np.sqrt(meas.confidence), [10.0 * (x[0] - yaw0)]])

        sol = least_squares(residuals, delta, loss="soft_l1", f_scale=ROBUST_SCALE_PX, x_scale=0.05,
                            diff_step=1e-4)
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
            if abs(slope) > 1e-6:
                delta[0] -= far / slope
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


def calibrate_from_merged(merged, progress=None) -> RigCalibration:
    """Rig calibration from a merged-directions directory (every direction's A and B images)."""
    model_a, model_b = merged.cameras["A"], merged.cameras["B"]
    meas = RigMeasurements.empty()
    sources = {(s.direction, s.camera): s for s in merged.sources()}
    dirs = [d for d in sorted({d for d, _ in sources}) if (d, "A") in sources and (d, "B") in sources]

    def measure(d: int) -> RigMeasurements:
        return measure_direction(d, sources[(d, "A")].read(), sources[(d, "B")].read(), model_a, model_b)

    for i, m in enumerate(ordered_thread_map(measure, dirs)):
        meas.extend(m)
        if progress is not None:
            progress(i + 1, len(dirs))
    return fit_b_mounting(meas, model_a, model_b, rig_name=merged.meta.get("rig", {}).get("name", ""))


def calibrate_session(session: str | Path, output: str | Path, work_dir: str | Path | None = None,
                      progress=None) -> RigCalibration:
    """Merge a session's brackets (into ``work_dir``, default a temporary directory) and fit camera B's
    mounting from them; saved to ``output`` (JSON) for ``process --rig-calibration``."""
    if "B" not in Session.open(session).cameras():
        raise InputFileError(session, "a one-camera session (three bands): there is no camera B to calibrate")
    with tempfile.TemporaryDirectory(prefix="omnispectral-rigcal-") as tmp:
        merged = merge_session(session, Path(work_dir) if work_dir else Path(tmp) / "merged",
                               progress=None if progress is None else (lambda i, n: progress("merge", i, n)))
        cal = calibrate_from_merged(merged, None if progress is None else (lambda i, n: progress("measure", i, n)))
    cal.source = str(Path(session).resolve())
    cal.save(output)
    return cal
