"""The ground truth of a simulated session: written beside the session by the simulator, read by the report.

:func:`write_ground_truth` renders the scene's exact band response, spectral radiance, depth and chart spectra on
equirectangular grids (``SESSION/ground_truth/``, format ``omnispectral-ground-truth``; files in its docstring);
:class:`GroundTruth` reads them back.  Processing never reads the truth: the report's accuracy section is given a
:class:`GroundTruth` by whoever knows the session is a simulation (the command line, the demo:
:meth:`GroundTruth.of_session`).
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from omnispectral.errors import InputFileError
from omnispectral.imaging.geometry import equirect_pixel_to_lonlat, lonlat_to_ray, native_width, ray_to_lonlat
from omnispectral.imaging.sundisk import disk_samples, n_radial_for_pixel, splat_equirect
from omnispectral.io import atomic_path, atomic_write_json, jsonable
from omnispectral.rig import Rig, camera_model
from omnispectral.sim.antialias import (
    REFINE_RAYS_PER_SIDE,
    differs_from_neighbours,
    pixels_to_refine,
    refined_mean,
    subpixel_offsets,
    unlike_pairs,
    with_neighbours,
)
from omnispectral.sim.scenes.base import SunDisk, footprint_kwargs, scene_sun_disk

__all__ = ["GROUND_TRUTH_FORMAT", "GroundTruth", "add_sun_disk_equirect", "check_ground_truth",
           "default_ground_truth_width", "equirect_ray_spread_rad", "patch_radiance_spread", "render_equirect_bands",
           "write_ground_truth"]

GROUND_TRUTH_FORMAT = "omnispectral-ground-truth"

log = logging.getLogger(__name__)

#: Arrays small enough to be read whole when a truth is opened (their values are checked to be finite).
SMALL_ARRAY_BYTES = 1 << 20


def default_ground_truth_width(rig: Rig) -> int:
    """The product's default panorama width (camera A's :func:`~omnispectral.imaging.geometry.native_width`):
    the truth on the product's own grid, each pixel the mean over its area.  A coarser truth resampled up
    to the product is a blurred truth and rewards blur (venice_sunset seed 0: the paper's per-direction
    offsets, which blend two slightly misregistered views beside the sun, scored 0.7 dB above the rig
    model against the 908-px truth of the paper's 7260-px width scaled down, 0.5 dB below it on the
    product's 952-px grid)."""
    return native_width(camera_model(rig, "A").fx)


def write_ground_truth(directory: str | Path, renderer, width: int, spectral_width: int = 512,
                       rows_per_chunk: int = 64) -> dict:
    """Save the scene's exact band response (every band of the rig) and spectral radiance on equirectangular grids.

    ``renderer``: the session's :class:`~omnispectral.sim.simulate.RigRenderer` (its scene, system and scale).

    Files (all float32 NumPy ``.npy``, row 0 = latitude +90°, column 0 = longitude -180°, pixel
    centres at +0.5, see :mod:`omnispectral.imaging.geometry`):

    ``bands.npy`` ``(H, W, m)``: noise-free response of the rig's bands (``A:R … B:B``, or ``A:R, A:G, A:B`` for
    a one-camera rig) in DN per second of exposure
    (what the HDR merge of a noise-free capture gives), seen from the head's rotation centre, averaged
    over each pixel's area (2 × 2 points, 64 lattice points where they disagree, like the sensor's pixels:
    :mod:`omnispectral.sim.antialias`); a scene's analytic sun is not
    point-sampled but added exactly (:func:`add_sun_disk_equirect`: every pixel gets the visible part of
    the disk it covers, so the truth holds the sun's energy on any grid).
    ``spectral.npy`` ``(h, w, n)`` at ``spectral_width``: spectral radiance in DN/s per unit of the
    system matrix (``bands = spectral @ matrix.T``), i.e. the unit a Wiener estimate of the bands is in.
    ``wavelength_nm.npy``, ``system_matrix.npy`` ``(m, n)``; for scenes with a chart
    ``colorchecker_radiance.npy`` ``(24, n)`` (spectral radiance at each patch centre, same units) and
    ``colorchecker_white.npy`` ``(n,)`` (a perfect white diffuser there); ``ground_truth.json`` describes it all.
    ``depth_m.npy`` ``(H, W)`` on the bands' grid: distance (m) from the viewpoint to the nearest surface that any
    of the pixel's 2 × 2 rays meets, inf where all four reach the sky; from the same ray casts as ``bands.npy``
    (:meth:`~omnispectral.sim.scenes.base.Scene.band_radiance_and_depth`).  The nearest, not a mean: a pixel
    across a depth edge takes the front surface's distance, so the edge stays a one-pixel step for the report's
    discontinuity test (:mod:`omnispectral.product.report_edges`).  Scenes without geometry (an environment map)
    have none: ``ground_truth.json``'s ``depth`` is then null and ``depth_note`` says why.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    height = width // 2
    scale = renderer.electrons_per_unit / renderer.rig.camera_a.noise_model().gain_e_per_dn
    matrix = renderer.system.matrix
    scene = renderer.scene
    sun = scene_sun_disk(scene)
    no_disk = {"sun_disk": False} if sun is not None else {}
    depth_m = np.full((height, width), np.nan, np.float32)

    def bands_and_depth(rays, spread_rad):
        values, distance_m = _band_radiance_and_depth(scene, rays, matrix, **no_disk,
                                                      **footprint_kwargs(scene, spread_rad))
        return values * np.float32(scale), distance_m

    with atomic_path(out / "bands.npy") as tmp:
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.float32, shape=(height, width, matrix.shape[0]))
        _fill_equirect(arr, bands_and_depth, rows_per_chunk, nearest_depth_m=depth_m)
        if sun is not None:
            add_sun_disk_equirect(arr, sun, sun.band_radiance(matrix) * scale)
        arr.flush()
        del arr
    sw = min(spectral_width, width)
    sh = sw // 2
    spectral = np.empty((sh, sw, matrix.shape[1]), np.float32)
    _fill_equirect(spectral, lambda rays, spread_rad: scene.spectral_radiance(
        rays, **no_disk, **footprint_kwargs(scene, spread_rad)) * np.float32(scale), rows_per_chunk)
    if sun is not None:
        add_sun_disk_equirect(spectral, sun, sun.spectral_radiance * scale)
    _save_npy(out / "spectral.npy", spectral)
    has_depth = not np.isnan(depth_m).any()
    if has_depth:
        _save_npy(out / "depth_m.npy", depth_m)
    _save_npy(out / "wavelength_nm.npy", np.asarray(renderer.system.wavelength_nm, np.float32))
    _save_npy(out / "system_matrix.npy", matrix.astype(np.float32))
    patches = renderer.scene.colorchecker_patches() if hasattr(renderer.scene, "colorchecker_patches") else []
    chart = {}
    if patches:
        for p in patches:
            p["radiance_spread"] = patch_radiance_spread(renderer.scene, p["lon_deg"], p["lat_deg"], p["half_size_deg"])
        rays = lonlat_to_ray(np.array([p["lon_deg"] for p in patches]), np.array([p["lat_deg"] for p in patches]))
        radiance = renderer.scene.spectral_radiance(rays) * np.float32(scale)
        refl = np.array([p["reflectance"] for p in patches], np.float32)
        white = radiance[np.argmax(refl.mean(axis=1))] / np.maximum(refl[np.argmax(refl.mean(axis=1))], 1e-6)
        _save_npy(out / "colorchecker_radiance.npy", radiance.astype(np.float32))
        _save_npy(out / "colorchecker_white.npy", white.astype(np.float32))
        chart = {"colorchecker_radiance": "colorchecker_radiance.npy", "colorchecker_white": "colorchecker_white.npy"}
    meta = {"format": GROUND_TRUTH_FORMAT, "format_version": 1,
            "bands": {"file": "bands.npy", "shape": [height, width, int(matrix.shape[0])],
                      "names": list(renderer.system.band_names),
                      "units": "DN per second of exposure (noise-free, 12-bit codes per second)"},
            "spectral": {"file": "spectral.npy", "shape": [sh, sw, int(matrix.shape[1])],
                         "units": "DN/s per unit of system_matrix: bands = spectral @ system_matrix.T"},
            "wavelength_nm": "wavelength_nm.npy", "system_matrix": "system_matrix.npy",
            "depth": ({"file": "depth_m.npy", "shape": [height, width], "units": "m",
                       "definition": "distance from the viewpoint to the nearest surface any of the pixel's 2 x 2 "
                                     "rays meets (the rays of bands.npy); inf where all four reach the sky"}
                      if has_depth else None),
            **({} if has_depth else {"depth_note": f"the scene ({type(scene).__name__}) has no geometry to "
                                                   "ray-trace: no depth, no depth edges in the report"}),
            "grid": "equirectangular: row 0 at latitude +90, column 0 at longitude -180, pixel centres at +0.5; "
                    "world +Y up, longitude 0 = +Z, longitude +90 = -X (omnispectral.imaging.geometry)",
            "viewpoint": "the head's rotation centre (camera A's optical centre)",
            "electrons_per_unit": renderer.electrons_per_unit, "dn_per_second_per_unit": scale,
            **({"sun_disk": {"direction": [float(x) for x in sun.direction], "radius_rad": sun.radius_rad,
                             "rendering": "exact: visible fraction of the disk in every pixel "
                                          "(omnispectral.imaging.sundisk), not point-sampled"}}
               if sun is not None else {}),
            **({"camera_b_true": {"mounting_error_deg": list(renderer.b_mounting_error_deg),
                                  "model": renderer.models["B"].to_dict(),
                                  "note": "what processing must estimate; never read by processing"}}
               if "B" in renderer.models else {}),
            "scene": jsonable(renderer.scene.describe()), "colorchecker_patches": jsonable(patches), **chart}
    atomic_write_json(out / "ground_truth.json", meta)
    return meta


def patch_radiance_spread(scene, lon_deg: float, lat_deg: float, half_size_deg: float, n: int = 9) -> float:
    """``(max − min) / mean`` of the radiance (summed over wavelength) at ``n × n`` directions spread over the
    central 80 % of a chart patch: 0 for a uniformly lit patch, of order 1 where a shadow edge crosses it.
    A patch that is not one colour has no single reference spectrum (the one at its centre describes
    only part of what a panorama pixel there integrates)."""
    g = np.linspace(-0.8, 0.8, n) * half_size_deg
    dlon, dlat = np.meshgrid(g / max(np.cos(np.radians(lat_deg)), 0.05), g)
    lon, lat = lon_deg + dlon, lat_deg + dlat
    radiance = np.asarray(scene.spectral_radiance(lonlat_to_ray(lon.ravel(), lat.ravel())), np.float64).sum(axis=1)
    mean = float(np.mean(radiance))
    return float((radiance.max() - radiance.min()) / mean) if mean > 0 else 0.0


def render_equirect_bands(scene, matrix: np.ndarray, width: int, row_start: int = 0, row_stop: int | None = None,
                          rows_per_chunk: int = 64) -> np.ndarray:
    """Band radiance ``(rows, W, m)`` float32 (scene units) of rows ``row_start:row_stop`` of the W × W/2 truth grid,
    as :func:`write_ground_truth` renders it (2 × 2 points per pixel, 64 lattice points where they disagree,
    the analytic sun added exactly), unscaled."""
    height = width // 2
    row_stop = height if row_stop is None else row_stop
    sun = scene_sun_disk(scene)
    no_disk = {"sun_disk": False} if sun is not None else {}
    arr = np.empty((row_stop - row_start, width, np.atleast_2d(matrix).shape[0]), np.float32)
    _fill_equirect(arr, lambda rays, spread_rad: scene.band_radiance(
        rays, matrix, **no_disk, **footprint_kwargs(scene, spread_rad)), rows_per_chunk,
                   row_offset=row_start, height=height)
    if sun is not None:
        add_sun_disk_equirect(arr, sun, sun.band_radiance(matrix), row_offset=row_start, height=height)
    return arr


def add_sun_disk_equirect(arr: np.ndarray, sun: SunDisk, values: np.ndarray, row_offset: int = 0,
                          height: int | None = None, origin_m=(0.0, 0.0, 0.0)) -> None:
    """Add a uniform disk of per-channel radiance ``values (c,)`` exactly to an equirect array, in place.

    ``arr (rows, W, c)`` holds rows ``row_offset:`` of a W × ``height`` grid (default: all of it).  The
    disk's stratified samples (:func:`~omnispectral.imaging.sundisk.disk_samples`, ≥ 20 k and about 80
    cells per pixel side, so that each pixel's value is within ≈ 0.3 % of the disk's radiance of its
    exact coverage, :func:`~omnispectral.imaging.sundisk.equirect_disk_coverage`) are tested with
    ``sun.visible`` from ``origin_m`` and splatted as ``Σ w / Ω_pixel`` (a building or hill edge across
    the disk is honoured), so ``Σ added · Ω_pixel = values · Ω_visible``.
    """
    width = arr.shape[1]
    height = arr.shape[0] if height is None else int(height)
    _, lat = ray_to_lonlat(sun.direction)
    cos_lat = np.cos(min(np.radians(abs(float(lat))) + sun.radius_rad, 0.5 * np.pi))
    pixel_rad = min(np.pi / height, 2.0 * np.pi / width * max(float(cos_lat), 1e-6))
    dirs, weights = disk_samples(sun.direction, sun.radius_rad, n_radial_for_pixel(sun.radius_rad, pixel_rad))
    vis = np.asarray(sun.visible(dirs, origin_m), bool)
    rows, cols, frac = splat_equirect(dirs[vis], weights[vis], width, height)
    sel = (rows >= row_offset) & (rows < row_offset + arr.shape[0])
    add = frac[sel, None] * np.asarray(values, np.float64).reshape(1, -1)
    arr[rows[sel] - row_offset, cols[sel]] += add.astype(arr.dtype)


def _band_radiance_and_depth(scene, rays: np.ndarray, matrix: np.ndarray, **kwargs):
    """``(bands, hit distance (m) or None)`` of any renderable scene (those without the method have no depth)."""
    method = getattr(scene, "band_radiance_and_depth", None)
    if method is None:
        return scene.band_radiance(rays, matrix, **kwargs), None
    return method(rays, matrix, **kwargs)


def equirect_ray_spread_rad(lat_deg, width: int, height: int, supersample: int) -> np.ndarray:
    """Angular side (rad, float32) of the share of its pixel one of ``supersample²`` points of a ``width`` ×
    ``height`` equirect grid stands for, at latitude ``lat_deg``: the square root of the share's solid angle,
    ``(2π / W / s) cos(lat)`` of longitude by ``(π / H / s)`` of latitude."""
    lat = np.radians(np.asarray(lat_deg, np.float64))
    return (np.sqrt(np.cos(lat) * (2 * np.pi / width) * (np.pi / height)) / supersample).astype(np.float32)


def _fill_equirect(arr: np.ndarray, fn, rows_per_chunk: int, supersample: int = 2, row_offset: int = 0,
                   height: int | None = None, nearest_depth_m: np.ndarray | None = None) -> None:
    """Fill an equirect array with ``fn(rays, spread_rad)`` averaged over ``supersample²`` points spread over each
    pixel's area, and over more where they disagree (an edge crosses the pixel, :mod:`omnispectral.sim.antialias`):
    the truth is the mean radiance of the pixel's solid angle, as the simulated sensor's pixels integrate over
    their area (:attr:`RigRenderer.supersample`, :attr:`RigRenderer.refine_per_side`), so that edges compare like
    with like.
    ``spread_rad`` ``(N,)`` is the angular side of each point's share of its pixel
    (:func:`equirect_ray_spread_rad`), for scenes that filter a texture finer than the points
    (:func:`~omnispectral.sim.scenes.base.footprint_kwargs`).  ``arr`` holds rows ``row_offset:`` of a grid
    ``height`` rows high (default: all of it).

    With ``nearest_depth_m`` (``(rows, W)``), ``fn`` returns ``(values, distance_m or None)`` and the array gets the
    smallest of each pixel's ray distances (left as it is where ``fn`` gives None)."""

    n_rows, w = arr.shape[:2]
    h = n_rows if height is None else int(height)
    s = max(1, int(supersample))
    sub = subpixel_offsets(s)
    for r0 in range(0, n_rows, rows_per_chunk):
        r1 = min(n_rows, r0 + rows_per_chunk)
        row, col, dr, dc = np.meshgrid(np.arange(r0, r1) + row_offset, np.arange(w), sub, sub, indexing="ij")
        lon, lat = equirect_pixel_to_lonlat((col + dc).ravel(), (row + dr).ravel(), w, h)
        values = fn(lonlat_to_ray(lon, lat), equirect_ray_spread_rad(lat, w, h, s))
        if nearest_depth_m is not None:
            values, distance_m = values
            if distance_m is not None:
                nearest_depth_m[r0:r1] = np.asarray(distance_m, np.float32).reshape(r1 - r0, w, s * s).min(axis=2)
        samples = np.asarray(values, np.float32).reshape((r1 - r0) * w, s * s, -1)
        means = samples.mean(axis=1)
        # the chunk's first row is compared with the row above it, already written (and refined) into ``arr``
        above = arr[r0 - 1] if r0 > 0 else None
        _refine_equirect(means, samples, fn, r0 + row_offset, r1 - r0, w, h, s, nearest_depth_m is not None, above)
        arr[r0:r1] = means.reshape(r1 - r0, w, -1)


def _refine_equirect(means: np.ndarray, samples: np.ndarray, fn, row0: int, n_rows: int, w: int, h: int, s: int,
                     with_depth: bool, above: np.ndarray | None = None) -> None:
    """Pixels of rows ``row0 …`` whose ``samples (P, s², c)`` disagree (and their neighbours), or whose mean differs
    from a neighbour's, get the mean of :data:`~omnispectral.sim.antialias.REFINE_RAYS_PER_SIDE` ² points instead
    (:mod:`omnispectral.sim.antialias`), written into ``means (P, c)``.  ``above (w, c)``: the final values of row
    ``row0 - 1`` (the previous chunk's last row), compared with row ``row0``; where they differ both are rendered
    again, ``above`` in place."""
    n = REFINE_RAYS_PER_SIDE
    if n <= s:
        return
    marked = (with_neighbours(pixels_to_refine(samples), n_rows, w, wrap_columns=True)
              | differs_from_neighbours(means, n_rows, w, wrap_columns=True))
    across = None
    if above is not None:
        across = unlike_pairs(np.asarray(above, np.float32), means[:w])
        marked[:w] |= across

    def render(points: np.ndarray) -> np.ndarray:
        lon, lat = equirect_pixel_to_lonlat(points[:, 0], points[:, 1], w, h)
        values = fn(lonlat_to_ray(lon, lat), equirect_ray_spread_rad(lat, w, h, n))
        return values[0] if with_depth else values

    idx = np.flatnonzero(marked)
    if idx.size:
        rows, cols = np.divmod(idx, w)
        means[idx] = refined_mean(render, np.stack([cols, rows + row0], axis=-1).astype(np.float64), n)
    if across is not None and across.any():
        cols = np.flatnonzero(across)
        above[cols] = refined_mean(render, np.stack([cols, np.full(cols.size, row0 - 1)], axis=-1).astype(np.float64),
                                   n)


def _save_npy(path: Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.save(fh, array)


def check_ground_truth(directory: str | Path) -> dict:
    """``ground_truth.json`` of a truth directory, after checking every array it names without decoding the big
    ones: each ``.npy`` file's header is read (float32, the shape the description states) and the file holds all
    the bytes of that shape; the small arrays (wavelengths, system matrix, chart spectra) are read and finite.

    Parameters
    ----------
    directory : str or pathlib.Path
        A ground-truth directory (:func:`write_ground_truth`).

    Returns
    -------
    dict
        The description (``ground_truth.json``).

    Raises
    ------
    InputFileError
        Naming the first file that is missing, unreadable, cut, of another type or shape, or not finite.
    """
    directory = Path(directory)
    meta = _read_description(directory / "ground_truth.json")
    for name, shape in _described_arrays(directory / "ground_truth.json", meta):
        _check_npy(directory / name, shape)
    return meta


def _read_description(path: Path) -> dict:
    """``ground_truth.json``, refused unless it is an object of :data:`GROUND_TRUTH_FORMAT`."""
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        problem = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise InputFileError(path, f"not a readable ground truth ({problem})") from None
    if not isinstance(meta, dict) or meta.get("format") != GROUND_TRUTH_FORMAT:
        raise InputFileError(path, f"not an {GROUND_TRUTH_FORMAT} file")
    return meta


def _described_arrays(path: Path, meta: dict) -> list[tuple[str, tuple[int, ...] | None]]:
    """``(file name, expected shape or None)`` of every array the description names, bands and spectra first."""
    try:
        bands, spectral = tuple(meta["bands"]["shape"]), tuple(meta["spectral"]["shape"])
        n_bands, n_wavelengths = int(bands[2]), int(spectral[2])
        arrays = [(meta["bands"]["file"], bands), (meta["spectral"]["file"], spectral),
                  (meta["wavelength_nm"], (n_wavelengths,)), (meta["system_matrix"], (n_bands, n_wavelengths))]
        if meta.get("depth"):
            arrays.append((meta["depth"]["file"], tuple(meta["depth"]["shape"])))
        for key in ("colorchecker_radiance", "colorchecker_white"):
            if meta.get(key):
                arrays.append((meta[key], None))
        arrays = [(name, None if shape is None else tuple(int(v) for v in shape)) for name, shape in arrays]
    except (KeyError, TypeError, ValueError, IndexError) as exc:
        raise InputFileError(path, f"incomplete ground-truth description ({type(exc).__name__}: {exc})") from None
    for name, _ in arrays:
        if not isinstance(name, str) or not name or Path(name).name != name:
            raise InputFileError(path, f"names {name!r}, not a file of the ground truth's directory")
    return arrays


def _check_npy(path: Path, shape: tuple[int, ...] | None) -> None:
    """Refuse a ``.npy`` file that is not float32 of ``shape`` (any shape when None) or holds fewer bytes than its
    header says; small arrays are read whole and must be finite (``depth_m.npy`` may hold inf: the sky)."""
    try:
        with open(path, "rb") as fh:
            version = np.lib.format.read_magic(fh)
            read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                           else np.lib.format.read_array_header_2_0)
            stated, fortran, dtype = read_header(fh)  # the header only: nothing is decoded
            offset = fh.tell()
            size = os.fstat(fh.fileno()).st_size
    except FileNotFoundError:
        raise InputFileError(path, "missing (the ground truth names it)") from None
    except (OSError, ValueError, EOFError, SyntaxError) as exc:
        raise InputFileError(path, f"damaged NumPy array ({type(exc).__name__}: {exc})") from None
    if dtype != np.float32 or fortran or (shape is not None and tuple(stated) != shape):
        raise InputFileError(path, f"holds {dtype} {tuple(stated)}, the ground truth describes float32 "
                                   f"{shape if shape is not None else 'arrays'}")
    need = offset + int(np.prod(stated, dtype=np.int64)) * 4
    if size < need:
        raise InputFileError(path, f"cut: {size} bytes, its header needs {need}")
    if need - offset <= SMALL_ARRAY_BYTES and path.name != "depth_m.npy":
        values = np.load(path)
        if not np.isfinite(values).all():
            raise InputFileError(path, "holds values that are not finite")


@dataclass
class GroundTruth:
    """A simulated session's ground truth (:func:`write_ground_truth`), read lazily from ``directory``.

    Arrays come in the units :func:`write_ground_truth` documents (DN per second of exposure on the
    equirectangular grids of ``ground_truth.json``).
    """

    directory: Path
    meta: dict = field(repr=False)

    @classmethod
    def open(cls, directory: str | Path) -> GroundTruth:
        """The truth in ``directory``, checked whole before anything reads it (:func:`check_ground_truth`).

        Raises
        ------
        InputFileError
            Naming the file that is missing, unreadable, cut or not what ``ground_truth.json`` describes.
        """
        directory = Path(directory)
        return cls(directory, check_ground_truth(directory))

    @classmethod
    def of_session(cls, session: str | Path) -> GroundTruth | None:
        """The truth of a simulated session (``SESSION/ground_truth``), or None for a session without one.

        A damaged or unreadable truth is None too, after one warning line naming the file (logged on
        ``omnispectral.sim.truth``; Python prints it alone on standard error when logging is not configured):
        the truth only adds the report's accuracy section, so the product is still made, without it.
        """
        directory = Path(session) / "ground_truth"
        if not (directory / "ground_truth.json").is_file():
            return None
        try:
            return cls.open(directory)
        except InputFileError as exc:
            log.warning("warning: %s; the report is written without its accuracy section", exc)
            return None

    @property
    def band_names(self) -> list[str]:
        return list(self.meta["bands"]["names"])

    def bands(self, mmap: bool = False) -> np.ndarray:
        """``(H, W, m)`` float32 noise-free band response (DN/s), memory-mapped when ``mmap``."""
        return np.load(self.directory / self.meta["bands"]["file"], mmap_mode="r" if mmap else None)

    def spectral(self, mmap: bool = False) -> np.ndarray:
        """``(h, w, n)`` float32 spectral radiance (DN/s per unit of the system matrix)."""
        return np.load(self.directory / self.meta["spectral"]["file"], mmap_mode="r" if mmap else None)

    def depth_m(self) -> tuple[np.ndarray | None, str | None]:
        """``(depth (H, W) in m, None)`` or ``(None, why there is none)``."""
        depth = self.meta.get("depth")
        if not depth or not (self.directory / depth["file"]).is_file():
            return None, self.meta.get("depth_note") or (
                "the ground truth has no depth map (simulated before depth was recorded; simulate the session "
                "again to measure depth edges)")
        return np.load(self.directory / depth["file"]), None

    @property
    def colorchecker_patches(self) -> list[dict]:
        return list(self.meta.get("colorchecker_patches") or [])

    def colorchecker_radiance(self) -> np.ndarray | None:
        """``(24, n)`` spectral radiance at the chart's patch centres, or None without a chart."""
        path = self.directory / "colorchecker_radiance.npy"
        return np.load(path) if self.colorchecker_patches and path.is_file() else None

    def colorchecker_white(self) -> np.ndarray | None:
        """``(n,)`` a perfect white diffuser at the chart, or None without a chart."""
        path = self.directory / "colorchecker_white.npy"
        return np.load(path) if path.is_file() else None
