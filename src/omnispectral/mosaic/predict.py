"""Camera B's bands where B saw nothing: predicted from camera A's bands and the surface around the pixel.

A tile pixel needs B's bands where no direction gives them (B's views of the point disagree and are
all dropped, :func:`~omnispectral.mosaic.blending.reject_inconsistent`; every view of it shows another
surface, :func:`omnispectral.imaging.parallax.sees_another_surface`; the point lies beyond B's frame),
where what B gave cannot be the surface A sees (:func:`implausible_b`, :func:`too_dark_b`), or where B's
sample beside such a pixel took in what hid it (:func:`contaminated_beside`).  Such a pixel takes

.. math:: \\hat\\rho_B = (M\\rho_A) \\odot \\exp\\bar\\ell, \\qquad
          \\bar\\ell = \\frac{\\sum_q w_q \\log\\big(\\rho_B(q) / M\\rho_A(q)\\big)}{\\sum_q w_q},

``M`` the prior's linear predictor (:func:`omnispectral.spectral.conditional.b_from_a_predictor`) and
``q`` the neighbours (within :data:`RADII_PX`) whose B bands were measured, weighted as a joint
bilateral filter guided by camera A (Kopf et al., "Joint bilateral upsampling", SIGGRAPH 2007): by
the difference of A's chromaticity (σ :data:`SIGMA_CHROMA`), of A's log brightness (σ
:data:`SIGMA_LOG_BRIGHTNESS`) and by distance, so the neighbours of the same surface set the
correction and those across a depth edge do not.  Its relative error per band,
:math:`\\sqrt{\\mathrm{var}_w(\\ell) + s_0^2/(1 + n_\\mathrm{eff})}` (``s0`` the prior's relative error,
``n_eff`` the weights' effective count), is what the quality layer records (its largest band) and what
the estimator adds to B's noise variance there (:func:`omnispectral.product.spectra.estimate_image`).
Without neighbours the prior's ``M ρ_A`` stands with error ``s0``.  The panorama covers what camera A
covers: a pixel only B sees is left out (NaN), like the rest of the uncovered sphere.
"""

from __future__ import annotations

import cv2
import numpy as np

from omnispectral.imaging.channels import all_channels, any_channel, finite_pixels
from omnispectral.spectral.conditional import BandPredictor

__all__ = ["IMPLAUSIBLE_RATIO", "UNCLIPPED_FRACTION", "b_outliers", "brightest_measured_b", "contaminated_beside",
           "fill_missing_b", "implausible_b", "tile_predictor", "too_dark_b"]

#: Neighbourhood radii (px) tried in turn: a pixel with no measured neighbour like it within the first
#: looks within the second (sampled every :data:`WIDE_STEP_PX`).
RADII_PX = (5, 16)
WIDE_STEP_PX = 3
#: Joint-bilateral guide widths: A's chromaticity ``a / Σa`` and A's natural-log brightness.
SIGMA_CHROMA = 0.03
SIGMA_LOG_BRIGHTNESS = 0.4
#: Sum of neighbour weights below which the neighbourhood says nothing about the pixel.
MIN_WEIGHT = 0.05
#: Fewest measured pixels in a tile for fitting the tile's own predictor (when none is given).
MIN_TILE_SAMPLES = 64
#: A measured B band this many times off (either way) the ratio to the prediction its neighbourhood shows
#: is taken for another surface than A's (:func:`implausible_b`); the neighbourhood's side (px).
IMPLAUSIBLE_RATIO = 8.0
IMPLAUSIBLE_WINDOW_PX = 31
#: A B darker than A allows is flagged (:func:`too_dark_b`) only below this share of the tile's brightest B.
UNCLIPPED_FRACTION = 0.25
#: :func:`contaminated_beside`: how far (px) from a missing pixel B's measurement is re-examined, by how many
#: times the prediction's relative error it must be off, and the least joint-bilateral weight of the
#: prediction's neighbours within the first radius.
BESIDE_MISSING_PX = 2
CONTAMINATION_SIGMAS = 3.0
MIN_NEAR_SUPPORT = 0.5
#: ... and the pixel must look like a hidden pixel within BESIDE_MISSING_PX in A: this near in the joint
#: bilateral guide's units (σ of chromaticity and of log brightness; :func:`_looks_like_a_hidden_pixel`).
SAME_SURFACE_DISTANCE = 3.0
#: ... and where its B is brighter than the prediction, a measured B at least as bright within this reach (px)
#: on the occluder's side of the hidden pixels (:func:`_may_hold_the_occluder`).
MIX_REACH_PX = 8


def tile_predictor(a: np.ndarray, b: np.ndarray) -> BandPredictor | None:
    """A predictor fitted to the tile's measured pixels (``a``, ``b`` ``(k, 3)``), relative least squares;
    ``None`` with fewer than :data:`MIN_TILE_SAMPLES` pixels.  Used when the mosaic is not given the prior's."""
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1) & (a.sum(axis=1) > 0)
    if ok.sum() < MIN_TILE_SAMPLES:
        return None
    s = a[ok].sum(axis=1, keepdims=True)
    an, bn = (a[ok] / s).astype(np.float64), (b[ok] / s).astype(np.float64)
    m, *_ = np.linalg.lstsq(an, bn, rcond=None)
    resid = bn - an @ m
    rel = np.sqrt((resid ** 2).mean(axis=0) / np.maximum((bn ** 2).mean(axis=0), 1e-30))
    return BandPredictor(m.T, rel)


def prior_log_ratio(a: np.ndarray, b: np.ndarray, predictor: BandPredictor) -> tuple[np.ndarray, np.ndarray]:
    """The prior's prediction ``Mρ_A`` of B's bands ``(…, 3)`` (float64) and ``ℓ = log(ρ_B / Mρ_A)``, NaN
    where either is not positive."""
    prior_b = a.astype(np.float64) @ np.asarray(predictor.matrix, np.float64).T
    with np.errstate(all="ignore"):
        ell = np.where((b > 0) & (prior_b > 0), np.log(b / prior_b), np.nan)
    return prior_b, ell


def _neighbour_stats(todo_yx: tuple[np.ndarray, np.ndarray], usable: np.ndarray, log_ratio: np.ndarray,
                     chroma: np.ndarray, log_bright: np.ndarray, radius: int, step: int):
    """Weighted sums over the neighbours of the ``todo`` pixels: ``(Σw, Σw², Σwℓ, Σwℓ²)``."""
    ys, xs = todo_yx
    h, w = usable.shape
    n = ys.size
    sw, sw2 = np.zeros(n), np.zeros(n)
    sl, sl2 = np.zeros((n, 3)), np.zeros((n, 3))
    c0, b0 = chroma[ys, xs], log_bright[ys, xs]
    sigma_px2 = 2.0 * (radius / 2.0) ** 2
    for dy in range(-radius, radius + 1, step):
        for dx in range(-radius, radius + 1, step):
            yy, xx = ys + dy, xs + dx
            inside = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            yy, xx = np.where(inside, yy, 0), np.where(inside, xx, 0)
            ok = inside & usable[yy, xx]
            if not ok.any():
                continue
            d_chroma = ((chroma[yy, xx] - c0) ** 2).sum(axis=1) / (2 * SIGMA_CHROMA ** 2)
            d_bright = (log_bright[yy, xx] - b0) ** 2 / (2 * SIGMA_LOG_BRIGHTNESS ** 2)
            wt = np.where(ok, np.exp(-d_chroma - d_bright - (dy * dy + dx * dx) / sigma_px2), 0.0)
            ell = log_ratio[yy, xx]
            sw += wt
            sw2 += wt * wt
            sl += wt[:, None] * ell
            sl2 += wt[:, None] * ell * ell
    return sw, sw2, sl, sl2


def implausible_b(values: np.ndarray, predictor: BandPredictor | None) -> np.ndarray:
    """``(h, w)`` bool: pixels whose measured B bands are brighter than A's allow, beyond anything a surface
    explains.

    ``ℓ = log(ρ_B / Mρ_A)`` per band; a pixel is implausible when some band's ``ℓ`` exceeds the mean of
    ``ℓ`` over its :data:`IMPLAUSIBLE_WINDOW_PX` neighbourhood by more than ``log``
    :data:`IMPLAUSIBLE_RATIO`: B saw another, brighter surface than A there (a thin near object whose
    parallax was missed, with the sun behind it: B 250 times the truth), while a surface's own colour,
    however far from the prior, moves its neighbours' ``ℓ`` with it.  B darker than A allows is
    :func:`too_dark_b`.  On the simulator's truth no pixel's ``ℓ`` leaves ``±log 8`` even against the
    prior alone.  Without a predictor nothing is flagged; the engine never lets the prediction exceed
    what B measured there."""
    return b_outliers(values, predictor)[0]


def too_dark_b(values: np.ndarray, predictor: BandPredictor | None) -> np.ndarray:
    """``(h, w)`` bool: pixels whose measured B bands are darker than A's allow, beyond anything a surface
    explains, where B cannot be clipped.

    The mirror of :func:`implausible_b`: some band's ``ℓ`` below its neighbourhood's mean by more than
    ``log`` :data:`IMPLAUSIBLE_RATIO`.  B saw another, darker surface than A there: a near object's silhouette
    against a bright sky, where the parallax gave the sky's pixels beside it the object's depth (its edge
    fattened into the sky: B's dark post 4 px into the sunrise sky, B at 1/140 of the truth).  A B clipped
    in every exposure (a lower bound beside the sun) also reads too dark; it sits at the brightest B of the
    tile, so only pixels whose B bands all stay below :data:`UNCLIPPED_FRACTION` of the tile's brightest B
    band are flagged (A clipped makes B look too bright, never too dark).  The prediction there may exceed
    what B measured at the pixel, not the brightest B measured around it (:func:`brightest_measured_b`)."""
    return b_outliers(values, predictor)[1]


def b_outliers(values: np.ndarray, predictor: BandPredictor | None) -> tuple[np.ndarray, np.ndarray]:
    """``(too bright, too dark)``: :func:`implausible_b` and :func:`too_dark_b` of ``values (h, w, 6)`` from one
    evaluation of ``ℓ``."""
    usable, excess = _log_ratio_excess(values, predictor)
    bright = usable & any_channel(excess > np.log(IMPLAUSIBLE_RATIO))
    if not usable.any():
        return bright, usable
    b = values[..., 3:6]
    brightest = float(np.max(np.where(usable[..., None], b, 0.0)))
    unclipped = all_channels(b < UNCLIPPED_FRACTION * brightest)
    return bright, usable & unclipped & any_channel(excess < -np.log(IMPLAUSIBLE_RATIO))


def brightest_measured_b(values: np.ndarray, missing: np.ndarray) -> np.ndarray:
    """``(h, w, 3)``: per band, the brightest B measured (finite and not ``missing``) within the pixel's
    :data:`IMPLAUSIBLE_WINDOW_PX` neighbourhood (0 where none): the ceiling of a prediction where B read too
    dark (:func:`too_dark_b`), which restores the light B saw beside the pixel and invents none (a noisy A
    at one pixel can make ``Mρ_A`` several times too bright)."""
    b = np.where((finite_pixels(values[..., 3:6]) & ~missing)[..., None], values[..., 3:6], 0.0).astype(np.float32)
    kernel = np.ones((IMPLAUSIBLE_WINDOW_PX, IMPLAUSIBLE_WINDOW_PX), np.uint8)
    return np.stack([cv2.dilate(b[..., i], kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0.0)
                     for i in range(3)], axis=-1)


def _log_ratio_excess(values: np.ndarray, predictor: BandPredictor | None) -> tuple[np.ndarray, np.ndarray]:
    """``(usable (h, w), ℓ − mean of ℓ over the pixel's IMPLAUSIBLE_WINDOW_PX neighbourhood (h, w, 3))``;
    nothing usable without a predictor."""
    h, w = values.shape[:2]
    if predictor is None:
        return np.zeros((h, w), bool), np.zeros((h, w, 3), np.float32)
    _, ell = prior_log_ratio(values[..., :3], values[..., 3:6].astype(np.float64), predictor)
    usable = finite_pixels(ell)
    ell = np.where(usable[..., None], ell, 0.0).astype(np.float32)
    k = (IMPLAUSIBLE_WINDOW_PX, IMPLAUSIBLE_WINDOW_PX)
    count = cv2.boxFilter(usable.astype(np.float32), -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    local = np.stack([cv2.boxFilter(ell[..., i], -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
                      for i in range(3)], axis=-1) / np.maximum(count, 1.0)[..., None]
    return usable, ell - local


def fill_missing_b(values: np.ndarray, missing: np.ndarray, predictor: BandPredictor | None = None) -> np.ndarray:
    """Predict camera B's bands (3–5) of ``values`` ``(h, w, 6)`` in place at ``missing`` pixels (module docstring).

    Parameters
    ----------
    values
        A tile's six bands; A's (0–2) must be finite where B's are to be predicted.
    missing
        ``(h, w)`` bool: pixels whose B bands are not to be trusted (not finite, or hidden in every view).
    predictor
        The prior's predictor; ``None`` fits one to the tile's measured pixels (:func:`tile_predictor`).

    Returns
    -------
    numpy.ndarray
        ``(h, w)`` float32: the prediction's relative error (largest band) where predicted, NaN elsewhere.
        Pixels with A not finite get NaN B bands (the panorama covers what camera A covers).
    """
    a, b = values[..., :3], values[..., 3:6]
    a_ok = finite_pixels(a)
    rel_out = np.full(missing.shape, np.nan, np.float32)
    b[~a_ok] = np.nan
    todo = missing & a_ok
    if not todo.any():
        return rel_out
    measured = a_ok & finite_pixels(b) & ~missing
    if predictor is None:
        predictor = tile_predictor(a[measured], b[measured])
        if predictor is None:
            b[todo] = np.nan
            return rel_out
    ys, xs = np.nonzero(todo)
    pred, rel, _ = _neighbourhood_prediction(values, (ys, xs), measured, predictor)
    b[ys, xs] = pred.astype(b.dtype)
    rel_out[ys, xs] = rel.max(axis=1)
    return rel_out


def _neighbourhood_prediction(values: np.ndarray, todo_yx: tuple[np.ndarray, np.ndarray], measured: np.ndarray,
                              predictor: BandPredictor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """B's bands predicted at the ``todo`` pixels from A's and the ``measured`` neighbours (module docstring):
    ``(prediction (n, 3) float64, relative error per band (n, 3), joint-bilateral weight within the first
    radius (n,))``."""
    a, b = values[..., :3], values[..., 3:6]
    prior_b, ell = prior_log_ratio(a, b, predictor)
    chroma, log_bright = _guide_features(a)
    usable = measured & finite_pixels(ell) & (a.sum(axis=-1, dtype=np.float64) > 0)
    log_ratio = np.where(usable[..., None], ell, 0.0)
    ys, xs = todo_yx
    sw, sw2 = np.zeros(ys.size), np.zeros(ys.size)
    sl, sl2 = np.zeros((ys.size, 3)), np.zeros((ys.size, 3))
    pending = np.ones(ys.size, bool)
    near_support = None
    for radius, step in zip(RADII_PX, (1, WIDE_STEP_PX), strict=True):
        if not pending.any():
            break
        idx = np.flatnonzero(pending)
        stats = _neighbour_stats((ys[idx], xs[idx]), usable, log_ratio, chroma, log_bright, radius, step)
        for acc, new in zip((sw, sw2, sl, sl2), stats, strict=True):
            acc[idx] = new
        if near_support is None:
            near_support = sw.copy()
        pending = sw < MIN_WEIGHT
    seen = sw >= MIN_WEIGHT
    mean = np.where(seen[:, None], sl / np.maximum(sw, 1e-30)[:, None], 0.0)
    var = np.where(seen[:, None], np.clip(sl2 / np.maximum(sw, 1e-30)[:, None] - mean ** 2, 0.0, None), 0.0)
    n_eff = np.where(seen, sw ** 2 / np.maximum(sw2, 1e-30), 0.0)
    rel = np.sqrt(var + np.asarray(predictor.rel_std) ** 2 / (1.0 + n_eff[:, None]))
    pred = np.maximum(prior_b[ys, xs], 0.0) * np.exp(mean)
    return pred, rel, near_support if near_support is not None else np.zeros(ys.size)


def contaminated_beside(values: np.ndarray, missing: np.ndarray, predictor: BandPredictor | None) -> np.ndarray:
    """``(h, w)`` bool: measured B pixels of a hidden surface, within :data:`BESIDE_MISSING_PX` of where it is
    hidden (``missing``), whose bands the surface around them contradicts: B's sample there took in what hid it.

    Beside the pixels B could not see (another surface in front of them, from B's viewpoint), B's own
    samples of the same surface are interpolated from B pixels within a pixel or two of the occluder's
    edge (the kernel's reach, and the edge's position known to a pixel): a post against a bright sky leaves
    a dark seam in B's sky beside the pixels predicted for it.  Each measured pixel within that reach that
    looks like one of those hidden pixels in A (:func:`_looks_like_a_hidden_pixel`: the same surface, not
    the occluder) is predicted as if missing, from the measured pixels beyond the reach
    (:func:`fill_missing_b`); it is contaminated when some band's measured value is more than
    :data:`CONTAMINATION_SIGMAS` times that prediction's relative error off it (in log), the prediction
    rests on neighbours of its own surface within the first radius (joint-bilateral weight at least
    :data:`MIN_NEAR_SUPPORT`), and the measurement can be a mix with the occluder: where it is brighter than
    the prediction, B measured something at least as bright on the occluder's side
    (:func:`_may_hold_the_occluder`).
    The occluder's own pixels are left as measured: where the occluder is a chart, its small patches'
    look-alikes in A may be other colours in B, and a prediction would replace a right measurement with a
    wrong one.  Without a predictor nothing is flagged."""
    h, w = missing.shape
    out = np.zeros((h, w), bool)
    if predictor is None or not missing.any():
        return out
    a_ok = finite_pixels(values[..., :3])
    measured = a_ok & finite_pixels(values[..., 3:6]) & ~missing
    reach = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * BESIDE_MISSING_PX + 1,) * 2)
    beside = (cv2.dilate(missing.astype(np.uint8), reach) > 0) & measured
    if not beside.any():
        return out
    ys, xs = np.nonzero(beside)
    guide = _guide_features(values[..., :3])
    hidden_side = _looks_like_a_hidden_pixel(guide, missing, ys, xs)
    occluder_side = np.zeros((h, w), bool)
    occluder_side[ys[~hidden_side], xs[~hidden_side]] = True
    ys, xs = ys[hidden_side], xs[hidden_side]
    if ys.size == 0:
        return out
    pred, rel, support = _neighbourhood_prediction(values, (ys, xs), measured & ~beside, predictor)
    b = values[ys, xs, 3:6].astype(np.float64)
    with np.errstate(all="ignore"):
        off = np.abs(np.log(b / pred))
    bad = (support >= MIN_NEAR_SUPPORT) & np.any(np.nan_to_num(off, nan=0.0) > CONTAMINATION_SIGMAS * rel, axis=1)
    bad[bad] = _may_hold_the_occluder(values[..., 3:6], guide, occluder_side, ys[bad], xs[bad], pred[bad],
                                       rel[bad])
    out[ys[bad], xs[bad]] = True
    return out


def _may_hold_the_occluder(b: np.ndarray, guide: tuple[np.ndarray, np.ndarray], others: np.ndarray, ys: np.ndarray,
                           xs: np.ndarray, pred: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: B's measurement ``b[ys, xs]`` can be the hidden surface mixed with what hid it: it is nowhere
    brighter than its prediction ``pred (n, 3)`` allows (its relative error ``rel``), or, in the bands where it is,
    one of the ``others`` (the measured pixels beside the hidden ones that do not look like them: the occluder's
    side) within :data:`MIX_REACH_PX` that is another surface in A (farther than :data:`SAME_SURFACE_DISTANCE` in
    the joint bilateral ``guide``, :func:`_guide_features`) is at least as bright.

    A sample that took in the occluder holds a share of the occluder's B.  A darker occluder may have filled it
    (the post by the low sun hides the sky from one of B's views, whose B there is 1/140 of the sky's), so a
    measurement below the prediction stays a candidate.  One brighter than the prediction must have taken in
    something brighter, which B measured on the far side of the hidden pixels; where nothing around is, the
    prediction is what is wrong (a chart's 3-px patch, part of it hidden, predicted from a patch that looks
    alike in A and is another colour in B: the yellow patch, 3× brighter in B than the prediction from the
    orange yellow above it)."""
    h, w = others.shape
    meas = b[ys, xs].astype(np.float64)
    brighter = meas > pred * np.exp(rel)
    found = ~brighter.any(axis=1)
    if found.all():
        return found
    for yy, xx in _within(ys, xs, MIX_REACH_PX, (h, w)):  # the pixel itself is no occluder: not in ``others``
        brighter_still = np.where(brighter, b[yy, xx] >= meas, True).all(axis=1)
        found |= others[yy, xx] & ~_alike(guide, ys, xs, yy, xx) & brighter_still
    return found


def _guide_features(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint bilateral guide of A's bands ``(..., 3)``: chromaticity ``a / Σa`` (0 where ``Σa ≤ 0``) and
    natural-log brightness ``log max(Σa, 1e-30)``, float64."""
    bright = a.sum(axis=-1, dtype=np.float64)
    with np.errstate(all="ignore"):
        chroma = np.where(bright[..., None] > 0, a / bright[..., None], 0.0)
    return chroma, np.log(np.maximum(bright, 1e-30))


def _looks_like_a_hidden_pixel(guide: tuple[np.ndarray, np.ndarray], missing: np.ndarray, ys: np.ndarray,
                               xs: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: a ``missing`` pixel within :data:`BESIDE_MISSING_PX` looks like the pixel in A (within
    :data:`SAME_SURFACE_DISTANCE` in the units of the joint bilateral ``guide``, :func:`_guide_features`): the
    pixel is of the surface hidden there, not of the one that hides it."""
    found = np.zeros(ys.size, bool)
    for yy, xx in _within(ys, xs, BESIDE_MISSING_PX, missing.shape):
        found |= missing[yy, xx] & _alike(guide, ys, xs, yy, xx)
    return found


def _within(ys: np.ndarray, xs: np.ndarray, radius: int, shape: tuple[int, int]):
    """For each offset within ``radius`` px (the disk, its centre included): the pixels ``(yy, xx)`` that far from
    ``(ys, xs)``, clipped to an image of ``shape``."""
    h, w = shape
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if dy * dy + dx * dx <= radius * radius:
                yield np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)


def _alike(guide: tuple[np.ndarray, np.ndarray], ys: np.ndarray, xs: np.ndarray, yy: np.ndarray,
           xx: np.ndarray) -> np.ndarray:
    """``(n,)`` bool: pixels ``(yy, xx)`` look like ``(ys, xs)`` in A: within :data:`SAME_SURFACE_DISTANCE` in the
    units of the joint bilateral ``guide`` (:func:`_guide_features`)."""
    chroma, log_bright = guide
    distance_sq = (((chroma[yy, xx] - chroma[ys, xs]) / SIGMA_CHROMA) ** 2).sum(axis=1) \
        + ((log_bright[yy, xx] - log_bright[ys, xs]) / SIGMA_LOG_BRIGHTNESS) ** 2
    return distance_sq <= SAME_SURFACE_DISTANCE ** 2
