"""The bundle's residuals and Jacobian blocks in one compiled pass per observation.

:meth:`fieldcal.field.bundle.BundleModel.residuals_and_blocks` evaluates, for every active
image point, the weighted image-space residual and its derivative blocks (interior,
exterior, target). The NumPy implementation in :mod:`fieldcal.field.bundle` is the
reference: ~40 whole-array operations, each writing an (m,) or (m, 2, 3) temporary. This
module does the same arithmetic, symbol for symbol (the module docstring of
:mod:`fieldcal.field.bundle` holds the derivation), as one Numba loop over the
observations with every intermediate in registers: ``Xc``, ``q``, the Newton iterations of
:func:`fieldcal.model.camera.distort` started at the measured point, ``G = dq/dx'`` and
the three derivative blocks. The contract test (``tests/field/test_bundle.py``) runs both
implementations on the same inputs.

Compilation, caching and the fallback are :mod:`fieldcal.contract.compiled`'s: when Numba is
missing or cannot compile on a platform, or the environment sets ``FIELDCAL_NUMBA=0``,
:func:`kernel` returns ``None`` and the bundle uses the NumPy reference; :func:`status`
says which and why (one line).
"""

from __future__ import annotations

import numpy as np

from fieldcal.contract import compiled
from fieldcal.model.camera import correction_terms

__all__ = ["kernel", "residuals_kernel", "status", "evaluate_reference_inputs"]

_NAME = "bundle residuals and blocks"
_NAME_RESIDUALS = "image residuals of all observations"


def _bundle_blocks(p, int_index, R, Jl, C, X, img, tgt, uv, sigma_px, start_mm,
                  W, H, d, tol_mm, max_iter, jacobian, res, d_int, d_ext, d_tgt):
    """Residuals ``res`` (m, 2) and blocks (m, 2, n_int), (m, 2, 6), (m, 2, 3), in place.

    ``p`` (13,) camera parameters (PARAM_NAMES order), ``int_index`` (n_int,) the
    estimated ones, ``R`` (n_img, 3, 3) the current rotations, ``Jl`` their left
    Jacobians, ``C`` (n_img, 3), ``X`` (n_t, 3), ``img``/``tgt`` (m,) indices, ``uv``
    (m, 2) measured pixels, ``sigma_px`` (m,), ``start_mm`` (m, 2) Newton start,
    sensor ``W, H`` [px] and pitch ``d`` [mm]. Points behind the camera or where the
    Newton iteration does not converge get NaN residuals.
    """
    f, xp, yp = p[0], p[1], p[2]
    n_int = int_index.shape[0]
    cu, cv = (W - 1.0) / 2.0, (H - 1.0) / 2.0
    for k in range(img.shape[0]):
        i, t = img[k], tgt[k]
        dx0, dx1, dx2 = X[t, 0] - C[i, 0], X[t, 1] - C[i, 1], X[t, 2] - C[i, 2]
        xc0 = R[i, 0, 0] * dx0 + R[i, 0, 1] * dx1 + R[i, 0, 2] * dx2
        xc1 = R[i, 1, 0] * dx0 + R[i, 1, 1] * dx1 + R[i, 1, 2] * dx2
        z = R[i, 2, 0] * dx0 + R[i, 2, 1] * dx1 + R[i, 2, 2] * dx2
        ok = z < 0.0
        if ok:
            qx_t, qy_t = -f * xc0 / z, -f * xc1 / z
            # Newton: correct(x') = q, from the measured point (a fraction of a pixel away)
            ok, xb, yb = _newton(p, qx_t, qy_t, start_mm[k, 0] - xp, start_mm[k, 1] - yp, tol_mm, max_iter)
        if not ok:
            _fill_nan(k, jacobian, res, d_int, d_ext, d_tgt)
            continue
        u = (xb + xp) / d + cu
        v = -(yb + yp) / d + cv
        s = sigma_px[k]
        res[k, 0] = (uv[k, 0] - u) / s
        res[k, 1] = (uv[k, 1] - v) / s
        if not jacobian:
            continue
        # G at the solution, then A = dr/dq = -diag(1, -1) G^-1 / (d sigma)
        _, _, g00, g01, g10, g11, r2, xy_ = _terms(xb, yb, p)
        w = -1.0 / (s * d * (g00 * g11 - g01 * g10))
        a00, a01, a10, a11 = w * g11, -w * g01, w * g10, -w * g00
        for j in range(n_int):
            # e = d q / d p at the fixed measured point, negated (dx'/dp = G^-1 (dq/dp - Q))
            e0, e1 = _interior_column(int_index[j], xb, yb, r2, xy_, g00, g01, g10, g11, qx_t / f, qy_t / f)
            d_int[k, 0, j] = a00 * e0 + a01 * e1
            d_int[k, 1, j] = a10 * e0 + a11 * e1
        # through Xc: dq/dXc = -f/Zc [[1, 0, -Xc/Zc], [0, 1, -Yc/Zc]]
        fz = -f / z
        B00, B01, B02 = a00 * fz, a01 * fz, -(a00 * qx_t + a01 * qy_t) / z
        B10, B11, B12 = a10 * fz, a11 * fz, -(a10 * qx_t + a11 * qy_t) / z
        # rotation: row b of B -> cross(Xc, b), times J_l(w)
        w00, w01, w02 = xc1 * B02 - z * B01, z * B00 - xc0 * B02, xc0 * B01 - xc1 * B00
        w10, w11, w12 = xc1 * B12 - z * B11, z * B10 - xc0 * B12, xc0 * B11 - xc1 * B10
        for c in range(3):
            d_ext[k, 0, c] = w00 * Jl[i, 0, c] + w01 * Jl[i, 1, c] + w02 * Jl[i, 2, c]
            d_ext[k, 1, c] = w10 * Jl[i, 0, c] + w11 * Jl[i, 1, c] + w12 * Jl[i, 2, c]
            t0 = B00 * R[i, 0, c] + B01 * R[i, 1, c] + B02 * R[i, 2, c]
            t1 = B10 * R[i, 0, c] + B11 * R[i, 1, c] + B12 * R[i, 2, c]
            d_tgt[k, 0, c] = t0
            d_tgt[k, 1, c] = t1
            d_ext[k, 0, 3 + c] = -t0
            d_ext[k, 1, 3 + c] = -t1


def _image_residuals(p, R, C, X, img, tgt, uv, W, H, d, tol_mm, max_iter, out):
    """Measured minus predicted pixels ``out`` (m, 2) of observations ``img``/``tgt`` through
    the camera ``p`` and poses ``R``, ``C`` (targets ``X``): the arithmetic of
    :func:`fieldcal.field.bundle.image_residuals`'s NumPy code, point by point (``Xc``, ``q``,
    :func:`fieldcal.model.camera.distort`'s Newton iteration started at ``q``, the pixel). NaN
    behind the camera or where Newton does not converge. ``Xc``'s three-term sums are added in
    the order NumPy's ``einsum("kab,kb->ka")`` adds them, ``(a0 b0 + a2 b2) + a1 b1``, so that
    both give the same bits (any order is right to round-off)."""
    f, xp, yp = p[0], p[1], p[2]
    cu, cv = (W - 1.0) / 2.0, (H - 1.0) / 2.0
    for k in range(img.shape[0]):
        i, t = img[k], tgt[k]
        dx0, dx1, dx2 = X[t, 0] - C[i, 0], X[t, 1] - C[i, 1], X[t, 2] - C[i, 2]
        xc0 = (R[i, 0, 0] * dx0 + R[i, 0, 2] * dx2) + R[i, 0, 1] * dx1
        xc1 = (R[i, 1, 0] * dx0 + R[i, 1, 2] * dx2) + R[i, 1, 1] * dx1
        z = (R[i, 2, 0] * dx0 + R[i, 2, 2] * dx2) + R[i, 2, 1] * dx1
        ok = z < 0.0
        if ok:
            qx_t, qy_t = -f * xc0 / z, -f * xc1 / z
            ok = np.isfinite(qx_t + qy_t)
            if ok:
                ok, xb, yb = _newton(p, qx_t, qy_t, qx_t, qy_t, tol_mm, max_iter)
        if not ok:
            out[k, 0] = np.nan
            out[k, 1] = np.nan
            continue
        out[k, 0] = uv[k, 0] - ((xb + xp) / d + cu)
        out[k, 1] = uv[k, 1] - (-(yb + yp) / d + cv)


def _newton(p, qx_t, qy_t, xb, yb, tol_mm, max_iter):
    """``(converged, xb, yb)``: the measured point whose correction is ``q`` (``distort``),
    Newton's method from ``(xb, yb)`` (the ideal point when that is not finite)."""
    if not (np.isfinite(xb) and np.isfinite(yb)):
        xb, yb = qx_t, qy_t
    for _ in range(max_iter):
        dx, dy, g00, g01, g10, g11, r2, xy_ = _terms(xb, yb, p)
        ex, ey = xb + dx - qx_t, yb + dy - qy_t
        det = g00 * g11 - g01 * g10
        sx = (g11 * ex - g01 * ey) / det
        sy = (g00 * ey - g10 * ex) / det
        xb -= sx
        yb -= sy
        if max(abs(sx), abs(sy)) <= tol_mm:
            return True, xb, yb
    return False, xb, yb


def _interior_column(c, xb, yb, r2, xy_, g00, g01, g10, g11, dqx_df, dqy_df):
    """Minus ``dq/dp_c`` at the fixed measured point (``fieldcal.model.camera.ideal_point_columns``),
    except for f (c = 0), whose column is ``dq/df = q/f`` on the collinearity side."""
    if c == 0:
        return dqx_df, dqy_df
    if c == 1:
        return g00, g10
    if c == 2:
        return g01, g11
    if c == 3:
        return -xb, -yb
    if c == 4:
        return -xb * r2, -yb * r2
    if c == 5:
        return -xb * r2 * r2, -yb * r2 * r2
    if c == 6:
        return -xb * r2 * r2 * r2, -yb * r2 * r2 * r2
    if c == 7:
        return -(r2 + 2 * xb * xb), -2 * xy_
    if c == 8:
        return -2 * xy_, -(r2 + 2 * yb * yb)
    if c == 9:
        return 0.0, -xb
    if c == 10:
        return 0.0, -yb
    if c == 11:
        return -xb, 0.0
    return -yb, 0.0


def _fill_nan(k, jacobian, res, d_int, d_ext, d_tgt):
    """Observation ``k`` has no prediction (behind the camera, or Newton did not converge)."""
    res[k, 0] = np.nan
    res[k, 1] = np.nan
    if jacobian:
        for a in range(2):
            d_int[k, a, :] = np.nan
            d_ext[k, a, :] = np.nan
            d_tgt[k, a, :] = np.nan


if compiled.numba is not None:
    # the one correction polynomial (fieldcal.model.camera), compiled for scalars
    _terms = compiled.numba.njit(cache=True, inline="always")(correction_terms)
    _newton = compiled.numba.njit(cache=True)(_newton)
    _interior_column = compiled.numba.njit(cache=True)(_interior_column)
    _fill_nan = compiled.numba.njit(cache=True)(_fill_nan)
    _compiled = compiled.numba.njit(cache=True, nogil=True, error_model="numpy")(_bundle_blocks)
    _compiled_residuals = compiled.numba.njit(cache=True, nogil=True, error_model="numpy")(_image_residuals)
else:  # pragma: no cover
    _compiled = _compiled_residuals = None


def kernel():
    """The compiled kernel, or ``None`` (then the NumPy reference runs; see :func:`status`)."""
    return compiled.kernel(_NAME, _compiled, _smoke)


def residuals_kernel():
    """The compiled :func:`_image_residuals`, or ``None`` (then the NumPy reference runs)."""
    return compiled.kernel(_NAME_RESIDUALS, _compiled_residuals, _smoke_residuals)


def _smoke_residuals(k):
    p = np.zeros(13)
    p[0] = 50.0
    out = np.empty((2, 2))
    k(p, np.tile(np.eye(3), (1, 1, 1)), np.array([[0.0, 0.0, 10.0]]), np.array([[0.1, 0.2, 0.0], [0.0, 0.0, 20.0]]),
      np.zeros(2, np.int64), np.array([0, 1], np.int64), np.array([[50.0, 40.0], [30.0, 45.0]]),
      100.0, 80.0, 0.005, 1e-10, 30, out)
    # the first point: q = (0.5, 1.0) mm -> (149.5, -160.5) px; the second is behind the camera
    if not (np.allclose(out[0], [50.0 - 149.5, 40.0 + 160.5]) and np.isnan(out[1]).all()):
        raise RuntimeError("the compiled image residuals give wrong numbers on a trivial problem")


def status() -> str:
    """One line: whether the compiled kernel is in use, and why not."""
    kernel()
    return compiled.status(_NAME)


def evaluate_reference_inputs():
    """A tiny consistent input set (2 observations) with the kernel's argument types."""
    p = np.zeros(13)
    p[0] = 50.0
    R = np.tile(np.eye(3), (1, 1, 1))
    return (p, np.arange(3, dtype=np.int64), R, R.copy(), np.array([[0.0, 0.0, 10.0]]),
            np.array([[0.1, 0.2, 0.0], [-0.3, 0.1, 0.0]]), np.zeros(2, np.int64),
            np.array([0, 1], np.int64), np.array([[50.0, 40.0], [30.0, 45.0]]), np.full(2, 0.1),
            np.zeros((2, 2)), 100.0, 80.0, 0.005, 1e-10, 30, True,
            np.empty((2, 2)), np.empty((2, 2, 3)), np.empty((2, 2, 6)), np.empty((2, 2, 3)))


def _smoke(k):
    args = evaluate_reference_inputs()
    k(*args)
    if not np.all(np.isfinite(args[-4])):
        raise RuntimeError("the compiled kernel returned non-finite residuals on a trivial problem")
