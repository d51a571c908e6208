"""An indoor scene lit by one chosen light source: the ground truth for relighting (paper Sec. 6.2, Fig. 17).

A room 6 m × 3.2 m × 6 m (x, y, z; the head 1.5 m above the floor, 2.5 m from the south wall) with
Lambertian walls (0.7), ceiling (0.8) and floor (0.25).  Two ceiling panels (0.6 m × 1.2 m, luminance
``lamp_cd_m2``) light it; their spectrum is the chosen light source (``FL11``, ``LED-B3``, ``D65``, ``A``,
any colour-science light source, or a CSV), normalised to unit luminous quantity so radiances are absolute.
On the north wall (longitude 0) hang a ColorChecker with 10 cm patches (N. Ohta's reflectances), beside it
a flat 0.95 white reference 25 cm square (``describe()["white_reference"]``), and to the chart's right
(longitude ≈ +25°) a 1.2 m wide "painting" from a reflectance cube: any ``.npz`` / ENVI cube
(:func:`~omnispectral.sim.scenes.cube.load_reflectance_cube`; ``simulate --scene indoor --cube FILE``),
by default :func:`synthetic_painting` (pigments not in the relighting prior, mixed subtractively).  Each
texel is a Lambertian square (nearest texel, no interpolation: a texel is one row of the material table).

Light: a surface point of normal ``n`` receives ``E = Σ_lamps L A cos θ_p cos θ_lamp / d²`` from each
panel (small-source approximation, no shadows: nothing stands in the room) plus a uniform ambient
``ambient_lx`` of the same spectrum standing in for light reflected by the walls, so the whole room is
lit by one spectrum and relighting has an exact answer.  Radiance ``L(λ) = ρ(λ) E S(λ)/π``; the panels
themselves are seen at ``lamp_cd_m2 · S(λ)``.  Every ray's radiance is one scalar times one row
``P[k] = ρ_k S/π`` (or ``S`` for a lamp), so the band path projects ``P`` once per sensitivity.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.sim.scenes.base import (
    BandProjectionCache,
    Scene,
    as_origin,
    direction_to_lonlat,
    render_rows,
)
from omnispectral.sim.scenes.cube import check_cube, load_reflectance_cube
from omnispectral.sim.scenes.materials import colorchecker_reflectances
from omnispectral.sim.scenes.procedural import ChartBoard, chart_patches
from omnispectral.spectral.colour import cmfs_on_grid
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM, resample_matrix
from omnispectral.spectral.library import CALIBRATION_REFLECTANCE_SETS, load_illuminant, load_reflectances

__all__ = ["LAMPS_M", "LAMP_SIZE_M", "LIGHTS", "PAINTING_CENTRE_M", "PAINTING_MAX_HEIGHT_M", "PAINTING_WIDTH_M",
           "ROOM_HI_M", "ROOM_LO_M", "WHITE_CENTRE_M", "WHITE_HALF_M", "WHITE_REFLECTANCE", "IndoorScene",
           "light_spectrum", "synthetic_painting"]

ROOM_LO_M = (-3.0, -1.5, -2.5)
ROOM_HI_M = (3.0, 1.7, 3.5)
LAMPS_M = ((-1.2, 0.5), (1.2, 0.5))  # panel centres (x, z) on the ceiling
LAMP_SIZE_M = (0.6, 1.2)
WHITE_CENTRE_M = (0.9, 0.0)  # (x, y) on the north wall
WHITE_HALF_M = 0.125
WHITE_REFLECTANCE = 0.95
LIGHTS = ("FL11", "LED-B3", "D65", "A")
PAINTING_CENTRE_M = (-1.6, 0.1)  # (x, y) on the north wall: right of the chart as seen from the rig
PAINTING_WIDTH_M = 1.2
PAINTING_MAX_HEIGHT_M = 1.6


def synthetic_painting(height: int = 48, width: int = 64, wavelength_nm=None, seed: int = 0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """A reflectance cube ``(height, width, n)`` that looks like a painting: smooth regions of pigments mixed
    subtractively (weighted geometric mean of reflectances: absorbances add, as for transparent glazes
    layered over a white ground, Beer-Lambert).  The pigments are the CIE 13.3 test colour samples and the
    NIST CQS 9.0 samples (:data:`~omnispectral.spectral.library.CALIBRATION_REFLECTANCE_SETS`), which the relighting's
    reflectance prior does not contain; the weights are low-frequency random fields (``seed``) sharpened so
    that one or two pigments dominate each region."""
    wl = DEFAULT_WAVELENGTH_NM if wavelength_nm is None else np.asarray(wavelength_nm, float)
    pigments = np.vstack([load_reflectances(n).resample(wl).values for n in CALIBRATION_REFLECTANCE_SETS])
    log_p = np.log(np.clip(pigments, 0.01, 1.0))
    rng = np.random.default_rng(seed)
    coarse = rng.standard_normal((pigments.shape[0], 4, 5)).astype(np.float32)
    fields = np.stack([cv2.resize(c, (width, height), interpolation=cv2.INTER_CUBIC) for c in coarse], axis=-1)
    wts = np.exp(4.0 * (fields - fields.max(axis=-1, keepdims=True)))
    wts /= wts.sum(axis=-1, keepdims=True)
    cube = np.exp(wts @ log_p)
    return np.clip(cube, 0.0, 1.0).astype(np.float32), wl.copy()


def light_spectrum(light: str, wavelength_nm: np.ndarray) -> np.ndarray:
    """A light source's spectrum on the grid, scaled so that ``683 Σ S ȳ Δλ = 1`` (unit luminous quantity)."""

    s = np.asarray(load_illuminant(light).resample(wavelength_nm).values[0], float)
    y = cmfs_on_grid(wavelength_nm)[1]
    lum = 683.0 * float(s @ (y * np.gradient(wavelength_nm)))
    if lum <= 0:
        raise ConfigurationError(f"light source {light!r} has no luminous output on {wavelength_nm[0]:g}-"
                                 f"{wavelength_nm[-1]:g} nm")
    return s / lum


class IndoorScene(Scene):
    """The indoor scene (module docstring).

    Parameters
    ----------
    light : str
        The light source of the panels and the ambient light: ``FL11``, ``LED-B3``, ``D65``, ``A``, any
        colour-science light source, or an illuminant CSV (:func:`light_spectrum`).
    wavelength_nm : array_like, optional
        The scene's wavelength grid (nm; default 400-700 nm every 5 nm).
    lamp_cd_m2 : float
        Luminance of the two ceiling panels (cd/m²).
    ambient_lx : float
        Uniform ambient illuminance of the same spectrum (lx), standing in for inter-reflections.
    chart_patch_m : float
        Side of a ColorChecker patch (m); the gaps are a fifth of it.
    painting : str or pathlib.Path or tuple, optional
        The painting's reflectance cube: a ``.npz`` / ENVI file, ``(cube, wavelength_nm)`` arrays, or ``None``
        for :func:`synthetic_painting`.

    Attributes
    ----------
    spectrum : numpy.ndarray
        ``(n,)`` the light's spectrum scaled to unit luminous quantity (``683 Σ S ȳ Δλ = 1``).
    patch_names, patch_reflectance
        The 24 ColorChecker patches' names and reflectances ``(24, n)``.
    painting_reflectance : numpy.ndarray
        ``(h, w, n)`` the painting's reflectance on the scene's grid.

    Raises
    ------
    ConfigurationError
        For a light with no luminous output on the grid, or painting arrays that do not cover it.
    InputFileError
        For a painting file that cannot be read or does not cover the grid.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 6.2, Fig. 17 (an indoor scene with an art painting, its illumination
       measured from a white reference in the scene, relit under CIE illuminant A).
    .. [2] CIE 015:2018, Colorimetry, 4th ed. (the light sources; the luminous quantity through ȳ of the CIE
       1931 observer).
    """

    kind = "indoor"

    def __init__(self, light: str = "FL11", wavelength_nm=None, lamp_cd_m2: float = 3000.0,
                 ambient_lx: float = 60.0, chart_patch_m: float = 0.10, painting=None):
        super().__init__(DEFAULT_WAVELENGTH_NM if wavelength_nm is None else wavelength_nm)
        self.light = str(light)
        self.spectrum = light_spectrum(self.light, self.wavelength_nm)
        self.lamp_cd_m2, self.ambient_lx = float(lamp_cd_m2), float(ambient_lx)
        self.lo, self.hi = np.array(ROOM_LO_M), np.array(ROOM_HI_M)
        self.patch_names, self.patch_reflectance = colorchecker_reflectances(self.wavelength_nm)
        self.chart = ChartBoard(np.array([0.0, 0.0, self.hi[2]]), np.array([0.0, 0.0, -1.0]), np.array([-1.0, 0, 0]),
                                np.array([0.0, 1.0, 0.0]), chart_patch_m, 0.2 * chart_patch_m)
        n = self.wavelength_nm.size
        self._set_painting(painting)
        # rows: 0 lamp, 1 wall, 2 ceiling, 3 floor, 4 white reference, 5 chart frame, 6.. patches, then texels
        refl = np.vstack([np.zeros(n), np.full(n, 0.7), np.full(n, 0.8), np.full(n, 0.25),
                          np.full(n, WHITE_REFLECTANCE), self.patch_reflectance[-1], self.patch_reflectance,
                          self.painting_reflectance.reshape(-1, n)])
        self._painting_row0 = 6 + len(self.patch_reflectance)
        table = refl * self.spectrum / math.pi
        table[0] = self.spectrum
        self._table64 = table
        self._table32 = table.astype(np.float32)
        self._bands = BandProjectionCache()

    def _set_painting(self, painting) -> None:
        """The painting's cube on the scene's grid (``painting``: ``None``, a cube file or ``(cube, wl_nm)``)."""
        if painting is None:
            cube, wl = synthetic_painting(wavelength_nm=self.wavelength_nm)
            source, where = "synthetic_painting (CIE 13.3 + NIST CQS pigments)", None
        elif isinstance(painting, (tuple, list)):
            (cube, wl), source, where = check_cube(*painting), "<array>", None
        else:
            (cube, wl), source, where = load_reflectance_cube(painting), str(painting), painting
        try:
            m = resample_matrix(wl, self.wavelength_nm)
        except ConfigurationError as exc:
            msg = f"the painting's bands do not cover the scene's wavelength grid: {exc}"
            raise (InputFileError(where, msg) if where is not None else ConfigurationError(msg)) from None
        h, w = cube.shape[:2]
        self.painting_reflectance = (cube.reshape(-1, cube.shape[2]).astype(np.float64) @ m.T).reshape(h, w, -1)
        self.painting_source = source
        width_m = min(PAINTING_WIDTH_M, PAINTING_MAX_HEIGHT_M * w / h)
        self.painting_half_m = (0.5 * width_m, 0.5 * width_m * h / w)  # (half width, half height)
        self.painting_centre_m = np.array([PAINTING_CENTRE_M[0], PAINTING_CENTRE_M[1], ROOM_HI_M[2]])

    def painting_texel(self, p: np.ndarray) -> np.ndarray:
        """Texel index (row-major) of points ``(N, 3)`` on the north wall, -1 off the painting.  Row 0 is the top,
        column 0 the left as seen from the rig (+x is to the left)."""
        h, w = self.painting_reflectance.shape[:2]
        hw, hh = self.painting_half_m
        u = self.painting_centre_m[0] - p[:, 0]  # to the right as seen from the room
        v = p[:, 1] - self.painting_centre_m[1]
        inside = (np.abs(u) < hw) & (np.abs(v) < hh)
        col = np.clip(np.floor((u + hw) / (2 * hw) * w), 0, w - 1).astype(np.int64)
        row = np.clip(np.floor((hh - v) / (2 * hh) * h), 0, h - 1).astype(np.int64)
        return np.where(inside, row * w + col, -1)

    def painting_cells(self, rows: int = 6, cols: int = 8, origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
        """The painting cut into ``rows × cols`` cells, like chart patches: centre direction, angular half-size (of
        the cell's shorter side) and the mean reflectance of the texels whose centres lie in the cell."""
        h, w = self.painting_reflectance.shape[:2]
        hw, hh = self.painting_half_m
        o = as_origin(origin_m)
        tr = (np.arange(h) + 0.5) / h * rows  # texel centre in cell units
        tc = (np.arange(w) + 0.5) / w * cols
        out = []
        for i in range(rows):
            for j in range(cols):
                sel = self.painting_reflectance[(tr >= i) & (tr < i + 1)][:, (tc >= j) & (tc < j + 1)]
                if sel.size == 0:
                    raise ConfigurationError(f"the painting ({h}×{w} texels) is too small for {rows}×{cols} cells")
                c = self.painting_centre_m + np.array([-(-hw + (j + 0.5) * 2 * hw / cols),
                                                       hh - (i + 0.5) * 2 * hh / rows, 0.0])
                rel = c - o
                dist = float(np.linalg.norm(rel))
                lon, lat = direction_to_lonlat(rel)
                out.append({"index": i * cols + j, "name": f"cell r{i} c{j}", "lon_deg": float(lon),
                            "lat_deg": float(lat), "distance_m": dist, "centre_m": [float(x) for x in c],
                            "half_size_deg": math.degrees(math.atan(min(hw / cols, hh / rows) / dist)),
                            "wavelength_nm": self.wavelength_nm.tolist(),
                            "reflectance": sel.reshape(-1, sel.shape[-1]).mean(axis=0).tolist()})
        return out

    # -- the interface ----------------------------------------------------------------------------
    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        return self._render(directions, origin_m, self._table32)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        s = self.check_sensitivity(sensitivity)
        table = self._bands.get(s, lambda m: (self._table64 @ m.T).astype(np.float32))
        return self._render(directions, origin_m, table)

    def band_radiance_and_depth(self, directions, sensitivity,
                                origin_m=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`band_radiance` and each ray's distance to the room's surface (m) from the same ray casts."""
        s = self.check_sensitivity(sensitivity)
        table = self._bands.get(s, lambda m: (self._table64 @ m.T).astype(np.float32))
        hits: list[np.ndarray] = []

        def shade(d, o):
            row, weight, t = self.shade_with_distance(d, o)
            hits.append(t)
            return row, weight

        bands = render_rows(directions, origin_m, table, shade)
        return bands, np.concatenate(hits).astype(np.float32).reshape(bands.shape[:-1])

    def _render(self, directions, origin_m, table: np.ndarray) -> np.ndarray:
        return render_rows(directions, origin_m, table, self.shade)

    # -- tracing ----------------------------------------------------------------------------------
    def shade(self, d: np.ndarray, o: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Material row and radiance weight (lx for surfaces, cd/m² for lamps) of unit rays from ``o``."""
        return self.shade_with_distance(d, o)[:2]

    def shade_with_distance(self, d: np.ndarray, o: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`shade` and each ray's distance (m) to the surface it meets."""
        if np.any(o <= self.lo) or np.any(o >= self.hi):
            raise ConfigurationError(f"the viewpoint {o.tolist()} is outside the room")
        with np.errstate(divide="ignore", invalid="ignore"):
            t_axes = np.where(d > 0, (self.hi - o) / d, np.where(d < 0, (self.lo - o) / d, np.inf))
        axis = np.argmin(t_axes, axis=1)
        t = t_axes[np.arange(d.shape[0]), axis]
        p = o + t[:, None] * d
        positive = d[np.arange(d.shape[0]), axis] > 0
        normal = np.zeros_like(d)
        normal[np.arange(d.shape[0]), axis] = np.where(positive, -1.0, 1.0)  # facing into the room
        row = np.ones(d.shape[0], np.int64)  # walls
        row[(axis == 1) & positive] = 2
        row[(axis == 1) & ~positive] = 3
        north = (axis == 2) & positive
        ch = self.chart
        rel = p[north] - ch.centre_m
        u, v = rel @ ch.right, rel @ ch.up
        on_board = (np.abs(u) <= ch.half_width_m) & (np.abs(v) <= ch.half_height_m)
        patch = ch.patch_index(u, v)
        idx = np.flatnonzero(north)
        row[idx[on_board]] = np.where(patch[on_board] >= 0, 6 + patch[on_board], 5)
        on_white = (np.abs(p[idx, 0] - WHITE_CENTRE_M[0]) <= WHITE_HALF_M) & (
            np.abs(p[idx, 1] - WHITE_CENTRE_M[1]) <= WHITE_HALF_M)
        row[idx[on_white]] = 4
        texel = self.painting_texel(p[idx])
        row[idx[texel >= 0]] = self._painting_row0 + texel[texel >= 0]
        weight = self.irradiance_lx(p, normal)
        ceiling = (axis == 1) & positive
        for cx, cz in LAMPS_M:
            lamp = ceiling & (np.abs(p[:, 0] - cx) <= LAMP_SIZE_M[0] / 2) & (np.abs(p[:, 2] - cz) <= LAMP_SIZE_M[1] / 2)
            row[lamp] = 0
            weight[lamp] = self.lamp_cd_m2
        return row, weight, t

    def irradiance_lx(self, points_m: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Illuminance (lx) on surfaces: the two panels as small sources plus the ambient term."""
        e = np.full(points_m.shape[0], self.ambient_lx)
        area = LAMP_SIZE_M[0] * LAMP_SIZE_M[1]
        for cx, cz in LAMPS_M:
            v = np.array([cx, self.hi[1], cz]) - points_m
            dist2 = np.einsum("ij,ij->i", v, v)
            dist = np.sqrt(dist2)
            cos_p = np.einsum("ij,ij->i", v, normals) / dist
            cos_l = v[:, 1] / dist  # the panel faces down (-Y): cos with the direction from it to the point
            e += np.where((cos_p > 0) & (cos_l > 0), self.lamp_cd_m2 * area * cos_p * cos_l / dist2, 0.0)
        return e

    # -- what a report needs ----------------------------------------------------------------------
    def colorchecker_patches(self, origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
        """The 24 patches: name, centre direction from ``origin_m``, angular half-size, reflectance."""
        return chart_patches(self.chart, self.patch_names, self.patch_reflectance, self.wavelength_nm, origin_m)

    def white_reference(self, origin_m=(0.0, 0.0, 0.0)) -> dict:
        """Direction, angular half-size and reflectance of the white reference seen from ``origin_m``."""
        c = np.array([WHITE_CENTRE_M[0], WHITE_CENTRE_M[1], self.hi[2]]) - as_origin(origin_m)
        lon, lat = direction_to_lonlat(c)
        return {"lon_deg": float(lon), "lat_deg": float(lat), "reflectance": WHITE_REFLECTANCE,
                "half_size_deg": math.degrees(math.atan(WHITE_HALF_M / float(np.linalg.norm(c))))}

    def describe(self) -> dict:
        return {"kind": self.kind, "light": self.light, "lamp_cd_m2": self.lamp_cd_m2, "ambient_lx": self.ambient_lx,
                "room_m": {"lo": list(ROOM_LO_M), "hi": list(ROOM_HI_M)},
                "lamps": [{"centre_m": [x, ROOM_HI_M[1], z], "size_m": list(LAMP_SIZE_M)} for x, z in LAMPS_M],
                "chart": {"reflectances": "ColorChecker N Ohta", "centre_m": self.chart.centre_m.tolist(),
                          "patch_m": self.chart.patch_m},
                "white_reference": self.white_reference(),
                "painting": {"source": self.painting_source, "texels": list(self.painting_reflectance.shape[:2]),
                             "centre_m": self.painting_centre_m.tolist(),
                             "size_m": [2 * self.painting_half_m[0], 2 * self.painting_half_m[1]]},
                "wavelength_nm": {"start": float(self.wavelength_nm[0]), "stop": float(self.wavelength_nm[-1]),
                                  "count": int(self.wavelength_nm.size)},
                "radiance_units": self.radiance_units}
