"""Initial values of the field adjustment (METHODS part A, steps 1-2).

1. Per image, the DLT (eq. 1-6, Hartley normalised, robust to blunders:
   :func:`fieldcal.field.dlt.dlt_robust`) on the surveyed targets it sees; the interior
   starting point is the median of the per-image ``f, xp, yp`` (within 0.5-2x of the
   nominal focal length, when the session gives one). Planar fields, or too few DLTs,
   start from the nominal focal length (or Zhang's closed form) instead.
2. Every image is oriented with that common interior orientation:
   images with a DLT pose all at once by :func:`refine_poses` (a Levenberg-Marquardt per
   image, vectorised over the images: the bundle with the interior and the targets held
   fixed), the others (and those whose refined pose keeps fewer than
   :data:`MIN_SUPPORT_FRACTION` of their points) one by one by
   :func:`fieldcal.field.resection.resect` (RANSAC, planar pose for coplanar points).
   Points further than ``threshold_px`` from their oriented image (the DLT's outliers, or,
   since the distortion is not known yet, points in strongly distorted corners) are flagged
   as initial outliers: the adjustment readmits those that fit once the distortion is
   estimated.
3. The distortion coefficients start from the linear least squares of eq. 7-8
   (:func:`fieldcal.field.distortion_init.distortion_lsq`) over the points not flagged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from fieldcal.errors import GeometryError
from fieldcal.field.bundle import BundleModel, image_residuals
from fieldcal.field.distortion_init import distortion_lsq
from fieldcal.field.dlt import dlt_robust, dlt_robust_many, zhang_focal
from fieldcal.field.geometry import is_coplanar
from fieldcal.field.intersection import intersect_targets
from fieldcal.field.relative_orientation import orient_pair
from fieldcal.field.resection import planar_pose, resect
from fieldcal.model.camera import INDEX, Camera
from fieldcal.session.data import FieldData

__all__ = ["InitialValues", "initial_values", "refine_poses", "per_image", "CORE_PARAMS"]

CORE_PARAMS = ("f_mm", "xp_mm", "yp_mm")
"""The interior parameters every start has (the rest start from the distortion fit)."""

MIN_SUPPORT_FRACTION = 0.5
"""A pose refined in the batch (step 2) is kept when at least this fraction of its image's
points lies within the threshold of it; otherwise the image is resected. A pose that
disagrees with most of its points is not that image's pose (blunders are a minority: the
robust DLT allows 30 %), and its RMS, taken over the few points it still keeps, says nothing:
a DLT pulled by 8 swapped ids of 125 refined to a pose that kept 1 point, at 0 px."""


@dataclass
class InitialValues:
    """Starting point of the adjustment, with how it was obtained."""

    params: np.ndarray
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    outliers: np.ndarray          # (m,) observations flagged by the robust initialisers
    dlt_f_mm: np.ndarray          # per image (NaN where no DLT)
    how: str
    lm_tau: float | None = None   # a warm start: the LM damping the adjustment it comes from ended with
    targets_m: np.ndarray | None = None   # (n_targets, 3) start (unsurveyed: intersected; NaN: not placed)
    free_frame: bool = False      # started by relative orientation and not moved onto the survey


def per_image(data: FieldData) -> list[np.ndarray]:
    """The observation indices of each image (a list of ``n_images`` int arrays)."""
    order = np.argsort(data.obs.image, kind="stable")
    bounds = np.searchsorted(data.obs.image[order], np.arange(len(data.images) + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(len(data.images))]


def _dlts(data: FieldData, groups):
    """Step 1: the robust DLT of every image that has non-coplanar targets (else NaN/None).

    The fast paths of all images are taken in one batch (:func:`dlt_robust_many`); the images
    it leaves (blunders, borderline geometry) get :func:`dlt_robust` one by one, as before.
    """
    n_img = len(data.images)
    dlt_f, dlt_pp = np.full(n_img, np.nan), np.full((n_img, 2), np.nan)
    poses: list = [None] * n_img
    outliers = np.zeros(len(data.obs), bool)
    X_all = data.targets.xyz_m
    if is_coplanar(X_all[np.unique(data.obs.target)]):
        return dlt_f, dlt_pp, poses, outliers
    views = [(X_all[data.obs.target[k]], data.obs.uv_px[k]) for k in groups]
    fast = dlt_robust_many(views, data.sensor, fallback=False)   # the fast paths, batched
    for i, k in enumerate(groups):
        res = fast[i]
        if res is None:                 # no fast path: this image's own robust DLT
            X, uv = views[i]
            if is_coplanar(X):
                continue
            try:
                res = dlt_robust(X, uv, data.sensor, where=data.images[i].file, seed=i)
            except GeometryError:
                continue
        dlt_f[i], dlt_pp[i] = res.f_mm, (res.xp_mm, res.yp_mm)
        poses[i] = (res.R_world_to_camera, res.center_m)
        outliers[k[~res.inliers]] = True
    return dlt_f, dlt_pp, poses, outliers


def _common_interior(data: FieldData, groups, dlt_f, dlt_pp):
    """Step 1: ``(params (13,), how)``: median DLT interior, nominal f, or Zhang's f."""
    n_img = len(data.images)
    nominal = data.nominal_focal_mm
    ok = np.isfinite(dlt_f)
    if nominal is not None and ok.any():
        ok &= (dlt_f > 0.5 * nominal) & (dlt_f < 2.0 * nominal)
    params = np.zeros(13)
    if ok.sum() >= max(1, n_img // 4):
        params[INDEX["f_mm"]] = np.median(dlt_f[ok])
        params[[INDEX["xp_mm"], INDEX["yp_mm"]]] = np.median(dlt_pp[ok], axis=0)
        return params, f"DLT on {ok.sum()} of {n_img} images (median f, xp, yp)"
    if nominal is not None:
        params[INDEX["f_mm"]] = nominal
        return params, "nominal focal length, principal point at the sensor centre"
    X_all = data.targets.xyz_m
    views = [(X_all[data.obs.target[k]], data.obs.uv_px[k]) for k in groups]
    params[INDEX["f_mm"]] = zhang_focal(views, data.sensor, where="session")
    return params, "Zhang's closed form from the planar views"


def _segment_sums(a, starts, counts):
    """Sums of ``a`` (m, ...) over consecutive segments (empty segments give 0)."""
    out = np.add.reduceat(a, starts, axis=0) if len(a) else np.zeros((len(starts),) + a.shape[1:])
    out[counts == 0] = 0.0
    return out


def refine_poses(data: FieldData, params, R, C, active, *, max_iter: int = 30, tol: float = 1e-10,
                 mu0: float = 1e-6):
    """Poses of all images with the camera ``params`` and the targets held fixed.

    A Levenberg-Marquardt iteration per image (its own damping and step acceptance),
    vectorised over the images: each image's 6 unknowns (rotation increment, centre) are
    solved from its 6x6 normal equations, built from the bundle's Jacobian blocks
    (:class:`fieldcal.field.bundle.BundleModel` with no interior unknowns).

    Parameters
    ----------
    data : FieldData
    params : (13,) ndarray
        The camera, held fixed.
    R : (n_images, 3, 3) ndarray
        Starting rotations (world to camera).
    C : (n_images, 3) ndarray
        Starting centres [m].
    active : (m,) bool ndarray
        Observations to orient on.
    max_iter : int
        At most this many iterations.
    tol : float
        An image has converged when its next step is predicted to lower its cost (the sum
        of squared weighted residuals) by at most ``tol`` times it: in units of the image
        noise the step is then below ``sqrt(2 tol cost)`` (1e-10: about 3e-4 sigma for
        200 points).
    mu0 : float
        Each image's initial damping, relative to the diagonal of its normal matrix. Small:
        the starts (DLT poses) are close, and with a long lens rotation and position are
        strongly correlated (weak directions ~1e-4 of the diagonal), along which a damping of
        1e-3 halves the step for several iterations (19 evaluations instead of 11 on the paper
        field; the same poses).

    Returns
    -------
    R, C : ndarray
        The refined poses (images without active points keep theirs).
    rms_px : (n_images,) ndarray
        Reprojection RMS of each image's active points [px] (NaN where none).
    """
    model = BundleModel(data, params, (), R, targets_adjusted=False, obs_active=active)
    n = model.n_images
    bounds = np.searchsorted(model.img, np.arange(n + 1))
    starts, counts = np.minimum(bounds[:-1], max(len(model.img) - 1, 0)), np.diff(bounds)
    x = model.pack(params, C)
    r, jb, _ = model.residuals_and_blocks(x)
    cost = _segment_sums(r.reshape(-1, 2) ** 2, starts, counts).sum(axis=1)
    mu = np.full(n, float(mu0))
    done = counts == 0
    eye = np.eye(6)
    for _ in range(max_iter):
        if done.all():
            break
        A2 = jb.d_ext.reshape(-1, 6)                 # rows of the images' points, image by image
        N, g = np.zeros((n, 6, 6)), np.zeros((n, 6))
        for i in np.flatnonzero(~done):             # one (2 k_i, 6) product per image (BLAS)
            rows = slice(2 * bounds[i], 2 * bounds[i + 1])
            N[i] = A2[rows].T @ A2[rows]
            g[i] = A2[rows].T @ r[rows]
        dg = np.einsum("kii->ki", N)
        Nd = N + (mu[:, None] * np.maximum(dg, 1e-300))[:, :, None] * eye + done[:, None, None] * eye
        h = -np.linalg.solve(Nd, g[:, :, None])[:, :, 0]
        done |= -0.5 * np.einsum("ki,ki->k", h, g) <= tol * cost     # predicted decrease negligible
        h[done] = 0.0
        x_new = x + h.ravel()
        live = ~done[model.img]                     # points of the images still iterating
        if live.sum() >= 0.8 * len(live):
            r_new, jb_new, _ = model.residuals_and_blocks(x_new)
            d_new = jb_new.d_ext
        else:   # only those images (each point is computed on its own: the same numbers)
            r_live, jb_live, _ = model.restricted(live).residuals_and_blocks(x_new)
            r_new, d_new = r.copy(), np.empty_like(jb.d_ext)
            r_new.reshape(-1, 2)[live] = r_live.reshape(-1, 2)
            d_new[live] = jb_live.d_ext
        cost_new = _segment_sums(r_new.reshape(-1, 2) ** 2, starts, counts).sum(axis=1)
        better = np.isfinite(cost_new) & (cost_new < cost) & ~done
        done |= ~better & (mu > 1e10)
        mu = np.where(better, mu / 3.0, mu * 4.0)
        take = better[model.img]
        x = np.where(np.repeat(better, 6), x_new, x)
        r = np.where(np.repeat(take, 2), r_new, r)
        np.copyto(jb.d_ext, d_new, where=take[:, None, None])
        cost = np.where(better, cost_new, cost)
    _, R_new, C_new, _ = model.unpack(x)
    sigma = _segment_sums(model.sigma_px ** 2, starts, counts) / np.maximum(counts, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.where(counts > 0, np.sqrt(cost * sigma / np.maximum(counts, 1)), np.nan)
    return R_new, C_new, rms


def _image_residuals_px(data: FieldData, params, R, C):
    """|measured - projected| [px] of every observation (NaN behind the camera)."""
    return np.hypot(*image_residuals(data, params, R, C).T)


def _orient(data: FieldData, groups, params, poses, outliers, threshold_px):
    """Step 2: every image oriented with the common camera; updates ``outliers`` in place."""
    n_img = len(data.images)
    R, C = np.zeros((n_img, 3, 3)), np.zeros((n_img, 3))
    batch = np.array([p is not None for p in poses])
    for i in np.flatnonzero(batch):
        R[i], C[i] = poses[i]
    if batch.any():
        on = batch[data.obs.image]
        use = on & ~outliers
        for _ in range(2):            # orient, flag what lies beyond the threshold, orient again
            R, C, rms = refine_poses(data, params, R, C, use)
            far = ~(_image_residuals_px(data, params, R, C) <= threshold_px) & on
            if not (far & use).any():
                break
            use &= ~far
        near = np.bincount(data.obs.image[on & ~far], minlength=n_img)
        supported = near >= MIN_SUPPORT_FRACTION * np.array([len(k) for k in groups])
        batch &= np.isfinite(rms) & (rms <= threshold_px) & supported    # the rest: resection, one by one
        outliers |= far & batch[data.obs.image]
    camera = Camera(data.sensor, params)
    X_all = data.targets.xyz_m
    for i in np.flatnonzero(~batch):
        k = groups[i]
        X, uv = X_all[data.obs.target[k]], data.obs.uv_px[k]
        where = data.images[i].file
        init = poses[i]
        if init is None and is_coplanar(X):
            R_i, C_i, _ = planar_pose(X, uv, camera, where=where)
            init = (R_i, C_i)
        res = resect(X, uv, camera, ransac=len(k) >= 8, where=where, init=init, threshold_px=threshold_px)
        R[i], C[i] = res.R_world_to_camera, res.center_m
        if res.inliers is not None:
            outliers[k[~np.asarray(res.inliers, bool)]] = True
    return R, C


MIN_RESECTION_POINTS = 4
"""An image is oriented from this many points of known coordinates at least (a pose's six
unknowns and a check; :func:`fieldcal.field.resection.resect`)."""


def _known(data: FieldData, X) -> FieldData:
    """``data`` with the target coordinates ``X`` (n, 3) and only the points of targets it places."""
    ok = np.isfinite(X).all(axis=1)
    return replace(data, targets=replace(data.targets, xyz_m=np.where(ok[:, None], X, 0.0)),
                   obs=data.obs.take(ok[data.obs.target]))


def _bootstrap(data: FieldData):
    """Starting coordinates of the unsurveyed targets (step 0; module docstring of
    :mod:`fieldcal.field.intersection`): images with at least :data:`MIN_RESECTION_POINTS`
    surveyed points are resected with the nominal camera (or the DLT's, when enough images
    allow one), the unsurveyed targets seen by two of them intersected, the images that now
    see enough targets of known coordinates resected, and so on while the network grows.

    No image sees enough surveyed targets: the network starts from the relative orientation of
    a pair (:mod:`fieldcal.field.relative_orientation`) and is moved onto the survey
    (:func:`_onto_survey`).

    Returns ``(X (n, 3), how, free_frame)``: surveyed coordinates, intersections, NaN for
    targets that could not be placed; ``free_frame`` when X is in a pair's frame although
    some targets are surveyed."""
    surveyed = data.targets.surveyed
    n_img = len(data.images)
    threshold_px = max(8.0, 0.002 * max(data.sensor.width_px, data.sensor.height_px))
    R, C = np.zeros((n_img, 3, 3)), np.zeros((n_img, 3))
    oriented = np.zeros(n_img, bool)
    n_seen = np.bincount(data.obs.image[surveyed[data.obs.target]], minlength=n_img)
    relative = not (n_seen >= MIN_RESECTION_POINTS).any()     # no image can be resected on the survey
    # relative orientation: every target is placed in the pair's frame first (surveyed ones too)
    unknown = np.ones(len(surveyed), bool) if relative else ~surveyed
    X = np.where(unknown[:, None], np.nan, data.targets.xyz_m)
    if relative:
        if data.nominal_focal_mm is None:
            raise GeometryError("no surveyed target and no nominal focal length: give lens.nominal_focal_mm "
                                "(the network is started by the relative orientation of two images with it)")
        params = np.zeros(13)
        params[INDEX["f_mm"]] = data.nominal_focal_mm
        i, j, R_pair, C_pair = orient_pair(data, params, threshold_px)
        R[[i, j]], C[[i, j]], oriented[[i, j]] = R_pair, C_pair, True
        how = (f"relative orientation of {data.images[i].file} and {data.images[j].file} "
               "(five-point essential matrix, nominal focal length)")
    else:
        known = _known(data, X)
        groups = per_image(known)
        dlt_f, dlt_pp, _, _ = _dlts(known, groups)
        if data.nominal_focal_mm is None and not np.isfinite(dlt_f).any():
            raise GeometryError("unsurveyed targets and no nominal focal length: give lens.nominal_focal_mm "
                                "(the images are resected from the few surveyed targets with it)")
        params, how = _common_interior(known, groups, dlt_f, dlt_pp)
    camera = Camera(data.sensor, params)
    while True:
        known = _known(data, X)
        counts = np.bincount(known.obs.image, minlength=n_img)
        todo = np.flatnonzero(~oriented & (counts >= MIN_RESECTION_POINTS))
        groups = per_image(known)
        for i in todo:
            k = groups[i]
            Xk, uv = known.targets.xyz_m[known.obs.target[k]], known.obs.uv_px[k]
            try:
                if is_coplanar(Xk):
                    R_i, C_i, _ = planar_pose(Xk, uv, camera, where=data.images[i].file)
                    res = resect(Xk, uv, camera, ransac=len(k) >= 8, where=data.images[i].file,
                                 init=(R_i, C_i), threshold_px=threshold_px)
                else:
                    res = resect(Xk, uv, camera, ransac=len(k) >= 8, where=data.images[i].file,
                                 threshold_px=threshold_px)
            except GeometryError:
                continue
            R[i], C[i], oriented[i] = res.R_world_to_camera, res.center_m, True
        use = oriented[data.obs.image] & unknown[data.obs.target]
        Xi, _ = intersect_targets(data, params, R, C, use, threshold_px=threshold_px)
        new = unknown & np.isfinite(Xi).all(axis=1) & ~np.isfinite(X).all(axis=1)
        X[new] = Xi[new]
        if not new.any() and not len(todo):
            break
    free_frame = False
    if relative:
        X, how, free_frame = _onto_survey(data, X, how)
    n_uns = int((~surveyed[np.unique(data.obs.target)]).sum())
    n_placed = int((~surveyed & np.isfinite(X).all(axis=1)).sum())
    return X, (f"{n_placed} of {n_uns} unsurveyed targets intersected from {int(oriented.sum())} images "
               f"oriented on the surveyed ones and the growing network ({how})"), free_frame


def _onto_survey(data: FieldData, X, how: str):
    """A network started by relative orientation, moved onto the survey: the similarity that
    fits its intersections of the surveyed targets to their surveyed coordinates (Umeyama
    1991; three or more, not collinear), then the surveyed coordinates themselves. With fewer,
    the pair's frame stays (a free network) and the surveyed coordinates are not used.
    Returns ``(X, how, free_frame)``."""
    s = data.targets.surveyed & np.isfinite(X).all(axis=1)
    P, Q = X[s], data.targets.xyz_m[s]
    if len(P) >= 3:
        mp, mq = P.mean(0), Q.mean(0)
        U, sv, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
        d = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
        if sv[1] > 1e-6 * sv[0]:                    # not collinear
            Rm = U @ d @ Vt
            scale = np.trace(np.diag(sv) @ d) / np.sum((P - mp) ** 2)
            X = scale * (X - mp) @ Rm.T + mq
            X[data.targets.surveyed] = data.targets.xyz_m[data.targets.surveyed]
            return X, f"{how}, moved onto {len(P)} surveyed targets", False
    return X, how, bool(data.targets.surveyed[np.unique(data.obs.target)].any())


def initial_values(data: FieldData, estimate: Sequence[str]) -> InitialValues:
    """Initial interior and exterior orientation (module docstring).

    With unsurveyed targets, their coordinates first (:func:`_bootstrap`); then the steps
    below on every target of known or intersected coordinates, and the intersections
    repeated with the oriented images (``InitialValues.targets_m``). Points of targets that
    could not be placed are flagged as initial outliers.

    Parameters
    ----------
    data : FieldData
    estimate : sequence of str
        The interior parameters to be estimated; those beyond ``f, xp, yp`` start from
        the distortion fit (the rest are 0).

    Returns
    -------
    InitialValues
    """
    if not data.targets.surveyed[np.unique(data.obs.target)].all():
        return _with_unsurveyed(data, estimate)
    return _initial_values(data, estimate)


def _with_unsurveyed(data: FieldData, estimate: Sequence[str]) -> InitialValues:
    """:func:`initial_values` of a network with unsurveyed targets."""
    X, how, free_frame = _bootstrap(data)
    placed = np.isfinite(X).all(axis=1)[data.obs.target]
    sub = _known(data, X)
    init = _initial_values(sub, estimate)
    threshold_px = max(8.0, 0.002 * max(data.sensor.width_px, data.sensor.height_px))
    use = np.zeros(len(data.obs), bool)
    use[np.flatnonzero(placed)] = ~init.outliers
    unsurveyed = ~data.targets.surveyed
    Xi, inlier = intersect_targets(data, init.params, init.R_world_to_camera, init.center_m,
                                   use & unsurveyed[data.obs.target], threshold_px=threshold_px)
    again = unsurveyed & np.isfinite(Xi).all(axis=1)
    X[again] = Xi[again]
    X[unsurveyed & ~again] = np.nan
    outliers = np.ones(len(data.obs), bool)
    outliers[np.flatnonzero(placed)] = init.outliers
    outliers |= ~np.isfinite(X).all(axis=1)[data.obs.target]
    outliers |= unsurveyed[data.obs.target] & ~inlier
    return InitialValues(init.params, init.R_world_to_camera, init.center_m, outliers, init.dlt_f_mm,
                         f"{how}; then {init.how}", targets_m=X, free_frame=free_frame)


def _initial_values(data: FieldData, estimate: Sequence[str]) -> InitialValues:
    """:func:`initial_values` of a network whose observed targets are all surveyed."""
    sensor = data.sensor
    groups = per_image(data)
    dlt_f, dlt_pp, poses, outliers = _dlts(data, groups)
    params, how = _common_interior(data, groups, dlt_f, dlt_pp)
    threshold_px = max(8.0, 0.002 * max(sensor.width_px, sensor.height_px))
    R, C = _orient(data, groups, params, poses, outliers, threshold_px)
    # distortion initial values, eq. 7-8, from the inliers of all images
    names = [n for n in estimate if n not in CORE_PARAMS]
    if names:
        use = ~outliers
        img = data.obs.image[use]
        Xc = np.einsum("kab,kb->ka", R[img], data.targets.xyz_m[data.obs.target[use]] - C[img])
        q = -params[INDEX["f_mm"]] * Xc[:, :2] / Xc[:, 2:3]
        xy = sensor.pixel_to_mm(data.obs.uv_px[use])
        fit = distortion_lsq(xy, q, params[INDEX["xp_mm"]], params[INDEX["yp_mm"]], names)
        for n in names:
            params[INDEX[n]] = fit.coefficients[n]
    return InitialValues(params, R, C, outliers, dlt_f, how)
