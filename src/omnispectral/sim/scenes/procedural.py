"""A procedural, spectral, sunlit outdoor scene: clear sky, HDR sun, ground, buildings, a ColorChecker.

The world (metres, frame of :mod:`omnispectral.sim.scenes.base`) has its origin at the head's
rotation centre, ``ground_y_m`` (default 1.5 m) above a flat, infinite ground: pavement within
8 m, grass beyond.  Axis-aligned boxes stand on it: buildings at 20-40 m, a free-standing concrete
wall 4 m away (where :class:`~omnispectral.sim.scenes.cube.CubeOnWallScene` hangs its cube), a
hedge, and optionally a painted post 1.5 m from the rig so that the two cameras, 60 mm apart, see
parallax.  A 24-patch ColorChecker (N. Ohta's reflectances) on a board faces the rig 2.5 m away at
longitude 30°, latitude -15°, its 50 mm patches ≈1.1° wide (≈23 px in a 7260 × 3630 panorama).
A horizontal diffuse white reference plate (0.3 × 0.3 m, flat reflectance 0.95: a stand-in for a
Spectralon-like target, which is ≈0.95-0.99 and close to flat over 400-700 nm) lies on a small stand
0.1 m above the ground, 1.2 m from the rig at longitude 160° (south-south-east of the head with the
default ``north_lon_deg``: no object shadows it at 08:00-17:00 on the default day nor at noon on the
solstice); ``describe()["reference"]`` gives its centre direction from the head's centre, normal and
reflectance, as a user would write them down (:mod:`omnispectral.product.sun_reference` measures the sun
from it).  Unlike the other surfaces (below), the plate is lit by what it actually sees: the sun (with
the shadow test) plus the scene's own radiance gathered over its upper hemisphere (sky without the disk,
buildings where they hide the sky, other surfaces as rendered: one bounce), so that its radiance is that
of a real reference under the scene's light field, not of one under an unobstructed sky dome.

Light (see :mod:`omnispectral.sim.scenes.sky`): a sun disk of 0.533° with the IES clear-sky
direct illuminance and a CIE type-12 clear sky, with D-series spectra whose CCT follows the sun.
Rays that fall in the disk see its luminance; renderers that must hold the sun's energy exactly
(the simulator's ground truth and camera frames) render with ``sun_disk=False`` and add the disk
from :meth:`ProceduralOutdoorScene.sun_disk` (:mod:`omnispectral.imaging.sundisk`).
Surfaces are Lambertian: ``L(λ) = ρ(λ)/π · (E_sun cos θ · V + E_sky(n)) `` with ``V`` the sun's
visibility from the point (a shadow ray against every box and the chart board) and ``E_sky(n)``
the illuminance of the unoccluded sky dome on a surface of normal ``n`` (no ambient occlusion, no
light reflected between surfaces).

Every ray's radiance is therefore ``a · P[k] + b · Q[k]`` with the material ``k``, ``P[k] =
ρ_k S_sun / π``, ``Q[k] = ρ_k S_sky / π`` (for the sky: ``P = S_sun``, ``Q = S_sky``) and two
scalars ``a`` (sun illuminance in lx, or the sun disk's luminance) and ``b`` (sky illuminance, or
the sky's luminance).  The band path projects ``P`` and ``Q`` on the sensitivities once and per
ray combines two scalars with two looked-up rows, so its cost does not depend on the number of
wavelengths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.sim.scenes.base import (
    RAY_BLOCK,
    BandProjectionCache,
    Scene,
    SunDisk,
    as_directions,
    as_origin,
    direction_to_lonlat,
    lonlat_to_direction,
)
from omnispectral.sim.scenes.materials import SCENE_MATERIALS, choose_materials, colorchecker_reflectances
from omnispectral.sim.scenes.raycast import N_PY, intersect_board, intersect_boxes, intersect_ground, sun_blocked
from omnispectral.sim.scenes.sky import ClearSkyDaylight
from omnispectral.spectral.curves import DEFAULT_WAVELENGTH_NM

__all__ = ["CHIBA_LATITUDE_DEG", "CHIBA_LONGITUDE_DEG", "DEFAULT_DAY_OF_YEAR", "GROUND_ID", "JST_UTC_OFFSET_H",
           "PAVEMENT_RADIUS_M", "REFERENCE_DISTANCE_M", "REFERENCE_HEIGHT_M", "REFERENCE_LON_DEG",
           "REFERENCE_MATERIAL", "REFERENCE_REFLECTANCE", "REFERENCE_SIZE_M", "REFERENCE_THICKNESS_M",
           "SKYLINE_DISTANCE_M", "SKYLINE_MAX_DEG", "SKY_ID", "Box", "ChartBoard", "ProceduralOutdoorScene",
           "ReferencePlate", "Shading", "SkylineProfile", "chart_patches", "combine", "facing_board",
           "reference_plate_at", "skyline_profile"]

#: Chiba University, Inage campus (the authors' institution; the paper's time-lapse is of "our
#: university campus", Sec. 5.4): latitude, longitude (east) and Japan Standard Time.
CHIBA_LATITUDE_DEG = 35.63
CHIBA_LONGITUDE_DEG = 140.10
JST_UTC_OFFSET_H = 9.0
#: Day 80 (21 March, near the vernal equinox): day length ≈ 12 h, so a 06:00-17:00 time-lapse is all daylight.
DEFAULT_DAY_OF_YEAR = 80
#: Radius (m) of the paved area around the rig; grass beyond.
PAVEMENT_RADIUS_M = 8.0
#: Distance (m) of the wooded hills on the horizon: far enough that the cameras' 60 mm baseline moves
#: them by 2·10⁻⁵ rad (0.004 px on the small rig, 0.04 px at full scale), i.e. they are "at infinity".
SKYLINE_DISTANCE_M = 3000.0

#: Object ids in the per-ray record.
SKY_ID = -1
GROUND_ID = 0


@dataclass(frozen=True)
class Box:
    """An axis-aligned box ``lo_m ≤ p ≤ hi_m`` (world metres) of one material."""

    name: str
    lo_m: tuple[float, float, float]
    hi_m: tuple[float, float, float]
    material: str

    def centre_m(self) -> np.ndarray:
        return 0.5 * (np.asarray(self.lo_m) + np.asarray(self.hi_m))

    def radius_m(self) -> float:
        return 0.5 * float(np.linalg.norm(np.asarray(self.hi_m) - np.asarray(self.lo_m)))


@dataclass(frozen=True)
class ChartBoard:
    """A ColorChecker board: 4 × 6 square patches on a thin rectangle facing the rig.

    ``right`` and ``up`` span the board as seen from the front (``normal`` points at the viewer);
    patch ``i`` (0 = dark skin, 23 = black) sits in row ``i // 6`` from the top and column ``i % 6``
    from the left, the standard layout.
    """

    centre_m: np.ndarray
    normal: np.ndarray
    right: np.ndarray
    up: np.ndarray
    patch_m: float
    gap_m: float
    rows: int = 4
    cols: int = 6

    @property
    def half_width_m(self) -> float:
        return 0.5 * (self.cols * self.patch_m + (self.cols + 1) * self.gap_m)

    @property
    def half_height_m(self) -> float:
        return 0.5 * (self.rows * self.patch_m + (self.rows + 1) * self.gap_m)

    def patch_centre_m(self, index: int) -> np.ndarray:
        r, c = divmod(index, self.cols)
        u = -self.half_width_m + self.gap_m + 0.5 * self.patch_m + c * (self.patch_m + self.gap_m)
        v = self.half_height_m - self.gap_m - 0.5 * self.patch_m - r * (self.patch_m + self.gap_m)
        return self.centre_m + u * self.right + v * self.up

    def patch_index(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Patch index at board coordinates ``(u, v)`` (m from the centre), -1 on the frame."""
        pitch = self.patch_m + self.gap_m
        cu = (u + self.half_width_m - self.gap_m) / pitch
        cv = (self.half_height_m - self.gap_m - v) / pitch
        c = np.floor(cu)
        r = np.floor(cv)
        on = ((cu - c) * pitch < self.patch_m) & ((cv - r) * pitch < self.patch_m)
        on &= (c >= 0) & (c < self.cols) & (r >= 0) & (r < self.rows)
        return np.where(on, r * self.cols + c, -1).astype(np.int32)


#: Highest elevation (deg) of the distant hills' silhouette.
SKYLINE_MAX_DEG = 3.5


@dataclass(frozen=True)
class SkylineProfile:
    """Silhouette elevation of distant hills as a sum of sines of longitude (degrees)."""

    base_deg: float
    amplitudes_deg: np.ndarray
    phases_rad: np.ndarray
    frequencies: np.ndarray

    def elevation_deg(self, lon_deg) -> np.ndarray:
        lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
        # an element-wise sum, not a BLAS product: the result must not depend on how many rays are traced at once
        waves = np.sin(np.multiply.outer(lon, self.frequencies) + self.phases_rad) * self.amplitudes_deg
        e = self.base_deg + waves.sum(axis=-1)
        return np.clip(e, 0.3, SKYLINE_MAX_DEG)

    def describe(self) -> dict:
        return {"base_deg": self.base_deg, "amplitudes_deg": self.amplitudes_deg.tolist(),
                "phases_rad": self.phases_rad.tolist(), "frequencies": self.frequencies.tolist()}


def skyline_profile(rng: np.random.Generator) -> SkylineProfile:
    """A random hill silhouette: ridges of 1/f amplitude at 3-40 cycles per turn, 0.3-3.5° high."""
    freq = np.arange(3, 41, dtype=np.float64)
    amp = rng.uniform(0.3, 1.0, freq.size) * 2.4 / freq ** 0.8
    return SkylineProfile(1.5, amp, rng.uniform(0, 2 * np.pi, freq.size), freq)


def chart_patches(chart: ChartBoard, names, reflectance: np.ndarray, wavelength_nm: np.ndarray,
                  origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
    """A chart's patches seen from ``origin_m``: name, centre direction, distance, angular half-size, reflectance."""
    o = as_origin(origin_m)
    out = []
    for i, name in enumerate(names):
        c = chart.patch_centre_m(i)
        rel = c - o
        dist = float(np.linalg.norm(rel))
        lon, lat = direction_to_lonlat(rel)
        out.append({"index": i, "name": name, "lon_deg": float(lon), "lat_deg": float(lat), "distance_m": dist,
                    "half_size_deg": math.degrees(math.atan(0.5 * chart.patch_m / dist)),
                    "half_size_m": 0.5 * chart.patch_m, "centre_m": [float(x) for x in c],
                    "normal": [float(x) for x in chart.normal], "wavelength_nm": wavelength_nm.tolist(),
                    "reflectance": reflectance[i].tolist()})
    return out


def facing_board(lon_deg: float, lat_deg: float, distance_m: float, patch_m: float, gap_m: float) -> ChartBoard:
    """A chart board centred ``distance_m`` from the origin at ``(lon_deg, lat_deg)``, facing the origin."""
    d = lonlat_to_direction(lon_deg, lat_deg)
    normal = -d
    right = np.cross(d, [0.0, 1.0, 0.0])
    if np.linalg.norm(right) < 1e-6:
        raise ConfigurationError("the chart cannot be placed straight up or down")
    right /= np.linalg.norm(right)
    up = np.cross(right, d)
    return ChartBoard(distance_m * d, normal, right, up / np.linalg.norm(up), patch_m, gap_m)


#: The white reference plate (module docstring): where it is, its size, height of its top above the ground,
#: its flat reflectance and its material's name.
REFERENCE_LON_DEG = 160.0
REFERENCE_DISTANCE_M = 1.2
REFERENCE_SIZE_M = 0.3
REFERENCE_HEIGHT_M = 0.1
REFERENCE_THICKNESS_M = 0.01
REFERENCE_REFLECTANCE = 0.95
REFERENCE_MATERIAL = "white reference"


@dataclass(frozen=True)
class ReferencePlate:
    """A horizontal square diffuse white plate (top face at ``centre_m``, normal +Y) on a thin stand."""

    centre_m: np.ndarray
    size_m: float
    thickness_m: float
    ground_y_m: float
    reflectance: float

    def boxes(self) -> list[Box]:
        c, h = self.centre_m, 0.5 * self.size_m
        top, bottom = float(c[1]), float(c[1]) - self.thickness_m
        return [Box("white reference", (c[0] - h, bottom, c[2] - h), (c[0] + h, top, c[2] + h), REFERENCE_MATERIAL),
                Box("white reference stand", (c[0] - 0.02, self.ground_y_m, c[2] - 0.02),
                    (c[0] + 0.02, bottom, c[2] + 0.02), "dark facade")]

    def describe(self, origin_m=(0.0, 0.0, 0.0)) -> dict:
        """Centre direction (from ``origin_m``, the head's centre by default), distance, normal, size and
        reflectance: what a user measures and writes down about their target."""
        rel = self.centre_m - as_origin(origin_m)
        lon, lat = direction_to_lonlat(rel)
        dist = float(np.linalg.norm(rel))
        # the plate's smallest angular half-extent seen from the origin (foreshortened along the line of sight)
        sin_el = abs(float(rel[1])) / dist
        half_deg = math.degrees(math.atan(0.5 * self.size_m * sin_el / dist))
        return {"name": "white reference", "kind": "horizontal diffuse plate, Spectralon-like stand-in",
                "lon_deg": float(lon), "lat_deg": float(lat), "distance_m": dist,
                "centre_m": [float(x) for x in self.centre_m], "normal": [0.0, 1.0, 0.0],
                "size_m": self.size_m, "height_above_ground_m": float(self.centre_m[1] - self.ground_y_m),
                "reflectance": self.reflectance, "half_size_deg": half_deg}


def reference_plate_at(lon_deg: float, distance_m: float, ground_y_m: float) -> ReferencePlate:
    """The white plate centred ``distance_m`` (horizontally) from the head's axis at longitude ``lon_deg``."""
    if not distance_m > REFERENCE_SIZE_M:
        raise ConfigurationError(f"reference_distance_m must exceed the plate's size ({REFERENCE_SIZE_M} m), "
                                 f"got {distance_m}")
    d = lonlat_to_direction(lon_deg, 0.0) * distance_m
    centre = np.array([d[0], ground_y_m + REFERENCE_HEIGHT_M, d[2]], np.float64)
    return ReferencePlate(centre, REFERENCE_SIZE_M, REFERENCE_THICKNESS_M, ground_y_m, REFERENCE_REFLECTANCE)


@dataclass
class Shading:
    """Per-ray record: material row, sun and sky weights, object hit, its face normal id and distance (m).

    ``sun`` and ``sky`` are illuminances (lx) on surfaces and luminances (cd/m²) in the sky;
    ``obj`` is -1 for the sky, 0 for the ground, ``1 + j`` for box ``j`` and ``len(boxes) + 1``
    for the chart board; ``normal_id`` indexes :attr:`ProceduralOutdoorScene.normals`.
    """

    material: np.ndarray
    sun: np.ndarray
    sky: np.ndarray
    obj: np.ndarray
    normal_id: np.ndarray
    t_m: np.ndarray


def combine(rec: Shading, table: np.ndarray) -> np.ndarray:
    """``sun · P[k] + sky · Q[k]`` per ray, from ``table = [P | Q]`` of shape ``(K, 2c)``."""
    c = table.shape[1] // 2
    rows = table[rec.material]
    out = rows[:, :c] * rec.sun[:, None]
    out += rows[:, c:] * rec.sky[:, None]
    return out


class ProceduralOutdoorScene(Scene):
    """The procedural outdoor scene (see the module docstring).

    Parameters
    ----------
    time_hhmm
        Local clock time (``"HH:MM"``, time zone ``utc_offset_h``).
    latitude_deg, longitude_deg, utc_offset_h
        Site; default Chiba (35.63° N, 140.10° E, JST).
    day_of_year
        1-366; default 80 (21 March).
    north_lon_deg
        Scene longitude that faces north (default 0: the head's pan 0 looks north, the noon sun is behind).
    near_object
        Add the painted post 1.5 m from the rig (parallax between the cameras).
    seed
        Chooses among the nearest measured reflectances and jitters building sizes; the scene is a
        deterministic function of its parameters.
    wavelength_nm
        Spectral grid (within 400-700 nm, the range of the measured reflectances); default 400-700 / 5 nm.
    ground_y_m
        Height of the ground (m, negative: below the head).
    chart_lon_deg, chart_lat_deg, chart_distance_m, chart_patch_m
        Where the ColorChecker is and how big its patches are.
    buildings
        The buildings, the near wall and the hedge; without them (and without ``skyline`` and
        ``near_object``) nothing stands above the horizon, so the whole sky and sun reach the head
        (tests of the daylight model's irradiances).
    skyline
        Wooded hills on the horizon, ``SKYLINE_DISTANCE_M`` away, whose silhouette (0.3-3.5° high,
        drawn with the seed) is the scene's texture at infinity, as distant terrain or buildings
        are in most real outdoor captures.
    reference_plate
        The horizontal white reference plate (module docstring; :class:`ReferencePlate`), on by default.
    reference_lon_deg, reference_distance_m
        Where the plate's centre is: its longitude and horizontal distance (m) from the head's axis.
    """

    kind = "procedural"

    def __init__(self, time_hhmm: str = "12:00", latitude_deg: float = CHIBA_LATITUDE_DEG,
                 longitude_deg: float = CHIBA_LONGITUDE_DEG, utc_offset_h: float = JST_UTC_OFFSET_H,
                 day_of_year: int = DEFAULT_DAY_OF_YEAR, north_lon_deg: float = 0.0, near_object: bool = True,
                 seed: int = 0, wavelength_nm=None, ground_y_m: float = -1.5, chart_lon_deg: float = 30.0,
                 chart_lat_deg: float = -15.0, chart_distance_m: float = 2.5, chart_patch_m: float = 0.05,
                 skyline: bool = True, buildings: bool = True, reference_plate: bool = True,
                 reference_lon_deg: float = REFERENCE_LON_DEG, reference_distance_m: float = REFERENCE_DISTANCE_M):
        super().__init__(DEFAULT_WAVELENGTH_NM if wavelength_nm is None else wavelength_nm)
        if ground_y_m >= 0:
            raise ConfigurationError(f"ground_y_m must be below the head (negative), got {ground_y_m}")
        self.params = {"time_hhmm": str(time_hhmm), "latitude_deg": float(latitude_deg),
                       "longitude_deg": float(longitude_deg), "utc_offset_h": float(utc_offset_h),
                       "day_of_year": int(day_of_year), "north_lon_deg": float(north_lon_deg),
                       "near_object": bool(near_object), "seed": int(seed), "ground_y_m": float(ground_y_m),
                       "chart_lon_deg": float(chart_lon_deg), "chart_lat_deg": float(chart_lat_deg),
                       "chart_distance_m": float(chart_distance_m), "chart_patch_m": float(chart_patch_m),
                       "skyline": bool(skyline), "buildings": bool(buildings),
                       "reference_plate": bool(reference_plate), "reference_lon_deg": float(reference_lon_deg),
                       "reference_distance_m": float(reference_distance_m)}
        self.ground_y_m = float(ground_y_m)
        self.daylight = ClearSkyDaylight(day_of_year, time_hhmm, latitude_deg, longitude_deg, utc_offset_h,
                                         north_lon_deg, self.wavelength_nm)
        rng = np.random.default_rng(seed)
        self.materials = choose_materials(SCENE_MATERIALS, self.wavelength_nm, rng)
        self.patch_names, self.patch_reflectance = colorchecker_reflectances(self.wavelength_nm)
        self.chart = facing_board(chart_lon_deg, chart_lat_deg, chart_distance_m, chart_patch_m, 0.2 * chart_patch_m)
        if chart_distance_m * math.sin(math.radians(-chart_lat_deg)) + self.chart.half_height_m >= -self.ground_y_m:
            raise ConfigurationError("the chart would reach below the ground; raise chart_lat_deg or move it closer")
        self.reference = (reference_plate_at(float(reference_lon_deg), float(reference_distance_m), self.ground_y_m)
                          if reference_plate else None)
        self.boxes = self._layout(rng, bool(near_object), bool(buildings))
        self.skyline = skyline_profile(np.random.default_rng([seed, 7])) if skyline else None
        self._build_tables()
        self._bands = BandProjectionCache()

    # -- construction -----------------------------------------------------------------------------
    def _layout(self, rng: np.random.Generator, near_object: bool, buildings: bool = True) -> list[Box]:
        """Buildings, the near wall, a hedge (unless ``buildings`` is false), the chart's stand and optionally the
        post (world metres)."""
        g = self.ground_y_m

        def jitter(h: float) -> float:
            return float(h * rng.uniform(0.9, 1.1))

        boxes = [] if not buildings else [
            Box("brick building", (-14.0, g, 22.0), (10.0, g + jitter(12.0), 34.0), "brick"),
            Box("white building", (-34.0, g, 14.0), (-16.0, g + jitter(18.0), 30.0), "white wall"),
            Box("dark building", (15.0, g, -34.0), (36.0, g + jitter(8.0), -14.0), "dark facade"),
            Box("near wall", (1.0, g, 4.0), (7.0, g + 3.0, 4.3), "concrete"),
            Box("hedge", (6.0, g, -9.0), (12.0, g + jitter(1.8), -6.0), "hedge"),
        ]
        back = self.chart.centre_m - 0.03 * self.chart.normal
        boxes.append(Box("chart stand", (back[0] - 0.015, g, back[2] - 0.015),
                         (back[0] + 0.015, float(self.chart.centre_m[1]), back[2] + 0.015), "dark facade"))
        if near_object:
            d = lonlat_to_direction(100.0, 0.0) * 1.5
            boxes.append(Box("post", (d[0] - 0.06, g, d[2] - 0.06), (d[0] + 0.06, 0.3, d[2] + 0.06), "painted post"))
        if self.reference is not None:
            boxes.extend(self.reference.boxes())
        return boxes

    def _build_tables(self) -> None:
        """Material rows (sky, surfaces, chart patches), per-object material, per-normal light."""
        names = ["sky", *[m.name for m in self.materials], "chart frame",
                 *[f"chart:{n}" for n in self.patch_names], REFERENCE_MATERIAL]
        frame = self.patch_reflectance[self.patch_names.index("black 2 (1.5 D)")]
        white = np.full(self.wavelength_nm.size, REFERENCE_REFLECTANCE)
        refl = np.vstack([np.zeros(self.wavelength_nm.size), *[m.reflectance for m in self.materials], frame,
                          self.patch_reflectance, white])
        self.material_names = tuple(names)
        self.material_reflectance = refl
        self._row = {n: i for i, n in enumerate(names)}
        self._first_patch_row = self._row[f"chart:{self.patch_names[0]}"]
        dl = self.daylight
        p = refl * dl.sun_spectrum / math.pi
        q = refl * dl.sky_spectrum / math.pi
        p[0], q[0] = dl.sun_spectrum, dl.sky_spectrum
        self._table64 = np.hstack([p, q])
        self._table32 = self._table64.astype(np.float32)
        # objects: 0 ground, 1..B boxes, B + 1 chart, B + 2 the distant hills
        self._chart_id = len(self.boxes) + 1
        self._skyline_id = len(self.boxes) + 2
        self._obj_row = np.array([self._row["pavement"], *[self._row[b.material] for b in self.boxes],
                                  self._row["chart frame"], self._row["hedge"]], dtype=np.int32)
        normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                            self.chart.normal, -self.chart.normal], dtype=np.float64)
        self.normals = normals
        self._sun_lx_by_normal = np.array([dl.sun_illuminance_lx(n) for n in normals], dtype=np.float32)
        self._sky_lx_by_normal = np.array([dl.sky_illuminance_lx(n) for n in normals], dtype=np.float32)
        self._box_lo = np.array([b.lo_m for b in self.boxes], dtype=np.float64)
        self._box_hi = np.array([b.hi_m for b in self.boxes], dtype=np.float64)
        self._box_centre = np.array([b.centre_m() for b in self.boxes])
        self._box_radius = np.array([b.radius_m() for b in self.boxes])
        if self.reference is not None:
            self._light_reference()

    def _light_reference(self, n_mu: int = 384, n_phi: int = 768) -> None:
        """Light the white plate with what its top face sees (module docstring): its sky row becomes
        ``ρ E_gathered(λ) / (π E_sky,h)`` with ``E_gathered = ∫ L(ω) cos θ dω`` over its upper hemisphere, the
        scene's own radiance (sky without the sun's disk, and every surface as rendered), evaluated as ``π``
        times the mean over an ``n_mu × n_phi`` grid uniform in ``cos² θ`` and azimuth (cosine-weighted)."""
        dl = self.daylight
        sky_up = float(dl.sky_illuminance_lx(np.array([0.0, 1.0, 0.0])))
        if not sky_up > 0:
            return
        mu = np.sqrt((np.arange(n_mu) + 0.5) / n_mu)
        phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
        mu, phi = np.meshgrid(mu, phi, indexing="ij")
        sin_t = np.sqrt(1.0 - mu ** 2)
        d = np.stack([sin_t * np.cos(phi), mu, sin_t * np.sin(phi)], axis=-1).reshape(-1, 3)
        origin = self.reference.centre_m + np.array([0.0, 2e-3, 0.0])
        n = self.wavelength_nm.size
        k = self._table64.shape[0]
        sun_w, sky_w = np.zeros(k), np.zeros(k)
        d32 = d.astype(np.float32)
        for b0 in range(0, d32.shape[0], RAY_BLOCK):  # per material: Σ sun weights · P[k] + Σ sky weights · Q[k]
            rec = self.shade(d32[b0:b0 + RAY_BLOCK], origin, sun_disk=False)
            sun_w += np.bincount(rec.material, rec.sun.astype(np.float64), minlength=k)
            sky_w += np.bincount(rec.material, rec.sky.astype(np.float64), minlength=k)
        gathered = (math.pi / d.shape[0]) * (sun_w @ self._table64[:, :n] + sky_w @ self._table64[:, n:])
        row = self._row[REFERENCE_MATERIAL]
        self._table64[row, n:] = self.reference.reflectance * gathered / (math.pi * sky_up)
        self._table32 = self._table64.astype(np.float32)
        self.reference_gathered_spectrum = gathered

    # -- the interface ----------------------------------------------------------------------------
    def spectral_radiance(self, directions, origin_m=(0.0, 0.0, 0.0), sun_disk: bool = True) -> np.ndarray:
        """Spectral radiance (W·sr⁻¹·m⁻²·nm⁻¹) ``(N, n)`` float32 arriving at ``origin_m`` from ``directions``.

        ``sun_disk=False`` leaves the sun's disk out (the sky behind it is kept): the caller adds it
        exactly from :meth:`sun_disk`.
        """
        return self._render(directions, origin_m, self._table32, sun_disk)

    def band_radiance(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0), sun_disk: bool = True) -> np.ndarray:
        """``spectral_radiance @ sensitivity.T`` ``(N, m)`` float32 via per-material band projections."""
        return self._render(directions, origin_m, self.band_table(sensitivity), sun_disk)

    def band_radiance_and_depth(self, directions, sensitivity, origin_m=(0.0, 0.0, 0.0),
                                sun_disk: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`band_radiance` and each ray's hit distance (m; inf for the sky, the hills at
        ``SKYLINE_DISTANCE_M``) from the same ray casts."""
        return self._render(directions, origin_m, self.band_table(sensitivity), sun_disk, with_depth=True)

    def sun_disk(self) -> SunDisk | None:
        """The sun as a uniform disk (:class:`~omnispectral.sim.scenes.base.SunDisk`): direction, radius
        ``SUN_DIAMETER_DEG / 2``, spectral radiance ``L_sun · S_sun(λ)`` (disk luminance × unit-luminance
        spectrum) and the visibility of the sky; None once the sun has set (no direct light)."""
        dl = self.daylight
        if not dl.direct_normal_lx > 0:
            return None
        return SunDisk(np.asarray(dl.sun_direction, np.float64).copy(), float(dl.sun_radius_rad),
                       dl.sun_luminance_cd_m2 * self._table64[0, :self.wavelength_nm.size], self.sky_visible)

    def sky_visible(self, directions, origin_m=(0.0, 0.0, 0.0)) -> np.ndarray:
        """Whether rays from ``origin_m`` along ``directions (N, 3)`` reach the sky (hit no surface), ``(N,)`` bool."""
        d, lead = as_directions(directions)
        o = as_origin(origin_m)
        out = np.empty(d.shape[0], dtype=bool)
        for b0 in range(0, d.shape[0], RAY_BLOCK):
            b1 = min(d.shape[0], b0 + RAY_BLOCK)
            out[b0:b1] = self.trace(d[b0:b1], o)[1] == SKY_ID
        return out.reshape(lead)

    @property
    def material_table(self) -> np.ndarray:
        """``[P | Q]`` ``(K, 2n)`` float32: every material's spectral radiance per lx of sun and of sky (module
        docstring); a ray's spectral radiance is ``sun · P[k] + sky · Q[k]`` (:func:`combine`)."""
        return self._table32

    def band_table(self, sensitivity) -> np.ndarray:
        """:attr:`material_table` projected on ``sensitivity`` ``(m, n)``: ``(K, 2m)`` float32 (cached)."""
        return self._bands.get(self.check_sensitivity(sensitivity), self._project)

    def _project(self, sensitivity: np.ndarray) -> np.ndarray:
        n = self.wavelength_nm.size
        return np.hstack([self._table64[:, :n] @ sensitivity.T, self._table64[:, n:] @ sensitivity.T]).astype(
            np.float32)

    def _render(self, directions, origin_m, table: np.ndarray, sun_disk: bool = True, with_depth: bool = False):
        """Radiance ``(..., c)`` of ``table``'s rows; ``with_depth``: also the rays' hit distances ``(...)`` (m)."""
        d, lead = as_directions(directions)
        o = as_origin(origin_m)
        out = np.empty((d.shape[0], table.shape[1] // 2), dtype=np.float32)
        depth = np.empty(d.shape[0], dtype=np.float32) if with_depth else None
        for b0 in range(0, d.shape[0], RAY_BLOCK):
            b1 = min(d.shape[0], b0 + RAY_BLOCK)
            rec = self.shade(d[b0:b1], o, sun_disk)
            out[b0:b1] = combine(rec, table)
            if depth is not None:
                depth[b0:b1] = rec.t_m
        out = out.reshape(*lead, out.shape[1])
        return (out, depth.reshape(lead)) if with_depth else out

    # -- tracing ----------------------------------------------------------------------------------
    def shade(self, d: np.ndarray, o: np.ndarray, sun_disk: bool = True) -> Shading:
        """Trace unit rays ``d (N, 3)`` float32 from ``o`` (m) and shade them (see the module docstring);
        ``sun_disk=False``: rays into the sun's disk see only the sky behind it."""
        t, obj, nid, patch = self.trace(d, o)
        return self._light(d, o, t, obj, nid, patch, sun_disk)

    def trace(self, d: np.ndarray, o: np.ndarray):
        """Nearest hit of unit rays ``d (N, 3)`` float32 from ``o``: distance, object id (``SKY_ID``: none),
        face normal id and the chart patch record."""
        n = d.shape[0]
        dx, dy, dz = (np.ascontiguousarray(d[:, i]) for i in range(3))
        t = np.full(n, np.inf, dtype=np.float32)
        obj = np.full(n, SKY_ID, dtype=np.int16)
        nid = np.zeros(n, dtype=np.int8)
        intersect_ground(dy, o, self.ground_y_m, GROUND_ID, t, obj, nid)
        intersect_boxes(d, (dx, dy, dz), o, self._box_lo, self._box_hi, self._box_centre, self._box_radius, t, obj,
                        nid)
        patch = intersect_board(d, o, self.chart, self._chart_id, t, obj, nid)
        self._hit_skyline(d, t, obj, nid)
        return t, obj, nid, patch

    def _hit_skyline(self, d, t, obj, nid) -> None:
        """Rays that reach the sky below the hills' silhouette end on the hills (lit like level ground)."""
        if self.skyline is None:
            return
        up = np.flatnonzero((obj == SKY_ID) & (d[:, 1] < np.float32(math.sin(math.radians(SKYLINE_MAX_DEG)))))
        if up.size == 0:
            return
        lon, lat = direction_to_lonlat(d[up].astype(np.float64))
        below = lat < self.skyline.elevation_deg(lon)
        sel = up[below]
        t[sel] = np.float32(SKYLINE_DISTANCE_M)
        obj[sel] = self._skyline_id
        nid[sel] = N_PY

    def _light(self, d, o, t, obj, nid, patch, sun_disk: bool = True) -> Shading:
        """Material rows and the sun/sky weights of every ray."""
        dl = self.daylight
        n = d.shape[0]
        material = np.zeros(n, dtype=np.int32)
        sun = np.zeros(n, dtype=np.float32)
        sky = np.zeros(n, dtype=np.float32)
        s = dl.sun_direction.astype(np.float32)
        # sky and sun disk
        up = np.flatnonzero(obj == SKY_ID)
        if up.size:
            ds = d[up]
            sky[up] = dl.sky_luminance_cd_m2(ds)
            if sun_disk and dl.direct_normal_lx > 0:
                on_disk = (ds @ s) >= np.float32(math.cos(dl.sun_radius_rad))
                sun[up[on_disk]] = np.float32(dl.sun_luminance_cd_m2)
        # surfaces
        hit = np.flatnonzero(obj != SKY_ID)
        if hit.size == 0:
            return Shading(material, sun, sky, obj, nid, t)
        material[hit] = self._obj_row[obj[hit]]
        p = o.astype(np.float32) + t[hit, None] * d[hit]
        ground = obj[hit] == GROUND_ID
        far = ground & (p[:, 0] ** 2 + p[:, 2] ** 2 > PAVEMENT_RADIUS_M**2)
        material[hit[far]] = self._row["grass"]
        on_patch = patch[1] >= 0
        material[patch[0][on_patch]] = self._first_patch_row + patch[1][on_patch]
        k = nid[hit]
        sky[hit] = self._sky_lx_by_normal[k]
        lit = self._sun_lx_by_normal[k] > 0
        if lit.any():
            lit_idx = np.flatnonzero(lit)
            visible = ~self.occluded(p[lit_idx])
            sun[hit[lit_idx[visible]]] = self._sun_lx_by_normal[k[lit_idx[visible]]]
        return Shading(material, sun, sky, obj, nid, t)

    def occluded(self, points_m: np.ndarray) -> np.ndarray:
        """Whether the sun's centre is hidden from each point ``(N, 3)`` by a box or the chart board."""
        return sun_blocked(points_m, self.daylight.sun_direction, self._box_lo, self._box_hi, self.chart)

    # -- what a report needs ----------------------------------------------------------------------
    def surface_irradiance(self, point_m, normal) -> np.ndarray:
        """Spectral irradiance (W·m⁻²·nm⁻¹, ``(n,)``) on a surface at ``point_m`` with unit ``normal``.

        Sun (with the shadow test of :meth:`occluded`) plus the unoccluded sky dome: the light the
        scene's Lambertian surfaces reflect, ``L = ρ E / π``.
        """
        dl = self.daylight
        nrm = np.asarray(normal, dtype=np.float64)
        sun_lx = dl.sun_illuminance_lx(nrm)
        if sun_lx > 0 and self.occluded(np.asarray(point_m, dtype=np.float64)[None])[0]:
            sun_lx = 0.0
        return sun_lx * dl.sun_spectrum + dl.sky_illuminance_lx(nrm) * dl.sky_spectrum

    def colorchecker_patches(self, origin_m=(0.0, 0.0, 0.0)) -> list[dict]:
        """The 24 patches: name, centre direction from ``origin_m``, angular half-size, reflectance."""
        return chart_patches(self.chart, self.patch_names, self.patch_reflectance, self.wavelength_nm, origin_m)

    def describe(self) -> dict:
        """Kind, parameters, sun and sky, materials, objects and the chart (JSON-able)."""
        return {
            "kind": self.kind,
            "parameters": dict(self.params),
            "wavelength_nm": {"start": float(self.wavelength_nm[0]), "stop": float(self.wavelength_nm[-1]),
                              "count": int(self.wavelength_nm.size)},
            "radiance_units": self.radiance_units,
            "daylight": self.daylight.describe(),
            "materials": [{"name": m.name, "set": m.source_set, "sample": m.sample,
                           "lab_d65": list(m.lab_d65)} for m in self.materials],
            "objects": [{"name": b.name, "lo_m": list(b.lo_m), "hi_m": list(b.hi_m), "material": b.material}
                        for b in self.boxes],
            "ground": {"y_m": self.ground_y_m, "pavement_radius_m": PAVEMENT_RADIUS_M},
            "chart": {"reflectances": "ColorChecker N Ohta", "centre_m": self.chart.centre_m.tolist(),
                      "normal": self.chart.normal.tolist(), "patch_m": self.chart.patch_m,
                      "gap_m": self.chart.gap_m},
            "skyline": None if self.skyline is None else {"distance_m": SKYLINE_DISTANCE_M, "material": "hedge",
                                                          **self.skyline.describe()},
            "reference": None if self.reference is None else self.reference.describe(),
        }
