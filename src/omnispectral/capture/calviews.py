"""Calibration views: chessboard pairs both cameras take once per mounting (``capture calibration-views``).

Camera B's mounting relative to A fixes where B sees content at infinity.  Fitted from a session's own
images, B's yaw is only as good as the scene's farthest content is far (``product.rigfit``); a board of
known square size, seen by both cameras at once at a few poses, fixes it to a few hundredths of a pixel
(``product.rigboard``).  The views are taken once per mounting of the cameras: a session records them
in ``SESSION/calibration/``, a time-lapse once for the whole series in ``SERIES/calibration/``, and
``process`` finds them there (:func:`find_calibration_views`).

Layout (what ``calibrate rig --chessboard`` reads; every file written atomically)::

    DIR/calibration/rig.toml           the rig the views were taken with
    DIR/calibration/board.json         the board: inner corners, square side (mm)
    DIR/calibration/A/view_00.tif …    camera A, 16-bit RGB (a raw Bayer frame is demosaiced)
    DIR/calibration/B/view_00.tif …    camera B, same names: a pair per name
    DIR/calibration/capture.json       how they were taken (exposures, times, board found), written last

:func:`record_calibration_views` is the loop on the rig's cameras (real or simulated ones): before each
shot it calls ``next_view`` (the command line asks the operator to move the board and press Enter, or
waits an interval), triggers both cameras, and keeps the pair only if both cameras see the whole board;
otherwise the operator is asked again.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
import tifffile

from omnispectral.capture.devices import Camera, Clock, DeviceError, SystemClock
from omnispectral.capture.session import CALIBRATION_DIR, utc_now_iso
from omnispectral.choices import DEFAULT_N_VIEWS
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.bayer import demosaic
from omnispectral.imaging.lens import check_board, find_board
from omnispectral.io import atomic_path, atomic_write_json, atomic_write_text, read_text_file
from omnispectral.locking import directory_lock
from omnispectral.ownership import claim_output_directory
from omnispectral.progress import ProgressCallback
from omnispectral.rig import Rig, rig_toml

__all__ = ["AUTO_EXPOSURE_TARGET", "BOARD_FILE", "BOARD_FORMAT", "CAPTURE_FILE", "DEFAULT_N_VIEWS", "IMAGE_SUFFIXES",
           "MAX_ATTEMPTS_PER_VIEW", "NextView", "auto_exposure_s", "board_problem", "calibration_folder",
           "clear_views", "find_calibration_views", "gray8", "has_views", "operator_next_view",
           "read_board_description", "record_calibration_views", "rgb_frame", "shoot_pair", "view_name",
           "write_board_description"]

BOARD_FILE = "board.json"
#: Image files a views folder may hold (``calibrate rig --chessboard`` reads any of them).
IMAGE_SUFFIXES = (".tif", ".tiff", ".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".exr")
BOARD_FORMAT = "omnispectral-chessboard-views"
CAPTURE_FILE = "capture.json"
#: The brightest 1 % of an auto-exposed calibration frame sits at this share of full scale.
AUTO_EXPOSURE_TARGET = 0.6
#: A view is asked for again at most this many times per view requested before the capture gives up.
MAX_ATTEMPTS_PER_VIEW = 3

#: ``next_view(k, n, problem)``: get the board into its next pose for view ``k`` of ``n`` (``problem``: why
#: the previous shot was not kept, or ``None``) and return once it is there.
NextView = Callable[[int, int, str | None], None]


def calibration_folder(root: str | Path) -> Path:
    """``ROOT/calibration``: where a session or a series keeps its calibration views."""
    return Path(root) / CALIBRATION_DIR


def view_name(k: int) -> str:
    """File name of the ``k``-th pair (the same in ``A/`` and ``B/``)."""
    return f"view_{k:02d}.tif"


def has_views(folder: str | Path) -> bool:
    """``folder`` holds chessboard pairs to calibrate from: ``A/`` and ``B/`` with images, and ``board.json``."""
    folder = Path(folder)
    return (folder / BOARD_FILE).is_file() and all(
        (folder / c).is_dir() and any(p.suffix.lower() in IMAGE_SUFFIXES for p in (folder / c).iterdir())
        for c in ("A", "B"))


def find_calibration_views(session: str | Path) -> Path | None:
    """The calibration views that apply to a session: its own ``calibration/``, else, for a slot of a
    time-lapse (its parent holds ``series.json``), the series' ``calibration/``; ``None`` when there are none."""
    session = Path(session)
    own = calibration_folder(session)
    if has_views(own):
        return own
    parent = session.resolve().parent
    if (parent / "series.json").is_file() and has_views(calibration_folder(parent)):
        return calibration_folder(parent)
    return None


def clear_views(folder: str | Path) -> list[Path]:
    """Remove the pairs and the record of earlier views from ``folder`` (views are taken again when the cameras
    were mounted again: old and new pairs must not mix); returns what was removed."""
    folder = claim_output_directory(folder, "calibration views")  # a user's folder: refused, nothing removed
    old = [p for c in ("A", "B") if (folder / c).is_dir() for p in (folder / c).iterdir()
           if p.suffix.lower() in IMAGE_SUFFIXES]
    old += [p for p in (folder / CAPTURE_FILE, folder / "ground_truth" / "views.json") if p.is_file()]
    for p in old:
        p.unlink()
    return old


def write_board_description(folder: str | Path, board: tuple[int, int], square_mm: float) -> Path:
    """``folder/board.json``: the board's inner corners and square side, what the fit needs to know."""
    spec = {"format": BOARD_FORMAT, "board": [int(board[0]), int(board[1])], "square_mm": float(square_mm)}
    return atomic_write_json(Path(folder) / BOARD_FILE, spec)


def read_board_description(folder: str | Path) -> tuple[tuple[int, int], float]:
    """``(board, square_mm)`` from ``folder/board.json``; a bad file is an error naming it."""
    path = Path(folder) / BOARD_FILE
    try:
        spec = json.loads(read_text_file(path, "board description"))
        board, square_mm = (int(spec["board"][0]), int(spec["board"][1])), float(spec["square_mm"])
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise InputFileError(path, f"not a board description ({exc})") from None
    if not square_mm > 0:
        raise InputFileError(path, f"square_mm must be positive, got {square_mm}")
    return board, square_mm


def rgb_frame(frame: np.ndarray, cfa_pattern: str | None) -> np.ndarray:
    """A camera's frame as 16-bit RGB: a raw Bayer mosaic ``(H, W)`` is demosaiced (OpenCV's edge-aware
    method; the views serve geometry, not radiometry), an RGB frame is kept."""
    if frame.ndim == 2 and cfa_pattern:
        return np.clip(np.rint(demosaic(frame.astype(np.uint16), cfa_pattern, "opencv-ea")), 0, 65535).astype(np.uint16)
    return np.asarray(frame, np.uint16)


def gray8(frame: np.ndarray, max_dn: float) -> np.ndarray:
    """8-bit grey of a 16-bit RGB frame, full scale at the frame's brightest 0.1 % (for the board's detection)."""
    f = frame.astype(np.float32)
    grey = f.mean(axis=2) if f.ndim == 3 else f
    top = max(float(np.percentile(grey, 99.9)), 1.0)
    return np.clip(grey * (255.0 / min(top, max_dn)), 0, 255).astype(np.uint8)


def shoot_pair(cameras: dict[str, Camera], timeout_s: float) -> dict[str, tuple[np.ndarray, dict]]:
    """Trigger every camera (both before reading either: the pair shows one moment) and read their frames."""
    for name in sorted(cameras):
        cameras[name].trigger()
    return {name: cameras[name].read_frame(timeout_s) for name in sorted(cameras)}


def auto_exposure_s(camera: Camera, start_s: float, max_dn: float, timeout_s: float,
                    target: float = AUTO_EXPOSURE_TARGET, iterations: int = 4) -> float:
    """The exposure (s) that puts the frame's brightest 1 % at ``target`` of full scale, from trial frames
    starting at ``start_s`` (a clipped trial divides the exposure by 4)."""
    exposure = float(camera.set_exposure(start_s))
    for _ in range(iterations):
        camera.trigger()
        frame, _ = camera.read_frame(timeout_s)
        level = float(np.percentile(frame, 99)) / max_dn
        if level >= 0.99:
            factor = 0.25
        elif level <= 0:
            factor = 16.0
        else:
            factor = float(np.clip(target / level, 1 / 16, 16.0))
        if abs(factor - 1.0) < 0.1:
            break
        exposure = float(camera.set_exposure(exposure * factor))
    return exposure


def board_problem(frames: dict[str, np.ndarray], board: tuple[int, int], max_dn: dict[str, float]) -> str | None:
    """Why a pair cannot be used (a camera that does not see the whole board), or ``None``."""
    for name, frame in frames.items():
        if find_board(gray8(frame, max_dn[name]), board) is None:
            return f"camera {name} does not see the whole {board[0]}x{board[1]} board"
    return None


def operator_next_view(ask: Callable[[str], None] | None = None, interval_s: float | None = None,
                       clock: Clock | None = None, say: Callable[[str], None] | None = None) -> NextView:
    """``next_view`` for an operator holding the board: asked through ``ask(message)`` (returns once the board
    is in place, e.g. after Enter), or, with ``interval_s``, told through ``say(message)`` and given that many
    seconds on ``clock`` to move it."""
    if interval_s is None and ask is None:
        raise ConfigurationError("give an ask() callback or an interval to move the board between views")

    def next_view(k: int, n: int, problem: str | None) -> None:
        again = f"not kept ({problem}); " if problem else ""
        what = f"{again}hold the chessboard at pose {k + 1} of {n}: whole board in both cameras, turned a new way"
        if interval_s is None:
            ask(f"{what}, then press Enter")
            return
        if say is not None:
            say(f"{what}: shooting in {interval_s:g} s")
        (clock or SystemClock()).sleep(interval_s)

    return next_view


def record_calibration_views(root: str | Path, rig: Rig, cameras: dict[str, Camera], next_view: NextView, *,
                             n_views: int = DEFAULT_N_VIEWS, board: tuple[int, int] = (9, 6),
                             square_mm: float = 60.0, exposure_s: dict[str, float] | None = None,
                             timeout_s: float = 30.0, progress: ProgressCallback | None = None
                             ) -> dict:
    """Take ``n_views`` chessboard pairs with the rig's cameras into ``ROOT/calibration/`` (module docstring).

    ``exposure_s`` per camera, or automatic (:func:`auto_exposure_s` on the first pose, then kept).  A pair
    where a camera misses the board is not kept and ``next_view`` is called again with the reason, at most
    :data:`MAX_ATTEMPTS_PER_VIEW` times per view.  Returns the summary written to ``capture.json``.
    """
    if "B" not in rig.camera_names or set(cameras) != {"A", "B"}:
        raise ConfigurationError(f"rig {rig.name!r}: calibration views need both cameras A and B")
    check_board(tuple(board))
    if n_views < 1 or not square_mm > 0:
        raise ConfigurationError(f"need at least one view and a positive square, got {n_views} views, "
                                 f"{square_mm} mm")
    folder = calibration_folder(root)
    max_dn = {c: float((1 << rig.cameras[c].bit_depth) - 1) for c in cameras}
    cfa = {c: (rig.cameras[c].raw.cfa_pattern if rig.cameras[c].raw is not None else None) for c in cameras}
    with directory_lock(folder, "capture calibration-views"):
        clear_views(folder)
        atomic_write_text(folder / "rig.toml", rig_toml(rig))
        write_board_description(folder, board, square_mm)
        views, rejected, problem = [], [], None
        for attempt in range(MAX_ATTEMPTS_PER_VIEW * n_views):
            k = len(views)
            next_view(k, n_views, problem)
            if exposure_s is None:
                start = float(np.exp(np.mean(np.log(rig.bracket.exposures_s))))
                exposure_s = {c: auto_exposure_s(cameras[c], start, max_dn[c], timeout_s) for c in sorted(cameras)}
            else:
                exposure_s = {c: float(cameras[c].set_exposure(exposure_s[c])) for c in sorted(cameras)}
            shot = shoot_pair(cameras, timeout_s)
            frames = {c: rgb_frame(shot[c][0], cfa[c]) for c in shot}
            problem = board_problem(frames, board, max_dn)
            if problem is not None:
                rejected.append({"attempt": attempt, "why": problem})
                continue
            name = view_name(k)
            for c, frame in frames.items():
                with atomic_path(folder / c / name) as tmp:
                    tifffile.imwrite(tmp, frame, photometric="rgb")
            views.append({"name": name, "time": shot["A"][1].get("camera_time"), "exposure_s": exposure_s})
            if progress is not None:
                progress("calibration views", len(views), n_views)
            if len(views) == n_views:
                break
        else:
            raise DeviceError(f"only {len(views)} of {n_views} calibration views kept after "
                              f"{MAX_ATTEMPTS_PER_VIEW * n_views} shots: {problem}")
        summary = {"format": "omnispectral-calibration-views", "format_version": 1, "created_utc": utc_now_iso(),
                   "rig": rig.name, "board": [int(board[0]), int(board[1])], "square_mm": float(square_mm),
                   "n_views": len(views), "views": views, "rejected": rejected, "folder": str(folder)}
        atomic_write_json(folder / CAPTURE_FILE, summary)
    return summary
