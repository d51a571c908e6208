"""Noise-free simulated captures of a panorama: merged directions whose ground truth is the panorama itself.

For each direction and camera, every sensor pixel is unprojected through the camera model
(:meth:`~omnispectral.imaging.geometry.CameraModel.unproject`, camera B's registration offset
subtracted first), turned into a world ray for the head's pan/tilt, and looked up in the
equirectangular panorama (cubic convolution at the exact position, wrapping around the ±180° seam
and continuing over the poles).  Used by the tests and benchmarks of the mosaic engine: stitching
these images back must give the panorama.

Six bands from an RGB panorama: camera A sees ``(R, G, B)``, camera B ``(G, B, R)``
(:func:`six_band_panorama`), so every band is a real image and A and B differ.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnispectral.imaging.geometry import CameraModel, lonlat_to_equirect_pixel, ray_to_lonlat
from omnispectral.mosaic.interp import remap
from omnispectral.mosaic.sources import CAMERA_BANDS, MergedDirections, MergedDirectionsWriter

__all__ = ["lookup", "pad_over_poles", "render_scene", "render_source", "six_band_panorama", "write_synthetic_merged"]

#: Rows added beyond each pole and columns beyond the seam before looking up, so the kernel sees real pixels.
_PAD = 4


def six_band_panorama(rgb: np.ndarray) -> np.ndarray:
    """``(H, W, 6)`` float32: bands A = ``(R, G, B)``, bands B = ``(G, B, R)``."""
    rgb = np.asarray(rgb, dtype=np.float32)
    return np.concatenate([rgb, rgb[..., [1, 2, 0]]], axis=-1)


def pad_over_poles(panorama: np.ndarray, pad: int = _PAD) -> np.ndarray:
    """Equirect image with ``pad`` rows continued over each pole (shifted half a turn) and columns wrapped."""
    h, w = panorama.shape[:2]
    half = np.roll(panorama, w // 2, axis=1)
    top = half[:pad][::-1]
    bottom = half[h - pad:][::-1]
    tall = np.concatenate([top, panorama, bottom], axis=0)
    return np.concatenate([tall[:, w - pad:], tall, tall[:, :pad]], axis=1)


def lookup(panorama_padded: np.ndarray, rays: np.ndarray, width: int, height: int, interp: str = "cubic") -> np.ndarray:
    """Values of a padded panorama (:func:`pad_over_poles`) along world rays ``(..., 3)``."""
    lon, lat = ray_to_lonlat(rays)
    col, row = lonlat_to_equirect_pixel(lon, lat, width, height)
    u = (col + _PAD).astype(np.float32)
    v = (row + _PAD).astype(np.float32)
    parts = [remap(panorama_padded[..., c:c + 3], u, v, interp) for c in range(0, panorama_padded.shape[2], 3)]
    return np.concatenate(parts, axis=-1)


def render_source(panorama_padded: np.ndarray, width: int, height: int, model: CameraModel, camera: str,
                  pan_deg: float, tilt_deg: float, offset_px: tuple[float, float] = (0.0, 0.0),
                  interp: str = "cubic") -> np.ndarray:
    """``(H, W, 3)`` image camera ``camera`` records at ``(pan, tilt)`` (bands of that camera), clipped at 0."""
    v, u = np.mgrid[0:model.height, 0:model.width].astype(np.float64)
    pix = np.stack([u - offset_px[0], v - offset_px[1]], axis=-1)
    rays, valid = model.pixel_to_world(pix, pan_deg, tilt_deg)
    bands = CAMERA_BANDS[camera]
    out = lookup(panorama_padded[..., bands[0]:bands[-1] + 1], np.nan_to_num(rays), width, height, interp)
    out[~valid] = np.nan
    return np.maximum(out, 0.0)


def render_scene(scene, model: CameraModel, camera: str, pan_deg: float, tilt_deg: float,
                 offset_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``(H, W, 3)`` image of an analytic scene ``scene(rays (..., 3)) -> (..., 6)`` (exact, no interpolation)."""
    v, u = np.mgrid[0:model.height, 0:model.width].astype(np.float64)
    rays, valid = model.pixel_to_world(np.stack([u - offset_px[0], v - offset_px[1]], axis=-1), pan_deg, tilt_deg)
    bands = list(CAMERA_BANDS[camera])
    out = np.asarray(scene(np.nan_to_num(rays)), np.float32)[..., bands]
    out[~valid] = np.nan
    return out


def write_synthetic_merged(path: str | Path, panorama6, cameras: dict[str, CameraModel],
                           directions: list[tuple[float, float]], offset_b_px: tuple[float, float] = (0.0, 0.0),
                           dtype: str = "float32", interp: str = "cubic", rig_name: str = "",
                           rig_toml: str = "", gains: np.ndarray | None = None,
                           system: dict | None = None) -> MergedDirections:
    """Merged directions of ``panorama6`` seen from ``directions`` ``[(pan_deg, tilt_deg), …]``.

    ``panorama6`` is an (H, W, 6) equirectangular image (looked up with ``interp``) or an analytic
    scene, a callable ``rays (..., 3) -> (..., 6)`` (evaluated exactly).  ``gains`` (n_directions, 6),
    if given, multiplies each direction's bands (a simulated exposure drift).  ``system``: the six bands'
    sensitivities to record (:meth:`~omnispectral.spectral.system.MultibandSystem.to_dict`), if any.
    """
    if callable(panorama6):
        padded, h, w = None, 0, 0
    else:
        h, w = panorama6.shape[:2]
        padded = pad_over_poles(np.asarray(panorama6, np.float32))
    plan = [{"index": k, "pan_deg": p, "tilt_deg": t} for k, (p, t) in enumerate(directions)]
    writer = MergedDirectionsWriter.create(path, cameras, plan, rig_name=rig_name, rig_toml=rig_toml, dtype=dtype,
                                           session={"synthetic": "rendered from a panorama"}, system=system)
    for k, (pan, tilt) in enumerate(directions):
        if k in writer.done():
            continue
        images = {}
        for cam in ("A", "B"):
            offset = offset_b_px if cam == "B" else (0.0, 0.0)
            img = render_scene(panorama6, cameras[cam], cam, pan, tilt, offset) if padded is None else \
                render_source(padded, w, h, cameras[cam], cam, pan, tilt, offset, interp)
            if gains is not None:
                img *= np.asarray(gains[k], np.float32)[list(CAMERA_BANDS[cam])]
            images[cam] = img
        writer.add(k, pan, tilt, images, {"B": offset_b_px})
    return MergedDirections.open(path)
