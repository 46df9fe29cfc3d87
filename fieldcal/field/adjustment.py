"""The field method's adjustment: initial values, LMQN solve, blunders, parameter selection.

Procedure (METHODS part A, with the safeguards a production calibration needs)
------------------------------------------------------------------------------
1. **Initial values** (:func:`initial_values`). Per image, the DLT (eq. 1-6, Hartley
   normalised, robust to blunders) on the surveyed targets it sees; the interior starting
   point is the median of the per-image ``f, xp, yp``. Planar fields (or images whose
   targets are coplanar) use the nominal focal length (or Zhang's closed form) instead.
   Every image is then resected with the common interior orientation, and the distortion
   coefficients start from the linear least squares of eq. 7-8.
2. **Adjustment** (:class:`FieldProblem`, :func:`fieldcal.solver.lsq.solve`): image-space
   residuals of all images, exterior orientations, interior parameters and (by default)
   the targets, whose surveyed coordinates enter as observations weighted by their sigma
   (a self-calibrating bundle; ``targets_adjusted=False`` holds them fixed as the paper does).
3. **Blunders**: first gross rejection on residuals normalised by a robust scale
   (``robust_k`` times 1.4826 MAD), then data snooping: the test statistic of each image
   point (2-D) and each survey (3-D) ``T = v^T Q_vv^-1 v / sigma0^2`` with
   ``Q_vv = I - J_g N^-1 J_g^T`` from the normal equations, rejected above the chi-square
   quantile of ``snoop_alpha``; repeat until nothing is rejected.
4. **Parameter selection** (when the session gives no ``estimate``): an additional
   parameter (``k1 .. a2``) is held fixed at 0 when the data cannot determine it: its
   correlation with another interior parameter exceeds ``max_correlation`` (the weaker
   of the pair is fixed) or it is not significant (``|value| < min_t * sigma``). One
   parameter per round, the worst first, each reason reported (``stats.fixed_parameters``).
5. **Diagnoses instead of calibrations** (:class:`~fieldcal.errors.GeometryError`): fewer
   than :data:`MIN_IMAGES` images or :data:`MIN_POINTS_PER_IMAGE` points in an image; a
   network that cannot determine f even with every additional parameter held fixed (checked
   on the first solve's a-priori covariance: relative sigma above ``max_rel_sigma_f``, naming
   the unknown f is most correlated with, e.g. the camera distance of a flat wall photographed
   from one direction); an automatic selection that ends with f still undetermined; singular
   normal equations (naming the unknown where known).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
from scipy.stats import chi2

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.bundle import BundleModel
from fieldcal.field.data import FieldData
from fieldcal.field.distortion_init import distortion_lsq
from fieldcal.field.dlt import dlt_robust, zhang_focal
from fieldcal.field.geometry import is_coplanar
from fieldcal.field.resection import planar_pose, resect
from fieldcal.model.camera import FIELD_PARAMS, INDEX, Camera
from fieldcal.robust import robust_sigma
from fieldcal.solver.blocksparse import BlockSparseJacobian, ResidualBlock, SingularSystemError
from fieldcal.solver.lsq import LsqResult, solve

__all__ = ["AdjustmentOptions", "FieldProblem", "FieldResult", "InitialValues", "initial_values",
           "adjust_field", "validate_field_data", "CORE_PARAMS"]

CORE_PARAMS = ("f_mm", "xp_mm", "yp_mm")
"""Never held fixed by the automatic selection (a degenerate one is a diagnosis, not a fix)."""

MIN_POINTS_PER_IMAGE = 6
MIN_IMAGES = 3
"""The field method needs at least this many images (as a session measured from images does)."""


@dataclass
class AdjustmentOptions:
    """Settings of :func:`adjust_field` (all recorded in the result and the fingerprint).

    Attributes
    ----------
    targets_adjusted : bool
        Surveyed coordinates as weighted observations (default) or held fixed.
    estimate : tuple of str or None
        Interior parameters to estimate; ``None``: the method's full set with the
        automatic selection of step 4.
    method : str
        ``"lmqn"`` (default) or ``"lm"``.
    tau, eps2, ftol : float
        LM's initial damping factor (small: the initial values are good), the step
        tolerance and the negligible-decrease tolerance of :func:`fieldcal.solver.lsq.solve`.
    robust_k : float
        Gross-error threshold in robust sigmas (normalised residual norm).
    snoop_alpha : float
        Significance level of data snooping (per observation).
    max_correlation : float
        Correlation above which the weaker of two interior parameters is fixed.
    min_t : float
        An additional parameter with ``|value| / sigma`` below this is fixed.
    max_rel_sigma_f : float
        When the principal distance is determined worse than this (relative sigma), the
        additional parameter that inflates the sigma of f, xp, yp most is fixed first.
    """

    targets_adjusted: bool = True
    estimate: tuple[str, ...] | None = None
    method: str = "lmqn"
    max_iter: int = 1000
    tau: float = 1e-6
    eps2: float = 1e-10
    ftol: float = 1e-12
    robust_k: float = 8.0
    snoop_alpha: float = 1e-6
    max_rounds: int = 20
    max_correlation: float = 0.995
    min_t: float = 1.0
    max_rel_sigma_f: float = 0.02

    def to_dict(self) -> dict:
        return {"targets_adjusted": self.targets_adjusted,
                "estimate": list(self.estimate) if self.estimate is not None else None,
                "method": self.method, "max_iter": self.max_iter, "tau": self.tau, "eps2": self.eps2,
                "ftol": self.ftol,
                "robust_k": self.robust_k,
                "snoop_alpha": self.snoop_alpha, "max_rounds": self.max_rounds,
                "max_correlation": self.max_correlation, "min_t": self.min_t,
                "max_rel_sigma_f": self.max_rel_sigma_f}


# ---------------------------------------------------------------------------- validation
def validate_field_data(data: FieldData, *, min_points: int = MIN_POINTS_PER_IMAGE) -> None:
    """Refuse data the adjustment cannot use, naming what and where.

    NaN or infinite coordinates, duplicate target ids, non-positive sigmas, observations
    of unknown targets or images, images with fewer than ``min_points`` points, and fewer
    than :data:`MIN_IMAGES` images.
    """
    t = data.targets
    if len(np.unique(t.ids)) != len(t.ids):
        ids, counts = np.unique(t.ids, return_counts=True)
        raise InputError(f"duplicate target id(s) {list(ids[counts > 1][:5])}", "targets")
    bad = ~np.isfinite(t.xyz_m).all(axis=1)
    if bad.any():
        raise InputError(f"target '{t.ids[np.argmax(bad)]}' has non-finite coordinates", "targets")
    if not (np.isfinite(t.sigma_mm) & (t.sigma_mm > 0)).all():
        raise InputError("target sigma_mm must be positive and finite", "targets")
    o = data.obs
    if len(o) == 0:
        raise GeometryError("no image observations")
    if o.target.min() < 0 or o.target.max() >= len(t) or o.image.min() < 0 or o.image.max() >= len(data.images):
        raise InputError("observations refer to unknown targets or images", "observations")
    bad = ~np.isfinite(o.uv_px).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise InputError(f"non-finite image coordinates of target {t.ids[o.target[k]]!r}",
                         data.images[o.image[k]].file)
    if not (np.isfinite(o.sigma_px) & (o.sigma_px > 0)).all():
        raise InputError("observation sigma_px must be positive and finite", "observations")
    counts = np.bincount(o.image, minlength=len(data.images))
    for i in np.flatnonzero(counts < min_points):
        raise GeometryError(f"{data.images[i].file}: only {counts[i]} observed target(s); an image "
                            f"needs at least {min_points} to be oriented (leave it out or add points)")
    if len(data.images) < MIN_IMAGES:
        raise GeometryError(f"only {len(data.images)} image(s) ({', '.join(im.file for im in data.images)}); "
                            f"the field method needs at least {MIN_IMAGES}, from different positions "
                            "and roll angles")


# ---------------------------------------------------------------------------- initial values
@dataclass
class InitialValues:
    """Starting point of the adjustment, with how it was obtained."""

    params: np.ndarray
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    outliers: np.ndarray          # (m,) observations flagged by the robust initialisers
    dlt_f_mm: np.ndarray          # per image (NaN where no DLT)
    how: str


def _per_image(data: FieldData):
    order = np.argsort(data.obs.image, kind="stable")
    bounds = np.searchsorted(data.obs.image[order], np.arange(len(data.images) + 1))
    return [order[bounds[i]:bounds[i + 1]] for i in range(len(data.images))]


def initial_values(data: FieldData, estimate: Sequence[str]) -> InitialValues:
    """Initial interior and exterior orientation (module docstring, step 1)."""
    sensor = data.sensor
    groups = _per_image(data)
    X_all = data.targets.xyz_m
    planar_field = is_coplanar(X_all[np.unique(data.obs.target)])
    n_img = len(data.images)
    dlt_f = np.full(n_img, np.nan)
    dlt_pp = np.full((n_img, 2), np.nan)
    poses: list = [None] * n_img
    outliers = np.zeros(len(data.obs), bool)
    nominal = data.nominal_focal_mm
    if not planar_field:
        for i, k in enumerate(groups):
            X, uv = X_all[data.obs.target[k]], data.obs.uv_px[k]
            if is_coplanar(X):
                continue
            try:
                res = dlt_robust(X, uv, sensor, where=data.images[i].file, seed=i)
            except GeometryError:
                continue
            dlt_f[i], dlt_pp[i] = res.f_mm, (res.xp_mm, res.yp_mm)
            poses[i] = (res.R_world_to_camera, res.center_m)
            outliers[k[~res.inliers]] = True
    ok = np.isfinite(dlt_f)
    if nominal is not None and ok.any():
        ok &= (dlt_f > 0.5 * nominal) & (dlt_f < 2.0 * nominal)
    params = np.zeros(13)
    if ok.sum() >= max(1, n_img // 4):
        params[INDEX["f_mm"]] = np.median(dlt_f[ok])
        params[[INDEX["xp_mm"], INDEX["yp_mm"]]] = np.median(dlt_pp[ok], axis=0)
        how = f"DLT on {ok.sum()} of {n_img} images (median f, xp, yp)"
    elif nominal is not None:
        params[INDEX["f_mm"]] = nominal
        how = "nominal focal length, principal point at the sensor centre"
    else:
        views = [(X_all[data.obs.target[k]], data.obs.uv_px[k]) for k in groups]
        params[INDEX["f_mm"]] = zhang_focal(views, sensor, where="session")
        how = "Zhang's closed form from the planar views"
    camera = Camera(sensor, params)
    R = np.zeros((n_img, 3, 3))
    C = np.zeros((n_img, 3))
    for i, k in enumerate(groups):
        X, uv = X_all[data.obs.target[k]], data.obs.uv_px[k]
        where = data.images[i].file
        if poses[i] is None and is_coplanar(X):
            R_i, C_i, _ = planar_pose(X, uv, camera, where=where)
            poses[i] = (R_i, C_i)
        res = resect(X, uv, camera, ransac=len(k) >= 8, where=where, init=poses[i],
                     threshold_px=max(8.0, 0.002 * max(sensor.width_px, sensor.height_px)))
        R[i], C[i] = res.R_world_to_camera, res.center_m
        if res.inliers is not None:
            outliers[k[~np.asarray(res.inliers, bool)]] = True
    # distortion initial values, eq. 7-8, from the inliers of all images
    names = [n for n in estimate if n not in CORE_PARAMS]
    if names:
        use = ~outliers
        img = data.obs.image[use]
        Xc = np.einsum("kab,kb->ka", R[img], X_all[data.obs.target[use]] - C[img])
        q = -params[INDEX["f_mm"]] * Xc[:, :2] / Xc[:, 2:3]
        xy = sensor.pixel_to_mm(data.obs.uv_px[use])
        fit = distortion_lsq(xy, q, params[INDEX["xp_mm"]], params[INDEX["yp_mm"]], names)
        for n in names:
            params[INDEX[n]] = fit.coefficients[n]
    return InitialValues(params, R, C, outliers, dlt_f, how)


# ---------------------------------------------------------------------------- the LSQ problem
class FieldProblem:
    """The bundle model as a problem for :func:`fieldcal.solver.lsq.solve` (block-sparse Jacobian)."""

    def __init__(self, model: BundleModel):
        self.model = model
        m = model
        k = len(m.img)
        self._rows_img = np.arange(2 * k).reshape(k, 2)
        self._cols_int = np.arange(m.n_int)
        self._cols_ext = m.n_int + 6 * m.img[:, None] + np.arange(6)
        self._cols_tgt = m.n_reduced + 3 * m.tgt_slot[:, None] + np.arange(3)
        ns = len(m.survey_k)
        self._rows_sur = m.n_rows_image + np.arange(3 * ns).reshape(ns, 3)
        self._cols_sur = m.n_reduced + 3 * m.t_slot[m.survey_k][:, None] + np.arange(3)
        self._template: list[ResidualBlock] | None = None
        self._structure = None

    def evaluate(self, x, jacobian: bool):
        m = self.model
        r, jb, sd = m.residuals_and_blocks(x, jacobian)
        if not jacobian:
            return r, None
        parts = [(self._cols_int, jb.d_int), (self._cols_ext, jb.d_ext)]
        if m.targets_adjusted:
            parts.append((self._cols_tgt, jb.d_tgt))
        sur_values = sd[:, None, None] * np.eye(3)[None]
        if self._template is None:
            blocks = [ResidualBlock.from_parts(self._rows_img, parts)]
            if len(sd):
                blocks.append(ResidualBlock.from_parts(self._rows_sur, [(self._cols_sur, sur_values)]))
            self._template = blocks
        else:
            blocks = [self._template[0].with_values(*[p[1] for p in parts])]
            if len(sd):
                blocks.append(self._template[1].with_values(sur_values))
        J = BlockSparseJacobian(m.n_rows, m.n_params, m.n_reduced, 3, blocks, structure=self._structure)
        self._structure = J.structure
        return r, J


# ---------------------------------------------------------------------------- the result
@dataclass
class FieldResult:
    """Everything the field adjustment produced (see :func:`adjust_field`)."""

    data: FieldData
    options: AdjustmentOptions
    params: np.ndarray
    estimate: tuple[str, ...]
    fixed_parameters: dict
    sigma: dict
    sigma0: float
    covariance: np.ndarray            # reduced block [interior | exterior], a-posteriori
    covariance_names: list[str]
    correlation_interior: np.ndarray
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    sigma_center_m: np.ndarray
    targets_m: np.ndarray
    sigma_targets_m: np.ndarray | None
    residual_px: np.ndarray           # (m, 2) measured - predicted, all observations
    obs_used: np.ndarray              # (m,) bool
    obs_reason: np.ndarray            # (m,) str ('' when used)
    obs_test: np.ndarray              # (m,) snooping statistic (NaN when not tested)
    survey_used: np.ndarray           # (n_targets,) bool
    survey_residual_mm: np.ndarray    # (n_targets, 3) surveyed - adjusted
    lsq: LsqResult
    iterations_total: int
    initial: InitialValues
    rounds: list = field(default_factory=list)

    @property
    def camera(self) -> Camera:
        return Camera(self.data.sensor, self.params)

    def stats(self) -> dict:
        """The document's ``stats`` (CONTRACT section 4) plus a few extras."""
        used = self.obs_used
        du = self.residual_px[used]
        norm = np.hypot(du[:, 0], du[:, 1])
        observed = np.unique(self.data.obs.target[used])
        return {
            "n_images": int(len(np.unique(self.data.obs.image[used]))),
            "n_targets": int(len(observed)),
            "n_observations": int(used.sum()),
            "n_rejected": int((self.obs_reason == "blunder").sum()),
            "rmse_px": float(np.sqrt(np.mean(norm**2))),
            "max_px": float(norm.max()),
            "mean_abs_u_px": float(np.mean(np.abs(du[:, 0]))),
            "mean_abs_v_px": float(np.mean(np.abs(du[:, 1]))),
            "sigma0": float(self.sigma0),
            "iterations": int(self.lsq.iterations),
            "solver": self.options.method,
            "targets_adjusted": bool(self.options.targets_adjusted),
            "fixed_parameters": dict(self.fixed_parameters),
            "n_surveys_rejected": int((~self.survey_used[observed]).sum()) if self.options.targets_adjusted else 0,
            "rejected_surveys": [str(t) for t in self.data.targets.ids[observed][~self.survey_used[observed]]]
            if self.options.targets_adjusted else [],
            "n_left_out": int(((~used) & (self.obs_reason != "blunder")).sum()),
            "iterations_total": int(self.iterations_total),
            "lsq_status": self.lsq.message,
            "initial_values": self.initial.how,
        }

    def images_section(self) -> list[dict]:
        """The document's ``images`` list (CONTRACT section 4)."""
        out = []
        used = self.obs_used
        for i, im in enumerate(self.data.images):
            k = (self.data.obs.image == i) & used
            res = self.residual_px[k]
            out.append({
                "file": im.file, "station": im.station,
                "center_m": self.center_m[i].tolist(),
                "rotation_world_to_camera": self.R_world_to_camera[i].tolist(),
                "sigma_center_m": self.sigma_center_m[i].tolist(),
                "n_observations": int(k.sum()),
                "rmse_px": float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if k.any() else None,
            })
        return out

    def residual_table(self) -> pa.Table:
        """One row per image observation: measured, residual, used, reason, test statistic."""
        d = self.data
        reason = [r if r else None for r in self.obs_reason]
        return pa.table({
            "image": pa.array([d.images[i].file for i in d.obs.image], pa.string()),
            "target_id": pa.array(d.targets.ids[d.obs.target], pa.string()),
            "u_px": d.obs.uv_px[:, 0], "v_px": d.obs.uv_px[:, 1],
            "du_px": self.residual_px[:, 0], "dv_px": self.residual_px[:, 1],
            "sigma_px": d.obs.sigma_px,
            "used": pa.array(self.obs_used, pa.bool_()),
            "reason": pa.array(reason, pa.string()),
            "normalized_residual": self.obs_test,
        })


# ---------------------------------------------------------------------------- the procedure
class _Solver:
    """Runs solves on changing active sets and keeps the current state."""

    def __init__(self, data, options, init: InitialValues, progress):
        self.data, self.options, self.progress = data, options, progress
        self.params = init.params.copy()
        self.R = init.R_world_to_camera.copy()
        self.C = init.center_m.copy()
        self.X = data.targets.xyz_m.copy()
        self.iterations = 0
        self.rounds: list[dict] = []
        self.model: BundleModel | None = None

    def run(self, estimate, obs_active, survey_active, label):
        o = self.options
        model = BundleModel(self.data, self.params, estimate, self.R,
                            targets_adjusted=o.targets_adjusted, obs_active=obs_active,
                            survey_active=survey_active)
        x0 = model.pack(self.params, self.C, self.X)
        self.model = model
        try:
            result = solve(FieldProblem(model), x0, method=o.method, max_iter=o.max_iter, tau=o.tau,
                           eps2=o.eps2, ftol=o.ftol)
        except InputError as err:          # not finite at x0: the previous round went astray
            raise GeometryError(f"the adjustment diverged before {label} ({err.reason}); the "
                                "data do not hold the camera in place") from None
        if not np.all(np.isfinite(result.r)):
            raise GeometryError("the adjustment diverged (points behind a camera)")
        self.params, self.R, self.C, X = model.unpack(result.x)
        if o.targets_adjusted:
            self.X = X
        self.iterations += result.iterations
        self.rounds.append({"round": label, "iterations": result.iterations,
                            "sigma0": result.sigma0, "status": result.message,
                            "n_obs": int(np.sum(obs_active)), "estimate": list(estimate)})
        if self.progress:
            self.progress(f"{label}: {result.iterations} iterations, sigma0 {result.sigma0:.3f}")
        return model, result

    def residuals_all(self):
        """Measured minus predicted pixels of every observation at the current state."""
        d = self.data
        Xc = np.einsum("kab,kb->ka", self.R[d.obs.image], self.X[d.obs.target] - self.C[d.obs.image])
        cam = Camera(d.sensor, self.params)
        with np.errstate(divide="ignore", invalid="ignore"):
            q = -cam.f_mm * Xc[:, :2] / np.where(Xc[:, 2] < 0, Xc[:, 2], np.nan)[:, None]
        uv = d.sensor.mm_to_pixel(cam.distort(q, check=False))
        return d.obs.uv_px - uv


def _robust_scale(z):
    return max(float(robust_sigma(z)), 1e-12)


def _drop_undetermined_targets(data, obs_active, survey_active, reason):
    """Targets whose survey is rejected need two images; otherwise their points go too."""
    n_img_per_target = np.zeros(len(data.targets), int)
    pairs = np.unique(np.stack([data.obs.target[obs_active], data.obs.image[obs_active]]), axis=1)
    np.add.at(n_img_per_target, pairs[0], 1)
    weak = (~survey_active) & (n_img_per_target < 2)
    drop = obs_active & weak[data.obs.target]
    obs_active[drop] = False
    reason[drop] = "target undetermined after its survey was rejected"
    return drop.sum()


def _intersect(rays, centers):
    """Least-squares intersection of rays (k, 3) from centres (k, 3): the point nearest all."""
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    return np.linalg.solve(P.sum(0), np.einsum("kab,kb->a", P, centers))


def _blame_the_survey(solver, obs_active, survey_active, reason, sigma0):
    """Targets whose rejected image points intersect consistently away from the survey.

    For each target with rejected points in at least two images, the rays of those points
    are intersected (least squares, current cameras), dropping the worst ray while the rest
    do not meet within the image noise. If at least two rays remain that meet within the
    noise, in front of their cameras and at an angle of at least ``10 / (n - 1)`` degrees
    (two rays always nearly meet: they need a wide angle), and the intersection lies more
    than 5 survey sigmas from the surveyed coordinates, the survey is the blunder: it is
    rejected and the consistent points are readmitted. Returns the number of surveys rejected.
    """
    data = solver.data
    out = ~obs_active & np.isin(reason, ("initial outlier", "blunder"))
    if not out.any():
        return 0
    cam = Camera(data.sensor, solver.params)
    n = 0
    for t in np.unique(data.obs.target[out]):
        if not survey_active[t]:
            continue
        k = np.flatnonzero(out & (data.obs.target == t))
        if len(np.unique(data.obs.image[k])) < 2:
            continue
        while len(k) >= 2:
            img = data.obs.image[k]
            rays = np.einsum("kba,kb->ka", solver.R[img], cam.unproject(data.obs.uv_px[k]))
            X = _intersect(rays, solver.C[img])
            uv = np.stack([cam.project(X, solver.R[i], solver.C[i]) for i in img])
            err = np.hypot(*(uv - data.obs.uv_px[k]).T)
            ok = np.isfinite(err) & (err < np.maximum(1.0, 5.0 * sigma0 * data.obs.sigma_px[k]))
            if ok.all():
                break
            k = np.delete(k, int(np.argmax(np.where(np.isfinite(err), err, np.inf))))
        if len(k) < 2:
            continue
        angle = np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0)))
        far = np.linalg.norm(X - data.targets.xyz_m[t]) * 1000.0 > 5.0 * data.targets.sigma_mm[t]
        if angle >= 10.0 / (len(k) - 1) and far:
            survey_active[t] = False
            obs_active[k] = True
            reason[k] = ""
            solver.X[t] = X
            n += 1
    return n


def _gross_rejection(solver, model, result, obs_active, survey_active, reason, o):
    """Reject observations beyond robust_k robust sigmas; returns how many.

    The robust scale (1.4826 MAD) is taken over points of targets seen in three or more
    images when targets are adjusted: a target seen once or twice absorbs its points'
    errors (redundancy near 0), and their near-zero residuals would shrink the scale.
    """
    r = result.r
    ri = r[: model.n_rows_image].reshape(-1, 2)
    norm_i = np.hypot(ri[:, 0], ri[:, 1])
    redundant = np.ones(len(ri), bool)
    if model.targets_adjusted:
        redundant = np.bincount(model.tgt, minlength=model.n_targets)[model.tgt] >= 3
        if redundant.sum() < 20:
            redundant[:] = True
    s = _robust_scale(ri[redundant].ravel())
    bad_i = norm_i > o.robust_k * s * np.sqrt(2.0)
    k = model.k[bad_i]
    obs_active[k] = False
    reason[k] = "blunder"
    n = int(bad_i.sum())
    if model.targets_adjusted and len(model.survey_k):
        rs = r[model.n_rows_image:].reshape(-1, 3)
        norm_s = np.linalg.norm(rs, axis=1)
        bad_s = norm_s > o.robust_k * max(s, 1.0) * np.sqrt(3.0)
        survey_active[model.survey_k[bad_s]] = False
        n += int(bad_s.sum())
    return n


def _snooping(model, result, obs_active, survey_active, reason, test, o):
    """Data snooping with redundancy (module docstring, step 3); returns how many rejected."""
    ne = result.jac.normal_equations()
    sigma0 = max(result.sigma0, 1e-12)
    n = 0
    Qi = np.eye(2) - ne.group_covariance(0)
    ri = result.r[: model.n_rows_image].reshape(-1, 2)
    Ti = _quadratic_form(Qi, ri) / sigma0**2
    test[model.k] = Ti
    lim2 = chi2.isf(o.snoop_alpha, 2)
    bad = Ti > lim2
    if bad.any():
        # reject the clearly worst ones only: a blunder inflates its neighbours' statistics
        worst = bad & (Ti > 0.25 * Ti.max())
        k = model.k[worst]
        obs_active[k] = False
        reason[k] = "blunder"
        n += int(worst.sum())
    if model.targets_adjusted and len(model.survey_k):
        Qs = np.eye(3) - ne.group_covariance(1)
        rs = result.r[model.n_rows_image:].reshape(-1, 3)
        Ts = _quadratic_form(Qs, rs) / sigma0**2
        bad_s = Ts > chi2.isf(o.snoop_alpha, 3)
        if bad_s.any():
            worst = bad_s & (Ts > 0.25 * Ts.max())
            survey_active[model.survey_k[worst]] = False
            n += int(worst.sum())
    return n


def _quadratic_form(Q, r):
    """``r^T Q^+ r`` per group (Q (k, d, d) possibly near-singular for zero redundancy)."""
    Qp = np.linalg.pinv(Q, rcond=1e-8, hermitian=True)
    return np.einsum("ki,kij,kj->k", r, Qp, r)


def _interior_stats(model, result):
    """Sigma (a-posteriori) and correlation of the estimated interior parameters."""
    cov = result.jac.normal_equations().covariance_reduced() * result.sigma0**2
    ci = cov[: model.n_int, : model.n_int]
    s = np.sqrt(np.diag(ci))
    corr = ci / np.outer(s, s)
    return cov, s, corr


def _select_parameter(model, result, estimate, o):
    """The next parameter to hold fixed and why, or None (module docstring, step 4)."""
    cov, s, corr = _interior_stats(model, result)
    C = cov[: model.n_int, : model.n_int]
    values = result.x[: model.n_int]
    names = list(estimate)
    core = [i for i, n in enumerate(names) if n in CORE_PARAMS]
    extra = [j for j, n in enumerate(names) if n not in CORE_PARAMS]
    if not extra:
        return None
    # (1) the principal distance is not determined: drop the parameter that inflates it most
    if "f_mm" in names:
        jf = names.index("f_mm")
        rel = s[jf] / abs(values[jf])
        if rel > o.max_rel_sigma_f:
            def inflation(j):
                cond = np.diag(C)[core] - C[core, j] ** 2 / C[j, j]
                return float(np.max(np.sqrt(np.diag(C)[core] / cond)))
            j = max(extra, key=inflation)
            i = max((i for i in range(len(names)) if i != j), key=lambda i: abs(corr[j, i]))
            return names[j], (f"f undetermined (sigma {100 * rel:.2g} %); {names[j]} inflates the sigma of "
                              f"f, xp, yp {inflation(j):.2g}x (correlation {corr[j, i]:.3f} with {names[i]})")
    # (2) an additional parameter nearly equal to another: fix the weaker of the pair
    candidates = []
    for j in extra:
        others = [i for i in range(len(names)) if i != j]
        i = others[int(np.argmax(np.abs(corr[j, others])))]
        t_j = abs(values[j]) / s[j]
        t_i = abs(values[i]) / s[i] if i not in core else np.inf
        if abs(corr[j, i]) > o.max_correlation and t_j <= t_i:
            candidates.append((2.0 + abs(corr[j, i]), names[j], f"correlation {corr[j, i]:.4f} with {names[i]}"))
        elif t_j < o.min_t:
            # (3) not significant
            candidates.append((1.0 + (o.min_t - t_j), names[j], f"not significant ({t_j:.2f} sigma)"))
    if not candidates:
        return None
    candidates.sort(reverse=True)
    return candidates[0][1], candidates[0][2]


_ADVICE = "add images from other positions and distances, rolled by 90 degrees, or targets in depth"


def _column_label(name: str) -> str:
    """``images/a.tif:Y_m`` -> ``Y_m of images/a.tif`` (a column of :meth:`BundleModel.column_names`)."""
    head, sep, tail = name.rpartition(":")
    return f"{tail} of {head}" if sep else name


def _f_determination(model, cov, fixed_extras: bool):
    """Relative sigma of f and its strongest correlation, optionally with the additional
    parameters held fixed (the conditional covariance ``C_rr - C_re C_ee^-1 C_er``).

    Returns ``(sigma_f, correlation, column name)`` (f must be estimated).
    """
    names = list(model.estimate)
    jf = names.index("f_mm")
    cf, var = cov[jf].copy(), np.diag(cov).copy()
    e = [j for j, n in enumerate(names) if n not in CORE_PARAMS] if fixed_extras else []
    if e:
        K = np.linalg.lstsq(cov[np.ix_(e, e)], cov[e], rcond=None)[0]
        cf -= cov[jf, e] @ K
        var -= np.einsum("ij,ij->j", cov[e], K)
    var = np.maximum(var, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cf / np.sqrt(var[jf] * var)
    corr[jf] = 0.0
    corr[e] = 0.0
    corr[~np.isfinite(corr)] = 0.0
    k = int(np.argmax(np.abs(corr)))
    return float(np.sqrt(var[jf])), float(corr[k]), model.column_names()[k]


def _f_undetermined(rel, c, name, held=""):
    return GeometryError(f"the data cannot determine the principal distance: its sigma is "
                         f"{100 * rel:.3g} % of f{held} (correlation {c:.4f} with "
                         f"{_column_label(name)}): {_ADVICE}")


def _check_f_determinable(model, result, o):
    """Refuse, right after the first adjustment, a network that cannot determine f.

    With the a-priori covariance (a property of the geometry, not of the residuals, which
    may still hold blunders) and every additional parameter held fixed (the most any choice
    of parameters could do): a relative sigma of f above ``max_rel_sigma_f`` then will not
    get better by fixing parameters, so the diagnosis is given now, naming the unknown that
    f cannot be told from. (A session's explicit ``estimate`` whose additional parameters
    alone make f uncertain is honoured, with the sigma it gives.)
    """
    if "f_mm" not in model.estimate:
        return
    ne = result.jac.normal_equations()
    try:
        cov = ne.covariance_reduced()
    except SingularSystemError:
        _f_in_null_space(model, ne)
        raise
    sigma_f, c, name = _f_determination(model, cov, fixed_extras=True)
    rel = sigma_f / max(abs(result.x[list(model.estimate).index("f_mm")]), 1e-12)
    if not (rel <= o.max_rel_sigma_f):
        extra = any(n not in CORE_PARAMS for n in model.estimate)
        raise _f_undetermined(rel, c, name, " even with every additional parameter held fixed" if extra else "")


def _f_in_null_space(model, ne) -> None:
    """Singular normal equations: if f takes part in their null space, say what it cannot be
    told from (the other unknown with the largest share of the null vector, equilibrated)."""
    S = ne.schur_complement()
    d = np.sqrt(np.clip(np.diag(S), 1e-300, None))
    w, V = np.linalg.eigh(S / np.outer(d, d))
    v = V[:, 0]
    jf = list(model.estimate).index("f_mm")
    if abs(v[jf]) < 0.1:
        return
    share = np.abs(v)
    share[jf] = 0.0
    k = int(np.argmax(share))
    raise GeometryError(f"the data cannot determine the principal distance: it cannot be told from "
                        f"{_column_label(model.column_names()[k])} (singular normal equations, "
                        f"smallest eigenvalue {w[0]:.1e} relative to the diagonal): {_ADVICE}")


def _singular_diagnosis(err, model) -> str:
    """A :class:`SingularSystemError` as a diagnosis naming the unknown, where known."""
    what = ""
    if model is not None and err.index is not None:
        names = model.column_names()
        if 0 <= err.index < len(names):
            what = f" ({_column_label(names[err.index])} cannot be determined)"
    return f"the data do not determine every unknown{what}: {err}; {_ADVICE}"


def _check_core_determined(model, result, corr, sigma, o):
    names = list(model.estimate)
    for a in CORE_PARAMS:
        if a not in names:
            continue
        j = names.index(a)
        for i, b in enumerate(names):
            if i != j and abs(corr[j, i]) > 0.9999:
                raise GeometryError(f"the data cannot separate {a} from {b} (correlation "
                                    f"{corr[j, i]:.5f}): add images with other roll angles, "
                                    "distances or a deeper target field")
    if o.estimate is None and "f_mm" in names:     # the automatic selection could not make f determined
        rel = sigma[names.index("f_mm")] / max(abs(result.x[names.index("f_mm")]), 1e-12)
        if not (rel <= o.max_rel_sigma_f):
            cov = result.jac.normal_equations().covariance_reduced() * result.sigma0**2
            raise _f_undetermined(rel, *_f_determination(model, cov, fixed_extras=False)[1:])


def adjust_field(data: FieldData, options: AdjustmentOptions | None = None, *,
                 progress: Callable[[str], None] | None = None, initial: InitialValues | None = None,
                 initial_targets_m=None) -> FieldResult:
    """Calibrate a camera from identified field observations (module docstring).

    Parameters
    ----------
    data : FieldData
    options : AdjustmentOptions, optional
    progress : callable, optional
        Called with one line per stage.
    initial : InitialValues, optional
        A warm start (e.g. a previous adjustment of most of the same points) instead of step 1;
        its ``outliers`` start as suspects that are readmitted when they fit.
    initial_targets_m : (n, 3) array_like, optional
        Starting target coordinates [m] (adjusted targets only); the survey stays the observation.

    Returns
    -------
    FieldResult

    Raises
    ------
    InputError, GeometryError
        Bad input (what and where), or geometry that cannot calibrate (with a diagnosis).
    """
    o = options or AdjustmentOptions()
    if o.method not in ("lmqn", "lm"):
        raise InputError(f"method must be 'lmqn' or 'lm', got {o.method!r}", "adjustment options")
    validate_field_data(data)
    if o.estimate is not None:
        bad = [p for p in o.estimate if p not in FIELD_PARAMS]
        if bad:
            raise InputError(f"estimate names {bad}, not in the field method's set {list(FIELD_PARAMS)}",
                             "adjustment options")
    full = tuple(p for p in FIELD_PARAMS if o.estimate is None or p in o.estimate)
    fixed = {p: "session" for p in FIELD_PARAMS if p not in full}
    init = initial if initial is not None else initial_values(data, full)
    if progress:
        progress(f"initial values: {init.how}; f {init.params[0]:.4f} mm; "
                 f"{init.outliers.sum()} points flagged by the robust initialisers")
    m = len(data.obs)
    obs_active = ~init.outliers
    reason = np.where(init.outliers, "initial outlier", "").astype(object)
    test = np.full(m, np.nan)
    survey_active = np.ones(len(data.targets), bool)
    solver = _Solver(data, o, init, progress)
    if initial_targets_m is not None and o.targets_adjusted:
        solver.X = np.array(initial_targets_m, float).reshape(-1, 3)
    estimate = list(full)

    def solve_clean(label):
        for rnd in range(o.max_rounds):
            _drop_undetermined_targets(data, obs_active, survey_active, reason)
            model, result = solver.run(estimate, obs_active, survey_active, f"{label} {rnd + 1}")
            if len(solver.rounds) == 1:       # the very first solve: can this network determine f?
                _check_f_determinable(model, result, o)
            n = _gross_rejection(solver, model, result, obs_active, survey_active, reason, o)
            if n == 0:
                n = _snooping(model, result, obs_active, survey_active, reason, test, o)
            # readmit initial outliers that now fit (they were only suspects)
            res = solver.residuals_all()
            s = data.obs.sigma_px * max(result.sigma0, 1.0)
            fits = (reason == "initial outlier") & (np.hypot(res[:, 0], res[:, 1]) < 3.0 * s)
            obs_active[fits] = True
            reason[fits] = ""
            # a target whose rejected image points agree with each other: its survey is wrong
            if o.targets_adjusted:
                n += _blame_the_survey(solver, obs_active, survey_active, reason, max(result.sigma0, 1.0))
            if n == 0 and not fits.any():
                return model, result
        return model, result

    try:
        model, result = solve_clean("adjustment")
        while o.estimate is None:
            pick = _select_parameter(model, result, estimate, o)
            if pick is None:
                break
            name, why = pick
            fixed[name] = why
            estimate.remove(name)
            solver.params[INDEX[name]] = 0.0
            if progress:
                progress(f"holding {name} fixed at 0: {why}")
            model, result = solve_clean("re-adjustment")
        try:
            cov, s, corr = _interior_stats(model, result)
        except SingularSystemError as err:
            raise GeometryError(f"the interior orientation is not determined: {err}") from None
        _check_core_determined(model, result, corr, s, o)
    except SingularSystemError as err:
        raise GeometryError(_singular_diagnosis(err, solver.model)) from None
    # everything not used: reason 'initial outlier' left -> it is a blunder
    reason[(reason == "initial outlier")] = "blunder"
    params, R, C, X = model.unpack(result.x)
    ne = result.jac.normal_equations()
    n_int = model.n_int
    ext_var = np.diag(cov)[n_int:].reshape(-1, 6)
    sigma_C = np.sqrt(ext_var[:, 3:])
    sigma_X = None
    if o.targets_adjusted:
        sigma_X = np.full((len(data.targets), 3), np.nan)    # NaN: not adjusted (no image sees it)
        sigma_X[model.target_index] = np.sqrt(np.einsum("kii->ki", ne.covariance_elim_blocks())) * result.sigma0
    sigma = {n: float(s[j]) for j, n in enumerate(estimate)}
    survey_res = (data.targets.xyz_m - solver.X) * 1000.0
    return FieldResult(
        data=data, options=o, params=params, estimate=tuple(estimate), fixed_parameters=fixed,
        sigma=sigma, sigma0=result.sigma0, covariance=cov, covariance_names=model.column_names()[: model.n_reduced],
        correlation_interior=corr, R_world_to_camera=R, center_m=C, sigma_center_m=sigma_C,
        targets_m=solver.X, sigma_targets_m=sigma_X, residual_px=solver.residuals_all(),
        obs_used=obs_active.copy(), obs_reason=np.array([str(r) for r in reason]), obs_test=test,
        survey_used=survey_active.copy(), survey_residual_mm=survey_res, lsq=result,
        iterations_total=solver.iterations, initial=init, rounds=solver.rounds)

