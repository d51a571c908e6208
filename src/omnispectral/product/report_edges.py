"""Per-pixel error against the simulator's truth, at depth edges and on smooth regions; holes; worst pixels.

What the report's aggregates (band PSNR, ColorChecker ΔE*ab) do not show: where the error is.  Everything here
is on the product's grid (pyramid level 0), over the *scored* pixels: covered by the panorama (every band
finite) and not touched by the saturated sun (the mask of :func:`omnispectral.product.report.accuracy`).

Per-pixel errors (:func:`pixel_errors`)
    ``band_nrmse`` = ‖b − t‖₂ / ‖t‖₂ over the bands at the pixel (b the panorama's bands, t the truth's bands
    area-averaged onto the grid, both DN/s): a relative error, scale included (the error map and the worst
    pixels).  ``delta_e_ab`` = CIE 1976
    ΔE*ab between the spectrum the product's estimator gives from b and the one it gives from t (the *same*
    estimator on both, so the estimator's own error cancels and what remains is the pipeline's: merge,
    registration, resampling, blending), CIELAB with the white of a perfect diffuser at the ColorChecker (the
    white of the report's chart ΔE*ab) or, without a chart, a perfect diffuser facing up under the truth's sky
    (:func:`reference_white`).

Region figures (:func:`region_figures`)
    ``band_nrmse``: the region's RMS band error over the RMS of its truth, ``sqrt(Σ‖b − t‖² / Σ‖t‖²)`` over its
    pixels (the usual NRMSE; a mean of per-pixel ratios would be ruled by a few dark pixels beside bright ones,
    where a tenth of a pixel of misregistration makes a relative error of several times 1);
    ``band_nrmse_by_camera``: the same per camera (``A``, ``B``: camera A is never registered, so what B adds at
    the edges is B's registration; what both have is resampling and blending); ``band_nrmse_median``: the median
    per-pixel ``band_nrmse``; ``delta_e_ab`` and ``delta_e_ab_median``: mean and median per-pixel ΔE*ab.
    ``ratio``: edge / smooth of each.

Depth discontinuities (:func:`depth_discontinuities`)
    On the truth's depth map (``ground_truth/depth_m.npy``: distance to the nearest surface a pixel's rays meet,
    inf for the sky), with inverse depth ρ = 1/d (0 for the sky), two 4-neighbours p, q (longitude wraps) are
    discontinuous when

    - one sees the sky and the other a surface, or
    - the jump ``|ρ_q − ρ_p|`` exceeds ``RELATIVE_JUMP`` (5 %) of ``max(ρ_p, ρ_q)`` (a relative jump in depth of
      about 5 %) *and* so do both residuals of the linear extrapolation from either side along the same line,
      ``|ρ_q − (2ρ_p − ρ_{p−1})|`` and ``|ρ_p − (2ρ_q − ρ_{q+1})|``.

    Inverse depth is an affine function of the ray direction on a plane (n·X = c gives ρ = n·r / c), so a
    slanted surface (the ground towards the horizon, a wall seen at a grazing angle) has a smooth ρ and is not
    an edge however fast its depth grows, while a step (an object in front of another, a silhouette against
    the sky or the hills) is.  Both pixels of a discontinuous pair are marked.

Depth edges (:func:`edge_band`)
    The pixels within ``EDGE_RADIUS_PX`` (2 px) of a discontinuity on the product's grid: a discontinuity lies
    between the centres of the two marked pixels, so a pixel is within 2 px of it when its centre is within
    1.5 px of a marked pixel's (Euclidean distance transform, longitude wrapping).  A straight step between
    columns k and k+1 gives the band k−1 … k+2.  The *smooth* region is every other scored pixel (≥ 2 px, in
    fact ≥ 2.5 px from any discontinuity).  When the truth's grid is not the product's, the marked pixels are
    carried over by area overlap (a product pixel is marked when it overlaps a marked truth pixel).

Holes (:func:`holes`)
    Pixels that camera A's bands cover (all of A's bands finite) with a non-finite band: camera B missing where
    A saw.  Counted on every product, simulated or not.

Worst pixels (:func:`worst_pixels`)
    The ``WORST_FRACTION`` (0.1 %, at least one) of the scored pixels with the largest ``band_nrmse``, each with
    its level-0 row and column, longitude and latitude of its centre (:mod:`omnispectral.imaging.geometry`),
    both errors and whether it lies in the depth-edge band; report.json lists the first ``MAX_WORST_LISTED``
    (a full-scale panorama has 26 000), the map marks them all.

References
----------
CIE 015:2018 Colorimetry, 4th ed. (CIELAB, ΔE*ab).  Hartley & Zisserman, Multiple View Geometry, 2nd ed.,
2004, Sec. 8.1 (the image of a plane: inverse depth affine in the ray).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy import ndimage

from omnispectral.imaging.geometry import equirect_pixel_to_lonlat
from omnispectral.spectral.colour import signal_to_Lab

__all__ = ["EDGE_RADIUS_PX", "ESTIMATE_BLOCK_PX", "MAX_WORST_LISTED", "REGION_FIGURES", "RELATIVE_JUMP",
           "WORST_FRACTION", "PixelErrors", "camera_a_bands", "camera_a_covered", "camera_groups",
           "delta_e_ab_same_estimator", "depth_discontinuities", "depth_edge_figures", "edge_band", "edge_to_smooth",
           "hole_figures", "hole_mask", "inverse_depth", "marks_on_grid", "pixel_errors", "reference_white",
           "region_figures", "squared_sums", "truth_edge_band", "worst_pixel_indices", "worst_pixel_summary",
           "worst_pixels"]

#: A jump in inverse depth larger than this fraction of the nearer side's (and not explained by the surface's
#: slope) is a depth discontinuity (module docstring).
RELATIVE_JUMP = 0.05
#: Pixels within this distance (px on the product's grid) of a discontinuity form the depth-edge band.
EDGE_RADIUS_PX = 2.0
#: The share of the scored pixels listed as the worst.
WORST_FRACTION = 0.001
#: At most this many of the worst pixels are listed in report.json (all are marked on the map).
MAX_WORST_LISTED = 1000
#: Pixels per block of rows of the per-pixel errors (bounds the memory at full scale).
ESTIMATE_BLOCK_PX = 1 << 18


@dataclass
class PixelErrors:
    """Per-pixel errors on the product's grid (NaN where not scored) and the depth-edge band (None: no depth).

    ``error_sq`` and ``truth_sq`` ``(H, W, k)``: per camera (``cameras``, :func:`camera_groups`) the sums over its
    bands of ``(b − t)²`` and of ``t²``, from which every band NRMSE is made (per pixel, pooled over a region, all
    bands or one camera's)."""

    error_sq: np.ndarray
    truth_sq: np.ndarray
    delta_e_ab: np.ndarray
    scored: np.ndarray
    edge: np.ndarray | None
    cameras: tuple[str, ...] = ("all",)

    @cached_property
    def band_nrmse(self) -> np.ndarray:
        """``(H, W)`` float32 per-pixel ``‖b − t‖₂ / ‖t‖₂`` over all bands (inf where the truth is black)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(self.error_sq.sum(axis=-1) / self.truth_sq.sum(axis=-1)).astype(np.float32)


# ---------------------------------------------------------------------------------------- depth edges
def depth_discontinuities(depth_m: np.ndarray, relative_jump: float = RELATIVE_JUMP) -> np.ndarray:
    """``(H, W)`` bool: pixels on either side of a depth discontinuity of an equirect depth map (module docstring).

    Parameters
    ----------
    depth_m : ndarray (H, W)
        Distance (m) from the viewpoint, inf for the sky.
    relative_jump : float
        Smallest jump in inverse depth, as a fraction of the nearer pixel's, that counts.
    """
    rho = inverse_depth(depth_m)
    marks = np.zeros(rho.shape, bool)
    along_rows = _discontinuous_pairs(rho, relative_jump, wrap=True)  # (H, W): pair (c, c + 1 mod W)
    marks |= along_rows
    marks |= np.roll(along_rows, 1, axis=1)
    along_cols = _discontinuous_pairs(rho.T, relative_jump, wrap=False).T  # (H - 1, W): pair (r, r + 1)
    marks[:-1] |= along_cols
    marks[1:] |= along_cols
    return marks


def inverse_depth(depth_m: np.ndarray) -> np.ndarray:
    """``1 / d`` (1/m), 0 where the depth is infinite (the sky), float64."""
    d = np.asarray(depth_m, np.float64)
    with np.errstate(divide="ignore"):
        return np.where(np.isfinite(d) & (d > 0), 1.0 / d, 0.0)


def _discontinuous_pairs(rho: np.ndarray, relative_jump: float, wrap: bool) -> np.ndarray:
    """For every pair of neighbours ``(k, k + 1)`` along the last axis: whether it is a discontinuity.

    ``wrap``: the last axis is periodic (longitude), ``(rows, C)`` pairs with ``C − 1 → 0``; otherwise
    ``(rows, C − 1)`` pairs and the lines are held constant beyond their ends for the extrapolation.
    """
    n = rho.shape[-1]
    padded = np.pad(rho, ((0, 0), (1, 2)), mode="wrap" if wrap else "edge")
    pairs = n if wrap else n - 1
    before, p, q, after = (padded[:, i:i + pairs] for i in range(4))
    scale = relative_jump * np.maximum(p, q)
    jump = np.abs(q - p) > scale
    from_left = np.abs(q - (2 * p - before)) > scale
    from_right = np.abs(p - (2 * q - after)) > scale
    sky_boundary = (p > 0) != (q > 0)
    return sky_boundary | (jump & from_left & from_right)


def marks_on_grid(marks: np.ndarray, height: int, width: int) -> np.ndarray:
    """Marked pixels of another equirect grid carried onto ``height × width``: a pixel is marked when it overlaps
    a marked pixel (area overlap when shrinking, bilinear support when enlarging)."""
    if marks.shape == (height, width):
        return marks.copy()
    interp = cv2.INTER_AREA if marks.shape[0] >= height else cv2.INTER_LINEAR
    return cv2.resize(marks.astype(np.float32), (width, height), interpolation=interp) > 0


def edge_band(marks: np.ndarray, radius_px: float = EDGE_RADIUS_PX) -> np.ndarray:
    """``(H, W)`` bool: pixels within ``radius_px`` of a discontinuity between marked pixels (module docstring):
    centre within ``radius_px − 0.5`` of a marked pixel's centre, longitude wrapping."""
    if not marks.any():
        return np.zeros(marks.shape, bool)
    pad = math.ceil(radius_px) + 1
    padded = np.pad(~marks, ((0, 0), (pad, pad)), mode="wrap")
    distance_px = ndimage.distance_transform_edt(padded)[:, pad:-pad]
    return distance_px <= radius_px - 0.5


def truth_edge_band(truth, height: int, width: int) -> tuple[np.ndarray | None, str | None]:
    """The depth-edge band on the product's grid from the ground truth's depth map, or ``(None, why not)``
    (``truth``: the interface of :class:`omnispectral.sim.truth.GroundTruth`)."""
    depth_m, note = truth.depth_m()
    if depth_m is None:
        return None, note
    return edge_band(marks_on_grid(depth_discontinuities(depth_m), height, width)), None


# ---------------------------------------------------------------------------------------- pixel errors
def camera_groups(band_names: list[str] | None, n_bands: int) -> dict[str, list[int]]:
    """Band indices per camera from names ``CAMERA:BAND`` (``{"all": …}`` when the bands are not named so)."""
    names = list(band_names) if band_names is not None and len(band_names) == n_bands else []
    groups: dict[str, list[int]] = {}
    for i, name in enumerate(names):
        if ":" not in str(name):
            return {"all": list(range(n_bands))}
        groups.setdefault(str(name).split(":", 1)[0], []).append(i)
    return groups or {"all": list(range(n_bands))}


def squared_sums(values: np.ndarray, groups: dict[str, list[int]]) -> np.ndarray:
    """``(N, k)`` float32: per group of bands, ``Σ values²`` over its bands (``values (N, m)``)."""
    v = np.asarray(values, np.float64) ** 2
    return np.stack([v[:, idx].sum(axis=1) for idx in groups.values()], axis=1).astype(np.float32)


def delta_e_ab_same_estimator(bands: np.ndarray, truth: np.ndarray, estimator, white: np.ndarray) -> np.ndarray:
    """ΔE*ab ``(N,)`` between the estimator's spectra of ``bands (N, m)`` and of ``truth (N, m)`` (module docstring),
    CIELAB with ``white (n,)`` (:func:`omnispectral.spectral.colour.signal_to_Lab`)."""
    wl = np.asarray(estimator.wavelength_nm, np.float64)
    lab_b = signal_to_Lab(estimator.estimate(bands), white, wl)
    lab_t = signal_to_Lab(estimator.estimate(truth), white, wl)
    return np.linalg.norm(lab_b - lab_t, axis=-1).astype(np.float32)


def reference_white(truth) -> tuple[np.ndarray, str]:
    """The white of the per-pixel ΔE*ab (module docstring): ``(spectrum (n,) in the truth's units, which)``.

    The perfect diffuser at the ColorChecker when the truth has one (``colorchecker_white.npy``), else a perfect
    diffuser facing up under the truth's spectral radiance: ``E/π`` with ``E = Σ L cos θ ΔΩ`` over the upper
    hemisphere of ``spectral.npy``.
    """
    white = truth.colorchecker_white()
    if white is not None:
        return white.astype(np.float64), "perfect diffuser at the ColorChecker"
    spectral = truth.spectral(mmap=True)
    h, w = spectral.shape[:2]
    rows = np.arange(h // 2)
    _, lat = equirect_pixel_to_lonlat(np.zeros_like(rows), rows, w, h)
    # solid angle of a pixel × cos θ (θ from the zenith: cos θ = sin lat)
    weight = np.cos(np.radians(lat)) * np.sin(np.radians(lat)) * (math.pi / h) * (2 * math.pi / w)
    irradiance = np.einsum("r,rn->n", weight, np.asarray(spectral[: h // 2], np.float64).sum(axis=1))
    return irradiance / math.pi, "perfect diffuser facing up under the truth's sky"


def pixel_errors(bands: np.ndarray, truth: np.ndarray, scored: np.ndarray, estimator, white: np.ndarray,
                 edge: np.ndarray | None, band_names: list[str] | None = None) -> PixelErrors:
    """Per-pixel band errors (per camera of ``band_names``) and ``delta_e_ab`` at the ``scored`` pixels (module
    docstring), NaN elsewhere; in blocks of rows of about ``ESTIMATE_BLOCK_PX`` pixels."""
    groups = camera_groups(band_names, bands.shape[-1])
    error_sq = np.full((*scored.shape, len(groups)), np.nan, np.float32)
    truth_sq = np.full((*scored.shape, len(groups)), np.nan, np.float32)
    delta_e = np.full(scored.shape, np.nan, np.float32)
    rows = max(1, ESTIMATE_BLOCK_PX // scored.shape[1])
    for r0 in range(0, scored.shape[0], rows):
        r1 = min(scored.shape[0], r0 + rows)
        sel = scored[r0:r1]
        b, t = bands[r0:r1][sel], truth[r0:r1][sel]
        error_sq[r0:r1][sel] = squared_sums(np.asarray(b, np.float64) - t, groups)
        truth_sq[r0:r1][sel] = squared_sums(t, groups)
        delta_e[r0:r1][sel] = delta_e_ab_same_estimator(b, t, estimator, white)
    return PixelErrors(error_sq, truth_sq, delta_e, scored, edge, tuple(groups))


#: The figures of a region (:func:`region_figures`), in the order they are reported.
REGION_FIGURES = ("band_nrmse", "band_nrmse_median", "delta_e_ab", "delta_e_ab_median")


def region_figures(errors: PixelErrors, region: np.ndarray) -> dict:
    """The region's pooled band NRMSE (all bands, and per camera when there are several), median per-pixel band
    NRMSE, mean and median ΔE*ab over its scored pixels (module docstring; None where it has none)."""
    sel = errors.scored & region
    n = int(sel.sum())
    by_camera = len(errors.cameras) > 1
    if n == 0:
        return {"n_pixels": 0, **dict.fromkeys(REGION_FIGURES),
                **({"band_nrmse_by_camera": dict.fromkeys(errors.cameras)} if by_camera else {})}
    err = errors.error_sq[sel].astype(np.float64).sum(axis=0)
    ref = errors.truth_sq[sel].astype(np.float64).sum(axis=0)
    d = errors.delta_e_ab[sel]
    out = {"n_pixels": n, "band_nrmse": _pooled(err.sum(), ref.sum()),
           "band_nrmse_median": float(np.median(errors.band_nrmse[sel])),
           "delta_e_ab": float(np.mean(d)), "delta_e_ab_median": float(np.median(d))}
    if by_camera:
        out["band_nrmse_by_camera"] = {c: _pooled(e, r) for c, e, r in zip(errors.cameras, err, ref, strict=True)}
    return out


def _pooled(error_sq: float, truth_sq: float) -> float | None:
    """``sqrt(Σ error² / Σ truth²)`` (None for a black truth)."""
    return float(math.sqrt(error_sq / truth_sq)) if truth_sq > 0 else None


def edge_to_smooth(edge: dict, smooth: dict) -> dict:
    """``edge / smooth`` of each region figure, per camera too (None where either is missing or the smooth one
    is 0)."""
    def ratio(a, b) -> float | None:
        return float(a / b) if a is not None and b else None

    out = {k: ratio(edge.get(k), smooth.get(k)) for k in REGION_FIGURES}
    if "band_nrmse_by_camera" in edge:
        out["band_nrmse_by_camera"] = {c: ratio(v, smooth["band_nrmse_by_camera"][c])
                                       for c, v in edge["band_nrmse_by_camera"].items()}
    return out


def depth_edge_figures(errors: PixelErrors) -> dict:
    """The ``depth_edges`` section: edge band and smooth region figures and their ratio."""
    edge = region_figures(errors, errors.edge)
    smooth = region_figures(errors, ~errors.edge)
    return {"relative_jump": RELATIVE_JUMP, "radius_px": EDGE_RADIUS_PX,
            "edge_fraction": float(edge["n_pixels"] / max(1, int(errors.scored.sum()))),
            "edge": edge, "smooth": smooth, "ratio": edge_to_smooth(edge, smooth)}


def worst_pixel_indices(errors: PixelErrors, fraction: float = WORST_FRACTION) -> tuple[np.ndarray, np.ndarray]:
    """Level-0 ``(rows, cols)`` of the worst ``fraction`` (at least one) of the scored pixels by ``band_nrmse``,
    worst first (ties in pixel order)."""
    flat = np.flatnonzero(errors.scored.ravel())
    if flat.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    k = max(1, math.ceil(fraction * flat.size))
    values = np.nan_to_num(errors.band_nrmse.ravel()[flat], nan=np.inf)
    part = np.argpartition(-values, k - 1)[:k] if k < flat.size else np.arange(flat.size)
    top = flat[part[np.lexsort((flat[part], -values[part]))]]
    return np.divmod(top, errors.scored.shape[1])


def worst_pixels(errors: PixelErrors, fraction: float = WORST_FRACTION) -> list[dict]:
    """The worst pixels (:func:`worst_pixel_indices`) with their position and errors (module docstring)."""
    rows, cols = worst_pixel_indices(errors, fraction)
    h, w = errors.scored.shape
    lon, lat = equirect_pixel_to_lonlat(cols, rows, w, h)
    return [{"row": int(r), "col": int(c), "lon_deg": round(float(lo), 4), "lat_deg": round(float(la), 4),
             "band_nrmse": float(errors.band_nrmse[r, c]), "delta_e_ab": float(errors.delta_e_ab[r, c]),
             "at_depth_edge": None if errors.edge is None else bool(errors.edge[r, c])}
            for r, c, lo, la in zip(rows, cols, lon, lat, strict=True)]


def worst_pixel_summary(worst: list[dict], n_scored: int) -> dict:
    """The ``worst_pixels`` section: how they were chosen, the share at depth edges and the list (worst first, at
    most ``MAX_WORST_LISTED``)."""
    at_edge = [p["at_depth_edge"] for p in worst if p["at_depth_edge"] is not None]
    return {"fraction": WORST_FRACTION, "ranked_by": "band_nrmse", "n_scored_pixels": int(n_scored),
            "n": len(worst), "n_listed": min(len(worst), MAX_WORST_LISTED),
            "at_depth_edge_fraction": float(np.mean(at_edge)) if at_edge else None,
            "band_nrmse_min": float(worst[-1]["band_nrmse"]) if worst else None,
            "pixels": worst[:MAX_WORST_LISTED]}


# ---------------------------------------------------------------------------------------- holes
def hole_mask(bands: np.ndarray, band_names: list[str]) -> np.ndarray:
    """``(H, W)`` bool: covered by camera A's bands (all finite), some band non-finite (module docstring)."""
    finite = np.isfinite(bands)
    return finite[..., camera_a_bands(band_names)].all(axis=-1) & ~finite.all(axis=-1)


def camera_a_covered(bands: np.ndarray, band_names: list[str]) -> np.ndarray:
    """``(H, W)`` bool: all of camera A's bands finite."""
    return np.isfinite(bands[..., camera_a_bands(band_names)]).all(axis=-1)


def camera_a_bands(band_names: list[str]) -> list[int]:
    """Indices of camera A's bands (``A:…``; all bands when none is named so)."""
    idx = [i for i, n in enumerate(band_names) if str(n).startswith("A:")]
    return idx or list(range(len(band_names)))


def hole_figures(n_holes: int, n_a_covered: int) -> dict:
    """The report's ``holes`` section from the counts of holes and of pixels camera A covers (level 0)."""
    return {"n_pixels": int(n_holes), "a_covered_pixels": int(n_a_covered),
            "fraction_of_a_covered": float(n_holes / n_a_covered) if n_a_covered else 0.0,
            "definition": "level-0 pixels where all of camera A's bands are finite and some band is not"}
