"""Spectral image-based rendering of a captured panorama with Mitsuba 3 (paper Sec. 6.1, Fig. 16).

**Band packing.** Light transport is linear and, for the materials used here (diffuse reflectance,
smooth conductors), acts on each wavelength separately.  A spectral render is therefore a series of
ordinary RGB renders, each carrying three wavelengths: the environment map's spectral radiance at
``λ_3i, λ_3i+1, λ_3i+2`` in R, G, B and every material's parameters at the same wavelengths (a
reflectance, or a metal's ``n`` and ``k``).  The passes use the same sampler seed, so camera rays
and purely specular paths are identical across passes; the spectral image is assembled from the
passes (61 wavelengths → 21 passes; a coarser grid on request).  Mitsuba rejects multi-channel
environment maps, which is why packing is needed at all.

**Fast path.** The six bands are rendered in two RGB passes (bands A:RGB, then B:RGB) and the
product's estimator turns the rendered bands into spectra per pixel.  It is exact only for
wavelength-flat materials and an estimator applied as one linear map: a coloured material's band
reflectance is approximated by its mean over each band weighted by the environment's mean spectrum,
and with the mixture prior the estimate of a sum of radiances is not the sum of the estimates.

**Scenes.** The built-in :class:`MirrorBallScene` is Fig. 16's mirror ball on a grey plate (silver
ball, Palik's optical constants; plate = the ColorChecker's neutral 5 patch).  :class:`XmlScene` takes any
Mitsuba scene file whose spectral parameters are given as CSV files (``<spectrum name="reflectance"
filename="paint.csv"/>``; for conductors ``name="eta"`` / ``name="k"`` with a ``wavelength_nm,n,k`` file);
its environment emitter, if any, is replaced by the product's map (its ``to_world`` and ``scale`` kept); its
film's width and height and its sampler's ``sample_count`` are the render's unless the caller gives others
(:func:`render_settings`), and a file without an ``<integrator>`` gets Mitsuba's ``path``.

**Variant.** ``llvm_ad_rgb`` when Dr.Jit finds an LLVM library of version 17 or later (Debian
``libllvm19``; older ones abort the process while compiling Mitsuba's kernels), else ``scalar_rgb``;
``OMNISPECTRAL_MITSUBA_VARIANT`` or ``variant=`` overrides.  Same images up to Monte
Carlo noise (different random number streams).
"""

from __future__ import annotations

import copy
import math
import os
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from omnispectral.apps.environment import EnvironmentMap, environment_from_product
from omnispectral.apps.materials import Conductor, Diffuse, load_metal, material_at
from omnispectral.errors import ConfigurationError, InputFileError
from omnispectral.imaging.geometry import lonlat_to_ray
from omnispectral.io import atomic_path, atomic_write_json
from omnispectral.ownership import check_output_outside_inputs, claim_output_directory
from omnispectral.product.exports import reinhard_srgb8, write_rgb_exr, write_spectral_exr
from omnispectral.product.spectra import estimate_image
from omnispectral.progress import ProgressCallback, report_progress
from omnispectral.spectral.colour import spectra_to_linear_srgb
from omnispectral.spectral.curves import resample_spectra
from omnispectral.spectral.library import load_reflectances

__all__ = ["DEFAULT_HEIGHT", "DEFAULT_SPP", "DEFAULT_WIDTH", "FAST_PATH_NOTE", "MAX_SAMPLES_PER_CALL",
           "MIN_LLVM_VERSION", "MIN_WAVELENGTHS", "VARIANT_ENV", "MirrorBallScene", "RenderResult", "XmlScene",
           "auto_exposure_reference", "auto_variant", "band_materials", "mitsuba", "render_fast", "render_product",
           "render_rgb", "render_settings", "render_spectral", "scene_from_name", "wavelength_grid", "write_render"]

#: Largest number of samples (pixels × spp) handed to one ``mi.render`` call: bounds the LLVM wavefront's memory.
MAX_SAMPLES_PER_CALL = 1 << 22
VARIANT_ENV = "OMNISPECTRAL_MITSUBA_VARIANT"
FAST_PATH_NOTE = ("six-band fast path: exact only for wavelength-flat materials and a linear estimator; coloured "
                  "materials use band-averaged reflectances")


# ------------------------------------------------------------------------------------------ Mitsuba
#: Oldest LLVM whose X86 back end lowers ``llvm.minimum``/``llvm.maximum`` on f32, which Dr.Jit's kernels use
#: (llvm/llvm-project#53353); with LLVM 15 the JIT aborts the process ("Cannot select ... fminimum").
MIN_LLVM_VERSION = (17, 0, 0)


def auto_variant(variants, llvm_version: tuple | None) -> str:
    """The Mitsuba variant to use when none is asked for.

    Parameters
    ----------
    variants
        The variants Mitsuba has.
    llvm_version
        The LLVM library Dr.Jit found, ``None`` when none.

    Returns
    -------
    str
        ``llvm_ad_rgb`` when Mitsuba has it and the LLVM is at least :data:`MIN_LLVM_VERSION`, else ``scalar_rgb``.
    """
    ok = llvm_version is not None and tuple(llvm_version) >= MIN_LLVM_VERSION
    return "llvm_ad_rgb" if "llvm_ad_rgb" in variants and ok else "scalar_rgb"


def _llvm_version(dr) -> tuple | None:
    if not dr.has_backend(dr.JitBackend.LLVM):
        return None
    try:
        return tuple(dr.detail.llvm_version())
    except (AttributeError, RuntimeError):  # a Dr.Jit without the query: trust the library it found
        return MIN_LLVM_VERSION


def mitsuba(variant: str | None = None):
    """The ``mitsuba`` module with a variant set (see the module docstring).

    Parameters
    ----------
    variant
        ``scalar_rgb`` or ``llvm_ad_rgb``; ``None`` for :data:`VARIANT_ENV`, the variant already set, or
        :func:`auto_variant`.

    Returns
    -------
    module
        ``mitsuba``.

    Raises
    ------
    ConfigurationError
        Without Mitsuba, for another variant, or for ``llvm_ad_rgb`` without a recent enough LLVM.
    """
    try:
        import drjit as dr
        import mitsuba as mi  # imported lazily: a large native library only rendering needs
    except ImportError as exc:
        raise ConfigurationError(f"rendering needs Mitsuba 3 (pip install mitsuba): {exc}") from None
    wanted = variant or os.environ.get(VARIANT_ENV) or None
    if wanted is None and mi.variant() is not None:
        return mi
    if wanted is None:
        wanted = auto_variant(mi.variants(), _llvm_version(dr))
    if wanted not in ("scalar_rgb", "llvm_ad_rgb"):
        raise ConfigurationError(f"Mitsuba variant {wanted!r} is not supported here; use scalar_rgb or llvm_ad_rgb")
    if wanted == "llvm_ad_rgb":
        version = _llvm_version(dr)
        if version is None or version < MIN_LLVM_VERSION:
            found = "none" if version is None else ".".join(map(str, version))
            raise ConfigurationError(f"Mitsuba's llvm_ad_rgb variant needs LLVM >= {MIN_LLVM_VERSION[0]} (found: "
                                     f"{found}; apt-get install libllvm19, or use scalar_rgb)")
    if mi.variant() != wanted:
        mi.set_variant(wanted)
    return mi


def render_rgb(mi, scene, spp: int, seed: int = 0) -> np.ndarray:
    """Radiance of a loaded scene, rendered in chunks of at most :data:`MAX_SAMPLES_PER_CALL` samples
    (independent seeds) and averaged.

    Parameters
    ----------
    mi
        The ``mitsuba`` module (:func:`mitsuba`).
    scene
        A loaded Mitsuba scene.
    spp
        Samples per pixel in all.
    seed
        Base seed of the chunks.

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` float32.
    """
    size = scene.sensors()[0].film().crop_size()
    per_call = max(1, min(spp, MAX_SAMPLES_PER_CALL // max(1, int(size[0]) * int(size[1]))))
    acc = None
    done = 0
    k = 0
    while done < spp:
        n = min(per_call, spp - done)
        img = np.asarray(mi.render(scene, spp=n, seed=seed * 1000 + k), np.float64)[..., :3]
        acc = img * n if acc is None else acc + img * n
        done += n
        k += 1
    return (acc / spp).astype(np.float32)


# -------------------------------------------------------------------------------------------- scenes
def _grey_plate() -> Diffuse:

    s = load_reflectances("colorchecker")
    i = s.names.index("neutral 5 (.70 D)")
    return Diffuse("ColorChecker neutral 5 (N. Ohta)", np.asarray(s.wavelength_nm, float), np.asarray(s.values[i]))


@dataclass
class MirrorBallScene:
    """Fig. 16: a mirror ball resting on a square grey plate, seen from slightly above.

    The camera looks towards longitude ``view_lon_deg`` (so that part of the panorama is the
    background) and ``elevation_deg`` down onto the ball; ``ball`` is any material (a metal by
    default; a black diffuse ball is a pure occluder, used by the tests).
    """

    ball_radius_m: float = 0.25
    plate_half_size_m: float = 0.8
    camera_distance_m: float = 1.8
    elevation_deg: float = 15.0
    view_lon_deg: float = 0.0
    fov_deg: float = 40.0
    ball: Conductor | Diffuse = field(default_factory=lambda: load_metal("silver"))
    plate: Diffuse = field(default_factory=_grey_plate)
    max_depth: int = 8

    kind = "mirror-ball"

    @property
    def materials(self) -> dict:
        return {"ball": self.ball, "plate": self.plate}

    @property
    def ball_centre_m(self) -> np.ndarray:
        return np.array([0.0, self.ball_radius_m, 0.0])

    @property
    def view_direction(self) -> np.ndarray:
        return lonlat_to_ray(self.view_lon_deg, -self.elevation_deg)

    @property
    def camera_position_m(self) -> np.ndarray:
        return self.ball_centre_m - self.camera_distance_m * self.view_direction

    def camera_ray(self, col: float, row: float, width: int, height: int) -> np.ndarray:
        """World direction through image position ``(col, row)`` (pixel centres at +0.5), for checks."""
        f = 0.5 * width / math.tan(math.radians(self.fov_deg) / 2)
        fwd = self.view_direction
        # Mitsuba's look_at builds left = up × forward; image columns grow towards -left (the viewer's right)
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        d = fwd * f + right * (col - 0.5 * width) - up * (row - 0.5 * height)
        return d / np.linalg.norm(d)

    def build(self, mi, material_rgb: dict, env_rgb: np.ndarray, width: int, height: int, spp: int):
        """The Mitsuba scene of one pass (materials' parameters and environment in R, G, B)."""
        T = mi.ScalarTransform4f
        r = self.ball_radius_m
        cam = self.camera_position_m
        return mi.load_dict({
            "type": "scene",
            "integrator": {"type": "path", "max_depth": self.max_depth},
            "environment": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(env_rgb, np.float32))},
            "ball": {"type": "sphere", "center": [0.0, r, 0.0], "radius": r,
                     "bsdf": _bsdf(material_rgb["ball"])},
            "plate": {"type": "rectangle",
                      "to_world": T().rotate([1, 0, 0], -90).scale([self.plate_half_size_m, self.plate_half_size_m, 1]),
                      "bsdf": _bsdf(material_rgb["plate"])},
            "sensor": {"type": "perspective", "fov": self.fov_deg, "fov_axis": "x",
                       "to_world": T().look_at(origin=cam.tolist(), target=self.ball_centre_m.tolist(), up=[0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": spp}},
        })

    def describe(self) -> dict:
        return {"kind": self.kind, "ball_radius_m": self.ball_radius_m, "plate_half_size_m": self.plate_half_size_m,
                "camera_distance_m": self.camera_distance_m, "elevation_deg": self.elevation_deg,
                "view_lon_deg": self.view_lon_deg, "fov_deg": self.fov_deg, "ball": self.ball.name,
                "plate": self.plate.name}


def _rgb(values) -> dict:
    v = np.asarray(values, float).reshape(-1)
    return {"type": "rgb", "value": [float(x) for x in v[:3]]}


def _bsdf(params: dict) -> dict:
    if "eta" in params:
        return {"type": "conductor", "eta": _rgb(params["eta"]), "k": _rgb(params["k"])}
    return {"type": "diffuse", "reflectance": _rgb(params["reflectance"])}


class XmlScene:
    """A Mitsuba scene file whose spectral parameters are CSV files (module docstring)."""

    kind = "xml"

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputFileError(self.path, "no such scene file")
        try:
            self.tree = ET.parse(self.path)
        except ET.ParseError as exc:
            raise InputFileError(self.path, f"not valid XML ({exc})") from None
        root = self.tree.getroot()
        if root.tag != "scene":
            raise InputFileError(self.path, f"the root element is <{root.tag}>, not <scene>")
        self.materials: dict[str, Conductor | Diffuse] = {}
        self._slots: list[tuple[str, str]] = []  # (material key, parameter) in document order
        for el in root.iter("spectrum"):
            fn = el.get("filename", "")
            if not fn.lower().endswith(".csv"):
                continue
            file = (self.path.parent / fn) if not Path(fn).is_absolute() else Path(fn)
            name = el.get("name", "reflectance")
            key = f"{fn}:{name}"
            if name in ("eta", "k"):
                self.materials.setdefault(fn, load_metal(str(file)))
                self._slots.append((fn, name))
            else:
                self.materials.setdefault(key, Diffuse.from_csv(file))
                self._slots.append((key, "reflectance"))
        if not any(el.tag == "sensor" for el in root):
            raise InputFileError(self.path, "has no <sensor>")

    def _integer(self, tag: str, name: str) -> int | None:
        """The first ``<integer name=NAME>`` of a ``<TAG>`` inside the first ``<sensor>`` (``$param`` resolved
        through the file's ``<default>`` elements); ``None`` when the file does not say."""
        root = self.tree.getroot()
        sensor = next(el for el in root if el.tag == "sensor")
        defaults = {el.get("name"): el.get("value") for el in root if el.tag == "default"}
        for el in sensor.iter(tag):
            for child in el:
                if child.tag == "integer" and child.get("name") == name:
                    text = str(child.get("value", "")).strip()
                    text = defaults.get(text[1:], "") if text.startswith("$") else text
                    try:
                        value = int(text)
                    except ValueError:
                        raise InputFileError(self.path, f"<{tag}>'s {name} is {child.get('value')!r}, not a "
                                                        "whole number") from None
                    if value < 1:
                        raise InputFileError(self.path, f"<{tag}>'s {name} must be positive, not {value}")
                    return value
        return None

    def film_size(self) -> tuple[int | None, int | None]:
        """Width and height of the scene file's film in pixels (``None`` for what the file does not give)."""
        return self._integer("film", "width"), self._integer("film", "height")

    def sample_count(self) -> int | None:
        """Samples per pixel of the scene file's sampler (``None`` when the file does not give it)."""
        return self._integer("sampler", "sample_count")

    def build(self, mi, material_rgb: dict, env_rgb: np.ndarray, width: int, height: int, spp: int):
        root = copy.deepcopy(self.tree.getroot())
        slots = iter(self._slots)
        for parent in list(root.iter()):
            for i, el in enumerate(list(parent)):
                if el.tag == "spectrum" and el.get("filename", "").lower().endswith(".csv"):
                    key, param = next(slots)
                    values = material_rgb[key][param]
                    new = ET.Element("rgb", {"name": el.get("name", "reflectance"),
                                             "value": ", ".join(f"{float(v):.9g}" for v in np.asarray(values)[:3])})
                    parent.remove(el)
                    parent.insert(i, new)
        _set_film_size(root, width, height)
        if not any(el.tag == "integrator" for el in root):  # Mitsuba's render() refuses a scene without one
            root.insert(0, ET.Element("integrator", {"type": "path"}))
        with tempfile.TemporaryDirectory(prefix="omnispectral-render-") as tmp:
            env_path = Path(tmp) / "environment.exr"
            mi.Bitmap(np.ascontiguousarray(env_rgb, np.float32)).write(str(env_path))
            emitters = [el for el in root if el.tag == "emitter" and el.get("type") == "envmap"]
            if emitters:
                for em in emitters:
                    for child in list(em):
                        if child.get("name") == "filename":
                            em.remove(child)
                    em.insert(0, ET.Element("string", {"name": "filename", "value": str(env_path)}))
            else:
                em = ET.SubElement(root, "emitter", {"type": "envmap"})
                ET.SubElement(em, "string", {"name": "filename", "value": str(env_path)})
            resolver = mi.file_resolver()
            base = str(self.path.parent.resolve())
            if not any(str(p) == base for p in resolver):  # relative meshes and textures of the scene file
                resolver.prepend(base)
            try:
                return mi.load_string(ET.tostring(root, encoding="unicode"))
            except Exception as exc:  # Mitsuba raises RuntimeError with its own message
                raise InputFileError(self.path, f"Mitsuba cannot load it: {str(exc).splitlines()[0]}") from None

    def describe(self) -> dict:
        return {"kind": self.kind, "file": str(self.path.resolve()), "materials": sorted(self.materials)}


def _set_film_size(root: ET.Element, width: int, height: int) -> None:
    """Give every sensor's film ``width`` × ``height`` pixels (a film is added where a sensor has none)."""
    for sensor in root.iter("sensor"):
        films = [el for el in sensor if el.tag == "film"] or [ET.SubElement(sensor, "film", {"type": "hdrfilm"})]
        for film in films:
            for name, value in (("width", width), ("height", height)):
                el = next((c for c in film if c.tag == "integer" and c.get("name") == name), None)
                if el is None:
                    el = ET.SubElement(film, "integer", {"name": name})
                el.set("value", str(value))


def scene_from_name(scene: str | None, **kwargs):
    """A scene by name.

    Parameters
    ----------
    scene
        ``None`` or ``"mirror-ball"`` for :class:`MirrorBallScene`, else a Mitsuba XML file (:class:`XmlScene`).
    **kwargs
        Fields of :class:`MirrorBallScene` (the built-in scene only).

    Returns
    -------
    MirrorBallScene or XmlScene

    Raises
    ------
    ConfigurationError
        When keyword arguments are given with a scene file.
    """
    if scene in (None, "mirror-ball"):
        return MirrorBallScene(**kwargs)
    if kwargs:
        raise ConfigurationError(f"{', '.join(kwargs)} only apply to the built-in mirror-ball scene")
    return XmlScene(scene)


# ------------------------------------------------------------------------------------------ rendering
@dataclass
class RenderResult:
    """A rendered spectral image, its grid and units, and what made it (``info``)."""

    spectra: np.ndarray  # (H, W, n) float32
    wavelength_nm: np.ndarray
    units: str
    info: dict

    def linear_srgb(self) -> np.ndarray:
        """The image's linear sRGB (:func:`omnispectral.spectral.colour.spectra_to_linear_srgb`).

        Returns
        -------
        numpy.ndarray
            ``(H, W, 3)`` float32.
        """
        return spectra_to_linear_srgb(self.spectra, self.wavelength_nm)


#: Fewest wavelengths of a spectral render (a coarser grid is refused: too few samples for its colour).
MIN_WAVELENGTHS = 6


def wavelength_grid(env: EnvironmentMap, step_nm: float | None) -> np.ndarray:
    """The wavelengths of a spectral render.

    Parameters
    ----------
    env
        The environment map.
    step_nm
        ``None`` for the environment's own grid, else a coarser one every ``step_nm`` within it.

    Returns
    -------
    numpy.ndarray
        The grid (nm).

    Raises
    ------
    ConfigurationError
        For a step that is not positive or leaves fewer than :data:`MIN_WAVELENGTHS` wavelengths.
    """
    wl = env.wavelength_nm
    if step_nm is None:
        return wl.copy()
    if step_nm <= 0:
        raise ConfigurationError(f"wavelength step must be positive, got {step_nm}")
    grid = np.arange(wl[0], wl[-1] + 1e-9, float(step_nm))
    if grid.size < MIN_WAVELENGTHS:
        raise ConfigurationError(f"a {step_nm:g} nm step leaves fewer than {MIN_WAVELENGTHS} wavelengths in "
                                 f"{wl[0]:g}-{wl[-1]:g} nm (the render's colour needs {MIN_WAVELENGTHS})")
    return grid


def _passes(n: int) -> list[np.ndarray]:
    return [np.arange(i, min(n, i + 3)) for i in range(0, n, 3)]


def render_spectral(env: EnvironmentMap, scene, width: int = 256, height: int = 256, spp: int = 64,
                    wavelength_step_nm: float | None = None, seed: int = 0, variant: str | None = None,
                    progress: ProgressCallback | None = None) -> RenderResult:
    """Band-packed spectral render (module docstring): ``ceil(n/3)`` RGB passes of Mitsuba.

    Parameters
    ----------
    env
        The environment map (resampled onto :func:`wavelength_grid`'s grid when that is coarser).
    scene
        :class:`MirrorBallScene` or :class:`XmlScene`.
    width, height, spp
        Image size (pixels) and samples per pixel.
    wavelength_step_nm
        A coarser grid (:func:`wavelength_grid`), ``None`` for the environment's.
    seed
        Sampler seed, the same in every pass.
    variant
        Mitsuba variant (:func:`mitsuba`).
    progress
        ``progress("render passes", done, total)`` before the first Mitsuba pass and after each.

    Returns
    -------
    RenderResult
        ``(height, width, n)`` float32 spectral radiance in the environment's units.
    """
    _check_size(width, height, spp)
    mi = mitsuba(variant)
    wl = wavelength_grid(env, wavelength_step_nm)
    env = env if np.array_equal(wl, env.wavelength_nm) else env.resampled(wl)
    out = np.empty((height, width, wl.size), np.float32)
    t0 = time.perf_counter()
    passes = _passes(wl.size)
    report_progress(progress or None, "render passes", 0, len(passes))
    for p, idx in enumerate(passes):
        idx3 = np.concatenate([idx, np.repeat(idx[-1:], 3 - idx.size)])
        lam = wl[idx3]
        mats = {k: material_at(m, lam) for k, m in scene.materials.items()}
        img = render_rgb(mi, scene.build(mi, mats, env.spectra[..., idx3], width, height, spp), spp, seed)
        out[..., idx] = img[..., :idx.size]
        report_progress(progress or None, "render passes", p + 1, len(passes))
    info = {"path": "spectral (band-packed)", "variant": mi.variant(), "passes": len(passes), "spp": spp,
            "width": width, "height": height, "seconds": time.perf_counter() - t0, "seed": seed,
            "scene": scene.describe(), "environment": env.describe()}
    return RenderResult(out, wl, env.units, info)


def band_materials(scene, sensitivity: np.ndarray, wavelength_nm: np.ndarray, env_mean: np.ndarray) -> dict:
    """Per-band material parameters of the fast path (exact for flat materials).

    Parameters
    ----------
    scene
        The scene (its ``materials``).
    sensitivity
        The bands' sensitivities ``(m, n)``.
    wavelength_nm
        Their grid ``(n,)`` (nm).
    env_mean
        The environment's mean spectrum ``(n,)`` on that grid.

    Returns
    -------
    dict
        Material key → parameter name → ``(m,)``: each band's mean of the parameter weighted by the band's
        sensitivity times the environment's mean spectrum.
    """
    w = np.asarray(sensitivity, float) * np.asarray(env_mean, float)[None, :]
    w /= np.maximum(w.sum(axis=1, keepdims=True), 1e-30)
    out = {}
    for key, m in scene.materials.items():
        params = material_at(m, wavelength_nm)
        out[key] = {p: w @ v for p, v in params.items()}
    return out


def render_fast(env: EnvironmentMap, estimator, scene, width: int = 256, height: int = 256, spp: int = 64,
                seed: int = 0, variant: str | None = None, linear_map: tuple[np.ndarray, np.ndarray] | None = None,
                progress: ProgressCallback | None = None) -> RenderResult:
    """Band fast path (module docstring): one RGB pass per camera's three bands, then the estimator per pixel.

    Parameters
    ----------
    env
        An environment map from a product (with its ``bands``, three per camera).
    estimator
        The product's estimator.
    scene
        :class:`MirrorBallScene` or :class:`XmlScene`.
    width, height, spp
        Image size (pixels) and samples per pixel.
    seed, variant
        Sampler seed and Mitsuba variant.
    linear_map
        ``(M (n, bands), b (n,))`` to apply as one linear map; ``None`` for the mixture with per-pixel weights.
    progress
        ``progress("render passes", done, total)`` before the first Mitsuba pass and after each.

    Returns
    -------
    RenderResult
        Spectra on the estimator's grid; its ``bands`` attribute holds the rendered bands.

    Raises
    ------
    ConfigurationError
        When the environment has no bands, three per camera.
    """

    _check_size(width, height, spp)
    if env.bands is None or env.bands.shape[2] % 3 or env.bands.shape[2] != estimator.n_bands:
        raise ConfigurationError("the fast path needs the environment's bands, three per camera (an environment "
                                 "from a product)")
    mi = mitsuba(variant)
    t0 = time.perf_counter()
    wl = np.asarray(estimator.wavelength_nm, float)
    omega = env.solid_angle_weights()[:, None, None]
    env_mean = (env.spectra * omega).sum(axis=(0, 1)) / (omega.sum() * env.width)
    env_mean = resample_spectra(env_mean, env.wavelength_nm, wl, outside="edge")
    mats = band_materials(scene, estimator.system_matrix, wl, env_mean)
    n_pass = env.bands.shape[2] // 3
    bands = np.empty((height, width, 3 * n_pass), np.float32)
    report_progress(progress or None, "render passes", 0, n_pass)
    for p, sl in enumerate(slice(3 * q, 3 * q + 3) for q in range(n_pass)):
        pass_mats = {k: {q: v[sl] for q, v in params.items()} for k, params in mats.items()}
        bands[..., sl] = render_rgb(mi, scene.build(mi, pass_mats, env.bands[..., sl], width, height, spp), spp, seed)
        report_progress(progress or None, "render passes", p + 1, n_pass)
    t_render = time.perf_counter() - t0
    if linear_map is not None:
        m, b = linear_map
        spectra = bands @ np.asarray(m, np.float32).T + np.asarray(b, np.float32)
    else:
        spectra = estimate_image(bands, estimator)
    spectra = np.maximum(spectra, 0.0).astype(np.float32)
    flat = all(getattr(m, "flat", False) for m in scene.materials.values())
    info = {"path": "six-band fast path", "variant": mi.variant(), "passes": 2, "spp": spp, "width": width,
            "height": height, "seconds": time.perf_counter() - t0, "render_seconds": t_render, "seed": seed,
            "exact": bool(flat and linear_map is not None), "note": FAST_PATH_NOTE,
            "materials_flat": flat, "scene": scene.describe(), "environment": env.describe()}
    result = RenderResult(spectra, wl, env.units, info)
    result.bands = bands
    return result


#: Image size and samples per pixel of a render when neither the caller nor the scene file gives them.
DEFAULT_WIDTH, DEFAULT_HEIGHT, DEFAULT_SPP = 256, 256, 64


def render_settings(scene, width: int | None = None, height: int | None = None,
                    spp: int | None = None) -> tuple[int, int, int]:
    """Width, height and samples per pixel of a render.

    Parameters
    ----------
    scene
        The scene (an :class:`XmlScene` gives its film's ``width``/``height`` and its sampler's ``sample_count``).
    width, height, spp
        Values given by the caller (``None``: not given).

    Returns
    -------
    tuple of int
        ``(width, height, spp)``: each value given wins, else the scene file's, else :data:`DEFAULT_WIDTH`,
        :data:`DEFAULT_HEIGHT`, :data:`DEFAULT_SPP`.
    """
    film_w, film_h = scene.film_size() if hasattr(scene, "film_size") else (None, None)
    count = scene.sample_count() if hasattr(scene, "sample_count") else None
    return (next(v for v in (width, film_w, DEFAULT_WIDTH) if v is not None),
            next(v for v in (height, film_h, DEFAULT_HEIGHT) if v is not None),
            next(v for v in (spp, count, DEFAULT_SPP) if v is not None))


def _check_size(width: int, height: int, spp: int) -> None:
    if min(width, height, spp) < 1:
        raise ConfigurationError(f"image size and samples per pixel must be positive, got {width}x{height}, {spp} spp")


# ------------------------------------------------------------------------------------------- outputs
def write_render(result: RenderResult, out_dir: str | Path, name: str = "render",
                 exposure: float | None = None) -> dict[str, str]:
    """Spectral EXR (Fichet 2021 layout), linear sRGB EXR and a tone-mapped PNG of a render, plus its JSON.

    Parameters
    ----------
    result
        The render.
    out_dir
        The output directory (created if needed).
    name
        Stem of the file names.
    exposure
        Scale of the linear RGB before the tone curve (default: the 99th luminance percentile at 1,
        :func:`auto_exposure_reference`).

    Returns
    -------
    dict
        ``spectral_exr``, ``srgb_exr``, ``png``, ``json`` → path.
    """

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rgb = result.linear_srgb()
    attrs = {"omnispectral_render": result.info["path"], "omnispectral_units": result.units}
    files = {"spectral_exr": str(write_spectral_exr(out / f"{name}_spectral.exr", result.spectra,
                                                    result.wavelength_nm, units=result.units, attributes=attrs)),
             "srgb_exr": str(write_rgb_exr(out / f"{name}_srgb.exr", rgb, attrs))}
    scale = exposure if exposure is not None else 1.0 / auto_exposure_reference(rgb)
    png = out / f"{name}.png"

    with atomic_path(png) as tmp:
        cv2.imwrite(str(tmp), np.ascontiguousarray(reinhard_srgb8(rgb * np.float32(scale))[..., ::-1]))
    files["png"] = str(png)
    atomic_write_json(out / f"{name}.json", {**result.info, "files": files, "exposure_scale": float(scale),
                                             "wavelength_nm": result.wavelength_nm.tolist()})
    files["json"] = str(out / f"{name}.json")
    return files


def auto_exposure_reference(rgb: np.ndarray, percentile: float = 99.0) -> float:
    """The level a preview puts at 1: a percentile of the luminance of linear sRGB.

    Parameters
    ----------
    rgb
        Linear sRGB ``(..., 3)`` (NaN as 0).
    percentile
        Of the positive pixels' luminance.

    Returns
    -------
    float
        The luminance; 1 when no pixel is positive.
    """
    lum = np.nan_to_num(np.asarray(rgb, np.float32)).clip(0) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    pos = lum[lum > 0]
    return float(np.percentile(pos, percentile)) if pos.size else 1.0


def render_product(product: str | Path, out_dir: str | Path, scene: str | None = None, width: int | None = None,
                   height: int | None = None, spp: int | None = None, level: int | None = None,
                   max_env_width: int = 1024, wavelength_step_nm: float | None = None, fast: bool = False,
                   seed: int = 0, variant: str | None = None, name: str = "render", exposure: float | None = None,
                   progress: ProgressCallback | None = None, **scene_kwargs) -> dict:
    """Render a product's environment with a scene (mirror ball by default) and write the outputs.

    Parameters
    ----------
    product
        The product directory.
    out_dir
        Where :func:`write_render` writes.
    scene
        ``None``/``"mirror-ball"`` or a Mitsuba XML file (:func:`scene_from_name`).
    width, height, spp
        ``None`` for the scene file's film and sampler, else the defaults (:func:`render_settings`).
    level, max_env_width
        The product's pyramid level for the environment (``None``: the finest at most ``max_env_width`` wide).
    wavelength_step_nm
        A coarser grid for the spectral render (:func:`wavelength_grid`).
    fast
        The six-band fast path (:func:`render_fast`) instead of the spectral render.
    seed, variant
        Sampler seed and Mitsuba variant.
    name, exposure
        Output file stem and exposure (:func:`write_render`).
    progress
        ``progress("environment", 0 | 1, 1)`` before and after reading the product, then
        ``progress("render passes", done, total)`` before the first Mitsuba pass and after each.
    **scene_kwargs
        Fields of :class:`MirrorBallScene`.

    Returns
    -------
    dict
        The render's ``info``, its ``files`` and ``total_seconds``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 6.1, Fig. 16 (spectral rendering with the captured panorama as the
       environment; a mirror ball on a grey plate).
    .. [2] A. Fichet, R. Pacanowski, A. Wilkie, "An OpenEXR Layout for Spectral Images", JCGT 10(3), 2021
       (the spectral EXR written by :func:`write_render`).
    .. [3] CIE 015:2018, Colorimetry, 4th ed. (the CIE 1931 observer of the sRGB outputs).
    """

    t0 = time.perf_counter()
    check_output_outside_inputs([out_dir], [product])
    sc = scene_from_name(scene, **scene_kwargs)
    width, height, spp = render_settings(sc, width, height, spp)
    report_progress(progress or None, "environment", 0, 1)  # reading the product and its estimator takes seconds
    env, estimator = environment_from_product(product, level, max_env_width)
    report_progress(progress or None, "environment", 1, 1)
    claim_output_directory(out_dir, "render")  # after the inputs opened: a bad input leaves no empty output
    if fast:
        result = render_fast(env, estimator, sc, width, height, spp, seed, variant, progress=progress)
    else:
        result = render_spectral(env, sc, width, height, spp, wavelength_step_nm, seed, variant, progress)
    files = write_render(result, out_dir, name, exposure)
    return {**result.info, "files": files, "total_seconds": time.perf_counter() - t0}
