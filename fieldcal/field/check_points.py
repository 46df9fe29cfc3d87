r"""Independent check points: surveyed targets withheld from the adjustment, and what they say.

A calibration's residuals describe the points that made it; they are no test of it. Check
points are: surveyed targets whose image points and coordinates the adjustment never saw
(not for the initial values either). After the adjustment they are measured again with the
calibrated camera and the adjusted exterior orientations (docs/uncertainty.md):

* **Object space** [mm]. Each check point seen in at least two images from directions at
  least ~5 degrees apart (the normal matrix of its intersection, ``N_X`` below, has a
  condition number of at most :data:`MAX_INTERSECTION_CONDITION`; images of one station
  see it along one ray) is intersected: the
  point ``X`` minimising the image residuals of its image points (Gauss-Newton over ``X``
  alone, the camera and orientations held; weighted by the image points' sigmas), started
  at the surveyed coordinates. Its difference from the survey ``d = X - X_s`` has the
  predicted covariance

      Cov(d) = N_X^-1 + G Sigma_p G^T + S,      G = N_X^-1 J_X^T J_p

  with ``N_X = J_X^T J_X`` (unit weight), ``Sigma_p`` the adjustment's covariance of the
  interior and exterior orientations (first order: the intersection moves with the
  camera), and ``S`` the survey's own covariance. ``rms_mm`` is
  ``sqrt(mean |d|^2)`` (per point, 3-D), ``rms_mm_predicted`` ``sqrt(mean tr Cov(d))``, and
  ``chi2_mm = sum d^T Cov(d)^-1 d`` on ``3 n`` degrees of freedom tests the two together.
* **Image space** [px]. Every image point of a check point against the projection of its
  surveyed coordinates: ``e = uv - uv(X_s)``, predicted
  ``Cov(e) = sigma^2 I + J_X S J_X^T + J_p Sigma_p J_p^T``; ``rms_px`` is
  ``sqrt(mean |e|^2)`` per point, as the document's ``rmse_px``.

Image points of check points whose image-space statistic ``e^T Cov(e)^-1 e`` exceeds the
chi-square quantile of ``snoop_alpha`` (2 degrees of freedom) are counted as rejected and
left out of both (a wrong identification says nothing about the calibration).

Sigmas are the adjustment's, with its variance components: an image point's
``sqrt(sigma^2 + floor^2)`` and a survey's ``sigma_mm`` times the survey factor, both times the
final unit-weight factor (:class:`fieldcal.field.variance_components.VarianceComponents`).

Choosing check points
---------------------
A session names them (``session.json`` ``check_points``: target ids), or the library draws a
fraction at random, stratified over the field (:func:`stratified_check_points`): the targets
are binned on a grid in the field's best-fitting plane (about ``1 / fraction`` targets per
cell) and each cell gives its share, so the check points cover the field as the targets
do. Plain (uncoded) targets are preferred: the coded ones seed the identification.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import chdtrc, chdtri  # chi2.sf(x, k), chi2.isf(p, k) without scipy.stats

from fieldcal.errors import InputError
from fieldcal.field.bundle import BundleModel
from fieldcal.session.data import FieldData, TargetField

__all__ = ["CheckPoints", "check_point_mask", "stratified_check_points", "evaluate_check_points",
           "GAUSS_NEWTON_ITERATIONS", "MAX_INTERSECTION_CONDITION"]

MAX_INTERSECTION_CONDITION = 300.0
"""Largest condition number of an intersection's 3 x 3 normal matrix (two rays: about 5 degrees
apart, the depth 10 times less precise than the position across the rays)."""
GAUSS_NEWTON_ITERATIONS = 6
"""Iterations of the intersection (from the survey, a few mm away: converged after 2-3)."""


@dataclass
class CheckPoints:
    """What the check points say about a calibration (module docstring).

    Attributes
    ----------
    ids : (n,) ndarray of str
        The check points intersected in object space.
    error_mm : (n, 3) ndarray
        Intersected minus surveyed [mm].
    cov_mm2 : (n, 3, 3) ndarray
        Predicted covariance of ``error_mm`` [mm^2].
    n_images : (n,) ndarray of int
    obs_index : (k,) ndarray of int
        The image points of check points (indices into the data's observations).
    residual_px : (k, 2) ndarray
        Measured minus projected surveyed coordinates [px].
    cov_px2 : (k, 2, 2) ndarray
        Their predicted covariance [px^2].
    used : (k,) bool ndarray
        False for the image points rejected (module docstring).
    statistic : (k,) ndarray
        ``e^T Cov(e)^-1 e`` of each image point.
    selection : str
        How they were chosen.
    """

    ids: np.ndarray
    error_mm: np.ndarray
    cov_mm2: np.ndarray
    n_images: np.ndarray
    obs_index: np.ndarray
    residual_px: np.ndarray
    cov_px2: np.ndarray
    used: np.ndarray
    statistic: np.ndarray
    selection: str = ""
    n_withheld: int = 0
    extra: dict = field(default_factory=dict)

    def rms_mm(self) -> float | None:
        return _rms(self.error_mm)

    def rms_mm_predicted(self) -> float | None:
        return float(np.sqrt(np.mean(np.einsum("kii->k", self.cov_mm2)))) if len(self.ids) else None

    def rms_px(self) -> float | None:
        return _rms(self.residual_px[self.used])

    def rms_px_predicted(self) -> float | None:
        c = self.cov_px2[self.used]
        return float(np.sqrt(np.mean(np.einsum("kii->k", c)))) if len(c) else None

    def chi2_mm(self) -> float | None:
        if not len(self.ids):
            return None
        w = np.linalg.solve(self.cov_mm2, self.error_mm[..., None])[..., 0]
        return float(np.einsum("ki,ki->", self.error_mm, w))

    def axis_stats(self) -> dict:
        """Per world axis X, Y, Z of the object-space errors [mm]: ``rms_x_mm`` (and y, z),
        ``mean_x_mm`` (a bias), ``max_x_mm`` (the largest absolute), ``rms_x_mm_predicted``;
        None without intersected check points."""
        out = {}
        e = np.asarray(self.error_mm, float).reshape(-1, 3)
        sd = np.einsum("kii->ki", np.asarray(self.cov_mm2, float).reshape(-1, 3, 3))
        for j, a in enumerate("xyz"):
            have = len(e) > 0
            out[f"rms_{a}_mm"] = float(np.sqrt(np.mean(e[:, j] ** 2))) if have else None
            out[f"mean_{a}_mm"] = float(np.mean(e[:, j])) if have else None
            out[f"max_{a}_mm"] = float(np.max(np.abs(e[:, j]))) if have else None
            out[f"rms_{a}_mm_predicted"] = float(np.sqrt(np.mean(sd[:, j]))) if have else None
        return out

    def to_stats(self) -> dict:
        """The document's ``stats.check_points`` (the certificate reads ``rms_px``, ``rms_mm`` and
        the per-axis figures of :meth:`axis_stats`)."""
        chi = self.chi2_mm()
        dof = 3 * len(self.ids)
        return {
            "n_withheld": int(self.n_withheld), "n": int(len(self.ids)),
            "n_observations": int(self.used.sum()), "n_rejected": int((~self.used).sum()),
            "rms_mm": self.rms_mm(), "rms_mm_predicted": self.rms_mm_predicted(),
            **self.axis_stats(),
            "rms_px": self.rms_px(), "rms_px_predicted": self.rms_px_predicted(),
            "chi2_mm": chi, "dof_mm": int(dof),
            "p_value_mm": None if chi is None else float(chdtrc(dof, chi)),
            "selection": self.selection,
        }


def _rms(e) -> float | None:
    e = np.asarray(e, float)
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1)))) if len(e) else None


# ---------------------------------------------------------------------------- choosing
def stratified_check_points(targets: TargetField, fraction: float, seed: int = 0) -> np.ndarray:
    """A random, spatially stratified ``fraction`` of the targets (module docstring).

    Returns
    -------
    (n,) bool ndarray
        True for the targets chosen.
    """
    if not (np.isfinite(fraction) and 0.0 <= fraction < 1.0):
        raise InputError(f"check-point fraction must lie in [0, 1), got {fraction}", "check points")
    n = len(targets)
    chosen = np.zeros(n, bool)
    n_pick = int(round(fraction * n))
    if n_pick == 0:
        return chosen
    rng = np.random.default_rng(seed)
    X = targets.xyz_m - targets.xyz_m.mean(axis=0)
    _, _, Vt = np.linalg.svd(X, full_matrices=False)
    ab = X @ Vt[:2].T                                               # in the field's best plane
    n_cells = max(1, int(round(np.sqrt(n_pick))))
    edges = [np.quantile(ab[:, j], np.linspace(0, 1, n_cells + 1)[1:-1]) for j in range(2)]
    cell = np.searchsorted(edges[0], ab[:, 0]) * n_cells + np.searchsorted(edges[1], ab[:, 1])
    # within a cell: plain targets first (random order), then coded ones; cells take turns
    key = rng.random(n) + (targets.codes >= 0)
    order = np.lexsort((key, cell))
    rank = np.empty(n, np.int64)
    starts = np.searchsorted(cell[order], np.arange(n_cells * n_cells))
    rank[order] = np.arange(n) - starts[cell[order]]
    share = rank / np.maximum(np.bincount(cell, minlength=n_cells * n_cells)[cell], 1)
    turn = np.lexsort((rng.random(n), share))                       # the smallest shares first
    chosen[turn[:n_pick]] = True
    return chosen


def check_point_mask(targets: TargetField, *, ids=(), fraction: float = 0.0, seed: int = 0) -> np.ndarray:
    """The targets to withhold: the named ``ids`` and a stratified ``fraction`` of the rest.

    Raises
    ------
    InputError
        An id that targets.csv does not hold.
    """
    index = targets.index()
    unknown = [str(t) for t in ids if str(t) not in index]
    if unknown:
        raise InputError(f"check point(s) {unknown[:5]} are not in targets.csv", "check_points")
    mask = np.zeros(len(targets), bool)
    mask[[index[str(t)] for t in ids]] = True
    if (mask & ~targets.surveyed).any():
        raise InputError(f"check point {str(targets.ids[mask & ~targets.surveyed][0])!r} is unsurveyed: "
                         "a check point needs surveyed coordinates", "check_points")
    if fraction > 0:
        surveyed = targets.surveyed
        if surveyed.all():
            mask |= stratified_check_points(targets, fraction, seed)
        else:           # drawn among the surveyed targets only
            from dataclasses import replace
            sub = replace(targets, ids=targets.ids[surveyed], xyz_m=targets.xyz_m[surveyed],
                          sigma_mm=targets.sigma_mm[surveyed], codes=targets.codes[surveyed], normals=None)
            mask[np.flatnonzero(surveyed)[stratified_check_points(sub, fraction, seed)]] = True
    return mask


# ---------------------------------------------------------------------------- evaluating
def evaluate_check_points(data: FieldData, check: np.ndarray, params, estimate, R_world_to_camera, center_m,
                          covariance, *, image_sigma_px, survey_sigma_mm, snoop_alpha: float = 1e-6,
                          selection: str = "") -> CheckPoints:
    """Measure the withheld targets with a calibration (module docstring).

    Parameters
    ----------
    data : FieldData
        All observations (those of the check points included).
    check : (n_targets,) bool ndarray
        The check points.
    params : (13,) ndarray
        The calibrated camera.
    estimate : sequence of str
        Its estimated parameters (the first rows of ``covariance``).
    R_world_to_camera : (n_images, 3, 3) ndarray
    center_m : (n_images, 3) ndarray
        The adjusted exterior orientations, in the data's frame.
    covariance : (p + 6 n_images, p + 6 n_images) ndarray
        A-posteriori covariance of ``[interior | exterior]`` (rotation increments [rad],
        centres [m]).
    image_sigma_px : (m,) ndarray
        Effective sigma of every image point [px].
    survey_sigma_mm : (n_targets,) ndarray
        Effective sigma of every surveyed coordinate [mm].

    Returns
    -------
    CheckPoints
    """
    k_all = np.flatnonzero(check[data.obs.target])
    origin = np.round(np.mean(data.targets.xyz_m[check], axis=0)) if check.any() else np.zeros(3)
    local = replace(data, targets=replace(data.targets, xyz_m=data.targets.xyz_m - origin,
                                          sigma_mm=np.asarray(survey_sigma_mm, float)),
                    obs=replace(data.obs, sigma_px=np.asarray(image_sigma_px, float)))
    C_local = np.asarray(center_m, float) - origin
    cov = np.asarray(covariance, float)
    used = np.ones(len(k_all), bool)
    stat = np.full(len(k_all), np.nan)
    res_px = np.full((len(k_all), 2), np.nan)
    cov_px = np.full((len(k_all), 2, 2), np.nan)
    lim = chdtri(2, snoop_alpha)
    while True:
        active = np.zeros(len(data.obs), bool)
        active[k_all[used]] = True
        model = BundleModel(local, params, estimate, R_world_to_camera, targets_adjusted=True,
                            obs_active=active, survey_active=np.zeros(len(data.targets), bool))
        pos = np.searchsorted(k_all, model.k)
        e, ce = _image_space(model, C_local, cov)
        res_px[pos], cov_px[pos] = e, ce
        stat[pos] = np.einsum("ki,ki->k", e, np.linalg.solve(ce, e[..., None])[..., 0])
        bad = used & (stat > lim)
        if not bad.any():
            break
        used &= ~(stat >= np.max(stat[bad]) * 0.25)        # the clearly worst, as data snooping does
    ids, err, cm, nim = _object_space(model, C_local, cov) if active.any() else _empty_object()
    return CheckPoints(ids=ids, error_mm=err, cov_mm2=cm, n_images=nim, obs_index=k_all, residual_px=res_px,
                       cov_px2=cov_px, used=used, statistic=stat, selection=selection,
                       n_withheld=int(check.sum()))


def _empty_object():
    return np.zeros(0, str), np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros(0, np.int64)


def _orientation_blocks(model, cov):
    """Per image point: the derivative columns' indices into ``cov`` (interior + its image)
    and the covariance block over them ((k, p + 6, p + 6))."""
    p = model.n_int
    cols = np.concatenate([np.broadcast_to(np.arange(p), (len(model.img), p)),
                           p + 6 * model.img[:, None] + np.arange(6)], axis=1)
    return cols, cov[cols[:, :, None], cols[:, None, :]]


def _image_space(model, C_local, cov):
    """Residuals (k, 2) [px] at the surveyed coordinates and their predicted covariance."""
    x = model.pack(model.params0, C_local, model.data.targets.xyz_m)
    r, jb, _ = model.residuals_and_blocks(x, True)
    s = model.sigma_px
    e = r[: model.n_rows_image].reshape(-1, 2) * s[:, None]
    Dp = np.concatenate([jb.d_int, jb.d_ext], axis=2)                  # (k, 2, p + 6), unit weight
    _, Cp = _orientation_blocks(model, cov)
    S = (model.data.targets.sigma_mm[model.tgt] / 1000.0) ** 2
    unit = (np.eye(2) + S[:, None, None] * np.einsum("kai,kbi->kab", jb.d_tgt, jb.d_tgt)
            + np.einsum("kai,kij,kbj->kab", Dp, Cp, Dp))
    return e, unit * (s**2)[:, None, None]


def _object_space(model, C_local, cov):
    """Intersect the check points seen in two or more images (module docstring)."""
    t_slot, n_t = model.tgt_slot, len(model.target_index)
    pairs = np.unique(t_slot * model.n_images + model.img)
    n_img = np.bincount(pairs // model.n_images, minlength=n_t)
    x = model.pack(model.params0, C_local, model.data.targets.xyz_m)
    X = x[model.n_reduced:].reshape(-1, 3)
    for _ in range(GAUSS_NEWTON_ITERATIONS):
        r, jb, _ = model.residuals_and_blocks(x, True)
        rk = r[: model.n_rows_image].reshape(-1, 2)
        N = np.zeros((n_t, 3, 3))
        g = np.zeros((n_t, 3))
        np.add.at(N, t_slot, np.einsum("kai,kaj->kij", jb.d_tgt, jb.d_tgt))
        np.add.at(g, t_slot, np.einsum("kai,ka->ki", jb.d_tgt, rk))
        ok = (n_img >= 2) & (np.linalg.cond(N) <= MAX_INTERSECTION_CONDITION)
        h = np.zeros((n_t, 3))
        h[ok] = -np.linalg.solve(N[ok], g[ok][..., None])[..., 0]
        X = X + h
        x[model.n_reduced:] = X.ravel()
        if np.all(np.abs(h) < 1e-9):
            break
    # covariance: N^-1 + G Sigma_p G^T with G = N^-1 sum_k J_X^T J_p (rows of the orientation unknowns)
    Dp = np.concatenate([jb.d_int, jb.d_ext], axis=2)
    cols, _ = _orientation_blocks(model, cov)
    H = np.zeros((n_t, 3, cov.shape[0]))
    contrib = np.einsum("kai,kaj->kij", jb.d_tgt, Dp)                  # (k, 3, p + 6)
    np.add.at(H, (t_slot[:, None, None], np.arange(3)[None, :, None], cols[:, None, :]), contrib)
    Ni = np.linalg.inv(N[ok])
    G = Ni @ H[ok]
    covX = Ni + np.einsum("tin,nm,tjm->tij", G, cov, G)
    S = (model.data.targets.sigma_mm[model.target_index[ok]] / 1000.0) ** 2
    cov_d = (covX + S[:, None, None] * np.eye(3)) * 1e6                # [mm^2]
    err = (X[ok] - model.data.targets.xyz_m[model.target_index[ok]]) * 1000.0
    return model.data.targets.ids[model.target_index[ok]], err, cov_d, n_img[ok]
