"""Per-direction gain compensation (Brown & Lowe, "Automatic panoramic image stitching using invariant
features", IJCV 74(1), 2007, Sec. 6, Eq. (29)).

Exposure drift between directions, or a vignetting residue, makes neighbouring images disagree in
their overlaps.  For every camera and band, gains ``g_i`` minimise

    ``e = ½ Σ_i Σ_j N_ij ((g_i Ī_ij - g_j Ī_ji)² / σ_N² + (1 - g_i)² / σ_g²)``,

where ``N_ij`` is the number of panorama pixels images ``i`` and ``j`` share and ``Ī_ij`` the mean
of image ``i`` there.  The first term equalises overlaps, the second keeps the gains near 1 (so
the absolute radiometry is kept on average).  Intensities are divided by their overall mean per
band, so ``σ_N = 0.1`` is relative (Brown & Lowe's 10 grey levels out of ~100).  Brown & Lowe's
``σ_g = 0.1`` makes the prior as strong as the data, which suits small auto-exposure errors of LDR
images but leaves a third of a 10 % drift in place; HDR radiance is calibrated, so here the prior
only anchors the overall scale: ``σ_g = 1``.  The normal equations are a small dense linear
system per band.

Overlap means come from a coarse equirectangular grid (``width`` pixels around), sampled from
every source at one pixel in ``decimate`` (rows read one at a time, so memory holds one decimated
image).  Only pixels with a positive linear-blending weight count.
"""

from __future__ import annotations

import numpy as np

from omnispectral.checksums import verified
from omnispectral.imaging.geometry import lonlat_to_equirect_pixel, ray_to_lonlat
from omnispectral.mosaic.blending import feather_weight
from omnispectral.mosaic.interp import remap
from omnispectral.mosaic.maps import Canvas, Rect, SourceGeometry, source_map
from omnispectral.mosaic.sources import MergedDirections, SourceImage, npy_shape, read_npy_rows

__all__ = ["SIGMA_G", "SIGMA_N", "coarse_width", "estimate_gains", "overlap_statistics", "read_decimated",
           "solve_gains", "source_samples"]

SIGMA_N = 0.1
SIGMA_G = 1.0


def coarse_width(fx_px: float, decimate: int) -> int:
    """Width of the coarse grid: the sources' angular pixel after decimation, at least 256 and at most 8192."""
    return int(np.clip(2 * round(np.pi * fx_px / decimate), 256, 8192))


def read_decimated(img: SourceImage, decimate: int) -> np.ndarray:
    """Every ``decimate``-th row and column of a source (float32 DN/s), read row by row."""

    h = npy_shape(img.path)[0][0]
    verified(img.path, img.checksum)
    rows = [read_npy_rows(img.path, r, r + 1)[0, ::decimate] for r in range(0, h, decimate)]
    return np.stack(rows).astype(np.float32) * np.float32(img.scale)


def source_samples(img: SourceImage, geo: SourceGeometry, canvas: Canvas, decimate: int) -> tuple[np.ndarray,
                                                                                                   np.ndarray]:
    """Flat coarse-grid indices covered by a source and its bilinear values there ``(n, 3)``."""
    rect = _cone_rect(geo, canvas)
    sm = source_map(geo, canvas, rect, margin_px=0.0)
    if sm is None:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    w = feather_weight(sm.u, sm.v, geo.model.width, geo.model.height)
    ii, jj = np.nonzero(w > 0)
    small = read_decimated(img, decimate)
    scale = np.float32(1.0 / decimate)
    vals = remap(small, (sm.u[ii, jj] * scale)[None], (sm.v[ii, jj] * scale)[None], "linear")[0]
    rows = ii + sm.row0
    cols = np.mod(jj + sm.col0, canvas.width)
    ok = np.isfinite(vals).all(axis=1) & (rows >= 0) & (rows < canvas.height)
    return (rows[ok] * canvas.width + cols[ok]).astype(np.int64), vals[ok]


def _cone_rect(geo: SourceGeometry, canvas: Canvas) -> Rect:
    """A canvas rectangle holding the source's bounding cone (whole rows around a pole)."""

    lon, lat = (float(x) for x in ray_to_lonlat(geo.axis))
    r = np.degrees(geo.radius_rad)
    lat0, lat1 = max(-90.0, lat - r), min(90.0, lat + r)
    _, row_top = lonlat_to_equirect_pixel(0.0, lat1, canvas.width, canvas.height)
    _, row_bottom = lonlat_to_equirect_pixel(0.0, lat0, canvas.width, canvas.height)
    row0, row1 = int(np.floor(row_top)), int(np.ceil(row_bottom)) + 1
    if lat1 >= 89.999 or lat0 <= -89.999 or r >= 89.0:
        return Rect(max(0, row0), min(canvas.height, row1), 0, canvas.width)
    half = r / max(np.cos(np.radians(max(abs(lat0), abs(lat1)))), 1e-6)
    if half >= 180.0:
        return Rect(max(0, row0), min(canvas.height, row1), 0, canvas.width)
    col_c, _ = lonlat_to_equirect_pixel(lon, 0.0, canvas.width, canvas.height)
    half_px = half * canvas.width / 360.0
    return Rect(max(0, row0), min(canvas.height, row1), int(np.floor(col_c - half_px)),
                int(np.ceil(col_c + half_px)) + 1)


def overlap_statistics(samples: list[tuple[np.ndarray, np.ndarray]],
                       pairs: list[tuple[int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``N`` (n, n) shared pixel counts and ``I`` (n, n, 3) with ``I[i, j]`` = mean of ``i`` where it meets ``j``.

    ``pairs`` (``i < j``) limits the pairs looked at (default: all).
    """
    n = len(samples)
    counts = np.zeros((n, n))
    means = np.zeros((n, n, 3))
    if pairs is None:
        pairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    for i, j in pairs:
        (idx_i, val_i), (idx_j, val_j) = samples[i], samples[j]
        common, ai, aj = np.intersect1d(idx_i, idx_j, assume_unique=True, return_indices=True)
        if common.size == 0:
            continue
        counts[i, j] = counts[j, i] = common.size
        means[i, j] = val_i[ai].mean(axis=0)
        means[j, i] = val_j[aj].mean(axis=0)
    return counts, means


def solve_gains(counts: np.ndarray, means: np.ndarray, sigma_n: float = SIGMA_N,
                sigma_g: float = SIGMA_G) -> np.ndarray:
    """Gains ``(n, bands)`` minimising Brown & Lowe's Eq. (29) (module docstring) for every band."""
    n, _, bands = means.shape
    gains = np.ones((n, bands))
    for b in range(bands):
        ib = means[..., b]
        scale = ib[counts > 0].mean() if (counts > 0).any() else 0.0
        if not scale > 0:
            continue
        ib = ib / scale
        a = -2.0 * counts * ib * ib.T / sigma_n ** 2
        np.fill_diagonal(a, 0.0)
        diag = (counts * (2.0 * ib ** 2 / sigma_n ** 2 + 1.0 / sigma_g ** 2)).sum(axis=1)
        a[np.diag_indices(n)] = diag
        rhs = counts.sum(axis=1) / sigma_g ** 2
        alone = diag == 0
        a[alone, alone] = 1.0
        rhs[alone] = 1.0
        gains[:, b] = np.linalg.solve(a, rhs)
    return gains


def estimate_gains(merged: MergedDirections, decimate: int = 8, width: int | None = None) -> np.ndarray:
    """Gains ``(n_sources, 3)`` in the order of :meth:`MergedDirections.sources`, per camera and band."""
    images = merged.sources()
    canvas_w = width or coarse_width(merged.cameras["A"].fx, decimate)
    canvas = Canvas(canvas_w, canvas_w // 2)
    gains = np.ones((len(images), 3), np.float32)
    for cam in merged.cameras:
        members = [k for k, s in enumerate(images) if s.camera == cam]
        if len(members) < 2:
            continue
        geos = [SourceGeometry.build(merged.cameras[cam], images[k].pan_deg, images[k].tilt_deg,
                                     images[k].offset_px) for k in members]
        samples = [source_samples(images[k], geo, canvas, decimate) for k, geo in zip(members, geos, strict=True)]
        axes = np.array([g.axis for g in geos])
        radii = np.array([g.radius_rad for g in geos])
        angle = np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))
        pairs = [(int(i), int(j)) for i, j in zip(*np.nonzero(angle <= radii[:, None] + radii[None, :]), strict=True)
                 if i < j]
        counts, means = overlap_statistics(samples, pairs)
        gains[members] = solve_gains(counts, means).astype(np.float32)
    return gains
