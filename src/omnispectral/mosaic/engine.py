"""The mosaic engine: merged directional images → six-band equirectangular panorama (paper Sec. 4.4–4.5).

For each output tile (a chunk of the store) the engine

1. finds the (direction, camera) images whose bounding cone meets the tile's cone
   (:mod:`omnispectral.mosaic.maps`);
2. computes for every tile pixel where it lands on each of those sensors through the composed
   geometry (equirect pixel → ray → inverse head rotation → mounting → OpenCV lens with
   distortion → sensor pixel, plus camera B's registration offset) — one map, no intermediate
   undistorted or polar image;
3. reads only the crop of each source the map touches, interpolates it once
   (:mod:`omnispectral.mosaic.interp`), weights it with the linear-blending weight
   (:mod:`omnispectral.mosaic.blending`) and accumulates camera A into bands 0–2 and camera B into
   bands 3–5, three bands for a one-camera rig (optionally multi-band blending and per-direction gains);
4. writes the chunk atomically with a completion marker (:mod:`omnispectral.mosaic.store`).

Tiles are independent tasks run by Dask (the local threaded scheduler, or a distributed cluster
given its address); a task holds its tile and the crops of the sources that overlap it, so peak
memory depends on the tile size and the directions per tile, never on the panorama size.  The
pyramid levels follow, chunk by chunk, from the level below.  An interrupted run resumes by skipping
chunks whose markers exist.
"""

from __future__ import annotations

import hashlib
import json
import os
import resource
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import native_width
from omnispectral.mosaic.blending import (
    BLENDS,
    DEFAULT_MULTIBAND_LEVELS,
    LinearBlend,
    feather_weight,
    multiband_blend,
    multiband_halo_px,
    reject_inconsistent,
)
from omnispectral.mosaic.gain import estimate_gains
from omnispectral.mosaic.interp import (
    KERNEL_RADIUS_PX,
    SPLINE_PREFILTER_MARGIN_PX,
    check_method,
    remap,
    spline_prefilter,
)
from omnispectral.mosaic.maps import Canvas, Rect, SourceGeometry, exact_map, source_map, tile_cone
from omnispectral.mosaic.predict import fill_missing_b, implausible_b
from omnispectral.mosaic.sources import BAND_NAMES, MergedDirections, SourceImage, read_npy_rows
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.spectral.conditional import BandPredictor
from omnispectral.threads import worker_call

DEFAULT_TILE = 512
DEFAULT_INTERP = "spline"
#: Bands of a two-camera rig's panorama; a one-camera rig's has three (``MosaicJob.n_bands``).
N_BANDS = 6
#: Registration-quality layer of a panorama whose camera B carries parallax maps: blended registration
#: confidence (0..1), occluded (1 where every direction that sees the pixel with B has it hidden), sun
#: (0 from the mosaic; 1 where processing painted the recovered sun, ``omnispectral.product.sun``) and
#: b_predicted (the relative error of B's bands predicted from A's where B saw nothing,
#: :mod:`omnispectral.mosaic.predict`; 0 where B measured the pixel).
N_QUALITY = 4


# ------------------------------------------------------------------------------------------ the job
@dataclass
class MosaicJob:
    """Everything a tile task needs (picklable, so it can be sent to Dask workers once)."""

    canvas: Canvas
    tile: int
    interp: str
    blend: str
    multiband_levels: int
    images: list[SourceImage]
    geometry: list[SourceGeometry]
    gains: np.ndarray  # (n_sources, 3): per source, per band of its camera
    store_path: Path
    run_id: str = ""  # recorded in the markers of the tiles this run computes
    n_bands: int = N_BANDS  # three per camera of the merged directions
    #: the prior's predictor of B's bands from A's (None: fitted per tile, mosaic.predict.tile_predictor)
    b_predictor: BandPredictor | None = None
    axes: np.ndarray = field(init=False)
    radii: np.ndarray = field(init=False)
    #: for a camera-B source with a parallax map: the index of camera A's source of the same direction
    partner: dict = field(init=False)

    def __post_init__(self):
        self.axes = np.array([g.axis for g in self.geometry]).reshape(-1, 3)
        self.radii = np.array([g.radius_rad for g in self.geometry])
        a_of = {s.direction: i for i, s in enumerate(self.images) if s.camera == "A"}
        self.partner = {i: a_of[s.direction] for i, s in enumerate(self.images)
                        if s.parallax is not None and s.direction in a_of}

    @property
    def has_quality(self) -> bool:
        """Whether the panorama carries a registration-quality layer (some source has a parallax map)."""
        return bool(self.partner)

    def sources_for(self, rect: Rect) -> np.ndarray:
        """Indices of the sources whose cones meet the cone of ``rect`` (vectorised test)."""
        centre, radius = tile_cone(self.canvas, rect)
        angle = np.arccos(np.clip(self.axes @ centre, -1.0, 1.0))
        return np.flatnonzero(angle <= radius + self.radii)


def build_job(merged: MergedDirections, store_path: Path, width: int, tile: int, interp: str, blend: str,
              multiband_levels: int, gains: np.ndarray | None = None,
              b_predictor: BandPredictor | None = None) -> MosaicJob:
    images = merged.sources()
    geometry = [SourceGeometry.build(merged.cameras[s.camera], s.pan_deg, s.tilt_deg, s.offset_px) for s in images]
    if gains is None:
        gains = np.ones((len(images), 3), np.float32)
    return MosaicJob(Canvas(width, width // 2), tile, interp, blend, multiband_levels, images, geometry,
                     np.asarray(gains, np.float32), Path(store_path), run_id=f"{os.getpid()}-{time.time_ns()}",
                     n_bands=merged.n_bands, b_predictor=b_predictor)


# ------------------------------------------------------------------------------------------ one tile
@dataclass
class Warped:
    """One source resampled onto (part of) a tile: values (h, w, 3), weights (h, w), at ``(row0, col0)``."""

    index: int
    row0: int
    col0: int
    values: np.ndarray
    weight: np.ndarray
    step: int
    max_error_px: float
    #: camera B with parallax: registration confidence and occlusion per pixel (else None)
    confidence: np.ndarray | None = None
    occluded: np.ndarray | None = None


#: Weight factor of an occluded camera-B pixel: it counts only where no direction sees the surface.
OCCLUDED_WEIGHT = 1e-6
#: Camera B's blending weight is multiplied by ``(CONFIDENCE_FLOOR + registration confidence)²``.
CONFIDENCE_FLOOR = 0.1


def parallax_positions(job: MosaicJob, i: int, row0: int, col0: int, u: np.ndarray,
                       v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Camera B's sensor positions corrected for parallax, with confidence and occlusion, for the output
    pixels ``[row0, row0 + h) × [col0, col0 + w)`` whose positions for points at infinity are ``u, v``.

    The output pixel's ray gives A's pixel (camera A of the same direction: the head's rotation centre,
    so A has no parallax), where the direction's parallax map holds the inverse depth ``w`` (nearest
    pixel: never a blend of two surfaces); B sees that point along ``ray − w · c_B`` (``c_B``, B's
    optical centre), evaluated exactly where ``w > 0`` — still one interpolation of B's image.
    """

    geo, img = job.geometry[i], job.images[i]
    a_geo = job.geometry[job.partner[i]]
    h, w = u.shape
    rows, cols = np.arange(row0, row0 + h), np.arange(col0, col0 + w)
    pa = exact_map(a_geo, job.canvas, rows, cols)
    ma = a_geo.model
    ia = np.clip(np.rint(np.nan_to_num(pa[..., 0], nan=-1.0)), 0, ma.width - 1).astype(np.int64)
    ja = np.clip(np.rint(np.nan_to_num(pa[..., 1], nan=-1.0)), 0, ma.height - 1).astype(np.int64)
    r_lo, r_hi = int(ja.min()), int(ja.max()) + 1
    par = read_npy_rows(img.parallax, r_lo, r_hi)
    sample = par[ja - r_lo, ia].astype(np.float32)
    inv_depth, conf, occ = sample[..., 0], sample[..., 1], sample[..., 2] > 0.5
    near = np.isfinite(inv_depth) & (inv_depth > 0)
    u, v = u.copy(), v.copy()
    if near.any():
        rays = job.canvas.rays(rows, cols)[near]
        centre_m = geo.model.camera_center_mm(geo.pan_deg, geo.tilt_deg) / 1000.0
        px, _ = geo.model.world_to_pixel(rays - inv_depth[near, None] * centre_m, geo.pan_deg, geo.tilt_deg,
                                         margin_px=None)
        u[near] = px[:, 0] + geo.offset_px[0]
        v[near] = px[:, 1] + geo.offset_px[1]
    return u, v, conf, occ


def warp_source(job: MosaicJob, i: int, rect: Rect) -> Warped | None:
    """Resample source ``i`` onto ``rect`` (the one interpolation); ``None`` if it does not land there."""
    geo, img = job.geometry[i], job.images[i]
    m = geo.model
    radius = KERNEL_RADIUS_PX[job.interp]
    sm = source_map(geo, job.canvas, rect, margin_px=radius + 1.0)
    if sm is None:
        return None
    conf = occ = None
    if i in job.partner:
        sm.u, sm.v, conf, occ = parallax_positions(job, i, sm.row0, sm.col0, sm.u, sm.v)
    weight = feather_weight(sm.u, sm.v, m.width, m.height)
    if occ is not None:
        # directions that registered the pixel confidently dominate those that did not; occluded ones
        # count only where no direction sees the surface
        trust = (np.float32(CONFIDENCE_FLOOR) + np.nan_to_num(conf)) ** 2
        weight = (weight * np.where(occ, np.float32(OCCLUDED_WEIGHT), trust)).astype(np.float32)
    rows_any = np.flatnonzero(weight.any(axis=1))
    if rows_any.size == 0:
        return None
    cols_any = np.flatnonzero(weight.any(axis=0))
    r_lo, r_hi, c_lo, c_hi = rows_any[0], rows_any[-1] + 1, cols_any[0], cols_any[-1] + 1
    u, v, weight = sm.u[r_lo:r_hi, c_lo:c_hi], sm.v[r_lo:r_hi, c_lo:c_hi], weight[r_lo:r_hi, c_lo:c_hi]
    values = sample_crop(img, u, v, weight > 0, job.interp, m.width, m.height)
    if not np.isfinite(values).all():  # (a whole-array test first: the per-pixel one is 50× slower)
        bad = ~np.isfinite(values).all(axis=-1)
        weight = np.where(bad, 0.0, weight).astype(np.float32)
        values[bad] = 0.0
    if (job.gains[i] != 1.0).any():
        values *= job.gains[i]
    if conf is not None:
        conf, occ = conf[r_lo:r_hi, c_lo:c_hi], occ[r_lo:r_hi, c_lo:c_hi]
    return Warped(i, sm.row0 + int(r_lo), sm.col0 + int(c_lo), values, weight, sm.step, sm.max_error_px, conf, occ)


def sample_crop(img: SourceImage, u: np.ndarray, v: np.ndarray, used: np.ndarray, interp: str, width: int,
                height: int) -> np.ndarray:
    """Read the part of the source the positions need (plus kernel margin) and interpolate it."""
    radius = KERNEL_RADIUS_PX[interp] + 1
    extra = SPLINE_PREFILTER_MARGIN_PX if interp == "spline" else 0
    uu, vv = u[used], v[used]
    x0 = int(max(0, np.floor(uu.min()) - radius - extra))
    x1 = int(min(width, np.ceil(uu.max()) + radius + extra + 1))
    y0 = int(max(0, np.floor(vv.min()) - radius - extra))
    y1 = int(min(height, np.ceil(vv.max()) + radius + extra + 1))
    crop = img.read((y0, y1), (x0, x1))
    finite = bool(np.isfinite(crop).all())
    bad = None if finite else ~np.isfinite(crop).all(axis=-1)
    if bad is not None:
        crop = np.where(bad[..., None], 0.0, crop).astype(np.float32)
    if interp == "spline":
        crop = spline_prefilter(crop)
    uc, vc = u - np.float32(x0), v - np.float32(y0)
    values = remap(crop, uc, vc, interp, prefiltered=interp == "spline")
    if bad is not None:
        values[_touches(bad, uc, vc, radius + (6 if interp == "spline" else 0))] = np.nan
    values[~used] = 0.0
    return values


def _touches(bad: np.ndarray, u: np.ndarray, v: np.ndarray, radius: int) -> np.ndarray:
    """Positions whose kernel (``radius`` px) reaches a bad source pixel."""

    grown = cv2.dilate(bad.astype(np.uint8), np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return remap(grown.astype(np.float32), u, v, "linear") > 0


def render_tile(job: MosaicJob, rect: Rect) -> tuple[np.ndarray, dict]:
    """The tile ``rect`` (h, w, bands) float32 (NaN where no source covers it) and its statistics.

    Linear blending accumulates each source as soon as it is resampled, so a tile holds one
    resampled source at a time; multi-band blending needs them all (on the tile plus its halo).
    """
    halo = multiband_halo_px(job.multiband_levels) if job.blend == "multiband" else 0
    work = rect.grow(halo) if halo else rect
    steps, errors = [], []
    if job.blend == "multiband":
        warped = [w for i in job.sources_for(work) if (w := warp_source(job, int(i), work)) is not None]
        steps, errors = [w.step for w in warped], [w.max_error_px for w in warped]
        out = _multiband(job, warped, work)[halo:halo + rect.shape[0], halo:halo + rect.shape[1]]
        del warped
        predicted = _predict_missing_b(job, out, None)
    else:
        acc = LinearBlend(rect.shape, job.n_bands)
        quality = LinearBlend(rect.shape, N_QUALITY) if job.has_quality else None
        with_parallax = []
        for i in job.sources_for(work):
            w = warp_source(job, int(i), work)
            if w is None:
                continue
            steps.append(w.step)
            errors.append(w.max_error_px)
            if w.confidence is not None:
                with_parallax.append(w)  # held until all are resampled: checked against each other
                continue
            acc.add(job.images[w.index].bands, w.row0 - rect.row0, w.col0 - rect.col0, w.values, w.weight)
        # camera B registered per pixel: where the directions disagree, the pixel keeps those that agree
        kept = reject_inconsistent([w.values for w in with_parallax], [w.weight for w in with_parallax],
                                   [(w.row0 - rect.row0, w.col0 - rect.col0) for w in with_parallax], rect.shape)
        for w, weight in zip(with_parallax, kept, strict=True):
            acc.add(job.images[w.index].bands, w.row0 - rect.row0, w.col0 - rect.col0, w.values, weight)
            if quality is not None:
                quality.add((0, 1), w.row0 - rect.row0, w.col0 - rect.col0,
                            np.stack([w.confidence, w.occluded], axis=-1).astype(np.float32), weight)
        out = acc.result()
        stats_quality = None
        if quality is not None:
            stats_quality = quality.result()
            stats_quality[..., 1] = (stats_quality[..., 1] > 0.5).astype(np.float32)
        predicted = _predict_missing_b(job, out, stats_quality)
    holes = int((~np.isfinite(out)).any(axis=-1).sum())
    stats = {"n_sources": len(steps), "holes": holes, "map_step_min": min(steps, default=0),
             "map_error_px": max(errors, default=0.0), "predicted_px": int(np.isfinite(predicted).sum())}
    if job.has_quality and job.blend != "multiband":
        stats["quality"] = stats_quality
    return out, stats


def _predict_missing_b(job: MosaicJob, out: np.ndarray, quality: np.ndarray | None) -> np.ndarray:
    """Fill camera B's bands of a rendered tile where no direction measured them or what B measured cannot
    be A's surface (:mod:`omnispectral.mosaic.predict`); completes ``quality``'s sun (0) and b_predicted layers.
    Returns the prediction's relative error per pixel (NaN where B was measured or nothing covers)."""
    if job.n_bands != N_BANDS:
        return np.full(out.shape[:2], np.nan, np.float32)
    implausible = implausible_b(out, job.b_predictor)
    measured = out[implausible, 3:6].copy()
    missing = ~np.isfinite(out[..., 3:6]).all(axis=-1) | implausible
    predicted = fill_missing_b(out, missing, job.b_predictor)
    out[implausible, 3:6] = np.minimum(out[implausible, 3:6], measured)  # it replaces light, never adds it
    if quality is not None:
        covered = np.isfinite(out).all(axis=-1)
        quality[..., 2] = np.where(covered, np.float32(0.0), np.float32(np.nan))
        quality[..., 3] = np.where(np.isfinite(predicted), predicted, quality[..., 2])
        quality[~covered, 0:2] = np.nan
    return predicted


def _multiband(job: MosaicJob, warped: list[Warped], work: Rect) -> np.ndarray:
    h, w = work.shape
    out = np.full((h, w, job.n_bands), np.nan, np.float32)
    for camera_bands in ((0, 1, 2), (3, 4, 5))[:job.n_bands // 3]:
        group = [x for x in warped if job.images[x.index].bands == camera_bands]
        if not group:
            continue
        values, weights, per_pixel = [], [], []
        for x in group:
            val = np.zeros((h, w, 3), np.float32)
            wt = np.zeros((h, w), np.float32)
            r, c = x.row0 - work.row0, x.col0 - work.col0
            val[r:r + x.weight.shape[0], c:c + x.weight.shape[1]] = x.values
            wt[r:r + x.weight.shape[0], c:c + x.weight.shape[1]] = x.weight
            values.append(val)
            weights.append(wt)
            per_pixel.append(x.confidence is not None)
        # camera B registered per pixel: views that disagree with the majority are dropped there, as in
        # linear blending (the seams then avoid them)
        checked = [i for i, p in enumerate(per_pixel) if p]
        if len(checked) >= 3:
            kept = reject_inconsistent([values[i] for i in checked], [weights[i] for i in checked],
                                       [(0, 0)] * len(checked), (h, w))
            for i, k in zip(checked, kept, strict=True):
                weights[i] = k
        out[..., camera_bands[0]:camera_bands[-1] + 1] = multiband_blend(values, weights, job.multiband_levels)
    return out


def tile_task(job: MosaicJob, ty: int, tx: int) -> dict:
    """Render and write chunk ``(ty, tx)`` of level 0; returns its statistics (also stored in its marker)."""
    t0 = time.perf_counter()
    store = PanoramaStore.open(job.store_path)
    r0, r1, c0, c1 = store.chunk_rect(0, ty, tx)
    data, stats = render_tile(job, Rect(r0, r1, c0, c1))
    quality = stats.pop("quality", None)
    if quality is not None:
        store.write_quality(ty, tx, quality)
        stats["occluded_px"] = int(np.nansum(quality[..., 1]))
    stats["seconds"] = round(time.perf_counter() - t0, 4)
    stats["pixels"] = int(data.shape[0] * data.shape[1])
    stats["run"] = job.run_id
    store.write_chunk(0, ty, tx, data, stats)
    return {"level": 0, "ty": ty, "tx": tx, **stats}


def pyramid_task(store_path: Path, level: int, ty: int, tx: int) -> dict:
    store = PanoramaStore.open(store_path)
    store.write_chunk(level, ty, tx, store.downsample_chunk(level, ty, tx))
    return {"level": level, "ty": ty, "tx": tx}


# ------------------------------------------------------------------------------------------ execution
def run_tasks(fn, shared, items: list[tuple], scheduler, workers: int | None,
              progress: Callable[[dict], None] | None) -> list[dict]:
    """Run ``fn(shared, *item)`` for every item with Dask: threads locally, or on the cluster at ``scheduler``.

    ``scheduler`` is ``None`` (local threaded scheduler, ``workers`` threads), a scheduler address
    (``tcp://…``) or a ``distributed.Client``; ``shared`` is sent to the cluster once.  ``progress``
    is called with each result as it finishes.
    """
    if not items:
        return []
    if scheduler is None:
        import dask  # lazy: dask (~0.4 s) and distributed (~0.5 s) serve only the task runner
        from dask.callbacks import Callback

        # one graph node holds ``shared``; the tasks name it by its key.  Passed as an argument as it is,
        # Dask would traverse the job (a dataclass with every source) once per task: ~0.4 ms per source
        # per task, 2 h of graph building for the 7000 tiles × 2520 sources of a gigapixel panorama
        leaf = dask.delayed(shared, name=f"shared-{uuid.uuid4().hex}", traverse=False)
        tasks = [dask.delayed(fn, pure=False)(leaf, *item) for item in items]
        keys = {t.key for t in tasks}

        def posttask(key, result, dsk, state, worker_id):
            if progress is not None and key in keys:
                progress(result)

        with Callback(posttask=posttask):
            return list(dask.compute(*tasks, scheduler="threads", num_workers=workers or None))
    from distributed import Client, as_completed

    # not the default client: dask collections elsewhere in this process keep their own scheduler
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler, set_as_default=False)
    try:
        # hash=False: a new key each time; with the value's hash as key, a client that has just closed (the
        # previous pyramid level) could release the same key under the new one ("lost dependencies")
        remote = client.scatter(shared, broadcast=True, hash=False)
        futures = [client.submit(worker_call, fn, remote, *item, pure=False) for item in items]
        results = []
        for future in as_completed(futures, loop=client.loop):
            results.append(future.result())
            if progress is not None:
                progress(results[-1])
        return results
    finally:
        if client is not scheduler:
            client.close()


# ------------------------------------------------------------------------------------------ the entry point
def open_input(source: str | Path | MergedDirections) -> MergedDirections:
    """Merged directions, open or as a directory; a raw session must be merged first
    (:func:`omnispectral.product.merge.merge_session`, which the ``mosaic`` command runs)."""
    if isinstance(source, MergedDirections):
        return source
    path = Path(source)
    if (path / "merged.json").is_file():
        return MergedDirections.open(path)
    if (path / "session.json").is_file():
        raise InputFileError(path, "a capture session: merge it into directions first "
                                   "(omnispectral.product.merge.merge_session, or the 'mosaic' command)")
    raise InputFileError(path, "neither a capture session (session.json) nor merged directions (merged.json)")


def mosaic(source: str | Path | MergedDirections, output: str | Path, *, width: int | None = None,
           tile: int = DEFAULT_TILE, interp: str = DEFAULT_INTERP, blend: str = "linear",
           multiband_levels: int = DEFAULT_MULTIBAND_LEVELS, gain_compensation: bool = False,
           scheduler=None, workers: int | None = None, overwrite: bool = False, compression: str = "blosc-zstd",
           region: tuple[int, int, int, int] | None = None, b_predictor: BandPredictor | None = None,
           progress: Callable[[str, dict, int, int], None] | None = None) -> dict:
    """Stitch a six-band panorama into a Zarr store; returns a summary (see :func:`summarise`).

    Parameters
    ----------
    source
        Merged directions (:mod:`omnispectral.mosaic.sources`), open or as a directory; everything the
        panorama's metadata needs (camera models, sensitivities, rig snapshot) is read from them, never
        from a rig file or a session.
    output
        The panorama store (``.zarr`` directory); an interrupted run with the same parameters resumes.
    width
        Panorama width (height = width / 2); default :func:`native_width` of camera A.
    tile
        Tile (and chunk) side in pixels.
    interp, blend, multiband_levels, gain_compensation
        Interpolation (:data:`omnispectral.mosaic.interp.METHODS`), ``"linear"`` (paper) or
        ``"multiband"`` blending, and per-direction gain compensation (:mod:`omnispectral.mosaic.gain`).
    scheduler, workers
        ``None`` for Dask's local threaded scheduler with ``workers`` threads (default: all cores),
        or a Dask distributed scheduler address / ``Client``.
    region
        ``(row0, row1, col0, col1)``: compute only the tiles meeting this window of level 0 (the
        rest stays NaN; a later run can add more).
    b_predictor
        The spectral prior's predictor of camera B's bands from A's
        (:func:`omnispectral.spectral.conditional.b_from_a_predictor`), used where B saw nothing
        (:mod:`omnispectral.mosaic.predict`); ``None`` fits one per tile to the tile's measured pixels.
    progress
        ``progress(stage, result, done, total)`` per finished tile (``stage`` is ``"tiles"`` or ``"pyramid"``).
    """
    check_method(interp)
    if blend not in BLENDS:
        raise ConfigurationError(f"unknown blend {blend!r}; expected one of {', '.join(BLENDS)}")
    if tile < 16:
        raise ConfigurationError(f"tile must be at least 16 px, got {tile}")
    t_start = time.perf_counter()
    output = Path(output).absolute()  # tasks may run in Dask worker processes started in other directories
    merged = open_input(source)
    merged.check_files()
    width = int(width) if width is not None else native_width(merged.cameras["A"].fx)
    if width < 8 or width % 2:
        raise ConfigurationError(f"width must be an even number ≥ 8, got {width}")
    gains = None
    if gain_compensation:
        gains = estimate_gains(merged)
    job = build_job(merged, Path(output), width, tile, interp, blend, multiband_levels, gains, b_predictor)
    attrs = panorama_attributes(merged, job, gain_compensation)
    store = PanoramaStore.create(output, width // 2, width, job.n_bands, tile, attrs, fingerprint(merged, job),
                                 overwrite=overwrite, compression=compression,
                                 quality_bands=N_QUALITY if job.has_quality and blend != "multiband" else 0)
    t_tiles = time.perf_counter()
    tiles = _tiles_in(store, region)
    computed = _run_level0(job, store, tiles, scheduler, workers, progress)
    t_pyramid = time.perf_counter()
    _run_pyramid(store, tiles, scheduler, workers, progress)
    t_end = time.perf_counter()
    return summarise(store, tiles, computed, {"prepare": t_tiles - t_start, "tiles": t_pyramid - t_tiles,
                                              "pyramid": t_end - t_pyramid, "total": t_end - t_start}, job)


def _tiles_in(store: PanoramaStore, region: tuple[int, int, int, int] | None) -> list[tuple[int, int]]:
    """Level-0 chunks meeting ``region`` (all by default)."""
    ny, nx = store.n_chunks(0)
    if region is None:
        return [(ty, tx) for ty in range(ny) for tx in range(nx)]
    r0, r1, c0, c1 = (int(x) for x in region)
    h, w = store.shapes[0]
    if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
        raise ConfigurationError(f"region {region} is not a window of the {w} x {h} panorama")
    t = store.tile
    return [(ty, tx) for ty in range(r0 // t, (r1 - 1) // t + 1) for tx in range(c0 // t, (c1 - 1) // t + 1)]


def _ancestors(tiles: list[tuple[int, int]], level: int) -> list[tuple[int, int]]:
    """Chunks of ``level`` computed from the given level-0 chunks (chunks keep their size, levels halve)."""
    return sorted({(ty >> level, tx >> level) for ty, tx in tiles})


def _run_level0(job, store, tiles, scheduler, workers, progress) -> int:
    done = set(store.done_markers(0))
    todo = [t for t in tiles if t not in done]
    for level in range(1, len(store.shapes)):  # new level-0 chunks make their pyramid chunks stale
        for ty, tx in _ancestors(todo, level):
            store.unmark(level, ty, tx)
    total = len(tiles)
    counter = [total - len(todo)]

    def on_tile(result):
        counter[0] += 1
        if progress is not None:
            progress("tiles", result, counter[0], total)

    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # Dask parallelises over tiles; OpenCV's own threads would oversubscribe the cores
    try:
        run_tasks(tile_task, job, todo, scheduler, workers, on_tile)
    finally:
        cv2.setNumThreads(threads)
    return len(todo)


def _run_pyramid(store, tiles, scheduler, workers, progress) -> None:
    wanted = {k: _ancestors(tiles, k) for k in range(1, len(store.shapes))}
    done = {k: set(store.done_markers(k)) for k in wanted}
    total = sum(len(v) for v in wanted.values())
    counter = [sum(len(done[k] & set(v)) for k, v in wanted.items())]

    def on_chunk(result):
        counter[0] += 1
        if progress is not None:
            progress("pyramid", result, counter[0], total)

    for level, chunks in wanted.items():
        todo = [c for c in chunks if c not in done[level]]
        run_tasks(pyramid_task, store.path, [(level, ty, tx) for ty, tx in todo], scheduler, workers, on_chunk)


# ------------------------------------------------------------------------------------------ metadata
def panorama_attributes(merged: MergedDirections, job: MosaicJob, gain_compensation: bool) -> dict:
    """The store's ``omnispectral`` attributes: bands, sensitivities, estimator, rig, session, geometry, method."""
    meta = merged.meta
    system = meta.get("system")  # recorded by the merge (product.merge); None for directions made without it
    return {
        "bands": list(meta.get("band_names", BAND_NAMES)),
        "units": meta.get("units", "DN per second of exposure"),
        "camera_bands": meta.get("camera_bands"),
        "wavelength_nm": system["wavelength_nm"] if system else None,
        "sensitivities": system["sensitivity"] if system else None,
        "sensitivity_description": system["description"] if system else None,
        "estimator": meta.get("estimator"),
        "rig": meta.get("rig"),
        "session": meta.get("session"),
        "merged_directions": str(merged.path.resolve()),
        "cameras": meta.get("cameras"),
        "n_directions": len(merged.directions),
        "geometry": "equirectangular: row 0 at latitude +90, column 0 at longitude -180, pixel centres at +0.5; "
                    "world +Y up, longitude 0 = +Z, longitude +90 = -X (omnispectral.imaging.geometry)",
        "mosaic": {"width": job.canvas.width, "height": job.canvas.height, "interp": job.interp, "blend": job.blend,
                   "multiband_levels": job.multiband_levels if job.blend == "multiband" else None,
                   "gain_compensation": gain_compensation,
                   "gains": job.gains.tolist() if gain_compensation else None,
                   "weights": "linear blending: tent (1 - |2(u+1/2)/W - 1|)(1 - |2(v+1/2)/H - 1|) per sensor",
                   "fill": "NaN where camera A covers no direction; camera B's bands predicted from A's where B "
                           "saw nothing (omnispectral.mosaic.predict; quality layer b_predicted)",
                   "b_predictor": job.b_predictor.to_dict() if job.b_predictor is not None else "per tile"},
    }


def fingerprint(merged: MergedDirections, job: MosaicJob) -> dict:
    """What determines the output: inputs (files, sizes, mtimes, poses, offsets, scales), grid and method."""
    h = hashlib.sha256()
    for img, geo in zip(job.images, job.geometry, strict=True):
        st = img.path.stat()
        par = None
        if img.parallax is not None:
            ps = img.parallax.stat()
            par = [str(img.parallax.resolve()), ps.st_size, ps.st_mtime_ns]
        h.update(json.dumps([str(img.path.resolve()), st.st_size, st.st_mtime_ns, img.pan_deg, img.tilt_deg,
                             img.scale, list(img.offset_px), geo.model.to_dict(), par], sort_keys=True).encode())
    h.update(job.gains.tobytes())
    predictor = job.b_predictor.to_dict() if job.b_predictor is not None else None
    return {"inputs_sha256": h.hexdigest(), "width": job.canvas.width, "tile": job.tile, "interp": job.interp,
            "blend": job.blend, "multiband_levels": job.multiband_levels, "b_predictor": predictor}


def peak_rss_mb() -> float:
    """Peak resident set size of this process in MiB (Linux ``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summarise(store: PanoramaStore, tiles: list[tuple[int, int]], computed: int, seconds: dict,
              job: MosaicJob) -> dict:
    """Summary of a run: output, sizes, tiles computed/skipped, holes, timings, throughput, peak memory."""
    all_markers = store.done_markers(0)
    markers = {t: all_markers[t] for t in tiles if t in all_markers}
    n_tiles = len(tiles)
    h, w = store.shapes[0]
    holes = sum(int(m.get("holes", 0)) for m in markers.values())
    n_src = [int(m.get("n_sources", 0)) for m in markers.values()]
    computed_px = sum(int(m.get("pixels", 0)) for t, m in markers.items() if m.get("run") == job.run_id)
    return {"output": str(store.path), "width": w, "height": h, "bands": store.n_bands, "levels": [list(s) for s in
                                                                                             store.shapes],
            "tile": store.tile, "interp": job.interp, "blend": job.blend, "n_sources": len(job.images),
            "tiles": n_tiles, "tiles_computed": computed, "tiles_skipped": n_tiles - computed,
            "holes_px": holes, "sources_per_tile_mean": float(np.mean(n_src)) if n_src else 0.0,
            "sources_per_tile_max": max(n_src, default=0),
            "max_map_error_px": max((float(m.get("map_error_px", 0.0)) for m in markers.values()), default=0.0),
            "seconds": {k: round(v, 3) for k, v in seconds.items()},
            "megapixels_per_s": round(computed_px / 1e6 / seconds["tiles"], 3) if seconds["tiles"] > 0 else None,
            "peak_rss_mb": round(peak_rss_mb(), 1)}
