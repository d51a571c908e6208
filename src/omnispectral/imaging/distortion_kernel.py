"""Compiled lens distortion (Numba): its inversion by Newton iterations and the forward projection, one point
at a time.

:meth:`omnispectral.imaging.geometry.CameraModel.undistort_normalized` runs damped Newton iterations on
whole arrays, taking the converged points out after every step; the fancy indexing that costs dominates
when a map of every pixel of a sensor is inverted (2.2 Mpx at full scale: ~4 s).  The kernel here runs
the same iterations point by point (start inside the monotonic region, full Newton step, halved while it
leaves the region or does not lower the residual, stop below the tolerance or when no step helps), with
the same float64 operations in the same order, so the results are the array version's (tested against
it).  :meth:`~omnispectral.imaging.geometry.CameraModel.project` (rays to pixels, the mosaic's exact maps and
camera B's per-pixel parallax) evaluates about thirty array operations, each a pass over memory with its
own temporary; ``compiled_project`` does them in one pass per point, the same float64 operations in the
same order (the same bits; tested against the array version).  Numba is imported on first use;
``compiled_undistort()`` and ``compiled_project()`` return ``None`` without it and the callers then run the
array versions.  The kernels release the GIL and start no threads.

References
----------
.. [1] OpenCV, ``cv::projectPoints`` and ``cv::undistortPoints``: the distortion model (radial rational,
   tangential, thin prism) inverted here.
.. [2] J. Nocedal and S. J. Wright, *Numerical Optimization*, 2nd ed., Springer 2006, Sec. 11.1 (Newton's
   method for nonlinear equations) and Sec. 3.1 (step-length backtracking).
"""

from __future__ import annotations

import numpy as np

from omnispectral.compiled import built_on_first_use

__all__ = ["compiled_project", "compiled_undistort", "distortion", "distortion_jacobian"]

def distortion(x, y, d):
    """OpenCV's distortion (radial rational, tangential, thin prism; before the tilt) of normalised ``x, y``.

    Scalars or arrays; ``d`` holds the 14 coefficients in OpenCV's order.  Returns ``(xd, yd)`` and the terms
    :func:`distortion_jacobian` reuses: ``r²``, the radial numerator and denominator (``1.0`` when the model
    is not rational) and their ratio ``g``.
    """
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    s1, s2, s3, s4 = d[8], d[9], d[10], d[11]
    x2, y2, xy = x * x, y * y, x * y
    r2 = x2 + y2
    num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    if k4 == 0.0 and k5 == 0.0 and k6 == 0.0:
        den = 1.0
        g = num
    else:
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        g = num / den
    sx = r2 * (s1 + r2 * s2)
    sy = r2 * (s3 + r2 * s4)
    xd = x * g + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x2) + sx
    yd = y * g + p1 * (r2 + 2.0 * y2) + 2.0 * p2 * xy + sy
    return xd, yd, r2, num, den, g


def distortion_jacobian(x, y, d, r2, num, den, g):
    """``(J00, J01, J10, J11)`` = ``∂(xd, yd)/∂(x, y)`` of :func:`distortion`, from the terms it returns."""
    k1, k2, p1, p2, k3, k4, k5, k6 = d[0], d[1], d[2], d[3], d[4], d[5], d[6], d[7]
    s1, s2, s3, s4 = d[8], d[9], d[10], d[11]
    dnum = k1 + r2 * (2.0 * k2 + r2 * 3.0 * k3)
    if k4 == 0.0 and k5 == 0.0 and k6 == 0.0:
        dg = dnum  # d g / d r²
    else:
        dden = k4 + r2 * (2.0 * k5 + r2 * 3.0 * k6)
        dg = (dnum * den - num * dden) / (den * den)
    dsx = s1 + 2.0 * s2 * r2  # d sx / d r²
    dsy = s3 + 2.0 * s4 * r2
    two_x, two_y = 2.0 * x, 2.0 * y
    j00 = g + x * dg * two_x + 2.0 * p1 * y + 6.0 * p2 * x + dsx * two_x
    j01 = x * dg * two_y + 2.0 * p1 * x + 2.0 * p2 * y + dsx * two_y
    j10 = y * dg * two_x + 2.0 * p1 * x + 2.0 * p2 * y + dsy * two_x
    j11 = g + y * dg * two_y + 6.0 * p1 * y + 2.0 * p2 * x + dsy * two_y
    return j00, j01, j10, j11


@built_on_first_use
def compiled_undistort(numba):
    """``undistort(xd, yd, d, r_max2, tol, max_iter, x, y, resid)`` compiled, or ``None`` without Numba.

    ``xd, yd``: flat float64 normalised distorted coordinates; ``d``: the 14 distortion coefficients in
    OpenCV's order; ``r_max2``: the squared radius of the monotonic region; writes the undistorted
    ``x, y`` and the final residual ``resid`` (``inf`` for non-finite input) into the flat output arrays.
    """
    # the inlined helpers are module globals, not closure cells: Numba keys its disk cache on the pickled
    # closure, which differs in every process (the kernel would compile on every run)
    global distort, distort_nb, jacobian_nb

    distort_nb = numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")(distortion)
    jacobian_nb = numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")(distortion_jacobian)

    @numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")
    def distort(x, y, d):  # pragma: no cover - compiled
        xd, yd, r2, num, den, g = distort_nb(x, y, d)
        j00, j01, j10, j11 = jacobian_nb(x, y, d, r2, num, den, g)
        return xd, yd, j00, j01, j10, j11

    @numba.njit(nogil=True, cache=True, error_model="numpy")
    def undistort(xd, yd, d, r_max2, tol, max_iter, x_out, y_out, resid_out):  # pragma: no cover - compiled
        for i in range(xd.shape[0]):
            ta, tb = xd[i], yd[i]
            if not (np.isfinite(ta) and np.isfinite(tb)):
                x_out[i], y_out[i], resid_out[i] = ta, tb, np.inf
                continue
            xa, ya = ta, tb
            r2 = xa * xa + ya * ya
            if r2 >= r_max2:  # start inside the valid region
                shrink = 0.5 * np.sqrt(r_max2 / r2)
                xa *= shrink
                ya *= shrink
            fx, fy, j00, j01, j10, j11 = distort(xa, ya, d)
            err = np.hypot(fx - ta, fy - tb)
            for _ in range(max_iter):
                if err < tol:
                    break
                ex, ey = fx - ta, fy - tb
                det = j00 * j11 - j01 * j10
                dx = (j11 * ex - j01 * ey) / det
                dy = (j00 * ey - j10 * ex) / det
                if not (np.isfinite(dx) and np.isfinite(dy)):
                    break  # no step: stalled
                xn, yn = xa - dx, ya - dy
                fxn, fyn, n00, n01, n10, n11 = distort(xn, yn, d)
                errn = np.hypot(fxn - ta, fyn - tb)
                step = 1.0
                worse = (xn * xn + yn * yn >= r_max2) or not (errn < err)
                while worse and step > 1e-9:
                    step *= 0.5
                    xw, yw = xa - step * dx, ya - step * dy
                    fxw, fyw, w00, w01, w10, w11 = distort(xw, yw, d)
                    ew = np.hypot(fxw - ta, fyw - tb)
                    if xw * xw + yw * yw < r_max2 and ew < err:
                        xn, yn, fxn, fyn, errn = xw, yw, fxw, fyw, ew
                        n00, n01, n10, n11 = w00, w01, w10, w11
                        worse = False
                if worse:
                    break  # no step lowers the residual: stalled
                xa, ya, fx, fy, err = xn, yn, fxn, fyn, errn
                j00, j01, j10, j11 = n00, n01, n10, n11
            x_out[i], y_out[i], resid_out[i] = xa, ya, err

    return undistort


@built_on_first_use
def compiled_project(numba):
    """``project(p, d, tilt, has_tilt, intrinsics, r_max2, window, uv, valid)`` compiled, or ``None`` without Numba.

    ``p``: ``(N, 3)`` float64 camera-frame points or rays; ``d``: the 14 distortion coefficients in OpenCV's
    order; ``tilt``: the ``(3, 3)`` tilted-sensor homography (used when ``has_tilt``); ``intrinsics``:
    ``(fx, fy, cx, cy)``; ``r_max2``: the squared radius of the monotonic region; ``window``: ``(u_lo, u_hi,
    v_lo, v_hi)`` of the image test (NaN bounds: no test).  Writes the pixels (NaN where not valid) into
    ``uv (N, 2)`` and the validity into ``valid (N,)``, as :meth:`~omnispectral.imaging.geometry.CameraModel.project`
    defines them.
    """
    global distort_project_nb

    distort_project_nb = numba.njit(nogil=True, cache=True, error_model="numpy", inline="always")(distortion)

    @numba.njit(nogil=True, cache=True, error_model="numpy")
    def project(p, d, tilt, has_tilt, intrinsics, r_max2, window, uv, valid):  # pragma: no cover - compiled
        fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
        u_lo, u_hi, v_lo, v_hi = window[0], window[1], window[2], window[3]
        test_window = not np.isnan(u_lo)
        for i in range(p.shape[0]):
            z = p[i, 2]
            x = p[i, 0] / z
            y = p[i, 1] / z
            ok = (z > 0.0) and (x * x + y * y < r_max2)
            xd, yd, _, _, _, _ = distort_project_nb(x, y, d)
            if has_tilt:
                w = tilt[2, 0] * xd + tilt[2, 1] * yd + tilt[2, 2]
                xd, yd = (tilt[0, 0] * xd + tilt[0, 1] * yd + tilt[0, 2]) / w, \
                    (tilt[1, 0] * xd + tilt[1, 1] * yd + tilt[1, 2]) / w
                ok = ok and w > 0.0
            u = fx * xd + cx
            v = fy * yd + cy
            if test_window:
                ok = ok and (u >= u_lo) and (u <= u_hi) and (v >= v_lo) and (v <= v_hi)
            valid[i] = ok
            uv[i, 0] = u if ok else np.nan
            uv[i, 1] = v if ok else np.nan

    return project
