"""Sub-pixel registration of camera B to camera A by phase-only correlation (paper Sec. 4.3, Eq. (3)).

The paper aligns the two cameras' images with phase-only correlation (POC; Kuglin & Hines 1975):

.. math::  R(u, v) = \\frac{F(u,v)\\,\\overline{G}(u,v)}{|F(u,v)\\,\\overline{G}(u,v)|}

and takes the displacement from the position of the maximum of the inverse transform of ``R``.
This module computes the conjugate, ``G F* / |G F*|``, so that the peak sits at ``+d`` rather than
``-d`` (see the sign convention below); the magnitude and the information are the same.

What is added to Eq. (3), following Takita et al. 2003 ("High-accuracy subpixel image
registration based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934):

1. **Window.**  Cropped images are not periodic; a 2-D Hann (or Tukey) window, applied after
   subtracting the window-weighted mean, removes the wrap-around edges that would otherwise pull
   the peak to zero shift.
2. **Band limit.**  Only frequencies ``|k| <= K`` (a fraction ``band_limit`` of Nyquist in each
   axis) enter the correlation; high frequencies, where sensor noise and aliasing dominate the
   phase, are dropped.  As in Takita et al., the inverse transform is taken on the small
   ``L = 2K + 1`` grid (here ``upsample`` times oversampled), which makes it cheap.
3. **Peak model.**  For a pure translation ``d`` the band-limited POC function is the separable
   Dirichlet kernel

   .. math::  r(n_1, n_2) = \\alpha\\, D_{L_1}(n_1 - \\delta_1)\\, D_{L_2}(n_2 - \\delta_2),\\qquad
              D_L(t) = \\frac{\\sin(\\pi L t / M)}{L \\sin(\\pi t / M)}

   on an ``M``-point grid (Takita et al. Eq. (13), with the oversampling factor ``M / L``).  It is
   fitted by least squares (Gauss-Newton) to the ``(2 r + 1)^2`` values around the integer
   maximum, giving ``delta`` and the peak height ``alpha``.  ``alpha`` is 1 for identical
   structure and about ``1/sqrt(L1 L2)`` for unrelated images: it is the confidence.

4. **Refinement on the common overlap** (``refine``, default one pass).  Both images are cropped to
   their overlap for ``round(d)``, the moving crop's window is evaluated at ``x - frac(d)`` so the
   two windowed crops are exact shifts of each other, and the residual shift maximises the
   ``|G F*|^0.5``-weighted correlation over the band (between POC, power 0, and cross-correlation,
   power 1) by Newton steps on separable phase factors.  This removes the window's pull towards
   zero shift; large images take the first pass on 2×2-binned pixels.

Beyond the paper:

- **Saturation.**  Clipped pixels (a sensor's full scale, e.g. the sun) have sharp, aliased
  boundaries that do not obey the shift theorem; a few of them bias the estimate by tenths of a
  pixel.  They are detected (a plateau at the image maximum, or a given level) and faded to the
  image mean with a soft mask.
- **Variance-stabilising pre-processing.**  ``preprocess="sqrt"`` (the Anscombe transform of
  photon-limited data) equalises shot noise between dark and bright regions and compresses the
  dynamic range of HDR input; ``"log"`` compresses further; ``"gradient"`` (gradient magnitude of
  the square root) is insensitive to contrast reversal between colour bands.
- **Fallback** to the rig's calibrated offset when the confidence is low (texture-less sky):
  :func:`register_with_fallback`.
- **Block-wise POC** (:func:`omnispectral.imaging.blockpoc.block_disparity`, in its own module): a
  coarse dense disparity map of camera B against camera A, with confidence, an unreliable mask and an
  occlusion mask (the paper's named open problem, near objects and occlusion).  It batches this
  module's building blocks over blocks: :func:`check_poc_options`, :func:`check_image_pair`,
  :func:`prepare_for_poc`, :func:`fade_saturated`, :func:`apply_window` and :func:`poc_shift`
  (band spectra, :func:`band_limited_poc` -- Eq. (3) -- and :func:`fit_peak`).

Sign convention
---------------
``dx, dy`` is the displacement of ``moving``'s content relative to ``reference``::

    moving(x, y) ~= reference(x - dx, y - dy)

A feature at ``(x, y)`` in the reference appears at ``(x + dx, y + dy)`` in the moving image; to
resample ``moving`` onto ``reference``'s grid, read it at ``(x + dx, y + dy)``.  This is the
convention of ``cv2.phaseCorrelate(reference, moving)``; ``skimage.registration.
phase_cross_correlation`` returns ``(-dy, -dx)``.  ``x`` is the column index, ``y`` the row index.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass
from types import SimpleNamespace

import cv2
import numpy as np
import scipy.fft as sfft
from scipy import ndimage

from omnispectral.choices import DEFAULT_BAND_LIMIT, DEFAULT_MIN_CONFIDENCE, DEFAULT_PREPROCESS, PREPROCESS, WINDOWS
from omnispectral.compiled import built_on_first_use
from omnispectral.errors import ConfigurationError
from omnispectral.threads import single_threaded_blas

__all__ = [
    "AUTO_SATURATION_MIN_PX", "COARSE_MIN_SIZE_PX", "DEFAULT_BAND_LIMIT", "DEFAULT_FIT_RADIUS",
    "DEFAULT_MIN_CONFIDENCE", "DEFAULT_PREPROCESS", "DEFAULT_REFINE", "DEFAULT_UPSAMPLE", "DEFAULT_WINDOW",
    "MIN_SIZE_PX", "PREPROCESS",
    "SPECTRAL_WEIGHT_POWER", "WINDOWS", "Registration", "apply_window", "as_gray", "band_limited_poc", "band_size",
    "check_image_pair", "check_poc_options", "fade_saturated", "fit_peak", "phase_correlate", "poc_shift",
    "prepare_for_poc", "preprocess_image", "register_with_fallback", "saturation_mask", "weighted_cross_power",
    "window_1d", "window_2d",
]

DEFAULT_WINDOW = "hann"
#: Oversampling of the band-limited correlation grid (``M / L``) on which the peak model is fitted.
DEFAULT_UPSAMPLE = 1.25
#: Half size of the neighbourhood fitted by the peak model (``2 r + 1`` samples per axis).
DEFAULT_FIT_RADIUS = 3
#: Passes on the common overlap with a moved window (:func:`_refine`).
DEFAULT_REFINE = 1
#: Exponent ``p`` of the spectral weight ``|G F*|^p`` of the refinement (0 = phase only, 1 = cross-correlation).
SPECTRAL_WEIGHT_POWER = 0.5
#: Images at least this large get the first pass on 2 x 2-binned pixels (4x fewer FFT samples).
COARSE_MIN_SIZE_PX = 512

#: Smallest image side accepted (below this a Hann window leaves almost nothing).
MIN_SIZE_PX = 8
#: A value attained by at least this many pixels at the image maximum is taken as clipping.
AUTO_SATURATION_MIN_PX = 4
_SATURATION_GROW_PX = 2
_SATURATION_SOFTNESS_PX = 1.5
_MAX_REFINE_CORRECTION_PX = 1.0
_TUKEY_ALPHA = 0.5
_TAYLOR_TERMS = 7
_TAYLOR_RADIUS_PX = 0.2


@dataclass(frozen=True)
class Registration:
    """Result of :func:`phase_correlate` / :func:`register_with_fallback`.

    ``dx, dy`` follow the module's convention ``moving(x, y) ~= reference(x - dx, y - dy)`` (pixels).
    ``confidence`` is the fitted POC peak height (1 = identical structure, ~0 = unrelated).  When
    ``used_fallback`` is true, ``dx, dy`` are the calibrated offset and ``measured_dx, measured_dy``
    what the correlation found.
    """

    dx: float
    dy: float
    confidence: float
    measured_dx: float
    measured_dy: float
    used_fallback: bool = False
    min_confidence: float | None = None
    window: str = DEFAULT_WINDOW
    band_limit: float = DEFAULT_BAND_LIMIT
    preprocess: str = DEFAULT_PREPROCESS
    saturated_fraction: float = 0.0
    shape: tuple[int, int] = (0, 0)

    def to_dict(self) -> dict:
        out = asdict(self)
        out["shape"] = list(self.shape)
        out["convention"] = "moving(x, y) ~= reference(x - dx, y - dy); x = column, y = row, pixels"
        return out


# ------------------------------------------------------------------------------------------ input
def as_gray(image, name: str = "image", check_finite: bool = True) -> np.ndarray:
    """``(H, W)`` or ``(H, W, C)`` numeric array → ``(H, W)`` float32 (mean of the channels).

    Raises :class:`ConfigurationError` for other shapes, non-numeric data, NaN or infinity (``check_finite``
    False: the caller checks the values itself, :func:`prepare_for_poc`).
    """
    arr = np.asarray(image)
    if arr.dtype.kind not in "uif":
        raise ConfigurationError(f"{name}: pixel type {arr.dtype} is not a real number type")
    if arr.ndim == 3:
        if arr.shape[2] == 0:
            raise ConfigurationError(f"{name}: image has no channels (shape {arr.shape})")
        arr = arr.mean(axis=2, dtype=np.float32) if arr.shape[2] > 1 else arr[:, :, 0]
    elif arr.ndim != 2:
        raise ConfigurationError(f"{name}: expected an (H, W) or (H, W, C) image, got shape {arr.shape}")
    if min(arr.shape) < MIN_SIZE_PX:
        raise ConfigurationError(f"{name}: image {arr.shape[0]}x{arr.shape[1]} is too small for phase correlation "
                                 f"(at least {MIN_SIZE_PX}x{MIN_SIZE_PX} px)")
    arr = np.asarray(arr, dtype=np.float32)
    if check_finite and not np.isfinite(arr.sum(dtype=np.float64)) and not np.isfinite(arr).all():
        _not_finite(name)
    return arr


def _not_finite(name: str):
    raise ConfigurationError(f"{name}: image contains NaN or infinite values; fill or crop them first")


def check_image_pair(reference, moving) -> tuple[np.ndarray, np.ndarray]:
    """Check that a reference and a moving image have the same size (rows, columns).

    Parameters
    ----------
    reference, moving
        ``(H, W)`` or ``(H, W, C)`` array-likes.

    Returns
    -------
    tuple of numpy.ndarray
        Both images as arrays (not copied).

    Raises
    ------
    ConfigurationError
        When their first two dimensions differ.
    """
    ref = np.asarray(reference)
    mov = np.asarray(moving)
    if ref.shape[:2] != mov.shape[:2]:
        raise ConfigurationError(f"reference and moving images differ in size: {ref.shape[:2]} vs {mov.shape[:2]} "
                                 "(crop both to the same region first)")
    return ref, mov


def check_poc_options(window: str, band_limit: float, upsample: float, preprocess: str, fit_radius: int) -> None:
    """Check the options of the band-limited POC (shared by :func:`phase_correlate` and block-wise POC).

    Parameters
    ----------
    window
        One of :data:`WINDOWS`.
    band_limit
        Fraction of Nyquist kept in each axis, in ``(0, 1]``.
    upsample
        Oversampling of the band-limited correlation grid, in ``[1, 8]``.
    preprocess
        One of :data:`PREPROCESS`.
    fit_radius
        Half size of the peak-fit neighbourhood, an integer in ``1..4``.

    Raises
    ------
    ConfigurationError
        For a value outside these ranges.
    """
    if window not in WINDOWS:
        raise ConfigurationError(f"unknown window {window!r}; choose one of {', '.join(WINDOWS)}")
    if preprocess not in PREPROCESS:
        raise ConfigurationError(f"unknown preprocess {preprocess!r}; choose one of {', '.join(PREPROCESS)}")
    if not 0.0 < band_limit <= 1.0:
        raise ConfigurationError(f"band_limit must be in (0, 1] (fraction of Nyquist), got {band_limit}")
    if not 1.0 <= upsample <= 8.0:
        raise ConfigurationError(f"upsample must be a number in [1, 8], got {upsample}")
    if int(fit_radius) != fit_radius or not 1 <= fit_radius <= 4:
        raise ConfigurationError(f"fit_radius must be an integer in 1..4, got {fit_radius}")


# ------------------------------------------------------------------------------ pre-processing
def saturation_mask(image, saturation: float | str | None = None) -> np.ndarray | None:
    """Pixels clipped at the sensor's full scale (any channel), or ``None`` when there are none.

    ``saturation`` is a level (pixels ``>=`` it are clipped), ``"auto"`` (a plateau of at least
    :data:`AUTO_SATURATION_MIN_PX` pixels at a channel's maximum value) or ``None`` (no detection).
    """
    if saturation is None:
        return None
    arr = np.asarray(image)
    chans = arr[:, :, None] if arr.ndim == 2 else arr
    mask = None
    for c in range(chans.shape[2]):
        ch = chans[:, :, c]
        if isinstance(saturation, str):
            if saturation != "auto":
                raise ConfigurationError(f"saturation must be a number, 'auto' or None, got {saturation!r}")
            top = ch.max()
            hit = ch >= top
            if np.count_nonzero(hit) < AUTO_SATURATION_MIN_PX:
                continue
        else:
            hit = ch >= saturation
        mask = hit if mask is None else (mask | hit)
    if mask is None or not mask.any():
        return None
    return mask


def fade_saturated(gray: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Blend clipped (or otherwise invalid) regions into the mean of the rest of the image.

    The masked region is grown by 2 px and its edge softened by a 1.5 px Gaussian, so that no sharp,
    aliased boundary (which does not obey the shift theorem) enters the correlation.

    Parameters
    ----------
    gray
        ``(H, W)`` float image (pre-processed).
    mask
        ``(H, W)`` boolean, ``True`` for the pixels to fade.

    Returns
    -------
    numpy.ndarray
        A faded copy of ``gray`` (``gray`` itself when ``mask`` is empty).
    """

    pad = _SATURATION_GROW_PX + int(np.ceil(4 * _SATURATION_SOFTNESS_PX)) + 1
    if not mask.any():
        return gray
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    y0, y1 = max(rows[0] - pad, 0), min(rows[-1] + pad + 1, gray.shape[0])
    x0, x1 = max(cols[0] - pad, 0), min(cols[-1] + pad + 1, gray.shape[1])
    sub = mask[y0:y1, x0:x1]
    grown = ndimage.binary_dilation(sub, iterations=_SATURATION_GROW_PX)
    keep = 1.0 - ndimage.gaussian_filter(grown.astype(np.float32), _SATURATION_SOFTNESS_PX)
    keep[grown] = 0.0
    unsat = ~mask
    mean = float(gray[unsat].mean()) if unsat.any() else float(gray.mean())
    out = gray.copy()
    out[y0:y1, x0:x1] = mean + (gray[y0:y1, x0:x1] - mean) * keep
    return out


def preprocess_image(gray: np.ndarray, kind: str = DEFAULT_PREPROCESS) -> np.ndarray:
    """Intensity transform applied before correlation (see the module docstring)."""
    if kind == "none":
        return gray
    if kind == "sqrt":
        if gray.ndim == 2 and gray.dtype == np.float32:  # OpenCV's vectorised loops: 2x NumPy's here
            out = cv2.max(gray, 0.0)
            return cv2.sqrt(out, dst=out)
        return np.sqrt(np.maximum(gray, 0.0, dtype=np.float32))
    if kind == "log":
        pos = gray[gray > 0]
        eps = np.float32(max(1e-3 * float(pos.mean()) if pos.size else 1.0, 1e-12))
        return np.log(np.maximum(gray, 0.0) + eps).astype(np.float32, copy=False)
    if kind == "gradient":
        s = np.sqrt(np.maximum(gray, 0.0, dtype=np.float32))
        gy, gx = np.gradient(s)
        return np.hypot(gx, gy).astype(np.float32, copy=False)
    raise ConfigurationError(f"unknown preprocess {kind!r}; choose one of {', '.join(PREPROCESS)}")


def prepare_for_poc(image, name: str, preprocess: str, saturation) -> tuple[np.ndarray, np.ndarray | None]:
    """An input image as the correlation uses it: grey (:func:`as_gray`), pre-processed, and its clipped pixels.

    Parameters
    ----------
    image
        ``(H, W)`` or ``(H, W, C)`` numeric array.
    name
        Name used in error messages.
    preprocess
        Intensity transform, see :func:`preprocess_image`.
    saturation
        ``None``, a clipping level or ``"auto"``, see :func:`saturation_mask`.

    Returns
    -------
    gray : numpy.ndarray
        ``(H, W)`` float32, pre-processed.
    saturated : numpy.ndarray or None
        ``(H, W)`` boolean mask of clipped pixels, or ``None`` when there are none.
    """
    kernels = _poc_kernels() if preprocess == "sqrt" else None
    gray = as_gray(image, name, check_finite=kernels is None)
    if kernels is None:
        return preprocess_image(gray, preprocess), saturation_mask(image, saturation)
    out = np.empty(gray.shape, np.float32)
    if not kernels.sqrt_of_positive(gray, out):  # one pass: the values checked and transformed
        _not_finite(name)
    return out, saturation_mask(image, saturation)


def _shift_mask(mask: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``mask`` moved by the rounded ``(dx, dy)`` (content at ``p`` goes to ``p + d``), zero-filled."""
    ix, iy = round(dx), round(dy)
    h, w = mask.shape
    out = np.zeros_like(mask)
    if abs(ix) >= w or abs(iy) >= h:
        return out
    out[max(iy, 0):h + min(iy, 0), max(ix, 0):w + min(ix, 0)] = mask[max(-iy, 0):h - max(iy, 0),
                                                                      max(-ix, 0):w - max(ix, 0)]
    return out


# ------------------------------------------------------------------------------------- windows
@functools.lru_cache(maxsize=64)
def window_1d(n: int, kind: str = DEFAULT_WINDOW) -> np.ndarray:
    """Symmetric 1-D window of ``n`` samples (read-only float32): Hann, Tukey (alpha 0.5) or none."""
    from scipy.signal import windows  # lazy: scipy.signal costs ~0.7 s to import; windows are cached

    if kind == "hann":
        w = windows.hann(n, sym=True)
    elif kind == "tukey":
        w = windows.tukey(n, _TUKEY_ALPHA, sym=True)
    elif kind == "none":
        w = np.ones(n)
    else:
        raise ConfigurationError(f"unknown window {kind!r}; choose one of {', '.join(WINDOWS)}")
    w = w.astype(np.float32)
    w.setflags(write=False)
    return w


@functools.lru_cache(maxsize=16)
def window_2d(shape: tuple[int, int], kind: str = DEFAULT_WINDOW) -> np.ndarray:
    """Separable 2-D window for ``shape`` (cached per shape and kind; read-only float32)."""
    w = window_1d(shape[0], kind)[:, None] * window_1d(shape[1], kind)[None, :]
    w.setflags(write=False)
    return w


def apply_window(x: np.ndarray, kind: str) -> np.ndarray:
    """Subtract the window-weighted mean of each image (last two axes), then multiply by the window.

    Removing the weighted mean first matters: the window's own spectrum times a non-zero mean
    is identical in both images and would add a spurious peak at zero shift.

    Parameters
    ----------
    x
        ``(..., H, W)`` float32 image or batch of images (e.g. blocks).
    kind
        Window, one of :data:`WINDOWS`.

    Returns
    -------
    numpy.ndarray
        ``(..., H, W)`` float32, the windowed zero-(weighted-)mean images (a new array).
    """
    if x.ndim == 2 and kind != "none":
        return _window_separable(x, window_1d(x.shape[0], kind), window_1d(x.shape[1], kind))
    w = window_2d((x.shape[-2], x.shape[-1]), kind)
    # einsum without BLAS: a threaded sgemv stalls for milliseconds when the cores are busy.
    mean = np.einsum("...ij,ij->...", x, w) / np.float32(w.sum(dtype=np.float64))
    centred = x - np.asarray(mean, dtype=np.float32)[..., None, None]
    if kind != "none":
        centred *= w
    return centred


# --------------------------------------------------------------------------- POC and peak fit
def band_size(n: int, band_limit: float) -> int:
    """Highest frequency index ``K`` kept for an axis of ``n`` samples (at least 2, below Nyquist)."""
    return int(max(2, min(n // 2 - 1, np.floor(band_limit * (n / 2.0 - 1.0)))))


def _take_band(f: np.ndarray, n0: int, k: tuple[int, int]) -> np.ndarray:
    """Rows ``0..K0`` and ``N0-K0..N0-1``, columns ``0..K1`` of half spectra ``(..., N0, N1 // 2 + 1)``."""
    k0, k1 = k
    return np.concatenate([f[..., :k0 + 1, :k1 + 1], f[..., n0 - k0:, :k1 + 1]], axis=-2)


def _band_spectrum(x: np.ndarray, k: tuple[int, int], overwrite: bool = False) -> np.ndarray:
    """The band of the real 2-D DFT of ``x`` (last two axes) that the correlation uses, as :func:`_take_band`.

    A single image goes through OpenCV's real DFT, whose packed ("CCS") output is unpacked here: on the
    2-core machine it took 2.4-3.6 ms for 1024 x 1024 float32 against 9-11 ms for ``scipy.fft.rfft2``
    of 1000 x 1000 (one or two workers) when the cores were busy (docs/benchmarks.md).  Batches (block
    disparity) go through ``scipy.fft.rfft2``.  Layout of the packed output (OpenCV ``dft``): columns
    ``j = 1 .. N1/2 - 1`` hold ``Re, Im`` of ``F[r, j]`` at ``2j - 1, 2j`` for every row ``r``; column 0
    holds ``F[0, 0]`` and then ``Re, Im`` of ``F[m, 0]`` at rows ``2m - 1, 2m``, with
    ``F[N0 - m, 0] = conj(F[m, 0])`` (a real input's column of row sums).  ``overwrite``: ``x`` (a
    temporary) may hold the transform afterwards (in place: 3x faster than into a new array here).
    """
    k0, k1 = k
    n0 = x.shape[-2]
    if x.ndim != 2:
        return _take_band(sfft.rfft2(x, axes=(-2, -1), workers=-1), n0, k)
    packed = np.ascontiguousarray(x, dtype=np.float32)
    packed = cv2.dft(packed, dst=packed) if overwrite or packed is not x else cv2.dft(packed)
    out = np.empty((2 * k0 + 1, k1 + 1), dtype=np.complex64)
    pairs = packed[:, 1:2 * k1 + 1]
    out[:k0 + 1, 1:] = pairs[:k0 + 1].view(np.complex64)
    out[k0 + 1:, 1:] = pairs[n0 - k0:].view(np.complex64)
    column = packed[1:2 * k0 + 1, 0]
    out[0, 0] = packed[0, 0]
    out[1:k0 + 1, 0].real = column[0::2]
    out[1:k0 + 1, 0].imag = column[1::2]
    out[k0 + 1:, 0] = np.conj(out[k0:0:-1, 0])
    return out


def band_limited_poc(b_ref: np.ndarray, b_mov: np.ndarray, k: tuple[int, int],
                     upsample: float) -> tuple[np.ndarray, tuple[int, int], tuple[int, int]]:
    """Band-limited POC function of two windowed images from their spectral bands (Eq. (3); Takita et al. 2003).

    The normalised cross-phase spectrum of paper Eq. (3), here its conjugate so that the peak sits at
    ``+d`` (module docstring),

    .. math::  R(k_0, k_1) = \\frac{G(k_0, k_1)\\,\\overline{F}(k_0, k_1)}{|G(k_0, k_1)\\,\\overline{F}(k_0, k_1)|},
               \\qquad |k_0| \\le K_0,\\ 0 \\le k_1 \\le K_1

    (``F``, ``G``: the DFTs of the reference and the moving image; the other half of the spectrum
    follows by Hermitian symmetry) is kept on the band only (Takita et al.'s band limitation,
    ``L = 2 K + 1`` frequencies per axis), zero-padded to an ``M``-point grid (``M`` the first fast FFT
    length ``>= upsample * L``) and inverse transformed.  The DC term, whose phase is undefined once the
    means are removed, is set to 1.

    Parameters
    ----------
    b_ref, b_mov
        ``(..., 2 K0 + 1, K1 + 1)`` complex64 bands of the real 2-D DFTs of the windowed reference and
        moving images (:func:`_band_spectrum`): rows ``0..K0`` then ``-K0..-1``, columns ``0..K1``.
        Leading axes are a batch (e.g. blocks).
    k
        ``(K0, K1)``, the highest frequency index kept per axis (:func:`band_size`).
    upsample
        Oversampling ``M / L`` of the correlation grid.

    Returns
    -------
    r : numpy.ndarray
        ``(..., M0, M1)`` float32 band-limited POC function, normalised so that a perfect match peaks
        at 1; a shift ``d`` (px) peaks at ``d * M / N`` (``N`` the image size) with wrap-around.
    big_l : tuple of int
        ``(L0, L1)``.
    big_m : tuple of int
        ``(M0, M1)``.

    References
    ----------
    Kuglin & Hines 1975 (phase correlation); K. Takita et al., "High-accuracy subpixel image
    registration based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003.
    """
    k0, k1 = k
    l0, l1 = 2 * k0 + 1, 2 * k1 + 1
    m0 = sfft.next_fast_len(int(np.ceil(upsample * l0)), real=True)
    m1 = sfft.next_fast_len(int(np.ceil(upsample * l1)), real=True)
    batch = b_ref.shape[:-2]
    cross = b_mov * np.conj(b_ref)
    mag = np.abs(cross)
    mag += np.float32(1e-30)
    cross /= mag
    if not batch and k1 < m1 // 2:
        return _inverse_band_opencv(cross, k, (m0, m1)) * np.float32(1.0 / (l0 * l1)), (l0, l1), (m0, m1)
    band = np.zeros((*batch, m0, m1 // 2 + 1), dtype=np.complex64)
    band[..., :k0 + 1, :k1 + 1] = cross[..., :k0 + 1, :]
    band[..., m0 - k0:, :k1 + 1] = cross[..., k0 + 1:, :]
    # The phase of the DC term is undefined once the means are removed; its consistent value is 1.
    band[..., 0, 0] = 1.0
    # one image: one thread (a second FFT thread stalls for milliseconds when the cores are busy)
    r = sfft.irfft2(band, s=(m0, m1), axes=(-2, -1), workers=-1 if batch else 1)
    r *= np.float32(m0 * m1 / (l0 * l1))
    return r, (l0, l1), (m0, m1)


def _inverse_band_opencv(cross: np.ndarray, k: tuple[int, int], big_m: tuple[int, int]) -> np.ndarray:
    """``M0 M1`` times the real inverse DFT of one band (:func:`band_limited_poc`'s, DC set to 1) on the ``M`` grid.

    The band is packed into OpenCV's "CCS" layout (:func:`_band_spectrum`) and transformed in place by
    ``cv2.dft`` (0.22 ms for 480 x 480 here against 0.41 ms for ``scipy.fft.irfft2`` on one thread).  Needs
    ``K1 < M1 / 2`` (no Nyquist column); column 0 is Hermitian in the rows, so only rows ``1..K0`` are packed.
    """
    (k0, k1), (m0, m1) = k, big_m
    packed = np.zeros((m0, m1), dtype=np.float32)
    packed[:k0 + 1, 1:2 * k1 + 1] = cross[:k0 + 1, 1:].view(np.float32)
    packed[m0 - k0:, 1:2 * k1 + 1] = cross[k0 + 1:, 1:].view(np.float32)
    packed[0, 0] = 1.0
    packed[1:2 * k0 + 1:2, 0] = cross[1:k0 + 1, 0].real
    packed[2:2 * k0 + 2:2, 0] = cross[1:k0 + 1, 0].imag
    return cv2.dft(packed, dst=packed, flags=cv2.DFT_INVERSE | cv2.DFT_REAL_OUTPUT)


def _dirichlet(t: np.ndarray, big_l: int, big_m: int) -> tuple[np.ndarray, np.ndarray]:
    """``D_L(t) = sin(pi L t / M) / (L sin(pi t / M))`` and its derivative in ``t`` (Takita et al. Eq. (13))."""
    u = np.pi * t / big_m
    s = np.sin(u)
    small = np.abs(s) < 1e-6
    s_safe = np.where(small, 1.0, s)
    num = np.sin(big_l * u)
    d = np.where(small, 1.0 - (big_l**2 - 1) * u * u / 6.0, num / (big_l * s_safe))
    dd_du = np.where(small, -(big_l**2 - 1) * u / 3.0,
                     (big_l * np.cos(big_l * u) * s - num * np.cos(u)) / (big_l * s_safe * s_safe))
    return d, dd_du * (np.pi / big_m)


def fit_peak(r: np.ndarray, big_l: tuple[int, int], big_m: tuple[int, int], radius: int = DEFAULT_FIT_RADIUS,
             iterations: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares fit of Takita et al.'s peak model around the integer maximum of each POC surface.

    ``r`` is ``(..., M0, M1)``.  Returns the peak position on the ``M`` grid (rows, cols; signed,
    wrapped to ``[-M/2, M/2)``) and the fitted height ``alpha``, each of shape ``r.shape[:-2]``.
    Gauss-Newton on ``alpha * D(n0 - d0) * D(n1 - d1)`` over the ``(2 radius + 1)^2`` samples,
    started from a 3-point parabola; sub-sample offsets are kept within +-1 sample.

    Parameters
    ----------
    r : numpy.ndarray
        ``(..., M0, M1)`` band-limited POC functions (:func:`band_limited_poc`); leading axes are a batch.
    big_l : tuple of int
        ``(L0, L1)``, the number of frequencies kept per axis (``2 K + 1``), the width of the Dirichlet kernel.
    big_m : tuple of int
        ``(M0, M1)``, the size of the correlation grid.
    radius : int
        The model is fitted to the ``(2 radius + 1)^2`` samples around the integer maximum (wrapped).
    iterations : int
        Gauss-Newton steps.

    Returns
    -------
    p0, p1 : numpy.ndarray
        The peak position in samples of the ``M`` grid (rows, columns; signed, wrapped to ``[-M/2, M/2)``),
        shape ``r.shape[:-2]`` (float64).  A shift ``d`` px of an ``N``-pixel image peaks at ``d * M / N``.
    alpha : numpy.ndarray
        The fitted peak height (the confidence: 1 for identical structure), shape ``r.shape[:-2]``.
        Where the fit is not finite the parabola's position and the sampled maximum are returned.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3) (the displacement at the maximum of the inverse
       transform of the cross-phase spectrum).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003,
       Eq. (13) (the peak model and its least-squares fit).
    """
    m0, m1 = big_m
    batch = r.shape[:-2]
    flat = r.reshape(-1, m0, m1)
    nb = flat.shape[0]
    idx = np.argmax(flat.reshape(nb, -1), axis=1)
    i0, i1 = np.divmod(idx, m1)
    offs = np.arange(-radius, radius + 1)
    rows = (i0[:, None] + offs[None, :]) % m0
    cols = (i1[:, None] + offs[None, :]) % m1
    y = flat[np.arange(nb)[:, None, None], rows[:, :, None], cols[:, None, :]].astype(np.float64)
    c = radius
    peak = y[:, c, c]

    def parabola(lo, mid, hi):
        den = lo - 2 * mid + hi
        return np.where(den < 0, np.clip(0.5 * (lo - hi) / np.where(den < 0, den, -1.0), -0.5, 0.5), 0.0)

    d0 = parabola(y[:, c - 1, c], peak, y[:, c + 1, c])
    d1 = parabola(y[:, c, c - 1], peak, y[:, c, c + 1])
    alpha = peak.copy()
    t = offs.astype(np.float64)[None, :]
    eye = np.eye(3)[None]
    for _ in range(iterations):
        g0, g0d = _dirichlet(t - d0[:, None], big_l[0], m0)
        g1, g1d = _dirichlet(t - d1[:, None], big_l[1], m1)
        model = g0[:, :, None] * g1[:, None, :]
        resid = (y - alpha[:, None, None] * model).reshape(nb, -1)
        jac = np.stack([model.reshape(nb, -1),
                        (-alpha[:, None, None] * g0d[:, :, None] * g1[:, None, :]).reshape(nb, -1),
                        (-alpha[:, None, None] * g0[:, :, None] * g1d[:, None, :]).reshape(nb, -1)], axis=2)
        jtj = np.einsum("bki,bkj->bij", jac, jac)
        jtr = np.einsum("bki,bk->bi", jac, resid)
        damp = 1e-9 * np.trace(jtj, axis1=1, axis2=2)[:, None, None] + 1e-30
        step = np.linalg.solve(jtj + damp * eye, jtr[:, :, None])[:, :, 0]
        alpha = alpha + step[:, 0]
        d0 = np.clip(d0 + step[:, 1], -1.0, 1.0)
        d1 = np.clip(d1 + step[:, 2], -1.0, 1.0)
    bad = ~(np.isfinite(alpha) & np.isfinite(d0) & np.isfinite(d1))
    if bad.any():
        d0[bad] = parabola(y[bad, c - 1, c], peak[bad], y[bad, c + 1, c])
        d1[bad] = parabola(y[bad, c, c - 1], peak[bad], y[bad, c, c + 1])
        alpha[bad] = peak[bad]
    p0 = ((i0 + m0 // 2) % m0) - m0 // 2 + d0
    p1 = ((i1 + m1 // 2) % m1) - m1 // 2 + d1
    return p0.reshape(batch), p1.reshape(batch), alpha.reshape(batch)


def poc_shift(ref_w: np.ndarray, mov_w: np.ndarray, band_limit: float, upsample: float,
              fit_radius: int, overwrite: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translation between windowed images by band-limited POC and the peak model (Eq. (3) + Takita 2003).

    The spectral bands (:func:`_band_spectrum`), the band-limited POC function
    (:func:`band_limited_poc`) and the Dirichlet peak fit (:func:`fit_peak`), converted from the
    correlation grid to pixels.  No refinement (see :func:`phase_correlate`).

    Parameters
    ----------
    ref_w, mov_w
        ``(..., H, W)`` float32 windowed images (:func:`apply_window`), same shape; leading axes are a
        batch (block-wise POC).
    band_limit
        Fraction of Nyquist kept in each axis.
    upsample
        Oversampling of the band-limited correlation grid.
    fit_radius
        The peak model is fitted to ``(2 fit_radius + 1)^2`` samples.
    overwrite
        The inputs are temporaries that the transforms may overwrite.

    Returns
    -------
    dx_px, dy_px, alpha : numpy.ndarray
        Arrays over the leading axes (0-d for single images): the shift of the moving image's content
        (module convention) in pixels, and the fitted peak height (the confidence).

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003
       (band limitation and peak model).
    """
    shape = ref_w.shape[-2:]
    k = (band_size(shape[0], band_limit), band_size(shape[1], band_limit))
    r, big_l, big_m = band_limited_poc(_band_spectrum(ref_w, k, overwrite), _band_spectrum(mov_w, k, overwrite), k,
                                       upsample)
    p0, p1, alpha = fit_peak(r, big_l, big_m, fit_radius)
    return p1 * (shape[1] / big_m[1]), p0 * (shape[0] / big_m[0]), alpha


def _window_at(n: int, kind: str, shift: float) -> np.ndarray:
    """1-D window of ``n`` samples evaluated at ``i - shift`` (zero outside its support), float32."""
    if kind == "none" or shift == 0.0:
        return window_1d(n, kind)
    u = (np.arange(n, dtype=np.float64) - shift) / (n - 1)
    if kind == "hann":
        w = 0.5 - 0.5 * np.cos(2.0 * np.pi * u)
    else:  # tukey
        a = _TUKEY_ALPHA
        w = np.ones(n)
        lo, hi = u < a / 2, u > 1 - a / 2
        w[lo] = 0.5 - 0.5 * np.cos(2.0 * np.pi * u[lo] / a)
        w[hi] = 0.5 - 0.5 * np.cos(2.0 * np.pi * (1.0 - u[hi]) / a)
    w[(u < 0.0) | (u > 1.0)] = 0.0
    return w.astype(np.float32)


def _window_separable(x: np.ndarray, wy: np.ndarray, wx: np.ndarray, origin: tuple[int, int] = (0, 0)) -> np.ndarray:
    """:func:`apply_window` for one image and a separable window ``wy wx^T``: ``(x - mean_w) * wy * wx``.

    The image is the crop of ``x`` of ``len(wy) x len(wx)`` pixels starting at ``origin`` (row, column), read
    in place when ``x`` is C-contiguous float32.  No 2-D window is built: the compiled kernel
    (:func:`_poc_kernels`) reads the crop twice, for the weighted mean and for the product, and writes the
    result once; without Numba, the weighted mean is two matrix-vector products (one thread) and the rest one
    new array and two in-place products (the time of this step doubled when other work had just evicted the
    caches; docs/benchmarks.md).
    """
    wy32, wx32 = np.asarray(wy, dtype=np.float32), np.asarray(wx, dtype=np.float32)
    norm = float(wy32.sum(dtype=np.float64)) * float(wx32.sum(dtype=np.float64))
    (y0, x0), h, w = origin, wy32.size, wx32.size
    kernels = _poc_kernels()
    if kernels is not None:
        if not (x.dtype == np.float32 and x.flags.c_contiguous):
            x, y0, x0 = np.ascontiguousarray(x[y0:y0 + h, x0:x0 + w], dtype=np.float32), 0, 0
        return kernels.centred_windowed(x, y0, x0, wy32, wx32, norm, np.empty((h, w), np.float32))
    x = np.asarray(x[y0:y0 + h, x0:x0 + w], dtype=np.float32)
    with single_threaded_blas():
        weighted = float(wy32 @ (x @ wx32))
    out = np.subtract(x, np.float32(weighted / norm))
    out *= wy32[:, None]
    out *= wx32[None, :]
    return out


@built_on_first_use
def _poc_kernels(numba):
    """Compiled passes of the one-image POC path.

    ``centred_windowed(x, y0, x0, wy, wx, norm, out)``: :func:`_window_separable` in two passes over the crop
    of ``x`` (2-D float32, C-contiguous) of ``out``'s shape at ``(y0, x0)``: row sums in float32 in any order
    (``reassoc``: vectorised; they differ from NumPy's by float32 rounding), the rows' sum in float64.
    ``sqrt_of_positive(x, out)``: the ``"sqrt"`` pre-processing ``sqrt(max(x, 0))`` (:func:`preprocess_image`)
    in one pass, False when a value is NaN or infinite.  ``weighted_cross_power``: see the function of that name.
    All are compiled with NumPy's error model: Python's check of every division for zero kept the cross-power
    loop scalar (0.82 ms for a 755 x 360 band; vectorised 0.065 ms, the same values).
    """
    options = {"nogil": True, "cache": True, "boundscheck": False, "error_model": "numpy"}

    @numba.njit(fastmath={"reassoc", "contract"}, **options)
    def centred_windowed(x, y0, x0, wy, wx, norm, out):
        h, w = out.shape
        total = 0.0
        for i in range(h):
            row = x[y0 + i, x0:x0 + w]  # a unit-step slice of a C-contiguous row: still vectorised
            s = np.float32(0.0)
            for j in range(w):
                s += row[j] * wx[j]
            total += float(s) * float(wy[i])
        mean = np.float32(total / norm)
        for i in range(h):
            row, o, a = x[y0 + i, x0:x0 + w], out[i], wy[i]
            for j in range(w):
                o[j] = (row[j] - mean) * (a * wx[j])
        return out

    @numba.njit(**options)
    def sqrt_of_positive(x, out):
        h, w = x.shape
        zero, inf = np.float32(0.0), np.float32(np.inf)
        finite = True
        for i in range(h):
            row, o = x[i], out[i]
            for j in range(w):
                v = row[j]
                finite &= abs(v) < inf  # False for NaN too
                o[j] = np.sqrt(max(v, zero))
        return finite

    @numba.njit(fastmath={"contract"}, **options)
    def weighted_cross_power(b_mov, b_ref, power, out):
        # complex64 read as (re, im) float32 pairs, |x| as sqrt(re^2 + im^2) and the power-0.5 case in its
        # own loop: 0.078 ms for a 755 x 360 band, where the loop over complex numbers took 1.05 ms
        h, w = b_mov.shape
        tiny, two = np.float32(1e-30), np.float32(2.0)
        exponent = power - np.float32(1.0)
        mov, ref, res = b_mov.view(np.float32), b_ref.view(np.float32), out.view(np.float32)
        for i in range(h):
            m, r, o = mov[i], ref[i], res[i]
            if power == np.float32(0.5):
                for j in range(w):
                    xr = m[2 * j] * r[2 * j] + m[2 * j + 1] * r[2 * j + 1]
                    xi = m[2 * j + 1] * r[2 * j] - m[2 * j] * r[2 * j + 1]
                    s = two / np.sqrt(np.sqrt(xr * xr + xi * xi) + tiny)
                    o[2 * j], o[2 * j + 1] = xr * s, xi * s
            else:
                for j in range(w):
                    xr = m[2 * j] * r[2 * j] + m[2 * j + 1] * r[2 * j + 1]
                    xi = m[2 * j + 1] * r[2 * j] - m[2 * j] * r[2 * j + 1]
                    s = two * (np.sqrt(xr * xr + xi * xi) + tiny) ** exponent
                    o[2 * j], o[2 * j + 1] = xr * s, xi * s
            o[0] /= two  # column 0 is not doubled (it has no Hermitian twin)
            o[1] /= two
        res[0, 0] = res[0, 1] = 0.0
        return out

    return SimpleNamespace(centred_windowed=centred_windowed, sqrt_of_positive=sqrt_of_positive,
                           weighted_cross_power=weighted_cross_power)


def _overlap(shape: tuple[int, int], sx: int, sy: int) -> tuple[slice, slice, slice, slice] | None:
    """Slices of the reference and moving images that show the same content for an integer shift."""
    h, w = shape
    ya0, ya1 = max(0, -sy), min(h, h - sy)
    xa0, xa1 = max(0, -sx), min(w, w - sx)
    if ya1 - ya0 < max(MIN_SIZE_PX, h // 2) or xa1 - xa0 < max(MIN_SIZE_PX, w // 2):
        return None
    # Shrink (centred) to a fast DFT length: an overlap of e.g. 1021 px would make the transform 3x slower.
    ny, nx = _fast_len_below(ya1 - ya0), _fast_len_below(xa1 - xa0)
    ya0 += (ya1 - ya0 - ny) // 2
    xa0 += (xa1 - xa0 - nx) // 2
    ya1, xa1 = ya0 + ny, xa0 + nx
    return slice(ya0, ya1), slice(xa0, xa1), slice(ya0 + sy, ya1 + sy), slice(xa0 + sx, xa1 + sx)


@functools.lru_cache(maxsize=256)
def _fast_len_below(n: int) -> int:
    """A fast length ``<= n`` for OpenCV's DFT: the largest 7-smooth one whose power of two is 2^4-2^7 or ``<= 512``.

    On the AMD EPYC host (docs/benchmarks.md), one thread, square float32 transforms of 400-1100 px took
    0.73-0.89 ns per pixel at such lengths (e.g. 960, 1008) against 0.86-1.40 ns with at most 2^3 (1000:
    1.18 ns) and 1.14-1.24 ns at 768 and 1024 (512, which fits the 2 MiB L2 cache, is kept: 0.72 ns).
    Searched down to ``0.9 n`` for ``n > 512`` (smaller transforms take well under a millisecond: there every
    pixel counts, the error grows as they are dropped); otherwise, the largest 5-smooth even length (``n``
    itself for ``n <= 8``).
    """
    for m in range(n, math.ceil(0.9 * n) - 1 if n > 512 else n, -1):
        twos = (m & -m).bit_length() - 1
        if (4 <= twos <= 7 and _smooth(m >> twos, (3, 5, 7))) or (m == 1 << twos and m <= 512):
            return m
    for m in range(n, 8, -1):
        if m % 2 == 0 and _smooth(m, (2, 3, 5)):
            return m
    return n


def _smooth(m: int, primes: tuple[int, ...]) -> bool:
    """``m`` has no prime factor outside ``primes``."""
    for p in primes:
        while m % p == 0:
            m //= p
    return m == 1


def _refine(a: np.ndarray, b: np.ndarray, dx: float, dy: float, window: str, band_limit: float,
            iterations: int) -> tuple[float, float]:
    """Re-estimate on the common overlap with the moving image's window moved by the sub-pixel shift.

    The moving crop is ``b`` moved by ``round(d)``, so both crops show the same content up to the
    fractional residual ``t = d - round(d)``; the moving crop's window is evaluated at ``x - t``, so
    that for the right ``t`` the windowed moving crop is exactly the windowed reference moved by
    ``t``: no window pull, no unshared margins.  The residual is measured and ``t`` updated.
    """
    cache = None
    for _ in range(iterations):
        sx, sy = round(dx), round(dy)
        sl = _overlap(a.shape, sx, sy)
        if sl is None:
            break
        ya, xa, yb, xb = sl
        shape = (ya.stop - ya.start, xa.stop - xa.start)
        k = (band_size(shape[0], band_limit), band_size(shape[1], band_limit))
        if cache is None or cache[0] != (sx, sy):
            windowed = _window_separable(a, window_1d(shape[0], window), window_1d(shape[1], window),
                                         (ya.start, xa.start))
            cache = ((sx, sy), _band_spectrum(windowed, k, overwrite=True))
        moved = _window_separable(b, _window_at(shape[0], window, dy - sy), _window_at(shape[1], window, dx - sx),
                                  (yb.start, xb.start))
        rx, ry = _weighted_peak(cache[1], _band_spectrum(moved, k, overwrite=True), shape, k, dx - sx, dy - sy,
                                SPECTRAL_WEIGHT_POWER)
        dx, dy = sx + rx, sy + ry
    return dx, dy


def weighted_cross_power(b_mov: np.ndarray, b_ref: np.ndarray, power: float) -> np.ndarray:
    """``W R`` of :func:`_weighted_peak` over the bands (:func:`_band_spectrum`: rows 0..K0 and -K0..-1, columns
    0..K1), complex64: ``x = G F*`` scaled by ``(|x| + 1e-30)^(power - 1)``, columns from 1 doubled (the other
    half of the Hermitian spectrum), the mean term zeroed.  One compiled pass (:func:`_poc_kernels`) for
    same-shape C-contiguous complex64 bands, else NumPy."""
    kernels = _poc_kernels()
    if (kernels is not None and b_mov.dtype == b_ref.dtype == np.complex64 and b_mov.shape == b_ref.shape
            and b_mov.flags.c_contiguous and b_ref.flags.c_contiguous):
        return kernels.weighted_cross_power(b_mov, b_ref, np.float32(power), np.empty_like(b_mov))
    x = b_mov * np.conj(b_ref)
    mag = np.abs(x)
    mag += np.float32(1e-30)
    if power == 0.5:
        np.sqrt(mag, out=mag)
        x /= mag
    else:
        x *= mag ** np.float32(power - 1.0)
    x[:, 1:] *= np.float32(2.0)
    x[0, 0] = 0.0
    return x


def _weighted_peak(b_ref: np.ndarray, b_mov: np.ndarray, shape: tuple[int, int], k: tuple[int, int], dx: float,
                   dy: float, power: float, iterations: int = 4) -> tuple[float, float]:
    """Newton maximisation of the weighted correlation over the band, at continuous ``d``.

    ``C(d) = Re sum_k W_k R_k exp(2 pi i k.d / N)`` with ``R = G F* / |G F*|`` and ``W = |G F*|^power``
    (``power`` 0: the band-limited POC function itself, 1: cross-correlation).  All sums are
    bilinear in the separable phase factors, so each Newton step costs three matrix-vector products.
    """
    n0, n1 = shape
    k0, k1 = k
    x = weighted_cross_power(b_mov, b_ref, power)
    wy = (2 * np.pi / n0) * np.r_[0:k0 + 1, -k0:0].astype(np.float64)
    wx = (2 * np.pi / n1) * np.arange(k1 + 1, dtype=np.float64)
    centre, q = None, None
    for _ in range(iterations):
        if centre is None or abs(dx - centre) > _TAYLOR_RADIUS_PX:
            # Row sums q[:, m] = sum_j x_ij exp(i wx_j c) wx_j^m, once per centre c, as one matrix product
            # (BLAS held to one thread: a threaded product stalls for milliseconds on busy cores);
            # exp(i wx dx) is then a Taylor series in dx - c.
            centre = dx
            moments = np.exp(1j * wx * centre)[:, None] * wx[:, None] ** np.arange(_TAYLOR_TERMS + 3)[None, :]
            with single_threaded_blas():
                q = (x @ moments.astype(np.complex64)).astype(np.complex128)
        delta = dx - centre
        coef = np.array([(1j * delta) ** m / math.factorial(m) for m in range(_TAYLOR_TERMS + 1)])
        # x @ (e^{i wx dx} wx^c), and the sums over rows below, element-wise: no BLAS call (see above)
        cols = np.stack([(q[:, c:c + _TAYLOR_TERMS + 1] * coef).sum(axis=1) for c in range(3)], axis=1)
        ey = np.exp(1j * wy * dy)
        s0, sx_, sxx = (ey[:, None] * cols).sum(axis=0)
        eyw = ey * wy
        sy_, sxy = (eyw[:, None] * cols[:, :2]).sum(axis=0)
        syy = (eyw * wy * cols[:, 0]).sum()
        gx, gy = -sx_.imag, -sy_.imag
        hxx, hyy, hxy = -sxx.real, -syy.real, -sxy.real
        det = hxx * hyy - hxy * hxy
        if not (hxx < 0 and det > 0 and s0.real > 0):
            break
        step_x = -(hyy * gx - hxy * gy) / det
        step_y = -(hxx * gy - hxy * gx) / det
        dx += float(np.clip(step_x, -0.5, 0.5))
        dy += float(np.clip(step_y, -0.5, 0.5))
        if abs(step_x) + abs(step_y) < 1e-4:
            break
    return dx, dy


# ---------------------------------------------------------------------------------- public API
def phase_correlate(reference, moving, *, window: str = DEFAULT_WINDOW, band_limit: float = DEFAULT_BAND_LIMIT,
                    upsample: float = DEFAULT_UPSAMPLE, preprocess: str = DEFAULT_PREPROCESS,
                    saturation: float | str | None = None, fit_radius: int = DEFAULT_FIT_RADIUS,
                    refine: int = DEFAULT_REFINE, reference_valid=None, moving_valid=None) -> Registration:
    """Sub-pixel translation of ``moving`` relative to ``reference`` by band-limited POC (Eq. (3) + Takita 2003).

    Parameters
    ----------
    reference, moving
        Same-size ``(H, W)`` or ``(H, W, C)`` arrays of any real dtype (channels are averaged).
        For the rig: camera A's image is the reference, camera B's the moving image.
    window
        ``"hann"`` (default), ``"tukey"`` (alpha 0.5, keeps more of the image) or ``"none"``
        (only for images that really are periodic).
    band_limit
        Fraction of Nyquist kept in each axis (Takita's band limitation).
    upsample
        Oversampling of the band-limited correlation grid on which the peak model is fitted.
    preprocess
        ``"sqrt"`` (default), ``"none"``, ``"log"`` or ``"gradient"`` (see the module docstring).
    saturation
        ``None`` (default), a clipping level or ``"auto"`` (plateau at the maximum): clipped pixels
        are treated as invalid (see ``reference_valid``).
    fit_radius
        The peak model is fitted to ``(2 fit_radius + 1)^2`` samples.
    refine
        Number of refinement passes on the common overlap (0 = Takita's peak fit only; see
        :func:`_refine`).
    reference_valid, moving_valid
        Optional boolean masks, ``(H, W)`` or ``(H, W, C)`` (``True`` = usable in every channel), e.g.
        ``~HDRResult.saturated`` of an HDR merge: invalid pixels (and a 2 px margin) are faded
        smoothly to the image mean before the correlation; for the refinement the union of both
        images' invalid areas (carried over by the first estimate) is faded in both.

    Returns
    -------
    Registration
        ``dx, dy`` with ``moving(x, y) ~= reference(x - dx, y - dy)``, and the peak height of the
        first pass as ``confidence``.  Shifts are found up to half the image size; accuracy is best
        below a tenth of it (the overlap shrinks with the shift).

    Raises
    ------
    ConfigurationError
        For invalid options, ``refine`` outside 0-4, images of different sizes, or a validity mask of
        another shape than the images.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.3, Eq. (3), Fig. 6 (registration of camera B to camera A by POC).
    .. [2] C. D. Kuglin, D. C. Hines, "The phase correlation image alignment method", Proc. IEEE Int. Conf. on
       Cybernetics and Society, 163-165, 1975.
    .. [3] K. Takita, T. Aoki, Y. Sasaki, T. Higuchi, K. Kobayashi, "High-accuracy subpixel image registration
       based on phase-only correlation", IEICE Trans. Fundamentals E86-A(8), 1925-1934, 2003
       (window, band limitation and peak model).
    """
    check_poc_options(window, band_limit, upsample, preprocess, fit_radius)
    if int(refine) != refine or not 0 <= refine <= 4:
        raise ConfigurationError(f"refine must be an integer in 0..4, got {refine}")
    ref, mov = check_image_pair(reference, moving)
    a, sat_a = prepare_for_poc(ref, "reference", preprocess, saturation)
    b, sat_b = prepare_for_poc(mov, "moving", preprocess, saturation)
    bad_a = _union(sat_a, _invalid(reference_valid, a.shape, "reference_valid"))
    bad_b = _union(sat_b, _invalid(moving_valid, b.shape, "moving_valid"))
    fa = a if bad_a is None else fade_saturated(a, bad_a)
    fb = b if bad_b is None else fade_saturated(b, bad_b)
    # Pass 1 (integer-level accuracy is enough for the refinement): on 2x2-binned images when large.
    binned = refine > 0 and min(a.shape) >= COARSE_MIN_SIZE_PX
    pa, pb = (_bin2(fa), _bin2(fb)) if binned else (fa, fb)
    dx, dy, alpha = poc_shift(apply_window(pa, window), apply_window(pb, window), band_limit, upsample, fit_radius,
                               overwrite=True)
    dx, dy = (2.0 * float(dx), 2.0 * float(dy)) if binned else (float(dx), float(dy))
    if refine:
        if bad_a is not None or bad_b is not None:
            # Invalid areas (e.g. a clipped sun) have sharp, aliased edges that bias the peak by tenths of a
            # pixel; fade the union of both images' invalid areas, carried over by the first estimate, so the
            # faded regions move with the content (the images may clip differently).
            union_a = _union(bad_a, None if bad_b is None else _shift_mask(bad_b, -dx, -dy))
            union_b = _union(bad_b, None if bad_a is None else _shift_mask(bad_a, dx, dy))
            fa, fb = fade_saturated(a, union_a), fade_saturated(b, union_b)
        rdx, rdy = _refine(fa, fb, dx, dy, window, band_limit, refine)
        # The refinement corrects sub-pixel bias; it must not move a (possibly wrong) first estimate far.
        if np.isfinite(rdx) and np.isfinite(rdy) and np.hypot(rdx - dx, rdy - dy) <= _MAX_REFINE_CORRECTION_PX:
            dx, dy = rdx, rdy
    sat = max(_fraction(bad_a), _fraction(bad_b))
    return Registration(dx=float(dx), dy=float(dy), confidence=float(alpha), measured_dx=float(dx),
                        measured_dy=float(dy), window=window, band_limit=band_limit, preprocess=preprocess,
                        saturated_fraction=sat, shape=(int(a.shape[0]), int(a.shape[1])))


def _invalid(valid, shape: tuple[int, int], name: str) -> np.ndarray | None:
    """``(H, W)`` mask of invalid pixels from a validity mask ``(H, W)`` / ``(H, W, C)``, or ``None``."""
    if valid is None:
        return None
    v = np.asarray(valid)
    if v.ndim == 3:
        v = v.all(axis=2)
    if v.shape != shape:
        raise ConfigurationError(f"{name}: mask of shape {np.shape(valid)} does not match the image {shape}")
    bad = ~v.astype(bool)
    return bad if bad.any() else None


def _bin2(x: np.ndarray) -> np.ndarray:
    """Mean of 2 x 2 pixel blocks (an odd last row / column is dropped)."""
    h, w = x.shape[0] // 2 * 2, x.shape[1] // 2 * 2
    # OpenCV's area resampling at exactly half size is the 2 x 2 mean (6x faster than four NumPy slices)
    return cv2.resize(np.ascontiguousarray(x[:h, :w], dtype=np.float32), (w // 2, h // 2),
                      interpolation=cv2.INTER_AREA)


def _union(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray:
    if a is None:
        return b
    return a if b is None else (a | b)


def _fraction(mask: np.ndarray | None) -> float:
    return 0.0 if mask is None else float(np.count_nonzero(mask)) / mask.size


def register_with_fallback(reference, moving, calibrated_offset: tuple[float, float],
                           min_confidence: float = DEFAULT_MIN_CONFIDENCE, **kwargs) -> Registration:
    """POC registration, or the rig's calibrated offset ``(dx, dy)`` when the confidence is below ``min_confidence``.

    Texture-less directions (clear sky, fog) give no reliable correlation peak; the offset
    measured once on a textured scene (same convention as the result) is then the best estimate.
    The result says which was used (``used_fallback``) and always carries the measured values.
    Keyword arguments go to :func:`phase_correlate`.
    """
    off = np.asarray(calibrated_offset, dtype=np.float64)
    if off.shape != (2,) or not np.isfinite(off).all():
        raise ConfigurationError(f"calibrated_offset must be two finite numbers (dx, dy), got {calibrated_offset!r}")
    if not np.isfinite(min_confidence):
        raise ConfigurationError(f"min_confidence must be a finite number, got {min_confidence}")
    reg = phase_correlate(reference, moving, **kwargs)
    if reg.confidence >= min_confidence:
        return Registration(**{**asdict(reg), "min_confidence": float(min_confidence)})
    return Registration(**{**asdict(reg), "dx": float(off[0]), "dy": float(off[1]), "used_fallback": True,
                           "min_confidence": float(min_confidence)})
