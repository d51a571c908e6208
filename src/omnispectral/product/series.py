"""Time-lapse products (paper Sec. 5.3, Fig. 13): every slot processed, a time stack, region spectra over the day.

``process_series(SERIES, OUT)`` processes each complete session of a time-lapse series
(:mod:`omnispectral.capture.timelapse`) into ``OUT/slot_HHMM/`` (resumable: finished products are kept),
stacks one pyramid level of every panorama into ``OUT/timestack.zarr`` (array ``(t, y, x, band)``,
float32 DN/s, attribute ``times``), and for each region (a longitude/latitude box) estimates the
spectral power distribution of the region's median band values at every time: ``OUT/region_spectra.json``
and ``OUT/region_spectra.png`` (one panel per region, one curve per time — the paper's Fig. 13).  Beside
them, per slot, the horizontal irradiance split into the recovered sun and the sky with their correlated
colour temperatures (:func:`omnispectral.product.irradiance.sun_sky_irradiance`): ``irradiance`` in
``region_spectra.json`` and ``OUT/irradiance.png`` (irradiance of sun, sky and total on a log scale, and
the CCTs of sun and sky, over the day).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from omnispectral.capture.calviews import calibration_folder, has_views
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.io import atomic_path, atomic_write_json
from omnispectral.ownership import check_output_outside_inputs, claim_output_directory
from omnispectral.product.irradiance import HORIZONTAL_NORMAL, IRRADIANCE_UNITS, sun_sky_irradiance
from omnispectral.product.layout import open_product, product_paths, read_index
from omnispectral.product.process import ProcessOptions, process
from omnispectral.progress import ProgressCallback, report_progress

__all__ = ["DEFAULT_REGIONS", "parse_region", "process_series", "region_pixels", "series_products",
           "slot_calibrations", "slot_finished"]

#: Default regions: the sky high above the horizon and the ground near the rig.
DEFAULT_REGIONS = {"sky": (-180.0, 180.0, 45.0, 75.0), "ground": (-180.0, 180.0, -75.0, -45.0)}


def parse_region(text: str) -> tuple[str, tuple[float, float, float, float]]:
    """``NAME:LON0,LON1,LAT0,LAT1`` (degrees) → name and box."""
    try:
        name, box = text.split(":", 1)
        lon0, lon1, lat0, lat1 = (float(v) for v in box.split(","))
    except ValueError:
        raise ConfigurationError(f"region {text!r} is not NAME:LON0,LON1,LAT0,LAT1 (degrees)") from None
    if not (-180 <= lon0 < lon1 <= 180 and -90 <= lat0 < lat1 <= 90):
        raise ConfigurationError(f"region {text!r}: need -180 <= LON0 < LON1 <= 180 and -90 <= LAT0 < LAT1 <= 90")
    return name, (lon0, lon1, lat0, lat1)


def slot_finished(product: str | Path) -> bool:
    """Whether a slot's product went through every stage of :func:`~omnispectral.product.process.process`, the
    report included: ``product.json`` is readable and lists the report's files, and they exist.

    ``process`` writes ``product.json`` before the report and again with the report's files after it, so a run
    killed while the report is written leaves a ``product.json`` without them: that slot is not finished.

    Parameters
    ----------
    product : str or pathlib.Path
        A slot's product directory.

    Returns
    -------
    bool
        True when the product and its report are complete.
    """
    try:
        index = json.loads((Path(product) / "product.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    files = index.get("report") if isinstance(index, dict) else None
    if not isinstance(files, dict) or "json" not in files:
        return False
    report = product_paths(product)["report"]  # by name: the product may have moved since its paths were recorded
    return all(isinstance(f, str) and (report / Path(f).name).is_file() for f in files.values())


def slot_calibrations(products: list[Path]) -> dict:
    """Which calibration of camera B the slots used (the first slot's ``rig_calibration_source``) and each
    slot's warning on how far off its far content may be (``{slot: line}``, only the slots that have one)."""
    registrations = {p.name: read_index(p)["registration"] for p in products}
    first = registrations[products[0].name].get("rig_calibration_source") if products else None
    far = {name: (reg.get("far_content") or {}).get("warning") for name, reg in registrations.items()}
    return {"rig_calibration_source": first, "far_content_warnings": {k: v for k, v in far.items() if v}}


def region_pixels(box, height: int, width: int) -> tuple[slice, slice]:
    """Rows and columns of an equirect grid whose pixel centres fall in a lon/lat box."""
    lon0, lon1, lat0, lat1 = box
    cols = np.flatnonzero(((np.arange(width) + 0.5) / width * 360 - 180 >= lon0)
                          & ((np.arange(width) + 0.5) / width * 360 - 180 <= lon1))
    rows = np.flatnonzero((90 - (np.arange(height) + 0.5) / height * 180 >= lat0)
                          & (90 - (np.arange(height) + 0.5) / height * 180 <= lat1))
    if rows.size == 0 or cols.size == 0:
        raise ConfigurationError(f"region {box} holds no pixel of a {width}x{height} panorama")
    return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def process_series(series: str | Path, output: str | Path, regions: dict | None = None, stack_width: int = 1024,
                   progress: ProgressCallback | None = None, rig_calibration: str | Path | None = None,
                   truth_of=None) -> dict:
    """Process every complete slot of a series, stack the panoramas and analyse region spectra over time.

    Camera B's mounting comes from ``rig_calibration`` (e.g. ``calibrate rig --chessboard``) for every slot,
    else from the series' chessboard views (``SERIES/calibration/``, one mounting for the whole series: every
    slot finds them, fitted once and cached there), else it is fitted on the first slot and reused for the
    others.  ``progress(stage, done, total)`` follows the slots (stage ``slots``) and each slot's processing.
    The summary names the calibration (``rig_calibration_source``) and each slot's far-content warning.
    ``truth_of(session folder)``: a simulated slot's ground truth for its report, or None
    (:meth:`omnispectral.sim.truth.GroundTruth.of_session`).

    Parameters
    ----------
    series : str or pathlib.Path
        The time-lapse series directory (``series.json`` and one session per slot); only complete slots
        are processed.
    output : str or pathlib.Path
        The output directory: a product per slot, ``timestack.zarr``, ``region_spectra.json/.png``,
        ``irradiance.png`` and ``series_product.json``.
    regions : dict, optional
        Region name → ``(lon0, lon1, lat0, lat1)`` box in degrees (:func:`parse_region`); default
        :data:`DEFAULT_REGIONS` (sky and ground).
    stack_width : int
        Width (px) of the time stack: the first pyramid level at most this wide (else the coarsest).
    progress : ProgressCallback, optional
        ``progress("slots", done, total)`` after each slot, and each slot's processing stages.
    rig_calibration : str or pathlib.Path, optional
        Camera B's calibration file for every slot.
    truth_of : callable, optional
        ``truth_of(session_dir)`` → a simulated slot's ground truth (or ``None``).

    Returns
    -------
    dict
        ``output``, ``n_slots``, ``timestack`` (path), ``stack_shape``, ``region_spectra``, ``plot`` and
        ``irradiance_plot`` (paths), ``regions`` (names) and the calibration the slots used
        (:func:`slot_calibrations`); also written to ``series_product.json``.

    Raises
    ------
    InputFileError
        For a directory without ``series.json``, a series without a complete slot, or slots whose panoramas
        differ in size.
    ConfigurationError
        For a region that holds no pixel.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 5.3, Fig. 12 (time-lapse omnidirectional sequence), Fig. 13 (spectral
       power distributions of fixed regions over the day), Eq. (7) (their Wiener estimates).
    .. [2] CIE 015:2018, Colorimetry, 4th ed. (the correlated colour temperatures of sun and sky; Ohno 2013's
       method).
    """
    import zarr  # lazy: zarr costs ~0.25 s to import; only the time stack needs it here

    series, out = Path(series), Path(output)
    try:
        index = json.loads((series / "series.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputFileError(series, "not a time-lapse series (no series.json)") from None
    slots = [e for e in index["slots"] if e["status"] == "complete"]
    if not slots:
        raise InputFileError(series / "series.json", "no complete slot to process")
    regions = regions or DEFAULT_REGIONS
    check_output_outside_inputs([out], [series, rig_calibration])
    claim_output_directory(out, "process-series")
    products, times = [], []
    calibration = rig_calibration  # else the series' views, else fitted on the first slot and reused
    series_views = rig_calibration is None and has_views(calibration_folder(series))
    for i, e in enumerate(slots):
        prod = out / e["session"]
        if not slot_finished(prod):  # a slot killed in any stage, its report included, is processed again (resumes)
            options = ProcessOptions(report=True, rig_calibration=calibration,
                                     truth=truth_of(series / e["session"]) if truth_of else None)
            process(series / e["session"], prod, options=options, progress=progress)
        report_progress(progress or None, "slots", i + 1, len(slots))
        if calibration is None and not series_views and product_paths(prod)["rig_calibration"].is_file():
            calibration = product_paths(prod)["rig_calibration"]
        products.append(prod)
        times.append(e["time"])
    # time stack of one pyramid level
    first_index, store, estimator = open_product(products[0])
    level = next((k for k, (_, w) in enumerate(store.shapes) if w <= stack_width), len(store.shapes) - 1)
    h, w = store.shapes[level]
    nb = store.n_bands  # six, or three for a one-camera rig
    stack_path = out / "timestack.zarr"
    group = zarr.open_group(str(stack_path), mode="w", zarr_format=3)
    arr = group.create_array("bands", shape=(len(products), h, w, nb), chunks=(1, min(h, 512), min(w, 512), nb),
                             dtype="float32", fill_value=np.nan, dimension_names=("t", "y", "x", "band"))
    analysis: dict = {"times": times, "regions": {}, "wavelength_nm": list(map(float, estimator.wavelength_nm))}
    for name in regions:
        analysis["regions"][name] = {"box_deg": list(regions[name]), "spd": [], "median_bands": []}
    analysis["irradiance"] = _new_irradiance_series(first_index["bands"])
    for t, prod in enumerate(products):
        _, st, est = open_product(prod)
        if st.shapes[level] != (h, w):
            raise InputFileError(prod, f"panorama level {level} is {st.shapes[level]}, the series' is {(h, w)}")
        bands = st.read(level)
        arr[t] = bands
        for name, box in regions.items():
            rows, cols = region_pixels(box, h, w)
            px = bands[rows, cols].reshape(-1, nb)
            px = px[np.isfinite(px).all(axis=1)]
            med = np.median(px, axis=0) if px.size else np.full(nb, np.nan)
            spd = est.estimate(med[None])[0] if px.size else np.full(len(est.wavelength_nm), np.nan)
            analysis["regions"][name]["median_bands"].append(med.tolist())
            analysis["regions"][name]["spd"].append(spd.tolist())
        _append_irradiance(analysis["irradiance"], sun_sky_irradiance(prod, HORIZONTAL_NORMAL, estimator=est))
    group.attrs.update({"times": times, "level": level, "units": first_index["units"],
                        "bands": first_index["bands"], "products": [str(p) for p in products]})
    atomic_write_json(out / "region_spectra.json", analysis)
    _plot_region_spectra(analysis, out / "region_spectra.png")
    _plot_irradiance(analysis, out / "irradiance.png")
    summary = {"output": str(out), "n_slots": len(products), "timestack": str(stack_path),
               "stack_shape": [len(products), h, w, nb], "region_spectra": str(out / "region_spectra.json"),
               "plot": str(out / "region_spectra.png"), "irradiance_plot": str(out / "irradiance.png"),
               "regions": list(regions), **slot_calibrations(products)}
    atomic_write_json(out / "series_product.json", summary)
    return summary


def _new_irradiance_series(band_names: list[str]) -> dict:
    """The empty ``irradiance`` entry of the analysis: one list element per slot is appended."""
    keys = ("sun_method", "sun_recovered", "panorama", "covered_fraction", "sun", "sky", "total",
            "sun_cct_K", "sky_cct_K", "total_cct_K")
    return {"normal": list(HORIZONTAL_NORMAL), "units": IRRADIANCE_UNITS, "band_names": list(band_names),
            **{k: [] for k in keys}}


def _append_irradiance(series: dict, split: dict) -> None:
    """Append one slot's :func:`~omnispectral.product.irradiance.sun_sky_irradiance` (horizontal) to ``series``."""
    series["sun_method"].append(split["sun_method"])
    series["sun_recovered"].append(split["sun_recovered"])
    series["panorama"].append(split["panorama"]["band_irradiance"])
    series["covered_fraction"].append(split["panorama"]["covered_fraction"])
    for part in ("sun", "sky", "total"):
        series[part].append(split[part]["band_irradiance"])
        series[f"{part}_cct_K"].append(split[part]["cct_K"])


def series_products(output: str | Path) -> list[tuple[str, Path]]:
    """``(time ISO 8601, product directory)`` of every slot of a :func:`process_series` output, in time order."""
    import zarr  # lazy: zarr costs ~0.25 s to import; only the time stack needs it here

    out = Path(output)
    stack = out / "timestack.zarr"
    try:
        attrs = zarr.open_group(str(stack), mode="r", zarr_format=3).attrs.asdict()
        times, products = list(attrs["times"]), list(attrs["products"])
    except Exception as exc:  # zarr raises several types for a missing or foreign store
        raise InputFileError(stack, f"not the time stack of a processed series ({type(exc).__name__})") from None
    slots = []
    for time, product in zip(times, products, strict=True):
        path = out / Path(product).name  # slot products are children of the output (paths recorded may be relative)
        if not (path / "product.json").is_file():
            raise InputFileError(path, f"the product of slot {time} is missing")
        slots.append((time, path))
    return slots


def _plot_region_spectra(analysis: dict, path: Path) -> None:
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    wl = np.asarray(analysis["wavelength_nm"])
    names = list(analysis["regions"])
    fig, axes = plt.subplots(1, len(names), figsize=(5.5 * len(names), 4), dpi=110, squeeze=False)
    cmap = plt.get_cmap("viridis")
    n = len(analysis["times"])
    for ax, name in zip(axes[0], names, strict=True):
        for t, spd in enumerate(analysis["regions"][name]["spd"]):
            ax.plot(wl, spd, color=cmap(t / max(n - 1, 1)), label=analysis["times"][t][11:16])
        ax.set_title(f"{name}: spectral power distribution over the day")
        ax.set_xlabel("wavelength (nm)")
        ax.set_ylabel("spectral radiance (DN/s per unit of R)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def _hours(times: list[str]) -> np.ndarray:
    """Hours of the day of ISO 8601 times (``YYYY-MM-DDTHH:MM…``, the slots' local time)."""
    return np.array([int(t[11:13]) + int(t[14:16]) / 60.0 for t in times])


def _plot_irradiance(analysis: dict, path: Path) -> None:
    """Horizontal irradiance (mean over the bands) of sun, sky and total on a log scale, and the CCTs of sun and sky,
    over the day."""
    import matplotlib  # lazy: matplotlib (pyplot) is needed for this plot only, and the backend must be set first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    irr = analysis["irradiance"]
    hours = _hours(analysis["times"])
    fig, (ax_e, ax_t) = plt.subplots(1, 2, figsize=(11, 4), dpi=110)
    for part, style in (("total", "k-o"), ("sun", "-o"), ("sky", "-s")):
        mean = np.array([np.mean(v) for v in irr[part]], float)
        ok = mean > 0  # log scale: an unrecovered sun (0) is left out
        ax_e.plot(hours[ok], mean[ok], style, label=part, markersize=4)
    ax_e.set_yscale("log")
    ax_e.set_title("horizontal irradiance over the day")
    ax_e.set_ylabel("mean band irradiance (DN/s·sr)")
    for part, style in (("sun", "-o"), ("sky", "-s")):
        cct = np.array([np.nan if v is None else v for v in irr[f"{part}_cct_K"]], float)
        ok = np.isfinite(cct)
        ax_t.plot(hours[ok], cct[ok], style, label=part, markersize=4)
    ax_t.set_title("correlated colour temperature (CIE 015:2018)")
    ax_t.set_ylabel("CCT (K)")
    if not all(irr["sun_recovered"]):
        ax_e.text(0.02, 0.02, "sun not recovered in some slots: the sky holds its lower bound",
                  transform=ax_e.transAxes, fontsize=7)
    for ax in (ax_e, ax_t):
        ax.set_xlabel("time of day (h)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
