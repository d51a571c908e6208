"""How far off content at infinity may be in the product, per direction, for the rig calibration used.

Beyond the paper: Hirai et al. (2018, Sec. 4.3) register camera B to camera A by one POC offset per
direction; here B's model is calibrated (:mod:`omnispectral.product.rigsource` says which calibration) and
each direction measures the offset the model still leaves at infinity
(:func:`~omnispectral.product.direction_parallax.far_offset`).  This module states the error bound that leaves.

Per direction (:func:`far_content_errors`): a chessboard fit states
its own standard deviation at infinity (:meth:`~omnispectral.product.rigfile.RigCalibration.infinity_std_px`),
the same for every direction.  A fit on the session's images states none: it puts the scene's farthest dense
content at infinity, so B's model misses true infinity by that content's parallax.  Each direction measures,
on what it finds at infinity, the offset the model leaves there (``far_offset_measured_a_px``,
:mod:`omnispectral.product.direction_parallax`), and applies it.  For points at infinity the A-to-B relation does not
depend on the head's direction, yet along the epipolar line ``ĝ`` (where the fit's yaw is uncertain; across
it the fit is good to hundredths of a pixel) the measurements range from about 0 (content as far as the fit's
anchor: the hills) to the model's whole error (sky, clouds, the sun).  The model's offset at infinity is
taken at that far end, ``E = e ĝ`` with ``e`` the along-line measurement at the
:data:`MODEL_ERROR_PERCENTILE` th percentile of their lengths (one false peak does not set it); the
measurements' median part across the line, ``s`` (at least :data:`MEASUREMENT_FLOOR_PX`), is their noise.  A
direction that applied its own measurement ``v`` may be off by ``|v − E| + s``, one that measured nothing by
``|e| + s``.  Against the simulator's truth (the median over the sensor of each direction's error at infinity,
docs/benchmarks.md): on the demo's session (small rig) 0.13–0.74 px stated where the product is 0.13–0.55 px
off, 0.64 where a direction measured nothing and is 0.45 off; at full scale 0.09–2.45 px stated where it is
0.11–2.26 px off, 1.91 where it is 1.73 (the median of the measurements said 0.01: most directions' far content
is the anchor's).  The sensor's corners may be a few tenths of a pixel further off than the median (B's roll
error is not one offset).  With fewer than :data:`MIN_MEASURED_DIRECTIONS` measurements,
:data:`SCENE_FIT_YAW_DEG` at the sensor's focal length is stated instead (what the benchmarks found such a
fit's yaw to miss by).
"""

from __future__ import annotations

import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.product.pairgeometry import epipolar_direction
from omnispectral.product.rigfile import RigCalibration
from omnispectral.product.rigsource import CalibrationSource

__all__ = ["FAR_CONTENT_TARGET_PX", "MEASUREMENT_FLOOR_PX", "MIN_MEASURED_DIRECTIONS", "MODEL_ERROR_PERCENTILE",
           "SCENE_FIT_YAW_DEG", "far_content_errors", "far_content_warning", "model_offset_at_infinity_px"]

#: B at infinity the product aims at (px): a product whose far content may be off by more says so.
FAR_CONTENT_TARGET_PX = 0.1
#: Fewest directions with a measured offset at infinity that give the session fit's per-direction estimate.
MIN_MEASURED_DIRECTIONS = 3
#: What a fit on a session's images leaves of B's yaw when nothing measures it (deg; docs/benchmarks.md).
SCENE_FIT_YAW_DEG = 0.15
#: The directions' measured offsets at infinity along the epipolar line (lengths) at this percentile stand for
#: the model's offset there.
MODEL_ERROR_PERCENTILE = 90
#: What POC on a direction's far pixels measures at best (px; ``product.direction_parallax.FAR_OFFSET_MIN_STD_PX``).
MEASUREMENT_FLOOR_PX = 0.05


def model_offset_at_infinity_px(directions: list[dict], along: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """``(E, s, n)``: the model's offset at infinity as the directions measured it on their far content, their
    noise across the epipolar line ``along`` and how many measured one (module docstring); ``None`` with fewer
    than :data:`MIN_MEASURED_DIRECTIONS`.

    Parameters
    ----------
    directions
        Each direction's statistics with ``far_offset_measured_a_px`` (A's px; zero: not measured).
    along
        ``(2,)`` unit vector along the epipolar line (:func:`~omnispectral.product.pairgeometry.epipolar_direction`).

    Returns
    -------
    tuple or None
        ``(E, s, n)``: ``E`` ``(2,)`` px, ``s`` px, ``n`` the number of directions that measured an offset.
    """
    measured = np.array([d["far_offset_measured_a_px"] for d in directions
                         if any(abs(x) > 0 for x in d.get("far_offset_measured_a_px") or (0.0, 0.0))], np.float64)
    n = measured.shape[0]
    if n < MIN_MEASURED_DIRECTIONS:
        return None
    e = measured @ along
    across = measured @ np.array([-along[1], along[0]])
    far_end = e[np.argsort(np.abs(e))[round(MODEL_ERROR_PERCENTILE / 100.0 * (n - 1))]]
    return far_end * along, max(float(np.median(np.abs(across))), MEASUREMENT_FLOOR_PX), int(n)


def far_content_errors(calibration: RigCalibration, directions: list[dict], model_a: CameraModel,
                       model_b: CameraModel) -> dict:
    """Per direction, how far off (px) content at infinity may be in the product (module docstring).

    Parameters
    ----------
    calibration
        The rig calibration used.
    directions
        Each direction's statistics (``direction``, ``far_offset_px``, ``far_offset_measured_a_px``).
    model_a, model_b
        Camera A's model and the calibrated camera B.

    Returns
    -------
    dict
        ``{"per_direction": {direction: px}, "basis": text, ...}`` with ``stated_std_px`` (a stated standard
        deviation) or ``model_offset_at_infinity_px``, ``noise_px`` and ``n_measured``.
    """
    std = calibration.infinity_std_px(model_b)
    if std is not None:
        return {"per_direction": {int(d["direction"]): std for d in directions}, "stated_std_px": std,
                "basis": "the chessboard fit's standard deviation at infinity"}
    measured = model_offset_at_infinity_px(directions, epipolar_direction(model_a, model_b))
    if measured is None:
        guess = float(np.radians(SCENE_FIT_YAW_DEG) * model_b.fx)
        return {"per_direction": {int(d["direction"]): guess for d in directions},
                "basis": f"too few directions measured their offset at infinity: what a fit on a session's own "
                         f"images typically leaves ({SCENE_FIT_YAW_DEG}° of yaw)"}
    e, s, n = measured
    per = {}
    for d in directions:
        applied = any(abs(x) > 0 for x in d.get("far_offset_px") or (0.0, 0.0))
        v = np.asarray(d.get("far_offset_measured_a_px") or (0.0, 0.0), np.float64)
        per[int(d["direction"])] = float(np.linalg.norm(v - e if applied else e) + s)
    return {"per_direction": per, "model_offset_at_infinity_px": [float(x) for x in e], "noise_px": s,
            "n_measured": n, "basis": f"the model's offset at infinity along the epipolar lines as the farthest "
                                      f"content of {n} directions measured it ({MODEL_ERROR_PERCENTILE}th "
                                      f"percentile), less what each direction applied, plus their noise"}


def far_content_warning(source: CalibrationSource, far: dict) -> str | None:
    """One line when far content may be off by more than :data:`FAR_CONTENT_TARGET_PX` in some direction.

    Parameters
    ----------
    source
        Where the calibration came from (:func:`~omnispectral.product.rigsource.choose_rig_calibration`).
    far
        :func:`far_content_errors`'s result.

    Returns
    -------
    str or None
        The warning, with what to do about it; ``None`` when every direction is within the target.
    """
    per = far["per_direction"]
    if not per:
        return None
    worst = max(per, key=per.get)
    if per[worst] <= FAR_CONTENT_TARGET_PX:
        return None
    values = np.array(list(per.values()))
    fix = ("" if source.kind == "chessboard-views" else
           ". Record chessboard views once per mounting of the cameras ('omnispectral capture calibration-views "
           "-o SESSION') or pass --rig-calibration FILE")
    return (f"far content may be off by up to {per[worst]:.2f} px (direction {worst}; {values.min():.2f}-"
            f"{values.max():.2f} px per direction, median {np.median(values):.2f}: product.json "
            f"registration.directions[].far_content_error_px): {source.describe()}{fix}")
