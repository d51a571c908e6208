"""The demo: simulate the paper's time-lapse geometry on the procedural scene, process, export, report,
and use the product as the paper does (Sec. 6): a rendered mirror ball and a relit preview.

:func:`run_demo` is what ``omnispectral demo`` (and ``make demo``) runs; it writes ``OUT/session``
(raw frames, journal, ground truth), ``OUT/product`` (six-band panorama, estimator, report), the
standard exports, the applications' files and ``OUT/report.json`` (accuracy, timings, files) and
returns that summary.  The applications are small on purpose (the whole demo stays within its time
budget): the mirror ball at 128 × 128 px, 16 spp, on a 10 nm grid (31 wavelengths, 11 Mitsuba passes);
relighting to illuminant A from the ColorChecker's white patch, whose direction and reflectance the
simulated session's ground truth gives.
"""

from __future__ import annotations

import datetime as _dt
import json
import time
from collections.abc import Callable
from pathlib import Path

from omnispectral.apps.relight import WhiteReference, relight_product
from omnispectral.apps.render import render_product
from omnispectral.io import atomic_write_json
from omnispectral.ownership import claim_output_directory
from omnispectral.product.exports import export_product
from omnispectral.product.layout import product_paths
from omnispectral.product.process import process
from omnispectral.progress import ProgressCallback
from omnispectral.rig import load_preset
from omnispectral.sim.scenes import DEFAULT_DATE, build_scene
from omnispectral.sim.simulate import simulate_session
from omnispectral.sim.truth import GroundTruth

__all__ = ["DEMO_EXPORTS", "calibration_summary", "demo_applications", "run_demo"]

#: The exports the demo writes, ``(format, file name)``.
DEMO_EXPORTS = (("spectral-exr", "panorama_spectral.exr"), ("png", "panorama_preview.png"),
                ("rgb-exr", "panorama_rgb.exr"), ("hdr", "panorama_rgb.hdr"), ("envi", "panorama_envi.hdr"),
                ("uncertainty", "panorama_uncertainty.exr"))


def run_demo(out: str | Path, *, full: bool = False, time_hhmm: str = "12:00", seed: int = 0,
             on_step: Callable[[int, int, str], None] | None = None,
             progress: ProgressCallback | None = None) -> dict:
    """Simulate (the ``small`` rig, or ``paper-timelapse`` with ``full``), process, export and report.

    ``on_step(k, n, description)`` announces each of the four steps; ``progress(stage, done, total)``
    follows the frames and the processing stages.  Returns the summary written to ``OUT/report.json``
    with the product report's full ``accuracy`` (the file keeps the ColorChecker numbers, not its spectra).
    """
    out = claim_output_directory(out, "demo")
    step = on_step or (lambda k, n, text: None)
    rig = load_preset("paper-timelapse" if full else "small")
    start = _dt.datetime.combine(DEFAULT_DATE, _dt.time.fromisoformat(time_hhmm), tzinfo=_dt.UTC)
    t0 = time.perf_counter()
    step(1, 4, f"simulate the {rig.name} rig ({rig.camera_a.width_px}×{rig.camera_a.height_px}, 36 directions × "
               f"2 cameras × {len(rig.bracket.exposures_s)} exposures) on the procedural scene at {time_hhmm}, and "
               "the rig's chessboard calibration views")
    sim = simulate_session(out / "session", rig, build_scene("procedural", None, start, seed=seed), start=start,
                           seed=seed, progress=progress)
    step(2, 4, f"process into {out / 'product'}")
    # a product left by another version (or before the session had its calibration views) is rebuilt
    index = process(out / "session", out / "product", report=True, progress=progress, overwrite=True,
                    truth=GroundTruth.of_session(out / "session"))
    step(3, 4, "export")
    level = 0 if not full else 1
    exports = {fmt: export_product(out / "product", fmt, out / name, level=level)["output"]
               for fmt, name in DEMO_EXPORTS}
    # the paper's applications (Sec. 6): a rendered mirror ball and a relit preview
    exports.update(demo_applications(out / "product", out, out / "session"))
    step(4, 4, "report")
    report_dir = product_paths(out / "product")["report"]
    report = json.loads((report_dir / "report.json").read_text())
    summary = {"accuracy": report["accuracy"], "timings_s": report["timings_s"], "simulation_s": sim["wall_s"],
               "total_s": time.perf_counter() - t0, "panorama": [index["width"], index["height"]],
               "session": str(out / "session"), "product": str(out / "product"),
               "report_html": str(report_dir / "report.html"), "exports": exports, "sun": index.get("sun"),
               "irradiance": report.get("irradiance"), "rig_calibration": calibration_summary(index),
               "holes": report.get("holes")}
    accuracy = dict(report["accuracy"])
    if accuracy.get("colorchecker"):  # the summary keeps the numbers, the product's report keeps the spectra
        accuracy["colorchecker"] = {k: v for k, v in accuracy["colorchecker"].items()
                                    if k not in ("estimated", "true", "wavelength_nm")}
    atomic_write_json(out / "report.json", {**summary, "accuracy": accuracy})
    return summary


def calibration_summary(index: dict) -> dict:
    """Which calibration of camera B the product used and how far off its far content may be (px, worst direction)."""
    reg = index["registration"]
    far = reg.get("far_content") or {}
    return {"source": (reg.get("rig_calibration_source") or {}).get("description"), "far_content_max_px":
            far.get("max_px"), "warning": far.get("warning")}


def demo_applications(product: str | Path, out: str | Path, session: str | Path | None = None,
                      progress: ProgressCallback | None = None) -> dict:
    """Render the mirror ball and relight the product (when the session knows its white patch); returns the files."""
    out = Path(out)
    files: dict = {}
    ball = render_product(product, out / "render_mirror_ball", width=128, height=128, spp=16, wavelength_step_nm=10.0,
                          progress=progress)
    files["render_mirror_ball"] = ball["files"]["png"]
    files["render_mirror_ball_spectral"] = ball["files"]["spectral_exr"]
    gt = Path(session) / "ground_truth" / "ground_truth.json" if session else None
    if gt is not None and gt.is_file():
        patches = json.loads(gt.read_text()).get("colorchecker_patches") or []
        white = next((p for p in patches if p["name"].startswith("white")), None)
        if white is not None:
            ref = WhiteReference(white["lon_deg"], white["lat_deg"], 0.6 * white["half_size_deg"])
            rel = relight_product(product, out / "relit_A", [ref], to="A",
                                  reflectance=(white["wavelength_nm"], white["reflectance"]), progress=progress)
            files["relit_preview"] = rel["previews"]["relit"]
            files["relit_product"] = rel["output"]
    return files
