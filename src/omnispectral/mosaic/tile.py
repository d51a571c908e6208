"""One tile of the panorama: the job every tile task shares, the resampling of each source onto a tile, the
blending of the resampled sources, and the tile and pyramid tasks (paper Sec. 4.4–4.5).

For each output tile (a chunk of the store) :func:`render_tile`

1. finds the (direction, camera) images whose bounding cone meets the tile's cone
   (:meth:`MosaicJob.sources_for`, :mod:`omnispectral.mosaic.maps`);
2. computes for every tile pixel where it lands on each of those sensors through the composed
   geometry (equirect pixel → ray → inverse head rotation → mounting → OpenCV lens with
   distortion → sensor pixel, plus camera B's registration offset, or B's per-pixel parallax:
   :func:`parallax_positions`) — one map, no intermediate undistorted or polar image;
3. reads only the crop of each source the map touches, interpolates it once
   (:func:`sample_crop`, :mod:`omnispectral.mosaic.interp`), weights it with the linear-blending weight
   ``w(u, v) = (1 - |2(u + 1/2)/W - 1|)(1 - |2(v + 1/2)/H - 1|)`` (:mod:`omnispectral.mosaic.blending`) and
   combines the sources by the job's blending method (:data:`TILE_RENDERERS`, keyed like
   :data:`omnispectral.mosaic.blending.BLENDS`): camera A into bands 0–2 and camera B into bands 3–5, three
   bands for a one-camera rig; camera B's bands are predicted from A's where B saw nothing
   (:mod:`omnispectral.mosaic.predict`).

:func:`tile_task` writes a rendered tile as its chunk, atomically with a completion marker
(:mod:`omnispectral.mosaic.store`); :func:`pyramid_task` makes a chunk of a pyramid level from the level
below.  A task holds its tile and the crops of the sources that overlap it, so its memory depends on the
tile size and the directions per tile, never on the panorama size.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.imaging.channels import finite_pixels
from omnispectral.imaging.geometry import native_width
from omnispectral.imaging.halffloat import to_float32
from omnispectral.imaging.parallax import OCCLUSION_HIDDEN, OCCLUSION_OTHER_SURFACE
from omnispectral.mosaic.blending import (
    LinearBlend,
    blend_method,
    feather_weight,
    multiband_blend,
    reject_inconsistent,
)
from omnispectral.mosaic.edges import HALO_PX as EDGE_HALO_PX
from omnispectral.mosaic.edges import REACH_PX as EDGE_REACH_PX
from omnispectral.mosaic.edges import resample_edges
from omnispectral.mosaic.interp import SPLINE_PREFILTER_MARGIN_PX, interpolation, remap, spline_prefilter
from omnispectral.mosaic.kernels import compiled_kernels
from omnispectral.mosaic.maps import Canvas, Rect, SourceGeometry, rect_map, source_map, tile_cone
from omnispectral.mosaic.options import MosaicOptions
from omnispectral.mosaic.predict import b_outliers, brightest_measured_b, contaminated_beside, fill_missing_b
from omnispectral.mosaic.sources import MergedDirections, SourceImage
from omnispectral.mosaic.store import PanoramaStore
from omnispectral.mosaic.unmix import HALO_PX as UNMIX_HALO_PX
from omnispectral.mosaic.unmix import unmix_b_at_edges
from omnispectral.spectral.conditional import BandPredictor

__all__ = ["CONFIDENCE_FLOOR", "N_BANDS", "N_QUALITY", "OCCLUDED_WEIGHT", "PREFILTER_BAD_REACH_PX", "TILE_RENDERERS",
           "MosaicJob", "Warped", "build_job", "parallax_positions", "pyramid_task", "render_tile", "sample_crop",
           "tile_task", "warp_source"]

#: Bands of a two-camera rig's panorama; a one-camera rig's has three (``MosaicJob.n_bands``).
N_BANDS = 6
#: Registration-quality layer of a panorama whose camera B carries parallax maps: blended registration
#: confidence (0..1), occluded (1 where every direction that sees the pixel with B has it hidden), sun
#: (0 from the mosaic; 1 where processing painted the recovered sun, ``omnispectral.product.sun``) and
#: b_predicted (the relative error of B's bands predicted from A's where B saw nothing,
#: :mod:`omnispectral.mosaic.predict`; 0 where B measured the pixel) and b_unmixed (the relative error of B's
#: bands where an edge mixes B's two surfaces in A's share, :mod:`omnispectral.mosaic.unmix`; 0 elsewhere).
N_QUALITY = 5


# ------------------------------------------------------------------------------------------ the job
@dataclass
class MosaicJob:
    """Everything a tile task needs (picklable, so it can be sent to Dask workers once).

    ``tile``, ``interp``, ``blend`` and ``multiband_levels`` are the run's :class:`MosaicOptions` (the job keeps
    what a tile needs, never the scheduler); ``gains`` is ``(n_sources, 3)``, per source and band of its camera.
    """

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
    #: resample straight edges by their partial areas (:mod:`omnispectral.mosaic.edges`)
    edge_model: bool = True
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


def build_job(merged: MergedDirections, store_path: Path, options: MosaicOptions,
              gains: np.ndarray | None = None) -> MosaicJob:
    """The job of a mosaic run: every source of ``merged`` with its geometry, on the options' canvas.

    Parameters
    ----------
    merged
        The merged directions.
    store_path
        The panorama store the tile tasks write to.
    options
        The run's options (width, tile, interpolation, blending, levels, B's predictor); without a width, the
        canvas is camera A's native width (:func:`~omnispectral.imaging.geometry.native_width`).
    gains
        ``(n_sources, 3)`` gain per source and band of its camera (default 1).

    Returns
    -------
    MosaicJob
        The job, with a run identifier recorded in the markers of the tiles it computes.
    """
    width_px = options.width if options.width is not None else native_width(merged.cameras["A"].fx)
    images = merged.sources()
    geometry = [SourceGeometry.build(merged.cameras[s.camera], s.pan_deg, s.tilt_deg, s.offset_px) for s in images]
    if gains is None:
        gains = np.ones((len(images), 3), np.float32)
    return MosaicJob(Canvas(width_px, width_px // 2), options.tile, options.interp, options.blend,
                     options.multiband_levels, images, geometry, np.asarray(gains, np.float32), Path(store_path),
                     run_id=f"{os.getpid()}-{time.time_ns()}", n_bands=merged.n_bands, b_predictor=options.b_predictor,
                     edge_model=options.edge_model)


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


#: A bad (non-finite) source pixel, zeroed before the B-spline prefilter, still disturbs the coefficients this
#: far (the filter's response decays as ``|√3 - 2|^k``: 4e-4 at 6 px); positions whose kernel reaches so far
#: are left out.
PREFILTER_BAD_REACH_PX = 6
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
    pa = rect_map(a_geo, job.canvas, Rect(row0, row0 + h, col0, col0 + w))  # A's pixel: within 1e-3 px
    sample = _records_at_nearest_pixels(img, pa.u, pa.v, a_geo.model.width, a_geo.model.height)
    inv_depth, conf, occ = sample[..., 0], sample[..., 1], sample[..., 2]
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


def _records_at_nearest_pixels(img: SourceImage, u: np.ndarray, v: np.ndarray, width: int,
                               height: int) -> np.ndarray:
    """Camera B's parallax records (float32 ``(*u.shape, 3)``) at camera A's sensor pixel nearest each position
    ``(u, v)`` (NaN as -1; clipped to the ``width × height`` sensor), read as the window those pixels span."""
    kernels = compiled_kernels()
    if kernels is not None:
        ia, ja = np.empty(u.shape, np.int64), np.empty(u.shape, np.int64)
        c_lo, c_hi, r_lo, r_hi = (int(b) for b in kernels.nearest_pixels(u, v, width, height, ia, ja))
        records = to_float32(_parallax_window(img, (r_lo, r_hi + 1), (c_lo, c_hi + 1)))
        out = np.empty((*u.shape, records.shape[-1]), np.float32)
        kernels.gather_records(records, ia, ja, r_lo, c_lo, out)
        return out
    ia = np.clip(np.rint(np.nan_to_num(u, nan=-1.0)), 0, width - 1).astype(np.int64)
    ja = np.clip(np.rint(np.nan_to_num(v, nan=-1.0)), 0, height - 1).astype(np.int64)
    r_lo, c_lo = int(ja.min()), int(ia.min())
    par = _parallax_window(img, (r_lo, int(ja.max()) + 1), (c_lo, int(ia.max()) + 1))
    # one flat index into the (pixel, 3) records: np.take gathers them 2x faster than a 2-D fancy index
    return to_float32(np.take(par.reshape(-1, par.shape[-1]), (ja - r_lo) * par.shape[1] + (ia - c_lo), axis=0))


def _parallax_window(img: SourceImage, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    """The window of camera B's parallax map, refused (naming the file) when the map does not cover it: a map
    smaller than camera A's sensor."""
    par = img.read_parallax(rows, cols)
    if par.ndim != 3 or par.shape[:2] != (rows[1] - rows[0], cols[1] - cols[0]) or par.shape[2] < 3:
        raise InputFileError(img.parallax, f"parallax map does not cover camera A's pixels {rows[0]}..{rows[1]} x "
                                           f"{cols[0]}..{cols[1]} (window read {par.shape})")
    return par


def warp_source(job: MosaicJob, i: int, rect: Rect) -> Warped | None:
    """Resample source ``i`` onto ``rect`` (the one interpolation); ``None`` if it does not land there."""
    geo, img = job.geometry[i], job.images[i]
    m = geo.model
    radius = interpolation(job.interp).radius_px
    sm = source_map(geo, job.canvas, rect, margin_px=radius + 1.0)
    if sm is None:
        return None
    conf = occ = None
    grid_u, grid_v = sm.u, sm.v  # at infinity: smooth, the footprint's shape for the edge model
    if i in job.partner:
        sm.u, sm.v, conf, occ = parallax_positions(job, i, sm.row0, sm.col0, sm.u, sm.v)
    weight = feather_weight(sm.u, sm.v, m.width, m.height)
    if occ is not None:
        # directions that registered the pixel confidently dominate those that did not; occluded ones
        # count only where no direction sees the surface; where B shows another surface it is not used
        trust = (np.float32(CONFIDENCE_FLOOR) + np.nan_to_num(conf)) ** 2
        hidden = occ > 0.5 * OCCLUSION_HIDDEN
        other = occ > 0.5 * (OCCLUSION_HIDDEN + OCCLUSION_OTHER_SURFACE)
        weight = (weight * np.where(other, np.float32(0.0), np.where(hidden, np.float32(OCCLUDED_WEIGHT), trust))
                  ).astype(np.float32)
        occ = hidden
    rows_any = np.flatnonzero(weight.any(axis=1))
    if rows_any.size == 0:
        return None
    cols_any = np.flatnonzero(weight.any(axis=0))
    r_lo, r_hi, c_lo, c_hi = rows_any[0], rows_any[-1] + 1, cols_any[0], cols_any[-1] + 1
    u, v, weight = sm.u[r_lo:r_hi, c_lo:c_hi], sm.v[r_lo:r_hi, c_lo:c_hi], weight[r_lo:r_hi, c_lo:c_hi]
    grid = (grid_u[r_lo:r_hi, c_lo:c_hi], grid_v[r_lo:r_hi, c_lo:c_hi]) if job.edge_model else None
    values = sample_crop(img, u, v, weight > 0, job.interp, m.width, m.height, job.edge_model, grid)
    if not np.isfinite(values).all():  # (a whole-array test first: the per-pixel one is 50× slower)
        bad = ~finite_pixels(values)
        weight = np.where(bad, 0.0, weight).astype(np.float32)
        values[bad] = 0.0
    if (job.gains[i] != 1.0).any():
        values *= job.gains[i]
    if conf is not None:
        conf, occ = conf[r_lo:r_hi, c_lo:c_hi], occ[r_lo:r_hi, c_lo:c_hi]
    return Warped(i, sm.row0 + int(r_lo), sm.col0 + int(c_lo), values, weight, sm.step, sm.max_error_px, conf, occ)


def sample_crop(img: SourceImage, u: np.ndarray, v: np.ndarray, used: np.ndarray, interp: str, width: int,
                height: int, edge_model: bool = False, grid_uv: tuple[np.ndarray, np.ndarray] | None = None
                ) -> np.ndarray:
    """Read the part of the source the positions need (plus kernel margin) and interpolate it; with
    ``edge_model``, then give output pixels at straight edges their footprint's share of each side
    (:func:`omnispectral.mosaic.edges.resample_edges`).

    Parameters
    ----------
    img
        The source.
    u, v
        Sensor positions (px, float32) of the output pixels.
    used
        Output pixels to sample (the others get 0).
    interp
        Interpolation, a key of :data:`omnispectral.mosaic.interp.METHODS`.
    width, height
        The sensor's size in px.
    edge_model
        Resample straight edges by their partial areas (:mod:`omnispectral.mosaic.edges`).
    grid_uv
        The output grid's smooth map for the edge model's footprints (default ``(u, v)``).

    Returns
    -------
    numpy.ndarray
        ``(*u.shape, 3)`` float32; NaN where the kernel reaches a non-finite source pixel.
    """
    method = interpolation(interp)
    radius = max(method.radius_px + 1, EDGE_REACH_PX if edge_model else 0)
    extra = SPLINE_PREFILTER_MARGIN_PX if method.prefilter else 0
    uu, vv = u[used], v[used]
    x0 = int(max(0, np.floor(uu.min()) - radius - extra))
    x1 = int(min(width, np.ceil(uu.max()) + radius + extra + 1))
    y0 = int(max(0, np.floor(vv.min()) - radius - extra))
    y1 = int(min(height, np.ceil(vv.max()) + radius + extra + 1))
    crop = img.read((y0, y1), (x0, x1))
    finite = bool(np.isfinite(crop).all())
    bad = None if finite else ~finite_pixels(crop)
    if bad is not None:
        crop = np.where(bad[..., None], 0.0, crop).astype(np.float32)
    coefficients = spline_prefilter(crop) if method.prefilter else crop
    uc, vc = u - np.float32(x0), v - np.float32(y0)
    values = remap(coefficients, uc, vc, interp, prefiltered=method.prefilter)
    if edge_model:
        grid = None if grid_uv is None else (grid_uv[0] - np.float32(x0), grid_uv[1] - np.float32(y0))
        resample_edges(crop, uc, vc, values, used, bad, grid)
    if bad is not None:
        values[_touches(bad, uc, vc, radius + (PREFILTER_BAD_REACH_PX if method.prefilter else 0))] = np.nan
    values[~used] = 0.0
    return values


def _touches(bad: np.ndarray, u: np.ndarray, v: np.ndarray, radius: int) -> np.ndarray:
    """Positions whose kernel (``radius`` px) reaches a bad source pixel."""

    grown = cv2.dilate(bad.astype(np.uint8), np.ones((2 * radius + 1, 2 * radius + 1), np.uint8))
    return remap(grown.astype(np.float32), u, v, "linear") > 0


def _render_linear(job: MosaicJob, work: Rect) -> tuple[np.ndarray, np.ndarray | None, list[int], list[float]]:
    """Linear blending (paper Sec. 4.5): each source accumulated as soon as it is resampled, so a tile holds one
    resampled source at a time; camera B registered per pixel is held until all are resampled and voted on
    (:func:`~omnispectral.mosaic.blending.reject_inconsistent`).  Returns the ``work`` area's bands, its quality
    layer (or None), the map steps and the map errors of the sources."""
    steps, errors = [], []
    acc = LinearBlend(work.shape, job.n_bands)
    quality = LinearBlend(work.shape, N_QUALITY) if job.has_quality else None
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
        acc.add(job.images[w.index].bands, w.row0 - work.row0, w.col0 - work.col0, w.values, w.weight)
    # camera B registered per pixel: where the directions disagree, the pixel keeps those that agree
    # (and of two that see two surfaces, the one A's bands predict)
    kept = reject_inconsistent([w.values for w in with_parallax], [w.weight for w in with_parallax],
                               [(w.row0 - work.row0, w.col0 - work.col0) for w in with_parallax], work.shape,
                               expected=_expected_b_sum(job, len(with_parallax), lambda: acc.result()[..., :3]))
    for w, weight in zip(with_parallax, kept, strict=True):
        acc.add(job.images[w.index].bands, w.row0 - work.row0, w.col0 - work.col0, w.values, weight)
        if quality is not None:
            quality.add((0, 1), w.row0 - work.row0, w.col0 - work.col0,
                        np.stack([w.confidence, w.occluded], axis=-1).astype(np.float32), weight)
    out = acc.result()
    stats_quality = None
    if quality is not None:
        stats_quality = quality.result()
        stats_quality[..., 1] = (stats_quality[..., 1] > 0.5).astype(np.float32)
    return out, stats_quality, steps, errors


def _render_multiband(job: MosaicJob, work: Rect) -> tuple[np.ndarray, np.ndarray | None, list[int], list[float]]:
    """Multi-band blending (Burt & Adelson 1983): every source resampled on the tile plus its halo (``work``), then
    blended per camera (:func:`_multiband`).  No quality layer."""
    warped = [w for i in job.sources_for(work) if (w := warp_source(job, int(i), work)) is not None]
    steps, errors = [w.step for w in warped], [w.max_error_px for w in warped]
    return _multiband(job, warped, work), None, steps, errors


#: Tile renderers by blending method (the keys of :data:`omnispectral.mosaic.blending.BLENDS`):
#: ``renderer(job, work) -> (the bands of work, its quality or None, map steps, map errors)``, ``work`` the tile
#: and its halo.
TILE_RENDERERS: dict[str, Callable[[MosaicJob, Rect],
                                   tuple[np.ndarray, np.ndarray | None, list[int], list[float]]]] = {
    "linear": _render_linear,
    "multiband": _render_multiband,
}


def render_tile(job: MosaicJob, rect: Rect) -> tuple[np.ndarray, dict]:
    """The tile ``rect`` (h, w, bands) float32 (NaN where no source covers it) and its statistics.

    Parameters
    ----------
    job
        The run's job (:func:`build_job`).
    rect
        The tile's pixels on the canvas.

    Returns
    -------
    tile : numpy.ndarray
        ``(h, w, n_bands)`` float32, DN/s.
    stats : dict
        ``n_sources``, ``holes`` (px), ``map_step_min``, ``map_error_px``, ``predicted_px``, ``unmixed_px``
        and, when the blending keeps it, the ``quality`` layer ``(h, w, N_QUALITY)``.

    Notes
    -----
    Linear blending accumulates each source as soon as it is resampled, so a tile holds one
    resampled source at a time; multi-band blending needs them all (on the tile plus its halo).  A six-band
    tile is rendered with at least :data:`omnispectral.mosaic.unmix.HALO_PX` pixels around it, so that camera B
    at its border pixels is unmixed from what the neighbouring tiles hold, and with the edge model one more
    (:data:`omnispectral.mosaic.edges.HALO_PX`: a pixel's footprint comes from its neighbours' positions): the
    same panorama whatever the tiling (any tile gets that one pixel for the edge model).  B's predictions
    (:mod:`omnispectral.mosaic.predict`), whose neighbourhoods reach farther (16 px, 31 px for the outlier
    tests), see only that halo beyond the tile.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.4, Eq. (4) (the polar-coordinate geometry, composed per output pixel
       with the lens model of Sec. 4.2), Sec. 4.5 (linear blending of the overlaps), Fig. 8.
    .. [2] R. G. Keys, "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981
       (the ``cubic`` interpolations).
    .. [3] P. J. Burt, E. H. Adelson, "A multiresolution spline with application to image mosaics", ACM TOG
       2(4), 1983 (multi-band blending).
    """
    blend = blend_method(job.blend)
    halo = max(blend.halo_px(job.multiband_levels),
               (UNMIX_HALO_PX if job.n_bands == N_BANDS else 0) + (EDGE_HALO_PX if job.edge_model else 0))
    work = rect.grow(halo) if halo else rect
    out, quality, steps, errors = TILE_RENDERERS[job.blend](job, work)
    predicted, unmixed = _predict_missing_b(job, out, quality)
    if halo:  # the halo served the blending and B's edges; the tile is what is kept
        inner = (slice(halo, halo + rect.shape[0]), slice(halo, halo + rect.shape[1]))
        out, predicted, unmixed = (np.ascontiguousarray(x[inner]) for x in (out, predicted, unmixed))
        quality = None if quality is None else np.ascontiguousarray(quality[inner])
    holes = int((~finite_pixels(out)).sum())
    stats = {"n_sources": len(steps), "holes": holes, "map_step_min": min(steps, default=0),
             "map_error_px": max(errors, default=0.0), "predicted_px": int(np.isfinite(predicted).sum()),
             "unmixed_px": int(np.isfinite(unmixed).sum())}
    if job.has_quality and blend.quality_layer:
        stats["quality"] = quality
    return out, stats


def _predict_missing_b(job: MosaicJob, out: np.ndarray, quality: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Fill camera B's bands of a rendered tile where no direction measured them, what B measured cannot
    be A's surface, or B's sample beside such a pixel took in what hid it (:mod:`omnispectral.mosaic.predict`),
    then mix B's two surfaces in A's share at edges between them (:mod:`omnispectral.mosaic.unmix`);
    completes ``quality``'s sun (0), b_predicted and b_unmixed layers.
    Returns the relative error of B's bands where they were predicted, and where they were unmixed (each NaN
    elsewhere)."""
    if job.n_bands != N_BANDS:
        return np.full(out.shape[:2], np.nan, np.float32), np.full(out.shape[:2], np.nan, np.float32)
    implausible, too_dark = b_outliers(out, job.b_predictor)
    measured = out[implausible, 3:6].copy()
    missing = ~finite_pixels(out[..., 3:6]) | implausible | too_dark
    missing |= contaminated_beside(out, missing, job.b_predictor)
    ceiling = brightest_measured_b(out, missing) if too_dark.any() else None
    predicted = fill_missing_b(out, missing, job.b_predictor)
    out[implausible, 3:6] = np.minimum(out[implausible, 3:6], measured)  # it replaces light, never adds it
    if ceiling is not None:  # nor more than B measured around it
        out[too_dark, 3:6] = np.minimum(out[too_dark, 3:6], ceiling[too_dark])
    unmixed = unmix_b_at_edges(out, predicted)
    predicted = np.where(np.isfinite(unmixed), np.float32(np.nan), predicted)  # mixed from its surfaces after all
    if quality is not None:
        covered = finite_pixels(out)
        quality[..., 2] = np.where(covered, np.float32(0.0), np.float32(np.nan))
        quality[..., 3] = np.where(np.isfinite(predicted), predicted, quality[..., 2])
        quality[..., 4] = np.where(np.isfinite(unmixed), unmixed, quality[..., 2])
        quality[~covered, 0:2] = np.nan
    return predicted, unmixed


def _expected_b_sum(job: MosaicJob, n_views: int, a_bands: Callable[[], np.ndarray]) -> np.ndarray | None:
    """``(h, w)`` float32: the band sum of camera B that A's bands (``a_bands()``, ``(h, w, 3)``) predict (the
    prior's linear predictor), NaN where A is not finite; None where it cannot settle anything: fewer than two
    B views, a one-camera job or no predictor."""
    if n_views < 2 or job.n_bands != N_BANDS or job.b_predictor is None:
        return None
    weights = np.asarray(job.b_predictor.matrix, np.float64).sum(axis=0)  # Σ_k M_kj: the sum of M a in one product
    return (np.asarray(a_bands(), np.float64) @ weights).astype(np.float32)


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
        # linear blending (the seams then avoid them); A is blended first, so its bands settle two B views
        checked = [i for i, p in enumerate(per_pixel) if p]
        kept = reject_inconsistent([values[i] for i in checked], [weights[i] for i in checked],
                                   [(0, 0)] * len(checked), (h, w),
                                   expected=_expected_b_sum(job, len(checked), lambda: out[..., :3]))
        for i, k in zip(checked, kept, strict=True):
            weights[i] = k
        out[..., camera_bands[0]:camera_bands[-1] + 1] = multiband_blend(values, weights, job.multiband_levels)
    return out


def tile_task(job: MosaicJob, ty: int, tx: int) -> dict:
    """Render and write chunk ``(ty, tx)`` of level 0; returns its statistics (also stored in its marker).

    Parameters
    ----------
    job
        The run's job (sent to every task once).
    ty, tx
        The chunk's row and column in level 0.

    Returns
    -------
    dict
        ``level`` (0), ``ty``, ``tx`` and :func:`render_tile`'s statistics with ``seconds``, ``pixels``, ``run``
        (and ``occluded_px`` with a quality layer).
    """
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
    """Make and write chunk ``(ty, tx)`` of pyramid ``level`` from the level below (2 × 2 box average).

    Parameters
    ----------
    store_path
        The panorama store.
    level
        The pyramid level (≥ 1).
    ty, tx
        The chunk's row and column in ``level``.

    Returns
    -------
    dict
        ``level``, ``ty``, ``tx``.
    """
    store = PanoramaStore.open(store_path)
    store.write_chunk(level, ty, tx, store.downsample_chunk(level, ty, tx))
    return {"level": level, "ty": ty, "tx": tx}
