"""Initial distortion coefficients by linear least squares (METHODS part A, step 2, eq. 7-8).

Method
------
For a measured image point ``(x', y')`` [mm] and a principal point ``(xp, yp)`` the
contract's correction (docs/conventions.md section 2) is

    q = (xb + dx, yb + dy),     xb = x' - xp,  yb = y' - yp,

where ``(dx, dy)`` is *linear* in every coefficient ``c_j`` (k0..k3, p1, p2, a1, a2, b1, b2)
once the principal point is fixed: ``(dx, dy) = sum_j c_j D_j(xb, yb)``, the columns
``D_j`` being the derivatives ``dq/dc_j`` that :func:`fieldcal.model.camera.correct_jacobian`
returns. Given ideal points ``q`` (from the DLT or a resection: the collinearity
projection ``q = -f (Xc, Yc)/Zc`` of the control points, :func:`ideal_points_mm`), every
point gives two equations

    D c = d,     d = q - (xb, yb)        (eq. 8)

solved in the least-squares sense, ``c = (D^T D)^-1 D^T d`` (the paper prints
``(D^T D)^-1 d``, a typo). The normal equations square the condition number of ``D``
(its columns differ by many orders of magnitude: r^2 ... r^7 in mm), so the solution is
computed by ``numpy.linalg.lstsq`` (SVD) on ``D`` with its columns scaled to unit length.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.dlt import DltResult, dlt, dlt_robust
from fieldcal.model.camera import INDEX, PARAM_NAMES, XP, YP, Camera, Sensor, correct, correct_jacobian

__all__ = [
    "DISTORTION_NAMES",
    "FIELD_DISTORTION_NAMES",
    "DistortionFit",
    "distortion_lsq",
    "ideal_points_mm",
    "fold_k0",
    "InitialValues",
    "initial_camera",
]

DISTORTION_NAMES: tuple[str, ...] = tuple(
    n for n in PARAM_NAMES if n not in ("f_mm", "xp_mm", "yp_mm")
)
"""The coefficients the linear fit can estimate: k0, k1, k2, k3, p1, p2, a1, a2, b1, b2."""

FIELD_DISTORTION_NAMES: tuple[str, ...] = ("k1", "k2", "k3", "p1", "p2", "a1", "a2")
"""The field method's coefficients (METHODS eq. 7), the default of :func:`distortion_lsq`."""


class DistortionFit(NamedTuple):
    """The result of :func:`distortion_lsq`.

    Attributes
    ----------
    coefficients : dict
        ``{name: value}`` in the order asked for (units of docs/conventions.md section 2).
    rms_mm : float
        ``sqrt(mean(rx^2 + ry^2))`` of the fit residuals over the points [mm].
    residuals_mm : (n, 2) ndarray
        ``d - D c`` per point [mm]: what the fitted model leaves of ``q - (xb, yb)``.
    sigma : dict
        ``{name: standard error}`` from ``rms`` and ``(D^T D)^-1`` (``nan`` with no redundancy).
    """

    coefficients: dict
    rms_mm: float
    residuals_mm: np.ndarray
    sigma: dict


def ideal_points_mm(X_world_m, R_world_to_camera, center_m, f_mm):
    """Collinearity projection ``q = -f (Xc, Yc) / Zc`` [mm] of world points (..., 3) [m].

    ``Xc = R_world_to_camera (X - C)`` (docs/conventions.md section 2). These are the ideal points,
    relative to the principal point, that :func:`distortion_lsq` fits the correction to.
    Points behind the camera (``Zc >= 0``) give NaN.
    """
    X = np.asarray(X_world_m, dtype=float)
    Xc = (X - np.asarray(center_m, float)) @ np.asarray(R_world_to_camera, float).T
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return -float(f_mm) * Xc[..., :2] / np.where(z < 0, z, np.nan)[..., None]


def distortion_lsq(
    xy_measured_mm,
    q_ideal_mm,
    xp_mm: float,
    yp_mm: float,
    names=FIELD_DISTORTION_NAMES,
    *,
    where: str = "",
) -> DistortionFit:
    """Least-squares distortion coefficients taking measured points to ideal points (eq. 7-8).

    Parameters
    ----------
    xy_measured_mm : (n, 2) array_like
        Measured image points [mm] in the image-plane frame (docs/conventions.md section 1; from pixels
        with :meth:`fieldcal.model.camera.Sensor.pixel_to_mm`). Points of several images may be
        stacked: the model does not depend on the pose.
    q_ideal_mm : (n, 2) array_like
        The ideal points [mm], relative to the principal point (:func:`ideal_points_mm`).
    xp_mm, yp_mm : float
        The principal point [mm], held fixed.
    names : sequence of str
        The coefficients to fit, any subset of :data:`DISTORTION_NAMES`; the others are 0.
    where : str
        Named in error messages.

    Returns
    -------
    DistortionFit

    Notes
    -----
    With ideal points from a DLT, include ``k0`` in ``names`` and fold it into ``f`` with
    :func:`fold_k0`: the DLT's principal distance has taken up part of the radial
    distortion as a scale, which ``k1..k3`` cannot represent; without ``k0`` they come out
    wrong, even in sign. :func:`initial_camera` does this and iterates.

    Raises
    ------
    InputError
        Shapes, NaN or infinite values, unknown or repeated names (``f_mm``, ``xp_mm``,
        ``yp_mm`` are not linear and not allowed).
    GeometryError
        Fewer equations than coefficients, or coefficients the points cannot separate (e.g.
        ``k0``, ``b1`` and ``a2`` together: the column of ``k0`` is the sum of the other two).
    """
    xy = np.asarray(xy_measured_mm, dtype=float)
    q = np.asarray(q_ideal_mm, dtype=float)
    names = tuple(names)
    _check_lsq_inputs(xy, q, xp_mm, yp_mm, names, where)
    n, m = len(xy), len(names)
    params = np.zeros(13)
    params[XP], params[YP] = xp_mm, yp_mm
    # Q (n, 2, 13): the columns of the coefficients do not depend on their values
    _, _, Q = correct_jacobian(xy, params)
    D = Q[:, :, [INDEX[k] for k in names]].reshape(2 * n, m)
    d = (q - (xy - [xp_mm, yp_mm])).reshape(2 * n)
    c, Ds, scale = _scaled_lstsq(D, d, names, where)
    res = (d - D @ c).reshape(n, 2)
    sq = float(np.sum(res**2))
    rms = float(np.sqrt(sq / n))
    dof = 2 * n - m
    if dof > 0:
        inv_scaled = np.linalg.inv(Ds.T @ Ds)
        sig = np.sqrt(sq / dof * np.diag(inv_scaled)) / scale
    else:
        sig = np.full(m, np.nan)
    return DistortionFit(
        coefficients={k: float(v) for k, v in zip(names, c, strict=True)},
        rms_mm=rms,
        residuals_mm=res,
        sigma={k: float(v) for k, v in zip(names, sig, strict=True)},
    )


def _check_lsq_inputs(xy, q, xp_mm, yp_mm, names, where):
    """The refusals of :func:`distortion_lsq` (shapes, finiteness, names, count)."""
    if xy.ndim != 2 or xy.shape[1] != 2 or q.shape != xy.shape:
        raise InputError(
            f"distortion_lsq: measured and ideal points must both have shape (n, 2), "
            f"got {xy.shape} and {q.shape}",
            where or None,
        )
    if not (np.isfinite(xy).all() and np.isfinite(q).all() and np.isfinite([xp_mm, yp_mm]).all()):
        raise InputError(
            "distortion_lsq: NaN or infinite coordinates or principal point", where or None
        )
    bad = [n for n in names if n not in DISTORTION_NAMES]
    if bad:
        raise InputError(
            f"distortion_lsq: cannot fit {bad} linearly; allowed: {list(DISTORTION_NAMES)}",
            where or None,
        )
    if len(set(names)) != len(names) or not names:
        raise InputError(
            f"distortion_lsq: names must be distinct and not empty, got {list(names)}",
            where or None,
        )
    n, m = len(xy), len(names)
    if 2 * n < m:
        raise GeometryError(
            f"{where + ': ' if where else ''}distortion_lsq: {n} points give {2 * n} "
            f"equations for {m} coefficients"
        )


def _scaled_lstsq(D, d, names, where):
    """``(c, D with unit columns, the column norms)``: the least squares of ``D c = d`` by SVD on
    the equilibrated columns; raises GeometryError for columns the points do not separate."""
    m = len(names)
    scale = np.linalg.norm(D, axis=0)
    if np.any(scale == 0):
        zero = [names[j] for j in np.flatnonzero(scale == 0)]
        raise GeometryError(
            f"{where + ': ' if where else ''}distortion_lsq: the points do not "
            f"constrain {zero} (all at the principal point?)"
        )
    Ds = D / scale
    sol, _, rank, sv = np.linalg.lstsq(Ds, d, rcond=None)
    if rank < m or sv[-1] < 1e-10 * sv[0]:
        # name the most dependent coefficient: the largest entry of the null direction
        _, _, Vt = np.linalg.svd(Ds, full_matrices=False)
        dep = [names[j] for j in np.flatnonzero(np.abs(Vt[-1]) > 0.1)]
        raise GeometryError(
            f"{where + ': ' if where else ''}distortion_lsq: coefficients {dep} "
            "cannot be separated from each other by these points"
        )
    return sol / scale, Ds, scale


def fold_k0(f_mm: float, coefficients: dict):
    """Move a fitted scale ``k0`` into the principal distance (exact, the model is linear).

    ``q = (1 + k0) xb + sum_j c_j D_j`` with ``q = -f Xc/Zc`` is the same as
    ``xb + sum_j c_j/(1 + k0) D_j = -(f/(1 + k0)) Xc/Zc``.

    Returns
    -------
    f_mm : float
        ``f / (1 + k0)`` [mm].
    coefficients : dict
        The other coefficients divided by ``1 + k0`` (``k0`` removed).
    """
    k0 = float(coefficients.get("k0", 0.0))
    s = 1.0 + k0
    return f_mm / s, {k: v / s for k, v in coefficients.items() if k != "k0"}


def _alternate(X, uv, sensor, first, fit_names, iterations, tol_px, where):
    """The rounds of :func:`initial_camera`: ``(dlt, fit, rounds, converged)`` of the round with
    the smallest fit RMS (DLT on corrected points, then the linear fit, until it stops improving)."""
    xy = sensor.pixel_to_mm(uv)
    inl = first.inliers
    uv_c, prev_rms_px, converged, it, best = uv, np.inf, False, 0, None
    for it in range(1, max(1, int(iterations)) + 1):
        r = first if it == 1 else dlt(X[inl], uv_c[inl], sensor, where=where)
        q = ideal_points_mm(X[inl], r.R_world_to_camera, r.center_m, r.f_mm)
        fit = distortion_lsq(xy[inl], q, r.xp_mm, r.yp_mm, fit_names, where=where)
        rms_px = fit.rms_mm / sensor.pixel_mm
        if best is None or rms_px < best[0]:
            best = (rms_px, r, fit)
        if prev_rms_px - rms_px < tol_px:
            converged = True
            break
        prev_rms_px = rms_px
        p = np.zeros(13)
        p[XP], p[YP] = r.xp_mm, r.yp_mm
        for k, v in fit.coefficients.items():
            p[INDEX[k]] = v
        uv_c = sensor.mm_to_pixel(correct(xy, p) + p[[XP, YP]])
    return best[1], best[2], it, converged


@dataclass(frozen=True)
class InitialValues:
    """The result of :func:`initial_camera`.

    Attributes
    ----------
    camera : Camera
        ``f_mm, xp_mm, yp_mm`` and the fitted coefficients (the rest 0).
    R_world_to_camera : (3, 3) ndarray
    center_m : (3,) ndarray
        The pose of that DLT [m].
    dlt : DltResult
        The DLT of the best round (the one with the smallest fit RMS; on corrected points
        after round 1).
    fit : DistortionFit
        The distortion fit of that round (with ``k0`` if it was added, before
        :func:`fold_k0`).
    inliers : (n,) bool ndarray
        Points used (all unless ``robust``).
    rms_px : float
        Reprojection RMS of the inliers through ``camera`` and the pose
        (:func:`fieldcal.model.camera.project`) [px].
    iterations : int
        DLT / distortion rounds done.
    converged : bool
        Whether the last round improved the fit RMS by less than ``tol_px``.
    """

    camera: Camera
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    dlt: DltResult
    fit: DistortionFit
    inliers: np.ndarray
    rms_px: float
    iterations: int
    converged: bool


def initial_camera(
    X_world_m,
    uv_px,
    sensor: Sensor,
    names=FIELD_DISTORTION_NAMES,
    *,
    iterations: int = 10,
    tol_px: float = 0.01,
    fit_scale: bool = True,
    robust: bool = False,
    where: str = "",
) -> InitialValues:
    """Initial values of one image: DLT and distortion LSQ, alternated (METHODS A, steps 1-2).

    Round 1 is the paper's procedure: the DLT of the measured points, the ideal points of
    that DLT, the linear fit of the coefficients. Each later round runs the DLT on the
    measured points corrected with the current coefficients (so the DLT no longer absorbs
    the distortion) and refits the coefficients to the measured points. The true camera
    is a fixed point of this iteration; it stops when a round lowers the RMS of the
    distortion fit by less than ``tol_px``.

    With ``fit_scale`` (default) a scale term ``k0`` is fitted along with ``names`` and
    folded into ``f`` (:func:`fold_k0`): the DLT's principal distance takes up part of a
    radial distortion as a scale, which ``k1..k3`` alone cannot represent, and without it
    the polynomial coefficients come out wrong (even in sign) on a wide-angle lens. The
    principal point and the decentering terms are strongly correlated in one image, more
    so for long lenses; they converge slowly and are meant for the adjustment to finish.

    Parameters
    ----------
    X_world_m : (n, 3) array_like
        Non-coplanar control points [m].
    uv_px : (n, 2) array_like
        Measured pixels [px].
    sensor : Sensor
    names : sequence of str
        Coefficients to fit (:func:`distortion_lsq`).
    iterations : int
        At most this many rounds (1: the paper's one-shot procedure).
    tol_px : float
        Convergence threshold on the improvement of the fit RMS [px].
    fit_scale : bool
        Fit and fold ``k0`` (ignored when ``names`` contains ``k0``, which is then kept and
        reported, or both ``a2`` and ``b1``, whose sum it is).
    robust : bool
        Use :func:`fieldcal.field.dlt.dlt_robust` in the first round and keep its inliers.
    where : str
        The image's name for error messages.

    Returns
    -------
    InitialValues
    """
    X = np.asarray(X_world_m, dtype=float)
    uv = np.asarray(uv_px, dtype=float)
    names = tuple(names)
    # k0 is the sum of b1 and a2: with both asked for, the scale is already in the model
    add_k0 = fit_scale and "k0" not in names and not {"a2", "b1"} <= set(names)
    fit_names = names + ("k0",) if add_k0 else names

    first = dlt_robust(X, uv, sensor, where=where) if robust else dlt(X, uv, sensor, where=where)
    inl = first.inliers
    r, fit, it, converged = _alternate(X, uv, sensor, first, fit_names, iterations, tol_px, where)
    if fit_names != names:
        f_mm, coef = fold_k0(r.f_mm, fit.coefficients)
    else:
        f_mm, coef = r.f_mm, dict(fit.coefficients)
    params = np.zeros(13)
    params[INDEX["f_mm"]], params[XP], params[YP] = f_mm, r.xp_mm, r.yp_mm
    for k, v in coef.items():
        params[INDEX[k]] = v
    camera = Camera(sensor, params)
    res = uv[inl] - camera.project(X[inl], r.R_world_to_camera, r.center_m)
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1))))
    return InitialValues(
        camera=camera,
        R_world_to_camera=r.R_world_to_camera,
        center_m=r.center_m,
        dlt=r,
        fit=fit,
        inliers=inl.copy(),
        rms_px=rms,
        iterations=it,
        converged=converged,
    )
