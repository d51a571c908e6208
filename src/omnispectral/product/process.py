"""``process``: a capture session into an HDR multiband panorama with its spectral estimator (paper Sec. 4).

Six bands from a two-camera rig; three from a one-camera rig (camera A alone), which skips camera B's
registration (``product.json``'s ``registration.method`` is ``"none"``) and is otherwise processed alike.

Stages (each timed, with progress; the whole run is resumable):

1. **check** the session against its plan (:func:`~omnispectral.capture.session.verify_session`; file
   sizes against the journal, SHA-256 with ``verify_checksums``): a missing or damaged frame stops the
   run with its name, unless ``skip_bad`` leaves out the directions concerned (recorded as holes in
   ``product.json``);
2. **merge + register** (:mod:`omnispectral.product.merge`), one direction at a time (memory holds one
   direction): the HDR merge of each camera's bracket (Eq. (1), inverse-variance weight by default),
   then camera B registered to A by POC through the geometry
   (:func:`~omnispectral.product.align.align_direction`, falling back to the calibrated offset when the
   confidence is low), written to ``PRODUCT/merged/``;
3. **mosaic**: :func:`omnispectral.mosaic.engine.mosaic` into ``PRODUCT/panorama.zarr`` (one resampling
   per pixel, linear blending, pyramid; local threads or a Dask cluster).  Interpolation defaults to
   Keys cubic clamped to the range of the 2 × 2 neighbours (``cubic-clamped``): like bilinear it never
   overshoots (plain cubic and spline ring beside the HDR sun and small high-contrast targets: chart
   patches +5 % and +10 % too bright), and it is sharper — on the ``small`` demo six-band PSNR 54.8 dB
   vs 54.0 (bilinear), ColorChecker ΔE*ab 1.17 / 2.51 vs 1.27 / 3.32, band error within 2 px of depth
   edges 0.142 vs 0.157;
4. **sun**: the saturated sun measured from the attenuated bracket and painted into the panorama
   (:mod:`omnispectral.product.sun`; ``sun.json``), or recorded as a lower bound;
5. **estimator**: the Wiener estimator for the rig's bands (ColorChecker held out), stored in the
   panorama's attributes and in ``product.json``: spectra are computed on demand from the bands.

``PRODUCT/product.json`` indexes it all (see docs/product.md).

A rerun on an existing product repairs instead of keeping damage: the merged files are checked against the
checksums ``merged.json`` recorded (:func:`omnispectral.product.verify.drop_damaged_merged`: a damaged image's
direction is merged again from the session's frames, a damaged parallax map measured again), the mosaic checks
every finished chunk against its marker's checksum and renders again what is damaged or missing, and the index's
``repaired`` says what was made again (``panorama_rebuilt`` when a merged file came out with other bytes).

Every choice of a run is one :class:`ProcessOptions` (validated once; :func:`process` builds it from its
keywords); camera B's registration is looked up by name in :data:`REGISTRATIONS`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.allocator import reuse_freed_memory
from omnispectral.capture.session import Session, verify_session
from omnispectral.choices import (
    DEFAULT_HDR_WEIGHT,
    DEFAULT_INTERP,
    DEFAULT_REGISTRATION,
    REGISTRATION_NAMES,
    method_from,
    options_or_keywords,
)
from omnispectral.errors import ConfigurationError, DamagedFrameError, InputFileError
from omnispectral.fingerprint import check_merged
from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.hdr import WEIGHTS
from omnispectral.imaging.registration import DEFAULT_MIN_CONFIDENCE
from omnispectral.io import atomic_write_json, clean_temp_files
from omnispectral.limits import check_memory, guard_product_output, memory_budget, sensor_memory_bytes
from omnispectral.locking import directory_lock
from omnispectral.mosaic.engine import mosaic
from omnispectral.mosaic.options import DEFAULT_TILE, MosaicOptions
from omnispectral.mosaic.sources import MergedDirections, MergedDirectionsWriter
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.ownership import MERGED_NAMES, check_output_outside_inputs, claim_output_directory, remove_owned_tree
from omnispectral.product.align import align_direction
from omnispectral.product.direction_parallax import FAR_OFFSET_MIN_STD_PX, off_model_warnings
from omnispectral.product.estimator import b_predictor, rig_estimator
from omnispectral.product.expectations import accuracy_warnings
from omnispectral.product.far_content import far_content_errors, far_content_warning
from omnispectral.product.fingerprint import product_fingerprint
from omnispectral.product.layout import MERGED, PANORAMA, PRODUCT_FORMAT, RIG_CALIBRATION, product_paths
from omnispectral.product.merge import merge_session
from omnispectral.product.parallax_ahead import ParallaxAhead, measure_parallax
from omnispectral.product.report import write_report
from omnispectral.product.rigfile import RigCalibration
from omnispectral.product.rigsession import calibrate_from_merged
from omnispectral.product.rigsource import CalibrationSource, choose_rig_calibration
from omnispectral.product.sun import SUN_FILE, paint_sun, sun_summary
from omnispectral.product.sun_methods import recover_sun, sun_method
from omnispectral.product.sun_reference import SunReference
from omnispectral.product.verify import changed_files, drop_damaged_merged
from omnispectral.progress import ProgressCallback, optional_progress, report_progress, under_stage
from omnispectral.threads import ordered_thread_map, single_threaded_libraries

__all__ = ["DEFAULT_INTERP", "PROCESS_BASE_BYTES", "PROCESS_BYTES_PER_SENSOR_PX", "REGISTRATIONS", "ProcessOptions",
           "Registration", "bad_directions", "calibration_source_of", "far_offset_applies", "merge_and_register",
           "merge_only", "parallax_registration", "process", "register_parallax", "registration_method"]

#: Peak working memory of :func:`process` per pixel of the rig's largest sensor (bytes), and its fixed part:
#: the merge's brackets (and the next direction's, read ahead), B's registration and the mosaic's tiles at two
#: threads.  Measured as the peak RSS above the interpreter's: 270 MB for 256 × 136 sensors, 573 MB (1917 B/px)
#: for 768 × 408 before the read-ahead (it adds 6 B/px per frame of a direction: 180 B/px for the paper's
#: 2 × 15), 3.1–3.5 GiB for 2048 × 1088 with it (docs/benchmarks.md, Processing).
PROCESS_BYTES_PER_SENSOR_PX = 2000
PROCESS_BASE_BYTES = 300e6


def bad_directions(report: dict) -> dict[int, list[str]]:
    """Directions with missing or damaged frames, and what is wrong with each frame."""
    out: dict[int, list[str]] = {}
    for item in report["missing"] + report["damaged"]:
        out.setdefault(int(item["direction"]), []).append(f"{item['file']}: {item['problem']}")
    return out


def _check_session(session_path: Path, skip_bad: bool, verify_checksums: bool,
                   full: bool = False) -> tuple[dict, dict[int, list[str]], bool]:
    """Stage 1.  Returns the check's report, the directions with missing or damaged frames, and whether the
    frames' checksums and pixels are left to the reads that use them (:meth:`Session.check_frames_on_read`).

    With ``verify_checksums`` every frame's checksum is checked (the fast XXH3-128 the journal records, else its
    SHA-256: :func:`~omnispectral.capture.session.content_matches`) and its TIFF decoded, so a same-size corrupted
    or undecodable frame counts as damaged.  Without ``skip_bad`` (and unless ``full``) this check happens as the
    merge reads each frame: the session is read once instead of twice (docs/benchmarks.md, Processing), and a
    damaged frame still stops the run before it is merged; here only the journal and the sizes are checked (and
    the sun brackets' few frames in full: they are read after the mosaic).
    ``skip_bad`` needs the whole list of damaged frames before the merge, so it checks everything first.
    """
    on_read = verify_checksums and not skip_bad and not full
    # the sun brackets' frames are read after the mosaic: checked in full now, so that a damaged one stops the run
    # before any work, as --skip-bad would need
    report = verify_session(session_path, check_pixels=verify_checksums and not on_read,
                            checksums=verify_checksums and not on_read, sun_in_full=on_read, cryptographic=False)
    if on_read and (report["missing"] or report["damaged"] or report["journal_bad_lines"]):
        return _check_session(session_path, skip_bad, verify_checksums, full=True)  # name every problem
    bad = bad_directions(report)
    if report["journal_bad_lines"] and not skip_bad:
        first = report["journal_bad_lines"][0]
        raise InputFileError(session_path / "journal.jsonl",
                             f"line {first['line']}: {first['problem']} ({len(report['journal_bad_lines'])} bad "
                             f"lines; 'omnispectral session repair {session_path}' rebuilds the journal from the "
                             f"frames, --skip-bad processes the frames it still lists)")
    if bad and not skip_bad:
        first = next(iter(bad.values()))[0]
        raise InputFileError(session_path / first.split(":")[0],
                             f"{first.split(': ', 1)[1]} ({report['n_missing']} missing and {report['n_damaged']} "
                             f"damaged frames in {len(bad)} directions; --skip-bad processes the rest)")
    return report, bad, on_read


def merge_and_register(session: Session, out: Path, skip: set[int], min_confidence: float,
                       progress: ProgressCallback | None = None, timings: dict | None = None,
                       hdr_weight: str = DEFAULT_HDR_WEIGHT, models: dict | None = None) -> tuple[object, list[dict]]:
    """Stage 2: :func:`omnispectral.product.merge.merge_session` (streamed per direction) with camera B
    registered to A by :func:`~omnispectral.product.align.align_direction`; returns the merged directions
    and the alignment of every direction.  ``models``: the rig's camera models (default: built here);
    ``progress("merge", done, total)`` per direction."""
    models = models or {c: session.rig().camera_model(c) for c in session.cameras()}
    t_reg, n_merged = 0.0, 0

    def register(direction: int, img_a, img_b):
        nonlocal t_reg, n_merged
        n_merged += 1
        t0 = time.perf_counter()
        # for points at infinity the A-to-B relation does not depend on the head direction (product.pairgeometry)
        al = align_direction(direction, img_a, img_b, models["A"], models["B"], 0.0, 0.0, min_confidence)
        t_reg += time.perf_counter() - t0
        return (*al.offset_px, {"alignment": al.to_dict()})

    t0 = time.perf_counter()
    merged = merge_session(session, out, register=register, skip=skip, progress=progress, cameras=models,
                           weight=hdr_weight)
    if timings is not None:
        merging = time.perf_counter() - t0 - t_reg if n_merged else 0.0  # a resumed run may merge nothing
        timings["hdr_merge"] = timings.get("hdr_merge", 0.0) + merging
        timings["registration"] = timings.get("registration", 0.0) + t_reg
    return merged, [d["alignment"] for d in merged.directions if "alignment" in d]


def merge_only(session: Session, out: Path, skip: set[int], progress: ProgressCallback | None = None,
               timings: dict | None = None, hdr_weight: str = DEFAULT_HDR_WEIGHT, models: dict | None = None,
               written: Callable[[dict], None] | None = None):
    """Stage 2 without registration: the HDR merge of every direction (camera B at the rig file's mounting);
    ``progress("merge", done, total)`` per direction, ``written(entry)`` after each (:func:`merge_session`)."""
    t0 = time.perf_counter()
    if (out / "merged.json").is_file():  # a resumed run: nothing to merge when the directory is complete
        try:
            done = MergedDirections.open(out)
            if timings is not None:
                timings.setdefault("hdr_merge", 0.0)
            return done
        except InputFileError:
            pass
    merged = merge_session(session, out, skip=skip, progress=progress, cameras=models, weight=hdr_weight,
                           written=written)
    if timings is not None:
        timings["hdr_merge"] = timings.get("hdr_merge", 0.0) + time.perf_counter() - t0
    return merged


def register_parallax(merged, calibration=None, progress: ProgressCallback | None = None,
                      timings: dict | None = None, measured: dict | None = None):
    """Stage 2b: camera B's mounting (``calibration``, or fitted now from every direction,
    :mod:`omnispectral.product.rigfit`), then every direction's per-pixel parallax
    (:func:`~omnispectral.product.direction_parallax.parallax_direction`) saved beside the merged images
    (``progress("parallax", done, total)`` per direction).

    Resumes: directions whose parallax was computed with the same calibration are kept, and so are those
    ``measured`` during the merge with this ``calibration`` (:class:`~omnispectral.product.parallax_ahead.
    ParallaxAhead`, by direction index).  Returns the calibration and the per-direction parallax statistics.
    """
    t0 = time.perf_counter()
    nominal = merged.meta.get("rig_file_camera_b") or merged.meta["cameras"]["B"]  # the rig file's camera B
    model_b_nominal = CameraModel.from_dict(nominal)
    if calibration is None:
        recorded = merged.meta.get("rig_calibration")
        if recorded and merged.meta.get("rig_file_camera_b"):
            calibration = RigCalibration.from_dict(recorded)
        else:
            calibration = calibrate_from_merged(merged)
    model_a = merged.cameras["A"]
    model_b = calibration.apply(model_b_nominal)
    writer = MergedDirectionsWriter(merged.path, merged.meta)
    cal_dict = calibration.to_dict()
    if merged.meta.get("rig_calibration", {}).get("camera_b_mounting") != cal_dict["camera_b_mounting"]:
        for d in writer.meta["directions"]:  # another calibration: every parallax map is stale
            d["images"]["B"].pop("parallax", None)
    calibration.save(merged.path.parent / RIG_CALIBRATION)
    writer.set_meta(rig_file_camera_b=nominal, rig_calibration=cal_dict,
                    cameras={**writer.meta["cameras"], "B": model_b.to_dict()}, registration="parallax")
    if timings is not None:
        timings["rig_calibration"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    for m in (measured or {}).values():  # measured while the merge went on, with this calibration
        m.record(writer)
    todo = [d for d in writer.meta["directions"] if "parallax" not in d["images"]["B"]
            or not (merged.path / d["images"]["B"]["parallax"]["file"]).is_file()]
    apply_far = far_offset_applies(calibration, model_b)
    n_total, n_done = len(writer.meta["directions"]), len(writer.meta["directions"]) - len(todo)
    for k, m in enumerate(ordered_thread_map(lambda d: measure_parallax(merged.path, d, model_a, model_b, apply_far),
                                             todo)):  # recorded in order, as they come
        m.record(writer)
        report_progress(progress, "parallax", n_done + k + 1, n_total)
    stats = [{"direction": int(d["index"]), **{k: v for k, v in d["images"]["B"]["parallax"].items()
                                               if k not in ("file", "checksum")}}
             for d in writer.meta["directions"]]
    if timings is not None:
        timings["registration"] = timings.get("registration", 0.0) + time.perf_counter() - t1
    return MergedDirections.open(merged.path), calibration, stats


def calibration_source_of(session_path: Path, registration: str, rig_calibration: str | Path | None,
                          use_views: bool = True) -> CalibrationSource | None:
    """Camera B's calibration for the parallax registration: ``rig_calibration``, else the chessboard views that
    apply to the session, else its own images (:func:`~omnispectral.product.rigsource.choose_rig_calibration`);
    ``None`` when B is not registered through a rig model (one camera, or the paper's method)."""
    if not registration_method(registration).rig_model:
        return CalibrationSource("file", str(rig_calibration), RigCalibration.load(rig_calibration)) \
            if rig_calibration is not None else None
    rig = Session.open(session_path).rig()
    if "B" not in rig.camera_names:
        return None
    return choose_rig_calibration(session_path, rig, rig_calibration, use_views=use_views)


def parallax_registration(calibration: RigCalibration, source: CalibrationSource, stats: list[dict],
                          model_a: CameraModel, model_b: CameraModel) -> dict:
    """The index's ``registration`` for the parallax method: the calibration and where it came from, every
    direction's statistics with how far off its far content may be (``far_content_error_px``,
    :func:`~omnispectral.product.far_content.far_content_errors`) and the warnings."""
    far = far_content_errors(calibration, stats, model_a, model_b)
    for d in stats:
        d["far_content_error_px"] = far["per_direction"].get(int(d["direction"]))
    values = list(far["per_direction"].values())
    summary = {k: v for k, v in far.items() if k != "per_direction"}
    summary.update(max_px=max(values) if values else None, median_px=float(np.median(values)) if values else None,
                   warning=far_content_warning(source, far))
    warnings = calibration.warnings() + off_model_warnings(stats) + list(source.notes)
    return {"method": "parallax", "rig_calibration": calibration.to_dict(), "rig_calibration_source": source.to_dict(),
            "far_content": summary, "warnings": warnings + ([summary["warning"]] if summary["warning"] else []),
            "directions": stats}


def _repaired(dropped: list[dict], summary: dict, stale: list[str]) -> dict:
    """The index's ``repaired``: the merged files and panorama chunks this run found missing or damaged (against
    their checksums) and made again, and whether the panorama was rebuilt because a merged file came out
    different."""
    return {"merged": [{"file": d["file"], "problem": d["problem"]} for d in dropped],
            "chunks": list(summary.get("repaired_chunks", [])), "panorama_rebuilt": bool(stale)}


# ------------------------------------------------------------------------------------------ registration methods
@dataclass
class _Run:
    """One ``process`` run as its registration method sees it: the session, the product's paths, the directions
    left out, the options, the rig's camera models, camera B's calibration source, the timings, the progress."""

    session: Session
    paths: dict
    bad: dict[int, list[str]]
    options: ProcessOptions
    models: dict
    calibration_source: CalibrationSource | None
    timings: dict
    progress: ProgressCallback | None


def _register_one_camera(run: _Run) -> tuple[MergedDirections, dict]:
    """One camera (three bands): the merge alone, nothing to register."""
    merged = merge_only(run.session, run.paths["merged"], set(run.bad), run.progress, run.timings,
                        run.options.hdr_weight, run.models)
    return merged, {"method": "none", "note": "one camera: nothing to register", "directions": []}


def _register_paper(run: _Run) -> tuple[MergedDirections, dict]:
    """The paper's registration (Sec. 4.3): one POC offset per direction during the merge
    (:func:`merge_and_register`, reported as stage ``"merge + register"``)."""
    min_confidence = run.options.min_confidence_or_default
    merged, alignments = merge_and_register(run.session, run.paths["merged"], set(run.bad), min_confidence,
                                            under_stage(run.progress, "merge + register"), run.timings,
                                            run.options.hdr_weight, run.models)
    return merged, {"method": "paper", "min_confidence": min_confidence, "directions": alignments}


def far_offset_applies(calibration: RigCalibration, model_b: CameraModel) -> bool:
    """Whether each direction's measured offset at infinity is applied: unless the rig model is more certain
    than the offset's measurement (:data:`~omnispectral.product.direction_parallax.FAR_OFFSET_MIN_STD_PX`)."""
    std_px = calibration.infinity_std_px(model_b)
    return std_px is None or std_px > FAR_OFFSET_MIN_STD_PX


def _register_parallax(run: _Run) -> tuple[MergedDirections, dict]:
    """The default registration: the merge, camera B's mounting (its calibration source), then every direction's
    per-pixel parallax (:func:`register_parallax`); the index's entry by :func:`parallax_registration`.

    With the mounting known before the merge (chessboard views or a file), the parallax of each direction is
    measured while the merge goes on (:class:`~omnispectral.product.parallax_ahead.ParallaxAhead`)."""
    source = run.calibration_source
    ahead = None
    if source.calibration is not None and run.models is not None and "B" in run.models:
        model_b = source.calibration.apply(run.models["B"])
        ahead = ParallaxAhead(run.paths["merged"], run.models["A"], model_b,
                              far_offset_applies(source.calibration, model_b))
    with ahead or nullcontext(), single_threaded_libraries() if ahead else nullcontext():
        merged = merge_only(run.session, run.paths["merged"], set(run.bad), run.progress, run.timings,
                            run.options.hdr_weight, run.models, written=ahead.submit if ahead else None)
        measured = ahead.finished() if ahead else None
    merged, calibration, stats = register_parallax(merged, source.calibration, run.progress, run.timings,
                                                   measured=measured)
    run.timings["rig_calibration"] = run.timings.get("rig_calibration", 0.0) + source.fit_s  # views' fit
    return merged, parallax_registration(calibration, source, stats, merged.cameras["A"], merged.cameras["B"])


@dataclass(frozen=True)
class Registration:
    """One registration method of camera B to camera A.

    Attributes
    ----------
    register
        ``register(run) -> (merged directions, the index's "registration" entry)``: stage 2 of the run.
    rig_model
        Whether camera B is registered through a calibrated model of the rig (its calibration source is chosen
        before the run: :func:`calibration_source_of`).
    """

    register: Callable[[_Run], tuple[MergedDirections, dict]]
    rig_model: bool


#: Registration methods by name (the valid names are its keys): ``parallax`` (default: rig calibration of
#: camera B + per-pixel parallax) and ``paper`` (one POC offset per direction, Sec. 4.3 of the paper).
REGISTRATIONS: dict[str, Registration] = dict(zip(REGISTRATION_NAMES, (
    Registration(_register_parallax, rig_model=True),  # parallax
    Registration(_register_paper, rig_model=False),  # paper
), strict=True))
#: What a one-camera rig runs whatever the registration asked for: the merge alone (``"method": "none"``).
ONE_CAMERA = Registration(_register_one_camera, rig_model=False)


def registration_method(name: str) -> Registration:
    """The :class:`Registration` called ``name``.

    Parameters
    ----------
    name
        A key of :data:`REGISTRATIONS`.

    Returns
    -------
    Registration
        The method's entry.

    Raises
    ------
    ConfigurationError
        For an unknown name (the message lists the valid ones).
    """
    return method_from(REGISTRATIONS, name, "registration")


# ------------------------------------------------------------------------------------------ options
@dataclass(frozen=True)
class ProcessOptions:
    """Every choice of a :func:`process` run, validated once when built (unknown method names list the valid
    ones).

    Attributes
    ----------
    width, tile
        Panorama width in px (default: camera A's native width) and the store's tile side in px (default
        :data:`omnispectral.mosaic.options.DEFAULT_TILE`).
    interp
        Interpolation, a key of :data:`omnispectral.mosaic.interp.METHODS` (``None``: :data:`DEFAULT_INTERP`).
    scheduler, workers
        The mosaic's Dask scheduler (``None``: local threads) and local threads.
    skip_bad
        Leave out the directions with missing or damaged frames instead of stopping.
    min_confidence
        The paper's registration: the POC confidence below which the calibrated offset is kept (``None``:
        :data:`omnispectral.imaging.registration.DEFAULT_MIN_CONFIDENCE`).
    hdr_weight
        The HDR merge's weight, a key of :data:`omnispectral.imaging.hdr.WEIGHTS` (default the inverse variance,
        ``"noise"``).
    report
        Write the report.
    verify_checksums
        Check every frame's SHA-256 and decode it (else sizes only).
    registration
        Camera B's registration, a key of :data:`REGISTRATIONS`.
    rig_calibration
        Camera B's calibration file for the parallax registration.
    overwrite
        Replace a product made with other settings instead of refusing.
    sun
        The sun's recovery, a key of :data:`omnispectral.product.sun_methods.SUN_METHODS`.
    sun_reference
        The diffuse reference ``sun="diffuse-reference"`` needs.
    calibration_views
        Use the chessboard views recorded for the session.
    truth
        A simulated session's ground truth for the report's accuracy section.
    """

    width: int | None = None
    tile: int | None = None
    interp: str | None = None
    scheduler: object = None
    workers: int | None = None
    skip_bad: bool = False
    min_confidence: float | None = None
    hdr_weight: str = DEFAULT_HDR_WEIGHT
    report: bool = True
    verify_checksums: bool = True
    registration: str = DEFAULT_REGISTRATION
    rig_calibration: str | Path | None = None
    overwrite: bool = False
    sun: str = "auto"
    sun_reference: SunReference | None = None
    calibration_views: bool = True
    truth: object = None

    def __post_init__(self):
        registration_method(self.registration)
        if self.interp is None:
            object.__setattr__(self, "interp", DEFAULT_INTERP)
        if self.hdr_weight not in WEIGHTS:
            raise ConfigurationError(f"unknown weight {self.hdr_weight!r}; expected one of {', '.join(WEIGHTS)}")
        sun_method(self.sun)
        self.mosaic_options()  # width, tile, interpolation

    @property
    def min_confidence_or_default(self) -> float:
        """``min_confidence``, or the default when it is ``None``."""
        return DEFAULT_MIN_CONFIDENCE if self.min_confidence is None else self.min_confidence

    def mosaic_options(self, b_predictor=None, overwrite: bool | None = None) -> MosaicOptions:
        """The mosaic's options of this run.

        Parameters
        ----------
        b_predictor
            The prior's predictor of camera B's bands from A's (:func:`omnispectral.product.estimator.b_predictor`).
        overwrite
            Replace the panorama (default: the options' ``overwrite``).

        Returns
        -------
        MosaicOptions
            Width, tile, interpolation, scheduler, workers, overwrite and the predictor; the rest at their
            defaults.
        """
        return MosaicOptions(width=self.width, tile=DEFAULT_TILE if self.tile is None else self.tile,
                             interp=self.interp, scheduler=self.scheduler, workers=self.workers,
                             overwrite=self.overwrite if overwrite is None else overwrite, b_predictor=b_predictor)

    @classmethod
    def from_keywords(cls, options: ProcessOptions | None = None, **keywords) -> ProcessOptions:
        """``options``, or the options the keywords of :func:`process` describe.

        Parameters
        ----------
        options
            Options built by the caller, or ``None``.
        **keywords
            :func:`process`'s keywords (one per field).  With ``options`` given, each must be left at its
            default: the two ways of choosing do not mix.

        Returns
        -------
        ProcessOptions
            The validated options.
        """
        return options_or_keywords(cls, options, keywords)


# ------------------------------------------------------------------------------------------ the run
def process(session: str | Path, output: str | Path, *, options: ProcessOptions | None = None,
            width: int | None = None, tile: int | None = None, interp: str | None = None, scheduler=None,
            workers: int | None = None, skip_bad: bool = False, min_confidence: float | None = None,
            hdr_weight: str = DEFAULT_HDR_WEIGHT, report: bool = True, progress: ProgressCallback | None = None,
            verify_checksums: bool = True, registration: str = DEFAULT_REGISTRATION,
            rig_calibration: str | Path | None = None,
            overwrite: bool = False, sun: str = "auto", sun_reference: SunReference | None = None,
            calibration_views: bool = True, truth=None) -> dict:
    """Run stages 1-4 (module docstring) and write ``product.json`` and, by default, the report.

    Every keyword but ``progress`` is a field of :class:`ProcessOptions` (documented there); ``options`` gives
    them as one object instead (then leave the keywords at their defaults).

    ``hdr_weight`` defaults to the inverse-variance weight: the paper's triangle weight lets 1-DN
    values of the shortest exposures bias dark regions upwards (+36 % at 360 DN in the longest
    exposure on the simulated rig; docs/benchmarks.md), which would show in the spectra.

    ``sun`` chooses how the saturated sun is recovered (:mod:`omnispectral.product.sun_methods`: ``auto``,
    ``nd-bracket``, ``diffuse-reference`` with ``sun_reference`` (a
    :class:`~omnispectral.product.sun_reference.SunReference`), ``sky-model``, ``none``); the product records
    the method and ``sun.json``.

    ``progress(stage, done, total)`` (:data:`omnispectral.progress.ProgressCallback`) is called as each stage
    advances (``merge``, ``parallax`` or ``merge + register``, then the mosaic's ``tiles`` and ``pyramid``,
    then ``sun``); the command line draws it.

    Camera B's mounting (parallax registration): ``rig_calibration``, else the chessboard views recorded for
    the session (``SESSION/calibration/``, or the series' for a time-lapse slot; fitted once and cached there)
    unless ``calibration_views`` is false, else fitted from the session's own images
    (:mod:`omnispectral.product.rigsource`); ``product.json`` says which (``registration.rig_calibration_source``)
    and how far off far content may be in each direction (``far_content_error_px``).

    ``truth``: a simulated session's ground truth for the report's accuracy section
    (:meth:`omnispectral.sim.truth.GroundTruth.of_session`; processing itself never reads it).

    The process's C allocator is told to keep freed memory for the next arrays
    (:func:`omnispectral.allocator.reuse_freed_memory`): speed only, never results.

    Parameters
    ----------
    session : str or pathlib.Path
        The capture session's directory.
    output : str or pathlib.Path
        The product directory (``product.json``, ``merged/``, ``panorama.zarr``, ``sun.json``, the report);
        the run holds its lock and resumes a run with the same settings.
    options : ProcessOptions, optional
        Every choice below as one object.
    width, tile : int, optional
        Panorama width in px (default: camera A's native width; height = width / 2) and tile side in px.
    interp : str, optional
        Interpolation of the mosaic (default :data:`DEFAULT_INTERP`, ``"cubic-clamped"``).
    scheduler, workers
        The mosaic's Dask scheduler (address or ``Client``; ``None``: local threads) and local threads (int).
    skip_bad : bool
        Leave out the directions with missing or damaged frames instead of stopping.
    min_confidence : float, optional
        The paper's registration: POC confidence (peak height, 0-1) below which the calibrated offset is kept.
    hdr_weight : str
        ``"noise"`` (inverse variance, default) or ``"triangle"`` (the paper's Eq. (2)).
    report : bool
        Write the report.
    progress : ProgressCallback, optional
        ``progress(stage, done, total)`` as each stage advances (above).
    verify_checksums : bool
        Check every frame's SHA-256 and decode it (else file sizes only).
    registration : str
        Camera B's registration: ``"parallax"`` (default, per pixel) or ``"paper"`` (one POC offset per
        direction).
    rig_calibration : str or pathlib.Path, optional
        Camera B's calibration file for the parallax registration.
    overwrite : bool
        Replace a product made with other settings instead of refusing.
    sun : str
        The sun's recovery: ``"auto"``, ``"nd-bracket"``, ``"diffuse-reference"``, ``"sky-model"`` or ``"none"``.
    sun_reference : SunReference, optional
        The diffuse reference ``sun="diffuse-reference"`` needs.
    calibration_views : bool
        Use the chessboard views recorded for the session (or its series).
    truth : GroundTruth, optional
        A simulated session's ground truth for the report's accuracy section.

    Returns
    -------
    dict
        The product's index (``product.json``).

    Raises
    ------
    ConfigurationError
        For invalid options (unknown method names list the valid ones).
    InputFileError
        For a session with missing or damaged frames (without ``skip_bad``).
    LockedError
        When another run holds the product's lock.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4, Fig. 5 (the processing flow): Sec. 4.1, Eqs. (1)-(2) (HDR
       synthesis), Sec. 4.2 (lens distortion), Sec. 4.3, Eq. (3) (registration), Sec. 4.4-4.5, Eq. (4),
       Fig. 8 (omnidirectional synthesis), Sec. 4.6, Eqs. (5)-(7) (the spectral estimator).
    .. [2] M. Granados et al., "Optimal HDR reconstruction with linear digital cameras", CVPR 2010 (the default
       inverse-variance HDR weight).
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003 (the POC of
       both registrations).
    .. [4] R. G. Keys, "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981
       (the default interpolation, clamped).
    """
    options = ProcessOptions.from_keywords(
        options, width=width, tile=tile, interp=interp, scheduler=scheduler, workers=workers, skip_bad=skip_bad,
        min_confidence=min_confidence, hdr_weight=hdr_weight, report=report, verify_checksums=verify_checksums,
        registration=registration, rig_calibration=rig_calibration, overwrite=overwrite, sun=sun,
        sun_reference=sun_reference, calibration_views=calibration_views, truth=truth)
    session_path = Path(session)
    paths = product_paths(output)
    guard_product_output(paths["root"], options.width)
    check_output_outside_inputs([paths["root"]], [session_path, options.rig_calibration])
    claim_output_directory(paths["root"], "process")
    with directory_lock(paths["root"], "process"):
        return _process_locked(session_path, paths, options, optional_progress(progress))


def _process_locked(session_path: Path, paths: dict, options: ProcessOptions,
                    progress: ProgressCallback | None) -> dict:
    """:func:`process` while holding the product's lock."""
    clean_temp_files(paths["root"])
    reuse_freed_memory()  # arrays of 10-30 MB freed and allocated per frame: no page faults for each (allocator)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    s = Session.open(session_path)  # opened once for the run: the merge reads its frames through it
    rig = s.rig()
    big = max(rig.cameras.values(), key=lambda c: c.width_px * c.height_px)
    check_memory(session_path / "rig.toml", sensor_memory_bytes(big.width_px * big.height_px,
                                                                PROCESS_BYTES_PER_SENSOR_PX, PROCESS_BASE_BYTES),
                 memory_budget(), f"processing {big.width_px} × {big.height_px} frames")  # before any frame is read
    check, bad, on_read = _check_session(session_path, options.skip_bad, options.verify_checksums)
    if on_read:
        s.check_frames_on_read()
    timings["check"] = time.perf_counter() - t0
    models = {c: rig.camera_model(c) for c in rig.camera_names}
    calibration_source = calibration_source_of(session_path, options.registration, options.rig_calibration,
                                               options.calibration_views)
    fingerprint = product_fingerprint(session_path, hdr_weight=options.hdr_weight, registration=options.registration,
                                      min_confidence=options.min_confidence, rig_calibration=options.rig_calibration,
                                      calibration_views_sha256=getattr(calibration_source, "views_sha256", None),
                                      skipped_directions=bad)
    state = check_merged(paths["merged"], fingerprint, options.overwrite,
                         dependents=(paths["panorama"], paths["rig_calibration"], paths["index"]))
    # a resumed run re-checks the merged files against their checksums: damaged or missing ones are made again
    dropped = drop_damaged_merged(paths["merged"]) if state == "resume" else []
    registration = ONE_CAMERA if "B" not in models else registration_method(options.registration)
    run = _Run(s, paths, bad, options, models, calibration_source, timings, progress)
    try:
        merged, registration_entry = registration.register(run)
    except DamagedFrameError:
        # a frame failed its check as the merge read it: what this run merged goes, and the whole session's
        # check names every damaged frame, as it would have before the merge
        if state != "resume":
            remove_owned_tree(paths["merged"], MERGED_NAMES, "merged directions")
        _check_session(session_path, options.skip_bad, options.verify_checksums, full=True)
        raise
    t2 = time.perf_counter()
    est, est_info = rig_estimator(rig)
    timings["estimator"] = time.perf_counter() - t2
    t1 = time.perf_counter()
    # B's bands where B saw nothing (mosaic.predict); a merged file made again with other bytes makes the
    # panorama stale: it is rebuilt
    stale = changed_files(dropped, merged)
    mosaic_options = options.mosaic_options(b_predictor(est), overwrite=options.overwrite or state == "overwritten"
                                            or bool(stale))
    summary = mosaic(merged, paths["panorama"], options=mosaic_options, progress=progress)
    timings["mosaic"] = time.perf_counter() - t1
    t_sun = time.perf_counter()
    store = PanoramaStore.open(paths["panorama"])
    sun = recover_sun(s, {**models, **merged.cameras}, rig, list(merged.meta["band_names"]), options.sun,
                      progress, store, options.sun_reference, merged)
    if sun.get("recovered"):
        sun["pixels"] = paint_sun(store, sun)
    store.update_attrs({"omnispectral": {**store.attrs()["omnispectral"], "sun": sun}})
    atomic_write_json(paths["root"] / SUN_FILE, sun)
    timings["sun"] = time.perf_counter() - t_sun
    t2 = time.perf_counter()
    estimator = {"params": est_info["params"], "sigma2": est_info["sigma2"], "prior": est_info["prior"],
                 "linear_maps": est.to_dict()}
    store.update_attrs({"omnispectral": {**store.attrs()["omnispectral"], "estimator": estimator}})
    timings["estimator"] += time.perf_counter() - t2
    timings["total"] = time.perf_counter() - t0
    index = {"format": PRODUCT_FORMAT, "format_version": 1, "session": str(session_path.resolve()),
             "session_kind": s.metadata().get("kind"), "rig": rig.name, "panorama": PANORAMA, "merged": MERGED,
             "width": summary["width"], "height": summary["height"], "bands": list(merged.meta["band_names"]),
             "units": merged.meta["units"], "hdr_weight": options.hdr_weight,
             "estimator": {k: estimator[k] for k in ("params", "sigma2", "prior")},
             "registration": registration_entry,
             "skipped_directions": [{"direction": d, "problems": p} for d, p in sorted(bad.items())],
             "session_check": {k: check[k] for k in ("n_planned", "n_ok", "n_missing", "n_damaged")},
             "mosaic": {k: v for k, v in summary.items() if k not in ("output",)},
             "sun": sun_summary(sun), "timings_s": timings, "fingerprint": fingerprint,
             "repaired": _repaired(dropped, summary, stale)}
    # accuracy limits this run's rig, settings and measurements imply (product.expectations)
    index["accuracy_warnings"] = accuracy_warnings(index, rig, {d.index: d.pan_deg for d in s.plan().directions})
    atomic_write_json(paths["index"], index)
    if options.report:
        t3 = time.perf_counter()
        rep = write_report(paths["root"], truth=options.truth)
        index["timings_s"]["report"] = time.perf_counter() - t3
        index["report"] = rep["files"]
        atomic_write_json(paths["index"], index)
    return index
