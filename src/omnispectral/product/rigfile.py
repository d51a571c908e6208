"""The rig calibration file: camera B's fitted mounting relative to camera A, as JSON, and how well it fits.

The paper registers camera B to camera A by one POC offset per direction (Hirai et al. 2018, Sec. 4.3);
here B's mounting (a small rotation and the baseline) is calibrated once, either from a session's own
images (:mod:`omnispectral.product.rigfit`, ``method = "scene"``) or from chessboard pairs
(:mod:`omnispectral.product.boardfit`, ``method = "chessboard"``).  Both give a :class:`RigCalibration`,
written by ``calibrate rig`` and read by ``process --rig-calibration`` and the cache of calibration views
(:mod:`omnispectral.product.rigsource`).

Format (``format = "omnispectral-rig-calibration"``, ``format_version = 1``), one JSON object:

- ``rig``, ``created_utc``, ``source`` (the session or folder it was fitted from), ``method``;
- ``camera_b_mounting``: the absolute mounting (:meth:`~omnispectral.imaging.geometry.Mounting.to_dict`),
  and ``delta_from_rig_file_deg`` (yaw, pitch, roll: the fitted change ``δ`` on top of the rig file's);
- ``n_blocks``, ``n_inliers``, ``rms_perpendicular_px``, ``far_anchor``, ``directions``: the scene fit's
  residuals (a chessboard fit counts corners and gives B's corner RMS);
- ``chessboard`` (chessboard fits only): board, views, residuals and standard deviations ``std_deg``;
- ``warnings``: :meth:`RigCalibration.warnings` when written (not read back).

A calibration that states standard deviations (a chessboard fit) gives its uncertainty at infinity,
``σ_∞ = hypot(f · hypot(σ_yaw, σ_pitch), d/2 · σ_roll)`` px (``f`` B's focal length in px, ``d`` its
sensor diagonal in px, angles in radians): :meth:`RigCalibration.infinity_std_px`.
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.imaging.geometry import CameraModel, Mounting
from omnispectral.io import atomic_write_json, read_text_file

__all__ = ["CALIBRATION_FORMAT", "CHESSBOARD_WARNING_PX", "DIRECTION_WARNING_PX", "RigCalibration"]

CALIBRATION_FORMAT = "omnispectral-rig-calibration"
#: A direction whose median perpendicular residual exceeds this (px) disagrees with the rig model.
DIRECTION_WARNING_PX = 0.5
#: A chessboard calibration whose B corners miss the fit by more than this RMS (px) is reported.
CHESSBOARD_WARNING_PX = 0.5


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
    #: ``"scene"`` (fitted from a session's blocks, :mod:`.rigfit`) or ``"chessboard"`` (:mod:`.boardfit`)
    method: str = "scene"
    #: the chessboard fit's board, views, residuals and standard deviations (``method == "chessboard"``)
    chessboard: dict | None = None

    def apply(self, model_b: CameraModel) -> CameraModel:
        """Camera B's model with the calibrated mounting (lens unchanged).

        Parameters
        ----------
        model_b
            Camera B's model (the rig file's).

        Returns
        -------
        CameraModel
            The model with this calibration's mounting.
        """
        return replace(model_b, mounting=Mounting.from_dict(self.mounting))

    def infinity_std_px(self, model_b: CameraModel) -> float | None:
        """The standard deviation (px) of B's predicted position of points at infinity that the calibration
        states for itself (a chessboard fit's covariance, :mod:`.boardfit`): yaw and pitch move B's image
        by ``f · σ``, roll by up to the half-diagonal ``· σ``.  ``None`` when it states none (a session's
        blocks fix the yaw along the epipolar lines only to a few tenths of a pixel: :mod:`.rigfit`).

        Parameters
        ----------
        model_b
            Camera B's model (its focal length and sensor size in px).

        Returns
        -------
        float or None
            ``σ_∞`` in px (module docstring), or ``None``.
        """
        std = (self.chessboard or {}).get("std_deg")
        if not std:
            return None
        s = np.radians([float(std[k]) for k in ("yaw", "pitch", "roll")])
        half_diagonal_px = 0.5 * np.hypot(model_b.width, model_b.height)
        return float(np.hypot(model_b.fx * np.hypot(s[0], s[1]), half_diagonal_px * s[2]))

    def warnings(self) -> list[str]:
        """What a user should know about the fit.

        Returns
        -------
        list of str
            Directions beyond :data:`DIRECTION_WARNING_PX`, a scene fit with too few far blocks, a chessboard
            fit beyond :data:`CHESSBOARD_WARNING_PX`.
        """
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
        """The file's JSON object (module docstring).

        Returns
        -------
        dict
            JSON-serialisable; its key order is the file's.
        """
        return {"format": CALIBRATION_FORMAT, "format_version": 1, "rig": self.rig_name,
                "created_utc": self.created_utc, "source": self.source, "method": self.method,
                **({"chessboard": self.chessboard} if self.chessboard is not None else {}),
                "camera_b_mounting": self.mounting, "delta_from_rig_file_deg":
                    dict(zip(("yaw", "pitch", "roll"), self.delta_deg, strict=True)),
                "n_blocks": self.n_blocks, "n_inliers": self.n_inliers,
                "rms_perpendicular_px": self.rms_perpendicular_px, "far_anchor": self.far_anchor,
                "directions": self.directions, "warnings": self.warnings()}

    def save(self, path: str | Path) -> Path:
        """Write the file atomically (:func:`~omnispectral.io.atomic_write_json`).

        Parameters
        ----------
        path
            The JSON file to write.

        Returns
        -------
        pathlib.Path
            ``path``.
        """
        atomic_write_json(Path(path), self.to_dict())
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> RigCalibration:
        """Read a rig calibration file.

        Parameters
        ----------
        path
            The JSON file (``calibrate rig``'s output or a views' cache).

        Returns
        -------
        RigCalibration
            The calibration, ``source`` set to ``path``.

        Raises
        ------
        InputFileError
            Not JSON, not a rig calibration, or a field missing or bad.
        """
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
        """The calibration of a file's JSON object (:meth:`to_dict`).

        Parameters
        ----------
        data
            The JSON object.
        source
            Where it was read from (default: the object's ``source``).

        Returns
        -------
        RigCalibration
            The calibration.
        """
        d = data["delta_from_rig_file_deg"]
        delta = (float(d["yaw"]), float(d["pitch"]), float(d["roll"]))
        return cls(data.get("rig", ""), data["camera_b_mounting"], delta,
                   int(data["n_blocks"]), int(data["n_inliers"]), float(data["rms_perpendicular_px"]),
                   data.get("far_anchor", {}), data.get("directions", []), source or data.get("source", ""),
                   data.get("created_utc", ""), data.get("method", "scene"), data.get("chessboard"))
