"""Geometry of the camera pair: where camera B sees the content of camera A's pixels, through the rig model.

The paper's rig (Hirai et al. 2018, Sec. 3, Fig. 2) has two cameras side by side on the rotating head;
camera A defines the optical axis and is the reference of the registration (Sec. 4.3).  Here the relation
between the cameras goes through their models (:class:`~omnispectral.imaging.geometry.CameraModel`): A's
pixel ``p`` has the ray ``r_A(p)`` (world frame, head at pan = tilt = 0), and content on that ray at
inverse depth ``w`` (1/m; 0 = infinity) is seen by B at

.. math:: q = \\pi_B\\big(R_B^\\top\\,(r_A(p) - w\\,c)\\big),

``c`` B's optical centre relative to A's (the rig file's baseline, metres, :func:`baseline_m`) and ``π_B``
B's projection with its mounting (:func:`predict_b_px`).  Depth moves ``q`` along the epipolar direction
``g = ∂q/∂w`` only (:func:`epipolar_direction`, :func:`cached_epipolar_field`).  For points at infinity
(``w = 0``) both cameras turn with the head, so the A → B pixel map does not depend on the head's pan and
tilt: it is computed once per pair of models (:func:`b_onto_a_maps`, :func:`cached_maps`) and B's image
is resampled onto A's grid with it (:func:`warp_b_onto_a`, one ``cv2.remap``, linear).  The local
Jacobian of that map (:func:`offset_jacobian`) carries a shift measured in A's pixels to B's sensor.

Calibrations change B's mounting by a small rotation ``δ`` (yaw, pitch, roll in degrees) on top of the rig
file's misalignment (:func:`adjusted_model`).
"""

from __future__ import annotations

import json
import threading
from dataclasses import replace

import cv2
import numpy as np

from omnispectral.imaging.geometry import CameraModel
from omnispectral.imaging.parallax import epipolar_field

__all__ = ["adjusted_model", "b_onto_a_maps", "baseline_m", "cached_epipolar_field", "cached_maps",
           "epipolar_direction", "offset_jacobian", "predict_b_px", "warp_b_onto_a"]


def baseline_m(model_b: CameraModel) -> np.ndarray:
    """B's optical centre relative to A's in the world frame at pan = tilt = 0.

    Parameters
    ----------
    model_b
        Camera B's model.

    Returns
    -------
    numpy.ndarray
        ``(3,)`` the baseline ``c`` in metres.
    """
    return model_b.camera_center_mm(0.0, 0.0) / 1000.0


def predict_b_px(model_a: CameraModel, model_b: CameraModel, a_px: np.ndarray, inv_depth_per_m) -> np.ndarray:
    """Where B sees the content of A's pixels at inverse depth ``w`` (module docstring's equation).

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.
    a_px
        ``(n, 2)`` A's pixel positions ``(x, y)``.
    inv_depth_per_m
        Inverse depth ``w`` of the content (1/m; 0 = infinity), a scalar or one per pixel.

    Returns
    -------
    numpy.ndarray
        ``(n, 2)`` B's pixel positions ``(x, y)``.
    """
    rays, _ = model_a.pixel_to_world(a_px, 0.0, 0.0)
    w = np.broadcast_to(np.asarray(inv_depth_per_m, np.float64), rays.shape[:-1])
    px, _ = model_b.world_to_pixel(rays - w[..., None] * baseline_m(model_b), 0.0, 0.0, margin_px=None)
    return px


def adjusted_model(model_b: CameraModel, delta_deg) -> CameraModel:
    """Camera B with a rotation change added to its mounting's misalignment.

    Parameters
    ----------
    model_b
        Camera B's model (the rig file's).
    delta_deg
        ``(yaw, pitch, roll)`` change in degrees.

    Returns
    -------
    CameraModel
        Camera B's model with the changed mounting (lens unchanged).
    """
    return replace(model_b, mounting=model_b.mounting.with_misalignment_change(delta_deg))


def epipolar_direction(model_a: CameraModel, model_b: CameraModel) -> np.ndarray:
    """Unit vector along which depth moves B's image at the centre of A's sensor (the epipolar line there).

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.

    Returns
    -------
    numpy.ndarray
        ``(2,)`` unit vector ``ĝ`` in B's pixels.
    """
    centre = np.array([[(model_a.width - 1) / 2.0, (model_a.height - 1) / 2.0]])
    g = (predict_b_px(model_a, model_b, centre, 0.01) - predict_b_px(model_a, model_b, centre, 0.0))[0]
    return g / max(float(np.linalg.norm(g)), 1e-12)


def b_onto_a_maps(model_a: CameraModel, model_b: CameraModel, pan_deg: float = 0.0, tilt_deg: float = 0.0,
                  step: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """For each of A's pixels (every ``step``), where the same ray at infinity lands on B's sensor.

    Both cameras turn with the head, so for points at infinity the map does not depend on the head's
    pan and tilt (the head rotation cancels): compute it once per rig (:func:`cached_maps`).

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.
    pan_deg, tilt_deg
        The head's direction (degrees).
    step
        Sampling of A's grid (px).

    Returns
    -------
    tuple of numpy.ndarray
        ``(map_x_px, map_y_px)``, float32 on A's (sampled) grid: B's sensor position of each of A's pixels;
        ``-1e6`` where either camera has no ray.
    """
    v, u = np.mgrid[0:model_a.height:step, 0:model_a.width:step]
    rays, ok = model_a.pixel_to_world(np.stack([u, v], axis=-1).astype(np.float64), pan_deg, tilt_deg)
    px, ok_b = model_b.world_to_pixel(np.nan_to_num(rays), pan_deg, tilt_deg, margin_px=None)
    px = np.where((ok & ok_b)[..., None], px, -1e6)
    return px[..., 0].astype(np.float32), px[..., 1].astype(np.float32)


_MAPS_CACHE: dict = {}
_CACHE_LOCK = threading.Lock()


def _computed_once(cache: dict, model_a: CameraModel, model_b: CameraModel, compute):
    """``cache``'s value for this pair of models, computed by ``compute()`` if it holds another pair's; under a
    lock, so that the registration's threads, which all ask at once, compute it once (one pair kept)."""
    key = json.dumps([model_a.to_dict(), model_b.to_dict()], sort_keys=True)
    with _CACHE_LOCK:
        value = cache.get(key)
        if value is None:
            value = compute()
            cache.clear()
            cache[key] = value
    return value


def cached_maps(model_a: CameraModel, model_b: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """:func:`b_onto_a_maps` at pan = tilt = 0, computed once per pair of camera models in this process.

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.

    Returns
    -------
    tuple of numpy.ndarray
        ``(map_x_px, map_y_px)`` as :func:`b_onto_a_maps` returns them (shared: do not modify).
    """

    return _computed_once(_MAPS_CACHE, model_a, model_b, lambda: b_onto_a_maps(model_a, model_b))


def warp_b_onto_a(image_b: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """B's image resampled onto A's grid (linear interpolation) for points at infinity.

    Parameters
    ----------
    image_b
        Camera B's image ``(H, W)`` or ``(H, W, C)``.
    maps
        ``(map_x_px, map_y_px)`` from :func:`cached_maps` or :func:`b_onto_a_maps`.

    Returns
    -------
    tuple of numpy.ndarray
        ``(warped, seen)``: B's image on A's grid (float32, 0 outside B's frame) and the boolean mask of A's
        pixels that B sees.
    """

    mx, my = maps
    img = np.asarray(image_b, np.float32)
    warped = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    h, w = img.shape[:2]
    seen = (mx >= 0) & (my >= 0) & (mx <= w - 1) & (my <= h - 1)
    return warped, seen


def offset_jacobian(model_a: CameraModel, model_b: CameraModel, pan_deg: float, tilt_deg: float,
                    delta_px: float = 1.0) -> np.ndarray:
    """Derivative of B's sensor position with respect to A's at A's image centre (finite differences).

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.
    pan_deg, tilt_deg
        The head's direction (degrees).
    delta_px
        Finite-difference step (A's pixels).

    Returns
    -------
    numpy.ndarray
        ``(2, 2)`` Jacobian, B's pixels per A's pixel (columns: ∂/∂x, ∂/∂y).
    """
    c = np.array([[model_a.cx, model_a.cy], [model_a.cx + delta_px, model_a.cy], [model_a.cx, model_a.cy + delta_px]])
    rays, _ = model_a.pixel_to_world(c, pan_deg, tilt_deg)
    px, _ = model_b.world_to_pixel(rays, pan_deg, tilt_deg, margin_px=None)
    return np.stack([(px[1] - px[0]) / delta_px, (px[2] - px[0]) / delta_px], axis=1)


_FIELD_CACHE: dict = {}


def cached_epipolar_field(model_a: CameraModel, model_b: CameraModel) -> np.ndarray:
    """:func:`~omnispectral.imaging.parallax.epipolar_field` of A's every pixel, once per pair of models.

    Parameters
    ----------
    model_a, model_b
        Camera A's and camera B's models.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 4)`` float32 on A's grid: per pixel the displacement ``e`` of the warped B image per unit of
        inverse depth (px · m) and its second derivative ``h`` (``p + w e + w² h / 2``); 0 where the lens
        model has no ray.  Shared: do not modify.
    """


    # pixels beyond the lens model have no ray: no parallax there
    return _computed_once(_FIELD_CACHE, model_a, model_b, lambda: np.nan_to_num(
        epipolar_field(model_a, baseline_m(model_b), second_order=True)).astype(np.float32))
