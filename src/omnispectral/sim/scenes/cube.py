"""A hyperspectral reflectance cube hung on a wall of the procedural scene and lit by its daylight.

The cube is a flat Lambertian panel on a vertical face of one of the base scene's boxes (by
default the concrete "near wall" 4 m north-west of the rig): row 0 of the cube at the top, column
0 at the left as seen from the front.  Each texel's reflectance is resampled linearly onto the
scene's wavelength grid (no extrapolation); a texel is a uniform square of the panel (what a pixel of
a hyperspectral image is: the mean reflectance over its cell).  A point of the panel reflects
``ρ(λ)/π · (E_sun cos θ V + E_sky(n))``, with the same sun, sky, shadows and units as the rest of
:class:`ProceduralOutdoorScene`.

Texture filtering
-----------------
A cube can hold many texels per pixel of the cameras that look at it (a 512-texel cube 1.2 m wide at
5 m puts ~14 × 14 texels in a pixel of the ``small`` preset), and a pixel's few rays would then pick a
few of them: point sampling aliases, in the cameras and in the truth alike.  Renderers that know how
much of the sphere a ray stands for pass it (``ray_spread_rad``, the angular side of the ray's share of
the pixel; :attr:`CubeOnWallScene.ray_footprint`), and the ray gets the exact mean of the texels over
its footprint on the panel: the footprint of the ray's angular square, projected onto the panel's
plane (the ray differentials of Igehy 1999), as the axis-aligned rectangle in the panel's (right, up)
axes with the same spread along each, and integrated over the piecewise-constant texels with a
summed-area table (Crow 1984; exact: the table's bilinear interpolation is the integral of a
piecewise-constant image).  A ray without a spread gets the texel it meets.  The tables are float64:
a 1024 × 1024 cube of 31 bands takes 260 MB for the spectral truth.

References
----------
.. [1] H. Igehy, "Tracing ray differentials", SIGGRAPH 1999.
.. [2] F. C. Crow, "Summed-area tables for texture mapping", SIGGRAPH 1984.

Files
-----
- ``.npz`` with ``cube`` (H, W, B) reflectances in 0..1 and ``wavelength_nm`` (B,), strictly increasing.
- ENVI (``.hdr`` header beside its data file) through Spectral Python (the ``spectral`` package,
  imported only when needed); wavelengths from the header's ``wavelength`` (nm, or µm when
  ``wavelength units`` says so) and values divided by ``reflectance scale factor`` when present.
"""

from __future__ import annotations

import math
import zipfile
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.sim.scenes.base import (
    RAY_BLOCK,
    BandProjectionCache,
    Scene,
    as_directions,
    as_origin,
    lonlat_to_direction,
)
from omnispectral.sim.scenes.procedural import ProceduralOutdoorScene, combine
from omnispectral.spectral.curves import resample_matrix

__all__ = ["RANGE_TOLERANCE", "CubeOnWallScene", "box_mean", "check_cube", "load_reflectance_cube",
           "summed_area_table"]

#: Tolerance on the 0..1 range of reflectances (rounding in stored files).
RANGE_TOLERANCE = 1e-6
_MICROMETRE_UNITS = ("micrometers", "micrometer", "micrometres", "micrometre", "um", "µm", "microns", "micron")


def summed_area_table(image: np.ndarray) -> np.ndarray:
    """``(H + 1, W + 1, C)`` float64 ``S`` with ``S[j, i]`` the sum of ``image (H, W, C)`` over rows ``< j`` and
    columns ``< i`` (Crow 1984)."""
    h, w, c = image.shape
    table = np.zeros((h + 1, w + 1, c), np.float64)
    np.cumsum(np.cumsum(image, axis=0, dtype=np.float64), axis=1, out=table[1:, 1:])
    return table


def _integral(table: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The integral of the piecewise-constant image of ``table`` over ``[0, x] × [0, y]`` (texel units), ``(P, C)``:
    the table interpolated bilinearly, which is exact for such an image."""
    h, w = table.shape[0] - 1, table.shape[1] - 1
    i = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
    j = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
    fx, fy = (x - i)[:, None], (y - j)[:, None]
    return ((1 - fy) * ((1 - fx) * table[j, i] + fx * table[j, i + 1])
            + fy * ((1 - fx) * table[j + 1, i] + fx * table[j + 1, i + 1]))


#: A footprint narrower than this (texels) takes the texel it lies in (a table difference over a sliver loses
#: precision).
MIN_FOOTPRINT_TEXELS = 1e-3


def box_mean(table: np.ndarray, x0: np.ndarray, x1: np.ndarray, y0: np.ndarray, y1: np.ndarray) -> np.ndarray:
    """Mean ``(P, C)`` float64 of the piecewise-constant image of the summed-area ``table`` over the rectangles
    ``[x0, x1] × [y0, y1]`` (texel units); where a side is below :data:`MIN_FOOTPRINT_TEXELS`, the texel at the
    rectangle's centre (its last row or column for a point on the far edge)."""
    h, w = table.shape[0] - 1, table.shape[1] - 1
    out = np.empty((x0.size, table.shape[2]), np.float64)
    point = ((x1 - x0) < MIN_FOOTPRINT_TEXELS) | ((y1 - y0) < MIN_FOOTPRINT_TEXELS)
    if point.any():
        i = np.clip(np.floor(0.5 * (x0[point] + x1[point])).astype(np.int64), 0, w - 1)
        j = np.clip(np.floor(0.5 * (y0[point] + y1[point])).astype(np.int64), 0, h - 1)
        out[point] = table[j + 1, i + 1] - table[j, i + 1] - table[j + 1, i] + table[j, i]
    area = ~point
    if area.any():
        a, b, c, d = x0[area], x1[area], y0[area], y1[area]
        total = _integral(table, b, d) - _integral(table, a, d) - _integral(table, b, c) + _integral(table, a, c)
        out[area] = total / ((b - a) * (d - c))[:, None]
    return out


def load_reflectance_cube(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a reflectance cube: ``(cube (H, W, B) float32, wavelength_nm (B,))``.

    Raises :class:`~omnispectral.errors.InputFileError` naming the file for anything unusable:
    missing or unreadable file, missing keys, wrong shapes, non-finite values, values outside 0..1.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        cube, wl = _read_npz(path)
    elif suffix in (".hdr", ".img", ".dat", ".raw") or suffix == "":
        cube, wl = _read_envi(path)
    else:
        raise InputFileError(path, f"unsupported cube format {suffix!r}; expected .npz or an ENVI .hdr header")
    return check_cube(cube, wl, path)


def _read_npz(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as f:
            keys = set(f.files)
            missing = [k for k in ("cube", "wavelength_nm") if k not in keys]
            if missing:
                raise InputFileError(path, f"missing array(s) {missing}; found {sorted(keys)}")
            return f["cube"], f["wavelength_nm"]
    except InputFileError:
        raise
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise InputFileError(path, f"cannot be read as a NumPy .npz archive ({exc})") from None


def _read_envi(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        import spectral.io.envi as envi
    except ImportError:
        raise InputFileError(path, "reading ENVI cubes needs Spectral Python: pip install spectral "
                                   "(or convert the cube to .npz with 'cube' and 'wavelength_nm')") from None
    header = path if path.suffix.lower() == ".hdr" else path.with_suffix(".hdr")
    if not header.is_file():
        raise InputFileError(path, f"ENVI header {header.name} not found")
    try:
        img = envi.open(str(header))
        cube = np.asarray(img.load(scale=False), dtype=np.float32)  # the scale factor is applied below
    except Exception as exc:  # Spectral Python raises several types for bad headers and data
        raise InputFileError(path, f"cannot be read as an ENVI image ({exc})") from None
    centers = getattr(img.bands, "centers", None)
    if not centers:
        raise InputFileError(header, "the ENVI header has no 'wavelength' list")
    wl = np.asarray(centers, dtype=np.float64)
    units = str(img.metadata.get("wavelength units", getattr(img.bands, "band_unit", "nm")) or "nm").lower()
    if units in _MICROMETRE_UNITS:
        wl = wl * 1000.0
    factor = img.metadata.get("reflectance scale factor")
    if factor is not None:
        cube = cube / np.float32(float(factor))
    return cube, wl


def check_cube(cube, wavelength_nm, source: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Validate a reflectance cube; errors name ``source`` (InputFileError) or are ConfigurationError for arrays."""
    def fail(problem: str):
        return InputFileError(source, problem) if source is not None else ConfigurationError(f"cube: {problem}")

    c = np.asarray(cube)
    wl = np.asarray(wavelength_nm)
    if c.ndim != 3 or min(c.shape) < 1:
        raise fail(f"'cube' must have shape (H, W, B), got {c.shape}")
    if c.dtype.kind not in "uif" or wl.dtype.kind not in "uif":
        raise fail(f"'cube' and 'wavelength_nm' must be numeric, got {c.dtype} and {wl.dtype}")
    if wl.ndim != 1 or wl.size != c.shape[2]:
        raise fail(f"'wavelength_nm' must have shape ({c.shape[2]},) to match the cube's bands, got {wl.shape}")
    if wl.size < 2:
        raise fail("the cube needs at least 2 bands")
    wl = wl.astype(np.float64)
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise fail("'wavelength_nm' must be finite and strictly increasing")
    c = np.ascontiguousarray(c, dtype=np.float32)
    if not np.all(np.isfinite(c)):
        raise fail("'cube' contains NaN or infinite values")
    lo, hi = float(c.min()), float(c.max())
    if lo < -RANGE_TOLERANCE or hi > 1.0 + RANGE_TOLERANCE:
        raise fail(f"reflectances must lie in 0..1; found {lo:g}..{hi:g}")
    return np.clip(c, 0.0, 1.0), wl


class CubeOnWallScene(Scene):
    """A reflectance cube on a wall of a :class:`ProceduralOutdoorScene` (see the module docstring).

    Parameters
    ----------
    cube
        A ``.npz`` / ENVI file, or a pair ``(cube (H, W, B), wavelength_nm (B,))``.
    base
        The scene to hang it in (default ``ProceduralOutdoorScene()``); its wavelength grid is used.
    wall
        Name of the base scene's box to hang it on.
    lon_deg, lat_deg
        Direction from the origin to the panel's centre; the ray must hit a vertical face of ``wall``.
    width_m
        Panel width; the height follows the cube's aspect ratio (square texels).
    """

    kind = "cube-on-wall"
    #: Renderers pass ``ray_spread_rad`` (module docstring, "Texture filtering").
    ray_footprint = True

    def __init__(self, cube, base: ProceduralOutdoorScene | None = None, wall: str = "near wall",
                 lon_deg: float = -40.0, lat_deg: float = 5.0, width_m: float = 1.2):
        base = ProceduralOutdoorScene() if base is None else base
        super().__init__(base.wavelength_nm)
        self.base = base
        if isinstance(cube, (str, Path)):
            self.source = str(cube)
            data, wl = load_reflectance_cube(cube)
            where: str | Path | None = cube
        else:
            self.source = "<array>"
            if not (isinstance(cube, (tuple, list)) and len(cube) == 2):
                raise ConfigurationError("cube must be a file path or a pair (cube (H, W, B), wavelength_nm (B,))")
            data, wl = check_cube(cube[0], cube[1])
            where = None
        try:
            self._resample = resample_matrix(wl, self.wavelength_nm)  # (n, B)
        except ConfigurationError as exc:
            msg = f"the cube's bands do not cover the scene's wavelength grid: {exc}"
            raise (InputFileError(where, msg) if where is not None else ConfigurationError(msg)) from None
        self.cube_wavelength_nm = wl
        self.cube_shape = data.shape
        self._texels = data.reshape(-1, data.shape[2])
        if not width_m > 0:
            raise ConfigurationError(f"width_m must be positive, got {width_m}")
        self.params = {"source": self.source, "wall": wall, "lon_deg": float(lon_deg), "lat_deg": float(lat_deg),
                       "width_m": float(width_m)}
        self._place(wall, lon_deg, lat_deg, float(width_m))
        self._bands = BandProjectionCache()
        self._reflectance_table: np.ndarray | None = None

    # -- placement --------------------------------------------------------------------------------
    def _place(self, wall: str, lon_deg: float, lat_deg: float, width_m: float) -> None:
        names = [b.name for b in self.base.boxes]
        if wall not in names:
            raise ConfigurationError(f"no box named {wall!r} in the base scene; boxes: {names}")
        self.wall_id = names.index(wall) + 1
        ray = lonlat_to_direction(lon_deg, lat_deg).astype(np.float32)[None]
        rec = self.base.shade(ray, np.zeros(3))
        if rec.obj[0] != self.wall_id:
            raise ConfigurationError(f"the direction lon {lon_deg}°, lat {lat_deg}° does not meet the {wall!r}")
        self.normal_id = int(rec.normal_id[0])
        normal = self.base.normals[self.normal_id]
        if abs(normal[1]) > 0.5:
            raise ConfigurationError(f"lon {lon_deg}°, lat {lat_deg}° meets the top or bottom of {wall!r}; "
                                     "the cube needs a vertical face")
        self.normal = normal
        self.right = np.cross([0.0, 1.0, 0.0], normal)
        self.up = np.array([0.0, 1.0, 0.0])
        self.centre_m = float(rec.t_m[0]) * lonlat_to_direction(lon_deg, lat_deg)
        h, w = self.cube_shape[:2]
        self.half_width_m = 0.5 * width_m
        self.half_height_m = 0.5 * width_m * h / w
        box = self.base.boxes[self.wall_id - 1]
        lo, hi = np.asarray(box.lo_m), np.asarray(box.hi_m)
        for corner in (-1, 1):
            for vert in (-1, 1):
                p = self.centre_m + corner * self.half_width_m * self.right + vert * self.half_height_m * self.up
                if np.any(p < lo - 1e-6) or np.any(p > hi + 1e-6):
                    raise ConfigurationError(f"a {2 * self.half_width_m:g} × {2 * self.half_height_m:g} m panel "
                                             f"centred there does not fit on the face of {wall!r}")

    def texel_centre_m(self, row: int, col: int) -> np.ndarray:
        """World position (m) of the centre of texel ``(row, col)``."""
        h, w = self.cube_shape[:2]
        u = -self.half_width_m + (col + 0.5) * (2.0 * self.half_width_m / w)
        v = self.half_height_m - (row + 0.5) * (2.0 * self.half_height_m / h)
        return self.centre_m + u * self.right + v * self.up

    def reflectance(self, row: int, col: int) -> np.ndarray:
        """Texel ``(row, col)``'s reflectance on the scene's wavelength grid."""
        w = self.cube_shape[1]
        return self._resample @ self._texels[row * w + col].astype(np.float64)

    # -- rendering --------------------------------------------------------------------------------
    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0), sun_disk: bool = True,
                          ray_spread_rad=None) -> np.ndarray:
        """Spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) ``(N, n)`` float32: the base scene with the cube on its wall
        (``sun_disk=False``: without the sun's disk, see :meth:`sun_disk`; ``ray_spread_rad``, scalar or
        ``(N,)``: each ray's angular footprint, module docstring)."""
        dl = self.base.daylight
        light = np.stack([dl.sun_spectrum, dl.sky_spectrum]) / math.pi  # (2, n)
        table = self._texel_table()

        def panel(box, sun, sky):
            refl = box_mean(table, *box).astype(np.float32) @ self._resample.T.astype(np.float32)
            return refl * (sun[:, None] * light[0].astype(np.float32) + sky[:, None] * light[1].astype(np.float32))

        return self._render(directions, origin_m, self.base.material_table, panel, sun_disk,
                            ray_spread_rad=ray_spread_rad)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0), sun_disk: bool = True,
                      ray_spread_rad=None) -> np.ndarray:
        """``spectral_radiance @ sensitivity.T`` via band projections of the materials and of every texel."""
        return self._band_render(directions, sensitivity, origin_m, sun_disk, ray_spread_rad=ray_spread_rad)

    def band_radiance_and_depth(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0),
                                sun_disk: bool = True, ray_spread_rad=None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`band_radiance` and each ray's hit distance (m; inf for the sky) from the same ray casts (the
        panel is flush with its wall: it adds no depth edge)."""
        return self._band_render(directions, sensitivity, origin_m, sun_disk, with_depth=True,
                                 ray_spread_rad=ray_spread_rad)

    def _band_render(self, directions, sensitivity, origin_m, sun_disk: bool, with_depth: bool = False,
                     ray_spread_rad=None):
        s = self.check_sensitivity(sensitivity)
        base_table = self.base.band_table(s)
        tex_sun, tex_sky = self._bands.get(s, self._project_texels)

        def panel(box, sun, sky):
            a = box_mean(tex_sun, *box)
            b = box_mean(tex_sky, *box)
            return (a * sun[:, None] + b * sky[:, None]).astype(np.float32)

        return self._render(directions, origin_m, base_table, panel, sun_disk, with_depth, ray_spread_rad)

    def sun_disk(self):
        """The base scene's sun (the panel hangs on a wall and hides none of the sky)."""
        return self.base.sun_disk()

    def _project_texels(self, sensitivity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Summed-area tables of every texel's band radiance per unit of sun and of sky irradiance."""
        dl = self.base.daylight
        to_bands = self._resample.T  # (B, n)
        sun = (to_bands * (dl.sun_spectrum / math.pi)) @ sensitivity.T  # (B, m)
        sky = (to_bands * (dl.sky_spectrum / math.pi)) @ sensitivity.T
        h, w = self.cube_shape[:2]
        t = self._texels.astype(np.float64)
        return summed_area_table((t @ sun).reshape(h, w, -1)), summed_area_table((t @ sky).reshape(h, w, -1))

    def _texel_table(self) -> np.ndarray:
        """Summed-area table of the texels' reflectances in the cube's own bands (built once)."""
        if self._reflectance_table is None:
            self._reflectance_table = summed_area_table(self._texels.reshape(self.cube_shape))
        return self._reflectance_table

    def _render(self, directions, origin_m, table, panel, sun_disk: bool = True, with_depth: bool = False,
                ray_spread_rad=None):
        """Radiance ``(..., c)``; ``with_depth``: also the rays' hit distances ``(...)`` (m, inf for the sky)."""
        d, lead = as_directions(directions)
        o = as_origin(origin_m)
        spread = None if ray_spread_rad is None else np.broadcast_to(
            np.asarray(ray_spread_rad, np.float64).reshape(-1), (d.shape[0],))
        out = np.empty((d.shape[0], table.shape[1] // 2), dtype=np.float32)
        depth = np.empty(d.shape[0], dtype=np.float32) if with_depth else None
        for b0 in range(0, d.shape[0], RAY_BLOCK):
            b1 = min(d.shape[0], b0 + RAY_BLOCK)
            rec = self.base.shade(d[b0:b1], o, sun_disk)
            block = combine(rec, table)
            sel, box = self._panel_hits(rec, d[b0:b1], o, None if spread is None else spread[b0:b1])
            if sel.size:
                block[sel] = panel(box, rec.sun[sel], rec.sky[sel])
            out[b0:b1] = block
            if depth is not None:
                depth[b0:b1] = rec.t_m
        out = out.reshape(*lead, out.shape[1])
        return (out, depth.reshape(lead)) if with_depth else out

    def _panel_hits(self, rec, d: np.ndarray, o: np.ndarray, spread: np.ndarray | None):
        """Rays on the panel and the texel-space rectangles ``(x0, x1, y0, y1)`` (each ``(P,)``, texel units,
        column 0 / row 0 at 0) their footprints cover (module docstring; zero-sized without a spread)."""
        on = np.flatnonzero((rec.obj == self.wall_id) & (rec.normal_id == self.normal_id))
        empty = np.zeros(0, np.int64)
        no_box = (np.zeros(0),) * 4
        if on.size == 0:
            return empty, no_box
        t_m = rec.t_m[on].astype(np.float64)
        rel = (o - self.centre_m) + t_m[:, None] * d[on].astype(np.float64)
        u = rel @ self.right
        v = rel @ self.up
        inside = (np.abs(u) <= self.half_width_m) & (np.abs(v) <= self.half_height_m)
        if not inside.any():
            return empty, no_box
        sel, u, v, t_m = on[inside], u[inside], v[inside], t_m[inside]
        h, w = self.cube_shape[:2]
        per_m_x, per_m_y = w / (2.0 * self.half_width_m), h / (2.0 * self.half_height_m)
        x = (u + self.half_width_m) * per_m_x
        y = (self.half_height_m - v) * per_m_y
        if spread is None:
            hx = hy = np.zeros_like(x)
        else:
            half_u_m, half_v_m = self._footprint_half_m(d[sel].astype(np.float64), t_m, spread[sel])
            hx, hy = half_u_m * per_m_x, half_v_m * per_m_y
        return sel, (np.clip(x - hx, 0, w), np.clip(x + hx, 0, w), np.clip(y - hy, 0, h), np.clip(y + hy, 0, h))

    def _footprint_half_m(self, d: np.ndarray, t_m: np.ndarray, spread_rad: np.ndarray):
        """Half extents (m) along the panel's right and up axes of the footprint of rays ``d (P, 3)`` hitting
        it at distance ``t_m``, each standing for an angular square of side ``spread_rad``.  The square's edges
        map to the parallelogram of the ray differentials ``t (e − d (n·e)/(n·d))`` of two unit directions
        ``e`` across the ray (Igehy 1999); the rectangle has the parallelogram's spread along each axis
        (side ``sqrt(a_u² + b_u²)`` for edges ``a``, ``b``: exact when they lie along the axes)."""
        e1 = np.cross(d, self.up)
        e1 /= np.maximum(np.linalg.norm(e1, axis=1, keepdims=True), 1e-12)
        e2 = np.cross(d, e1)
        n_d = d @ self.normal
        n_d = np.where(np.abs(n_d) < 1e-6, 1e-6, n_d)
        g1 = e1 - d * ((e1 @ self.normal) / n_d)[:, None]
        g2 = e2 - d * ((e2 @ self.normal) / n_d)[:, None]
        scale = 0.5 * spread_rad * t_m
        return scale * np.hypot(g1 @ self.right, g2 @ self.right), scale * np.hypot(g1 @ self.up, g2 @ self.up)

    # -- reports ----------------------------------------------------------------------------------
    def colorchecker_patches(self, origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
        """The base scene's ColorChecker."""
        return self.base.colorchecker_patches(origin_m)

    def describe(self) -> dict:
        """Kind, the cube (file, shape, bands), where it hangs and the base scene's description."""
        h, w, b = self.cube_shape
        return {
            "kind": self.kind,
            "parameters": dict(self.params),
            "cube": {"source": self.source, "height_px": h, "width_px": w, "bands": b,
                     "wavelength_nm": [float(self.cube_wavelength_nm[0]), float(self.cube_wavelength_nm[-1])]},
            "panel": {"centre_m": self.centre_m.tolist(), "normal": self.normal.tolist(),
                      "width_m": 2 * self.half_width_m, "height_m": 2 * self.half_height_m},
            "radiance_units": self.radiance_units,
            "base": self.base.describe(),
        }
