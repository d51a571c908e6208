"""Spectra as a linear view of the six bands: per-pixel spectra, uncertainty and colour on demand.

The product stores six bands (DN/s) and the estimator's parameters.  A spectrum at a direction is the
Wiener estimate of the six bands there (mixture prior: per-pixel posterior weights), with its
posterior standard deviation.  Whole images use the mixture per pixel (exports) or, for colour
previews, the single linear map the mixture becomes for the region's mean component weights
(``WienerEstimator.linear_map``), folded with the CIE 1931 observer into one 3 × 6 matrix.

Pixels holding the recovered sun (:mod:`omnispectral.product.sun`) are not left to the Wiener prior, whose
colour signals are reflectances under light sources, not the sun itself: their bands are split into the sun's
share ``c L_sun`` (``c`` the least-squares coverage of the pixel by the disk) and the sky's rest, and the
spectrum is the rest's estimate plus ``c`` times the sun's measured spectral radiance (:func:`SunOverlay`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from omnispectral.errors import ConfigurationError
from omnispectral.imaging.geometry import lonlat_to_equirect_pixel
from omnispectral.product.layout import open_product
from omnispectral.product.saturation import recovered_sun_mask, saturated_mask, saturation_level_dn_s
from omnispectral.spectral.colour import spectra_to_linear_srgb, spectra_to_xyz, xyz_to_linear_srgb

__all__ = ["DERIVED_B_LAYERS", "SunOverlay", "bands_to_linear_srgb", "derived_b_layers", "estimate_image",
           "linear_srgb_map", "predicted_b_rel_std", "predicted_noise_variance", "region_weights", "spectrum_at",
           "spectrum_in_store", "sun_state"]


def region_weights(bands: np.ndarray, estimator, n_sample: int = 20000, seed: int = 0) -> np.ndarray | None:
    """Mean posterior component weights over (a sample of) the finite pixels; ``None`` for a single Gaussian."""
    if estimator.n_components == 1:
        return None
    flat = bands.reshape(-1, bands.shape[-1])
    ok = np.flatnonzero(np.isfinite(flat).all(axis=1) & (flat.sum(axis=1) > 0))
    if ok.size == 0:
        return np.asarray(estimator.weights, float)
    pick = np.random.default_rng(seed).choice(ok, min(n_sample, ok.size), replace=False)
    return np.asarray(estimator.component_posterior(flat[pick]), float).mean(axis=0)


def bands_to_linear_srgb(bands: np.ndarray, estimator, sun: SunOverlay | None = None) -> np.ndarray:
    """Linear sRGB-primaries RGB of a six-band image through the region's linear spectral map (NaN kept);
    at the recovered sun's pixels (``sun``) the disk's share takes the colour of its measured spectrum."""
    mat, offset = linear_srgb_map(bands, estimator)
    if sun is None:
        return np.asarray(bands, np.float32) @ mat + offset
    h, w, m = bands.shape
    flat = np.asarray(bands, np.float64).reshape(-1, m)
    cov = np.zeros(flat.shape[0])
    at = sun.mask.reshape(-1) & np.isfinite(flat).all(axis=1)
    cov[at] = sun.coverage(flat[at])
    wl = np.asarray(estimator.wavelength_nm)
    sun_rgb = spectra_to_linear_srgb(sun.spectral_radiance[None], wl)[0]
    rgb = (flat - cov[:, None] * sun.band_radiance[None]) @ mat + offset + cov[:, None] * sun_rgb[None]
    return rgb.reshape(h, w, 3).astype(np.float32)


def linear_srgb_map(bands: np.ndarray, estimator) -> tuple[np.ndarray, np.ndarray]:
    """``(6 × 3 matrix, offset (3,))`` taking six bands to linear sRGB-primaries RGB: the estimator's linear map
    for the region weights of ``bands`` (:func:`region_weights`), folded with the CIE 1931 observer."""

    m, b = estimator.linear_map(region_weights(bands, estimator))
    wl = np.asarray(estimator.wavelength_nm)
    to_rgb = xyz_to_linear_srgb(spectra_to_xyz(np.eye(wl.size, dtype=np.float32), wl))  # (n, 3)
    mat = (np.asarray(m).T @ to_rgb).astype(np.float32)  # (6, 3)
    return mat, (np.asarray(b, np.float32) @ to_rgb).astype(np.float32)


@dataclass(frozen=True)
class SunOverlay:
    """The recovered sun in a window of a pyramid level: which pixels hold it and its measured radiance."""

    mask: np.ndarray  # (H, W) bool
    background: np.ndarray  # (m,) sky bands around the disk
    band_radiance: np.ndarray  # (m,)
    spectral_radiance: np.ndarray  # (n,)
    spectral_radiance_std: np.ndarray  # (n,)

    @classmethod
    def of(cls, store, level: int, shape: tuple[int, int], origin: tuple[int, int] = (0, 0)) -> SunOverlay | None:
        """The overlay of a ``shape`` window at ``origin`` of ``level``, or ``None`` (no recovered sun there)."""
        return cls.from_attrs(store.attrs(), tuple(store.shapes[0]), level, shape, origin)

    @classmethod
    def from_attrs(cls, attrs: dict, level0_shape: tuple[int, int], level: int, shape: tuple[int, int],
                   origin: tuple[int, int] = (0, 0)) -> SunOverlay | None:
        """:meth:`of` from the store's attributes already read (a caller visiting many windows reads them once)."""
        sun = (attrs.get("omnispectral") or {}).get("sun") or {}
        if not sun.get("recovered"):
            return None
        mask = recovered_sun_mask(attrs, level, shape, origin, level0_shape)
        if not mask.any():
            return None
        return cls(mask, np.asarray(sun["pixels"]["background"], np.float64),
                   np.asarray(sun["band_radiance"], np.float64), np.asarray(sun["spectral_radiance"], np.float64),
                   np.asarray(sun["spectral_radiance_std"], np.float64))

    def coverage(self, bands: np.ndarray) -> np.ndarray:
        """Least-squares share of the disk in each pixel ``(k,)`` of bands ``(k, m)``:
        ``c = Σ (b − b_sky) L / Σ L²``, at least 0."""
        lr = self.band_radiance
        return np.clip((bands - self.background) @ lr / float(lr @ lr), 0.0, None)


#: The quality layers (``mosaic.store.QUALITY_LAYERS``) that hold the relative error of camera B's bands where
#: they are derived from A's: predicted where B saw nothing (:mod:`omnispectral.mosaic.predict`), B's two
#: surfaces mixed in A's share at an edge (:mod:`omnispectral.mosaic.unmix`).
DERIVED_B_LAYERS = ("b_predicted", "b_unmixed")


def derived_b_layers(store, level: int, shape: tuple[int, int],
                     origin: tuple[int, int] = (0, 0)) -> dict[str, np.ndarray]:
    """Each of :data:`DERIVED_B_LAYERS` the product has, over a ``shape`` window at ``origin`` of ``level``, from
    one read of the quality array: the relative error of camera B's bands derived from A's (a pixel of a coarser
    level takes the largest of the level-0 pixels it averages), 0 where B measured the pixel."""
    if not store.has_quality():
        return {}
    names = (store.attrs().get("omnispectral", {}).get("quality") or {}).get("layers", [])
    present = [name for name in DERIVED_B_LAYERS if name in names]
    if not present:
        return {}
    f = 2 ** level
    h0, w0 = store.shapes[0]
    r0, c0 = origin[0] * f, origin[1] * f
    quality = store.read_quality(slice(r0, min(h0, r0 + shape[0] * f)), slice(c0, min(w0, c0 + shape[1] * f)))
    return {name: _largest_per_cell(np.nan_to_num(quality[..., names.index(name)], nan=0.0), f, shape)
            for name in present}


def _largest_per_cell(layer: np.ndarray, f: int, shape: tuple[int, int]) -> np.ndarray:
    """``shape`` float32: the largest value of each ``f × f`` cell of a level-0 ``layer`` (0 beyond it)."""
    out = np.zeros(shape, np.float32)
    hh, ww = -(-layer.shape[0] // f), -(-layer.shape[1] // f)
    padded = np.zeros((hh * f, ww * f), np.float32)
    padded[:layer.shape[0], :layer.shape[1]] = layer
    coarse = padded.reshape(hh, f, ww, f).max(axis=(1, 3))
    out[:min(hh, shape[0]), :min(ww, shape[1])] = coarse[:shape[0], :shape[1]]
    return out


def predicted_b_rel_std(store, level: int, shape: tuple[int, int],
                        origin: tuple[int, int] = (0, 0)) -> np.ndarray | None:
    """The relative error of camera B's derived bands over a window (:func:`derived_b_layers`, the largest of
    its layers), 0 where B measured the pixel; ``None`` when the product has none of them."""
    layers = derived_b_layers(store, level, shape, origin)
    return np.maximum.reduce(list(layers.values())) if layers else None


def predicted_noise_variance(bands: np.ndarray, b_rel_std: np.ndarray) -> np.ndarray:
    """Noise variance ``(k, m)`` of bands ``(k, m)`` whose camera-B bands (3–5) were predicted from A's with
    relative error ``b_rel_std`` ``(k,)`` (:func:`predicted_b_rel_std`)."""
    var = np.zeros(bands.shape, np.float64)
    var[:, 3:6] = (np.asarray(b_rel_std, np.float64)[:, None] * bands[:, 3:6]) ** 2
    return var


def estimate_image(bands: np.ndarray, estimator, with_std: bool = False, sun: SunOverlay | None = None,
                   b_rel_std: np.ndarray | None = None):
    """Per-pixel mixture estimate of an image ``(H, W, 6)`` → ``(H, W, n)`` (NaN where bands are not finite);
    ``sun`` replaces the prior's guess at the recovered sun's pixels (module docstring).  ``b_rel_std``
    ``(H, W)`` (:func:`predicted_b_rel_std`, NaN or 0 where B measured the pixel) adds the error of B's
    derived bands to their noise variance there, so estimate and posterior std weigh them accordingly.

    Parameters
    ----------
    bands : numpy.ndarray
        ``(H, W, m)`` bands in DN/s (six; B's noise term applies to six bands only).
    estimator : WienerEstimator
        The product's estimator.
    with_std : bool
        Also return the posterior standard deviation.
    sun : SunOverlay, optional
        The recovered sun's pixels, band and spectral radiance.
    b_rel_std : numpy.ndarray, optional
        ``(H, W)`` relative error of camera B's predicted bands (NaN or 0 where B measured the pixel).

    Returns
    -------
    spectra : numpy.ndarray
        ``(H, W, n)`` float32 spectra on ``estimator.wavelength_nm``, in DN/s per unit of the system matrix
        (relative spectral radiance); NaN where the bands are not finite.
    std : numpy.ndarray
        ``(H, W, n)`` posterior standard deviations in the same units; only with ``with_std``.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.6, Eq. (7) (the Wiener estimate of each pixel's colour signal).
    .. [2] S. M. Kay, Fundamentals of Statistical Signal Processing: Estimation Theory, Prentice Hall, 1993,
       Ch. 11-12 (the linear MMSE estimate and its posterior covariance under a per-pixel noise covariance).
    """
    h, w, c = bands.shape
    flat = bands.reshape(-1, c)
    ok = np.isfinite(flat).all(axis=1)
    cov = np.zeros(flat.shape[0])
    if sun is not None:
        at = sun.mask.reshape(-1) & ok
        cov[at] = sun.coverage(flat[at].astype(np.float64))
        flat = flat - (cov[:, None] * sun.band_radiance[None, :]).astype(flat.dtype)
    noisy = np.zeros(flat.shape[0], bool)
    if b_rel_std is not None and c == 6:
        rel = np.nan_to_num(np.asarray(b_rel_std, np.float64).reshape(-1), nan=0.0)
        noisy = ok & (rel > 0)
    plain = ok & ~noisy
    var = predicted_noise_variance(flat[noisy].astype(np.float64), rel[noisy]) if noisy.any() else None
    spectra = np.full((flat.shape[0], len(estimator.wavelength_nm)), np.nan, np.float32)
    spectra[plain] = estimator.estimate(flat[plain])
    if var is not None:
        spectra[noisy] = estimator.estimate(flat[noisy], noise_variance=var)
    if sun is not None:
        spectra += (cov[:, None] * sun.spectral_radiance[None, :]).astype(np.float32)
    if not with_std:
        return spectra.reshape(h, w, -1)
    std = np.full_like(spectra, np.nan)
    std[plain] = estimator.posterior_std(flat[plain])
    if var is not None:
        std[noisy] = estimator.posterior_std(flat[noisy], noise_variance=var)
    if sun is not None:
        std = np.hypot(std, (cov[:, None] * sun.spectral_radiance_std[None, :]).astype(np.float32))
    return spectra.reshape(h, w, -1), std.reshape(h, w, -1)


def sun_state(store, level: int, patch: np.ndarray, origin: tuple[int, int], recovered: bool) -> dict:
    """What a probe at the sun says: ``sun`` is ``"recovered"`` (the disk's share is the measured or modelled
    sun, :mod:`omnispectral.product.sun`), ``"lower bound"`` (clipped in every exposure and not recovered:
    ``warning``) or absent."""
    if recovered:
        return {"sun": "recovered"}
    level_dn_s = saturation_level_dn_s(store.attrs())
    if level_dn_s is None or not saturated_mask(store, level, patch, level_dn_s, origin).any():
        return {}
    return {"sun": "lower bound", "warning": "the direction is clipped in every exposure (the sun) and the product "
                                             "did not recover it: the values are a lower bound"}


def spectrum_at(product: str | Path, lon_deg: float, lat_deg: float, level: int = 0) -> dict:
    """The six bands, estimated spectrum, its posterior std and colour at a direction (bilinear in the bands)."""
    return spectrum_in_store(*open_product(product), lon_deg, lat_deg, level=level)


def spectrum_in_store(index: dict, store, estimator, lon_deg: float, lat_deg: float, level: int = 0) -> dict:
    """:func:`spectrum_at` for a product already opened with :func:`open_product` (index, store, estimator).

    Parameters
    ----------
    index : dict
        The product's ``product.json`` (its ``units`` and ``bands``).
    store : PanoramaStore
        The product's panorama.
    estimator : WienerEstimator
        The product's estimator.
    lon_deg, lat_deg : float
        The direction in degrees (longitude wrapped to [-180, 180), latitude in [-90, 90]).
    level : int
        The pyramid level read (0: full resolution).

    Returns
    -------
    dict
        ``lon_deg``, ``lat_deg``, ``level``, ``pixel`` (column, row on the level), the ``bands`` (bilinear in
        the four nearest pixels, DN/s), ``wavelength_nm``, ``spectrum`` and its posterior ``std`` (DN/s per
        unit of the system matrix, ``units``), its CIE ``XYZ`` and ``linear_srgb``, and the sun's state and
        ``b_predicted_rel_std`` (the relative error of camera B's bands where they were derived from A's:
        predicted or unmixed, :data:`DERIVED_B_LAYERS`) where they apply.

    Raises
    ------
    ConfigurationError
        For a direction that is not finite or a latitude beyond ±90°, a level that does not exist, or a
        direction the panorama does not cover.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.6, Eq. (7) (the Wiener estimate), Fig. 11 (spectra at points of
       the scene).
    .. [2] S. M. Kay, Fundamentals of Statistical Signal Processing: Estimation Theory, Prentice Hall, 1993,
       Ch. 11-12 (the posterior covariance of the linear MMSE estimator).
    .. [3] CIE 015:2018, Colorimetry, 4th ed. (the CIE 1931 observer of ``XYZ`` and ``linear_srgb``).
    """

    if not (np.isfinite(lon_deg) and np.isfinite(lat_deg)) or abs(lat_deg) > 90:
        raise ConfigurationError(f"no direction at lon {lon_deg}, lat {lat_deg} (latitude must be in [-90, 90])")
    if not 0 <= level < len(store.shapes):
        raise ConfigurationError(f"level {level} does not exist (0-{len(store.shapes) - 1})")
    h, w = store.shapes[level]
    lon = (lon_deg + 180.0) % 360.0 - 180.0
    col, row = lonlat_to_equirect_pixel(lon, lat_deg, w, h)
    c0, r0 = int(np.floor(col)), int(np.clip(np.floor(row), 0, h - 2))
    fc, fr = float(col - c0), float(np.clip(row - r0, 0, 1))
    cols = [c0 % w, (c0 + 1) % w]
    patch = np.stack([store.read(level, slice(r0, r0 + 2), slice(c, c + 1))[:, 0] for c in cols], axis=1)
    wts = np.array([[(1 - fr) * (1 - fc), (1 - fr) * fc], [fr * (1 - fc), fr * fc]])
    if not np.isfinite(patch).all():
        raise ConfigurationError(f"lon {lon_deg}, lat {lat_deg} is not covered by the panorama (no direction saw it)")
    bands = np.tensordot(wts, patch, axes=([0, 1], [0, 1]))
    sun = SunOverlay.of(store, level, (2, 2), (r0, c0 % w))
    if sun is not None:  # bilinear weights over the four pixels: the sun's share follows the same weights
        sun = SunOverlay(np.ones((1, 1), bool), sun.background, sun.band_radiance, sun.spectral_radiance,
                         sun.spectral_radiance_std)
    rel_cols = [predicted_b_rel_std(store, level, (2, 1), (r0, c)) for c in cols]
    b_rel = None if rel_cols[0] is None else np.array([[float((wts * np.hstack(rel_cols)).sum())]])
    spectrum, std = (x[0, 0] for x in estimate_image(bands[None, None], estimator, True, sun, b_rel))
    wl = np.asarray(estimator.wavelength_nm)
    return {"lon_deg": lon, "lat_deg": float(lat_deg), "level": level, "pixel": [float(col), float(row)],
            **sun_state(store, level, patch, (r0, c0 % w), sun is not None),
            **({"b_predicted_rel_std": float(b_rel[0, 0])} if b_rel is not None and b_rel[0, 0] > 0 else {}),
            "units": index["units"] + " per unit of the system matrix (spectral radiance, relative)",
            "bands": dict(zip(index["bands"], map(float, bands), strict=True)),
            "wavelength_nm": wl.tolist(), "spectrum": spectrum.tolist(), "std": std.tolist(),
            "XYZ": spectra_to_xyz(spectrum[None], wl)[0].tolist(),
            "linear_srgb": spectra_to_linear_srgb(spectrum[None], wl)[0].tolist()}
