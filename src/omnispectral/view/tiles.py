"""Display images of a product made on demand: windows of the equirectangular panorama, tone mapped, encoded.

A viewer asks for equirectangular tiles on a power-of-two grid (Photo Sphere Viewer's tiled adapter:
level width ``W_v = cols × tile``, height ``W_v / 2``).  A tile is a window ``[u0, u1) × [v0, v1)`` of the
panorama in fractions of its width and height; :meth:`SlotRenderer.render` reads only that window from the
coarsest Zarr level that is at least as fine as the request (the pyramid of ``mosaic.store``), computes the
display quantity on it and resamples it bilinearly onto the output pixel centres (OpenCV ``remap``).

Display modes (:data:`MODES`):

- ``colour``: linear sRGB-primaries RGB of the estimated spectra under the light that was captured, through
  the single 6 × 3 map the Wiener mixture becomes for the panorama's mean component weights
  (:func:`omnispectral.product.spectra.linear_srgb_map`), exposed by ``2**ev`` relative to the automatic
  exposure (the 99th luminance percentile of the coarsest level at 1) and tone mapped with the Reinhard
  (2002) global operator and the sRGB curve (:func:`omnispectral.product.exports.reinhard_srgb8`);
- ``band``: one of the six bands in grey, exposed and tone mapped the same way;
- ``uncertainty``: the relative posterior standard deviation of the spectrum (RMS of σ over RMS of the
  estimate, paper Eq. (7) posterior), shown with the viridis colour map from 0 to ``uncertainty_max``;
  it is computed on a grid 4 × coarser than the window and interpolated (the posterior solves 6 × 6
  systems per pixel and per light-source component) and does not depend on the exposure;
- ``registration``: camera B's registration confidence (viridis, 0 to 1) from the panorama's quality
  layer (``panorama.zarr/quality``, written when B was registered with per-pixel parallax), occluded
  pixels in red (B's bands there come from a view hidden by a nearer surface), pixels whose B bands were
  predicted from A's (B saw nothing there, :mod:`omnispectral.mosaic.predict`) in orange, pixels where an
  edge mixes B's two surfaces in A's share (:mod:`omnispectral.mosaic.unmix`) in light blue and the
  recovered sun in magenta; level 0 sampled at the nearest pixel.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import lonlat_to_ray
from omnispectral.product.exports import reinhard_srgb8
from omnispectral.product.layout import open_product
from omnispectral.product.spectra import linear_srgb_map

__all__ = ["AUTO_PERCENTILE", "MODES", "OCCLUDED_RGB", "PREDICTED_RGB", "SUN_RGB", "UNCERTAINTY_STEP", "Display",
           "SlotRenderer", "TileCache", "encode_png", "luminance", "relative_uncertainty", "viewer_levels",
           "viridis_lut"]

MODES = ("colour", "band", "uncertainty", "registration")
#: Colour of occluded pixels in the ``registration`` mode.
OCCLUDED_RGB = (230, 30, 30)
#: The recovered sun's pixels in the registration display (off the viridis scale of the confidence).
SUN_RGB = (255, 0, 255)
#: Pixels whose camera-B bands were predicted from camera A's (B saw nothing there), registration display.
PREDICTED_RGB = (255, 160, 0)
#: Pixels whose camera-B bands mix B's two surfaces in A's share at an edge, registration display.
UNMIXED_RGB = (90, 200, 255)
#: Automatic exposure puts this percentile of the luminance (or band value) at 1 before the tone curve.
AUTO_PERCENTILE = 99.0
#: Subsampling of the window on which the posterior uncertainty is computed.
UNCERTAINTY_STEP = 4


@dataclass(frozen=True)
class Display:
    """What a tile shows: ``mode`` (one of :data:`MODES`), ``band`` index for ``band``, exposure ``ev`` (stops)."""

    mode: str = "colour"
    band: int = 0
    ev: float = 0.0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ConfigurationError(f"display mode {self.mode!r} is not one of {', '.join(MODES)}")
        if not (math.isfinite(self.ev) and -40.0 <= self.ev <= 40.0):
            raise ConfigurationError(f"exposure {self.ev} EV is outside -40..40")


def viewer_levels(width_px: int, tile_px: int = 256) -> list[dict]:
    """Photo Sphere Viewer tile levels for a panorama ``width_px`` wide: ``cols = 2, 4, …`` (powers of two,
    ``rows = cols / 2``, square tiles of ``tile_px``) up to the first level at least as wide as the panorama."""
    levels, cols = [], 2
    while True:
        levels.append({"width": cols * tile_px, "cols": cols, "rows": cols // 2})
        if cols * tile_px >= width_px:
            return levels
        cols *= 2


def viridis_lut() -> np.ndarray:
    """256 × 3 uint8 RGB of matplotlib's viridis colour map."""
    from matplotlib import colormaps  # lazy: matplotlib only for the colour map table, built once

    return np.round(colormaps["viridis"](np.linspace(0, 1, 256))[:, :3] * 255).astype(np.uint8)


def relative_uncertainty(bands: np.ndarray, estimator) -> np.ndarray:
    """RMS posterior std over RMS estimate per pixel of ``bands`` ``(..., 6)`` (NaN where bands are not finite)."""
    flat = bands.reshape(-1, bands.shape[-1])
    ok = np.isfinite(flat).all(axis=1) & (flat.sum(axis=1) > 0)
    out = np.full(flat.shape[0], np.nan, np.float32)
    if ok.any():
        est = estimator.estimate(flat[ok])
        std = estimator.posterior_std(flat[ok])
        out[ok] = np.sqrt(np.mean(std**2, axis=1)) / np.maximum(np.sqrt(np.mean(est**2, axis=1)), 1e-30)
    return out.reshape(bands.shape[:-1])


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB."""
    return rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)


class SlotRenderer:
    """Display images of one product (one time slot): windows of its panorama in any mode, at any size."""

    def __init__(self, product: str | Path):
        self.path = Path(product)
        self.index, self.store, self.estimator = open_product(product)
        self.shapes = list(self.store.shapes)
        self.bands = list(self.index["bands"])
        self._arrays = [self.store.array(k) for k in range(len(self.shapes))]
        coarse = self.read(len(self.shapes) - 1)
        self.colour_matrix, self.colour_offset = linear_srgb_map(coarse, self.estimator)
        self._coarse = coarse
        self.reference = {"colour": _percentile_positive(luminance(self._colour(coarse)))}
        for k in range(len(self.bands)):
            self.reference[f"band{k}"] = _percentile_positive(coarse[..., k])
        u = relative_uncertainty(coarse[::2, ::2], self.estimator)
        u = u[np.isfinite(u)]
        self.uncertainty_max = float(np.ceil(np.percentile(u, 99) * 20) / 20) if u.size else 1.0
        self._lut = viridis_lut()
        self.has_quality = self.store.has_quality()

    # ------------------------------------------------------------------ reading
    def read(self, level: int, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """Bands of a window of pyramid ``level`` (float32, DN/s, NaN where uncovered)."""
        return np.asarray(self._arrays[level][rows, cols, :], np.float32)

    def level_for(self, source_width_px: float) -> int:
        """The coarsest pyramid level at least ``source_width_px`` wide (level 0 if none is)."""
        fits = [k for k, (_, w) in enumerate(self.shapes) if w >= source_width_px * 0.999]
        return max(fits) if fits else 0

    # ------------------------------------------------------------------ display quantities
    def _colour(self, bands: np.ndarray) -> np.ndarray:
        return bands @ self.colour_matrix + self.colour_offset

    def _reference(self, display: Display) -> float:
        return self.reference["colour" if display.mode == "colour" else f"band{display.band}"]

    def _quantity(self, bands: np.ndarray, display: Display) -> np.ndarray:
        """The float image that is resampled: exposed RGB / band (…, 1) or relative uncertainty (…, 1)."""
        if display.mode == "uncertainty":
            s = UNCERTAINTY_STEP
            small = relative_uncertainty(bands[::s, ::s], self.estimator)
            return cv2.resize(small, (bands.shape[1], bands.shape[0]), interpolation=cv2.INTER_LINEAR)[..., None]
        if display.mode == "band" and not 0 <= display.band < len(self.bands):
            raise ConfigurationError(f"band {display.band} does not exist (0-{len(self.bands) - 1})")
        gain = np.float32(2.0**display.ev / self._reference(display))
        if display.mode == "colour":
            return self._colour(bands) * gain
        return bands[..., display.band:display.band + 1] * gain

    def _quality_window(self, level: int, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """The quality layer (confidence, occluded, sun, b_predicted, b_unmixed) under a window of ``level``, nearest
        level-0 pixel."""
        if not self.has_quality:
            raise ConfigurationError("this product has no registration-quality layer (camera B was registered "
                                     "with one offset per direction: process --registration paper)")
        f = 2**level
        h0, w0 = self.shapes[0]
        rows = np.clip((np.arange(r0, r1) + 0.5) * f, 0, h0 - 1).astype(int)
        cols = np.clip((np.arange(c0, c1) + 0.5) * f, 0, w0 - 1).astype(int)
        q = self.store.read_quality(slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
        return q[(rows - rows[0])[:, None], (cols - cols[0])[None, :]]

    def _to_rgb8(self, quantity: np.ndarray, display: Display) -> np.ndarray:
        if display.mode == "registration":
            conf, occ = quantity[..., 0], quantity[..., 1]
            rgb = self._lut[np.clip(np.nan_to_num(conf, nan=0.0) * 255, 0, 255).astype(np.uint8)]
            rgb[np.nan_to_num(occ) > 0.5] = OCCLUDED_RGB
            rgb[~np.isfinite(conf)] = 0
            if quantity.shape[-1] > 4:  # B's two surfaces mixed in A's share at an edge (mosaic.unmix)
                rgb[np.nan_to_num(quantity[..., 4]) > 0] = UNMIXED_RGB
            if quantity.shape[-1] > 3:  # B's bands predicted from A's (mosaic.predict)
                rgb[np.nan_to_num(quantity[..., 3]) > 0] = PREDICTED_RGB
            if quantity.shape[-1] > 2:  # the recovered sun's pixels (camera B's confidence there is moot)
                rgb[np.nan_to_num(quantity[..., 2]) > 0.5] = SUN_RGB
            return rgb
        if display.mode == "uncertainty":
            q = quantity[..., 0]
            idx = np.clip(np.nan_to_num(q / self.uncertainty_max, nan=0.0) * 255, 0, 255).astype(np.uint8)
            rgb = self._lut[idx]
            rgb[~np.isfinite(q)] = 0
            return rgb
        out = reinhard_srgb8(quantity)
        return np.repeat(out, 3, axis=-1) if out.shape[-1] == 1 else out

    # ------------------------------------------------------------------ windows
    def render(self, display: Display, u0: float, u1: float, v0: float, v1: float, out_w: int, out_h: int
               ) -> np.ndarray:
        """RGB uint8 ``(out_h, out_w, 3)`` of the panorama window ``u ∈ [u0, u1)``, ``v ∈ [v0, v1)`` (fractions of
        width from longitude −180° and of height from latitude +90°), bilinear from the level that fits."""
        if not (0 <= u0 < u1 <= 1 and 0 <= v0 < v1 <= 1 and 0 < out_w <= 4096 and 0 < out_h <= 4096):
            raise ConfigurationError(f"window u {u0}-{u1}, v {v0}-{v1} at {out_w}x{out_h} px is not a window")
        level = self.level_for(out_w / (u1 - u0))
        h, w = self.shapes[level]
        xs = (u0 + (np.arange(out_w) + 0.5) / out_w * (u1 - u0)) * w - 0.5
        ys = (v0 + (np.arange(out_h) + 0.5) / out_h * (v1 - v0)) * h - 0.5
        c0, c1 = max(0, int(np.floor(xs[0])) - 1), min(w, int(np.ceil(xs[-1])) + 2)
        r0, r1 = max(0, int(np.floor(ys[0])) - 1), min(h, int(np.ceil(ys[-1])) + 2)
        if display.mode == "registration":
            quantity = np.ascontiguousarray(self._quality_window(level, r0, r1, c0, c1), np.float32)
        else:
            quantity = np.ascontiguousarray(self._quantity(self.read(level, slice(r0, r1), slice(c0, c1)), display))
        map_x = np.broadcast_to((xs - c0).astype(np.float32)[None, :], (out_h, out_w))
        map_y = np.broadcast_to((ys - r0).astype(np.float32)[:, None], (out_h, out_w))
        interp = cv2.INTER_NEAREST if display.mode == "registration" else cv2.INTER_LINEAR
        planes = [cv2.remap(quantity[..., i], np.ascontiguousarray(map_x), np.ascontiguousarray(map_y),
                            interp, borderMode=cv2.BORDER_REPLICATE) for i in range(quantity.shape[-1])]
        return self._to_rgb8(np.stack(planes, axis=-1), display)

    def render_tile(self, display: Display, level: dict, col: int, row: int) -> np.ndarray:
        """Tile ``(col, row)`` of a :func:`viewer_levels` level."""
        cols, rows = level["cols"], level["rows"]
        if not (0 <= col < cols and 0 <= row < rows):
            raise ConfigurationError(f"tile ({col}, {row}) is outside the {cols}x{rows} grid of this level")
        size_w, size_h = level["width"] // cols, level["width"] // 2 // rows
        return self.render(display, col / cols, (col + 1) / cols, row / rows, (row + 1) / rows, size_w, size_h)

    def auto_ev(self, display: Display, lon_deg: float, lat_deg: float, fov_deg: float) -> float:
        """Exposure (stops, relative to the automatic one) that puts the 99th percentile of what is within
        ``fov_deg / 2`` of the direction ``(lon, lat)`` at 1, on the coarsest level."""
        if display.mode in ("uncertainty", "registration"):
            return 0.0
        h, w = self._coarse.shape[:2]
        lon = (np.arange(w) + 0.5) / w * 360 - 180
        lat = 90 - (np.arange(h) + 0.5) / h * 180
        rays = lonlat_to_ray(*np.meshgrid(lon, lat))
        centre = lonlat_to_ray(np.asarray(lon_deg, float), np.asarray(lat_deg, float))
        inside = rays @ centre >= np.cos(np.radians(np.clip(fov_deg, 1, 180) / 2))
        sample = self._coarse[inside]
        values = luminance(self._colour(sample)) if display.mode == "colour" else sample[:, display.band]
        values = values[np.isfinite(values) & (values > 0)]
        if values.size == 0:
            return 0.0
        return float(np.log2(self._reference(display) / np.percentile(values, AUTO_PERCENTILE)))


def _percentile_positive(values: np.ndarray) -> float:
    v = values[np.isfinite(values) & (values > 0)]
    return float(np.percentile(v, AUTO_PERCENTILE)) if v.size else 1.0


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image (fast zlib level 1)."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


class TileCache:
    """Thread-safe LRU of encoded images, bounded by the total number of bytes it holds."""

    def __init__(self, max_bytes: int = 64 * 2**20):
        self.max_bytes = int(max_bytes)
        self.n_bytes = 0
        self.hits = 0
        self.misses = 0
        self._items: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key) -> bytes | None:
        with self._lock:
            value = self._items.get(key)
            if value is None:
                self.misses += 1
                return None
            self._items.move_to_end(key)
            self.hits += 1
            return value

    def put(self, key, value: bytes) -> None:
        if len(value) > self.max_bytes:
            return
        with self._lock:
            old = self._items.pop(key, None)
            if old is not None:
                self.n_bytes -= len(old)
            self._items[key] = value
            self.n_bytes += len(value)
            while self.n_bytes > self.max_bytes:
                _, dropped = self._items.popitem(last=False)
                self.n_bytes -= len(dropped)

    def __len__(self) -> int:
        return len(self._items)
