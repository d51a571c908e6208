"""The report's maps: per-pixel error against the truth, the quality layer, the worst pixels on the preview.

PNG figures for ``report.html`` (:mod:`omnispectral.product.report`), drawn at the preview's pyramid level (the
first whose width is ≤ the preview width, 2048 px by default) so that they stay small whatever the panorama's
size: level-0 maps are shrunk by a NaN-aware area mean (:func:`shrink_nanmean`; a NaN pixel is one the map does
not score).  The errors themselves are computed on level 0 (:mod:`omnispectral.product.report_edges`).

- ``error_map.png``: ``band_nrmse`` (log scale) and ``delta_e_ab`` per pixel, grey where not scored, and the
  depth-edge band when the truth has depth;
- ``quality.png``: every layer the store's ``quality`` attribute names (``registration_confidence``, ``occluded``,
  ``sun``, ``b_predicted``, …), each with its colour bar;
- ``worst_pixels.png``: the preview with a red ring around each of the worst pixels and a cyan dot on each hole.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from omnispectral.io import atomic_path
from omnispectral.product.report_edges import PixelErrors

__all__ = ["BAND_NRMSE_RANGE", "DELTA_E_RANGE", "FIGURE_DPI", "QUALITY_RANGES", "mark_worst_pixels",
           "plot_error_maps", "plot_quality", "shrink_nanmean"]

#: Colour range of quality layers whose meaning fixes it (others: 0 to their 99.5th percentile).
QUALITY_RANGES = {"registration_confidence": (0.0, 1.0), "occluded": (0.0, 1.0), "sun": (0.0, 1.0)}
#: Colour range of the band NRMSE map (log scale) and of the ΔE*ab map.
BAND_NRMSE_RANGE = (1e-3, 1.0)
DELTA_E_RANGE = (0.0, 10.0)
#: Resolution of the figures (10 inches wide: 960 px).
FIGURE_DPI = 96


def shrink_nanmean(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area mean of a ``(H, W)`` map onto ``height × width`` ignoring NaN (NaN where no finite value falls)."""
    img = np.asarray(image, np.float32)
    if img.shape == (height, width):
        return img.copy()
    finite = np.isfinite(img)
    total = cv2.resize(np.where(finite, img, 0).astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    count = cv2.resize(finite.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32)


def _pyplot():
    import matplotlib  # lazy: pyplot is needed for the figures only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _show(ax, image: np.ndarray, title: str, label: str, norm=None, vmin=None, vmax=None, cmap="magma") -> None:
    """One equirect map with a colour bar (NaN in grey), longitude and latitude on the axes."""
    plt = _pyplot()
    colours = plt.get_cmap(cmap).with_extremes(bad="0.6")
    im = ax.imshow(np.ma.masked_invalid(image), extent=(-180, 180, -90, 90), cmap=colours, norm=norm, vmin=vmin,
                   vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xticks(range(-180, 181, 60))
    ax.set_yticks(range(-90, 91, 45))
    ax.tick_params(labelsize=7)
    plt.colorbar(im, ax=ax, fraction=0.025, pad=0.01).set_label(label, fontsize=8)


def _save(fig, path: Path) -> Path:
    """The figure as a 256-colour palette PNG (a third of the size of full colour; the colour maps have 256
    colours anyway), written atomically."""
    fig.canvas.draw()
    rgb = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    _pyplot().close(fig)
    image = Image.fromarray(np.ascontiguousarray(rgb)).quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)
    return path


def plot_error_maps(errors: PixelErrors, height: int, width: int, path: Path) -> Path:
    """``error_map.png`` (module docstring) at ``height × width``."""
    from matplotlib.colors import LogNorm

    plt = _pyplot()
    panels = 3 if errors.edge is not None else 2
    fig, axes = plt.subplots(panels, 1, figsize=(10, 4.3 * panels), dpi=FIGURE_DPI)
    nrmse = np.clip(shrink_nanmean(errors.band_nrmse, height, width), *BAND_NRMSE_RANGE)
    _show(axes[0], nrmse, "Band error against the truth: ‖b − t‖ / ‖t‖ per pixel (grey: not scored)",
          "band NRMSE", norm=LogNorm(*BAND_NRMSE_RANGE))
    _show(axes[1], shrink_nanmean(errors.delta_e_ab, height, width),
          "ΔE*ab between the estimator's spectra of the panorama's and of the truth's bands", "ΔE*ab",
          vmin=DELTA_E_RANGE[0], vmax=DELTA_E_RANGE[1])
    if errors.edge is not None:
        band = shrink_nanmean(np.where(errors.scored, errors.edge.astype(np.float32), np.nan), height, width)
        _show(axes[2], band, "Depth-edge band (within 2 px of a depth discontinuity)", "share of edge pixels",
              vmin=0, vmax=1, cmap="Blues")
    fig.tight_layout()
    return _save(fig, path)


def plot_quality(quality: np.ndarray, layers: list[str], height: int, width: int, path: Path) -> Path:
    """``quality.png``: one map per named layer of the store's ``(H, W, k)`` quality array."""
    plt = _pyplot()
    names = list(layers)[: quality.shape[2]]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 4.3 * len(names)), squeeze=False, dpi=FIGURE_DPI)
    for k, (ax, name) in enumerate(zip(axes[:, 0], names, strict=True)):
        layer = shrink_nanmean(quality[..., k], height, width)
        lo, hi = QUALITY_RANGES.get(name, (0.0, _upper(layer)))
        _show(ax, layer, f"quality: {name}", name, vmin=lo, vmax=hi, cmap="viridis")
    fig.tight_layout()
    return _save(fig, path)


def _upper(layer: np.ndarray) -> float:
    """The 99.5th percentile of a layer's finite values (1 when it has none, or only zeros)."""
    finite = layer[np.isfinite(layer)]
    top = float(np.percentile(finite, 99.5)) if finite.size else 0.0
    return top if top > 0 else 1.0


def mark_worst_pixels(preview_png: Path, worst_rows: np.ndarray, worst_cols: np.ndarray, holes: np.ndarray | None,
                      level0_shape: tuple[int, int], path: Path) -> Path:
    """``worst_pixels.png``: the preview with a red ring at each worst pixel (level-0 ``worst_rows``, ``worst_cols``)
    and a cyan dot at each hole (``holes``: level-0 mask); level-0 positions are scaled to the preview's size."""
    img = cv2.imread(str(preview_png), cv2.IMREAD_COLOR)
    ph, pw = img.shape[:2]
    sy, sx = ph / level0_shape[0], pw / level0_shape[1]
    if holes is not None:
        rows, cols = np.nonzero(holes)
        img[np.minimum((rows + 0.5) * sy, ph - 1).astype(int), np.minimum((cols + 0.5) * sx, pw - 1).astype(int)] = (
            255, 255, 0)
    radius = max(3, round(pw / 300))
    for r, c in zip(worst_rows, worst_cols, strict=True):
        centre = (int((c + 0.5) * sx), int((r + 0.5) * sy))
        cv2.circle(img, centre, radius, (0, 0, 255), 1, lineType=cv2.LINE_AA)
    with atomic_path(path) as tmp:
        cv2.imwrite(str(tmp), img)
    return path
