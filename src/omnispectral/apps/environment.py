"""A product's spectral radiance as an environment map for image-based lighting (paper Sec. 6.1).

The product stores six bands (DN/s) and its Wiener estimator; the environment map is the estimator
applied per pixel (mixture prior, per-pixel posterior weights) at one pyramid level, clipped at 0
(an estimate can undershoot on dark or noisy pixels; light is never negative).

- **Saturated pixels.** Pixels saturated in every exposure of the bracket (the sun disk) hold the
  shortest exposure's value: a lower bound of the true radiance (paper Sec. 4.1, ``imaging.hdr``).
  They are flagged: a pixel of the chosen level is saturated when any level-0 pixel under it reaches
  95 % of the shortest exposure's clipping level (``0.99 · max_dn / t_shortest``, from the rig
  snapshot in the store).  Their share of the map's energy is reported, since a render's highlights
  and cast shadows are then too weak by an unknown factor.
- **Uncovered pixels** (``NaN``: no direction saw them, e.g. below the head) take the value of the
  nearest covered pixel of the same column, and are flagged.
- **Grid.** Spectra are on the estimator's grid (400–700 nm / 5 nm); :meth:`EnvironmentMap.resampled`
  gives a coarser grid (linear interpolation, no extrapolation).
- **Orientation.** The panorama's equirectangular convention (row 0 at +90°, column 0 at −180°, +Y up,
  lon 0 = +Z, lon +90° = −X) is Mitsuba's environment-map orientation: the map is used unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.product.layout import open_product
from omnispectral.product.saturation import saturated_mask, saturation_level_dn_s
from omnispectral.product.spectra import SunOverlay, estimate_image
from omnispectral.spectral.curves import resample_matrix

__all__ = ["DEFAULT_MAX_WIDTH", "EnvironmentMap", "choose_level", "environment_from_bands", "environment_from_product",
           "fill_uncovered", "uniform_environment"]

#: Default largest environment width picked when no level is given (px).
DEFAULT_MAX_WIDTH = 1024


@dataclass
class EnvironmentMap:
    """Spectral radiance on an equirectangular grid, with what it knows about its own reliability."""

    spectra: np.ndarray  # (H, W, n) float32, >= 0
    wavelength_nm: np.ndarray  # (n,)
    units: str
    bands: np.ndarray | None = None  # (H, W, m) float32 >= 0 (the six bands it was estimated from), if any
    saturated: np.ndarray | None = None  # (H, W) bool: a lower bound only (None: unknown)
    filled: np.ndarray | None = None  # (H, W) bool: uncovered in the product, filled from its column
    info: dict = field(default_factory=dict)

    @property
    def height(self) -> int:
        """Rows of the map."""
        return self.spectra.shape[0]

    @property
    def width(self) -> int:
        """Columns of the map."""
        return self.spectra.shape[1]

    def resampled(self, wavelength_nm: np.ndarray) -> EnvironmentMap:
        """The same map on another wavelength grid.

        Linear interpolation within the current range, as one float32 matrix product
        (:func:`omnispectral.spectral.curves.resample_matrix`).

        Parameters
        ----------
        wavelength_nm
            The new grid (nm), within the current one.

        Returns
        -------
        EnvironmentMap
            A copy with the resampled spectra.

        Raises
        ------
        ConfigurationError
            When the new grid reaches outside the current one.
        """
        m = resample_matrix(self.wavelength_nm, np.asarray(wavelength_nm, float)).astype(np.float32)
        return replace(self, spectra=self.spectra @ m.T, wavelength_nm=np.asarray(wavelength_nm, float).copy())

    def solid_angle_weights(self) -> np.ndarray:
        """Solid angle of each row's pixels.

        Returns
        -------
        numpy.ndarray
            ``(H,)`` steradians.
        """
        h, w = self.height, self.width
        lat_edges = np.radians(90.0 - np.arange(h + 1) * 180.0 / h)
        return (2 * math.pi / w) * (np.sin(lat_edges[:-1]) - np.sin(lat_edges[1:]))

    def describe(self) -> dict:
        """JSON-able summary: size, grid, flags and the saturated pixels' share of the energy.

        Returns
        -------
        dict
        """
        omega = self.solid_angle_weights()[:, None]
        power = (self.spectra.sum(axis=2) * omega)
        total = float(power.sum())
        out = {"width": self.width, "height": self.height, "n_wavelengths": int(self.wavelength_nm.size),
               "wavelength_nm": [float(self.wavelength_nm[0]), float(self.wavelength_nm[-1])],
               "units": self.units, **self.info}
        if self.saturated is None:
            out["saturated"] = "unknown (the product has no rig snapshot to tell the clipping level)"
        else:
            out["saturated_pixels"] = int(self.saturated.sum())
            out["saturated_energy_fraction"] = float(power[self.saturated].sum() / total) if total > 0 else 0.0
        if self.filled is not None:
            out["filled_fraction"] = float(self.filled.mean())
        return out


def uniform_environment(spectrum: np.ndarray, wavelength_nm: np.ndarray, height: int = 16,
                        units: str = "relative") -> EnvironmentMap:
    """A constant environment (every direction the same spectral radiance): a test and a reference.

    Parameters
    ----------
    spectrum
        The spectral radiance ``(n,)``.
    wavelength_nm
        Its grid (nm).
    height
        Rows (the width is twice that).
    units
        The radiance's units.

    Returns
    -------
    EnvironmentMap
    """
    s = np.asarray(spectrum, np.float32)
    return EnvironmentMap(np.broadcast_to(s, (height, 2 * height, s.size)).copy(),
                          np.asarray(wavelength_nm, float), units, info={"source": "uniform"})


def fill_uncovered(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Replace non-finite pixels by the nearest finite pixel of their column; columns with nothing finite become 0.

    Parameters
    ----------
    values
        ``(H, W, c)``.

    Returns
    -------
    tuple
        The filled values and the ``(H, W)`` mask of the replaced pixels.
    """
    bad = ~np.isfinite(values).all(axis=2)
    if not bad.any():
        return values, bad
    h, w = bad.shape
    rows = np.arange(h)[:, None].repeat(w, axis=1)
    above = np.where(~bad, rows, -1)
    above = np.maximum.accumulate(above, axis=0)  # last finite row at or above
    below = np.where(~bad, rows, h)
    below = np.minimum.accumulate(below[::-1], axis=0)[::-1]  # first finite row at or below
    use_above = (above >= 0) & ((below >= h) | (rows - above <= below - rows))
    src = np.where(use_above, above, below)
    cols = np.arange(w)[None, :].repeat(h, axis=0)
    ok = (src >= 0) & (src < h)
    out = values.copy()
    out[bad & ok] = values[src[bad & ok], cols[bad & ok]]
    out[bad & ~ok] = 0.0
    return out, bad


def choose_level(shapes: list[tuple[int, int]], level: int | None, max_width: int = DEFAULT_MAX_WIDTH) -> int:
    """The pyramid level to use.

    Parameters
    ----------
    shapes
        ``(height, width)`` of each level, finest first.
    level
        A level asked for (checked), or ``None``.
    max_width
        With ``level=None``: the finest level at most this wide (the coarsest if none is).

    Returns
    -------
    int

    Raises
    ------
    ConfigurationError
        For a level that does not exist.
    """
    if level is not None:
        if not 0 <= level < len(shapes):
            raise ConfigurationError(f"level {level} does not exist; the product has levels 0-{len(shapes) - 1} "
                                     f"({', '.join(f'{w}x{h}' for h, w in shapes)})")
        return level
    for k, (_, w) in enumerate(shapes):
        if w <= max_width:
            return k
    return len(shapes) - 1


def environment_from_bands(bands: np.ndarray, estimator, units: str, saturated: np.ndarray | None = None,
                           info: dict | None = None, linear_map: tuple | None = None,
                           sun: SunOverlay | None = None) -> EnvironmentMap:
    """Environment map from band radiance: uncovered pixels filled, spectra estimated, clipped at 0.

    Parameters
    ----------
    bands
        Band radiance ``(H, W, m)``.
    estimator
        The product's estimator (per-pixel mixture estimate).
    units
        The radiance's units.
    saturated
        ``(H, W)`` flags of lower-bound pixels, if known.
    info
        Recorded in the map's ``info``.
    linear_map
        ``(M (n, m), b (n,))`` to apply instead of the mixture estimate.
    sun
        The recovered sun (:class:`~omnispectral.product.spectra.SunOverlay`): its pixels take its measured
        spectrum.

    Returns
    -------
    EnvironmentMap
    """

    filled_bands, filled = fill_uncovered(np.asarray(bands, np.float32))
    filled_bands = np.maximum(filled_bands, 0.0)
    if linear_map is not None:
        spectra = filled_bands @ np.asarray(linear_map[0], np.float32).T + np.asarray(linear_map[1], np.float32)
    else:
        spectra = estimate_image(filled_bands, estimator, sun=sun)
    spectra = np.maximum(spectra, 0.0)
    return EnvironmentMap(spectra.astype(np.float32), np.asarray(estimator.wavelength_nm, float), units,
                          filled_bands, saturated, filled, dict(info or {}))


def environment_from_product(product: str | Path, level: int | None = None, max_width: int = DEFAULT_MAX_WIDTH):
    """The environment map of a processed product at a pyramid level (module docstring).

    Parameters
    ----------
    product
        The product directory.
    level, max_width
        The level (:func:`choose_level`).

    Returns
    -------
    tuple
        ``(EnvironmentMap, estimator)``.
    """

    index, store, estimator = open_product(product)
    level = choose_level(store.shapes, level, max_width)
    bands = store.read(level)
    clip = saturation_level_dn_s(store.attrs())
    sat = saturated_mask(store, level, bands, clip) if clip is not None else None
    units = f"{index.get('units', 'DN per second of exposure')} per unit of the system matrix"
    sun_record = (store.attrs().get("omnispectral") or {}).get("sun") or {}
    env = environment_from_bands(bands, estimator, units, sat,
                                 {"source": str(Path(product).resolve()), "level": level,
                                  "saturation_level_dn_s": clip,
                                  "sun": {k: sun_record.get(k) for k in ("method", "recovered", "model_estimate",
                                                                         "note")}},
                                 sun=SunOverlay.of(store, level, bands.shape[:2]))
    return env, estimator
