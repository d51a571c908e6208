"""Measured surface reflectances for the procedural scene, chosen by colour from the built-in sets.

Each material of the scene names a pool of measured reflectances and a target colour (CIELAB
under D65, CIE 1931 2°); the material is one of the ``k`` samples nearest to the target (ΔE*ab),
drawn with the scene's seed.  The pools are the Vrhel, Gershon & Iwan (1994) sets shipped with
the package and the RAW to ACES training spectra from colour-science; "natural" is Vrhel objects
1-44 (the natural objects of ISETCam's ``Nature_Vhrel`` selection, without the food items).
So the scene's walls, ground and foliage carry real spectral shapes, not synthetic curves.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.spectral.colour import reflectance_lab
from omnispectral.spectral.curves import SpectralSet
from omnispectral.spectral.library import load_reflectances

__all__ = ["SCENE_MATERIALS", "Material", "MaterialSpec", "choose_materials", "colorchecker_reflectances"]

#: Grid on which candidate colours are computed (covered by every pool).
_LAB_GRID_NM = np.arange(400.0, 700.0 + 1e-9, 10.0)


@dataclass(frozen=True)
class MaterialSpec:
    """What a scene material should look like and where to look for it."""

    name: str
    target_lab: tuple[float, float, float]
    pools: tuple[str, ...]
    max_chroma: float | None = None


@dataclass(frozen=True)
class Material:
    """A chosen reflectance: the scene's name for it, its data-set sample and the curve on the scene grid."""

    name: str
    source_set: str
    sample: str
    lab_d65: tuple[float, float, float]
    reflectance: np.ndarray


#: The procedural scene's materials (name, target CIELAB under D65, pools).
SCENE_MATERIALS = (
    MaterialSpec("pavement", (45.0, 0.0, 3.0), ("vrhel-munsell", "vrhel-objects", "rawtoaces-training"), 5.0),
    MaterialSpec("grass", (40.0, -15.0, 26.0), ("natural",)),
    MaterialSpec("hedge", (33.0, -12.0, 20.0), ("natural",)),
    MaterialSpec("brick", (42.0, 22.0, 22.0), ("vrhel-objects", "vrhel-munsell", "rawtoaces-training")),
    MaterialSpec("white wall", (82.0, 0.0, 4.0), ("vrhel-munsell", "vrhel-objects", "rawtoaces-training"), 6.0),
    MaterialSpec("concrete", (60.0, 0.0, 5.0), ("vrhel-munsell", "vrhel-objects", "rawtoaces-training"), 8.0),
    MaterialSpec("dark facade", (30.0, 2.0, 6.0), ("vrhel-objects", "vrhel-munsell", "rawtoaces-training")),
    MaterialSpec("painted post", (45.0, -5.0, -35.0), ("vrhel-dupont",)),
)


@cache
def _pool(name: str) -> tuple[SpectralSet, np.ndarray]:
    """A pool's reflectances (native sampling) and their CIELAB under D65."""
    if name == "natural":
        s = load_reflectances("vrhel-objects")
        s = s.subset(np.arange(len(s)) < 44)
    else:
        s = load_reflectances(name)
    return s, reflectance_lab(_LAB_GRID_NM, s.resample(_LAB_GRID_NM).values)


def _pool_label(name: str) -> str:
    return "vrhel-objects" if name == "natural" else name


def choose_materials(specs, wavelength_nm: np.ndarray, rng: np.random.Generator, k: int = 3) -> list[Material]:
    """For each spec, one of the ``k`` pool samples nearest its target (ΔE*ab), drawn with ``rng``; no sample twice."""
    used: set[str] = set()
    out = []
    for spec in specs:
        names, rows, lab = [], [], []
        for pool in spec.pools:
            s, c = _pool(pool)
            names += [f"{_pool_label(pool)}:{n}" for n in s.names]
            rows += [(s, j) for j in range(len(s))]
            lab.append(c)
        lab_a = np.vstack(lab)
        de = np.linalg.norm(lab_a - np.asarray(spec.target_lab), axis=1)
        if spec.max_chroma is not None:
            de[np.hypot(lab_a[:, 1], lab_a[:, 2]) > spec.max_chroma] = np.inf
        de[[i for i, n in enumerate(names) if n in used]] = np.inf
        order = np.argsort(de, kind="stable")[:k]
        order = order[np.isfinite(de[order])]
        if order.size == 0:
            raise ConfigurationError(f"no reflectance in {spec.pools} fits material {spec.name!r}")
        i = int(order[rng.integers(order.size)])
        used.add(names[i])
        set_name, sample = names[i].split(":", 1)
        s, j = rows[i]
        curve = _resample_curve(s.subset(np.arange(len(s)) == j), wavelength_nm)
        out.append(Material(spec.name, set_name, sample, tuple(float(x) for x in lab_a[i]), curve))
    return out


def _resample_curve(curve: SpectralSet, wavelength_nm: np.ndarray) -> np.ndarray:
    """One measured curve on the scene grid (linear interpolation, no extrapolation)."""
    wl = np.asarray(wavelength_nm, dtype=np.float64)
    if not curve.covers(wl):
        raise ConfigurationError(f"the procedural scene's reflectances cover 400-700 nm; the wavelength grid "
                                 f"{wl.min():g}-{wl.max():g} nm goes beyond it")
    return curve.resample(wl).values[0]


def colorchecker_reflectances(wavelength_nm: np.ndarray) -> tuple[tuple[str, ...], np.ndarray]:
    """The 24 ColorChecker patches (N. Ohta, via ``load_reflectances("colorchecker")``) on ``wavelength_nm``."""
    s = load_reflectances("colorchecker").resample(np.asarray(wavelength_nm, dtype=np.float64))
    return s.names, s.values
