"""Where each output pixel lands on each source sensor: the engine's composed inverse map.

For output pixel ``(col, row)`` of a W × H equirectangular canvas the chain is (all in
:mod:`omnispectral.imaging.geometry`, the one geometry definition)

    ``equirect_pixel_to_lonlat`` → ``lonlat_to_ray`` → ``CameraModel.world_to_pixel(ray, pan, tilt)``
    (inverse head rotation, mounting, OpenCV lens with distortion) → ``+ (dx, dy)`` (camera B's
    registration offset).

The map is smooth (a composition of analytic functions) wherever the ray is in front of the
camera, including across the ±180° seam and the poles (rows beyond the canvas continue over the
pole).  It is evaluated exactly on nodes every ``step`` output pixels and interpolated with
Catmull–Rom splines in between (error O(step³)); the interpolation is checked against exact
evaluations at the cell centres and the step halved until the largest error is below
``tol_px`` (default 10⁻³ px), down to exact evaluation at every pixel.  Nodes whose ray has no
image (behind the camera, beyond the lens model's monotonic region) are never interpolated: the
pixels they influence are evaluated exactly.

Overlap tests use angular cones: each source image is bounded by a cone around the mean ray of its
border (radius = largest angle to a border ray), each tile by a cone around its centre ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnispectral.imaging.channels import finite_pixels
from omnispectral.imaging.geometry import CameraModel, equirect_pixel_to_lonlat, lonlat_to_ray
from omnispectral.mosaic.kernels import compiled_kernels

__all__ = ["MAP_STEP_PX", "MAP_TOL_PX", "Canvas", "Rect", "SourceGeometry", "SourceMap", "catmull_rom_weights",
           "exact_map", "interpolate_nodes", "rect_map", "source_map", "tile_cone"]

#: Node spacing (output pixels) of the first attempt.
MAP_STEP_PX = 8
#: Largest accepted interpolation error of the map, in source pixels.
MAP_TOL_PX = 1e-3
#: Samples per image edge for a source's bounding cone, per tile edge for a tile's.
_CONE_SAMPLES = 64


@dataclass(frozen=True)
class Canvas:
    """A W × H equirectangular output grid (conventions of :mod:`omnispectral.imaging.geometry`)."""

    width: int
    height: int

    def rays(self, rows, cols) -> np.ndarray:
        """World rays ``(len(rows), len(cols), 3)`` of pixel centres (rows/cols may lie beyond the canvas).

        Separable: longitude depends on the column only and latitude on the row only, so the
        trigonometry runs once per column and once per row, and the ray is
        ``(cos lat · (−sin lon), sin lat, cos lat · cos lon)`` from the two — the same values as
        :meth:`rays_at` per pixel, bit for bit.
        """
        cols = np.asarray(cols, dtype=np.float64).reshape(-1)
        rows = np.asarray(rows, dtype=np.float64).reshape(-1)
        lon, _ = equirect_pixel_to_lonlat(cols, np.zeros_like(cols), self.width, self.height)
        _, lat = equirect_pixel_to_lonlat(np.zeros_like(rows), rows, self.width, self.height)
        per_col = lonlat_to_ray(lon, np.zeros_like(lon))  # (-sin lon, 0, cos lon)
        per_row = lonlat_to_ray(np.zeros_like(lat), lat)  # (-0, sin lat, cos lat)
        out = np.empty((rows.size, cols.size, 3), np.float64)
        np.multiply(per_row[:, None, 2], per_col[None, :, 0], out=out[..., 0])
        out[..., 1] = per_row[:, None, 1]
        np.multiply(per_row[:, None, 2], per_col[None, :, 2], out=out[..., 2])
        return out

    def rays_at(self, row, col) -> np.ndarray:
        """World rays ``(..., 3)`` of the points ``(row, col)`` (element-wise)."""
        return lonlat_to_ray(*equirect_pixel_to_lonlat(col, row, self.width, self.height))


@dataclass(frozen=True)
class Rect:
    """Output pixels ``[row0, row1) × [col0, col1)`` (rows may extend beyond the canvas by a halo)."""

    row0: int
    row1: int
    col0: int
    col1: int

    @property
    def shape(self) -> tuple[int, int]:
        return self.row1 - self.row0, self.col1 - self.col0

    def grow(self, margin: int) -> Rect:
        return Rect(self.row0 - margin, self.row1 + margin, self.col0 - margin, self.col1 + margin)


@dataclass(frozen=True)
class SourceGeometry:
    """A source image's geometry: camera model, head position, registration offset, bounding cone."""

    model: CameraModel
    pan_deg: float
    tilt_deg: float
    offset_px: tuple[float, float]
    axis: np.ndarray
    radius_rad: float

    @classmethod
    def build(cls, model: CameraModel, pan_deg: float, tilt_deg: float,
              offset_px: tuple[float, float] = (0.0, 0.0), margin_px: float = 2.0) -> SourceGeometry:
        """Geometry with its bounding cone (image border grown by ``margin_px`` and by the offset)."""
        dx, dy = offset_px
        grow = margin_px
        border = _rect_border(-0.5 - grow, model.width - 0.5 + grow, -0.5 - grow, model.height - 0.5 + grow)
        rays, valid = model.pixel_to_world(border - np.array([dx, dy]), pan_deg, tilt_deg)
        centre, _ = model.pixel_to_world(np.array([[model.cx - dx, model.cy - dy]]), pan_deg, tilt_deg)
        rays = rays[valid]
        axis = rays.mean(axis=0) if rays.size else centre[0]
        axis = axis / np.linalg.norm(axis)
        if not valid.all():  # the image reaches beyond the lens model: only its valid part matters
            radius = np.pi
        else:
            step = np.max(np.arccos(np.clip(np.sum(rays[1:] * rays[:-1], axis=1), -1.0, 1.0)))
            radius = float(np.max(np.arccos(np.clip(rays @ axis, -1.0, 1.0))) + step)
        return cls(model, float(pan_deg), float(tilt_deg), (float(dx), float(dy)), axis, min(np.pi, radius))


def _rect_border(x0: float, x1: float, y0: float, y1: float, n: int = _CONE_SAMPLES) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n, endpoint=False)
    xs, ys = x0 + (x1 - x0) * t, y0 + (y1 - y0) * t
    top, right = np.stack([xs, np.full(n, y0)], 1), np.stack([np.full(n, x1), ys], 1)
    bottom, left = np.stack([x1 - (xs - x0), np.full(n, y1)], 1), np.stack([np.full(n, x0), y1 - (ys - y0)], 1)
    return np.concatenate([top, right, bottom, left])


def tile_cone(canvas: Canvas, rect: Rect) -> tuple[np.ndarray, float]:
    """Centre ray and angular radius of a cone holding every pixel of ``rect`` (π for very large tiles)."""
    h, w = rect.shape
    lon_span = w * 360.0 / canvas.width
    lat_span = h * 180.0 / canvas.height
    centre = canvas.rays([(rect.row0 + rect.row1 - 1) / 2.0], [(rect.col0 + rect.col1 - 1) / 2.0])[0, 0]
    if lon_span > 90.0 or lat_span > 90.0:
        return centre, np.pi
    border = _rect_border(rect.col0 - 0.5, rect.col1 - 0.5, rect.row0 - 0.5, rect.row1 - 0.5)
    rays = canvas.rays_at(border[:, 1], border[:, 0])
    angles = np.arccos(np.clip(rays @ centre, -1.0, 1.0))
    step = np.max(np.arccos(np.clip(np.sum(rays[1:] * rays[:-1], axis=1), -1.0, 1.0)))
    return centre, float(min(np.pi, angles.max() + step))


# ------------------------------------------------------------------------------------------ interpolation
def catmull_rom_weights(positions_px: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Catmull–Rom weights for pixel positions (≥ 0) between nodes at ``(j - 1) step``, ``j = 0, 1, …``.

    Returns ``(k, w)``: position ``x`` is ``Σ_j w[:, j] node[k + j]`` for ``j = 0 … 3``.
    """
    x = np.asarray(positions_px, dtype=np.float64)
    cell = np.floor(x / step)
    t = x / step - cell
    w = np.stack([((-t + 2.0) * t - 1.0) * t / 2.0, ((3.0 * t - 5.0) * t * t + 2.0) / 2.0,
                  ((-3.0 * t + 4.0) * t + 1.0) * t / 2.0, (t - 1.0) * t * t / 2.0], axis=1)
    return cell.astype(np.int64), w


def interpolate_nodes(nodes: np.ndarray, rows: tuple[np.ndarray, np.ndarray],
                      cols: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Separable Catmull–Rom interpolation of a node grid ``(n_r, n_c)`` at ``rows × cols`` (four taps each)."""
    kc, wc = cols
    kr, wr = rows
    kernels = compiled_kernels()
    if kernels is not None:  # one pass per axis, the same sums in the same order
        out = np.empty((kr.shape[0], kc.shape[0]), np.float64)
        kernels.catmull_rom(np.ascontiguousarray(nodes, np.float64), kr, np.ascontiguousarray(wr, np.float64), kc,
                            np.ascontiguousarray(wc, np.float64), out)
        return out
    t = sum(nodes[:, kc + j] * wc[None, :, j] for j in range(4))
    return sum(t[kr + j, :] * wr[:, j, None] for j in range(4))


def exact_map(source: SourceGeometry, canvas: Canvas, rows, cols) -> np.ndarray:
    """Exact sensor positions ``(len(rows), len(cols), 2)`` (offset included; NaN where the ray has no image)."""
    px, _ = source.model.world_to_pixel(canvas.rays(rows, cols), source.pan_deg, source.tilt_deg, margin_px=None)
    return px + np.asarray(source.offset_px)


@dataclass
class SourceMap:
    """Sensor positions of the output pixels ``[row0, row1) × [col0, col1)`` (absolute canvas coordinates)."""

    row0: int
    col0: int
    u: np.ndarray
    v: np.ndarray
    step: int
    max_error_px: float

    @property
    def rect(self) -> Rect:
        return Rect(self.row0, self.row0 + self.u.shape[0], self.col0, self.col0 + self.u.shape[1])


def source_map(source: SourceGeometry, canvas: Canvas, rect: Rect, margin_px: float = 4.0,
               step: int = MAP_STEP_PX, tol_px: float = MAP_TOL_PX) -> SourceMap | None:
    """The composed map of ``source`` on ``rect``, cut to the part that lands on the image (± ``margin_px``).

    Returns ``None`` if no pixel of ``rect`` lands on the image.  ``u``/``v`` are float32 with NaN
    where the ray has no image point.

    Parameters
    ----------
    source : SourceGeometry
        The source image: its camera model (lens with distortion, mounting), head pan and tilt (deg) and
        registration offset (source px).
    canvas : Canvas
        The equirectangular output grid.
    rect : Rect
        The output pixels to map (rows may extend beyond the canvas by a halo).
    margin_px : float
        Margin (source px) around the image within which output pixels are kept.
    step : int
        Node spacing (output px) of the first attempt; halved until the interpolation error is below
        ``tol_px`` (down to 1: exact evaluation at every pixel).
    tol_px : float
        Largest accepted interpolation error of the map (source px).

    Returns
    -------
    SourceMap or None
        The map cut to the part of ``rect`` that lands on the image: its first row and column (canvas
        coordinates), ``u``, ``v`` (float32 sensor positions in source px, offset included), the node
        step used and the largest interpolation error found (px; 0 when evaluated exactly).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.4, Eq. (4) (polar coordinates of a directional image; here composed
       with the lens model of Sec. 4.2 and the head direction, per output pixel), Sec. 4.5.
    .. [2] R. G. Keys, "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981
       (the Catmull–Rom weights between nodes: cubic convolution with ``a = -1/2``).
    """
    h, w = rect.shape
    while True:
        nodes = exact_map(source, canvas, rect.row0 + (np.arange((h - 1) // step + 4) - 1) * step,
                          rect.col0 + (np.arange((w - 1) // step + 4) - 1) * step)
        window = _window(nodes, source.model, margin_px, step, h, w)
        if window is None:
            return None
        if step == 1:
            r_lo, r_hi, c_lo, c_hi = window
            u, v = nodes[1 + r_lo:1 + r_hi, 1 + c_lo:1 + c_hi].transpose(2, 0, 1)
            return SourceMap(rect.row0 + r_lo, rect.col0 + c_lo, u.astype(np.float32), v.astype(np.float32), 1, 0.0)
        error = _check_error(source, canvas, rect, nodes, step, margin_px, window)
        if error <= tol_px:
            break
        step = max(1, step // 2)
    return _interpolated_map(source, canvas, rect, nodes, step, window, error)



def rect_map(source: SourceGeometry, canvas: Canvas, rect: Rect, margin_px: float = 2.0, step: int = MAP_STEP_PX,
             tol_px: float = MAP_TOL_PX) -> SourceMap:
    """The composed map of ``source`` on the whole of ``rect`` (not cut to where it lands, unlike :func:`source_map`).

    The same nodes, Catmull–Rom interpolation and error check as :func:`source_map`: within ``tol_px`` of
    :func:`exact_map` wherever the position lands on the image (± ``margin_px``); beyond it the positions
    are the interpolation's (off the image by more than the margin).  For a lookup in the source's own
    grid, e.g. camera A's parallax map under camera B's pixels: ~30x fewer exact projections.

    Parameters
    ----------
    source : SourceGeometry
        The source image's geometry.
    canvas : Canvas
        The equirectangular output grid.
    rect : Rect
        The output pixels to map.
    margin_px : float
        Margin (source px) around the image within which the error is checked.
    step : int
        Node spacing (output px) of the first attempt; halved until the error is below ``tol_px``.
    tol_px : float
        Largest accepted interpolation error (source px).

    Returns
    -------
    SourceMap
        The map of every pixel of ``rect`` (``u``, ``v`` float32, NaN where the ray has no image point).

    References
    ----------
    .. [1] R. G. Keys, "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981
       (the Catmull–Rom weights between nodes).
    """
    h, w = rect.shape
    window = (0, h, 0, w)
    while step > 1:
        nodes = exact_map(source, canvas, rect.row0 + (np.arange((h - 1) // step + 4) - 1) * step,
                          rect.col0 + (np.arange((w - 1) // step + 4) - 1) * step)
        error = _check_error(source, canvas, rect, nodes, step, margin_px, window)
        if error <= tol_px:
            return _interpolated_map(source, canvas, rect, nodes, step, window, error)
        step //= 2
    u, v = exact_map(source, canvas, np.arange(rect.row0, rect.row1), np.arange(rect.col0, rect.col1)
                     ).transpose(2, 0, 1)
    return SourceMap(rect.row0, rect.col0, u.astype(np.float32), v.astype(np.float32), 1, 0.0)


def _window(nodes: np.ndarray, model: CameraModel, margin_px: float, step: int, h: int,
            w: int) -> tuple[int, int, int, int] | None:
    """Pixel window ``(r_lo, r_hi, c_lo, c_hi)`` of the rect whose node cells can land on the image."""
    with np.errstate(invalid="ignore"):
        # (u, v) gap of neighbouring nodes: np.maximum of the two, not .max(axis=-1) (a reduction over a
        # 2-long last axis, 16 % of a small panorama's tiles)
        gaps = [np.maximum(*np.abs(np.diff(nodes, axis=a)).transpose(2, 0, 1)) for a in (0, 1)]
        cell_px = max((float(np.nanmax(g)) if np.isfinite(g).any() else 0.0) for g in gaps)
        inside = model.inside(nodes[..., 0], nodes[..., 1], margin_px + 1.5 * cell_px)
    if not inside.any():
        return None
    rr = np.flatnonzero(inside.any(axis=1))
    cc = np.flatnonzero(inside.any(axis=0))
    r_lo, r_hi = max(0, (rr[0] - 3) * step), min(h, (rr[-1] + 2) * step)
    c_lo, c_hi = max(0, (cc[0] - 3) * step), min(w, (cc[-1] + 2) * step)
    return None if r_lo >= r_hi or c_lo >= c_hi else (r_lo, r_hi, c_lo, c_hi)


def _interpolated_map(source: SourceGeometry, canvas: Canvas, rect: Rect, nodes: np.ndarray, step: int,
                      window: tuple[int, int, int, int], error: float) -> SourceMap:
    r_lo, r_hi, c_lo, c_hi = window
    rows = catmull_rom_weights(np.arange(r_lo, r_hi), step)
    cols = catmull_rom_weights(np.arange(c_lo, c_hi), step)
    bad = ~np.isfinite(nodes[..., 0])
    filled = np.where(bad[..., None], 0.0, nodes)
    u = interpolate_nodes(filled[..., 0], rows, cols)
    v = interpolate_nodes(filled[..., 1], rows, cols)
    if bad.any():
        taint = interpolate_nodes(bad.astype(np.float64), (rows[0], np.abs(rows[1])), (cols[0], np.abs(cols[1])))
        ti, tj = np.nonzero(taint > 0)
        if ti.size:
            rays = lonlat_to_ray(*equirect_pixel_to_lonlat(tj + rect.col0 + c_lo, ti + rect.row0 + r_lo,
                                                          canvas.width, canvas.height))
            exact = source.model.world_to_pixel(rays, source.pan_deg, source.tilt_deg, margin_px=None)[0]
            u[ti, tj] = exact[:, 0] + source.offset_px[0]
            v[ti, tj] = exact[:, 1] + source.offset_px[1]
    return SourceMap(rect.row0 + r_lo, rect.col0 + c_lo, u.astype(np.float32), v.astype(np.float32), step, error)


def _check_error(source: SourceGeometry, canvas: Canvas, rect: Rect, nodes: np.ndarray, step: int,
                 margin_px: float, window: tuple[int, int, int, int]) -> float:
    """Largest |interpolated − exact| (px) at cell centres in ``window`` that land on the image (± margin).

    Points whose interpolation touches a node without image are skipped: those pixels are computed exactly.
    """
    r_lo, r_hi, c_lo, c_hi = window
    h, w = rect.shape
    pr = np.arange(r_lo, r_hi, step) + step / 2.0
    pc = np.arange(c_lo, c_hi, step) + step / 2.0
    pr, pc = pr[pr <= h - 1], pc[pc <= w - 1]
    if pr.size == 0 or pc.size == 0:
        return 0.0
    exact = exact_map(source, canvas, rect.row0 + pr, rect.col0 + pc)
    with np.errstate(invalid="ignore"):
        relevant = source.model.inside(exact[..., 0], exact[..., 1], margin_px)
        rows, cols = catmull_rom_weights(pr, step), catmull_rom_weights(pc, step)
        approx = np.stack([interpolate_nodes(nodes[..., k], rows, cols) for k in range(2)], axis=-1)
        err = np.hypot(*(approx - exact).transpose(2, 0, 1))
    err = err[relevant & finite_pixels(approx)]
    return float(err.max()) if err.size else 0.0
