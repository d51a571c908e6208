"""HDR synthesis from an exposure bracket of a linear sensor (paper Sec. 4.1, Eqs. (1)-(2)).

.. math::  I^{HDR}_{ij} = \\frac{\\sum_k w(I^k_{ij})\\, I^k_{ij} / t^k}{\\sum_k w(I^k_{ij})}

Weights:

``"triangle"`` (default, Eq. (2) generalised to the bit depth)
    ``w(I) = I`` for ``I <= M/2`` and ``M - I`` above, with ``M = 2^bits - 1``.
``"noise"`` (Granados et al., CVPR 2010, for a linear sensor)
    ``w = t^2 / Var(I)`` with ``Var`` from the sensor noise model: the inverse variance of each
    exposure's radiance estimate ``I/t``.  The triangle weight gives 1-DN values of short exposures
    as much say as well-exposed long ones in dark regions; this one does not.

Saturated values (``I >= saturation_dn``) and zeros (clipped at the bottom, or a masked code) get
zero weight.  A pixel saturated in every exposure
takes the shortest exposure's value and is flagged; one that is dark (zero in every exposure, or
zero weight everywhere) takes the longest exposure's value and is flagged.  The merge also returns
each pixel's variance (for the Wiener estimator's signal-dependent noise).

Non-linear inputs (8-bit JPEG/PNG) are linearised through a :class:`~.response.CameraResponse`
(Debevec & Malik 1997) before Eq. (1); the weight stays a function of the code.

Ghosts (the paper's future work): with ``deghost=True`` a pixel whose usable exposures disagree
with the merged value beyond their noise (``|I_k/t_k - I| > z sigma``, with a relative tolerance for
model error) is re-merged from one reference exposure and the exposures consistent with it.

Speed: the work is fused per row chunk in float32.  For linear sensors (raw frames) a compiled
kernel (Numba, :func:`_fused_kernel`) walks each block of 2048 values through all exposures, five at a
time, with the sums of Eq. (1) held in cache: one read of the inputs and one write of the outputs, the
same float32 operations in the same order as the NumPy evaluation (:func:`_merge_rows`, kept for
recovered responses, for mixed frame dtypes and when Numba is missing; the tests hold the two
bit-identical).  Row chunks run on :func:`omnispectral.threads.kernel_threads` threads; no
per-exposure float64 image is ever formed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

from omnispectral.choices import HDR_WEIGHT_NAMES
from omnispectral.compiled import built_on_first_use
from omnispectral.errors import ConfigurationError
from omnispectral.imaging.response import CameraResponse
from omnispectral.imaging.weights import triangle_weight
from omnispectral.limits import check_exposure_times
from omnispectral.spectral.noise import CMV2000, SensorNoiseModel
from omnispectral.threads import kernel_threads

__all__ = ["WEIGHTS", "HDRResult", "HDRWeight", "merge_exposures"]

#: The weights of :func:`merge_exposures`.
@dataclass(frozen=True)
class HDRWeight:
    """One weight of Eq. (1): ``of(model, k, codes, variance)`` gives each pixel's weight in exposure ``k``;
    ``inverse_variance``: the weights are inverse variances of ``I/t``, so the merged variance is ``1 / Σw``
    (else it is propagated from the codes' variances)."""

    of: Callable
    inverse_variance: bool


def _triangle(model, k: int, x: np.ndarray, var: np.ndarray) -> np.ndarray:
    return triangle_weight(x, model.bit_depth)


def _inverse_variance(model, k: int, x: np.ndarray, var: np.ndarray) -> np.ndarray:
    return np.float32(model.times[k] ** 2) / var


#: The HDR merge's weights by name: ``"triangle"`` (the paper's Eq. (2)), ``"noise"`` (inverse variance,
#: Granados et al. 2010).
WEIGHTS = dict(zip(HDR_WEIGHT_NAMES, (HDRWeight(_triangle, inverse_variance=False),
                                      HDRWeight(_inverse_variance, inverse_variance=True)), strict=True))


@dataclass(frozen=True)
class HDRResult:
    """Merged radiance (DN per second), its variance, and per-pixel flags, all ``(H, W, C)``."""

    radiance: np.ndarray
    variance: np.ndarray
    saturated: np.ndarray
    dark: np.ndarray
    ghost: np.ndarray | None = field(default=None)

    @property
    def valid(self) -> np.ndarray:
        """True where at least one exposure was usable (neither saturated everywhere nor dark everywhere)."""
        return ~(self.saturated | self.dark)


def _check_inputs(frames: Sequence[np.ndarray], exposure_s: Sequence[float], bit_depth: int):
    if len(frames) == 0:
        raise ConfigurationError("no exposures to merge")
    times = np.asarray(exposure_s, dtype=np.float64)
    if times.shape != (len(frames),):
        raise ConfigurationError(f"{len(frames)} frames but {times.size} exposure times")
    if np.any(~np.isfinite(times)) or np.any(times <= 0):
        k = int(np.flatnonzero(~np.isfinite(times) | (times <= 0))[0])
        raise ConfigurationError(f"exposure {k}: exposure time {times[k]!r} s is not positive")
    check_exposure_times(times, "exposure times")  # 1e-300 s would make every radiance infinite
    if not 1 <= bit_depth <= 16:
        raise ConfigurationError(f"bit depth {bit_depth} is outside 1-16")
    shape = np.shape(frames[0])
    for k, f in enumerate(frames):
        if np.shape(f) != shape:
            raise ConfigurationError(f"exposure {k} has shape {np.shape(f)}, exposure 0 has {shape}")
        if not np.issubdtype(np.asarray(f).dtype, np.integer):
            raise ConfigurationError(f"exposure {k} has dtype {np.asarray(f).dtype}; expected uint8 or uint16 raw")
    return times




@dataclass(frozen=True)
class _Model:
    """Per-code linearisation, variance and weight of one merge, shared by all chunks."""

    times: np.ndarray  # (N,) float64 seconds
    bit_depth: int
    weight: str
    saturation_dn: float
    var_a: float  # variance of a linear code: var_a * code + var_b (DN^2)
    var_b: float
    lin_table: np.ndarray | None  # (L*C,) float32 for a recovered response, else None (identity)
    var_table: np.ndarray | None
    channels: int

    @property
    def top(self) -> float:
        return float((1 << self.bit_depth) - 1)

    def linear_and_variance(self, z: np.ndarray):
        """Linear value and its variance (code units) of raw codes ``z`` (rows, W, C), float32."""
        x = z.astype(np.float32)
        if self.lin_table is None:
            return x, x, x * np.float32(self.var_a) + np.float32(self.var_b)
        idx = z.astype(np.intp) * self.channels + np.arange(self.channels)
        return x, np.take(self.lin_table, idx), np.take(self.var_table, idx)

    def weight_of(self, k: int, x: np.ndarray, var: np.ndarray) -> np.ndarray:
        """The weight of :data:`WEIGHTS` ``[self.weight]`` (Eq. (2) or inverse variance), zero where saturated."""
        w = WEIGHTS[self.weight].of(self, k, x, var)
        w *= (x < np.float32(self.saturation_dn)) & (x > 0)
        return w


def _build_model(times, bit_depth, weight, noise, saturation_dn, response, channels) -> _Model:
    top = (1 << bit_depth) - 1
    sat = float(saturation_dn) if saturation_dn is not None else 0.99 * top
    if noise is None:
        noise = CMV2000 if bit_depth == CMV2000.bit_depth else SensorNoiseModel(bit_depth=bit_depth)
    g = noise.gain_e_per_dn
    var_a, var_b = 1.0 / g, noise.read_noise_e**2 / g**2 + 1.0 / 12.0
    lin_table = var_table = None
    if response is not None and not response.is_identity:
        if response.n_codes != top + 1:
            raise ConfigurationError(f"response has {response.n_codes} codes but the frames are {bit_depth}-bit")
        lin = response.linear
        if lin.shape[1] == 1:
            lin = np.repeat(lin, channels, axis=1)
        if lin.shape[1] != channels:
            raise ConfigurationError(f"response has {lin.shape[1]} channels, frames have {channels}")
        deriv = CameraResponse(lin, response.kind).derivative
        code_var = var_a * np.arange(top + 1)[:, None] + var_b
        lin_table = np.ascontiguousarray(lin, np.float32).ravel()
        var_table = np.ascontiguousarray(deriv**2 * code_var, np.float32).ravel()
    return _Model(times, bit_depth, weight, sat, var_a, var_b, lin_table, var_table, channels)


def _merge_rows(model: _Model, frames: list[np.ndarray], rows: slice):
    """Eq. (1) on one row chunk: radiance, variance, sum of weights, max |z| disagreement."""
    num = den = vnum = None
    for k, frame in enumerate(frames):
        x, lin, var = model.linear_and_variance(frame[rows])
        w = model.weight_of(k, x, var)
        inv_t = np.float32(1.0 / model.times[k])
        if num is None:
            num, den = np.zeros_like(x), np.zeros_like(x)
            vnum = None if WEIGHTS[model.weight].inverse_variance else np.zeros_like(x)
        den += w
        lin *= inv_t  # in place: for a linear sensor ``lin`` is ``x``, which is not used after the weight
        num += w * lin
        if vnum is not None:
            w *= w
            w *= var
            vnum += w * np.float32(inv_t * inv_t)
    with np.errstate(invalid="ignore", divide="ignore"):
        rad = num / den
        var = vnum / (den * den) if vnum is not None else 1.0 / den
    return rad, var, den


#: Exposures the compiled kernel takes in one pass over a block: their weights are summed in registers, in
#: Eq. (1)'s order, so the block's sums are loaded and stored once per five exposures instead of once per
#: exposure (a bracket whose length is not a multiple of it is padded with weightless exposures).
FUSED_GROUP = 5


@built_on_first_use
def _fused_kernel(numba):
    """The compiled Eq. (1) kernel for linear sensors, or ``None`` without Numba (imported on first use,
    :mod:`omnispectral.compiled`: modules that import ``hdr`` without merging do not pay for it)."""
    # the helpers are module globals, not closure cells: Numba keys its disk cache on the pickled closure, which
    # differs in every process, and would compile the kernel that calls them on every run
    global _code_weight, _add_five, _five_exposures

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def _code_weight(x, on, ts, top, sat, var_a, var_b, triangle):
        """One code's weight (Eq. (2) or the inverse variance) times ``on`` (1, or 0 for a padding pass)."""
        zero = np.float32(0.0)
        if not ((x < sat) & (x > zero)):
            return zero
        if triangle:
            return max(min(x, top - x), zero) * on  # triangle_weight, inline
        return (ts * on) / (x * var_a + var_b)

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False, inline="always")
    def _add_five(i, f0, f1, f2, f3, f4, on, t_squared, inv_t, top, sat, var_a, var_b, triangle, num, den):
        """Value ``i`` of five exposures (``on``, ``t_squared``, ``inv_t``: their 5-tuples) added to ``den`` and
        ``num``, one exposure after the other; returns their codes and weights."""
        x = (np.float32(f0[i]), np.float32(f1[i]), np.float32(f2[i]), np.float32(f3[i]), np.float32(f4[i]))
        w = (_code_weight(x[0], on[0], t_squared[0], top, sat, var_a, var_b, triangle),
             _code_weight(x[1], on[1], t_squared[1], top, sat, var_a, var_b, triangle),
             _code_weight(x[2], on[2], t_squared[2], top, sat, var_a, var_b, triangle),
             _code_weight(x[3], on[3], t_squared[3], top, sat, var_a, var_b, triangle),
             _code_weight(x[4], on[4], t_squared[4], top, sat, var_a, var_b, triangle))
        den[i] = ((((den[i] + w[0]) + w[1]) + w[2]) + w[3]) + w[4]
        s = (num[i] + w[0] * (x[0] * inv_t[0])) + w[1] * (x[1] * inv_t[1])
        num[i] = ((s + w[2] * (x[2] * inv_t[2])) + w[3] * (x[3] * inv_t[3])) + w[4] * (x[4] * inv_t[4])
        return x, w

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def _five_exposures(f0, f1, f2, f3, f4, k, on, inv_t, t_squared, top, sat, var_a, var_b, triangle, num, den,
                        vnum):
        """Add exposures ``k … k+4`` (frames ``f0 … f4``) to the sums, each sum in the order of
        :func:`_merge_rows` (one exposure after the other), so the result is the same bit for bit."""
        it = (inv_t[k], inv_t[k + 1], inv_t[k + 2], inv_t[k + 3], inv_t[k + 4])
        o = (on[k], on[k + 1], on[k + 2], on[k + 3], on[k + 4])
        q = (t_squared[k], t_squared[k + 1], t_squared[k + 2], t_squared[k + 3], t_squared[k + 4])
        if not triangle:  # two loops: a test of ``triangle`` inside one keeps LLVM from vectorising it
            for i in range(num.size):
                _add_five(i, f0, f1, f2, f3, f4, o, q, it, top, sat, var_a, var_b, False, num, den)
            return
        for i in range(num.size):
            x, w = _add_five(i, f0, f1, f2, f3, f4, o, q, it, top, sat, var_a, var_b, True, num, den)
            v = vnum[i]
            for j in range(5):  # a constant trip count: unrolled
                v = v + w[j] * w[j] * (x[j] * var_a + var_b) * (it[j] * it[j])
            vnum[i] = v

    @numba.njit(nogil=True, cache=True, error_model="numpy", boundscheck=False)
    def merge_linear(frames, start, stop, inv_t, t_squared, on, top, sat, var_a, var_b, triangle,
                     sat64, shortest, longest, rad, var, den_out, saturated, dark):
        """Eq. (1) over flat values ``start:stop`` of all frames into ``rad[0:stop-start]`` etc.

        float32, the operations of :func:`_merge_rows` (and, when ``saturated`` is not empty, of
        :func:`_fallbacks`) in the same order; blocks of 2048 values keep the sums in cache while
        all exposures pass, :data:`FUSED_GROUP` at a time (``frames`` padded to a multiple of it; ``on``
        is 0 for the padding).
        """
        block = 2048
        num_b = np.empty(block, np.float32)
        den_b = np.empty(block, np.float32)
        vnum_b = np.empty(block, np.float32)
        zero, one = np.float32(0.0), np.float32(1.0)
        fallbacks = saturated.size > 0
        # every loop runs over slices indexed from 0: index arithmetic like f[s0 + i] may wrap
        # around (negative indices), which stops LLVM from vectorising (3-4x slower)
        for s0 in range(start, stop, block):
            n = min(s0 + block, stop) - s0
            num, den, vnum = num_b[:n], den_b[:n], vnum_b[:n]
            num[:] = zero
            den[:] = zero
            vnum[:] = zero
            for k in range(0, len(frames), FUSED_GROUP):
                _five_exposures(frames[k][s0:s0 + n], frames[k + 1][s0:s0 + n], frames[k + 2][s0:s0 + n],
                                frames[k + 3][s0:s0 + n], frames[k + 4][s0:s0 + n], k, on, inv_t, t_squared, top,
                                sat, var_a, var_b, triangle, num, den, vnum)
            o = s0 - start
            rad_o, var_o, den_o = rad[o:o + n], var[o:o + n], den_out[o:o + n]
            if triangle:
                for i in range(n):
                    d = den[i]
                    rad_o[i] = num[i] / d
                    var_o[i] = vnum[i] / (d * d)
                    den_o[i] = d
            else:
                for i in range(n):
                    d = den[i]
                    rad_o[i] = num[i] / d
                    var_o[i] = one / d
                    den_o[i] = d
            if fallbacks:  # saturated everywhere: the shortest exposure; dark: the longest
                fs, fl = frames[shortest][s0:s0 + n], frames[longest][s0:s0 + n]
                sat_o, dark_o = saturated[o:o + n], dark[o:o + n]
                its, itl = inv_t[shortest], inv_t[longest]
                for i in range(n):
                    z_short = np.float32(fs[i])
                    z_long = np.float32(fl[i])
                    is_sat = np.float64(z_short) >= sat64  # _fallbacks compares the codes in float64
                    is_dark = ((z_long <= zero) | ~(den[i] > zero)) & ~is_sat
                    if is_sat:
                        rad_o[i] = z_short * its
                        var_o[i] = (z_short * var_a + var_b) * its * its
                    elif is_dark:
                        rad_o[i] = z_long * itl
                        var_o[i] = (z_long * var_a + var_b) * itl * itl
                    sat_o[i] = is_sat
                    dark_o[i] = is_dark

    return merge_linear


def _fused_frames(model: _Model, frames: list[np.ndarray]):
    """The frames as a tuple of flat arrays when the compiled kernel applies, else ``None``.

    It applies to linear sensors (no response table) whose frames share one dtype.  (A tuple, not
    a Numba typed list: the kernel is compiled once per bracket length and cached on disk, whereas
    a typed list costs ~1.4 s of compilation in every new process.)  Every array of the tuple is a read-only
    view: Numba types writable and read-only arrays apart, and a bracket can mix frames mapped from the page
    cache (read-only) with frames read past it (:mod:`omnispectral.filebytes`), which a tuple of two array
    types would not index.  The last frame is repeated up to a multiple of :data:`FUSED_GROUP`; the kernel gives
    the repeats no weight (``on`` = 0, :func:`_merge_rows_fused`).
    """
    if model.lin_table is not None or len({f.dtype for f in frames}) != 1 or _fused_kernel() is None:
        return None
    flat = [_read_only_flat(f) for f in frames]
    return tuple(flat + flat[-1:] * (-len(flat) % FUSED_GROUP))


def _padding_factors(values: np.ndarray, n_padded: int) -> np.ndarray:
    """float32 ``values`` (one per exposure) with the last one repeated up to ``n_padded``."""
    return np.concatenate([values, np.repeat(values[-1:], n_padded - values.size)]).astype(np.float32)


def _read_only_flat(frame: np.ndarray) -> np.ndarray:
    flat = frame.reshape(-1).view()  # a view of its own, so that the caller's array keeps its flags
    flat.flags.writeable = False
    return flat


def _merge_rows_fused(model: _Model, flat_frames, shape: tuple[int, int, int], rows: slice,
                      out: HDRResult | None = None, extremes: tuple[int, int] = (0, 0)):
    """:func:`_merge_rows` by the compiled kernel on the values of ``rows`` (same results, bit for bit).

    With ``out`` the kernel also applies :func:`_fallbacks` (``extremes`` = shortest and longest
    exposure) and writes straight into ``out``; it then returns only the sum of weights.
    """
    h, w, c = shape
    r0, r1 = rows.indices(h)[:2]
    lo, hi = r0 * w * c, r1 * w * c
    den = np.empty(hi - lo, np.float32)
    if out is not None:
        rad, var = out.radiance.reshape(-1)[lo:hi], out.variance.reshape(-1)[lo:hi]
        saturated, dark = out.saturated.reshape(-1)[lo:hi], out.dark.reshape(-1)[lo:hi]
    else:
        rad, var = np.empty(hi - lo, np.float32), np.empty(hi - lo, np.float32)
        saturated = dark = np.empty(0, bool)
    n = len(flat_frames)
    on = np.zeros(n, np.float32)
    on[:model.times.size] = 1.0
    inv_t = _padding_factors((1.0 / model.times).astype(np.float32), n)
    t_squared = _padding_factors((model.times**2).astype(np.float32), n)
    _fused_kernel()(flat_frames, lo, hi, inv_t, t_squared, on, np.float32(model.top),
                     np.float32(model.saturation_dn), np.float32(model.var_a), np.float32(model.var_b),
                     not WEIGHTS[model.weight].inverse_variance, float(model.saturation_dn), extremes[0], extremes[1],
                     rad, var, den, saturated, dark)
    shape = (r1 - r0, w, c)
    return rad.reshape(shape), var.reshape(shape), den.reshape(shape)

def _disagreement(model: _Model, frames, rows, rad, var, rel_tol):
    """Largest |I_k/t_k - I| / sigma over the usable exposures of each pixel (ghost statistic)."""
    zmax = np.zeros_like(rad)
    for k, frame in enumerate(frames):
        x, lin, lvar = model.linear_and_variance(frame[rows])
        usable = model.weight_of(k, x, lvar) > 0
        inv_t = np.float32(1.0 / model.times[k])
        sigma2 = lvar * inv_t * inv_t + var + (np.float32(rel_tol) * rad) ** 2
        z = np.abs(lin * inv_t - rad) / np.sqrt(sigma2)
        np.maximum(zmax, np.where(usable, z, 0.0), out=zmax)
    return zmax


def _fallbacks(model, frames, rows, rad, var, den, out, shortest, longest):
    """Saturated-everywhere and dark-everywhere pixels: flags and the shortest/longest exposure's value."""
    z_short = frames[shortest][rows]
    z_long = frames[longest][rows]
    saturated = z_short >= model.saturation_dn
    dark = ((z_long <= 0) | ~(den > 0)) & ~saturated
    for flag, k, z in ((saturated, shortest, z_short), (dark, longest, z_long)):
        if flag.any():
            _, lin, lvar = model.linear_and_variance(z)
            inv_t = np.float32(1.0 / model.times[k])
            np.copyto(rad, lin * inv_t, where=flag)
            np.copyto(var, lvar * inv_t * inv_t, where=flag)
    out.radiance[rows] = rad
    out.variance[rows] = var
    out.saturated[rows] = saturated
    out.dark[rows] = dark


def _remerge_from_reference(model, frames, pix, reference, z_thresh, rel_tol):
    """Radiance at ghost pixels ``pix`` from one reference exposure and the exposures consistent with it.

    The reference of a pixel is the given exposure or, where it is saturated or dark in every
    channel, the nearest (in exposure time) exposure usable in some channel.  An exposure is
    consistent when it agrees with the reference (within ``z_thresh`` sigma plus ``rel_tol``) in every
    channel where both are usable, and is not clipped where the reference predicts a value well below
    clipping: motion changes all channels, so one disagreeing channel excludes
    the exposure in all of them.  Channels the reference cannot see (dark or saturated there) are
    then merged from the consistent exposures only, so every value comes from one moment in time.
    """
    order = np.argsort(model.times)
    rank_ref = int(np.flatnonzero(order == reference)[0])
    by_distance = [int(order[r]) for r in sorted(range(len(order)), key=lambda r: (abs(r - rank_ref), r))]
    vals = []
    sat_code = np.full((1, 1, frames[0].shape[-1]), np.ceil(model.saturation_dn), frames[0].dtype)
    sat_lin = 0.7 * model.linear_and_variance(sat_code)[1][0]  # linear value where clipping begins, margin
    for k, frame in enumerate(frames):
        z = frame.reshape(-1, frame.shape[-1])[pix][None]  # (1, n, C)
        x, lin, lvar = (a[0] for a in model.linear_and_variance(z))
        inv_t = np.float32(1.0 / model.times[k])
        saturated = x >= np.float32(model.saturation_dn)
        vals.append((model.weight_of(k, x, lvar), lin * inv_t, lvar * inv_t * inv_t, saturated))
    n, c = vals[0][0].shape
    ref_k = np.full(n, -1)
    for k in by_distance:
        ref_k[(ref_k < 0) & (vals[k][0] > 0).any(axis=-1)] = k
    stack = np.stack([np.stack(v[:3]) for v in vals])  # (N, 3, n, C): weight, radiance, variance
    chosen = stack[np.maximum(ref_k, 0), :, np.arange(n)]  # (n, 3, C)
    ref_ok = (chosen[:, 0] > 0) & (ref_k >= 0)[:, None]
    ref, ref_var = np.where(ref_ok, chosen[:, 1], np.nan), chosen[:, 2]
    num = np.zeros((n, c), np.float32)
    den = np.zeros_like(num)
    for k, (w, e, v, saturated) in enumerate(vals):
        tol2 = z_thresh**2 * (v + ref_var + (rel_tol * ref) ** 2)
        with np.errstate(invalid="ignore"):
            inconsistent = (w > 0) & ref_ok & ((e - ref) ** 2 > tol2)
            # clipped although the reference says the value is well below clipping: another moment
            inconsistent |= saturated & ref_ok & (ref * np.float32(model.times[k]) < sat_lin)
        inconsistent = inconsistent.any(axis=-1, keepdims=True)
        w = np.where(inconsistent, 0.0, w)
        num += w * e
        den += w
    with np.errstate(invalid="ignore", divide="ignore"):
        rad = np.where(den > 0, num / den, np.nan_to_num(ref))
    return rad


def merge_exposures(frames: Sequence[np.ndarray], exposure_s: Sequence[float], bit_depth: int = 12,
                    weight: str = "triangle", noise: SensorNoiseModel | None = None,
                    saturation_dn: float | None = None, response: CameraResponse | None = None,
                    deghost: bool = False, reference: int | None = None, ghost_z: float = 5.0,
                    ghost_rel_tol: float = 0.05, chunk_rows: int = 32, workers: int | None = None) -> HDRResult:
    """Merge an exposure bracket into linear radiance per second (Eqs. (1)-(2)).

    Parameters
    ----------
    frames
        N raw frames, each ``(H, W)`` or ``(H, W, C)``, unsigned integers with ``bit_depth`` bits.
    exposure_s
        Exposure time of each frame in seconds (> 0).
    bit_depth : int
        Bits per code, 1-16 (default 12, the paper's cameras); sets the triangle weight's full scale
        ``M = 2^bits - 1`` and the default saturation.
    weight
        ``"triangle"`` (paper) or ``"noise"`` (inverse variance, Granados et al. 2010).
    noise
        Sensor model for the variance estimate and the noise weight (default CMV2000 with
        ``bit_depth`` bits).  For a recovered response it describes the code noise before linearisation.
    saturation_dn
        Values at or above this are saturated (default: the largest code minus 1 %).
    response
        Camera response of non-linear frames (:func:`~.response.recover_response`); ``None`` = linear.
    deghost
        Re-merge pixels whose exposures disagree beyond ``ghost_z`` standard deviations (plus a
        relative tolerance ``ghost_rel_tol``) from the ``reference`` exposure (default: the middle
        one by exposure time) and the exposures consistent with it; such pixels are flagged in
        ``ghost`` (dilated by one pixel).
    reference : int, optional
        Index (in ``frames``) of the reference exposure of ``deghost``; default the middle one by exposure time.
    ghost_z : float
        Disagreement, in standard deviations of ``I_k/t_k - I``, above which a pixel is a ghost (default 5).
    ghost_rel_tol : float
        Relative model error, a fraction of the merged radiance, added in quadrature to that standard deviation
        (default 5 %).
    chunk_rows, workers
        Rows per work unit and threads (default :func:`omnispectral.threads.kernel_threads`: the
        usable cores, one inside another thread pool such as a Dask worker).

    Returns
    -------
    HDRResult
        ``radiance`` float32 ``(H, W, C)`` in DN/s (or response units per second), ``variance`` of
        it, ``saturated`` / ``dark`` flags and, with ``deghost``, the ``ghost`` mask ``(H, W)``.

    Raises
    ------
    ConfigurationError
        For an unknown weight, no frames, a count of exposure times other than the frames', a time that is
        not positive, a bit depth outside 1-16, frames of different shapes or not integer, or a
        ``reference`` outside the bracket.

    References
    ----------
    .. [1] Hirai et al., "High-Dynamic-Range Spectral Imaging System for Omnidirectional Scene Capture",
       J. Imaging 4(4):53, 2018, Sec. 4.1, Eqs. (1)-(2) (the HDR merge and its triangle weight; ghost removal
       left as future work, Sec. 7).
    .. [2] P. E. Debevec, J. Malik, "Recovering High Dynamic Range Radiance Maps from Photographs", SIGGRAPH 1997
       (the method the paper adopts; the response of non-linear frames).
    .. [3] M. Granados et al., "Optimal HDR reconstruction with linear digital cameras", CVPR 2010 (the
       inverse-variance weight ``"noise"``).
    """
    if weight not in WEIGHTS:
        raise ConfigurationError(f"unknown weight {weight!r}; expected one of {', '.join(WEIGHTS)}")
    times = _check_inputs(frames, exposure_s, bit_depth)
    frames = [np.ascontiguousarray(f if np.ndim(f) == 3 else np.asarray(f)[..., None]) for f in frames]
    h, w, c = frames[0].shape
    model = _build_model(times, bit_depth, weight, noise, saturation_dn, response, c)
    order = np.argsort(times)
    shortest, longest = int(order[0]), int(order[-1])
    out = HDRResult(np.empty((h, w, c), np.float32), np.empty((h, w, c), np.float32),
                    np.zeros((h, w, c), bool), np.zeros((h, w, c), bool),
                    np.zeros((h, w), bool) if deghost else None)
    zmax = np.zeros((h, w), np.float32) if deghost else None

    flat_frames = _fused_frames(model, frames)

    def work(r0: int) -> None:
        rows = slice(r0, min(r0 + chunk_rows, h))
        if flat_frames is not None and zmax is None:  # merge and fallbacks in one pass, straight into out
            _merge_rows_fused(model, flat_frames, (h, w, c), rows, out, (shortest, longest))
            return
        if flat_frames is not None:
            rad, var, den = _merge_rows_fused(model, flat_frames, (h, w, c), rows)
        else:
            rad, var, den = _merge_rows(model, frames, rows)
        if zmax is not None:
            ok = den > 0
            z = _disagreement(model, frames, rows, np.where(ok, rad, 0), np.where(ok, var, 0), ghost_rel_tol)
            zmax[rows] = z.max(axis=-1)
        _fallbacks(model, frames, rows, rad, var, den, out, shortest, longest)

    n_workers = kernel_threads() if workers is None else max(1, int(workers))
    starts = range(0, h, chunk_rows)
    if n_workers > 1 and h > chunk_rows:
        with ThreadPoolExecutor(n_workers) as pool:
            list(pool.map(work, starts))
    else:
        for r0 in starts:
            work(r0)
    if deghost:
        ref = int(order[len(order) // 2]) if reference is None else int(reference)
        if not 0 <= ref < len(frames):
            raise ConfigurationError(f"reference exposure {ref} is outside 0-{len(frames) - 1}")
        ghost = ndimage.binary_dilation(zmax > ghost_z, iterations=1)
        pix = np.flatnonzero(ghost)
        if pix.size:
            rad = _remerge_from_reference(model, frames, pix, ref, ghost_z, ghost_rel_tol)
            out.radiance.reshape(-1, c)[pix] = rad
        out.ghost[...] = ghost
    return out
