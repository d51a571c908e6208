"""Which calibration of camera B ``process`` uses, and how far off it may leave content at infinity.

Order (:func:`choose_rig_calibration`):

1. ``--rig-calibration FILE`` (``calibrate rig``), when given;
2. chessboard views that apply to the session (``SESSION/calibration/``, or the series' ``calibration/`` for a
   slot of a time-lapse: :func:`~omnispectral.capture.calviews.find_calibration_views`), fitted once
   (:mod:`omnispectral.product.rigboard`) and cached beside them in ``rig-calibration.json``, fingerprinted
   by the views (:func:`views_sha256`): a changed folder is fitted again;
3. the session's own images (:mod:`omnispectral.product.rigcal`, fitted during the registration).

How far off content at infinity may be, per direction (:func:`far_content_errors`).  A chessboard fit states
its own standard deviation at infinity (:meth:`~omnispectral.product.rigcal.RigCalibration.infinity_std_px`),
the same for every direction.  A fit on the session's images states none: it puts the scene's farthest dense
content at infinity, so B's model misses true infinity by that content's parallax.  Each direction measures,
on what it finds at infinity, the offset the model leaves there (``far_offset_measured_a_px``,
:mod:`omnispectral.product.align`), and applies it.  For points at infinity the A-to-B relation does not
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

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnispectral.capture.calviews import (
    BOARD_FILE,
    IMAGE_SUFFIXES,
    find_calibration_views,
    read_board_description,
)
from omnispectral.errors import InputFileError, OmnispectralError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.product.rigboard import calibrate_rig_from_boards
from omnispectral.product.rigcal import RigCalibration, predict_b_px
from omnispectral.rig import Rig, load_rig

#: The cached fit beside the views.
CACHE_FILE = "rig-calibration.json"
#: B at infinity the product aims at (px): a product whose far content may be off by more says so.
FAR_CONTENT_TARGET_PX = 0.1
#: Fewest directions with a measured offset at infinity that give the session fit's per-direction estimate.
MIN_MEASURED_DIRECTIONS = 3
#: What a fit on a session's images leaves of B's yaw when nothing measures it (deg; docs/benchmarks.md).
SCENE_FIT_YAW_DEG = 0.15
#: The directions' measured offsets at infinity along the epipolar line (lengths) at this percentile stand for
#: the model's offset there.
MODEL_ERROR_PERCENTILE = 90
#: What POC on a direction's far pixels measures at best (px; ``product.align.FAR_OFFSET_MIN_STD_PX``).
MEASUREMENT_FLOOR_PX = 0.05


@dataclass
class CalibrationSource:
    """Where camera B's calibration comes from (module docstring): ``kind`` ``"file"``, ``"chessboard-views"``
    or ``"session"`` (``calibration`` is then ``None``: fitted during the registration)."""

    kind: str
    path: str | None = None
    calibration: RigCalibration | None = None
    views_sha256: str | None = None
    #: the views' fit was read from the cache (``False``: fitted in this run)
    cached: bool = False
    fit_s: float = 0.0
    notes: list[str] = field(default_factory=list)
    #: why a ``"session"`` source has no better calibration
    why: str = "no chessboard views in SESSION/calibration/ and no --rig-calibration"

    def describe(self) -> str:
        """One line for a user: which calibration, from where."""
        if self.kind == "file":
            method = self.calibration.method if self.calibration is not None else "?"
            return f"camera B's mounting from --rig-calibration {self.path} ({method} fit)"
        if self.kind == "chessboard-views":
            n = (self.calibration.chessboard or {}).get("n_pairs", "?") if self.calibration is not None else "?"
            how = "cached fit" if self.cached else f"fitted in {self.fit_s:.1f} s"
            return f"camera B's mounting from {n} chessboard views in {self.path} ({how})"
        return f"camera B's mounting fitted from this session's own images ({self.why})"

    def to_dict(self) -> dict:
        return {"kind": self.kind, "path": self.path, "views_sha256": self.views_sha256, "cached": self.cached,
                "fit_s": self.fit_s, "description": self.describe(), "notes": list(self.notes)}


def view_files(folder: Path) -> list[Path]:
    """The views' files that determine the fit: ``rig.toml``, ``board.json`` and every image of ``A/`` and ``B/``."""
    images = sorted(p for c in ("A", "B") if (folder / c).is_dir() for p in (folder / c).iterdir()
                    if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    return [p for p in (folder / "rig.toml", folder / BOARD_FILE) if p.is_file()] + images


def views_sha256(folder: str | Path) -> str:
    """SHA-256 over the views' files (:func:`view_files`): their paths in the folder and their contents."""
    folder = Path(folder)
    h = hashlib.sha256()
    for p in view_files(folder):
        h.update(p.relative_to(folder).as_posix().encode() + b"\0")
        with open(p, "rb") as fh:
            for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def cached_views_calibration(folder: Path, sha: str) -> RigCalibration | None:
    """The cached fit of the views, if it was made from exactly these views (``None`` otherwise)."""
    path = folder / CACHE_FILE
    if not path.is_file():
        return None
    try:
        cal = RigCalibration.load(path)
    except InputFileError:
        return None  # a damaged cache is fitted again and rewritten
    return cal if (cal.chessboard or {}).get("views_sha256") == sha else None


def views_rig(folder: Path, session_rig: Rig) -> Rig:
    """The rig the views were taken with (``folder/rig.toml``), else the session's."""
    return load_rig(folder / "rig.toml") if (folder / "rig.toml").is_file() else session_rig


def fit_views(folder: Path, session_rig: Rig, sha: str) -> RigCalibration:
    """Fit camera B's mounting to the views (:func:`~omnispectral.product.rigboard.calibrate_rig_from_boards`)
    and cache it in ``folder/rig-calibration.json`` (not cached on a read-only folder)."""
    board, square_mm = read_board_description(folder)
    rig = views_rig(folder, session_rig)
    if "B" not in rig.camera_names:
        raise InputFileError(folder / "rig.toml", "a one-camera rig: there is no camera B to calibrate")
    cal = calibrate_rig_from_boards(folder, rig.camera_model("A"), rig.camera_model("B"), board, square_mm,
                                    rig_name=rig.name)
    cal.chessboard["views_sha256"] = sha
    try:
        cal.save(folder / CACHE_FILE)
    except OSError:
        pass  # a read-only session: the fit is used, and made again next time
    return cal


def choose_rig_calibration(session: str | Path, rig: Rig, rig_calibration: str | Path | None = None, *,
                           use_views: bool = True) -> CalibrationSource:
    """Camera B's calibration for a session (module docstring: file > chessboard views > the session's fit).

    Views that cannot be fitted (no board found, a bad ``board.json``) leave the session's fit, with a note
    naming the folder and why; ``use_views=False`` ignores them (``process --no-calibration-views``)."""
    if rig_calibration is not None:
        return CalibrationSource("file", str(rig_calibration), RigCalibration.load(rig_calibration))
    folder = find_calibration_views(session)
    if folder is None:
        return CalibrationSource("session")
    if not use_views:
        return CalibrationSource("session", why=f"--no-calibration-views: the views in {folder} not used")
    t0 = time.perf_counter()
    sha = views_sha256(folder)
    cal = cached_views_calibration(folder, sha)
    cached = cal is not None
    if cal is None:
        try:
            cal = fit_views(folder, rig, sha)
        except OmnispectralError as exc:
            return CalibrationSource("session", why=f"the views in {folder} could not be fitted",
                                     notes=[f"the chessboard views in {folder} could not be fitted, so camera B's "
                                            f"mounting was fitted from the session's own images: {exc}"])
    source = CalibrationSource("chessboard-views", str(folder), cal, sha, cached, time.perf_counter() - t0)
    if cal.rig_name and cal.rig_name != rig.name:
        source.notes.append(f"the views in {folder} were taken with rig {cal.rig_name!r}, the session with "
                            f"{rig.name!r}")
    return source


# ------------------------------------------------------------------------------------------ far content
def epipolar_direction(model_a: CameraModel, model_b: CameraModel) -> np.ndarray:
    """Unit vector along which depth moves B's image at the centre of A's sensor (the epipolar line there)."""
    centre = np.array([[(model_a.width - 1) / 2.0, (model_a.height - 1) / 2.0]])
    g = (predict_b_px(model_a, model_b, centre, 0.01) - predict_b_px(model_a, model_b, centre, 0.0))[0]
    return g / max(float(np.linalg.norm(g)), 1e-12)


def model_offset_at_infinity_px(directions: list[dict], along: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """``(E, s, n)``: the model's offset at infinity as the directions measured it on their far content, their
    noise across the epipolar line ``along`` and how many measured one (module docstring); ``None`` with fewer
    than :data:`MIN_MEASURED_DIRECTIONS`."""
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
    """Per direction, how far off (px) content at infinity may be in the product (module docstring; ``model_b``
    the calibrated camera B); returns ``{"per_direction": {direction: px}, "basis": text, ...}``."""
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
    """One line when far content may be off by more than :data:`FAR_CONTENT_TARGET_PX` in some direction."""
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
