"""Which calibration of camera B ``process`` uses: a file, the session's chessboard views, or the session.

Order (:func:`choose_rig_calibration`):

1. ``--rig-calibration FILE`` (``calibrate rig``), when given;
2. chessboard views that apply to the session (``SESSION/calibration/``, or the series' ``calibration/`` for a
   slot of a time-lapse: :func:`~omnispectral.capture.calviews.find_calibration_views`), fitted once
   (:mod:`omnispectral.product.rigboard`) and cached beside them in ``rig-calibration.json``, fingerprinted
   by the views (:func:`views_sha256`): a changed folder is fitted again;
3. the session's own images (:mod:`omnispectral.product.rigfit`, fitted during the registration).

Every source gives a :class:`~omnispectral.product.rigfile.RigCalibration`; how far off it may leave content at
infinity is :mod:`omnispectral.product.far_content`'s.  The paper (Hirai et al. 2018, Sec. 4.3) has no
calibration of camera B: it registers B to A by one POC offset per direction.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

from omnispectral.capture.calviews import (
    BOARD_FILE,
    IMAGE_SUFFIXES,
    find_calibration_views,
    read_board_description,
)
from omnispectral.errors import InputFileError, OmnispectralError
from omnispectral.product.rigboard import calibrate_rig_from_boards
from omnispectral.product.rigfile import RigCalibration
from omnispectral.rig import Rig, load_rig

__all__ = ["CACHE_FILE", "CalibrationSource", "cached_views_calibration", "choose_rig_calibration", "fit_views",
           "view_files", "views_rig", "views_sha256"]

#: The cached fit beside the views.
CACHE_FILE = "rig-calibration.json"


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
        """The source as written in ``product.json`` (``registration.rig_calibration_source``)."""
        return {"kind": self.kind, "path": self.path, "views_sha256": self.views_sha256, "cached": self.cached,
                "fit_s": self.fit_s, "description": self.describe(), "notes": list(self.notes)}


def view_files(folder: Path) -> list[Path]:
    """The views' files that determine the fit: ``rig.toml``, ``board.json`` and every image of ``A/`` and ``B/``.

    Parameters
    ----------
    folder
        The calibration views' folder.

    Returns
    -------
    list of pathlib.Path
        The files present, ``rig.toml`` and ``board.json`` first, then the images sorted.
    """
    images = sorted(p for c in ("A", "B") if (folder / c).is_dir() for p in (folder / c).iterdir()
                    if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    return [p for p in (folder / "rig.toml", folder / BOARD_FILE) if p.is_file()] + images


def views_sha256(folder: str | Path) -> str:
    """SHA-256 over the views' files (:func:`view_files`): their paths in the folder and their contents.

    Parameters
    ----------
    folder
        The calibration views' folder.

    Returns
    -------
    str
        The hex digest.
    """
    folder = Path(folder)
    h = hashlib.sha256()
    for p in view_files(folder):
        h.update(p.relative_to(folder).as_posix().encode() + b"\0")
        with open(p, "rb") as fh:
            for block in iter(lambda fh=fh: fh.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()


def cached_views_calibration(folder: Path, sha: str) -> RigCalibration | None:
    """The cached fit of the views, if it was made from exactly these views (``None`` otherwise).

    Parameters
    ----------
    folder
        The calibration views' folder (the cache is ``folder/rig-calibration.json``).
    sha
        The views' :func:`views_sha256`.

    Returns
    -------
    RigCalibration or None
        The cached fit; ``None`` when missing, damaged or made from other views.
    """
    path = folder / CACHE_FILE
    if not path.is_file():
        return None
    try:
        cal = RigCalibration.load(path)
    except InputFileError:
        return None  # a damaged cache is fitted again and rewritten
    return cal if (cal.chessboard or {}).get("views_sha256") == sha else None


def views_rig(folder: Path, session_rig: Rig) -> Rig:
    """The rig the views were taken with (``folder/rig.toml``), else the session's.

    Parameters
    ----------
    folder
        The calibration views' folder.
    session_rig
        The session's rig.

    Returns
    -------
    Rig
        The views' rig.
    """
    return load_rig(folder / "rig.toml") if (folder / "rig.toml").is_file() else session_rig


def fit_views(folder: Path, session_rig: Rig, sha: str) -> RigCalibration:
    """Fit camera B's mounting to the views (:func:`~omnispectral.product.rigboard.calibrate_rig_from_boards`)
    and cache it in ``folder/rig-calibration.json`` (not cached on a read-only folder).

    Parameters
    ----------
    folder
        The calibration views' folder (``A/``, ``B/``, ``board.json``, optionally ``rig.toml``).
    session_rig
        The session's rig (used when the folder has no ``rig.toml``).
    sha
        The views' :func:`views_sha256`, recorded in the fit's ``chessboard.views_sha256``.

    Returns
    -------
    RigCalibration
        The chessboard fit.

    Raises
    ------
    OmnispectralError
        A bad board description, a one-camera rig, or no board to fit.
    """
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
    naming the folder and why; ``use_views=False`` ignores them (``process --no-calibration-views``).

    Parameters
    ----------
    session
        The session directory.
    rig
        The session's rig.
    rig_calibration
        ``--rig-calibration FILE``, or ``None``.
    use_views
        Use the chessboard views that apply to the session.

    Returns
    -------
    CalibrationSource
        The choice; its ``calibration`` is ``None`` for ``"session"`` (fitted during the registration).
    """
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
