"""Lens calibration from chessboard views: Zhang's method through OpenCV (paper Sec. 4.2).

The paper measures each lens's distortion "by using Zhang's method in advance" and corrects the
captured images with it (Hirai et al. 2018, Sec. 4.2; Z. Zhang, "A flexible new technique for
camera calibration", IEEE TPAMI 22(11):1330-1334, 2000).  :func:`calibrate_lens` runs the usual
OpenCV pipeline ("Camera calibration With OpenCV" tutorial): ``cv2.findChessboardCorners``
(``cv2.findChessboardCornersSB`` as a fallback), ``cv2.cornerSubPix`` and ``cv2.calibrateCamera``,
and returns a :class:`~omnispectral.imaging.geometry.CameraModel`, the single geometry object the
mosaic engine and the simulator use.

Corner refinement.  OpenCV's tutorial refines corners with an 11 px half-window (a 23 × 23 px
window).  When the board's squares are smaller than that in the image (a board seen small or
obliquely), the window reaches the neighbouring corners and pulls corners off the saddle point, or
merges two corners into one.  The default here, ``subpix_window_px="auto"``, uses
``min(11, 0.4 × smallest corner spacing)`` per image; ``subpix_window_px=11`` is OpenCV's own
pipeline exactly.  On OpenCV's sample boards (``left*.jpg``, 9 × 6) OpenCV's setting gives RMS
0.409 px, fx = 536.07 (one view, left02 with 22 px squares, at 1.22 px); the adapted window gives
0.181 px, fx = 533.30, left02 at 0.17 px.  On synthetic views with known parameters (tests), the
fixed window merges corners of an oblique board and misplaces the principal point by 40 px, the
adapted one recovers fx, fy, cx, cy within 0.4 px.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from PIL import Image, UnidentifiedImageError

from omnispectral.choices import DEFAULT_SUBPIX_WINDOW, DETECTORS, LENS_MODEL_NAMES, MIN_IMAGES
from omnispectral.errors import ConfigurationError, InputFileError, OmnispectralError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.limits import check_image_header

__all__ = ["DEFAULT_SUBPIX_WINDOW", "DETECTORS", "MIN_IMAGES", "MODELS", "SUBPIX_WINDOW_PX", "BoardView",
           "CalibrationError", "LensCalibration", "board_object_points", "calibrate_lens", "check_board",
           "find_board", "parse_board", "read_gray8"]

#: Distortion models offered: name (:data:`~omnispectral.choices.LENS_MODEL_NAMES`, in that order) →
#: (``cv2.calibrateCamera`` flags, number of coefficients).
MODELS = dict(zip(LENS_MODEL_NAMES, (
    (0, 5),  # standard: k1 k2 p1 p2 k3
    (cv2.CALIB_RATIONAL_MODEL, 8),  # rational: + k4 k5 k6
    (cv2.CALIB_RATIONAL_MODEL | cv2.CALIB_THIN_PRISM_MODEL, 12),  # thin-prism: + s1..s4
), strict=True))
#: OpenCV tutorial's ``cornerSubPix`` half-window (the largest "auto" uses) and termination criteria.
SUBPIX_WINDOW_PX = 11
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
_CLASSIC_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
_SB_FLAGS = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY


class CalibrationError(OmnispectralError):
    """Calibration cannot be done with the images given (e.g. too few boards found)."""


@dataclass(frozen=True)
class BoardView:
    """One image in which the board was found: corners, detector, pose and reprojection error."""

    path: Path
    corners_px: np.ndarray  # (N, 2) float64, OpenCV order (row by row)
    detector: str  # "classic" or "sb"
    rvec: np.ndarray  # board → camera rotation (Rodrigues), as cv2.calibrateCamera returns it
    tvec_mm: np.ndarray
    rms_px: float


@dataclass(frozen=True)
class LensCalibration:
    """Result of :func:`calibrate_lens`."""

    camera: CameraModel
    rms_px: float
    board: tuple[int, int]
    square_mm: float
    model: str
    views: tuple[BoardView, ...]
    rejected: tuple[tuple[Path, str], ...]
    warnings: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The camera (:meth:`CameraModel.to_dict`) plus RMS, board and the images used and rejected."""
        return {**self.camera.to_dict(),
                "rms_px": self.rms_px,
                "calibration": {"method": "Zhang (2000) via OpenCV calibrateCamera", "model": self.model,
                                "board": {"cols": self.board[0], "rows": self.board[1], "square_mm": self.square_mm},
                                "opencv": cv2.__version__},
                "images_used": [{"path": str(v.path), "rms_px": v.rms_px, "detector": v.detector}
                                for v in self.views],
                "images_rejected": [{"path": str(p), "reason": why} for p, why in self.rejected],
                "warnings": list(self.warnings)}


# ------------------------------------------------------------------------------------------ input
def parse_board(text: str) -> tuple[int, int]:
    """``"9x6"`` → ``(9, 6)``: inner corners per row (columns) × per column (rows)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX×]\s*(\d+)\s*", text)
    if not m:
        raise ConfigurationError(f"board must be COLSxROWS inner corners, e.g. 9x6; got {text!r}")
    board = int(m.group(1)), int(m.group(2))
    check_board(board)
    return board


def check_board(board: tuple[int, int]) -> None:
    cols, rows = board
    if cols < 3 or rows < 3:
        raise ConfigurationError(f"a board needs at least 3x3 inner corners, got {cols}x{rows}")


def read_gray8(path: str | Path) -> np.ndarray:
    """Read an image file as 8-bit grayscale (decoded by OpenCV, as in OpenCV's own calibration).

    Raises :class:`InputFileError` naming the file when it is missing, empty, not an image, or
    truncated/corrupt (OpenCV's JPEG decoder only warns on a truncated file and returns a partly
    grey image, so the file is also fully decoded by Pillow, which fails on missing data).
    Colour images are converted with OpenCV's luma weights; 16-bit and float images are scaled
    to their maximum.
    """
    path = Path(path)
    if not path.exists():
        raise InputFileError(path, "file not found")
    if not path.is_file():
        raise InputFileError(path, "not a file")
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise InputFileError(path, f"cannot read the file ({exc.strerror or exc})") from None
    if data.size == 0:
        raise InputFileError(path, "file is empty")
    check_image_header(path)  # the size from the header, before OpenCV (which is not lazy) decodes it
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise InputFileError(path, "not a readable image (OpenCV cannot decode it)")
    _check_complete(path)
    return _to_gray8(img)


def _check_complete(path: Path) -> None:
    try:
        with Image.open(path) as im:
            im.load()
    except (UnidentifiedImageError, Image.DecompressionBombError):
        return  # a format or size Pillow does not handle; OpenCV decoded it
    except (OSError, SyntaxError, ValueError) as exc:
        raise InputFileError(path, f"image data is truncated or corrupt ({exc})") from None


def _to_gray8(img: np.ndarray) -> np.ndarray:
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[..., 0]
        else:
            code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
            img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        top = float(np.nanmax(img)) if img.size else 0.0
        img = np.clip(np.nan_to_num(img) * (255.0 / top if top > 0 else 0.0), 0, 255).round().astype(np.uint8)
    return np.ascontiguousarray(img)


# ------------------------------------------------------------------------------------------ detection
def board_object_points(board: tuple[int, int], square_mm: float) -> np.ndarray:
    """Board corners ``(cols·rows, 3)`` float32 in mm on ``z = 0``, in OpenCV's corner order (row by row)."""
    cols, rows = board
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    obj = np.zeros((cols * rows, 3), np.float32)
    obj[:, :2] = grid * float(square_mm)
    return obj


def _corner_spacing_px(corners: np.ndarray, board: tuple[int, int]) -> float:
    cols, rows = board
    c = corners.reshape(rows, cols, 2)
    return float(min(np.linalg.norm(np.diff(c, axis=0), axis=-1).min(),
                     np.linalg.norm(np.diff(c, axis=1), axis=-1).min()))


def find_board(gray: np.ndarray, board: tuple[int, int], detector: str = "auto",
               subpix_window_px: int | str = DEFAULT_SUBPIX_WINDOW) -> tuple[np.ndarray, str] | None:
    """Chessboard inner corners ``(N, 2)`` float64 and the detector used, or ``None`` if not found.

    ``classic``: ``cv2.findChessboardCorners`` then ``cv2.cornerSubPix`` (half-window
    ``subpix_window_px``, or 40 % of the smallest corner spacing with ``"auto"``);
    ``sb``: ``cv2.findChessboardCornersSB`` (sector-based, sub-pixel by itself);
    ``auto``: classic, then sb if classic fails.
    """
    if detector not in DETECTORS:
        raise ConfigurationError(f"detector must be one of {', '.join(DETECTORS)}, got {detector!r}")
    if detector in ("auto", "classic"):
        found, corners = cv2.findChessboardCorners(gray, board, flags=_CLASSIC_FLAGS)
        if found:
            if subpix_window_px == "auto":
                half = int(max(2, min(SUBPIX_WINDOW_PX, 0.4 * _corner_spacing_px(corners, board))))
            else:
                half = int(subpix_window_px)
            corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
            return corners.reshape(-1, 2).astype(np.float64), "classic"
    if detector in ("auto", "sb"):
        found, corners = cv2.findChessboardCornersSB(gray, board, flags=_SB_FLAGS)
        if found:
            return corners.reshape(-1, 2).astype(np.float64), "sb"
    return None


# ------------------------------------------------------------------------------------------ calibration
def calibrate_lens(paths: Iterable[str | Path], board: tuple[int, int], square_mm: float, *,
                   model: str = "standard", detector: str = "auto", min_images: int = MIN_IMAGES,
                   subpix_window_px: int | str = DEFAULT_SUBPIX_WINDOW) -> LensCalibration:
    """Calibrate a lens from chessboard images with Zhang's method (OpenCV ``calibrateCamera``).

    Images where the board is not found are listed in ``rejected``, not fatal.  Unreadable
    files raise :class:`InputFileError`; images of another size than the first raise it too.

    Parameters
    ----------
    paths : iterable of str or pathlib.Path
        Image files, all from one camera at one resolution.
    board : tuple of int
        Inner corners ``(cols, rows)``, e.g. ``(9, 6)`` for OpenCV's sample board.
    square_mm : float
        Side of a square (mm); sets the unit of the board poses (intrinsics do not depend on it).
    model : str
        ``"standard"`` (k1 k2 p1 p2 k3), ``"rational"`` (+ k4 k5 k6) or ``"thin-prism"`` (+ s1..s4).
    detector : str
        ``"auto"`` (classic detector, sector-based as fallback), ``"classic"`` or ``"sb"``.
    min_images : int
        Fewest images with a detected board (at least 3); fewer raise :class:`CalibrationError`.
    subpix_window_px : int or "auto"
        ``cornerSubPix`` half-window: ``"auto"`` (default, ``min(11, 0.4 × corner spacing)``) or
        pixels (11 reproduces OpenCV's tutorial pipeline exactly); see the module docstring.

    Returns
    -------
    LensCalibration
        The :class:`~omnispectral.imaging.geometry.CameraModel` (intrinsics in pixels, distortion
        coefficients of ``model``), the overall reprojection RMS (px), the board, the views used (each with
        its pose and RMS), the images rejected and warnings (a distortion that folds inside the image).

    Raises
    ------
    ConfigurationError
        For no images, an invalid board, a square size that is not positive, an unknown model, ``min_images``
        below 3 or an invalid ``subpix_window_px``.
    InputFileError
        For an unreadable image or one of another size than the first.
    CalibrationError
        When fewer than ``min_images`` images show the board.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.2 (lens distortion measured by Zhang's method in advance).
    .. [2] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11):1330-1334, 2000.
    .. [3] "Camera calibration With OpenCV", OpenCV tutorial (the detection, corner refinement and
       ``calibrateCamera`` pipeline).
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ConfigurationError("no calibration images given")
    check_board(tuple(board))
    board = (int(board[0]), int(board[1]))
    if not (square_mm > 0):
        raise ConfigurationError(f"square size must be positive, got {square_mm} mm")
    if model not in MODELS:
        raise ConfigurationError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    if min_images < 3:
        raise ConfigurationError(f"min_images must be at least 3 (Zhang's method), got {min_images}")
    if subpix_window_px != "auto" and not (isinstance(subpix_window_px, int) and subpix_window_px >= 1):
        raise ConfigurationError(f"subpix_window_px must be a positive integer or 'auto', got {subpix_window_px!r}")

    size = None
    first = None
    found: list[tuple[Path, np.ndarray, str]] = []
    rejected: list[tuple[Path, str]] = []
    for path in paths:
        gray = read_gray8(path)
        this = (gray.shape[1], gray.shape[0])
        if size is None:
            size, first = this, path
        elif this != size:
            raise InputFileError(path, f"image is {this[0]}x{this[1]} but {first} is {size[0]}x{size[1]}; "
                                       "all calibration images must come from one camera at one resolution")
        hit = find_board(gray, board, detector, subpix_window_px)
        if hit is None:
            rejected.append((path, f"{board[0]}x{board[1]} board not found"))
        else:
            found.append((path, *hit))
    if len(found) < min_images:
        missing = ", ".join(str(p) for p, _ in rejected) or "none"
        raise CalibrationError(f"{board[0]}x{board[1]} board found in {len(found)} of {len(paths)} images; "
                               f"at least {min_images} are needed (not found in: {missing})")

    flags, n_coeffs = MODELS[model]
    obj = board_object_points(board, square_mm)
    image_points = [c.astype(np.float32).reshape(-1, 1, 2) for _, c, _ in found]
    rms, k, dist, rvecs, tvecs = cv2.calibrateCamera([obj] * len(found), image_points, size, None, None,
                                                     flags=flags)
    camera = CameraModel.from_opencv(k, np.asarray(dist).ravel()[:n_coeffs], size)
    views = tuple(BoardView(path=p, corners_px=c, detector=det, rvec=np.asarray(r, float).ravel(),
                            tvec_mm=np.asarray(t, float).ravel(),
                            rms_px=_view_rms(camera, obj, c, r, t))
                  for (p, c, det), r, t in zip(found, rvecs, tvecs, strict=True))
    return LensCalibration(camera=camera, rms_px=float(rms), board=board, square_mm=float(square_mm),
                           model=model, views=views, rejected=tuple(rejected), warnings=_model_warnings(camera))


def _model_warnings(camera: CameraModel, step_px: int = 4) -> tuple[str, ...]:
    """Warn when the fitted distortion folds inside the image (pixels there have no unique ray)."""
    u = np.arange(0, camera.width, step_px, dtype=np.float64)
    v = np.arange(0, camera.height, step_px, dtype=np.float64)
    _, ok = camera.unproject(np.stack(np.meshgrid(u, v), axis=-1))
    if ok.all():
        return ()
    theta = np.degrees(np.arctan(camera.max_radius))
    return (f"the fitted distortion is not monotonic beyond {theta:.1f}° from the optical axis, so "
            f"{100 * (1 - ok.mean()):.0f}% of the image has no unique ray; use a simpler --model or more views "
            "covering the image corners",)


def _view_rms(camera: CameraModel, obj: np.ndarray, corners: np.ndarray, rvec, tvec) -> float:
    """RMS distance between detected corners and the board reprojected with the fitted model.

    Uses ``cv2.projectPoints`` (the raw model, as ``calibrateCamera`` measures its error), so a
    statistic is reported even where :meth:`CameraModel.project` would flag a fold.
    """
    k, dist, _ = camera.to_opencv()
    uv, _ = cv2.projectPoints(obj.astype(np.float64), np.asarray(rvec, np.float64), np.asarray(tvec, np.float64),
                              k, dist)
    return float(np.sqrt(np.mean(np.sum((uv.reshape(-1, 2) - corners) ** 2, axis=-1))))
