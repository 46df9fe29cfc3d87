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
   A **planar board** (observed targets all surveyed and coplanar to 1 um: nominal coordinates,
   :mod:`fieldcal.field.board`) is by default held fixed up to a low-order warp whose three
   coefficients are unknowns of this adjustment (``board_model``; ``stats.board``).
3. **Blunders**: first gross rejection on residuals normalised by a robust scale
   (``robust_k`` times 1.4826 MAD), then data snooping: the test statistic of each image
   point (2-D), each survey (3-D) and each scale bar (1-D) ``T = v^T Q_vv^-1 v / sigma0^2`` with
   ``Q_vv = I - J_g N^-1 J_g^T`` from the normal equations, rejected above the chi-square
   quantile of ``snoop_alpha`` (bars: the worst one per round, while
   :data:`MIN_BARS_TO_REJECT` are in use); repeat until nothing is rejected. Each round starts at the
   previous round's solution and continues LM with the damping it ended with (a warm start:
   1-2 iterations where a cold damping took 4-5); a round over the same observations (a
   re-weighting, step 4b) reuses the Jacobian's index analysis.
4. **Parameter selection** (when the session gives no ``estimate``): an additional
   parameter (``k1 .. a2``) is held fixed at 0 when the data cannot determine it: its
   correlation with another interior parameter exceeds ``max_correlation`` (the weaker
   of the pair is fixed), or f is undetermined and it inflates f's sigma most. One
   parameter per round, the worst first, each reason reported (``stats.fixed_parameters``).
   A parameter that is merely *not significant* is kept, with its sigma: holding it at 0
   would move its correlated partners by its (unknown) true value while the covariance,
   conditional on the 0, shrinks (docs/uncertainty.md; the issue's draw where holding
   p1 cut the sigma of xp from 2.77 px to 0.50 px and left a 3.3-sigma error). The old
   rule is still there for who asks for it (``min_t > 0``), with that caveat.
4b. **Variance components** (:mod:`fieldcal.field.variance_components`; ``variance_components``):
   with adjusted targets, a floor added in quadrature to the image points' sigmas and a
   factor of the surveys' sigmas are estimated from the residuals and their redundancy
   numbers, and the adjustment re-weighted (warm) until they settle; with fixed targets the
   survey errors, which the image residuals then carry identically in every image of a
   target, are propagated into the covariance. ``stats.sigma0`` stays the factor of the
   session's own a-priori sigmas; ``stats.variance_components`` says what was used.
5. **Diagnoses instead of calibrations** (:class:`~fieldcal.errors.GeometryError`): fewer
   than :data:`MIN_IMAGES` images or :data:`MIN_POINTS_PER_IMAGE` points in an image; a
   network that cannot determine f even with every additional parameter held fixed (checked
   on the a-priori covariance at the initial values: relative sigma above ``max_rel_sigma_f``,
   naming the unknown f cannot be told from, e.g. the camera distance of a flat wall
   photographed from one direction; the same diagnosis whether or not a factorisation of the
   near-singular system breaks down); an automatic selection that ends with f still undetermined; singular
   normal equations (naming the unknown where known).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pyarrow as pa
import scipy.linalg
from scipy.special import chdtri  # chi2.isf(p, k) = chdtri(k, p), without scipy.stats' import

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.board import BOARD_MODELS, BoardWarp, board_warp, facing, is_planar_board, resolve_board_model
from fieldcal.field.bundle import BundleModel, image_residuals
from fieldcal.field.check_points import CheckPoints, check_point_mask, evaluate_check_points
from fieldcal.field.datum import MIN_CONTROL_POINTS, minimal_constraints, to_minimum_trace
from fieldcal.field.initial import CORE_PARAMS, InitialValues, initial_values
from fieldcal.field.scale_bars import BarObservations, bar_ends, covariance_blocks, usable
from fieldcal.field.variance_components import (
    MIN_GROUP_REDUNDANCY,
    WEIGHT_TOLERANCE,
    VarianceComponents,
    fixed_target_covariance,
    group_factor,
    image_floor_px,
    survey_consider_matrix,
    weight_change,
)
from fieldcal.model.camera import FIELD_PARAMS, Camera
from fieldcal.robust import robust_sigma
from fieldcal.session.data import FieldData
from fieldcal.solver.blocksparse import (
    BlockSparseJacobian,
    ResidualBlock,
    SingularSystemError,
    equilibrated_cholesky,
)
from fieldcal.solver.lsq import LsqResult, solve

__all__ = ["AdjustmentOptions", "FieldProblem", "FieldResult", "InitialValues", "initial_values",
           "adjust_field", "validate_field_data", "CORE_PARAMS", "centred", "snooping_statistic", "snooped"]

# CORE_PARAMS (f, xp, yp; fieldcal.field.initial) are never held fixed by the automatic
# selection: a degenerate one is a diagnosis, not a fix.

MIN_POINTS_PER_IMAGE = 6
MIN_IMAGES = 3
"""The field method needs at least this many images (as a session measured from images does)."""
CHECK_POINT = "check point"
"""The residual table's ``reason`` of an image point of a check point."""
MAX_COMPONENT_ROUNDS = 4
MIN_BARS_TO_REJECT = 3
"""Data snooping rejects a scale bar only while at least this many are in use (step 3)."""
"""At most this many re-weighted re-solutions for the variance components (step 4b)."""


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
    tau, eps2, ftol, sigma_tol : float
        LM's initial damping factor (small: the initial values are good), the step
        tolerance and the negligible-decrease tolerances of :func:`fieldcal.solver.lsq.solve`
        (``sigma_tol``: stop when a step is below this many a-posteriori standard
        deviations: 1e-3 leaves every parameter within a thousandth of its sigma of the
        optimum, whatever its units and wherever the origin lies).
    robust_k : float
        Gross-error threshold in robust sigmas (normalised residual norm).
    snoop_alpha : float
        Significance level of data snooping (per observation).
    max_correlation : float
        Correlation above which the weaker of two interior parameters is fixed.
    min_t : float
        An additional parameter with ``|value| / sigma`` below this is fixed. Default 0:
        no parameter is held for being insignificant (module docstring, step 4): a held
        parameter biases its partners by its true value while their covariance shrinks.
    variance_components : bool
        Estimate an image-point floor and a survey factor and re-weight (adjusted targets),
        or propagate the survey errors of fixed targets (module docstring, step 4b).
    check_points : tuple of str
        Ids of surveyed targets to withhold as independent check points
        (:mod:`fieldcal.field.check_points`; ``session.json`` ``check_points``).
    check_fraction : float
        Withhold also this fraction of the targets, drawn at random and stratified over the
        field (seeded by ``check_seed``).
    max_rel_sigma_f : float
        When the principal distance is determined worse than this (relative sigma), the
        additional parameter that inflates the sigma of f, xp, yp most is fixed first.
    datum : str
        ``"auto"`` or ``"free"`` (:mod:`fieldcal.field.datum`).
    board_model : str
        How a planar board's nominal coordinates enter (:mod:`fieldcal.field.board`):
        ``"auto"`` (default: ``"warp"`` on a planar board, ``"rigid"`` when
        ``targets_adjusted`` is False, nothing on another field), ``"warp"``, ``"rigid"``
        or ``"points"``. ``"warp"`` and ``"rigid"`` hold the targets fixed, ``"points"``
        adjusts them.
    """

    targets_adjusted: bool = True
    estimate: tuple[str, ...] | None = None
    method: str = "lmqn"
    max_iter: int = 1000
    tau: float = 1e-6
    eps2: float = 1e-10
    ftol: float = 1e-12
    sigma_tol: float = 1e-3
    robust_k: float = 8.0
    snoop_alpha: float = 1e-6
    max_rounds: int = 20
    max_correlation: float = 0.995
    min_t: float = 0.0
    max_rel_sigma_f: float = 0.02
    variance_components: bool = True
    check_points: tuple[str, ...] = ()
    check_fraction: float = 0.0
    check_seed: int = 0
    datum: str = "auto"
    board_model: str = "auto"

    def to_dict(self) -> dict:
        return {"targets_adjusted": self.targets_adjusted,
                "estimate": list(self.estimate) if self.estimate is not None else None,
                "method": self.method, "max_iter": self.max_iter, "tau": self.tau, "eps2": self.eps2,
                "ftol": self.ftol, "sigma_tol": self.sigma_tol,
                "robust_k": self.robust_k,
                "snoop_alpha": self.snoop_alpha, "max_rounds": self.max_rounds,
                "max_correlation": self.max_correlation, "min_t": self.min_t,
                "max_rel_sigma_f": self.max_rel_sigma_f, "variance_components": self.variance_components,
                "check_points": list(self.check_points), "check_fraction": self.check_fraction,
                "check_seed": self.check_seed, **({"datum": self.datum} if self.datum != "auto" else {}),
                **({"board_model": self.board_model} if self.board_model != "auto" else {})}


# ---------------------------------------------------------------------------- validation
def validate_field_data(data: FieldData, *, min_points: int = MIN_POINTS_PER_IMAGE) -> None:
    """Refuse data the adjustment cannot use, naming what and where.

    Infinite or partly NaN coordinates (all three NaN: an unsurveyed target), duplicate target
    ids, non-positive sigmas, observations of unknown targets or images, images with fewer
    than ``min_points`` points, and fewer than :data:`MIN_IMAGES` images.
    """
    t = data.targets
    if len(np.unique(t.ids)) != len(t.ids):
        ids, counts = np.unique(t.ids, return_counts=True)
        raise InputError(f"duplicate target id(s) {list(ids[counts > 1][:5])}", "targets")
    bad = ~np.isfinite(t.xyz_m).all(axis=1) & ~np.isnan(t.xyz_m).all(axis=1)   # all NaN: unsurveyed
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


# ---------------------------------------------------------------------------- the LSQ problem
class FieldProblem:
    """The bundle model as a problem for :func:`fieldcal.solver.lsq.solve` (block-sparse Jacobian).

    ``like``: a previous problem; when it has the same unknowns and active observations (a
    re-weighted round), its blocks' index arrays and the Jacobian's index analysis are reused
    (they depend only on which observations enter, ~10-15 ms to make on the paper field).
    """

    def __init__(self, model: BundleModel, like: FieldProblem | None = None, bars: BarObservations | None = None):
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
        # eliminated blocks: the targets (3 each) when adjusted, but the bar ends (global, dense;
        # fieldcal.field.scale_bars); with the targets fixed, the exterior orientations (6 each),
        # so that only the interior is solved densely
        self.n_dense = m.n_reduced + 3 * m.n_global if m.targets_adjusted else m.n_int
        self.block_size = 3 if m.targets_adjusted else 6
        self.bars = bars if bars is not None and len(bars) else None
        # image points and surveys of the bar ends are blocks of their own (dense target columns)
        self._img_split = [g for g in (m.tgt_slot >= m.n_global, m.tgt_slot < m.n_global) if g.any()] \
            if m.n_global else [None]
        sur_slot = m.t_slot[m.survey_k]
        self._sur_split = [g for g in (sur_slot >= m.n_global, sur_slot < m.n_global) if g.any()] \
            if m.n_global else ([None] if ns else [])
        if like is not None and like._template is not None and _same_pattern(like.model, m) and \
                _same_bars(like.bars, self.bars):
            self._template, self._structure = like._template, like._structure
        self._last = None               # (x, r, J) of the last evaluation with the Jacobian
        self.datum = None               # MinimalConstraints of a free network (fieldcal.field.datum)

    @property
    def n_rows_data(self) -> int:
        """Rows of the observations: image points, surveys, bars (the datum's come after)."""
        return self.model.n_rows + (len(self.bars) if self.bars is not None else 0)

    def evaluate(self, x, jacobian: bool):
        """``(r, J)`` at ``x``; the last evaluation with the Jacobian is kept, and asked again at
        the same ``x`` (the start, seen by the f check and then by the solver) it is returned
        as it is, with the normal equations already made from it."""
        if jacobian and self._last is not None and np.array_equal(self._last[0], x):
            return self._last[1], self._last[2]
        m = self.model
        r, jb, sd = m.residuals_and_blocks(x, jacobian)
        if self.bars is not None:
            r = np.concatenate([r, self.bars.residuals(x)])
        if self.datum is not None:
            r = np.concatenate([r, self.datum.residuals(x)])
        if not jacobian:
            return r, None
        parts = [(self._cols_int, jb.d_int), (self._cols_ext, jb.d_ext)]
        if m.targets_adjusted:
            parts.append((self._cols_tgt, jb.d_tgt))
        sur_values = sd[:, None, None] * np.eye(3)[None]
        if m.n_global:
            blocks = self._split_blocks(parts, sur_values)
        elif self._template is None:
            blocks = [ResidualBlock.from_parts(self._rows_img, parts)]
            if len(sd):
                blocks.append(ResidualBlock.from_parts(self._rows_sur, [(self._cols_sur, sur_values)]))
            self._template = blocks
        else:
            blocks = [self._template[0].with_values(*[p[1] for p in parts], combined=jb.combined)]
            if len(sd):
                blocks.append(self._template[1].with_values(sur_values))
        n_rows = self.n_rows_data
        if self.bars is not None:
            blocks = [*blocks, self.bars.block(m.n_rows, x)]
        if self.datum is not None:
            blocks = [*blocks, self.datum.block(n_rows)]
            n_rows += len(self.datum.D)
        J = BlockSparseJacobian(n_rows, m.n_params, self.n_dense, self.block_size, blocks,
                                structure=self._structure)
        self._structure = J.structure
        self._last = (np.array(x, float), r, J)
        return r, J

    def _split_blocks(self, parts, sur_values):
        """The image and survey blocks split into those of eliminated and of global targets."""
        def cut(c, g):
            return c if c.ndim == 1 else c[g]
        blocks = [ResidualBlock.from_parts(self._rows_img[g], [(cut(c, g), v[g]) for c, v in parts])
                  for g in self._img_split]
        blocks += [ResidualBlock.from_parts(self._rows_sur[g], [(self._cols_sur[g], sur_values[g])])
                   for g in self._sur_split]
        return blocks

    def group_covariances(self, ne):
        """``J_g N^-1 J_g^T`` of every image point (m_active, 2, 2) and survey (n_survey, 3, 3),
        in the model's order, and of every bar (n_bars,), whatever the blocks' split."""
        out, b = [], 0
        m = self.model
        for split, size, d in ((self._img_split, len(m.img), 2), (self._sur_split, len(m.survey_k), 3)):
            Q = np.zeros((size, d, d))
            for g in split:
                Q[slice(None) if g is None else g] = ne.group_covariance(b)
                b += 1
            out.append(Q)
        out.append(ne.group_covariance(b)[:, 0, 0] if self.bars is not None else np.zeros(0))
        return out

    def observation_blocks(self, x):
        """``(d_int, d_ext)`` (m, 2, n_int), (m, 2, 6) of the image residuals at ``x``: those of the
        kept Jacobian when ``x`` is its point (the same numbers), else evaluated."""
        if self._last is not None and np.array_equal(self._last[0], x) and not self.model.n_global:
            parts = self._last[2].blocks[0].part_values
            return parts[0], parts[1]
        _, jb, _ = self.model.residuals_and_blocks(x, True)
        return jb.d_int, jb.d_ext


def _same_bars(a: BarObservations | None, b: BarObservations | None) -> bool:
    """Whether two problems carry the same bars (the same rows and columns)."""
    if a is None or b is None:
        return a is None and b is None
    return np.array_equal(a.index, b.index) and np.array_equal(a.cols, b.cols)


def _same_pattern(a: BundleModel, b: BundleModel) -> bool:
    """Whether two models have the same unknowns and active observations (the same Jacobian
    pattern: rows, columns and groups), whatever their values and weights."""
    return (a.estimate == b.estimate and a.targets_adjusted == b.targets_adjusted
            and a.n_images == b.n_images and a.n_targets == b.n_targets
            and np.array_equal(a.k, b.k) and np.array_equal(a.img, b.img)
            and np.array_equal(a.tgt, b.tgt) and np.array_equal(a.survey_k, b.survey_k)
            and np.array_equal(a.target_index, b.target_index) and a.n_global == b.n_global)


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
    variance_components: VarianceComponents = field(default_factory=VarianceComponents)
    check_points: CheckPoints | None = None
    datum: dict = field(default_factory=dict)
    board: dict = field(default_factory=dict)     # stats.board: the planar board's model (empty: not a board)

    @property
    def camera(self) -> Camera:
        return Camera(self.data.sensor, self.params)

    def stats(self) -> dict:
        """The document's ``stats`` (docs/conventions.md section 4) plus a few extras."""
        used = self.obs_used
        du = self.residual_px[used]
        norm = np.hypot(du[:, 0], du[:, 1])
        observed = np.unique(self.data.obs.target[used])
        rejected = ((~self.survey_used[observed] & self.data.targets.surveyed[observed])
                    if self.options.targets_adjusted else np.zeros(len(observed), bool))
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
            "n_surveys_rejected": int(rejected.sum()),
            "rejected_surveys": [str(t) for t in self.data.targets.ids[observed][rejected]],
            **self.unsurveyed_stats(),
            **({"datum": self.datum} if self.datum else {}),
            **({"board": self.board} if self.board else {}),
            "n_left_out": int(((~used) & (self.obs_reason != "blunder") & (self.obs_reason != CHECK_POINT)).sum()),
            "iterations_total": int(self.iterations_total),
            "lsq_status": self.lsq.message,
            "initial_values": self.initial.how,
            "variance_components": self.variance_components.to_dict(),
            **({"check_points": self.check_points.to_stats()} if self.check_points is not None else {}),
        }

    def unsurveyed_stats(self) -> dict:
        """The document's account of the unsurveyed targets (:func:`unsurveyed_account`)."""
        return unsurveyed_account(self.data.targets, self.data.obs.target[self.obs_used],
                                  self.data.meta.get("unlisted_targets", []), self.targets_m,
                                  self.sigma_targets_m)

    def images_section(self) -> list[dict]:
        """The document's ``images`` list (docs/conventions.md section 4)."""
        out = []
        img = self.data.obs.image
        k_used = np.flatnonzero(self.obs_used)          # the used points, image by image, in order
        k_used = k_used[np.argsort(img[k_used], kind="stable")]
        bounds = np.searchsorted(img[k_used], np.arange(len(self.data.images) + 1))
        for i, im in enumerate(self.data.images):
            k = k_used[bounds[i]:bounds[i + 1]]
            res = self.residual_px[k]
            out.append({
                "file": im.file, "station": im.station,
                "center_m": self.center_m[i].tolist(),
                "rotation_world_to_camera": self.R_world_to_camera[i].tolist(),
                "sigma_center_m": self.sigma_center_m[i].tolist(),
                "n_observations": len(k),
                "rmse_px": float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(k) else None,
            })
        return out

    def residual_table(self) -> pa.Table:
        """One row per image observation: measured, residual, used, reason, test statistic."""
        d = self.data
        reason = np.where(self.obs_reason == "", None, self.obs_reason.astype(object))
        files = np.array([im.file for im in d.images], dtype=object)
        return pa.table({
            "image": pa.array(files[d.obs.image], pa.string()),
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
        if init.targets_m is not None:          # unsurveyed targets: their intersections (NaN: not placed)
            self.X = np.array(init.targets_m, float)
        self.iterations = 0
        self.rounds: list[dict] = []
        self.model: BundleModel | None = None
        self.problem: FieldProblem | None = None
        self.free = False                                  # a free network (fieldcal.field.datum)
        self.warp: BoardWarp | None = None                 # a planar board's warp model (fieldcal.field.board)
        self.warp_mm = np.zeros(0)
        bars = data.scale_bars
        self.bar_active = np.ones(len(bars) if bars is not None else 0, bool)   # not rejected
        self.sigma_px0 = data.obs.sigma_px.copy()          # the session's a-priori sigmas
        self.sigma_mm0 = data.targets.sigma_mm.copy()
        self.vc = VarianceComponents()
        self.tau = options.tau          # LM's damping, carried from solve to solve (warm starts)
        if init.lm_tau is not None and np.isfinite(init.lm_tau) and init.lm_tau > 0:
            self.tau = min(self.tau, float(init.lm_tau))

    def reweight(self, floor_px: float, survey_factor: float):
        """Weight the next solves with the variance components (step 4b): image sigmas
        ``sqrt(sigma^2 + floor^2)``, survey sigmas times ``survey_factor``."""
        d = self.data
        obs = replace(d.obs, sigma_px=np.sqrt(self.sigma_px0**2 + floor_px**2))
        targets = replace(d.targets, sigma_mm=self.sigma_mm0 * survey_factor)
        self.data = replace(d, obs=obs, targets=targets)
        self.vc.image_floor_px, self.vc.survey_factor = float(floor_px), float(survey_factor)
        self.vc.rounds += 1

    def run(self, estimate, obs_active, survey_active, label, before=None):
        """One adjustment from the current state; ``before(model, x0, J0)`` sees its start."""
        o = self.options
        bars, used = self.data.scale_bars, None
        if o.targets_adjusted and len(self.bar_active):
            seen = np.zeros(len(self.data.targets), bool)
            seen[self.data.obs.target[obs_active]] = True
            used = usable(bars, self.bar_active, seen)
        model = BundleModel(self.data, self.params, estimate, self.R,
                            targets_adjusted=o.targets_adjusted, obs_active=obs_active,
                            survey_active=survey_active,
                            global_targets=bar_ends(bars, self.bar_active, seen) if used is not None else None,
                            warp=self.warp)
        x0 = model.pack(self.params, self.C, self.X, self.warp_mm if self.warp is not None else None)
        self.model = model
        problem = FieldProblem(model, like=self.problem,
                               bars=BarObservations(bars, used, model) if used is not None else None)
        if self.free:
            problem.datum = minimal_constraints(model, x0, np.bincount(model.img, minlength=model.n_images),
                                                scale=problem.bars is None)
        self.problem = problem
        if before is not None:
            r0, J0 = problem.evaluate(x0, True)
            if np.all(np.isfinite(r0)) and J0.all_finite():
                before(model, x0, J0)
        try:
            result = solve(problem, x0, method=o.method, max_iter=o.max_iter, tau=self.tau,
                           eps2=o.eps2, ftol=o.ftol, sigma_tol=o.sigma_tol)
        except InputError as err:          # not finite at x0: the previous round went astray
            raise GeometryError(f"the adjustment diverged before {label} ({err.reason}); the "
                                "data do not hold the camera in place") from None
        if not np.all(np.isfinite(result.r)):
            raise GeometryError("the adjustment diverged (points behind a camera)")
        self.params, self.R, self.C, X = model.unpack(result.x)
        self.warp_mm = model.warp_mm(result.x)
        if o.targets_adjusted:
            self.X = X
        # the next solve starts at this one's solution, a few points or a weight away from its
        # own: it continues with the damping this one ended with (never above the option's)
        if np.isfinite(result.mu) and result.mu > 0:
            self.tau = min(self.tau, result.mu)
        self.iterations += result.iterations
        self.rounds.append({"round": label, "iterations": result.iterations,
                            "sigma0": result.sigma0, "status": result.message,
                            "n_obs": int(np.sum(obs_active)), "estimate": list(estimate)})
        if self.progress:
            self.progress(f"{label}: {result.iterations} iterations, sigma0 {result.sigma0:.3f}")
        return model, result

    def hold_fixed(self, model, result, j):
        """Fix interior unknown ``j`` of ``model`` at 0 and move the others to where the
        linearised problem puts them (the conditional mean given ``x_j = 0``):
        ``x - N^-1 e_j x_j / (N^-1)_jj``, one solve with the factorisation already made.
        The next adjustment then starts next to its optimum (a warm start)."""
        ne = result.jac.normal_equations()
        e = np.zeros(len(result.x))
        e[j] = 1.0
        try:
            y = ne.solve(-e)                                   # N^-1 e_j
            x = result.x - y * (result.x[j] / y[j])
        except SingularSystemError:
            x = result.x.copy()
        x[j] = 0.0
        if np.all(np.isfinite(x)):
            self.params, self.R, self.C, X = model.unpack(x)
            self.warp_mm = model.warp_mm(x)
            if self.options.targets_adjusted:
                self.X = X
        self.params[model.int_index[j]] = 0.0

    def targets_now(self):
        """The targets (n, 3) [m] at the current state: with a board warp, displaced by it."""
        return self.X if self.warp is None else self.warp.displaced(self.warp_mm, self.X)

    def residuals_all(self):
        """Measured minus predicted pixels of every observation at the current state."""
        return image_residuals(self.data, self.params, self.R, self.C, self.targets_now())


def _robust_scale(z):
    return max(float(robust_sigma(z)), 1e-12)


def _drop_undetermined_targets(data, obs_active, survey_active, reason, X=None, C=None):
    """Targets whose survey is rejected need two images seen from directions at least
    :data:`MIN_INTERSECTION_DEG` apart (two rolls from one station do not intersect);
    otherwise their points go too. ``X`` (n_targets, 3) and ``C`` (n_images, 3) are the
    current targets and camera centres [m]; without them two images suffice."""
    if survey_active.all():
        return 0
    n_img = len(data.images)
    pairs = np.unique(data.obs.target[obs_active] * n_img + data.obs.image[obs_active])
    t_of, i_of = pairs // n_img, pairs % n_img
    n_img_per_target = np.bincount(t_of, minlength=len(data.targets))
    weak = (~survey_active) & (n_img_per_target < 2)
    if X is not None and C is not None:
        for t in np.flatnonzero((~survey_active) & ~weak & (n_img_per_target > 0)):
            d = C[i_of[t_of == t]] - X[t]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
            weak[t] = bool((d @ d.T).min() > np.cos(np.radians(MIN_INTERSECTION_DEG)))
    drop = obs_active & weak[data.obs.target]
    obs_active[drop] = False
    reason[drop] = "target undetermined after its survey was rejected"
    return drop.sum()


MIN_INTERSECTION_DEG = 0.05
"""Rays (unit vectors) whose widest angle is below this [deg] are taken as parallel: their
intersection is not determined (repeated exposures from one station), and
:func:`_blame_the_survey` asks for a far wider angle anyway."""


def _intersect(rays, centers):
    """Least-squares intersection of rays (k, 3) from centres (k, 3): the point nearest all,
    or None when the rays are parallel (:data:`MIN_INTERSECTION_DEG`)."""
    if (rays @ rays.T).min() > np.cos(np.radians(MIN_INTERSECTION_DEG)):
        return None
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    return np.linalg.solve(P.sum(0), np.einsum("kab,kb->a", P, centers))


def _blame_the_survey(solver, obs_active, survey_active, reason, sigma0):
    """Targets whose rejected image points intersect consistently away from the survey.

    For each target with rejected points in at least two images, the rays of those points
    are intersected (least squares, current cameras), dropping the worst ray while the rest
    do not meet within the image noise. If at least two rays remain that meet within the
    noise, in front of their cameras and at an angle of at least ``10 / (n - 1)`` degrees
    (two rays always nearly meet: they need a wide angle), they outnumber the target's points
    still in use (those fit the survey: the rejected ones are then blunders of their own, e.g.
    two swapped ids that happen to meet), and the intersection lies more than 5 survey sigmas
    from the surveyed coordinates, the survey is the blunder: it is rejected and the
    consistent points are readmitted. Returns the number of surveys rejected.
    """
    data = solver.data
    out = ~obs_active & np.isin(reason, ("initial outlier", "blunder"))
    suspects = _suspect_points(data, out, survey_active)
    if not suspects:
        return 0
    cam = Camera(data.sensor, solver.params)
    first = _meeting_points(solver, cam, suspects)           # all targets' first try: one call
    n = 0
    for (t, k), (rays, X, err) in zip(suspects, first, strict=True):
        while True:
            if X is None:          # parallel rays: they cannot place the target
                k = k[:0]
                break
            ok = np.isfinite(err) & (err < np.maximum(1.0, 5.0 * sigma0 * data.obs.sigma_px[k]))
            if ok.all():
                break
            k = np.delete(k, int(np.argmax(np.where(np.isfinite(err), err, np.inf))))
            if len(k) < 2:
                break
            ((rays, X, err),) = _meeting_points(solver, cam, [(t, k)])
        if len(k) < 2:
            continue
        angle = np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1.0, 1.0)))
        far = np.linalg.norm(X - data.targets.xyz_m[t]) * 1000.0 > 5.0 * data.targets.sigma_mm[t]
        outvote = len(k) > np.count_nonzero(obs_active & (data.obs.target == t))
        if angle >= 10.0 / (len(k) - 1) and far and outvote:
            survey_active[t] = False
            obs_active[k] = True
            reason[k] = ""
            solver.X[t] = X
            n += 1
    return n


def _suspect_points(data, out, survey_active) -> list[tuple[int, np.ndarray]]:
    """``(target, its rejected observations)`` of the surveyed targets whose rejected points
    lie in two or more images (:func:`_blame_the_survey`), in target order."""
    k = np.flatnonzero(out & survey_active[data.obs.target])
    if not len(k):
        return []
    k = k[np.argsort(data.obs.target[k], kind="stable")]
    targets, first = np.unique(data.obs.target[k], return_index=True)
    groups = np.split(k, first[1:])
    return [(int(t), g) for t, g in zip(targets, groups, strict=True) if len(np.unique(data.obs.image[g])) >= 2]


def _meeting_points(solver, cam, groups):
    """For each ``(target, observations)``: the rays (k, 3) of its points, their least-squares
    intersection (None: parallel rays) and each point's distance from its reprojection [px].
    The rays and the reprojections of all groups are computed in one call each (the same
    numbers as group by group: every point is its own row)."""
    data = solver.data
    k = np.concatenate([g for _, g in groups])
    img = data.obs.image[k]
    rays = np.einsum("kba,kb->ka", solver.R[img], cam.unproject(data.obs.uv_px[k]))
    bounds = np.cumsum([0] + [len(g) for _, g in groups])
    X = [_intersect(rays[a:b], solver.C[img[a:b]]) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    placed = np.array([x is not None for x in X])
    err = np.full(len(k), np.nan)
    rows = np.repeat(placed, np.diff(bounds))
    if rows.any():
        Xk = np.repeat(np.array([x for x in X if x is not None]).reshape(-1, 3), np.diff(bounds)[placed], axis=0)
        uv = cam.project(Xk, solver.R[img[rows]], solver.C[img[rows]])
        err[rows] = np.hypot(*(uv - data.obs.uv_px[k[rows]]).T)
    return [(rays[a:b], x, err[a:b]) for a, b, x in zip(bounds[:-1], bounds[1:], X, strict=True)]


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
        rs = r[model.n_rows_image:model.n_rows].reshape(-1, 3)
        norm_s = np.linalg.norm(rs, axis=1)
        bad_s = norm_s > o.robust_k * max(s, 1.0) * np.sqrt(3.0)
        survey_active[model.survey_k[bad_s]] = False
        n += int(bad_s.sum())
    return n


def _snooping(problem, result, flags: _Flags, o, bar_active=None):
    """Data snooping with redundancy (module docstring, step 3); returns how many rejected.

    Records every tested observation's redundancy (the trace of its ``Q_vv`` block) in
    ``flags`` for the variance components. Scale bars are tested too (one row each; a bar
    rejected leaves ``bar_active``)."""
    model = problem.model
    obs_active, survey_active, reason, test = flags.obs_active, flags.survey_active, flags.reason, flags.test
    ne = result.jac.normal_equations()
    sigma0 = max(result.sigma0, 1e-12)
    n = 0
    Qg_img, Qg_sur, qg_bar = problem.group_covariances(ne)
    ri = result.r[: model.n_rows_image].reshape(-1, 2)
    Ti, flags.red_img[model.k] = snooping_statistic(Qg_img, ri, sigma0)
    test[model.k] = Ti
    lim2 = chdtri(2, o.snoop_alpha)
    bars_worse = _snoop_bars(problem, result, qg_bar, Ti.max() / lim2, bar_active, sigma0, o)
    if bars_worse is not None:
        return bars_worse
    worst = snooped(Ti, o.snoop_alpha)
    if worst.any():
        k = model.k[worst]
        obs_active[k] = False
        reason[k] = "blunder"
        n += int(worst.sum())
    if model.targets_adjusted and len(model.survey_k):
        Qs = np.eye(3) - Qg_sur
        flags.red_sur[model.survey_k] = np.einsum("kii->k", Qs)
        rs = result.r[model.n_rows_image:model.n_rows].reshape(-1, 3)
        Ts = _quadratic_form(Qs, rs) / sigma0**2
        bad_s = Ts > chdtri(3, o.snoop_alpha)
        if bad_s.any():
            worst = bad_s & (Ts > 0.25 * Ts.max())
            survey_active[model.survey_k[worst]] = False
            n += int(worst.sum())
    return n


def _snoop_bars(problem, result, qg_bar, worst_image, bar_active, sigma0, o) -> int | None:
    """When a scale bar is worse than every image point (its statistic over its chi-square
    limit above ``worst_image``, the image points'), the bar, not the points it bends, is the
    suspect, and no image point or survey is rejected this round: returns how many bars were
    rejected (the worst, in ``bar_active``, while :data:`MIN_BARS_TO_REJECT` are in use; with
    fewer, two disagreeing lengths cannot tell which one is wrong: both residuals show it and
    neither is rejected, 0). None: the bars are not the worst."""
    bars = problem.bars
    if bars is None or bar_active is None:
        return None
    model = problem.model
    qv = 1.0 - qg_bar
    rb = result.r[model.n_rows:problem.n_rows_data]
    Tb = np.where(qv > 1e-8, rb**2 / np.maximum(qv, 1e-300), 0.0) / sigma0**2
    k = int(np.argmax(Tb))
    ratio = Tb[k] / chdtri(1, o.snoop_alpha)
    if not (ratio > 1.0 and ratio >= worst_image):
        return None
    if len(bars) >= MIN_BARS_TO_REJECT:
        bar_active[bars.index[k]] = False
        return 1
    return 0


def snooping_statistic(Qg, r, sigma0: float):
    """Data snooping's test statistic and redundancy of 2-D image points (module docstring, step 3).

    Parameters
    ----------
    Qg : (k, 2, 2) ndarray
        ``J_g N^-1 J_g^T`` of each point's unit-weight residual rows.
    r : (k, 2) ndarray
        The unit-weight residuals.
    sigma0 : float
        The fit's a-posteriori factor.

    Returns
    -------
    T : (k,) ndarray
        ``v^T Q_vv^+ v / sigma0^2`` with ``Q_vv = I - Qg`` (chi-square, 2 degrees of freedom).
    redundancy : (k,) ndarray
        The trace of ``Q_vv`` (the point's two redundancy numbers summed).
    """
    Qv = np.eye(2) - Qg
    return _quadratic_form(Qv, r) / max(sigma0, 1e-12) ** 2, Qv[:, 0, 0] + Qv[:, 1, 1]


def snooped(T, alpha: float) -> np.ndarray:
    """(k,) bool: the 2-D points data snooping rejects this round: above the chi-square(2) quantile
    of ``alpha`` and, since a blunder inflates its neighbours' statistics, the clearly worst
    ones only (above a quarter of the largest statistic)."""
    T = np.asarray(T, float)
    if not len(T):
        return np.zeros(0, bool)
    return (T > chdtri(2, alpha)) & (T > 0.25 * T.max())


def _quadratic_form(Q, r, rcond: float = 1e-8):
    """``r^T Q^+ r`` per group (Q (k, d, d) symmetric, possibly near-singular for zero redundancy).

    The pseudo-inverse drops eigenvalues below ``rcond`` times the largest (as
    ``numpy.linalg.pinv``); for d = 2 in closed form (no batched SVD of 10^4 tiny matrices).
    """
    if Q.shape[1] != 2:
        Qp = np.linalg.pinv(Q, rcond=rcond, hermitian=True)
        return np.einsum("ki,kij,kj->k", r, Qp, r)
    a, b, c = Q[:, 0, 0], 0.5 * (Q[:, 0, 1] + Q[:, 1, 0]), Q[:, 1, 1]
    half = np.hypot(0.5 * (a - c), b)
    lam_hi, lam_lo = 0.5 * (a + c) + half, 0.5 * (a + c) - half
    # eigenvector of lam_hi: (b, lam_hi - a) or (lam_hi - c, b), whichever is longer
    v0, v1 = np.where(a >= c, lam_hi - c, b), np.where(a >= c, b, lam_hi - a)
    nv = np.hypot(v0, v1)
    with np.errstate(divide="ignore", invalid="ignore"):
        p_hi = np.where(nv > 0, (v0 * r[:, 0] + v1 * r[:, 1]) / nv, np.hypot(r[:, 0], r[:, 1]))
        p_lo2 = np.maximum(r[:, 0] ** 2 + r[:, 1] ** 2 - p_hi**2, 0.0)
        keep_hi = lam_hi > 0
        keep_lo = lam_lo > rcond * lam_hi
        return (np.where(keep_hi, p_hi**2 / lam_hi, 0.0)
                + np.where(keep_hi & keep_lo, p_lo2 / lam_lo, 0.0))


def _interior_stats(model, result):
    """Sigma (a-posteriori) and correlation of the estimated interior parameters."""
    cov = _reduced_covariance(model, result.jac.normal_equations()) * result.sigma0**2
    ci = cov[: model.n_int, : model.n_int]
    s = np.sqrt(np.diag(ci))
    corr = ci / np.outer(s, s)
    return cov, s, corr


def _final_stats(model, result, solver, o):
    """:func:`_interior_stats` of the final adjustment; with fixed targets (and
    ``variance_components``) the survey errors are propagated (step 4b)."""
    if model.targets_adjusted or not o.variance_components:
        solver.vc.unit_sigma = float(result.sigma0)
        return _interior_stats(model, result)
    problem = solver.problem
    if problem is not None and problem.model is model:
        d_int, d_ext = problem.observation_blocks(result.x)
    else:
        _, jb, _ = model.residuals_and_blocks(result.x, True)
        d_int, d_ext = jb.d_int, jb.d_ext
    M, trace_q = survey_consider_matrix(d_int, d_ext, model.img, model.tgt, model.sigma_m[model.tgt],
                                        model.n_images)
    m, n = result.jac.shape
    unit = _reduced_covariance(model, result.jac.normal_equations())
    cov, factor = fixed_target_covariance(unit, M, float(result.r @ result.r), m - n, trace_q)
    solver.vc.survey_consider, solver.vc.error_model_factor, solver.vc.unit_sigma = True, factor, factor
    ci = cov[: model.n_int, : model.n_int]
    s = np.sqrt(np.diag(ci))
    return cov, s, ci / np.outer(s, s)


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


def _reduced_covariance(model, ne):
    """``N^-1`` over ``[interior | exterior]`` (n_reduced, n_reduced), unit weight.

    With the targets adjusted they are the eliminated blocks and this is the inverse Schur
    complement; with the targets fixed the exteriors are eliminated and it is all of N^-1.
    """
    if not model.targets_adjusted:
        return ne.covariance_dense()
    return ne.covariance_reduced()[: model.n_reduced, : model.n_reduced]     # bar ends: after


def _reduced_normal_matrix(model, ne):
    """``N`` reduced to ``[interior | exterior]`` (targets eliminated), dense."""
    return ne.schur_complement() if model.targets_adjusted else ne.dense_matrix()


def _covariance_via_eigen(S):
    """``S^+`` of a symmetric positive semi-definite S, eigenvalues floored at ``n eps`` of the
    largest after equilibration: a null direction gets a huge (not infinite) variance."""
    d = np.sqrt(np.clip(np.diag(S), 1e-300, None))
    w, V = np.linalg.eigh(S / np.outer(d, d))
    w = np.maximum(w, len(w) * np.finfo(float).eps * max(w[-1], 1e-300))
    return (V / w) @ V.T / np.outer(d, d)


_CLOSE_CALL_REL = 1e-6
""":func:`_check_f_determinable` passes a network on f's variance from one triangular solve
only when its relative sigma is below the limit by more than this fraction; closer calls are
decided on the full inverse, as the diagnosis is (round-off cannot change the decision)."""


def _check_f_determinable(model, x, J, o):
    """Refuse, before the first adjustment, a network that cannot determine f.

    With the a-priori covariance at the initial values ``x`` (Jacobian ``J``): a property
    of the geometry, not of the residuals, which may still hold blunders, and taken before
    the solver can wander along a direction the data do not fix (f -> 0, say). With
    every additional parameter held fixed (the most any choice
    of parameters could do: their rows and columns are taken out of the normal equations):
    a relative sigma of f above ``max_rel_sigma_f`` then will not get better by fixing
    parameters, so the diagnosis is given now, naming the unknown f cannot be told from:
    the one whose knowledge would determine f best (the smallest conditional variance of f),
    with its correlation. The covariance is the inverse of the equilibrated reduced normal matrix, by
    Cholesky, or where that breaks down by its eigen-decomposition with the eigenvalues
    floored at round-off: a singular system gives f a huge sigma and the correlation with its
    partner in the null space, so the diagnosis does not depend on which pivot fails first.
    (A session's explicit ``estimate`` whose additional parameters alone make f uncertain is
    honoured, with the sigma it gives.)
    """
    names = list(model.estimate)
    if "f_mm" not in names:
        return
    S = _reduced_normal_matrix(model, J.normal_equations())
    keep = np.array([n in CORE_PARAMS for n in names] + [True] * (S.shape[0] - len(names)))
    Sk = S[np.ix_(keep, keep)]
    jf = names.index("f_mm")
    try:
        cho, scale = equilibrated_cholesky(Sk)
    except SingularSystemError:
        cov = _covariance_via_eigen(Sk)
    else:
        # f's variance alone decides (one triangular solve: e_f^T S^-1 e_f = |U^-T e_f|^2 with
        # S = U^T U); all of S^-1 only for the diagnosis, or when that decision is a close call
        y = scipy.linalg.solve_triangular(cho[0], np.eye(len(Sk))[jf], trans="T", lower=cho[1],
                                          check_finite=False)
        rel = np.sqrt(max(float(y @ y), 0.0)) * scale[jf] / max(abs(x[jf]), 1e-12)
        if rel <= o.max_rel_sigma_f * (1.0 - _CLOSE_CALL_REL):
            return
        cov = scipy.linalg.cho_solve(cho, np.eye(len(Sk)), check_finite=False) * np.outer(scale, scale)
    var = np.maximum(np.diag(cov), 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov[jf] / np.sqrt(var[jf] * var)
        # what f cannot be told from: the unknown whose knowledge would determine f best
        # (the smallest conditional variance var_f - cov_fj^2 / var_j)
        cond = var[jf] - cov[jf] ** 2 / var
    cond[jf] = np.inf
    cond[~np.isfinite(cond)] = np.inf
    corr[~np.isfinite(corr)] = 0.0
    k = int(np.argmin(cond))
    rel = np.sqrt(var[jf]) / max(abs(x[jf]), 1e-12)
    if not (rel <= o.max_rel_sigma_f):
        extra = any(n not in CORE_PARAMS for n in names)
        label = np.array(model.column_names()[: S.shape[0]])[keep][k]
        raise _f_undetermined(rel, float(corr[k]), str(label),
                              " even with every additional parameter held fixed" if extra else "")


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
            cov = _reduced_covariance(model, result.jac.normal_equations()) * result.sigma0**2
            jf = names.index("f_mm")
            rel_images = np.sqrt(max(cov[jf, jf], 0.0)) / max(abs(result.x[jf]), 1e-12)
            if not model.targets_adjusted and rel_images <= o.max_rel_sigma_f:
                raise _survey_dominates(model, rel, rel_images)
            raise _f_undetermined(rel, *_f_determination(model, cov, fixed_extras=False)[1:])


def _survey_dominates(model, rel, rel_images) -> GeometryError:
    """The diagnosis when the fixed targets' survey errors, not the geometry, leave f undetermined
    (issue 26, goal 4): names the surveys with the largest sigmas and the remedies."""
    t = model.data.targets
    seen = np.unique(model.tgt)
    sig = t.sigma_mm[seen]
    order = np.argsort(-sig, kind="stable")
    top = order[sig[order] >= 0.5 * sig[order[0]]]
    ids = ", ".join(repr(str(x)) for x in t.ids[seen][top[:4]]) + (f" and {len(top) - 4} more" if len(top) > 4 else "")
    return GeometryError(
        f"the principal distance is not determined: its sigma is {100 * rel:.3g} % of f, and the survey "
        f"of the fixed targets makes it so (the image geometry alone gives {100 * rel_images:.2g} %): the "
        f"targets are held fixed and their survey errors enter the uncertainty; target(s) {ids} have "
        f"sigma_mm {sig[order[0]]:.4g} (the median is {np.median(sig):.3g}): adjust the targets "
        "(targets_adjusted, the default), give those points a realistic sigma_mm, or leave them "
        "unsurveyed (empty X, Y, Z in targets.csv)")


def adjust_field(data: FieldData, options: AdjustmentOptions | None = None, *,
                 progress: Callable[[str], None] | None = None, initial: InitialValues | None = None,
                 initial_targets_m=None) -> FieldResult:
    """Calibrate a camera from identified field observations (module docstring).

    The problem is solved in a frame whose origin is the rounded centroid of the observed
    targets (surveyed coordinates in a national grid or UTM, 1e5-1e6 m, would otherwise
    carry their offset into every difference and every stopping test); centres and targets
    are translated back, rotations and covariances do not change under a translation.

    Parameters
    ----------
    data : FieldData
    options : AdjustmentOptions, optional
    progress : callable, optional
        Called with one line per stage.
    initial : InitialValues, optional
        A warm start (e.g. a previous adjustment of most of the same points) instead of step 1,
        in the data's frame; its ``outliers`` start as suspects that are readmitted when they fit.
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
    _check_options(o)
    validate_field_data(data)
    check = check_point_mask(data.targets, ids=o.check_points, fraction=o.check_fraction, seed=o.check_seed)
    if not check.any():
        return _adjust(data, o, progress, initial, initial_targets_m)
    keep = ~check[data.obs.target]
    if progress:
        progress(f"{int(check.sum())} check point(s) withheld ({int((~keep).sum())} image points)")
    if initial is not None:
        initial = replace(initial, outliers=np.asarray(initial.outliers)[keep])
    res = _adjust(data.with_obs(data.obs.take(keep)), o, progress, initial, initial_targets_m)
    return _with_check_points(res, data, check, keep, o)


def _with_check_points(res: FieldResult, data: FieldData, check, keep, o) -> FieldResult:
    """The result over all of ``data``, the check points evaluated (:mod:`fieldcal.field.check_points`)."""
    vc = res.variance_components
    how = [f"session ({len(o.check_points)})"] if o.check_points else []
    if o.check_fraction > 0:
        how.append(f"stratified random fraction {o.check_fraction:g} (seed {o.check_seed})")
    cp = evaluate_check_points(
        data, check, res.params, res.estimate, res.R_world_to_camera, res.center_m, res.covariance,
        image_sigma_px=np.sqrt(data.obs.sigma_px**2 + vc.image_floor_px**2) * vc.unit_sigma,
        survey_sigma_mm=data.targets.sigma_mm * vc.survey_factor * vc.unit_sigma,
        snoop_alpha=o.snoop_alpha, selection=" and ".join(how))

    def expand(a, fill):
        out = np.full((len(keep), *np.shape(a)[1:]), fill, dtype=np.asarray(a).dtype)
        out[keep] = a
        return out

    residual, test = expand(res.residual_px, np.nan), expand(res.obs_test, np.nan)
    residual[cp.obs_index], test[cp.obs_index] = cp.residual_px, cp.statistic
    reason = expand(res.obs_reason.astype(object), CHECK_POINT).astype(str)
    initial = replace(res.initial, outliers=expand(res.initial.outliers, False))
    return replace(res, data=data, residual_px=residual, obs_used=expand(res.obs_used, False), obs_reason=reason,
                   obs_test=test, survey_used=res.survey_used & ~check, initial=initial, check_points=cp)


def _adjust(data: FieldData, o: AdjustmentOptions, progress, initial, initial_targets_m) -> FieldResult:
    """:func:`adjust_field` of the data without check points."""
    validate_field_data(data)
    local, origin = centred(data)
    board = _board_model(local, o)
    if board is not None:      # recorded as resolved: a re-adjustment (cross-validation) uses the same model
        o = replace(o, targets_adjusted=board == "points", board_model=board)
    full = tuple(p for p in FIELD_PARAMS if o.estimate is None or p in o.estimate)
    fixed = {p: "session" for p in FIELD_PARAMS if p not in full}
    _check_unsurveyed(data, o)
    if initial is not None:
        init = replace(initial, center_m=np.asarray(initial.center_m, float) - origin)
        if initial.targets_m is not None:
            init = replace(init, targets_m=np.asarray(initial.targets_m, float) - origin)
    else:
        init = initial_values(local, full)
    if progress:
        progress(f"initial values: {init.how}; f {init.params[0]:.4f} mm; "
                 f"{init.outliers.sum()} points flagged by the robust initialisers")
    flags = _Flags(local, init)
    solver = _Solver(local, o, init, progress)
    if initial_targets_m is not None and o.targets_adjusted:
        solver.X = np.array(initial_targets_m, float).reshape(-1, 3) - origin
    _start_unsurveyed(solver, flags)
    if board == "warp":
        observed = np.unique(local.obs.target)
        solver.warp = facing(board_warp(local.targets.xyz_m[observed]), init.center_m)
        solver.warp_mm = np.zeros(len(solver.warp.names))
    if progress and board is not None:
        progress(f"planar board: board model {board!r}")
    solver.free = _free_network(local, flags, o, progress, init.free_frame)
    solver.X_start = solver.X.copy()
    estimate = list(full)
    try:
        model, result = _solve_clean(solver, flags, estimate, o, "adjustment")
        while o.estimate is None:
            pick = _select_parameter(model, result, estimate, o)
            if pick is None:
                break
            name, why = pick
            fixed[name] = why
            solver.hold_fixed(model, result, estimate.index(name))
            estimate.remove(name)
            if progress:
                progress(f"holding {name} fixed at 0: {why}")
            model, result = _solve_clean(solver, flags, estimate, o, "re-adjustment")
        try:
            cov, s, corr = _final_stats(model, result, solver, o)
        except SingularSystemError as err:
            raise GeometryError(f"the interior orientation is not determined: {err}") from None
        _check_core_determined(model, result, corr, s, o)
    except SingularSystemError as err:
        raise GeometryError(_singular_diagnosis(err, solver.model)) from None
    # everything not used: reason 'initial outlier' left -> it is a blunder
    flags.reason[(flags.reason == "initial outlier")] = "blunder"
    res = _field_result(data, o, origin, solver, flags, model, result, (cov, s, corr), estimate, fixed, init)
    if board is not None:
        res = replace(res, board=_board_stats(board, solver, model, cov, origin))
    if progress:
        progress(_outcome_line(res, result.sigma0, bool(solver.vc.rounds)))
    return res


def _board_model(data: FieldData, o: AdjustmentOptions) -> str | None:
    """The board model of this adjustment (:func:`fieldcal.field.board.resolve_board_model`):
    a planar board is a field whose observed targets are all surveyed and coplanar to 1 um
    (:func:`fieldcal.field.board.is_planar_board`); a free datum adjusts the points."""
    observed = np.unique(data.obs.target)
    planar = bool(data.targets.surveyed[observed].all()) and is_planar_board(data.targets.xyz_m[observed])
    if planar and o.datum == "free" and o.board_model == "auto":
        return "points"
    board = resolve_board_model(o.board_model, planar, o.targets_adjusted)
    if board in ("warp", "rigid") and o.datum == "free":
        raise InputError(f"board_model {board!r} holds the targets fixed: a free network (datum 'free') adjusts "
                         "them; use board_model 'points' or the survey's datum", "adjustment options")
    return board


def _board_stats(board: str, solver, model, cov, origin) -> dict:
    """``stats.board``: the board model and, for the warp, its frame and fitted coefficients with
    their a-posteriori sigmas and correlations (docs/uncertainty.md section 2c)."""
    out = {"model": board, "planar_board": True}
    if board != "warp":
        return out
    w, j = solver.warp, slice(model.n_cam, model.n_int)
    c = solver.warp_mm
    C = cov[j, j]
    s = np.sqrt(np.diag(C))
    observed = np.unique(model.tgt)
    defl = w.deflection_mm(c, solver.X[observed])
    frame = w.to_dict()
    frame["origin_m"] = (w.origin_m + origin).tolist()
    return {**out, "deflection": "w(u, v) = warp_uu_mm (1 - u^2) + warp_vv_mm (1 - v^2) + warp_uv_mm u v "
                                 "along the normal (u, v in [-1, 1] over the targets)",
            "frame": frame,
            "coefficients_mm": {n: float(v) for n, v in zip(w.names, c, strict=True)},
            "sigma_mm": {n: float(v) for n, v in zip(w.names, s, strict=True)},
            "correlation": (C / np.outer(s, s)).tolist(),
            "peak_to_valley_mm": float(np.ptp(defl)) if len(defl) else 0.0}


UNPLACED = "unsurveyed target not intersected"
"""The residual table's ``reason`` of a point of an unsurveyed target the initial values could
not place (seen in fewer than two oriented images, or at too narrow an angle)."""


def _check_unsurveyed(data: FieldData, o: AdjustmentOptions) -> None:
    """Unsurveyed targets are unknowns: they cannot be held fixed."""
    observed = np.unique(data.obs.target)
    n = int((~data.targets.surveyed[observed]).sum())
    if n and not o.targets_adjusted:
        raise InputError(f"{n} observed target(s) are unsurveyed (e.g. "
                         f"{str(data.targets.ids[observed][~data.targets.surveyed[observed]][0])!r}); "
                         "their coordinates must be adjusted: targets cannot be held fixed", "targets")


def _start_unsurveyed(solver: _Solver, flags: _Flags) -> None:
    """Unsurveyed targets start at their intersections (``InitialValues.targets_m``) with no
    survey; the points of those that could not be placed are left out (:data:`UNPLACED`)."""
    flags.survey_active &= solver.data.targets.surveyed
    placed = np.isfinite(solver.X).all(axis=1)
    if placed.all():
        return
    solver.X[~placed] = 0.0
    lost = ~placed[solver.data.obs.target]
    flags.obs_active[lost] = False
    flags.reason[lost] = UNPLACED


def _free_network(data: FieldData, flags: _Flags, o: AdjustmentOptions, progress, free_frame: bool) -> bool:
    """Whether the datum is a free network (:mod:`fieldcal.field.datum`); then no survey enters."""
    observed = np.zeros(len(data.targets), bool)
    observed[data.obs.target[flags.obs_active]] = True
    n = int((observed & flags.survey_active).sum())
    free = o.datum == "free" or n < MIN_CONTROL_POINTS or free_frame
    if free:
        flags.survey_active[:] = False
        if progress:
            why = ("field.datum 'free'" if o.datum == "free" else "the network's start could not be moved onto "
                   "the survey" if free_frame and n >= MIN_CONTROL_POINTS else f"{n} surveyed target(s)")
            progress(f"datum: free network, inner constraints ({why}; surveyed coordinates serve as "
                     "initial values only)")
    return free


def _outcome_line(res: FieldResult, last_sigma0: float, reweighted: bool) -> str:
    """What this adjustment ended with: the parameters estimated and held, and its sigma0 -- the
    document's, of the session's own a-priori sigmas, which after a re-weighting by the variance
    components is not the last round's (that one is about 1 by construction)."""
    held = [n for n in FIELD_PARAMS if n not in res.estimate]
    text = f"adjusted: {', '.join(res.estimate)} estimated" + (f", {', '.join(held)} held at 0" if held else "")
    text += f"; sigma0 {res.sigma0:.3f}"
    if reweighted:
        text += (f" with the session's a-priori sigmas (the last round, re-weighted by the variance "
                 f"components: {last_sigma0:.3f})")
    return text


def _check_options(o: AdjustmentOptions) -> None:
    if o.board_model not in BOARD_MODELS:
        raise InputError(f"board_model must be one of {', '.join(map(repr, BOARD_MODELS))}, got {o.board_model!r}",
                         "adjustment options")
    if o.datum not in ("auto", "free"):
        raise InputError(f"datum must be 'auto' or 'free', got {o.datum!r}", "adjustment options")
    if o.datum == "free" and (o.check_points or o.check_fraction > 0):
        raise InputError("check points are compared with their survey in the control's frame: a free "
                         "network (datum 'free') has none; leave out check_points or the free datum",
                         "adjustment options")
    if o.method not in ("lmqn", "lm"):
        raise InputError(f"method must be 'lmqn' or 'lm', got {o.method!r}", "adjustment options")
    if not (np.isfinite(o.check_fraction) and 0.0 <= o.check_fraction < 1.0):
        raise InputError(f"check_fraction must lie in [0, 1), got {o.check_fraction}", "adjustment options")
    if o.estimate is not None:
        bad = [p for p in o.estimate if p not in FIELD_PARAMS]
        if bad:
            raise InputError(f"estimate names {bad}, not in the field method's set {list(FIELD_PARAMS)}",
                             "adjustment options")


def centred(data: FieldData) -> tuple[FieldData, np.ndarray]:
    """The data translated so that the rounded centroid of the observed surveyed targets is the origin.

    Returns the translated :class:`FieldData` (only the target coordinates change) and the
    origin (3,) [m] in the data's frame. Rounding to whole metres keeps the subtraction
    exact for coordinates of 10^5-10^6 m (Sterbenz), so a field in UTM and the same field
    in local coordinates become the same numbers up to the rounding of their inputs.
    """
    observed = np.unique(data.obs.target)
    observed = observed[data.targets.surveyed[observed]]          # unsurveyed targets: NaN
    origin = np.round(np.mean(data.targets.xyz_m[observed], axis=0)) if len(observed) else np.zeros(3)
    targets = replace(data.targets, xyz_m=data.targets.xyz_m - origin)
    return replace(data, targets=targets), origin


@dataclass
class _Flags:
    """What the procedure decides per observation and survey (module docstring, step 3)."""

    obs_active: np.ndarray        # (m,) bool
    reason: np.ndarray            # (m,) object: '' or why the point is not used
    test: np.ndarray              # (m,) snooping statistic
    survey_active: np.ndarray     # (n_targets,) bool
    red_img: np.ndarray           # (m,) redundancy of each image point (sum of its two numbers)
    red_sur: np.ndarray           # (n_targets,) redundancy of each survey (sum of its three)

    def __init__(self, data: FieldData, init: InitialValues):
        self.obs_active = ~init.outliers
        self.reason = np.where(init.outliers, "initial outlier", "").astype(object)
        self.test = np.full(len(data.obs), np.nan)
        self.survey_active = np.ones(len(data.targets), bool)
        self.red_img = np.full(len(data.obs), np.nan)
        self.red_sur = np.full(len(data.targets), np.nan)


def _solve_clean(solver, flags: _Flags, estimate, o, label):
    """Adjust, reject blunders, readmit what fits, adjust again until nothing changes."""
    data = solver.data
    for rnd in range(o.max_rounds):
        _drop_undetermined_targets(data, flags.obs_active, flags.survey_active, flags.reason, solver.X, solver.C)
        # before the very first solve: can this network determine f at all?
        check = (lambda m, x, J: _check_f_determinable(m, x, J, o)) if not solver.rounds else None
        model, result = solver.run(estimate, flags.obs_active, flags.survey_active, f"{label} {rnd + 1}",
                                   before=check)
        n = _gross_rejection(solver, model, result, flags.obs_active, flags.survey_active, flags.reason, o)
        if n == 0:
            n = _snooping(solver.problem, result, flags, o, solver.bar_active)
        # readmit initial outliers that now fit (they were only suspects)
        res = solver.residuals_all()
        s = data.obs.sigma_px * max(result.sigma0, 1.0)
        fits = (flags.reason == "initial outlier") & (np.hypot(res[:, 0], res[:, 1]) < 3.0 * s)
        flags.obs_active[fits] = True
        flags.reason[fits] = ""
        # a target whose rejected image points agree with each other: its survey is wrong
        if o.targets_adjusted:
            n += _blame_the_survey(solver, flags.obs_active, flags.survey_active, flags.reason,
                                   max(result.sigma0, 1.0))
        if n == 0 and not fits.any() and not _update_components(solver, model, result, flags, o):
            return model, result
    return model, result


def _update_components(solver, model, result, flags: _Flags, o) -> bool:
    """Step 4b with adjusted targets: estimate the image floor and the survey factor at a clean
    solution and re-weight when they moved (True: solve again)."""
    vc = solver.vc
    if not (o.variance_components and o.targets_adjusted):
        return False
    k = model.k
    v_px = result.r[: model.n_rows_image].reshape(-1, 2) * model.sigma_px[:, None]
    rho = flags.red_img[k]
    vc.image_redundancy = float(np.nansum(rho))
    floor = vc.image_floor_px
    if vc.image_redundancy >= MIN_GROUP_REDUNDANCY and np.all(np.isfinite(rho)):
        floor = image_floor_px(v_px, solver.sigma_px0[k], rho, vc.image_floor_px)
    factor = vc.survey_factor
    if len(model.survey_k):
        red_s = flags.red_sur[model.survey_k]
        vc.survey_redundancy = float(np.nansum(red_s))
        rel = group_factor(result.r[model.n_rows_image:model.n_rows], red_s)
        factor = vc.survey_factor * rel if np.isfinite(rel) else vc.survey_factor
    change = max(weight_change(solver.sigma_px0[k], vc.image_floor_px, floor), abs(factor / vc.survey_factor - 1.0))
    if change <= WEIGHT_TOLERANCE or vc.rounds >= MAX_COMPONENT_ROUNDS:
        return False
    solver.reweight(floor, factor)
    if solver.progress:
        solver.progress(f"variance components: image floor {floor:.4g} px, survey sigmas x {factor:.3g}; "
                        "re-weighted")
    return True


def _bar_report(solver, result, bars) -> dict:
    """The datum's account of the scale bars (observations of the adjustment,
    :mod:`fieldcal.field.scale_bars`): each bar in use with its residual and test statistic,
    and the bars rejected or not usable (an end no image point placed)."""
    sb = solver.data.scale_bars
    if sb is None or not len(sb):
        return {}
    ids = solver.data.targets.ids
    out: dict = {"n_scale_bars_unused": int(len(sb) - (len(bars) if bars is not None else 0)),
                 "rejected_scale_bars": [f"{ids[a]}-{ids[c]}" for a, c in
                                         zip(sb.from_target[~solver.bar_active], sb.to_target[~solver.bar_active],
                                             strict=True)]}
    if bars is None:
        return {**out, "scale_bars": []}
    ne = result.jac.normal_equations()
    rows = bars.report(result.x, ne.covariance_reduced(), result.sigma0, ids)
    qv = 1.0 - solver.problem.group_covariances(ne)[2]
    for row, q in zip(rows, qv, strict=True):
        row["redundancy"] = float(q)
        row["normalized_residual"] = (float(abs(row["residual_mm"]) / row["sigma_mm"] / np.sqrt(q) / result.sigma0)
                                      if q > 1e-8 else None)
    return {**out, "scale_bars": rows}


def _field_result(data, o, origin, solver, flags, model, result, stats, estimate, fixed, init) -> FieldResult:
    """The :class:`FieldResult`, centres and targets translated back to the data's frame."""
    cov, s, corr = stats
    s, corr = s[: model.n_cam], corr[: model.n_cam, : model.n_cam]     # the camera's (a board warp follows)
    params, R, C, _ = model.unpack(result.x)
    ne = result.jac.normal_equations()
    X, var_X = solver.targets_now(), None
    datum = {"type": "weighted control", "n_control": int(len(model.survey_k))}
    bars = solver.problem.bars
    if solver.free:
        fn = to_minimum_trace(model, result, R, C, solver.X, solver.X_start, bars, result.sigma0)
        R, C, X = fn.R, fn.C, fn.X
        cov = fn.cov_reduced * result.sigma0**2
        var_X = np.einsum("kii->ki", fn.cov_targets)
        datum = {"type": "free network", "constraints": "inner (minimum trace over the adjusted targets)",
                 "scale": f"{len(bars)} scale bar(s)" if bars is not None
                 else "the initial values' (no scale bars)", **fn.info}
    datum.update(_bar_report(solver, result, bars))
    ext_var = np.diag(cov)[model.n_int:].reshape(-1, 6)
    sigma_C = np.sqrt(ext_var[:, 3:])
    sigma_X = None
    if o.targets_adjusted:
        sigma_X = np.full((len(data.targets), 3), np.nan)    # NaN: not adjusted (no image sees it)
        if var_X is None:
            var_X = np.einsum("kii->ki", covariance_blocks(model, ne)[1])
        sigma_X[model.target_index] = np.sqrt(var_X) * result.sigma0
    sigma = {n: float(s[j]) for j, n in enumerate(estimate)}
    targets_m = X + origin
    adjusted = np.zeros(len(data.targets), bool)
    adjusted[model.target_index] = True
    targets_m[~solver.data.targets.surveyed & ~adjusted] = np.nan     # unsurveyed, not placed
    survey_res = (solver.data.targets.xyz_m - X) * 1000.0
    residual_px = solver.residuals_all()
    sigma0 = result.sigma0
    if solver.vc.rounds:           # re-weighted: sigma0 of the session's own a-priori sigmas
        used = flags.obs_active
        ss = np.sum((residual_px[used] / solver.sigma_px0[used, None]) ** 2)
        ss += np.sum((survey_res[model.survey_k] / solver.sigma_mm0[model.survey_k, None]) ** 2)
        ss += np.sum(result.r[model.n_rows:solver.problem.n_rows_data] ** 2)       # bars: not re-weighted
        m, n = result.jac.shape
        sigma0 = float(np.sqrt(ss / (m - n))) if m > n else float("nan")
    init = replace(init, center_m=init.center_m + origin)
    return FieldResult(
        data=data, options=o, params=params, estimate=tuple(estimate), fixed_parameters=fixed,
        sigma=sigma, sigma0=sigma0, covariance=cov, covariance_names=model.column_names()[: model.n_reduced],
        correlation_interior=corr, R_world_to_camera=R, center_m=C + origin, sigma_center_m=sigma_C,
        targets_m=targets_m, sigma_targets_m=sigma_X, residual_px=residual_px,
        obs_used=flags.obs_active.copy(), obs_reason=flags.reason.astype(str), obs_test=flags.test,
        survey_used=flags.survey_active.copy(), survey_residual_mm=survey_res, lsq=result,
        iterations_total=solver.iterations, initial=init, rounds=solver.rounds, variance_components=solver.vc,
        datum=datum)


def unsurveyed_account(targets, observed_targets, unlisted, targets_m, sigma_targets_m) -> dict:
    """The document's account of the unsurveyed targets (CONTRACT section 3): how many the
    adjustment estimated among ``observed_targets`` (indices of the points in use), the ids
    targets.csv does not list, and each one's adjusted coordinates [m] and sigmas [mm] (``{}``
    when every target is surveyed). The single camera's and the rig's documents share it."""
    observed = np.unique(observed_targets)
    uns = observed[~targets.surveyed[observed]]
    unlisted = list(unlisted)
    if not len(uns) and not unlisted:
        return {}
    sigma = (sigma_targets_m[uns] * 1000.0 if sigma_targets_m is not None else np.full((len(uns), 3), np.nan))
    return {"n_unsurveyed_targets": int(len(uns)), "n_unlisted_targets": len(unlisted),
            "unlisted_targets": unlisted,
            "unsurveyed_targets": [{"id": str(targets.ids[j]), "xyz_m": [float(v) for v in targets_m[j]],
                                    "sigma_mm": [float(v) for v in sig]}
                                   for j, sig in zip(uns, sigma, strict=True)]}
