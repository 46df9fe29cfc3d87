"""The rig adjustment: every head's interior orientation, each head's relative orientation to
the reference head, one rig pose per exposure and the targets, in one least-squares problem.

Unknowns (the layout of the parameter vector ``x``)::

    x = [ interior of head 0 .. head H-1   (each head its own estimated subset)    sum n_int_h
          relative orientation of every head but the reference:  b (3), t (3) [m]   6 (H - 1)
          rig pose of every exposure in use:  a (3), C_rig (3) [m]                 6 n_exposures
          targets: per adjusted target  X (3) [m]                                  3 n_adjusted ]

with ``R_camera_to_rig = exp([b]x) R0_camera_to_rig`` (a small rotation about the rig frame's
axes, the one ``sigma_rotation_arcsec`` of the rig document describes) and
``R_world_to_rig = exp([a]x) R0_world_to_rig``; the references are rebased between solves.
A head's exterior orientation is the rig pose composed with its relative orientation
(:func:`fieldcal.rig.poses.head_pose`)::

    R_world_to_camera = R_camera_to_rig^T R_world_to_rig,   C = C_rig + R_world_to_rig^T t

Residuals are those of the single camera (:mod:`fieldcal.field.bundle`): image-space pixels
divided by their sigma, and the surveyed coordinates of the adjusted targets. They and their
derivatives with respect to each image's own exterior orientation (a left rotation increment
``w`` and the centre) come from one :class:`~fieldcal.field.bundle.BundleModel` per head
(the compiled kernel), evaluated with every image's reference rotation set to its current
exterior orientation (``w = 0``). The chain rule to the rig's unknowns, with left
perturbations ``delta = J_l(a) da`` of ``R_world_to_rig`` and ``eps = J_l(b) db`` of
``R_camera_to_rig``::

    w = R_camera_to_rig^T (delta - eps)
    dC = dC_rig + R_world_to_rig^T [t]x delta + R_world_to_rig^T dt

so ``dr/da = (dr/dw R_cr^T + dr/dC R_wr^T [t]x) J_l(a)``, ``dr/dC_rig = dr/dC``,
``dr/db = -dr/dw R_cr^T J_l(b)``, ``dr/dt = dr/dC R_wr^T``: the Jacobian is exact. The
problem goes to the project's LMQN engine (:func:`fieldcal.solver.lsq.solve`) as a
block-sparse Jacobian with the targets eliminated (3 x 3 blocks, Schur complement), as the
single camera's does: interiors, relative orientations and rig poses are the dense part.

Procedure
---------
1. Initial values: each head calibrated alone (:func:`fieldcal.field.adjustment.adjust_field`
   on its images with at least :data:`MIN_SOLO_POINTS` points), with its own automatic parameter
   selection (or the session's ``estimate``); the relative orientation is the median
   (:func:`fieldcal.rig.poses.median_relative_pose`) over the exposures where the head and the
   reference were both oriented; each exposure's rig pose from its reference image, else
   from the first head that oriented it.
2. The rig adjustment from there, over every image point of every exposure in use (an
   exposure with at least :data:`MIN_EXPOSURE_POINTS` points over all heads): an image in
   which its head saw too few targets to be oriented alone still enters, through the rig
   pose the other heads determine.
3. Blunders, as the single camera's (:mod:`fieldcal.field.adjustment`, step 3): points whose
   normalised residual exceeds ``robust_k`` robust sigmas are rejected; when none is, data
   snooping on every head's image points (``T = v^T Q_vv^-1 v / sigma0^2`` from the rig's normal
   equations, :func:`~fieldcal.field.adjustment.snooping_statistic`) rejects the clearly worst
   above the chi-square quantile of ``snoop_alpha``; the adjustment is repeated until nothing is.
3b. Variance components (``variance_components``, with adjusted targets, as the single camera's
   step 4b): at a clean solution every head's image floor ``phi_h`` is estimated from its points'
   residuals and redundancy numbers (:func:`fieldcal.field.variance_components.image_floor_px`),
   its points re-weighted with ``sqrt(sigma^2 + phi_h^2)`` and the adjustment repeated (warm)
   until no weight moves by more than :data:`~fieldcal.field.variance_components.WEIGHT_TOLERANCE`.
   ``stats.variance_components`` records per head the floor and the image factor (the
   a-posteriori over the session's a-priori sigmas, :func:`~fieldcal.field.variance_components.group_factor`
   of the residuals in the session's sigmas over the head's redundancy): a head whose points are
   3x noisier than stated has a factor near 3 and no longer pulls the others with a weight it
   does not deserve. ``stats.sigma0`` is the last solve's, in the re-weighted sigmas.
4. The covariance (a-posteriori, scaled by ``sigma0^2``) of interiors, relative orientations
   and rig poses from the normal equations at the solution, its reference rotations rebased
   so that the rotation increments are the rig-frame small rotations.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.adjustment import (
    UNPLACED,
    AdjustmentOptions,
    FieldResult,
    adjust_field,
    snooped,
    snooping_statistic,
    unsurveyed_account,
)
from fieldcal.field.bundle import BundleModel
from fieldcal.field.datum import MIN_CONTROL_POINTS
from fieldcal.field.variance_components import (
    MIN_GROUP_REDUNDANCY,
    WEIGHT_TOLERANCE,
    group_factor,
    image_floor_px,
    weight_change,
)
from fieldcal.model.camera import FIELD_PARAMS
from fieldcal.model.rotations import R_from_rotvec, left_jacobian_so3, skew
from fieldcal.rig.data import RigData
from fieldcal.rig.poses import head_pose, median_relative_pose, relative_pose, rig_pose_from_head
from fieldcal.robust import robust_sigma
from fieldcal.solver.blocksparse import BlockSparseJacobian, ResidualBlock, SingularSystemError
from fieldcal.solver.lsq import LsqResult, solve

__all__ = ["RigOptions", "RigResult", "RigProblem", "adjust_rig", "initial_rig", "RigStart",
           "MIN_SOLO_POINTS", "MIN_EXPOSURE_POINTS", "ARCSEC_PER_RAD"]

MIN_SOLO_POINTS = 6
"""An image enters its head's own calibration (the initial values) with at least this many points."""
MAX_COMPONENT_ROUNDS = 4
"""At most this many re-weightings by the variance components (as the single camera's)."""
MIN_EXPOSURE_POINTS = 6
"""An exposure enters the rig adjustment with at least this many points over all its heads."""
ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi
LEFT_OUT = "exposure left out"
"""The reason of the points of an exposure the rig adjustment could not use."""


@dataclass
class RigOptions:
    """Settings of :func:`adjust_rig`.

    Attributes
    ----------
    targets_adjusted : bool
        Surveyed coordinates as weighted observations (default) or held fixed.
    estimate : tuple of str or None
        Interior parameters of every head; ``None``: each head's own automatic selection
        (its calibration alone, :mod:`fieldcal.field.adjustment` step 4).
    method, max_iter, tau, eps2, ftol, sigma_tol
        Of :func:`fieldcal.solver.lsq.solve` (as :class:`~fieldcal.field.adjustment.AdjustmentOptions`).
    robust_k : float
        Rejection threshold in robust sigmas of the normalised residual norm.
    snoop_alpha : float
        Significance level of data snooping (per image point).
    variance_components : bool
        Estimate every head's image floor and re-weight (module docstring, step 3b).
    max_rounds : int
        At most this many rounds of rejection and re-weighting.
    """

    targets_adjusted: bool = True
    estimate: tuple[str, ...] | None = None
    method: str = "lmqn"
    max_iter: int = 500
    tau: float = 1e-6
    eps2: float = 1e-10
    ftol: float = 1e-12
    sigma_tol: float = 1e-3
    robust_k: float = 8.0
    snoop_alpha: float = 1e-6
    variance_components: bool = True
    max_rounds: int = 14

    def to_dict(self) -> dict:
        return {"targets_adjusted": self.targets_adjusted,
                "estimate": list(self.estimate) if self.estimate is not None else None,
                "method": self.method, "max_iter": self.max_iter, "tau": self.tau, "eps2": self.eps2,
                "ftol": self.ftol, "sigma_tol": self.sigma_tol, "robust_k": self.robust_k,
                "snoop_alpha": self.snoop_alpha, "variance_components": self.variance_components,
                "max_rounds": self.max_rounds}

    def head_options(self) -> AdjustmentOptions:
        """The options of a head's calibration alone (the initial values)."""
        return AdjustmentOptions(targets_adjusted=self.targets_adjusted, estimate=self.estimate,
                                 method=self.method)


@dataclass
class RigStart:
    """The state the rig adjustment starts from (or ended at), in the data's world frame.

    Attributes
    ----------
    params : list of (13,) ndarray
        Per head, the camera parameters.
    estimate : list of tuple of str
        Per head, the estimated interior parameters.
    fixed_parameters : list of dict
        Per head, the parameters held and why (as ``stats.fixed_parameters``).
    R_camera_to_rig : (n_heads, 3, 3) ndarray
    t_camera_in_rig_m : (n_heads, 3) ndarray
    R_world_to_rig : (n_exposures, 3, 3) ndarray
    C_rig_m : (n_exposures, 3) ndarray
        Rig poses (NaN for an exposure no head oriented).
    targets_m : (n_targets, 3) ndarray
    solo : list of FieldResult
        Per head, its calibration alone.
    """

    params: list
    estimate: list
    fixed_parameters: list
    R_camera_to_rig: np.ndarray
    t_camera_in_rig_m: np.ndarray
    R_world_to_rig: np.ndarray
    C_rig_m: np.ndarray
    targets_m: np.ndarray
    solo: list = field(default_factory=list)


@dataclass
class RigResult:
    """Everything the rig adjustment produced.

    Attributes
    ----------
    state : RigStart
        The adjusted values (``solo``: each head's calibration alone, the initial values).
    sigma : list of dict
        Per head, the a-posteriori sigma of each estimated interior parameter.
    sigma_rotation_arcsec, sigma_t_mm : (n_heads, 3) ndarray
        Sigmas of each head's relative orientation (0 for the reference).
    covariance : (n, n) ndarray
        A-posteriori covariance of interiors, relative orientations and rig poses, in the order
        of ``covariance_names`` (rotations in rad, lengths in m).
    residual_px : list of (m_h, 2) ndarray
        Per head, measured minus predicted pixels of every observation (NaN: not evaluated).
    obs_used : list of (m_h,) bool ndarray
    obs_reason : list of (m_h,) str ndarray
    exposure_used : (n_exposures,) bool ndarray
    """

    data: RigData
    options: RigOptions
    state: RigStart
    sigma: list
    sigma0: float
    sigma_rotation_arcsec: np.ndarray
    sigma_t_mm: np.ndarray
    covariance: np.ndarray
    covariance_names: list
    residual_px: list
    obs_used: list
    obs_reason: list
    exposure_used: np.ndarray
    lsq: LsqResult
    iterations_total: int
    rounds: list = field(default_factory=list)
    variance_components: dict = field(default_factory=dict)
    sigma_targets_m: np.ndarray | None = None

    def relative_names(self) -> list[str]:
        """Names of the relative-orientation parameters, as in ``covariance_names``."""
        return [n for n in self.covariance_names if n.split(":")[-1] in _REL_COMPONENTS]

    def relative_covariance(self) -> np.ndarray:
        """The covariance of the relative orientations alone (rotation [rad], lever arm [m])."""
        names = self.covariance_names
        k = [names.index(n) for n in self.relative_names()]
        return self.covariance[np.ix_(k, k)]

    def head_stats(self, h: int) -> dict:
        """Residual statistics of head ``h`` in the rig (as the calibration document's)."""
        used = self.obs_used[h]
        du = self.residual_px[h][used]
        norm = np.hypot(du[:, 0], du[:, 1])
        return {"n_images": int(len(np.unique(self.data.head_data[h].obs.image[used]))),
                "n_observations": int(used.sum()), "n_rejected": int((self.obs_reason[h] == "blunder").sum()),
                "rmse_px": float(np.sqrt(np.mean(norm**2))) if len(norm) else None,
                "max_px": float(norm.max()) if len(norm) else None}

    def stats(self) -> dict:
        """The rig document's ``stats``."""
        n_img = sum(self.head_stats(h)["n_images"] for h in range(self.data.n_heads))
        return {"n_exposures": int(self.exposure_used.sum()), "n_images": n_img,
                "n_observations": int(sum(u.sum() for u in self.obs_used)),
                "n_rejected": int(sum((r == "blunder").sum() for r in self.obs_reason)),
                "sigma0": float(self.sigma0), "iterations": int(self.lsq.iterations),
                "iterations_total": int(self.iterations_total), "solver": self.options.method,
                "targets_adjusted": bool(self.options.targets_adjusted),
                "variance_components": self.variance_components, **self.unsurveyed_stats(),
                "heads": {hd.camera_id: self.head_stats(h) for h, hd in enumerate(self.data.heads)}}

    def unsurveyed_stats(self, h: int | None = None) -> dict:
        """The account of the unsurveyed targets (as the single camera's
        :meth:`~fieldcal.field.adjustment.FieldResult.unsurveyed_stats`) over every head's points in
        use, or head ``h``'s: how many were estimated, the ids targets.csv does not list, each one's
        adjusted coordinates and sigmas (``{}`` when every target is surveyed)."""
        heads = range(self.data.n_heads) if h is None else [h]
        observed = np.concatenate([self.data.head_data[g].obs.target[self.obs_used[g]] for g in heads])
        return unsurveyed_account(self.data.targets, observed, self.data.meta.get("unlisted_targets", []),
                                  self.state.targets_m, self.sigma_targets_m)


_REL_COMPONENTS = ("rot_x", "rot_y", "rot_z", "t_x_m", "t_y_m", "t_z_m")


# ---------------------------------------------------------------------------- initial values
def initial_rig(data: RigData, options: RigOptions | None = None, *,
                progress: Callable[[str], None] | None = None) -> RigStart:
    """Step 1 of the module docstring: every head alone, then the median relative poses."""
    o = options or RigOptions()
    n_e = len(data.exposures)
    solo, R_img, C_img = [], [], []
    for h, d in enumerate(data.head_data):
        counts = np.bincount(d.obs.image, minlength=len(d.images))
        keep_img = np.flatnonzero(counts >= MIN_SOLO_POINTS)
        local = np.full(len(d.images), -1, np.int64)
        local[keep_img] = np.arange(len(keep_img))
        k = local[d.obs.image] >= 0
        o_sub = d.obs.take(k)
        o_sub.image = local[o_sub.image]
        sub = type(d)(sensor=d.sensor, targets=d.targets, images=[d.images[i] for i in keep_img], obs=o_sub,
                      nominal_focal_mm=d.nominal_focal_mm, default_sigma_px=d.default_sigma_px, meta=d.meta)
        try:
            res = adjust_field(sub, o.head_options())
        except GeometryError as err:
            raise GeometryError(f"camera {data.heads[h].camera_id!r} cannot be calibrated alone for the rig's "
                                f"initial values: {err}") from None
        if res.datum.get("type") == "free network":
            raise GeometryError(f"camera {data.heads[h].camera_id!r} alone sees too few surveyed targets to be "
                                "placed in the survey's frame for the rig's initial values (its calibration alone is "
                                "a free network)")
        if progress:
            progress(f"{data.heads[h].camera_id}: alone, rmse {res.stats()['rmse_px']:.3f} px, "
                     f"{len(keep_img)} of {len(d.images)} images")
        R = np.full((n_e, 3, 3), np.nan)
        C = np.full((n_e, 3), np.nan)
        e = data.image_exposure[h][keep_img]
        R[e], C[e] = res.R_world_to_camera, res.center_m
        solo.append(res)
        R_img.append(R)
        C_img.append(C)
    return _start_from_solo(data, solo, np.stack(R_img), np.stack(C_img))


def _start_from_solo(data: RigData, solo, R_img, C_img) -> RigStart:
    """Relative orientations (medians) and rig poses from every head's own exterior orientations
    ``R_img`` (n_heads, n_exposures, 3, 3), ``C_img`` (n_heads, n_exposures, 3) (NaN: not oriented)."""
    ref = data.reference
    n_h, n_e = R_img.shape[:2]
    R_cr = np.tile(np.eye(3), (n_h, 1, 1))
    t = np.zeros((n_h, 3))
    oriented = np.isfinite(C_img).all(axis=2)
    for h in range(n_h):
        if h == ref:
            continue
        both = oriented[h] & oriented[ref]
        if not both.any():
            raise GeometryError(f"camera {data.heads[h].camera_id!r} shares no exposure with the reference "
                                f"{data.heads[ref].camera_id!r} in which both were oriented: its relative "
                                "orientation has no initial value")
        Rs, ts = relative_pose(R_img[ref, both], C_img[ref, both], R_img[h, both], C_img[h, both])
        R_cr[h], t[h] = median_relative_pose(Rs, ts)
    R_wr = np.full((n_e, 3, 3), np.nan)
    C_r = np.full((n_e, 3), np.nan)
    for h in [ref] + [h for h in range(n_h) if h != ref]:
        todo = oriented[h] & ~np.isfinite(C_r).all(axis=1)
        if todo.any():
            R_wr[todo], C_r[todo] = rig_pose_from_head(R_img[h, todo], C_img[h, todo], R_cr[h], t[h])
    X = solo[ref].targets_m.copy()
    for h in range(n_h):            # unsurveyed targets: placed by the reference, else by the first head that did
        todo = ~np.isfinite(X).all(axis=1)
        X[todo] = solo[h].targets_m[todo]
    return RigStart(params=[s.params.copy() for s in solo], estimate=[tuple(s.estimate) for s in solo],
                    fixed_parameters=[dict(s.fixed_parameters) for s in solo], R_camera_to_rig=R_cr,
                    t_camera_in_rig_m=t, R_world_to_rig=R_wr, C_rig_m=C_r, targets_m=X, solo=list(solo))


# ---------------------------------------------------------------------------- the LSQ problem
class RigProblem:
    """The rig model as a problem for :func:`fieldcal.solver.lsq.solve` (module docstring).

    Parameters
    ----------
    data : RigData
    start : RigStart
        Values of everything; the interior parameters not estimated stay at these.
    obs_active : list of (m_h,) bool ndarray
        Per head, the image points in use.
    exposure_used : (n_exposures,) bool ndarray
        The exposures whose rig pose is an unknown (points of the others must not be active).
    targets_adjusted : bool
    """

    def __init__(self, data: RigData, start: RigStart, obs_active, exposure_used, *, targets_adjusted=True):
        self.data, self.start = data, start
        self.targets_adjusted = bool(targets_adjusted)
        self.R_cr0 = start.R_camera_to_rig.copy()
        self.R_wr0 = start.R_world_to_rig.copy()
        self.exposure_used = np.asarray(exposure_used, bool)
        n_h = data.n_heads
        self.exp_slot = np.full(len(data.exposures), -1, np.int64)
        self.exp_slot[self.exposure_used] = np.arange(self.exposure_used.sum())
        self.n_exp = int(self.exposure_used.sum())
        self.int_off = np.concatenate([[0], np.cumsum([len(e) for e in start.estimate])]).astype(np.int64)
        self.rel_heads = [h for h in range(n_h) if h != data.reference]
        self.rel_off = {h: int(self.int_off[-1]) + 6 * j for j, h in enumerate(self.rel_heads)}
        self.rig_off = int(self.int_off[-1]) + 6 * len(self.rel_heads)
        self.n_reduced = self.rig_off + 6 * self.n_exp
        self.models = [BundleModel(d, start.params[h], start.estimate[h], np.tile(np.eye(3), (len(d.images), 1, 1)),
                                   targets_adjusted=self.targets_adjusted, obs_active=obs_active[h],
                                   survey_active=np.zeros(len(d.targets), bool))
                       for h, d in enumerate(data.head_data)]
        seen = np.unique(np.concatenate([m.tgt for m in self.models])) if self.targets_adjusted else np.zeros(0, int)
        self.target_index = seen
        n_t = len(data.targets)
        self.t_slot = np.full(n_t, -1, np.int64)
        self.t_slot[seen] = np.arange(len(seen))
        self.n_params = self.n_reduced + 3 * len(seen)
        self.X_base = start.targets_m.copy()
        self.sigma_m = data.targets.sigma_mm / 1000.0
        self.survey_k = seen[data.targets.surveyed[seen]]          # unsurveyed targets: no survey row
        self.row_off = np.concatenate([[0], np.cumsum([m.n_rows_image for m in self.models])]).astype(np.int64)
        self.n_rows_image = int(self.row_off[-1])
        self.n_rows = self.n_rows_image + 3 * len(self.survey_k)
        self._templates = None
        self._structure = None

    # ------------------------------------------------------------------ packing
    def pack(self, state: RigStart) -> np.ndarray:
        """The parameter vector of ``state`` (rotation increments 0 about this problem's references,
        which must be ``state``'s rotations)."""
        x = np.zeros(self.n_params)
        for h, m in enumerate(self.models):
            x[self.int_off[h]:self.int_off[h + 1]] = np.asarray(state.params[h])[m.int_index]
        for h in self.rel_heads:
            x[self.rel_off[h] + 3:self.rel_off[h] + 6] = state.t_camera_in_rig_m[h]
        ext = x[self.rig_off:self.n_reduced].reshape(-1, 6)
        ext[:, 3:] = state.C_rig_m[self.exposure_used]
        if self.targets_adjusted:
            x[self.n_reduced:] = state.targets_m[self.target_index].ravel()
        return x

    def unpack(self, x) -> RigStart:
        """The state of ``x`` (rotations with their increments applied)."""
        x = np.asarray(x, float)
        s = self.start
        params = []
        for h, m in enumerate(self.models):
            p = np.asarray(s.params[h], float).copy()
            p[m.int_index] = x[self.int_off[h]:self.int_off[h + 1]]
            params.append(p)
        R_cr, t = self.R_cr0.copy(), s.t_camera_in_rig_m.copy()
        for h in self.rel_heads:
            b = x[self.rel_off[h]:self.rel_off[h] + 6]
            R_cr[h] = R_from_rotvec(b[:3]) @ self.R_cr0[h]
            t[h] = b[3:]
        R_wr, C_r = self.R_wr0.copy(), s.C_rig_m.copy()
        ext = x[self.rig_off:self.n_reduced].reshape(-1, 6)
        R_wr[self.exposure_used] = R_from_rotvec(ext[:, :3]) @ self.R_wr0[self.exposure_used]
        C_r[self.exposure_used] = ext[:, 3:]
        X = self.X_base.copy()
        if self.targets_adjusted:
            X[self.target_index] = x[self.n_reduced:].reshape(-1, 3)
        return RigStart(params, list(s.estimate), list(s.fixed_parameters), R_cr, t, R_wr, C_r, X, s.solo)

    def rebase(self, x) -> np.ndarray:
        """Fold the rotation increments of ``x`` into the references; the equivalent ``x``."""
        st = self.unpack(x)
        self.R_cr0, self.R_wr0 = st.R_camera_to_rig.copy(), st.R_world_to_rig.copy()
        x = np.array(x, float)
        for h in self.rel_heads:
            x[self.rel_off[h]:self.rel_off[h] + 3] = 0.0
        x[self.rig_off:self.n_reduced].reshape(-1, 6)[:, :3] = 0.0
        return x

    def column_names(self) -> list[str]:
        """Names of the dense columns (interiors, relative orientations, rig poses)."""
        names = []
        for h, hd in enumerate(self.data.heads):
            names += [f"{hd.camera_id}:{p}" for p in self.start.estimate[h]]
        for h in self.rel_heads:
            names += [f"{self.data.heads[h].camera_id}:{c}" for c in _REL_COMPONENTS]
        for e in np.flatnonzero(self.exposure_used):
            names += [f"{self.data.exposures[e]}:{c}" for c in ("rig_w_x", "rig_w_y", "rig_w_z", "X_m", "Y_m", "Z_m")]
        return names

    # ------------------------------------------------------------------ model
    def _head_blocks(self, h, x, st: RigStart, jacobian: bool):
        """Weighted residuals of head ``h`` and its Jacobian parts (module docstring)."""
        m = self.models[h]
        e_img = self.data.image_exposure[h]
        slot = self.exp_slot[e_img]
        ok = slot >= 0
        R_wr = np.where(ok[:, None, None], st.R_world_to_rig[np.where(ok, e_img, 0)], np.eye(3))
        C_r = np.where(ok[:, None], st.C_rig_m[np.where(ok, e_img, 0)], 0.0)
        R_wc, C_c = head_pose(R_wr, C_r, st.R_camera_to_rig[h], st.t_camera_in_rig_m[h])
        m.R0 = R_wc
        xh = m.pack(st.params[h], C_c, st.targets_m)
        r, jb, _ = m.residuals_and_blocks(xh, jacobian)
        if not jacobian:
            return r, None
        ext = x[self.rig_off:self.n_reduced].reshape(-1, 6)
        Jl_a = left_jacobian_so3(ext[np.maximum(slot, 0), :3])                   # (n_img, 3, 3)
        R_crT = st.R_camera_to_rig[h].T
        tx = skew(st.t_camera_in_rig_m[h])
        A_w = R_crT @ Jl_a                                                      # dw/da per image
        A_c = np.swapaxes(R_wr, 1, 2) @ tx @ Jl_a                               # dC/da per image
        img = m.img
        d_w, d_C = jb.d_ext[:, :, :3], jb.d_ext[:, :, 3:]
        d_rig = np.empty((len(img), 2, 6))
        d_rig[:, :, :3] = np.einsum("kra,kab->krb", d_w, A_w[img]) + np.einsum("kra,kab->krb", d_C, A_c[img])
        d_rig[:, :, 3:] = d_C
        parts = [(self.int_off[h] + np.arange(m.n_int), jb.d_int),
                 (self.rig_off + 6 * slot[img][:, None] + np.arange(6), d_rig)]
        if h != self.data.reference:
            b = x[self.rel_off[h]:self.rel_off[h] + 3]
            d_rel = np.empty((len(img), 2, 6))
            d_rel[:, :, :3] = -np.einsum("kra,ab->krb", d_w, R_crT @ left_jacobian_so3(b))
            d_rel[:, :, 3:] = np.einsum("kra,kba->krb", d_C, R_wr[img])        # dr/dC R_wr^T
            parts.append((self.rel_off[h] + np.arange(6), d_rel))
        if self.targets_adjusted:
            parts.append((self.n_reduced + 3 * self.t_slot[m.tgt][:, None] + np.arange(3), jb.d_tgt))
        return r, parts

    def evaluate(self, x, jacobian: bool):
        """``(r, J)`` at ``x``: image rows head by head (u, v per point), then the surveys."""
        x = np.asarray(x, float)
        st = self.unpack(x)
        rs, all_parts = [], []
        for h in range(self.data.n_heads):
            r, parts = self._head_blocks(h, x, st, jacobian)
            rs.append(r[: self.models[h].n_rows_image])
            all_parts.append(parts)
        if self.targets_adjusted and len(self.survey_k):
            t = self.survey_k
            X = x[self.n_reduced:].reshape(-1, 3)
            rs.append(((X[self.t_slot[t]] - self.data.targets.xyz_m[t]) / self.sigma_m[t, None]).ravel())
        r = np.concatenate(rs)
        if not jacobian:
            return r, None
        return r, self._jacobian(all_parts)

    def _jacobian(self, all_parts) -> BlockSparseJacobian:
        if self._templates is None:
            blocks = []
            for h, parts in enumerate(all_parts):
                k = len(self.models[h].img)
                if k:
                    rows = self.row_off[h] + np.arange(2 * k).reshape(k, 2)
                    blocks.append(ResidualBlock.from_parts(rows, parts))
            if self.targets_adjusted and len(self.survey_k):
                ns = len(self.survey_k)
                rows = self.n_rows_image + np.arange(3 * ns).reshape(ns, 3)
                cols = self.n_reduced + 3 * self.t_slot[self.survey_k][:, None] + np.arange(3)
                blocks.append(ResidualBlock.from_parts(rows, [(cols, self._survey_values())]))
            self._templates = blocks
        else:
            it = iter(self._templates)
            blocks = [next(it).with_values(*[p[1] for p in parts])
                      for h, parts in enumerate(all_parts) if len(self.models[h].img)]
            blocks += [blk.with_values(self._survey_values()) for blk in it]
        n_dense = self.n_reduced if self.targets_adjusted else self.n_params
        J = BlockSparseJacobian(self.n_rows, self.n_params, n_dense, 3, blocks, structure=self._structure)
        self._structure = J.structure
        return J

    def _survey_values(self):
        return (1.0 / self.sigma_m[self.survey_k])[:, None, None] * np.eye(3)[None]

    def residuals_px(self, state: RigStart) -> list[np.ndarray]:
        """Per head, measured minus predicted pixels (m_h, 2) of every observation at ``state``
        (NaN for points of exposures not in use)."""
        from fieldcal.field.bundle import image_residuals

        out = []
        for h, d in enumerate(self.data.head_data):
            e_img = self.data.image_exposure[h]
            ok = self.exp_slot[e_img] >= 0
            R_wr = np.where(ok[:, None, None], state.R_world_to_rig[np.where(ok, e_img, 0)], np.eye(3))
            C_r = np.where(ok[:, None], state.C_rig_m[np.where(ok, e_img, 0)], 0.0)
            R_wc, C_c = head_pose(R_wr, C_r, state.R_camera_to_rig[h], state.t_camera_in_rig_m[h])
            res = image_residuals(d, state.params[h], R_wc, C_c, state.targets_m)
            res[~ok[d.obs.image]] = np.nan
            out.append(res)
        return out


# ---------------------------------------------------------------------------- the procedure
def adjust_rig(data: RigData, options: RigOptions | None = None, *,
               progress: Callable[[str], None] | None = None, start: RigStart | None = None) -> RigResult:
    """Calibrate a rig from identified field observations (module docstring).

    Parameters
    ----------
    data : RigData
    options : RigOptions, optional
    progress : callable, optional
        Called with one line per stage.
    start : RigStart, optional
        Initial values instead of step 1 (e.g. from a previous rig calibration).

    Raises
    ------
    InputError, GeometryError
        Bad input, or a rig the observations cannot determine (with a diagnosis).
    """
    o = options or RigOptions()
    if o.method not in ("lmqn", "lm"):
        raise InputError(f"method must be 'lmqn' or 'lm', got {o.method!r}", "rig options")
    if o.estimate is not None and (bad := [p for p in o.estimate if p not in FIELD_PARAMS]):
        raise InputError(f"estimate names {bad}, not in the field method's set {list(FIELD_PARAMS)}", "rig options")
    _check_unsurveyed(data, o)
    _check_control(data, [np.ones(len(d.obs), bool) for d in data.head_data])
    start = start if start is not None else initial_rig(data, o, progress=progress)
    placed = np.isfinite(start.targets_m).all(axis=1)
    if not placed.all():            # unsurveyed targets no head placed alone: their points left out
        start = replace(start, targets_m=np.where(placed[:, None], start.targets_m, 0.0))
    oriented = np.isfinite(start.C_rig_m).all(axis=1)
    counts = np.zeros(len(data.exposures), np.int64)
    for h, d in enumerate(data.head_data):
        counts += np.bincount(data.image_exposure[h][d.obs.image], minlength=len(data.exposures))
    exposure_used = oriented & (counts >= MIN_EXPOSURE_POINTS)
    active, reason = [], []
    for h, d in enumerate(data.head_data):
        use = exposure_used[data.image_exposure[h][d.obs.image]]
        if start.solo:       # the head's own blunders start as rejected (readmitted when they fit)
            solo_bad = _solo_blunders(start.solo[h], d)
            use &= ~solo_bad
        active.append(use)
        reason.append(np.where(exposure_used[data.image_exposure[h][d.obs.image]], "", LEFT_OUT).astype(object))
        if start.solo:
            reason[h][solo_bad & (reason[h] == "")] = "blunder"
        lost = ~placed[d.obs.target] & (reason[h] == "")
        active[h] &= ~lost
        reason[h][lost] = UNPLACED
    _check_control(data, active)
    return _iterate(data, o, start, active, reason, exposure_used, progress)


def _check_unsurveyed(data: RigData, o: RigOptions) -> None:
    """Unsurveyed targets are unknowns: they cannot be held fixed (as for one camera)."""
    t = data.targets
    observed = np.unique(np.concatenate([d.obs.target for d in data.head_data]))
    uns = observed[~t.surveyed[observed]]
    if len(uns) and not o.targets_adjusted:
        raise InputError(f"{len(uns)} observed target(s) are unsurveyed (e.g. {str(t.ids[uns[0]])!r}); their "
                         "coordinates must be adjusted: targets cannot be held fixed", "targets")


def _check_control(data: RigData, active) -> None:
    """The datum: the surveyed targets the rig's points see, weighted control (at least
    :data:`~fieldcal.field.datum.MIN_CONTROL_POINTS`; a free network is the single camera's only)."""
    seen = np.unique(np.concatenate([d.obs.target[a] for d, a in zip(data.head_data, active, strict=True)]))
    n = int(data.targets.surveyed[seen].sum())
    if n < MIN_CONTROL_POINTS:
        raise GeometryError(f"the rig's points see {n} surveyed target(s): a rig needs at least "
                            f"{MIN_CONTROL_POINTS} as its datum (a free network is supported for single cameras only)")


def _solo_blunders(res: FieldResult, d) -> np.ndarray:
    """(m,) bool: points of ``d`` that the head's calibration alone rejected as blunders (its data
    are ``d`` without the images it could not orient alone: matched by image name and target)."""
    files = {im.file: i for i, im in enumerate(d.images)}
    sub = res.data
    to_d = np.array([files[im.file] for im in sub.images], np.int64)
    n_t = len(d.targets)
    k = np.flatnonzero(res.obs_reason == "blunder")
    bad_keys = to_d[sub.obs.image[k]] * n_t + sub.obs.target[k]
    return np.isin(d.obs.image * n_t + d.obs.target, bad_keys)


def _iterate(data, o: RigOptions, start, active, reason, exposure_used, progress) -> RigResult:
    """Solve, reject, readmit, re-weight until nothing changes (module docstring, steps 2-3b)."""
    state, tau, total, rounds = start, o.tau, 0, []
    floors, factor = np.zeros(data.n_heads), 1.0
    vc = {"rounds": 0}
    weighted = data
    for rnd in range(o.max_rounds):
        problem = RigProblem(weighted, state, active, exposure_used, targets_adjusted=o.targets_adjusted)
        x0 = problem.pack(state)
        try:
            result = solve(problem, x0, method=o.method, max_iter=o.max_iter, tau=tau, eps2=o.eps2,
                           ftol=o.ftol, sigma_tol=o.sigma_tol)
        except SingularSystemError as err:
            raise GeometryError(f"the rig adjustment is singular: {err}") from None
        except InputError as err:
            raise GeometryError(f"the rig adjustment diverged ({err.reason})") from None
        total += result.iterations
        if np.isfinite(result.mu) and result.mu > 0:
            tau = min(tau, result.mu)
        state = problem.unpack(result.x)
        rounds.append({"round": rnd + 1, "iterations": result.iterations, "sigma0": result.sigma0,
                       "status": result.message})
        if progress:
            progress(f"rig adjustment {rnd + 1}: {result.iterations} iterations, sigma0 {result.sigma0:.3f}")
        res_px = problem.residuals_px(state)
        if _reject(weighted, res_px, active, reason, o, max(result.sigma0, 1.0)):
            continue
        redundancy = _snoop(problem, result, active, reason, o)
        if redundancy is None:
            continue
        new = _components(data, problem, result, res_px, redundancy, floors, factor, vc, o)
        if new is None:
            break
        floors, factor = new
        weighted = _reweighted(data, floors, factor)
        vc["rounds"] += 1
        if progress:
            progress("re-weighting the heads' image points: floors "
                     + ", ".join(f"{hd.camera_id} {f:.3f} px" for hd, f in zip(data.heads, floors, strict=True))
                     + f"; survey sigmas x {factor:.3g}")
    out = _result(data, o, problem, result, state, res_px, active, reason, exposure_used, total, rounds)
    out.variance_components = vc
    return out


def _reject(data, res_px, active, reason, o: RigOptions, sigma0) -> bool:
    """Reject points beyond ``robust_k`` robust sigmas, readmit suspects within 3 sigma; whether
    anything changed."""
    norms = [np.hypot(*(r / d.obs.sigma_px[:, None]).T) for r, d in zip(res_px, data.head_data, strict=True)]
    used = np.concatenate([n[a] for n, a in zip(norms, active, strict=True)])
    s = float(robust_sigma(used / np.sqrt(2.0))) * np.sqrt(2.0) if len(used) else 1.0
    changed = False
    for n, a, why in zip(norms, active, reason, strict=True):
        bad = a & (n > o.robust_k * max(s, 1e-12))
        back = (~a) & (why == "blunder") & (n < 3.0 * sigma0)
        a[bad], why[bad] = False, "blunder"
        a[back], why[back] = True, ""
        changed |= bool(bad.any() or back.any())
    return changed


def _snoop(problem: RigProblem, result, active, reason, o: RigOptions):
    """Data snooping over every head's points (module docstring, step 3): rejects the clearly worst
    beyond the chi-square limit; None when it did, else per head the points' redundancies (m_h,)
    (NaN for points not in use)."""
    ne = result.jac.normal_equations()
    sigma0 = max(result.sigma0, 1e-12)
    T, red, b = [], [], 0
    for h, m in enumerate(problem.models):
        r = result.r[problem.row_off[h]:problem.row_off[h + 1]].reshape(-1, 2)
        if len(m.img):
            t, rho = snooping_statistic(ne.group_covariance(b), r, sigma0)
            b += 1
        else:
            t, rho = np.zeros(0), np.zeros(0)
        T.append(t)
        red.append(rho)
    worst = np.split(snooped(np.concatenate(T), o.snoop_alpha), np.cumsum([len(t) for t in T])[:-1])
    out = []
    for h, m in enumerate(problem.models):
        k = m.k[worst[h]]
        active[h][k], reason[h][k] = False, "blunder"
        rho = np.full(len(active[h]), np.nan)
        rho[m.k] = red[h]
        out.append(rho)
    red_sur = np.zeros(0)
    if problem.targets_adjusted and len(problem.survey_k):     # the survey block follows the heads'
        red_sur = np.einsum("kii->k", np.eye(3) - ne.group_covariance(b))
    return None if any(w.any() for w in worst) else (out, red_sur)


def _components(data, problem: RigProblem, result, res_px, redundancy, floors, survey_factor: float, vc: dict,
                o: RigOptions):
    """Every head's image floor and factor and the survey factor at a clean solution (step 3b)
    into ``vc``; ``(floors, survey factor)`` when some weight moved by more than the tolerance
    (solve again), else None."""
    if not (o.variance_components and o.targets_adjusted):
        return None
    redundancy, red_sur = redundancy
    new = floors.copy()
    heads, change = {}, 0.0
    for h, (d, m) in enumerate(zip(data.head_data, problem.models, strict=True)):
        k = m.k
        s0, v, rho = d.obs.sigma_px[k], res_px[h][k], redundancy[h][k]
        red = float(np.sum(rho))
        if red >= MIN_GROUP_REDUNDANCY and np.all(np.isfinite(rho)) and np.all(np.isfinite(v)):
            new[h] = image_floor_px(v, s0, rho, floors[h])
        factor = group_factor(v / s0[:, None], rho)
        heads[data.heads[h].camera_id] = {"image_floor_px": float(floors[h]), "image_redundancy": red,
                                          "image_factor": float(factor) if np.isfinite(factor) else None}
        change = max(change, weight_change(s0, floors[h], new[h]))
    vc["heads"] = heads
    new_factor = survey_factor
    if len(red_sur):                # the surveyed targets' factor, as the single camera's (step 4b)
        rel = group_factor(result.r[problem.n_rows_image:problem.n_rows], red_sur)
        new_factor = survey_factor * rel if np.isfinite(rel) else survey_factor
        vc.update(survey_factor=float(survey_factor), survey_redundancy=float(np.sum(red_sur)),
                  survey_factor_estimate=float(new_factor))
        change = max(change, abs(new_factor / survey_factor - 1.0))
    if change <= WEIGHT_TOLERANCE or vc["rounds"] >= MAX_COMPONENT_ROUNDS:
        return None
    return new, new_factor


def _reweighted(data: RigData, floors, survey_factor: float = 1.0) -> RigData:
    """``data`` with every head's image sigmas ``sqrt(sigma^2 + floor_h^2)`` and the survey sigmas
    times ``survey_factor``."""
    targets = replace(data.targets, sigma_mm=data.targets.sigma_mm * survey_factor)
    heads = [replace(d.with_obs(replace(d.obs, sigma_px=np.sqrt(d.obs.sigma_px**2 + f**2))), targets=targets)
             for d, f in zip(data.head_data, floors, strict=True)]
    return replace(data, head_data=heads)


def _result(data, o, problem: RigProblem, result, state, res_px, active, reason, exposure_used, total, rounds):
    """Rebase, the covariance at the rebased point, the :class:`RigResult`."""
    x = problem.rebase(result.x)
    _, J = problem.evaluate(x, True)
    try:
        ne = J.normal_equations()
        cov = ne.covariance_reduced() * result.sigma0**2
    except SingularSystemError as err:
        raise GeometryError(f"the rig's covariance is singular: {err}") from None
    names = problem.column_names()
    s = np.sqrt(np.diag(cov))
    sigma = []
    for h in range(data.n_heads):
        sl = slice(problem.int_off[h], problem.int_off[h + 1])
        sigma.append({p: float(v) for p, v in zip(state.estimate[h], s[sl], strict=True)})
    s_rot = np.zeros((data.n_heads, 3))
    s_t = np.zeros((data.n_heads, 3))
    for h in problem.rel_heads:
        k = problem.rel_off[h]
        s_rot[h] = s[k:k + 3] * ARCSEC_PER_RAD
        s_t[h] = s[k + 3:k + 6] * 1000.0
    sigma_X = None
    if o.targets_adjusted is False:
        state.targets_m = data.targets.xyz_m.copy()
    else:
        sigma_X = np.full((len(data.targets), 3), np.nan)      # NaN: not adjusted (no point in use sees it)
        var = np.einsum("kii->ki", ne.covariance_elim_blocks())
        sigma_X[problem.target_index] = np.sqrt(var) * result.sigma0
        state.targets_m[~data.targets.surveyed & ~np.isin(np.arange(len(data.targets)), problem.target_index)] = np.nan
    return RigResult(data=data, options=o, state=state, sigma=sigma, sigma0=float(result.sigma0),
                     sigma_rotation_arcsec=s_rot, sigma_t_mm=s_t, covariance=cov, covariance_names=names,
                     residual_px=res_px, obs_used=[a.copy() for a in active],
                     obs_reason=[r.astype(str) for r in reason], exposure_used=exposure_used, lsq=result,
                     iterations_total=total, rounds=rounds, sigma_targets_m=sigma_X)

