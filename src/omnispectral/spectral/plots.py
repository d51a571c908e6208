"""Plots of spectral estimation results (matplotlib, written atomically)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnispectral.io import atomic_path

__all__ = ["FIG9_PATCHES", "plot_estimates"]

FIG9_PATCHES = (12, 13, 14, 15, 16, 18)
"""ColorChecker patches of paper Fig. 9: No. 13 blue, 14 green, 15 red, 16 yellow, 17 magenta, 19 white (0-based)."""


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-300)


def plot_estimates(result: dict, path: str | Path, patches: tuple[int, ...] | None = None) -> Path:
    """Estimated vs true spectra of six targets, like paper Fig. 9 (unit-L2-norm spectra).

    ``result`` is the output of :func:`omnispectral.spectral.evaluate.evaluate`.  The six-band
    estimate is drawn with its ±2σ posterior band; the RGB estimate dotted.

    Parameters
    ----------
    result : dict
        :func:`~omnispectral.spectral.evaluate.evaluate`'s result, with its private ``_spectra`` (not the
        JSON-only :func:`~omnispectral.spectral.evaluate.public` part).
    path : str or pathlib.Path
        The image written; its suffix names the format (``.png`` when it has none).
    patches : tuple of int, optional
        Up to six 0-based target indices; default :data:`FIG9_PATCHES` for the 24 ColorChecker patches, else
        six evenly spaced targets.

    Returns
    -------
    pathlib.Path
        ``path``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Fig. 9 (estimated spectral power distributions of ColorChecker No. 13, 14,
       15, 16, 17 and 19), Sec. 5.2.
    """
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    six, rgb = result["six_band"], result["rgb"]
    names = six["target_names"]
    if patches is None:
        patches = FIG9_PATCHES if len(names) == 24 else tuple(np.linspace(0, len(names) - 1, min(6, len(names)),
                                                                          dtype=int))
    sp6, sp3 = six["_spectra"], rgb["_spectra"]
    wl = sp6["wavelength_nm"]
    fig, axes = plt.subplots(2, 3, figsize=(12, 7), sharex=True, constrained_layout=True)
    for ax, p in zip(axes.ravel(), patches, strict=False):
        norm = np.linalg.norm(sp6["estimated"][p])
        true, est6, est3 = _unit(sp6["true"][p]), _unit(sp6["estimated"][p]), _unit(sp3["estimated"][p])
        std = sp6["std"][p] / max(norm, 1e-300)
        ax.fill_between(wl, est6 - 2 * std, est6 + 2 * std, color="tab:blue", alpha=0.2, lw=0, label="six-band ±2σ")
        ax.plot(wl, true, "k--", lw=1.5, label="ground truth")
        ax.plot(wl, est6, color="tab:blue", lw=1.8,
                label=f"six-band (NRMSE {six['per_target']['nrmse'][p]:.4f})")
        ax.plot(wl, est3, color="tab:red", lw=1.2, ls=":",
                label=f"RGB (NRMSE {rgb['per_target']['nrmse'][p]:.4f})")
        ax.set_title(f"No. {p + 1}: {names[p]}")
        ax.set_ylim(bottom=0)
        ax.legend(fontsize=7, loc="best")
    for ax in axes[-1]:
        ax.set_xlabel("wavelength (nm)")
    for ax in axes[:, 0]:
        ax.set_ylabel("relative spectral power (unit norm)")
    fig.suptitle(f"{result['target']} under {result['illuminant']}: estimated vs true colour signals")
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
    plt.close(fig)
    return path
