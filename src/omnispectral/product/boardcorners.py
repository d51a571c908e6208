"""Chessboard pairs for the rig calibration: image files paired by name, and the board's corners in both.

The measurements of the chessboard fit of camera B's mounting (:mod:`omnispectral.product.boardfit`).
Input: pairs of images with the same file name in two folders (``A/`` and ``B/``), taken at the same moment
with the head still; any format :func:`~omnispectral.imaging.lens.read_gray8` reads.  In each image the
board's inner corners are found (:func:`~omnispectral.imaging.lens.find_board`, OpenCV's detectors, Zhang
2000); a pair where either camera misses the board is listed and skipped.  The paper's rig (Hirai et al.
2018, Sec. 3, Fig. 2) is the two cameras side by side on the head; camera A is the reference.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.capture.calviews import IMAGE_SUFFIXES
from omnispectral.errors import InputFileError
from omnispectral.imaging.lens import find_board, read_gray8

__all__ = ["BoardPair", "find_board_pairs", "pair_files"]


@dataclass(frozen=True)
class BoardPair:
    """One view: the board's inner corners ``(N, 2)`` found in camera A's and in camera B's image."""

    name: str
    corners_a_px: np.ndarray
    corners_b_px: np.ndarray


def pair_files(folder_a: str | Path, folder_b: str | Path) -> list[tuple[Path, Path]]:
    """Image files of ``folder_a`` paired with the file of the same name in ``folder_b``, sorted by name.

    Parameters
    ----------
    folder_a, folder_b
        Camera A's and camera B's folders of chessboard images.

    Returns
    -------
    list of tuple of pathlib.Path
        ``(image of A, image of B)`` per name (hidden files ignored).

    Raises
    ------
    InputFileError
        A folder is missing, ``folder_a`` holds no image, or B has no image of one of A's names.
    """
    fa, fb = Path(folder_a), Path(folder_b)
    for f in (fa, fb):
        if not f.is_dir():
            raise InputFileError(f, "not a folder of chessboard images")
    names_a = sorted(p.name for p in fa.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith("."))
    if not names_a:
        raise InputFileError(fa, "no images (tif, png, jpg, ...)")
    missing = [n for n in names_a if not (fb / n).is_file()]
    if missing:
        raise InputFileError(fb / missing[0], f"camera B has no image of this name for camera A's {fa / missing[0]}")
    return [(fa / n, fb / n) for n in names_a]


def find_board_pairs(pairs: list[tuple[Path, Path]], board: tuple[int, int], detector: str = "auto"
                     ) -> tuple[list[BoardPair], list[tuple[str, str]]]:
    """The board's corners in both images of every pair.

    Parameters
    ----------
    pairs
        ``(image of A, image of B)`` (:func:`pair_files`).
    board
        Inner corners ``(columns, rows)``.
    detector
        :func:`~omnispectral.imaging.lens.find_board`'s detector.

    Returns
    -------
    tuple
        ``(found, rejected)``: the pairs with the board in both images (:class:`BoardPair`, corners in px)
        and ``(name, why)`` of the others.
    """
    found, rejected = [], []
    for pa, pb in pairs:
        hit_a = find_board(read_gray8(pa), board, detector)
        hit_b = find_board(read_gray8(pb), board, detector)
        if hit_a is None or hit_b is None:
            rejected.append((pa.name, f"{board[0]}x{board[1]} board not found in camera "
                                      f"{'A' if hit_a is None else 'B'}'s image"))
            continue
        found.append(BoardPair(pa.name, hit_a[0], hit_b[0]))
    return found, rejected
