"""The one definition of the rig's geometry: equirectangular panoramas, the pan/tilt head, the lens.

Everything here is vectorised float64 NumPy: arrays of any leading shape, no loop per point, so
the mosaic engine (output pixel → world ray → camera pixel) and the rig simulator (camera pixel →
world ray → scene) can push millions of points through the same functions.

Conventions
-----------
**World frame.** Right-handed, ``+Y`` up.  Longitude 0 / latitude 0 is ``+Z``; longitude ``+90°``
is the direction a viewer faces after turning right (clockwise seen from above) from ``+Z``, which
with ``+Y`` up in a right-handed frame is ``-X``.  A unit ray is therefore

    ``(x, y, z) = (-cos(lat) sin(lon), sin(lat), cos(lat) cos(lon))``.

This is Mitsuba's environment-map convention (``u = atan2(x, -z) / 2π``, ``v = acos(y) / π``):
``u = 0.25`` faces ``+X``, ``u = 0.5`` faces ``+Z`` and the top row is ``+Y``, so a panorama made
here renders unchanged as a Mitsuba ``envmap``.

**Equirectangular image** (W × H).  ``lon_deg`` in ``[-180, 180)`` increases to the right,
``lat_deg`` in ``[-90, 90]`` is ``+90`` at the top row.  Pixel coordinates follow OpenCV: the
centre of pixel ``(col, row)`` is at integer coordinates, so that centre is at
``lon = (col + 0.5) / W · 360 - 180`` and ``lat = 90 - (row + 0.5) / H · 180`` and the image
spans ``[-0.5, W - 0.5] × [-0.5, H - 0.5]``.  Column ``W / 2 - 0.5`` is ``+Z`` and the ±180° seam
runs along the left and right borders.

**Camera frame.** OpenCV's: ``x`` right, ``y`` down, ``z`` forward along the optical axis; pixel
``(u, v)`` with ``u`` to the right and ``v`` down, pixel centres at integers.

**Head frame.** The camera frame of an ideal, unrolled camera on the pan/tilt head (``x`` right,
``y`` down, ``z`` forward), origin at the head's rotation centre, which is taken to be camera A's
optical centre (the paper sets the system's optical axis to camera A's, Sec. 2).
:func:`head_rotation` turns head-frame vectors into world vectors: ``pan_deg > 0`` turns right
(about world ``+Y``, the outer axis), ``tilt_deg > 0`` looks up (about the head's horizontal axis,
the inner axis, which turns with the pan).  At ``pan = tilt = 0`` the head looks along ``+Z`` with
the image's up (``-y``) along ``+Y``, so pan ``p`` and tilt ``t`` look at ``lon = p``, ``lat = t``.

**Mounting** (:class:`Mounting`) places a camera on the head: ``roll_deg`` about the optical axis
(positive = camera body turned clockwise as seen from behind it; the paper's cameras are mounted
at 90°, portrait), a small misalignment ``(yaw, pitch, roll)`` in degrees (positive yaw turns the
camera right, positive pitch looks up, positive roll as ``roll_deg``), and ``baseline_mm``, the
camera's optical centre in the head frame (camera B relative to camera A), so near objects show
parallax in the simulator.

**Lens** (:class:`CameraModel`).  OpenCV's pinhole model with its full distortion model ("Camera
Calibration and 3D Reconstruction", OpenCV documentation; coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6
[s1 s2 s3 s4 [τx τy]]]]``): for a camera-frame point ``(X, Y, Z)``, ``x' = X/Z``, ``y' = Y/Z``,
``r² = x'² + y'²``,

    ``x'' = x' (1 + k1 r² + k2 r⁴ + k3 r⁶) / (1 + k4 r² + k5 r⁴ + k6 r⁶) + 2 p1 x'y' + p2 (r² + 2x'²)
    + s1 r² + s2 r⁴`` (and symmetrically for ``y''``), then the tilted-sensor homography
    ``τ(τx, τy)``, then ``u = fx x'' + cx``, ``v = fy y'' + cy``.

The parameters are those estimated by Zhang's method (Zhang, "A flexible new technique for camera
calibration", IEEE TPAMI 22(11), 2000) through ``cv2.calibrateCamera``, which the paper uses to
correct lens distortion (Hirai et al. 2018, Sec. 4.2); see :mod:`omnispectral.imaging.lens`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import brentq

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.distortion_kernel import compiled_project, compiled_undistort, distortion, distortion_jacobian
from omnispectral.io import atomic_write_json, read_text_file

__all__ = ["DIST_LENGTHS", "DIST_NAMES", "HEAD_TO_WORLD_AT_ZERO", "JSON_FORMAT", "JSON_VERSION",
           "UNDISTORT_ACCEPT_TOL", "UNDISTORT_TOL", "CameraModel", "Mounting", "equirect_pixel_to_lonlat",
           "head_rotation", "lonlat_to_equirect_pixel", "lonlat_to_ray", "monotonic_radius", "native_width",
           "ray_to_lonlat", "rot_x", "rot_y", "rot_z", "tilt_matrix", "wrap_lon_deg"]

#: Names of OpenCV's distortion coefficients, in OpenCV's order.
DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
#: Vector lengths OpenCV accepts for ``distCoeffs``.
DIST_LENGTHS = (0, 4, 5, 8, 12, 14)

#: Largest undistorted radius ``tan(θ)`` searched for the monotonic region (θ ≈ 89.94°).
_R_SCAN = 1e3
#: Newton iterations of :meth:`CameraModel.unproject` stop once the residual in normalised
#: coordinates is below this (≈ 1e-9 px at f = 1000 px).
UNDISTORT_TOL = 1e-12
#: Residual still accepted where float64 rounding stalls the iteration before ``UNDISTORT_TOL`` (≈ 1e-6 px).
UNDISTORT_ACCEPT_TOL = 1e-9
_UNDISTORT_MAX_ITER = 60
#: Fewest points for which :meth:`CameraModel.undistort_normalized` runs the compiled iterations (below, the
#: array version: no compilation or cache load for a handful of points).
_COMPILED_UNDISTORT_MIN = 4096
#: Fewest points for which :meth:`CameraModel.project` runs the compiled kernel (likewise).
_COMPILED_PROJECT_MIN = 4096

JSON_FORMAT = "omnispectral.camera"
JSON_VERSION = 1


# ------------------------------------------------------------------------------------------ equirect
def _f64(a) -> np.ndarray:
    return np.asarray(a, dtype=np.float64)


def wrap_lon_deg(lon_deg) -> np.ndarray:
    """Longitude wrapped into ``[-180, 180)``."""
    return np.mod(_f64(lon_deg) + 180.0, 360.0) - 180.0


def equirect_pixel_to_lonlat(col, row, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates of a W × H equirectangular image → ``(lon_deg, lat_deg)``.

    Integer ``(col, row)`` are pixel centres (OpenCV convention); see the module docstring.
    Longitudes are wrapped into ``[-180, 180)``.
    """
    lon = (_f64(col) + 0.5) * (360.0 / width) - 180.0
    lat = 90.0 - (_f64(row) + 0.5) * (180.0 / height)
    return wrap_lon_deg(lon), lat


def lonlat_to_equirect_pixel(lon_deg, lat_deg, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(lon_deg, lat_deg)`` → pixel ``(col, row)`` of a W × H equirectangular image.

    Longitude is wrapped first, so ``col`` lies in ``[-0.5, W - 0.5)``; ``row`` in ``[-0.5, H - 0.5]``.
    """
    col = (wrap_lon_deg(lon_deg) + 180.0) * (width / 360.0) - 0.5
    row = (90.0 - _f64(lat_deg)) * (height / 180.0) - 0.5
    return col, row


def native_width(fx_px: float) -> int:
    """Equirect panorama width whose pixel matches a sensor's on its optical axis: ``2π f`` rounded to an
    even number (the mosaic's default width; the simulator's ground truth is rendered on the same grid)."""
    return max(8, 2 * round(np.pi * fx_px))


def lonlat_to_ray(lon_deg, lat_deg) -> np.ndarray:
    """Unit world rays ``(..., 3)``: ``(-cos lat sin lon, sin lat, cos lat cos lon)``."""
    lon = np.radians(_f64(lon_deg))
    lat = np.radians(_f64(lat_deg))
    lon, lat = np.broadcast_arrays(lon, lat)
    cos_lat = np.cos(lat)
    return np.stack((-cos_lat * np.sin(lon), np.sin(lat), cos_lat * np.cos(lon)), axis=-1)


def ray_to_lonlat(rays) -> tuple[np.ndarray, np.ndarray]:
    """World rays ``(..., 3)`` (any length > 0) → ``(lon_deg, lat_deg)``, ``lon`` in ``[-180, 180)``.

    At the poles the longitude is undefined; 0 is returned there.
    """
    rays = _f64(rays)
    x, y, z = rays[..., 0], rays[..., 1], rays[..., 2]
    lon = np.degrees(np.arctan2(-x, z))
    lat = np.degrees(np.arctan2(y, np.hypot(x, z)))
    return wrap_lon_deg(lon), lat


# ------------------------------------------------------------------------------------------ rotations
def rot_x(angle_deg: float) -> np.ndarray:
    """Right-handed rotation by ``angle_deg`` about ``+x``."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_deg: float) -> np.ndarray:
    """Right-handed rotation by ``angle_deg`` about ``+y``."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_deg: float) -> np.ndarray:
    """Right-handed rotation by ``angle_deg`` about ``+z``."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


#: Head frame (x right, y down, z forward) → world frame at pan = tilt = 0: x → -X, y → -Y, z → +Z.
HEAD_TO_WORLD_AT_ZERO = np.diag([-1.0, -1.0, 1.0])


def head_rotation(pan_deg: float, tilt_deg: float) -> np.ndarray:
    """3 × 3 rotation taking head-frame (camera-frame, OpenCV axes) rays to world rays.

    ``R = R_Y(-pan) · R_X(-tilt) · diag(-1, -1, 1)``: pan about world ``+Y`` (outer axis,
    positive turns right), tilt about the head's horizontal axis (inner axis, positive looks up).
    The optical axis ``(0, 0, 1)`` goes to the ray of ``lon = pan_deg``, ``lat = tilt_deg``.
    """
    return rot_y(-pan_deg) @ rot_x(-tilt_deg) @ HEAD_TO_WORLD_AT_ZERO


# ------------------------------------------------------------------------------------------ mounting
@dataclass(frozen=True)
class Mounting:
    """How one camera sits on the pan/tilt head (see the module docstring for the signs).

    Parameters
    ----------
    roll_deg
        Nominal rotation about the optical axis (90 for the paper's portrait mounting).
    misalignment_deg
        Small residual rotation ``(yaw, pitch, roll)`` in degrees (see :meth:`rotation`).
    baseline_mm
        Optical centre of this camera in the head frame (x right, y down, z forward), in mm,
        relative to the head's reference point (camera A).
    """

    roll_deg: float = 0.0
    misalignment_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    baseline_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        object.__setattr__(self, "roll_deg", float(self.roll_deg))
        for name in ("misalignment_deg", "baseline_mm"):
            value = tuple(float(v) for v in getattr(self, name))
            if len(value) != 3 or not all(math.isfinite(v) for v in value):
                raise ConfigurationError(f"Mounting.{name} must be three finite numbers, got {value}")
            object.__setattr__(self, name, value)
        if not math.isfinite(self.roll_deg):
            raise ConfigurationError(f"Mounting.roll_deg must be finite, got {self.roll_deg}")

    def rotation(self) -> np.ndarray:
        """3 × 3 rotation taking camera-frame rays to head-frame rays.

        ``R = R_y(yaw) · R_x(pitch) · R_z(roll + roll_deg)`` with OpenCV axes, so positive yaw
        turns the optical axis towards ``+x`` (right), positive pitch towards ``-y`` (up) and
        positive roll turns the camera's ``x`` axis towards ``+y`` (clockwise seen from behind).
        """
        yaw, pitch, roll = self.misalignment_deg
        return rot_y(yaw) @ rot_x(pitch) @ rot_z(roll + self.roll_deg)

    def with_misalignment_change(self, delta_deg) -> Mounting:
        """This mounting with ``delta_deg = (yaw, pitch, roll)`` added to its misalignment."""
        mis = tuple(float(a) + float(b) for a, b in zip(self.misalignment_deg, delta_deg, strict=True))
        return Mounting(self.roll_deg, mis, self.baseline_mm)

    def to_dict(self) -> dict[str, Any]:
        yaw, pitch, roll = self.misalignment_deg
        return {"roll_deg": self.roll_deg,
                "misalignment_deg": {"yaw": yaw, "pitch": pitch, "roll": roll},
                "baseline_mm": list(self.baseline_mm)}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Mounting:
        if not isinstance(data, dict):
            raise ConfigurationError("'mounting' must be an object")
        mis = data.get("misalignment_deg", {})
        if isinstance(mis, dict):
            unknown = set(mis) - {"yaw", "pitch", "roll"}
            if unknown:
                raise ConfigurationError(f"unknown misalignment_deg keys {sorted(unknown)} (use yaw, pitch, roll)")
            mis = (mis.get("yaw", 0.0), mis.get("pitch", 0.0), mis.get("roll", 0.0))
        try:
            return cls(roll_deg=float(data.get("roll_deg", 0.0)), misalignment_deg=tuple(mis),
                       baseline_mm=tuple(data.get("baseline_mm", (0.0, 0.0, 0.0))))
        except (TypeError, ValueError) as exc:
            raise ConfigurationError(f"bad 'mounting': {exc}") from exc


# ------------------------------------------------------------------------------------------ distortion
def _dist14(dist) -> np.ndarray:
    out = np.zeros(14)
    out[: len(dist)] = dist
    return out


def _distort(x, y, d: np.ndarray, jacobian: bool = False):
    """OpenCV distortion (radial rational + tangential + thin prism, before the tilt) of normalised ``x, y``.

    Returns ``(xd, yd)`` and, with ``jacobian=True``, also ``(J00, J01, J10, J11)`` =
    ``∂(xd, yd)/∂(x, y)``.  ``d`` holds the 14 coefficients in OpenCV's order
    (:func:`~omnispectral.imaging.distortion_kernel.distortion`, shared with the compiled unprojection).
    """
    xd, yd, r2, num, den, g = distortion(x, y, d)
    if not jacobian:
        return xd, yd
    return xd, yd, distortion_jacobian(x, y, d, r2, num, den, g)


def tilt_matrix(tau_x_rad: float, tau_y_rad: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection ``matTilt`` (``computeTiltProjectionMatrix``), angles in radians."""
    cx, sx = math.cos(tau_x_rad), math.sin(tau_x_rad)
    cy, sy = math.cos(tau_y_rad), math.sin(tau_y_rad)
    rot_xy = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]]) @ np.array(
        [[1.0, 0.0, 0.0], [0.0, cx, sx], [0.0, -sx, cx]])
    proj_z = np.array([[rot_xy[2, 2], 0.0, -rot_xy[0, 2]], [0.0, rot_xy[2, 2], -rot_xy[1, 2]], [0.0, 0.0, 1.0]])
    return proj_z @ rot_xy


def _apply_homography(h: np.ndarray, x, y):
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w, w


def _radial_limit_r2(d: np.ndarray) -> float:
    """Smallest ``s = r² > 0`` where the radial part ``r g(r²)`` stops increasing or ``g`` turns non-positive.

    With ``g = num/den`` (``num = 1 + k1 s + k2 s² + k3 s³``, ``den = 1 + k4 s + k5 s² + k6 s³``),
    ``d(r g)/dr = g + 2 s g'`` has the sign of ``P = num·den + 2 s (num'·den - num·den')`` and
    ``g`` that of ``Q = num·den``; both are polynomials in ``s``, so the limit is their smallest
    positive real root (exact: a grid can miss the narrow ripple of a rational fit whose numerator
    and denominator nearly cancel).
    """
    poly = np.polynomial.Polynomial
    num = poly([1.0, d[0], d[1], d[4]])
    den = poly([1.0, d[5], d[6], d[7]])
    s_ = poly([0.0, 1.0])
    q = num * den
    p = q + 2.0 * s_ * (num.deriv() * den - num * den.deriv())
    best = np.inf
    for f in (p, q):
        f = f.trim()
        if f.degree() < 1:
            continue
        roots = f.roots()
        real = roots.real[(np.abs(roots.imag) <= 1e-9 * np.maximum(1.0, np.abs(roots.real))) & (roots.real > 0)]
        for root in np.sort(real):
            # A root where the polynomial only touches zero does not end the region; check the sign beyond it.
            eps = 1e-9 * max(root, 1e-12)
            if f(root + eps) <= 0 or f(root - eps) <= 0:
                best = min(best, float(root))
                break
    return best


def monotonic_radius(dist, n_azimuth: int = 180, n_radius: int = 3000) -> float:
    """Largest undistorted radius ``r = tan θ`` up to which OpenCV's distortion does not fold.

    The radial part is bounded exactly by :func:`_radial_limit_r2`.  With tangential or thin-prism
    terms, the full map is also checked along rays from the principal point at ``n_azimuth``
    azimuths (geometric radius grid from 1e-3 to 1e3): the Jacobian determinant must stay positive
    and the distorted radius must grow with ``r``; the last good grid radius bounds the region.
    Returns at most ``1e3`` (θ ≈ 89.94°).  Beyond the limit a strongly distorted model maps rays
    far outside the field of view back into the image, so those rays are invalid.
    """
    d = _dist14(dist)
    if not np.any(d[:12]):
        return _R_SCAN
    limit = min(_R_SCAN, math.sqrt(_radial_limit_r2(d)) * (1.0 - 1e-9))
    if not np.any(d[[2, 3, 8, 9, 10, 11]]) or limit <= 1e-3:
        return limit
    r = np.geomspace(1e-3, limit, n_radius)[:, None]
    phi = np.linspace(0.0, 2.0 * np.pi, n_azimuth, endpoint=False)[None, :]
    c, s = np.cos(phi), np.sin(phi)
    xd, yd, (j00, j01, j10, j11) = _distort(r * c, r * s, d, jacobian=True)
    det = j00 * j11 - j01 * j10
    radial_growth = (j00 * c + j01 * s) * xd + (j10 * c + j11 * s) * yd  # d|D|²/dr / 2
    bad = ~((det > 0.0) & (radial_growth > 0.0))
    bad_rows = np.flatnonzero(bad.any(axis=1))
    if bad_rows.size == 0:
        return limit
    first = bad_rows[0]
    return float(r[first - 1, 0]) if first > 0 else 0.0


# ------------------------------------------------------------------------------------------ camera
@dataclass(frozen=True)
class CameraModel:
    """A calibrated camera: OpenCV pinhole + distortion model, plus its mounting on the head.

    Maps pixel ↔ ray in the camera frame (:meth:`project`, :meth:`unproject`) and in the world
    frame for a head direction (:meth:`world_to_pixel`, :meth:`pixel_to_world`,
    :meth:`world_points_to_pixel`).  Forward maps return ``(values, valid)``; invalid entries are
    NaN.  The paper corrects lens distortion with a model from Zhang's method (Sec. 4.2); this is
    that model, in OpenCV's parametrisation so calibrations interoperate.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    fx, fy, cx, cy : float
        Focal lengths and principal point in pixels (OpenCV's camera matrix, no skew).
    dist : tuple of float
        OpenCV distortion coefficients ``k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [τx τy]]]]``
        (length 0, 4, 5, 8, 12 or 14; see :data:`DIST_NAMES`).
    mounting : Mounting
        Placement on the pan/tilt head (:class:`Mounting`).

    Raises
    ------
    ConfigurationError
        For a size that is not a positive integer, non-finite or non-positive focal lengths, a non-finite
        principal point, distortion coefficients of another length or not finite, or a ``mounting`` that is
        not a :class:`Mounting`.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.2 (lens distortion measured by Zhang's method), Sec. 3, Fig. 2
       (the two cameras mounted on the rotating table, turned by 90 degrees).
    .. [2] Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11):1330-1334, 2000.
    .. [3] "Camera Calibration and 3D Reconstruction", OpenCV documentation (the pinhole and distortion
       model and its coefficients).
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = ()
    mounting: Mounting = field(default_factory=Mounting)

    def __post_init__(self):
        for name in ("width", "height"):
            value = getattr(self, name)
            if int(value) != value or value <= 0:
                raise ConfigurationError(f"CameraModel.{name} must be a positive integer, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("fx", "fy", "cx", "cy"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise ConfigurationError(f"CameraModel.{name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        if self.fx <= 0 or self.fy <= 0:
            raise ConfigurationError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        dist = tuple(float(v) for v in np.asarray(self.dist, dtype=np.float64).ravel())
        if len(dist) not in DIST_LENGTHS:
            raise ConfigurationError(f"OpenCV takes 4, 5, 8, 12 or 14 distortion coefficients, got {len(dist)}")
        if not all(math.isfinite(v) for v in dist):
            raise ConfigurationError(f"distortion coefficients must be finite, got {dist}")
        object.__setattr__(self, "dist", dist)
        if not isinstance(self.mounting, Mounting):
            raise ConfigurationError("CameraModel.mounting must be a Mounting")

    # ---------------------------------------------------------------- constructors
    @classmethod
    def from_opencv(cls, camera_matrix, dist_coeffs, image_size: tuple[int, int],
                    mounting: Mounting | None = None) -> CameraModel:
        """From OpenCV's camera matrix ``K`` (3 × 3, zero skew), ``distCoeffs`` and ``(width, height)``."""
        k = np.asarray(camera_matrix, dtype=np.float64)
        if k.shape != (3, 3):
            raise ConfigurationError(f"camera matrix must be 3 x 3, got shape {k.shape}")
        if abs(k[0, 1]) > 1e-12 * abs(k[0, 0]) or np.any(k[2] != (0.0, 0.0, 1.0)) or k[1, 0] != 0.0:
            raise ConfigurationError(f"camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), "
                                     f"got {k.tolist()}")
        dist = () if dist_coeffs is None else tuple(np.asarray(dist_coeffs, dtype=np.float64).ravel())
        width, height = image_size
        return cls(width=width, height=height, fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], dist=dist,
                   mounting=mounting or Mounting())

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_deg: float, dist=(),
                 mounting: Mounting | None = None) -> CameraModel:
        """A camera of horizontal field of view ``hfov_deg`` (edge to edge through the centre row).

        Square pixels, principal point at the image centre ``((W-1)/2, (H-1)/2)``.  Without
        distortion ``fx = fy = (W/2) / tan(hfov/2)``; with distortion the focal length is solved
        so that the distorted lens has the requested :attr:`hfov_deg`.
        """
        if not 0.0 < hfov_deg < 180.0:
            raise ConfigurationError(f"hfov_deg must lie in (0, 180), got {hfov_deg}")
        mounting = mounting or Mounting()
        f0 = 0.5 * width / math.tan(math.radians(hfov_deg) / 2.0)

        def make(f: float) -> CameraModel:
            return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0, tuple(dist), mounting)

        if not any(dist):
            return make(f0)

        def excess(log_f: float) -> float:
            fov = make(math.exp(log_f)).hfov_deg
            return 180.0 if not math.isfinite(fov) else fov - hfov_deg

        lo, hi = math.log(f0), math.log(f0)
        for _ in range(60):
            if excess(lo) > 0:
                break
            lo -= 0.1
        for _ in range(60):
            if excess(hi) < 0:
                break
            hi += 0.1
        if not (excess(lo) > 0 > excess(hi)):
            raise ConfigurationError(f"no focal length gives a {hfov_deg}° field of view with distortion {dist}")
        return make(math.exp(brentq(excess, lo, hi, xtol=1e-12)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CameraModel:
        """From the dictionary written by :meth:`to_dict` (unknown keys are ignored)."""
        if not isinstance(data, dict):
            raise ConfigurationError("a camera must be a JSON object")
        missing = [k for k in ("image_size", "fx", "fy", "cx", "cy") if k not in data]
        if missing:
            raise ConfigurationError(f"missing {', '.join(repr(m) for m in missing)}")
        size = data["image_size"]
        if isinstance(size, dict):
            size = (size.get("width"), size.get("height"))
        if not isinstance(size, list | tuple) or len(size) != 2 or not all(isinstance(v, int) for v in size):
            raise ConfigurationError(f"'image_size' must be {{\"width\": W, \"height\": H}}, "
                                     f"got {data['image_size']!r}")
        dist = _dist_from_json(data.get("distortion", ()))
        mounting = Mounting.from_dict(data["mounting"]) if "mounting" in data else Mounting()
        try:
            return cls(width=size[0], height=size[1], fx=float(data["fx"]), fy=float(data["fy"]),
                       cx=float(data["cx"]), cy=float(data["cy"]), dist=dist, mounting=mounting)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, ConfigurationError):
                raise
            raise ConfigurationError(f"bad camera parameter: {exc}") from exc

    @classmethod
    def from_json(cls, path: str | Path) -> CameraModel:
        """Read a camera written by :meth:`to_json` or by ``omnispectral calibrate lens``."""

        path = Path(path)
        text = read_text_file(path)
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputFileError(path, f"not valid JSON ({exc.msg})", line=exc.lineno) from None
        try:
            return cls.from_dict(data)
        except ConfigurationError as exc:
            raise InputFileError(path, f"not a camera model: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: image size, ``fx fy cx cy``, named distortion coefficients, mounting."""
        return {"format": JSON_FORMAT, "version": JSON_VERSION, "model": "opencv-pinhole",
                "image_size": {"width": self.width, "height": self.height},
                "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "distortion": self.distortion, "mounting": self.mounting.to_dict(),
                "hfov_deg": _finite_or_none(self.hfov_deg), "vfov_deg": _finite_or_none(self.vfov_deg)}

    def to_json(self, path: str | Path, extra: dict[str, Any] | None = None) -> Path:
        """Write :meth:`to_dict` (plus ``extra`` keys, e.g. calibration statistics) atomically."""

        return atomic_write_json(path, {**self.to_dict(), **(extra or {})})

    def to_opencv(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """``(K, distCoeffs, (width, height))`` for OpenCV functions."""
        return self.camera_matrix, np.array(self.dist, dtype=np.float64), self.image_size

    # ---------------------------------------------------------------- properties
    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` in pixels (OpenCV order)."""
        return self.width, self.height

    @property
    def camera_matrix(self) -> np.ndarray:
        """OpenCV's ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def distortion(self) -> dict[str, float]:
        """The distortion coefficients by name (``k1``, ``k2``, ``p1``, …, as many as :attr:`dist` has)."""
        return dict(zip(DIST_NAMES, self.dist, strict=False))

    @cached_property
    def _d(self) -> np.ndarray:
        return _dist14(self.dist)

    @cached_property
    def _tilt(self) -> tuple[np.ndarray, np.ndarray] | None:
        tau_x, tau_y = self._d[12:14]
        if tau_x == 0.0 and tau_y == 0.0:
            return None
        h = tilt_matrix(tau_x, tau_y)
        return h, np.linalg.inv(h)

    @cached_property
    def max_radius(self) -> float:
        """Undistorted radius ``tan θ`` (normalised coordinates) bounding the region where the
        distortion is monotonic (:func:`monotonic_radius`); rays beyond it are invalid."""
        return monotonic_radius(self.dist)

    @property
    def hfov_deg(self) -> float:
        """Angle between the rays of the left and right image edges on row ``cy`` (NaN if not invertible)."""
        return self._edge_angle((-0.5, self.cy), (self.width - 0.5, self.cy))

    @property
    def vfov_deg(self) -> float:
        """Angle between the rays of the top and bottom image edges on column ``cx`` (NaN if not invertible)."""
        return self._edge_angle((self.cx, -0.5), (self.cx, self.height - 0.5))

    def _edge_angle(self, a, b) -> float:
        rays, valid = self.unproject(np.array([a, b], dtype=np.float64))
        if not valid.all():
            return float("nan")
        return math.degrees(math.atan2(np.linalg.norm(np.cross(rays[0], rays[1])), float(rays[0] @ rays[1])))

    # ---------------------------------------------------------------- camera frame
    def project(self, rays_cam, margin_px: float | None = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points or rays ``(..., 3)`` → pixels ``(..., 2)`` and a validity mask ``(...)``.

        Implements ``cv2.projectPoints`` with zero pose (OpenCV camera model; see the module
        docstring).  Valid means: in front of the camera (``Z > 0``), inside the monotonic region of
        the distortion (:attr:`max_radius`) so that the pixel is a true image of the ray and not a
        fold-back, and inside the image ``[-0.5 - m, W - 0.5 + m] × [-0.5 - m, H - 0.5 + m]`` for
        ``m = margin_px`` (``None`` skips the image test).  Invalid pixels are NaN.
        """
        p = _f64(rays_cam)
        if p.shape[-1] != 3:
            raise ConfigurationError(f"rays must have shape (..., 3), got {p.shape}")
        kernel = compiled_project() if p.size >= 3 * _COMPILED_PROJECT_MIN else None
        if kernel is not None:
            return self._project_compiled(kernel, p, margin_px)
        z = p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            x = p[..., 0] / z
            y = p[..., 1] / z
            valid = (z > 0) & (x * x + y * y < self.max_radius**2)
            xd, yd = _distort(x, y, self._d)
            if self._tilt is not None:
                xd, yd, w = _apply_homography(self._tilt[0], xd, yd)
                valid &= w > 0
            u = self.fx * xd + self.cx
            v = self.fy * yd + self.cy
        if margin_px is not None:
            valid &= self.inside(u, v, margin_px)
        uv = np.stack((u, v), axis=-1)
        uv[~valid] = np.nan
        return uv, valid

    def _project_compiled(self, kernel, p: np.ndarray, margin_px: float | None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` by the compiled kernel (:func:`~.distortion_kernel.compiled_project`): the same bits."""
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        uv = np.empty((flat.shape[0], 2), np.float64)
        valid = np.empty(flat.shape[0], bool)
        window = np.full(4, np.nan)
        if margin_px is not None:
            lo = -0.5 - margin_px
            window[:] = (lo, self.width - 0.5 + margin_px, lo, self.height - 0.5 + margin_px)
        tilt = self._tilt[0] if self._tilt is not None else np.eye(3)
        kernel(flat, self._d, np.ascontiguousarray(tilt, np.float64), self._tilt is not None,
               np.array([self.fx, self.fy, self.cx, self.cy], np.float64), float(self.max_radius**2), window, uv,
               valid)
        return uv.reshape(*p.shape[:-1], 2), valid.reshape(p.shape[:-1])

    def inside(self, u, v, margin_px: float = 0.0) -> np.ndarray:
        """True where pixel ``(u, v)`` lies in ``[-0.5 - m, W - 0.5 + m] × [-0.5 - m, H - 0.5 + m]``."""
        lo = -0.5 - margin_px
        return (u >= lo) & (u <= self.width - 0.5 + margin_px) & (v >= lo) & (v <= self.height - 0.5 + margin_px)

    def undistort_normalized(self, xd, yd, tol: float = UNDISTORT_TOL, accept_tol: float = UNDISTORT_ACCEPT_TOL,
                             max_iter: int = _UNDISTORT_MAX_ITER) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Invert the distortion for normalised distorted coordinates (before the tilt homography is undone).

        Damped Newton iterations with the analytic Jacobian of the distortion, started at the
        distorted point and kept inside :attr:`max_radius`, until ``|D(x) - x_d| < tol``.  Where
        rounding stops the iteration earlier (e.g. a rational model whose numerator and
        denominator nearly cancel), a residual below ``accept_tol`` still counts as converged.
        Returns ``(x, y, converged)``.  (``cv2.undistortPoints`` uses fixed-point iterations that can
        diverge for strong distortion; Newton converges quadratically inside the monotonic region.)
        """
        xd, yd = np.broadcast_arrays(_f64(xd), _f64(yd))
        shape = xd.shape
        xd, yd = xd.ravel(), yd.ravel()
        x, y = xd.copy(), yd.copy()
        converged = np.zeros(xd.shape, dtype=bool)
        if not np.any(self._d[:12]):
            converged[:] = np.isfinite(xd) & np.isfinite(yd)
            return x.reshape(shape), y.reshape(shape), converged.reshape(shape)
        r_max2 = self.max_radius**2
        d = self._d
        kernel = compiled_undistort() if xd.size >= _COMPILED_UNDISTORT_MIN else None
        if kernel is not None:  # the same iterations point by point, compiled (distortion_kernel)
            resid = np.empty(xd.shape)
            kernel(xd, yd, np.ascontiguousarray(d, np.float64), float(r_max2), float(tol), int(max_iter), x, y,
                   resid)
            converged[:] = resid < max(tol, accept_tol)
            return x.reshape(shape), y.reshape(shape), converged.reshape(shape)
        active = np.flatnonzero(np.isfinite(xd) & np.isfinite(yd))
        xa, ya, ta, tb = x[active], y[active], xd[active], yd[active]
        # Start inside the valid region (the distorted point itself, pulled in if it lies beyond it).
        r2 = xa * xa + ya * ya
        pull = r2 >= r_max2
        if pull.any():
            shrink = 0.5 * np.sqrt(r_max2 / r2[pull])
            xa[pull] *= shrink
            ya[pull] *= shrink
        fxa, fya, jac = _distort(xa, ya, d, jacobian=True)
        err = np.hypot(fxa - ta, fya - tb)
        resid = np.full(xd.shape, np.inf)
        for _ in range(max_iter):
            done = err < tol
            if done.any():
                resid[active[done]] = err[done]
                x[active[done]], y[active[done]] = xa[done], ya[done]
                keep = ~done
                active, xa, ya, ta, tb, fxa, fya, err = (
                    a[keep] for a in (active, xa, ya, ta, tb, fxa, fya, err))
                jac = tuple(j[keep] for j in jac)
            if active.size == 0:
                break
            j00, j01, j10, j11 = jac
            ex, ey = fxa - ta, fya - tb
            with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                det = j00 * j11 - j01 * j10
                dx = (j11 * ex - j01 * ey) / det
                dy = (j00 * ey - j10 * ex) / det
            ok = np.isfinite(dx) & np.isfinite(dy)
            dx[~ok] = 0.0
            dy[~ok] = 0.0
            # Full Newton step; halve it where it would leave the valid region or not reduce the residual.
            xn, yn = xa - dx, ya - dy
            fxn, fyn, jn = _distort(xn, yn, d, jacobian=True)
            errn = np.hypot(fxn - ta, fyn - tb)
            step = 1.0
            worse = ok & ((xn * xn + yn * yn >= r_max2) | ~(errn < err))
            while worse.any() and step > 1e-9:
                step *= 0.5
                idx = np.flatnonzero(worse)
                xw, yw = xa[idx] - step * dx[idx], ya[idx] - step * dy[idx]
                fxw, fyw, jw = _distort(xw, yw, d, jacobian=True)
                ew = np.hypot(fxw - ta[idx], fyw - tb[idx])
                better = (xw * xw + yw * yw < r_max2) & (ew < err[idx])
                good = idx[better]
                xn[good], yn[good], fxn[good], fyn[good], errn[good] = (
                    xw[better], yw[better], fxw[better], fyw[better], ew[better])
                for jj, jwj in zip(jn, jw, strict=True):
                    jj[good] = jwj[better]
                worse[good] = False
            stalled = ~ok | worse
            x[active[stalled]], y[active[stalled]] = xa[stalled], ya[stalled]
            resid[active[stalled]] = err[stalled]
            keep = ~stalled
            active, xa, ya, ta, tb, fxa, fya, err = (
                a[keep] for a in (active, xn, yn, ta, tb, fxn, fyn, errn))
            jac = tuple(j[keep] for j in jn)
        x[active], y[active] = xa, ya
        resid[active] = err
        converged[:] = resid < max(tol, accept_tol)
        return x.reshape(shape), y.reshape(shape), converged.reshape(shape)

    def unproject(self, pixels) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(..., 2)`` → unit camera-frame rays ``(..., 3)`` and a validity mask ``(...)``.

        Inverse of :meth:`project` (the inverse of ``cv2.projectPoints``, like
        ``cv2.undistortPoints`` but with Newton iterations to a residual of 1e-12 in normalised
        coordinates, ≈ 1e-9 px).  Valid means the iteration converged inside the monotonic region;
        pixels outside the image are allowed.  Invalid rays are NaN.
        """
        uv = _f64(pixels)
        if uv.shape[-1] != 2:
            raise ConfigurationError(f"pixels must have shape (..., 2), got {uv.shape}")
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        tilt_ok = True
        if self._tilt is not None:
            xd, yd, w = _apply_homography(self._tilt[1], xd, yd)
            tilt_ok = w > 0
        x, y, valid = self.undistort_normalized(xd, yd)
        valid &= tilt_ok & (x * x + y * y < self.max_radius**2)
        rays = np.stack((x, y, np.ones_like(x)), axis=-1)
        rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
        rays[~valid] = np.nan
        return rays, valid

    # ---------------------------------------------------------------- world frame
    def camera_to_world(self, pan_deg: float, tilt_deg: float) -> np.ndarray:
        """3 × 3 rotation taking this camera's rays to world rays: ``head_rotation · mounting``."""
        return head_rotation(pan_deg, tilt_deg) @ self.mounting.rotation()

    def camera_center_mm(self, pan_deg: float, tilt_deg: float) -> np.ndarray:
        """World position (mm, origin at the head's rotation centre) of this camera's optical centre."""
        return head_rotation(pan_deg, tilt_deg) @ np.asarray(self.mounting.baseline_mm)

    def world_to_pixel(self, rays_world, pan_deg: float, tilt_deg: float,
                       margin_px: float | None = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """World directions ``(..., 3)`` (points at infinity) → pixels and validity, head at ``(pan, tilt)``.

        The mosaic engine's inverse map: equirect pixel → :func:`lonlat_to_ray` → this.
        Translation (``baseline_mm``) does not move points at infinity; see :meth:`world_points_to_pixel`.
        """
        r = self.camera_to_world(pan_deg, tilt_deg)
        return self.project(_f64(rays_world) @ r, margin_px=margin_px)

    def world_points_to_pixel(self, points_mm, pan_deg: float, tilt_deg: float,
                              margin_px: float | None = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """World points ``(..., 3)`` in mm (origin at the head's rotation centre) → pixels and validity.

        Includes the camera's ``baseline_mm``, so near points show parallax between cameras A and B.
        """
        h = head_rotation(pan_deg, tilt_deg)
        p_head = _f64(points_mm) @ h - np.asarray(self.mounting.baseline_mm)
        return self.project(p_head @ self.mounting.rotation(), margin_px=margin_px)

    def pixel_to_world(self, pixels, pan_deg: float, tilt_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """Pixels ``(..., 2)`` → unit world rays ``(..., 3)`` and validity, head at ``(pan, tilt)``.

        The rays start at :meth:`camera_center_mm` (the simulator's camera rays).
        """
        rays, valid = self.unproject(pixels)
        return rays @ self.camera_to_world(pan_deg, tilt_deg).T, valid


def _finite_or_none(value: float) -> float | None:
    return value if math.isfinite(value) else None


def _dist_from_json(value) -> tuple[float, ...]:
    """Distortion from a ``{"k1": …}`` object (OpenCV names) or an OpenCV-ordered list."""
    if isinstance(value, dict):
        unknown = [k for k in value if k not in DIST_NAMES]
        if unknown:
            raise ConfigurationError(f"unknown distortion coefficient(s) {unknown}; known: {', '.join(DIST_NAMES)}")
        if not value:
            return ()
        last = max(DIST_NAMES.index(k) for k in value)
        n = next(n for n in DIST_LENGTHS if n > last)
        try:
            return tuple(float(value.get(name, 0.0)) for name in DIST_NAMES[:n])
        except (TypeError, ValueError) as exc:
            raise ConfigurationError(f"bad distortion coefficient: {exc}") from exc
    if isinstance(value, list | tuple):
        try:
            return tuple(float(v) for v in value)
        except (TypeError, ValueError) as exc:
            raise ConfigurationError(f"bad distortion coefficient: {exc}") from exc
    raise ConfigurationError("'distortion' must be an object of named coefficients or a list")
