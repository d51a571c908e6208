"""Eq. (4) of the paper: an image to its polar-coordinate image (Hirai et al. 2018, Sec. 4.4, Fig. 7).

For a pinhole image with focal length ``f`` (pixels) and image coordinates ``(x, y)`` measured
from the principal point (``x`` right, ``y`` down), the 3D point ``(x, y, f)`` has the spherical
coordinates

    ``θ = atan(x / f)``,  ``φ = atan(y / sqrt(x² + f²))``.                                    (4)

``θ`` is the longitude and ``-φ`` the latitude of the pixel's ray for a camera looking at
longitude 0, latitude 0 (``φ`` grows downwards like ``y``), so the polar-coordinate image is a
piece of an equirectangular panorama, flipped vertically.  The mosaic engine does not build these
images (it composes the whole geometry into one resampling, see :mod:`omnispectral.mosaic.tile`);
this module keeps Eq. (4) as a function because the paper and its users speak in those terms, and
the tests check that the engine's single-direction output agrees with it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.mosaic.interp import remap

__all__ = ["PolarImage", "polar_angles_rad", "polar_image", "polar_to_image_px"]


def polar_angles_rad(x_px, y_px, f_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (4): image coordinates ``(x, y)`` (pixels from the principal point) → ``(θ, φ)`` in radians."""
    if not f_px > 0:
        raise ConfigurationError(f"the focal length must be positive, got {f_px}")
    x = np.asarray(x_px, dtype=np.float64)
    y = np.asarray(y_px, dtype=np.float64)
    return np.arctan(x / f_px), np.arctan(y / np.sqrt(x * x + f_px * f_px))


def polar_to_image_px(theta_rad, phi_rad, f_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of Eq. (4): ``x = f tan θ``, ``y = tan φ · sqrt(x² + f²) = f tan φ / cos θ``."""
    theta = np.asarray(theta_rad, dtype=np.float64)
    phi = np.asarray(phi_rad, dtype=np.float64)
    return f_px * np.tan(theta), f_px * np.tan(phi) / np.cos(theta)


@dataclass(frozen=True)
class PolarImage:
    """A polar-coordinate image: ``image[i, j]`` is at ``φ = phi_deg[i]``, ``θ = theta_deg[j]``.

    ``valid`` marks the pixels whose ray falls inside the source image; the others are NaN.
    """

    image: np.ndarray
    theta_deg: np.ndarray
    phi_deg: np.ndarray
    valid: np.ndarray


def polar_image(image: np.ndarray, f_px: float, cx: float | None = None, cy: float | None = None,
                step_deg: float | None = None, interp: str = "cubic") -> PolarImage:
    """The polar-coordinate image of an undistorted pinhole image (Eq. (4), the paper's Fig. 7).

    Parameters
    ----------
    image
        ``(H, W)`` or ``(H, W, C)`` float image, already free of lens distortion.
    f_px
        Focal length in pixels.
    cx, cy
        Principal point (OpenCV convention, pixel centres at integers); default the image centre.
    step_deg
        Angular size of an output pixel; default ``1/f`` radian, the input's resolution on axis.
    interp
        ``"linear"``, ``"cubic"`` or ``"lanczos"`` (see :mod:`omnispectral.mosaic.interp`).

    The output spans the angles of the image's left/right edges in ``θ`` (Eq. (4): ``θ`` depends
    on ``x`` only) and of the top/bottom edges on the centre column in ``φ``; away from the centre
    column the top and bottom borders curve inwards (``φ`` shrinks as ``sqrt(x² + f²)`` grows).
    """

    img = np.asarray(image, dtype=np.float32)
    squeeze = img.ndim == 2
    if squeeze:
        img = img[..., None]
    h, w = img.shape[:2]
    cx = (w - 1) / 2.0 if cx is None else float(cx)
    cy = (h - 1) / 2.0 if cy is None else float(cy)
    step = np.radians(step_deg) if step_deg is not None else 1.0 / f_px
    t0, _ = polar_angles_rad(-0.5 - cx, 0.0, f_px)
    t1, _ = polar_angles_rad(w - 0.5 - cx, 0.0, f_px)
    _, p0 = polar_angles_rad(0.0, -0.5 - cy, f_px)
    _, p1 = polar_angles_rad(0.0, h - 0.5 - cy, f_px)
    n_theta = max(1, int(np.ceil((t1 - t0) / step)))
    n_phi = max(1, int(np.ceil((p1 - p0) / step)))
    theta = t0 + (np.arange(n_theta) + 0.5) * (t1 - t0) / n_theta
    phi = p0 + (np.arange(n_phi) + 0.5) * (p1 - p0) / n_phi
    x, y = polar_to_image_px(theta[None, :], phi[:, None], f_px)
    u, v = np.broadcast_arrays(x + cx, y + cy)
    valid = (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)
    out = remap(img, u.astype(np.float32), v.astype(np.float32), interp)
    out[~valid] = np.nan
    return PolarImage(out[..., 0] if squeeze else out, np.degrees(theta), np.degrees(phi), valid)
