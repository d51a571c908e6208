"""Rig calibration from a folder of chessboard pairs, end to end (``omnispectral calibrate rig --chessboard``).

Why a chessboard: a session's own images fix camera B's yaw only as well as their farthest content is far
(:mod:`omnispectral.product.rigfit`); a board of known square size fixes the distance of every corner
(:mod:`omnispectral.product.boardfit`).  The steps, each in its module:

1. the board and the rig: ``--board``/``--square-mm`` or ``folder/board.json``, ``--rig`` or
   ``folder/rig.toml``;
2. pairs of images of the same name in ``folder/A`` and ``folder/B`` and the board's corners in both
   (:mod:`omnispectral.product.boardcorners`);
3. camera B's mounting fitted to every pair's corners (:func:`~omnispectral.product.boardfit.fit_b_mounting_to_boards`,
   a stereo calibration with the lenses fixed: Zhang 2000, OpenCV's ``stereoCalibrate``);
4. the result written as a rig calibration file (:class:`~omnispectral.product.rigfile.RigCalibration`)
   for ``process --rig-calibration``; ``process`` also fits the views a session records
   (:mod:`omnispectral.product.rigsource`).

The paper (Hirai et al. 2018, Sec. 4.3) registers B to A by one POC offset per direction; a calibrated
mounting gives the offset at infinity of every direction at once.
"""

from __future__ import annotations

import json
from pathlib import Path

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.lens import CalibrationError, check_board
from omnispectral.io import read_text_file
from omnispectral.product.boardcorners import find_board_pairs, pair_files
from omnispectral.product.boardfit import MIN_PAIRS, fit_b_mounting_to_boards
from omnispectral.product.rigfile import RigCalibration
from omnispectral.rig import Rig, load_rig

__all__ = ["calibrate_chessboard_folder", "calibrate_rig_from_boards"]


def calibrate_rig_from_boards(folder: str | Path, model_a: CameraModel, model_b: CameraModel,
                              board: tuple[int, int], square_mm: float, *, refine_baseline: bool = False,
                              detector: str = "auto", rig_name: str = "") -> RigCalibration:
    """Find the board in every pair of ``folder/A`` and ``folder/B`` and fit B's mounting to them.

    Parameters
    ----------
    folder
        The folder holding ``A/`` and ``B/``.
    model_a, model_b
        Camera A's and camera B's models (the rig file's).
    board
        Inner corners ``(columns, rows)``.
    square_mm
        The board's square size (mm).
    refine_baseline
        Fit B's baseline (mm) too.
    detector
        :func:`~omnispectral.imaging.lens.find_board`'s detector.
    rig_name
        The rig's name, recorded in the result.

    Returns
    -------
    RigCalibration
        The chessboard fit (:func:`~omnispectral.product.boardfit.fit_b_mounting_to_boards`), its rejected
        views including those without the board, ``source`` the folder's absolute path.

    Raises
    ------
    ConfigurationError
        A bad board or square size.
    CalibrationError
        No pair with the board in both images, or none left to fit.
    """
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
    ``simulate-chessboard`` writes); the calibration saved to ``output`` (JSON) for ``process --rig-calibration``.

    Parameters
    ----------
    folder
        The folder of chessboard pairs.
    output
        The rig calibration file to write (JSON).
    board, square_mm
        Inner corners ``(columns, rows)`` and square size (mm); ``None``: from ``folder/board.json``.
    rig
        The rig; ``None``: ``folder/rig.toml``.
    refine_baseline
        Fit B's baseline (mm) too.
    detector
        :func:`~omnispectral.imaging.lens.find_board`'s detector.

    Returns
    -------
    RigCalibration
        The calibration written.

    Raises
    ------
    InputFileError
        Not a folder, a bad ``board.json`` or a one-camera rig.
    ConfigurationError
        No board given and no ``board.json``.
    """
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
