"""Rendering every slot of a time-lapse (paper Fig. 16): per-slot outputs, a frame sequence and a contact sheet.

``render_series(SERIES, OUT)`` renders each slot's product (a ``process-series`` output, or any directory
whose sub-directories are products) with the same scene and settings into ``OUT/slot_<time>/`` (e.g.
``slot_2017-06-21T0630``; :func:`slot_folder_names`), copies the
tone-mapped images to ``OUT/frames/frame_0000.png …`` (video-ready: ``ffmpeg -i frames/frame_%04d.png``) and
assembles ``OUT/contact_sheet.png`` labelled with the times.  ``exposure="common"`` tone-maps every frame
with one exposure (the brightest slot's automatic one) so brightness changes over the day stay visible;
``"auto"`` exposes each frame for itself.
"""

from __future__ import annotations

import datetime as _dt
import math
import shutil
from pathlib import Path

import cv2
import numpy as np

from omnispectral.apps.render import auto_exposure_reference, render_product
from omnispectral.errors import InputFileError
from omnispectral.imaging.imageio import read_image
from omnispectral.io import atomic_path, atomic_write_json
from omnispectral.ownership import check_output_outside_inputs, claim_output_directory
from omnispectral.product.exports import reinhard_srgb8
from omnispectral.product.series import series_products
from omnispectral.progress import ProgressCallback, report_progress

__all__ = ["contact_sheet", "render_series", "series_slots", "slot_folder_names"]


def series_slots(series: str | Path) -> list[tuple[str, Path]]:
    """``(label, product)`` of a processed series (time stack) or of the product sub-directories of a folder."""

    root = Path(series)
    if (root / "timestack.zarr").exists():
        return series_products(root)
    slots = sorted((p.name, p) for p in root.iterdir() if (p / "product.json").is_file()) if root.is_dir() else []
    if not slots:
        raise InputFileError(root, "holds no processed series (timestack.zarr) and no product sub-directories")
    return slots


def slot_folder_names(labels: list[str]) -> list[str]:
    """The output folder of each slot, from its label: readable, unique, and sorting in time order.

    A time (ISO 8601, a processed series' slots) gives ``slot_YYYY-MM-DDTHHMM`` (``SS`` appended when the
    seconds are not 0) in the time's own zone, e.g. ``2017-06-21T06:30:00+00:00`` → ``slot_2017-06-21T0630``;
    any other label (a product folder's name) keeps its letters, digits, ``-`` and ``_`` with one ``slot_``
    prefix (``slot_0630`` stays ``slot_0630``).  A name met again gets ``_2``, ``_3``… (the hour repeated when
    clocks go back).

    Parameters
    ----------
    labels : list of str
        The slots' labels, in slot order (:func:`series_slots`).

    Returns
    -------
    list of str
        One folder name per label, all different.
    """
    names: list[str] = []
    used: set[str] = set()
    for label in labels:
        base = _folder_name(label)
        name, k = base, 1
        while name in used:
            k += 1
            name = f"{base}_{k}"
        used.add(name)
        names.append(name)
    return names


def _folder_name(label: str) -> str:
    try:
        t = _dt.datetime.fromisoformat(label)
    except ValueError:
        t = None
    if t is not None and "T" in label:
        return f"slot_{t:%Y-%m-%dT%H%M}" + (f"{t:%S}" if t.second else "")
    safe = "".join(ch for ch in label if ch.isalnum() or ch in "-_")[:40]
    return safe if safe.startswith("slot_") else f"slot_{safe}" if safe else "slot"


def contact_sheet(images: list[np.ndarray], labels: list[str], columns: int | None = None) -> np.ndarray:
    """8-bit RGB images of one size on a grid (4 columns at most), each labelled at its top-left corner."""

    n = len(images)
    columns = columns or min(4, n)
    rows = math.ceil(n / columns)
    h, w = images[0].shape[:2]
    sheet = np.full((rows * h, columns * w, 3), 32, np.uint8)
    for i, (img, label) in enumerate(zip(images, labels, strict=True)):
        r, c = divmod(i, columns)
        tile = np.ascontiguousarray(img[..., :3]).copy()
        scale = max(0.35, w / 400)
        cv2.putText(tile, label, (6, int(20 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(tile, label, (6, int(20 * scale)), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * scale, (255, 255, 255), 1,
                    cv2.LINE_AA)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = tile
    return sheet


def render_series(series: str | Path, output: str | Path, exposure: str = "auto",
                  progress: ProgressCallback | None = None, **render_kwargs) -> dict:
    """Render every slot (keyword arguments as :func:`omnispectral.apps.render.render_product`).

    Parameters
    ----------
    series : str or pathlib.Path
        A processed series (a ``process-series`` output with ``timestack.zarr``) or a directory whose
        sub-directories are products (:func:`series_slots`).
    output : str or pathlib.Path
        The output directory: ``slot_<time>/`` per slot (:func:`slot_folder_names`), ``frames/frame_NNNN.png``,
        ``contact_sheet.png`` and ``render_series.json``.
    exposure : {"auto", "common"}
        ``"auto"``: each frame exposed for itself; ``"common"``: every frame's PNG re-tone-mapped with one
        exposure scale, ``1 /`` the largest automatic reference of the slots (the brightest slot's).
    progress : ProgressCallback, optional
        ``progress("slots", done, total)``: once before the first slot, then after each; within each slot the
        render's own reports (``"environment"``, ``"render passes"``: :func:`~omnispectral.apps.render.render_product`).
    **render_kwargs
        Keyword arguments of :func:`~omnispectral.apps.render.render_product` (scene, size, samples, ...),
        the same for every slot.

    Returns
    -------
    dict
        ``n_slots``, ``contact_sheet`` and ``frames`` (paths), ``exposure``, and ``slots``: per slot its
        ``label``, its output ``folder`` and :func:`~omnispectral.apps.render.render_product`'s result (also in
        ``render_series.json``).

    Raises
    ------
    ValueError
        For an ``exposure`` other than ``"auto"`` or ``"common"``.
    InputFileError
        When ``series`` holds neither a processed series nor product sub-directories.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 6.1, Fig. 16 (time-lapse spectral rendering), Fig. 12 (the time-lapse).
    .. [2] A. Fichet, R. Pacanowski, A. Wilkie, "An OpenEXR Layout for Spectral Images", JCGT 10(3), 2021
       (each slot's spectral EXR).
    """


    if exposure not in ("auto", "common"):
        raise ValueError(f"exposure must be 'auto' or 'common', got {exposure!r}")
    check_output_outside_inputs([output], [series])
    out = claim_output_directory(output, "render-series")
    slots = series_slots(series)
    folders = slot_folder_names([label for label, _ in slots])
    results = []
    report_progress(progress or None, "slots", 0, len(slots))
    for k, ((label, product), folder) in enumerate(zip(slots, folders, strict=True)):
        res = render_product(product, out / folder, progress=progress, **render_kwargs)
        results.append((label, {"folder": str(out / folder), **res}))
        report_progress(progress or None, "slots", k + 1, len(slots))
    if exposure == "common":
        refs = [auto_exposure_reference(read_image(r["files"]["srgb_exr"])) for _, r in results]
        scale = 1.0 / max(refs)

        for _, r in results:
            rgb = read_image(r["files"]["srgb_exr"])
            with atomic_path(Path(r["files"]["png"])) as tmp:
                cv2.imwrite(str(tmp), np.ascontiguousarray(reinhard_srgb8(rgb * np.float32(scale))[..., ::-1]))
    frames = out / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    images = []
    for k, (_, r) in enumerate(results):
        shutil.copyfile(r["files"]["png"], frames / f"frame_{k:04d}.png")
        images.append(cv2.imread(r["files"]["png"], cv2.IMREAD_COLOR)[..., ::-1])
    sheet = contact_sheet(images, [_short(label) for label, _ in results])
    with atomic_path(out / "contact_sheet.png") as tmp:
        cv2.imwrite(str(tmp), np.ascontiguousarray(sheet[..., ::-1]))
    summary = {"n_slots": len(results), "contact_sheet": str(out / "contact_sheet.png"), "frames": str(frames),
               "exposure": exposure, "slots": [{"label": label, **r} for label, r in results]}
    atomic_write_json(out / "render_series.json", summary)
    return summary


def _short(label: str) -> str:
    """``2017-06-21T06:30:00+00:00`` → ``06:30``; other labels unchanged."""
    return label[11:16] if len(label) >= 16 and label[10] == "T" else label
