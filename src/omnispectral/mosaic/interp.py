"""Interpolation of source images at arbitrary (sub-pixel) sensor positions: the engine's one resampling.

Methods (all separable kernels, evaluated at the exact floating-point position):

``linear``
    Bilinear (2 × 2 taps).
``cubic``
    Keys cubic convolution, ``a = -1/2`` (4 × 4 taps, third-order accurate, Catmull–Rom; Keys,
    "Cubic convolution interpolation for digital image processing", IEEE TASSP 29(6), 1981).
    OpenCV's ``INTER_CUBIC`` uses ``a = -3/4``, which reproduces constants but not ramps (first-order
    error): on smooth HDR content it is worse than bilinear, so it is not used.
``spline``
    Cardinal cubic B-spline interpolation (Unser, Aldroubi & Eden, "Fast B-spline transforms for
    continuous image representation and interpolation", IEEE TPAMI 13(3), 1991): the source is
    prefiltered into B-spline coefficients (recursive filter, pole ``√3 - 2``), then the cubic
    B-spline is evaluated as four bilinear fetches (Sigg & Hadwiger, "Fast third-order texture
    filtering", GPU Gems 2, ch. 20, 2005).  This is the interpolator Hugin's ``spline36``
    approximates with a 6-tap kernel.
``lanczos``
    Lanczos-3 (6 × 6 taps, weights normalised to sum 1; Duchon, "Lanczos filtering in one and two
    dimensions", J. Appl. Meteor. 18, 1979).
``cubic-clamped`` (what ``process`` uses)
    ``cubic``, then clipped to the range of the 2 × 2 source pixels around the position (the
    "anti-ringing" clamp of image scalers): the cubic's sharpness on texture and edges without its
    overshoot beside small high-contrast targets and the HDR sun, where a negative lobe multiplies a
    value 10⁵ times its neighbours.  The result always lies between the bilinear neighbours' extremes.

Implementation.  ``spline``, ``cubic`` and ``cubic-clamped`` run compiled one-pass kernels
(:mod:`omnispectral.mosaic.kernels`: all 4 × 4 taps and the clamp per output pixel, ~5x faster than the
fetches below).  Without Numba (and for ``linear``) OpenCV's bilinear ``cv2.remap`` does the fetches when it
interpolates at the exact position: OpenCV ≥ 5 does for ≤ 4 float32 channels, OpenCV 4 rounds positions to 1/32 px
(``INTER_BITS = 5``), and every version does so for Lanczos and for more than 4 channels.
:func:`opencv_is_exact` probes the installed OpenCV once; where it rounds, a NumPy gather with the
same kernel is used.  ``cubic`` is three bilinear fetches per axis (nine in all: the two positive
middle taps merged into one fetch between them, the negative outer taps fetched at their pixel);
``spline`` four (all B-spline weights are positive).  ``lanczos`` is always the NumPy gather
(OpenCV only has Lanczos-4, rounded).  Sources are cropped before remapping, so OpenCV's
limit of 32767 px per side never applies (sources are sensor frames).  Borders replicate the edge
pixel; the mosaic's feathering weight is zero at the sensor border, so they never show.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import spline_filter1d

from omnispectral.choices import INTERP_NAMES, method_from
from omnispectral.mosaic.kernels import compiled_kernels

__all__ = ["CUBIC_A", "KERNEL_RADIUS_PX", "LANCZOS_A", "METHODS", "SPLINE_PREFILTER_MARGIN_PX", "Interpolation",
           "bspline3_kernel", "check_method", "clamp_to_neighbours", "cubic_kernel", "interpolation",
           "lanczos_kernel", "linear_kernel", "opencv_is_exact", "remap", "remap_reference", "spline_prefilter"]

#: Extra source pixels prefiltered around a crop for ``spline``: the recursive filter's impulse response
#: decays as ``|√3 - 2|^k``, below 2e-8 at 14 px.
SPLINE_PREFILTER_MARGIN_PX = 14
CUBIC_A = -0.5
LANCZOS_A = 3
_SPLINE_POLE = np.sqrt(3.0) - 2.0
_SPLINE_FIR = (np.sqrt(3.0) * _SPLINE_POLE ** np.abs(np.arange(-SPLINE_PREFILTER_MARGIN_PX,
                                                                SPLINE_PREFILTER_MARGIN_PX + 1))).astype(np.float32)


# ------------------------------------------------------------------------------------------ kernels
def cubic_kernel(t, a: float = CUBIC_A) -> np.ndarray:
    """Cubic convolution kernel (Keys 1981) with parameter ``a``."""
    t = np.abs(np.asarray(t, dtype=np.float64))
    near = ((a + 2.0) * t - (a + 3.0)) * t * t + 1.0
    far = ((a * t - 5.0 * a) * t + 8.0 * a) * t - 4.0 * a
    return np.where(t <= 1.0, near, np.where(t < 2.0, far, 0.0))


def lanczos_kernel(t, a: int = LANCZOS_A) -> np.ndarray:
    """Lanczos kernel ``sinc(t) sinc(t / a)`` on ``|t| < a``."""
    t = np.asarray(t, dtype=np.float64)
    return np.where(np.abs(t) < a, np.sinc(t) * np.sinc(t / a), 0.0)


def linear_kernel(t) -> np.ndarray:
    return np.maximum(0.0, 1.0 - np.abs(np.asarray(t, dtype=np.float64)))


def bspline3_kernel(t) -> np.ndarray:
    """Cubic B-spline ``β³(t)``."""
    t = np.abs(np.asarray(t, dtype=np.float64))
    return np.where(t < 1.0, 2.0 / 3.0 - t * t + 0.5 * t ** 3, np.where(t < 2.0, (2.0 - t) ** 3 / 6.0, 0.0))


# ------------------------------------------------------------------------------------------ prefilter
def spline_prefilter(image: np.ndarray) -> np.ndarray:
    """Cubic B-spline coefficients of ``image`` (H, W[, C]) along rows and columns (mirror boundaries).

    Interpolating the result with the B-spline kernel reproduces ``image`` at the pixel centres
    (Unser et al. 1991).  float32 in, float32 out.  The inverse filter's impulse response is
    ``√3 · z^|k|`` with ``z = √3 - 2`` (Unser et al. 1991, Eq. 2.5 with the cubic B-spline's
    sampled kernel ``(1, 4, 1)/6``); it is applied as a separable FIR of ±14 taps
    (:data:`SPLINE_PREFILTER_MARGIN_PX`: the neglected tail is below 2e-8) by OpenCV in float32, with
    mirror borders (``BORDER_REFLECT_101``, SciPy's ``mirror``): 3× faster than SciPy's recursive
    filter (``scipy.ndimage.spline_filter1d``, used for images smaller than the filter), the same
    coefficients to float32 rounding.
    """

    out = np.asarray(image, dtype=np.float32)
    if min(out.shape[:2]) > 2 * SPLINE_PREFILTER_MARGIN_PX:
        return cv2.sepFilter2D(np.ascontiguousarray(out), cv2.CV_32F, _SPLINE_FIR, _SPLINE_FIR,
                               borderType=cv2.BORDER_REFLECT_101).reshape(out.shape)
    for axis in (0, 1):
        if out.shape[axis] > 1:
            out = spline_filter1d(out, order=3, axis=axis, output=np.float32, mode="mirror")
    return out


# ------------------------------------------------------------------------------------------ OpenCV
_CV_FLAGS = {"linear": "INTER_LINEAR"}


@functools.cache
def opencv_is_exact(method: str) -> bool:
    """True if ``cv2.remap`` with ``method`` (``linear``) interpolates float32 3-channel images at the exact position.

    Probe: a 1/100-px shift of a random image must change the result by about 1/100 of the gradient
    (OpenCV 4 rounds positions to 1/32 px, so the shift would vanish).
    """

    if method not in _CV_FLAGS:
        return False
    rng = np.random.default_rng(0)
    src = rng.random((16, 16, 3)).astype(np.float32)
    yy, xx = np.mgrid[4:12, 4:12].astype(np.float32)
    flag = getattr(cv2, _CV_FLAGS[method])
    a = cv2.remap(src, xx + np.float32(0.25), yy, flag, borderMode=cv2.BORDER_REPLICATE)
    b = cv2.remap(src, xx + np.float32(0.26), yy, flag, borderMode=cv2.BORDER_REPLICATE)
    ref_a = remap_reference(src, xx + 0.25, yy, method)
    ref_b = remap_reference(src, xx + 0.26, yy, method)
    return bool(np.abs((b - a) - (ref_b - ref_a)).max() < 1e-4)


def _cv_remap(src: np.ndarray, u: np.ndarray, v: np.ndarray, method: str) -> np.ndarray:
    flag = getattr(cv2, _CV_FLAGS[method])
    parts = [cv2.remap(src[..., c0:c0 + 4], u, v, flag, borderMode=cv2.BORDER_REPLICATE)
             for c0 in range(0, src.shape[2], 4)]
    parts = [p[..., None] if p.ndim == 2 else p for p in parts]
    return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=-1)


# ------------------------------------------------------------------------------------------ NumPy
def _gather_remap(src: np.ndarray, u: np.ndarray, v: np.ndarray, kernel, radius: int,
                  normalise: bool) -> np.ndarray:
    """Separable kernel at exact positions by gathering ``(2 radius)²`` taps (float32 accumulation)."""
    h, w, c = src.shape
    u = np.asarray(u, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    shape = u.shape
    u, v = u.ravel(), v.ravel()
    missing = ~(np.isfinite(u) & np.isfinite(v))
    if missing.any():
        u, v = np.where(missing, 0.0, u), np.where(missing, 0.0, v)
    iu, iv = np.floor(u), np.floor(v)
    fu, fv = u - iu, v - iv
    iu, iv = iu.astype(np.int64), iv.astype(np.int64)
    taps = range(1 - radius, radius + 1)
    wu = [kernel(fu - k).astype(np.float32) for k in taps]
    wv = [kernel(fv - k).astype(np.float32) for k in taps]
    if normalise:
        su, sv = sum(wu), sum(wv)
        wu = [x / su for x in wu]
        wv = [x / sv for x in wv]
    cols = [np.clip(iu + k, 0, w - 1) for k in taps]
    flat = src.reshape(-1, c)
    out = np.zeros((u.size, c), np.float32)
    for j, k in enumerate(taps):
        row_base = np.clip(iv + k, 0, h - 1) * w
        acc = np.zeros((u.size, c), np.float32)
        for i in range(len(wu)):
            acc += wu[i][:, None] * flat[row_base + cols[i]]
        out += wv[j][:, None] * acc
    out[missing] = np.nan
    return out.reshape(*shape, c)


def remap_reference(src: np.ndarray, u, v, method: str) -> np.ndarray:
    """NumPy evaluation of ``method`` at the exact positions ``(u, v)`` (the definition; slow).

    ``spline`` expects ``src`` to be the raw image and prefilters it here.
    """
    m = interpolation(method)
    src = np.asarray(src, dtype=np.float32)
    squeeze = src.ndim == 2
    if squeeze:
        src = src[..., None]
    raw = src
    if m.prefilter:
        src = spline_prefilter(src)
    out = _gather_remap(src, u, v, m.kernel, m.radius_px, normalise=m.normalise)
    if m.clamped:
        out = clamp_to_neighbours(out, raw, u, v)
    return out[..., 0] if squeeze else out


def clamp_to_neighbours(values: np.ndarray, src: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``values`` ``(*u.shape, C)`` clipped to the range of the 2 × 2 pixels of ``src`` ``(H, W, C)`` around each
    position (``floor(u) … floor(u) + 1``, likewise in ``v``; borders replicate).  Positions that are not
    finite are left as they are."""
    h, w = src.shape[:2]
    kernel = np.ones((2, 2), np.uint8)
    planes = [np.ascontiguousarray(src[..., k]) for k in range(src.shape[2])]
    lo = np.stack([cv2.erode(p, kernel, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE) for p in planes], axis=-1)
    hi = np.stack([cv2.dilate(p, kernel, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE) for p in planes], axis=-1)
    uf, vf = np.asarray(u, np.float32), np.asarray(v, np.float32)
    finite = np.isfinite(uf) & np.isfinite(vf)
    i = np.clip(np.floor(np.where(finite, uf, 0.0)), 0, w - 1).astype(np.intp)
    j = np.clip(np.floor(np.where(finite, vf, 0.0)), 0, h - 1).astype(np.intp)
    clipped = np.minimum(np.maximum(values, lo[j, i]), hi[j, i])
    return np.where(finite[..., None], clipped, values).astype(np.float32)


def _spline_taps(x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Cubic B-spline as two linear fetches per axis: ``[(weight, position), …]`` (Sigg & Hadwiger 2005)."""
    i = np.floor(x)
    t = x - i
    t2 = t * t
    t3 = t2 * t
    w0 = (1.0 - 3.0 * t + 3.0 * t2 - t3) * np.float32(1 / 6)
    w1 = (4.0 - 6.0 * t2 + 3.0 * t3) * np.float32(1 / 6)
    w3 = t3 * np.float32(1 / 6)
    g0 = w0 + w1
    g1 = 1.0 - g0
    return [(g0, i - 1.0 + w1 / g0), (g1, i + 1.0 + w3 / g1)]


def _keys_taps(x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Keys (a = -1/2) as three fetches per axis: the outer taps at their pixels, the middle two merged."""
    i = np.floor(x)
    t = x - i
    t2 = t * t
    t3 = t2 * t
    wm1 = (-t3 + 2.0 * t2 - t) * np.float32(0.5)
    w0 = (3.0 * t3 - 5.0 * t2 + 2.0) * np.float32(0.5)
    w1 = (-3.0 * t3 + 4.0 * t2 + t) * np.float32(0.5)
    w2 = (t3 - t2) * np.float32(0.5)
    g = w0 + w1
    return [(wm1, i - 1.0), (g, i + w1 / g), (w2, i + 2.0)]


def _separable_fetches(src: np.ndarray, taps_u, taps_v, exact_linear: bool) -> np.ndarray:
    """``Σ_a Σ_b wu_a wv_b · bilinear(src, pu_a, pv_b)`` (float32)."""
    fetch = (lambda a, b: _cv_remap(src, a, b, "linear")) if exact_linear else \
        (lambda a, b: _gather_remap(src, a, b, linear_kernel, 1, False))
    out = None
    for wv, pv in taps_v:
        row = None
        for wu, pu in taps_u:
            term = fetch(pu, pv)
            term *= wu[..., None]
            row = term if row is None else np.add(row, term, out=row)
        row *= wv[..., None]
        out = row if out is None else np.add(out, row, out=out)
    return out


def _remap_linear(src: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear: OpenCV where it interpolates at the exact position, else the NumPy gather."""
    if opencv_is_exact("linear"):
        return _cv_remap(src, u, v, "linear")
    return _gather_remap(src, u, v, linear_kernel, 1, normalise=False)


def _remap_keys(src: np.ndarray, u: np.ndarray, v: np.ndarray, clamp: bool) -> np.ndarray:
    """Keys cubic (``clamp``: clipped to the range of the 2 × 2 neighbours): the compiled kernel in one pass, else
    nine bilinear fetches (and the clamp as a second pass)."""
    kernels = compiled_kernels()
    if kernels is not None:
        out = np.empty((*u.shape, src.shape[2]), np.float32)
        kernels.keys(src, u, v, clamp, out)
        return out
    out = _separable_fetches(src, _keys_taps(u), _keys_taps(v), opencv_is_exact("linear"))
    return clamp_to_neighbours(out, src, u, v) if clamp else out


def _remap_cubic(src: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Keys cubic."""
    return _remap_keys(src, u, v, clamp=False)


def _remap_cubic_clamped(src: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Keys cubic clipped to the range of the 2 × 2 neighbours."""
    return _remap_keys(src, u, v, clamp=True)


def _remap_spline(coef: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Cubic B-spline of the coefficients ``coef``: the compiled kernel, else four bilinear fetches."""
    kernels = compiled_kernels()
    if kernels is not None:
        out = np.empty((*u.shape, coef.shape[2]), np.float32)
        kernels.spline(coef, u, v, out)
        return out
    return _separable_fetches(coef, _spline_taps(u), _spline_taps(v), opencv_is_exact("linear"))


def _remap_lanczos(src: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Lanczos-3 by the NumPy gather, weights normalised."""
    return _gather_remap(src, u, v, lanczos_kernel, LANCZOS_A, normalise=True)


@dataclass(frozen=True)
class Interpolation:
    """One interpolation method (module docstring): its definition, its reach and its fast evaluation.

    Attributes
    ----------
    remap
        ``remap(src, u, v) -> (*u.shape, C)`` float32: the fast evaluation on a contiguous float32
        ``(H, W, C)`` source (B-spline coefficients when ``prefilter``) at float32 positions.
    kernel
        The separable 1-D kernel ``k(t)`` that defines the method (:func:`remap_reference`).
    radius_px
        Taps on each side of the sample position the method reads (crop margins).
    prefilter
        The source must first be turned into B-spline coefficients (:func:`spline_prefilter`); a crop then
        needs :data:`SPLINE_PREFILTER_MARGIN_PX` more source pixels.
    normalise
        The kernel's weights are normalised to sum 1 at each position.
    clamped
        The result is clipped to the range of the 2 × 2 source pixels around the position.
    """

    remap: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]
    kernel: Callable
    radius_px: int
    prefilter: bool = False
    normalise: bool = False
    clamped: bool = False


#: The interpolation methods by name (the valid names are its keys, :data:`~omnispectral.choices.INTERP_NAMES` in
#: that order): one lookup, :func:`interpolation`.
METHODS: dict[str, Interpolation] = dict(zip(INTERP_NAMES, (
    Interpolation(_remap_linear, linear_kernel, 1),  # linear
    Interpolation(_remap_cubic, cubic_kernel, 2),  # cubic
    Interpolation(_remap_spline, bspline3_kernel, 2, prefilter=True),  # spline
    Interpolation(_remap_lanczos, lanczos_kernel, LANCZOS_A, normalise=True),  # lanczos
    Interpolation(_remap_cubic_clamped, cubic_kernel, 2, clamped=True),  # cubic-clamped
), strict=True))
#: Taps on each side of the sample position a method reads (crop margins), by method name.
KERNEL_RADIUS_PX = {name: m.radius_px for name, m in METHODS.items()}


def interpolation(method: str) -> Interpolation:
    """The :class:`Interpolation` called ``method``.

    Parameters
    ----------
    method
        A key of :data:`METHODS`.

    Returns
    -------
    Interpolation
        The method's entry.

    Raises
    ------
    ConfigurationError
        For an unknown name (the message lists the valid ones).
    """
    return method_from(METHODS, method, "interpolation")


def check_method(method: str) -> str:
    """``method`` if it names an interpolation of :data:`METHODS`, else :class:`ConfigurationError`."""
    interpolation(method)
    return method


def remap(src: np.ndarray, u: np.ndarray, v: np.ndarray, method: str = "cubic",
          prefiltered: bool = False) -> np.ndarray:
    """Interpolate ``src`` (H, W[, C]) float32 at positions ``u`` (column) and ``v`` (row), float32 maps.

    Pixel centres are at integer coordinates (OpenCV convention).  Returns ``(*u.shape, C)``
    float32 (or ``u.shape`` for a 2-D ``src``).  For ``spline``, ``prefiltered=True`` says ``src``
    already holds B-spline coefficients (:func:`spline_prefilter`).
    """
    m = interpolation(method)
    src = np.ascontiguousarray(src, dtype=np.float32)
    squeeze = src.ndim == 2
    if squeeze:
        src = src[..., None]
    u = np.ascontiguousarray(u, dtype=np.float32)
    v = np.ascontiguousarray(v, dtype=np.float32)
    if m.prefilter and not prefiltered:
        src = spline_prefilter(src)
    out = m.remap(src, u, v)
    return out[..., 0] if squeeze else out
