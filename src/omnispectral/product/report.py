"""The report of a product: preview, timings, registration per direction and, for simulations, accuracy.

``PRODUCT/report/report.json`` (keys at least ``accuracy`` and ``timings_s``) and ``report.html`` with
PNG plots.  Accuracy against the simulator's ground truth (``SESSION/ground_truth``):

- ``band_psnr_db``: ``10 log10(peak² / MSE)`` of the panorama's bands (DN/s; six, or three for a one-camera
  rig: ``n_bands``; ``six_band_psnr_db`` is the same number for six-band products) against the ground truth
  resampled to the panorama grid (area average), over pixels the panorama covers and where the truth
  is below the shortest exposure's saturation (the sun disk saturates every exposure and is flagged,
  not measured); ``peak`` = the largest ground-truth value on those pixels.
- ``spectral_nrmse``: mean per-pixel NRMSE (unit-L2-norm spectra, as in the spectral core) of the
  Wiener estimate from the panorama's bands, on the ground truth's spectral grid (the panorama is
  area-averaged onto it), over the same kind of pixels.
- ``colorchecker``: the 24 patches located in the panorama from their directions (mean of the six
  bands within half the patch's angular size), estimated, against the patch spectral radiance:
  NRMSE and ΔE*ab (CIE 1976, white = a perfect diffuser at the chart), per patch and mean.  A patch
  crossed by a shadow edge (the ground truth's ``radiance_spread`` over the patch above
  :data:`MAX_PATCH_RADIANCE_SPREAD`) is not one colour: its centre's spectrum is no reference for what
  the panorama integrates there.  It is listed under ``not_uniformly_lit`` with its ΔE*ab and left
  out of the mean, max and NRMSE (``n_patches_scored``).

``irradiance`` (every product; :func:`irradiance_report`): the horizontal irradiance per band (DN/s·sr,
:func:`omnispectral.product.irradiance.irradiance` of level 0), its split into the recovered sun and the sky
with their correlated colour temperatures (:func:`~omnispectral.product.irradiance.sun_sky_irradiance`), the
sun's method or the lower-bound note; for simulations also the truth's horizontal irradiance (the same
integral of ``ground_truth/bands.npy``), ``ratio_to_truth`` = panorama / truth per band and the worst band
(largest ``|ratio − 1|``).
"""

from __future__ import annotations

import html
from pathlib import Path

import cv2
import numpy as np

from omnispectral.capture.session import Session
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_equirect_pixel, lonlat_to_ray
from omnispectral.io import atomic_path, atomic_write_json, atomic_write_text
from omnispectral.product.expectations import product_accuracy_warnings
from omnispectral.product.exports import write_preview
from omnispectral.product.irradiance import HORIZONTAL_NORMAL, IRRADIANCE_UNITS, irradiance, sun_sky_irradiance
from omnispectral.product.layout import open_product, product_paths
from omnispectral.product.report_edges import (
    PixelErrors,
    camera_a_covered,
    depth_edge_figures,
    hole_figures,
    hole_mask,
    pixel_errors,
    reference_white,
    region_figures,
    truth_edge_band,
    worst_pixel_indices,
    worst_pixel_summary,
    worst_pixels,
)
from omnispectral.product.report_maps import mark_worst_pixels, plot_error_maps, plot_quality
from omnispectral.product.rigfile import DIRECTION_WARNING_PX
from omnispectral.product.spectra import bands_to_linear_srgb
from omnispectral.spectral.metrics import colour_differences, nrmse

__all__ = ["MAX_PATCH_RADIANCE_SPREAD", "accuracy", "accuracy_and_pixel_errors", "calibration_basis", "chart_scores",
           "irradiance_report", "patch_bands", "pixel_error_report", "psnr_db", "store_holes", "write_report"]

#: A chart patch whose radiance varies more than this over its central 80 % (``(max − min) / mean``) is
#: crossed by a shadow edge and is not scored (module docstring).  Sky light varies < 1 % over a patch.
MAX_PATCH_RADIANCE_SPREAD = 0.05


def _resize_to(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Area average (or linear when enlarging) onto an equirect grid of ``height × width`` (same conventions)."""

    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image
    interp = cv2.INTER_AREA if h >= height else cv2.INTER_LINEAR
    chans = [cv2.resize(np.ascontiguousarray(image[..., c]), (width, height), interpolation=interp)
             for c in range(image.shape[2])]
    return np.stack(chans, axis=-1)


def _truth_grid_note(truth_width: int, width: int) -> dict:
    """The truth's grid against the panorama's: a truth rendered on another grid is area-resampled onto the
    panorama's, which spreads each of its edge pixels' mix over its whole area, so that at sharp edges the truth
    compared is up to one of its pixels blurrier than the scene (simulate with ``--gt-width`` equal to the
    product's width for exact edges)."""
    if truth_width == width:
        return {"width": int(truth_width), "resampled": False}
    return {"width": int(truth_width), "resampled": True,
            "note": f"the truth ({truth_width} px wide) is area-resampled onto the panorama's {width} px: at sharp "
                    "edges it is up to one of its pixels blurrier than the scene, which favours blurred edges"}


def _saturated_mask(saturated: np.ndarray, height: int, width: int, margin_px: int = 3) -> np.ndarray:
    """Pixels of a ``height × width`` grid touched by the ground truth's ``saturated`` pixels (with a margin
    for the interpolation kernel): the sun saturates every exposure and is flagged, not measured."""

    small = cv2.resize(saturated.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA) > 0
    return cv2.dilate(small.astype(np.uint8), np.ones((2 * margin_px + 1,) * 2, np.uint8)) > 0


def psnr_db(estimate: np.ndarray, truth: np.ndarray, valid: np.ndarray) -> float:
    """PSNR over ``valid`` pixels (all bands) with the ground truth's maximum there as the peak."""
    e, t = estimate[valid], truth[valid]
    mse = float(np.mean((e.astype(np.float64) - t) ** 2))
    return float(10 * np.log10(float(t.max()) ** 2 / mse)) if mse > 0 else float("inf")


def patch_bands(bands: np.ndarray, lon_deg: float, lat_deg: float, radius_deg: float) -> np.ndarray:
    """Mean band values within ``radius_deg`` of a direction on an equirect panorama (NaNs ignored)."""

    h, w = bands.shape[:2]
    radius_deg = max(radius_deg, 0.75 * 360.0 / w)  # at least the nearest pixel centre
    col, row = lonlat_to_equirect_pixel(lon_deg, lat_deg, w, h)
    r_px = max(1.0, radius_deg / 360.0 * w / max(np.cos(np.radians(lat_deg)), 0.05))
    r0, r1 = int(max(0, np.floor(row - r_px - 1))), int(min(h, np.ceil(row + r_px + 2)))
    c0, c1 = int(max(0, np.floor(col - r_px - 1))), int(min(w, np.ceil(col + r_px + 2)))
    rr, cc = np.mgrid[r0:r1, c0:c1]

    lon, lat = equirect_pixel_to_lonlat(cc, rr, w, h)
    centre = lonlat_to_ray(lon_deg, lat_deg)
    ang = np.degrees(np.arccos(np.clip(lonlat_to_ray(lon, lat) @ centre, -1, 1)))
    sel = bands[r0:r1, c0:c1][ang <= radius_deg]
    sel = sel[np.isfinite(sel).all(axis=1)] if sel.size else sel
    return sel.mean(axis=0) if sel.size else np.full(bands.shape[2], np.nan)


def accuracy(bands: np.ndarray, estimator, truth, shortest_s: float, max_dn: int,
             band_names: list[str] | None = None) -> dict:
    """Accuracy of a panorama against the simulator's ground truth (module docstring).

    ``truth``: the interface of :class:`omnispectral.sim.truth.GroundTruth`.  ``band_names``: the panorama's bands;
    when the truth holds more (a one-camera product compared with the truth of a two-camera simulation), the
    truth's bands of those names are compared.

    Parameters
    ----------
    bands : numpy.ndarray
        ``(H, W, m)`` panorama bands in DN/s (NaN where nothing covers a pixel).
    estimator : WienerEstimator
        The product's estimator.
    truth : GroundTruth
        The simulated session's ground truth: bands (DN/s), spectral radiance, the ColorChecker's patches.
    shortest_s : float
        The bracket's shortest exposure (s): truth values at or above ``max_dn / shortest_s`` saturate every
        exposure and are not measured.
    max_dn : int
        The largest code (DN).
    band_names : list of str, optional
        The panorama's band names.

    Returns
    -------
    dict
        ``band_psnr_db`` (dB), ``n_bands`` (and ``six_band_psnr_db`` for six bands), ``pixels_compared_fraction``,
        ``uncovered_fraction``, ``truth_grid`` (the truth's width and, where it is not the panorama's, why the
        figures at edges are then biased), ``pixel_errors``, ``spectral_nrmse`` and ``spectral_pixels``, and
        ``colorchecker``
        (per-patch and mean NRMSE and ΔE*ab, estimated and true spectra; ``None`` with a note when the chart
        is not covered).

    Raises
    ------
    ConfigurationError
        When the truth's bands do not include the panorama's.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.2, Fig. 9 (ColorChecker spectra: normalized RMSE and ΔE*ab), Fig. 11
       (spectra at points of the scene).
    .. [2] CIE 015:2018, Colorimetry, 4th ed. (CIELAB, ΔE*ab).
    """
    return accuracy_and_pixel_errors(bands, estimator, truth, shortest_s, max_dn, band_names)[0]


def accuracy_and_pixel_errors(bands: np.ndarray, estimator, truth, shortest_s: float, max_dn: int,
                              band_names: list[str] | None = None) -> tuple[dict, PixelErrors]:
    """:func:`accuracy` and the per-pixel errors behind its ``pixel_errors`` section (for the report's maps)."""

    h, w = bands.shape[:2]
    gt_bands = truth.bands()
    saturated = gt_bands.max(axis=2) >= max_dn / shortest_s  # read and reduced once
    if gt_bands.shape[2] != bands.shape[2]:
        gt_names = truth.band_names
        missing = [n for n in band_names or [] if n not in gt_names]
        if band_names is None or missing or len(band_names) != bands.shape[2]:
            raise ConfigurationError(f"{truth.directory}: the ground truth has bands {gt_names}, the panorama "
                                     f"{band_names or bands.shape[2]}")
        gt_bands = gt_bands[..., [gt_names.index(n) for n in band_names]]
    truth_grid = _truth_grid_note(gt_bands.shape[1], w)
    on_grid = _resize_to(gt_bands, h, w)
    del gt_bands
    unsaturated = ~_saturated_mask(saturated, h, w)
    covered = np.isfinite(bands).all(axis=2)
    valid = covered & unsaturated
    out: dict = {"band_psnr_db": psnr_db(bands, on_grid, valid), "n_bands": int(bands.shape[2]),
                 "pixels_compared_fraction": float(valid.mean()), "uncovered_fraction": float(1 - covered.mean()),
                 "truth_grid": truth_grid}
    if bands.shape[2] == 6:
        out["six_band_psnr_db"] = out["band_psnr_db"]
    edge, edge_note = truth_edge_band(truth, h, w)
    white, white_name = reference_white(truth)
    errors = pixel_errors(bands, on_grid, valid, estimator, white, edge, band_names)
    del on_grid
    out["pixel_errors"] = pixel_error_report(errors, white_name, edge_note)
    spectral = truth.spectral()
    sh, sw = spectral.shape[:2]
    small = _resize_to(np.where(covered[..., None], bands, np.nan).astype(np.float32), sh, sw)
    ok = np.isfinite(small).all(axis=2) & ~_saturated_mask(saturated, sh, sw)
    est = estimator.estimate(small[ok])
    out["spectral_nrmse"] = float(np.mean(nrmse(est, spectral[ok])))
    out["spectral_pixels"] = int(ok.sum())
    patches = truth.colorchecker_patches
    true = truth.colorchecker_radiance()
    if patches and true is not None:
        white = truth.colorchecker_white()
        measured = np.array([patch_bands(bands, p["lon_deg"], p["lat_deg"], 0.5 * p["half_size_deg"])
                             for p in patches])
        seen = np.isfinite(measured).all(axis=1)
        if not seen.any():
            out["colorchecker"] = None
            out["colorchecker_note"] = "the chart is not covered by the panorama"
            return out, errors
        est = np.full(true.shape, np.nan)
        est[seen] = estimator.estimate(measured[seen])
        wl = np.asarray(estimator.wavelength_nm)
        errs = np.full(len(patches), np.nan)
        de = np.full(len(patches), np.nan)
        errs[seen] = nrmse(est[seen], true[seen])
        de[seen] = colour_differences(est[seen], true[seen], white, wl)["delta_e_ab"]
        out["colorchecker"] = {**chart_scores(patches, errs, de, seen),
                               "estimated": est.tolist(), "true": true.tolist(), "wavelength_nm": wl.tolist()}
    return out, errors


def pixel_error_report(errors: PixelErrors, white_name: str, edge_note: str | None) -> dict:
    """The ``accuracy.pixel_errors`` section (:mod:`omnispectral.product.report_edges`): the per-pixel errors over
    all scored pixels, at depth edges against smooth regions (None and ``depth_edges_note`` without a depth map)
    and the worst pixels."""
    out = {"band_nrmse_definition": "sqrt(sum ||b - t||^2 / sum ||t||^2) over a region's pixels (b: panorama, "
                                    "t: truth on the panorama's grid, DN/s); per pixel (map, median, worst "
                                    "pixels): ||b - t|| / ||t||",
           "delta_e_ab_definition": "CIE 1976 Delta E*ab between the spectra the product's estimator gives from the "
                                    "panorama's bands and from the truth's bands (same estimator: the pipeline's "
                                    f"error, not the estimator's), white: {white_name}; mean over a region's pixels",
           "all": region_figures(errors, errors.scored),
           "depth_edges": depth_edge_figures(errors) if errors.edge is not None else None}
    if errors.edge is None:
        out["depth_edges_note"] = edge_note
    out["worst_pixels"] = worst_pixel_summary(worst_pixels(errors), int(errors.scored.sum()))
    return out


def irradiance_report(store, estimator, band_names: list[str], bands: np.ndarray | None = None,
                      truth=None) -> dict:
    """The report's ``irradiance`` section (module docstring): horizontal irradiance, sun/sky split, truth.

    Parameters
    ----------
    store : PanoramaStore
        The product's panorama (its ``omnispectral.sun`` record says how the sun was recovered).
    estimator : WienerEstimator
        The product's estimator (the sky's spectrum).
    band_names : list of str
        The panorama's bands (a one-camera product compared with a two-camera truth takes these of its bands).
    bands : ndarray (H, W, m), optional
        Level 0 already in memory; else the store is streamed.
    truth : GroundTruth, optional
        The ground truth of a simulation (the interface of :class:`omnispectral.sim.truth.GroundTruth`).
    """
    split = sun_sky_irradiance(store, HORIZONTAL_NORMAL, estimator=estimator, bands=bands)
    horizontal = np.asarray(split["panorama"]["band_irradiance"])
    out = {"normal": list(HORIZONTAL_NORMAL), "band_names": list(band_names), "units": IRRADIANCE_UNITS,
           "horizontal": horizontal.tolist(), "covered_fraction": split["panorama"]["covered_fraction"],
           "sun_method": split["sun_method"], "sun_recovered": split["sun_recovered"],
           "sun": split["sun"]["band_irradiance"], "sky": split["sky"]["band_irradiance"],
           "total": split["total"]["band_irradiance"], "sun_fraction": split["sun_fraction"],
           "sun_cct_K": split["sun"]["cct_K"], "sky_cct_K": split["sky"]["cct_K"],
           "total_cct_K": split["total"]["cct_K"]}
    if "note" in split:
        out["note"] = split["note"]
    if truth is not None:
        truth_e = _truth_irradiance(truth, band_names)
        ratio = horizontal / truth_e
        worst = int(np.argmax(np.abs(ratio - 1.0)))
        out.update({"truth": truth_e.tolist(), "ratio_to_truth": ratio.tolist(),
                    "worst_band": {"name": band_names[worst], "ratio_to_truth": float(ratio[worst])}})
    return out


def _truth_irradiance(truth, band_names: list[str]) -> np.ndarray:
    """Horizontal irradiance of the ground truth's bands (memory-mapped, streamed), those named ``band_names``."""
    values = irradiance(truth.bands(mmap=True), HORIZONTAL_NORMAL).band_irradiance_dn_s_sr
    if values.shape[0] == len(band_names):
        return values
    names = truth.band_names
    return values[[names.index(n) for n in band_names]]


def chart_scores(patches: list[dict], nrmse_per_patch: np.ndarray, delta_e_ab: np.ndarray, seen: np.ndarray) -> dict:
    """Mean and max ΔE*ab and mean NRMSE over the chart's seen, uniformly lit patches (module docstring);
    patches crossed by a shadow edge are listed under ``not_uniformly_lit`` with their ΔE*ab."""
    spread = np.array([float(p.get("radiance_spread", 0.0)) for p in patches])
    scored = seen & (spread <= MAX_PATCH_RADIANCE_SPREAD)
    if not scored.any():  # every seen patch crossed by a shadow: score them all rather than none
        scored = seen
    return {"n_patches_seen": int(seen.sum()), "n_patches_scored": int(scored.sum()),
            "nrmse": float(np.mean(nrmse_per_patch[scored])), "delta_e_ab": float(np.mean(delta_e_ab[scored])),
            "delta_e_ab_max": float(np.max(delta_e_ab[scored])),
            "not_uniformly_lit": [{"name": p["name"], "radiance_spread": float(sp), "delta_e_ab": float(d)}
                                  for p, sp, d, ok, s in zip(patches, spread, delta_e_ab, scored, seen, strict=True)
                                  if s and not ok],
            "per_patch": [{"name": p["name"], "nrmse": float(e), "delta_e_ab": float(d), "scored": bool(ok)}
                          for p, e, d, ok in zip(patches, nrmse_per_patch, delta_e_ab, scored, strict=True)]}


def _plot_registration(alignments: list[dict], path: Path) -> None:
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = [a["direction"] for a in alignments]
    fig, ax = plt.subplots(2, 1, figsize=(7, 4.5), dpi=110, sharex=True)
    ax[0].plot(d, [a["offset_dx_px"] for a in alignments], "o-", label="dx")
    ax[0].plot(d, [a["offset_dy_px"] for a in alignments], "s-", label="dy")
    ax[0].set_ylabel("camera B offset (px)")
    ax[0].legend(fontsize=8)
    ax[1].bar(d, [a["confidence"] for a in alignments],
              color=["tab:red" if a["used_fallback"] else "tab:blue" for a in alignments])
    ax[1].set_ylabel("POC confidence")
    ax[1].set_xlabel("direction (red: calibrated offset used)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _plot_rig_residuals(directions: list[dict], path: Path) -> None:
    """Per direction: camera B's median residual across the epipolar lines after the rig calibration."""
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = [x["direction"] for x in directions]
    r = [x["median_perpendicular_px"] if x["median_perpendicular_px"] is not None else np.nan for x in directions]
    fig, ax = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    ax[0].bar(d, r, color=["tab:red" if v > DIRECTION_WARNING_PX else "tab:blue" for v in np.nan_to_num(r)])
    ax[0].axhline(DIRECTION_WARNING_PX, color="k", ls="--", lw=0.8)
    ax[0].set_ylabel("median |residual| (px)")
    ax[0].set_title("Camera B against the fitted rig model (across epipolar lines)")
    ax[1].bar(d, [x["n_blocks"] for x in directions], color="tab:gray")
    ax[1].set_ylabel("blocks measured")
    ax[1].set_xlabel("direction")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _plot_chart(chart: dict, path: Path) -> None:
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wl = np.asarray(chart["wavelength_nm"])
    est, true = np.asarray(chart["estimated"]), np.asarray(chart["true"])
    fig, axes = plt.subplots(4, 6, figsize=(12, 7), dpi=90, sharex=True)
    for i, ax in enumerate(axes.ravel()):
        n = np.linalg.norm(true[i]) or 1.0
        ax.plot(wl, true[i] / n, "k-", lw=1.2)
        ax.plot(wl, est[i] / max(np.linalg.norm(est[i]), 1e-30), "r--", lw=1.2)
        p = chart["per_patch"][i]
        ax.set_title(f"{p['name'][:14]}  ΔE {p['delta_e_ab']:.1f}", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle("ColorChecker in the panorama: ground truth (black) vs estimate (red dashed), unit-norm spectra")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def write_report(product: str | Path, preview_width: int = 2048, truth=None) -> dict:
    """Write ``report/report.json``, ``report.html`` and its PNGs for a processed product.

    Parameters
    ----------
    product : str or Path
        The product folder.
    preview_width : int
        Largest width of the preview and maps (the pyramid level at or below it).
    truth : GroundTruth, optional
        The ground truth of a simulated session (the interface of :class:`omnispectral.sim.truth.GroundTruth`,
        which the caller opens: processing never imports the simulator); with it the report gains the
        ``accuracy`` section, the error maps and the truth's irradiance.

    Returns
    -------
    dict
        ``{"report": the report.json content, "files": the files written}``.
    """

    paths = product_paths(product)
    index, store, estimator = open_product(product)
    out_dir = paths["report"]
    out_dir.mkdir(parents=True, exist_ok=True)
    level = next((k for k, (_, w) in enumerate(store.shapes) if w <= preview_width), len(store.shapes) - 1)
    preview = store.read(level)
    files = {"preview": str(write_preview(out_dir / "preview.png", bands_to_linear_srgb(preview, estimator)))}
    reg = index["registration"]
    alignments = reg["directions"]
    if alignments and reg.get("method", "paper") == "paper":
        _plot_registration(alignments, out_dir / "registration.png")
        files["registration_plot"] = str(out_dir / "registration.png")
    elif reg.get("method") == "parallax" and reg.get("rig_calibration", {}).get("directions"):
        _plot_rig_residuals(reg["rig_calibration"]["directions"], out_dir / "registration.png")
        files["registration_plot"] = str(out_dir / "registration.png")
    report = {"product": str(paths["root"]), "rig": index["rig"], "session": index["session"],
              "size": [index["height"], index["width"]], "n_bands": len(index["bands"]),
              "timings_s": index["timings_s"],
              "registration_method": reg.get("method", "paper"), "registration": alignments,
              "rig_calibration": reg.get("rig_calibration"), "registration_warnings": reg.get("warnings", []),
              "skipped_directions": index["skipped_directions"],
              "accuracy_warnings": product_accuracy_warnings(index), "accuracy": None}
    bands = errors = None
    if truth is not None:
        s = Session.open(index["session"])
        rig = s.rig()
        bands = store.read(0)
        report["accuracy"], errors = accuracy_and_pixel_errors(bands, estimator, truth, min(s.plan().exposures_s),
                                                               rig.camera_a.max_dn, index["bands"])
        if report["accuracy"].get("colorchecker"):
            _plot_chart(report["accuracy"]["colorchecker"], out_dir / "colorchecker.png")
            files["colorchecker_plot"] = str(out_dir / "colorchecker.png")
    report["irradiance"] = irradiance_report(store, estimator, index["bands"], bands, truth)
    report["holes"], holes_px = store_holes(store, index["bands"], bands)
    files.update(_write_maps(store, out_dir, level, errors, holes_px))
    report["files"] = files
    atomic_write_json(out_dir / "report.json", report)
    atomic_write_text(out_dir / "report.html", _html(report))
    files["json"] = str(out_dir / "report.json")
    files["html"] = str(out_dir / "report.html")
    return {"report": report, "files": files}


def store_holes(store, band_names: list[str], bands: np.ndarray | None = None,
                rows_per_block: int = 1024) -> tuple[dict, np.ndarray]:
    """The ``holes`` section (:func:`~omnispectral.product.report_edges.hole_figures`) and the level-0 hole mask,
    from ``bands`` (level 0) when in memory, else streamed from the store ``rows_per_block`` rows at a time."""
    h, w = store.shapes[0]
    mask = np.zeros((h, w), bool)
    n_a_covered = 0
    for r0 in range(0, h, rows_per_block):
        r1 = min(h, r0 + rows_per_block)
        block = bands[r0:r1] if bands is not None else store.read(0, rows=slice(r0, r1))
        mask[r0:r1] = hole_mask(block, band_names)
        n_a_covered += int(camera_a_covered(block, band_names).sum())
    return hole_figures(int(mask.sum()), n_a_covered), mask


def _write_maps(store, out_dir: Path, level: int, errors: PixelErrors | None, holes_px: np.ndarray) -> dict:
    """The report's maps (:mod:`omnispectral.product.report_maps`) at pyramid level ``level``: the quality layer
    (every product that has one) and, for simulations, the error maps and the worst pixels on the preview."""
    height, width = store.shapes[level]
    files = {}
    if store.has_quality():
        layers = (store.attrs()["omnispectral"].get("quality") or {}).get("layers") or []
        if layers:
            files["quality_map"] = str(plot_quality(store.read_quality(), layers, height, width,
                                                    out_dir / "quality.png"))
    if errors is not None:
        files["error_map"] = str(plot_error_maps(errors, height, width, out_dir / "error_map.png"))
    rows, cols = worst_pixel_indices(errors) if errors is not None else (np.zeros(0, int), np.zeros(0, int))
    if rows.size or holes_px.any():
        files["worst_pixels_map"] = str(mark_worst_pixels(out_dir / "preview.png", rows, cols, holes_px,
                                                          store.shapes[0], out_dir / "worst_pixels.png"))
    return files


def calibration_basis(calibration: dict) -> str:
    """What camera B's mounting was fitted from, in a few words: the chessboard corners of K views (with B's corner
    RMS and the stated standard deviations) or the blocks of a session's images (with the residual across the
    epipolar lines and the far anchor).

    Parameters
    ----------
    calibration
        The rig calibration's JSON object (:meth:`omnispectral.product.rigfile.RigCalibration.to_dict`, as in
        ``product.json``'s ``registration.rig_calibration``).

    Returns
    -------
    str
        E.g. ``"324 chessboard corners of 6 views (camera B's corner RMS 0.031 px; ± 0.0040° yaw, …)"``.
    """
    def px(v) -> str:
        return "–" if v is None else f"{v:.3f}"

    board = calibration.get("chessboard")
    if calibration.get("method") == "chessboard" and board:
        sd = board.get("std_deg") or {}
        stated = (f"; ± {sd['yaw']:.4f}° yaw, {sd['pitch']:.4f}° pitch, {sd['roll']:.4f}° roll"
                  if all(k in sd for k in ("yaw", "pitch", "roll")) else "")
        return (f"{calibration.get('n_blocks', 0)} chessboard corners of {board.get('n_pairs', '?')} views (camera B's "
                f"corner RMS {px(board.get('rms_b_px'))} px{stated})")
    anchor = calibration.get("far_anchor") or {}
    n_dirs = len(anchor.get("directions") or [])
    rms = px(calibration.get("rms_perpendicular_px"))
    return (f"{calibration.get('n_inliers', 0)} of {calibration.get('n_blocks', 0)} blocks of the session's images "
            f"(RMS residual across the epipolar lines {rms} px; infinity anchored on {anchor.get('n_blocks', 0)} "
            f"blocks in {n_dirs} direction{'' if n_dirs == 1 else 's'})")


def _accuracy_warnings_html(warnings: list[dict]) -> str:
    """The accuracy limits of the run (:mod:`omnispectral.product.expectations`), one item each."""
    if not warnings:
        return "<p>None found from the rig, the run's settings and the session's own measurements.</p>"
    return "<ul>" + "".join(f"<li>{html.escape(w['message'])}</li>" for w in warnings) + "</ul>"


def _html(report: dict) -> str:
    acc = report.get("accuracy")
    rows = "".join(f"<tr><td>{k}</td><td>{v:.2f} s</td></tr>" for k, v in report["timings_s"].items())
    acc_html = "<p>No readable ground truth (a real capture, or its truth is damaged).</p>"
    if acc:
        cc = acc.get("colorchecker") or {}
        acc_html = (f"<table><tr><td>{acc['n_bands']}-band PSNR</td><td>{acc['band_psnr_db']:.2f} dB</td></tr>"
                    f"<tr><td>spectral NRMSE (panorama)</td><td>{acc['spectral_nrmse']:.4f}</td></tr>"
                    + (f"<tr><td>ColorChecker NRMSE</td><td>{cc['nrmse']:.4f}</td></tr>"
                       f"<tr><td>ColorChecker ΔE*ab (mean / max)</td><td>{cc['delta_e_ab']:.2f} / "
                       f"{cc['delta_e_ab_max']:.2f}</td></tr>" if cc else "")
                    + "".join(f"<tr><td>not scored: {html.escape(x['name'])}</td><td>shadow edge (radiance "
                              f"spread {x['radiance_spread']:.0%}), ΔE*ab {x['delta_e_ab']:.2f}</td></tr>"
                              for x in cc.get("not_uniformly_lit", [])) + "</table>"
                    + ('<img src="colorchecker.png" width="900">' if cc else ""))
    if report.get("registration_method") == "none":
        reg_html = "<p>One camera: nothing to register.</p>"
    elif report.get("registration_method") == "parallax":
        cal = report.get("rig_calibration") or {}
        delta = cal.get("delta_from_rig_file_deg", {})
        warn = "".join(f"<li>{html.escape(w)}</li>" for w in report.get("registration_warnings", []))
        reg_html = (f"<p>Camera B's mounting fitted from {html.escape(calibration_basis(cal))}; change from the rig "
                    f"file: yaw {delta.get('yaw', 0):+.3f}°, pitch {delta.get('pitch', 0):+.3f}°"
                    f", roll {delta.get('roll', 0):+.3f}°. Per-pixel parallax in {len(report['registration'])} "
                    "directions.</p>" + (f"<ul>{warn}</ul>" if warn else "")
                    + ('<img src="registration.png" width="760">'
                       if "registration_plot" in report.get("files", {}) else ""))
    else:
        n_fallback = sum(a["used_fallback"] for a in report["registration"])
        reg_html = (f"<p>{len(report['registration'])} directions, {n_fallback} used the calibrated offset (low "
                    'confidence).</p><img src="registration.png" width="760">')
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>omnispectral report: {report['rig']}</title>
<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}}td{{padding:2px 12px}}</style></head><body>
<h1>omnispectral report</h1><p>Product {report['product']} from session {report['session']} (rig {report['rig']}),
{report['size'][1]} × {report['size'][0]} px, {report['n_bands']} bands.</p>
<h2>Accuracy limits of this run</h2>{_accuracy_warnings_html(report.get("accuracy_warnings") or [])}
<h2>Preview</h2><img src="preview.png" width="960">
<p>sRGB rendering of the Wiener estimate, global Reinhard tone map.</p>
<h2>Accuracy against ground truth</h2>{acc_html}
<h2>Where the error is</h2>{_pixel_errors_html(acc, report.get("holes"), report.get("files", {}))}
<h2>Horizontal irradiance</h2>{_irradiance_html(report.get("irradiance"))}
<h2>Registration of camera B to A</h2>{reg_html}
<h2>Timings</h2><table>{rows}</table>
<p>Skipped directions: {len(report['skipped_directions'])}.</p></body></html>
"""


def _pixel_errors_html(acc: dict | None, holes: dict | None, files: dict) -> str:
    """The per-pixel section: holes, the edge / smooth table, the error map, the worst pixels, the quality layer."""
    parts = []
    if holes is not None:
        parts.append(f"<p>Holes (camera A covers the pixel, some band is missing): <b>{holes['n_pixels']}</b> "
                     f"pixels of {holes['a_covered_pixels']} ({holes['fraction_of_a_covered']:.4%})"
                     + (", cyan dots on the image below" if holes["n_pixels"] else "") + ".</p>")
    pe = (acc or {}).get("pixel_errors")
    if pe:
        parts.append(_edge_table_html(pe))
        if "error_map" in files:
            parts.append('<img src="error_map.png" width="960">')
        worst = pe["worst_pixels"]
        share = worst["at_depth_edge_fraction"]
        parts.append(f"<p>Worst {worst['fraction']:.1%} of the scored pixels by band NRMSE ({worst['n']}, band NRMSE "
                     f"≥ {worst['band_nrmse_min'] or 0:.3g})"
                     + (f", {share:.0%} of them at depth edges" if share is not None else "")
                     + ": red rings (listed with longitude, latitude and errors in report.json).</p>")
    elif acc:
        parts.append("<p>Per-pixel errors not measured.</p>")
    if "worst_pixels_map" in files:
        parts.append('<img src="worst_pixels.png" width="960">')
    if "quality_map" in files:
        parts.append("<h3>Quality layer</h3><p>Every layer of the panorama's quality array (level 0).</p>"
                     '<img src="quality.png" width="960">')
    return "".join(parts) or "<p>Nothing to show.</p>"


def _edge_table_html(pe: dict) -> str:
    """All scored pixels, depth edges, smooth regions and edge / smooth, or why the edges are not measured."""
    def num(v, fmt: str) -> str:
        return "–" if v is None else format(v, fmt)

    regions = [("all scored pixels", pe["all"])]
    de = pe.get("depth_edges")
    if de:
        regions += [(f"depth edges (≤ {de['radius_px']:g} px, {de['edge_fraction']:.1%})", de["edge"]),
                    ("smooth regions", de["smooth"])]
    rows = "".join(f"<tr><td>{html.escape(name)}</td><td>{r['n_pixels']}</td><td>{num(r['band_nrmse'], '.4f')}</td>"
                   f"<td>{num(r['band_nrmse_median'], '.4f')}</td><td>{num(r['delta_e_ab'], '.2f')}</td>"
                   f"<td>{num(r['delta_e_ab_median'], '.2f')}</td></tr>" for name, r in regions)
    if de:
        q = de["ratio"]
        rows += (f"<tr><td><b>edge / smooth</b></td><td></td><td><b>{num(q['band_nrmse'], '.2f')}</b></td>"
                 f"<td>{num(q['band_nrmse_median'], '.2f')}</td><td><b>{num(q['delta_e_ab'], '.2f')}</b></td>"
                 f"<td>{num(q['delta_e_ab_median'], '.2f')}</td></tr>")
    note = "" if de else f"<p>Depth edges not measured: {html.escape(pe.get('depth_edges_note') or '')}.</p>"
    if de and "band_nrmse_by_camera" in de["edge"]:
        note += ("<p>Band NRMSE per camera, depth edges / smooth regions (camera A is not registered: what B adds at "
                 "the edges is its registration): " + "; ".join(
                     f"{html.escape(c)} {num(v, '.4f')} / {num(de['smooth']['band_nrmse_by_camera'][c], '.4f')} "
                     f"({num(de['ratio']['band_nrmse_by_camera'][c], '.1f')}×)"
                     for c, v in de["edge"]["band_nrmse_by_camera"].items()) + ".</p>")
    return ("<table><tr><th>pixels</th><th>n</th><th>band NRMSE</th><th>median</th><th>ΔE*ab mean</th>"
            f"<th>median</th></tr>{rows}</table>{note}<p>Band NRMSE: {html.escape(pe['band_nrmse_definition'])}. "
            f"ΔE*ab: {html.escape(pe['delta_e_ab_definition'])}.</p>")


def _irradiance_html(irr: dict | None) -> str:
    """The ``irradiance`` section as a small table (one row per band) and a line on the sun and the CCTs."""
    if not irr:
        return "<p>Not computed.</p>"

    def num(v) -> str:
        return "–" if v is None else f"{v:.4g}"

    def kelvin(v) -> str:
        return "–" if v is None else f"{v:.0f} K"

    truth = irr.get("truth")
    head = ("<tr><th>band</th><th>panorama</th><th>sun</th><th>sky</th>"
            + ("<th>truth</th><th>panorama / truth</th>" if truth else "") + "</tr>")
    rows = "".join(
        f"<tr><td>{html.escape(name)}</td><td>{num(irr['horizontal'][i])}</td><td>{num(irr['sun'][i])}</td>"
        f"<td>{num(irr['sky'][i])}</td>"
        + (f"<td>{num(truth[i])}</td><td>{irr['ratio_to_truth'][i]:.4f}</td>" if truth else "") + "</tr>"
        for i, name in enumerate(irr["band_names"]))
    if irr["sun_recovered"]:
        sun = f"Sun recovered ({html.escape(irr['sun_method'])}), painted into the panorama."
    else:
        sun = f"Sun not recovered ({html.escape(irr['sun_method'])}): {html.escape(irr.get('note', ''))}."
    worst = irr.get("worst_band")
    worst_text = (f" Worst band against the truth: {html.escape(worst['name'])} "
                  f"({worst['ratio_to_truth']:.4f})." if worst else "")
    return (f"<p>On a horizontal plane facing up, {html.escape(irr['units'])}; "
            f"{irr['covered_fraction']:.1%} of the upper hemisphere (cosine-weighted) covered. {sun} "
            f"CCT: sun {kelvin(irr['sun_cct_K'])}, sky {kelvin(irr['sky_cct_K'])}, "
            f"total {kelvin(irr['total_cct_K'])}.{worst_text}</p><table>{head}{rows}</table>")
