r"""How precise the field observations really were: variance components and survey errors.

The adjustment weights every observation by its a-priori sigma (an image point's
``sigma_px``, a surveyed coordinate's ``sigma_mm``). A single a-posteriori factor
``sigma0`` scales the covariance when those sigmas are wrong by one common factor; it cannot
help when they are wrong in different ways (docs/uncertainty.md):

* **Image points measured from images** carry a-priori sigmas from the centre detector
  (~0.004 px for a well exposed disc) that describe the pixel noise only, not what the PSF,
  defocus, the illumination across a disc or a marker's edges add. Those errors do not
  shrink with the signal: they act as a **floor** ``phi`` added in quadrature,
  ``sigma_k^2 -> sigma_k^2 + phi^2``. With the floor the precise points stop dominating
  the solution (and its covariance), as they must when their precision is not real.
* **Surveys and images** are two groups with their own factors: an image factor does not
  say how good the survey was (Helmert's variance components).
* **Targets held fixed** (``targets_adjusted=False``, as the field paper does): the survey
  errors do not disappear, they move into the image residuals, identically in every image
  that sees the target. ``sigma0^2 N^-1`` treats them as independent per image point and
  is too small by a factor of 2-4 on the synthetic fields; :func:`survey_consider_matrix`
  propagates them as the correlated errors they are ("consider parameters").

Estimation (Foerstner's simplified variance-component estimate)
--------------------------------------------------------------
For unit-weight residuals ``r`` of a least-squares fit with Jacobian ``J``, the redundancy
numbers are the diagonal of ``R = I - J N^-1 J^T`` (``N = J^T J``); an observation group
``g`` has redundancy ``r_g = sum_{i in g} R_ii`` and ``E[r_g^T r_g] = r_g`` when its sigmas
are right. Hence

* the survey factor ``s_s^2 = r_s^T r_s / r_s`` (:func:`group_factor`), and
* the image floor (:func:`image_floor_px`): with the current weights
  ``w_k = 1 / (sigma_k^2 + phi^2)``, residuals ``v_k`` (2-vectors, px) and redundancies
  ``rho_k`` (the sum of the point's two numbers), the moment equation
  ``sum w_k |v_k|^2 = sum w_k rho_k (sigma_k^2 + phi'^2)`` gives
  ``phi'^2 = (sum w_k |v_k|^2 - sum w_k rho_k sigma_k^2) / sum w_k rho_k``, clamped at 0
  (a-priori sigmas that are too large are left to ``sigma0``).

The adjustment re-weights with the new values and re-solves from where it stands (a warm
start, a few iterations) until the weights change by less than
:data:`WEIGHT_TOLERANCE`; then ``sigma0 ~ 1`` and ``sigma0^2 N^-1`` is the covariance.

Survey errors of fixed targets (consider covariance)
----------------------------------------------------
With the targets held at their surveyed coordinates ``X_s = X + e``, ``e ~ N(0, S)``
(``S`` diagonal, ``sigma_mm`` per coordinate), the image residuals are
``r = eps + J_X e`` (``J_X = d r / d X``, unit weight) and the estimate moves by
``N^-1 J^T r``. Its covariance is the sandwich

    Cov = s^2 (N^-1 + N^-1 M N^-1),     M = B S B^T,   B = J^T J_X

over the reduced unknowns (interior and exterior orientations), ``B`` summed per target
(:func:`survey_consider_matrix`). The common factor ``s^2`` is the ``sigma0^2`` of this
complete error model, ``r^T r / E[r^T r]`` with
``E[r^T r] = (m - n) + tr(J_X S J_X^T) - tr(N^-1 M)``: the survey part of the residuals
is expected, only the rest is news about the a-priori sigmas (taken at least 1:
:func:`fixed_target_covariance`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse

from fieldcal.field import consider_kernel

__all__ = ["VarianceComponents", "WEIGHT_TOLERANCE", "MIN_GROUP_REDUNDANCY", "image_floor_px",
           "group_factor", "weight_change", "survey_consider_matrix", "fixed_target_covariance"]

WEIGHT_TOLERANCE = 0.10
"""Re-weight (and re-solve) only when some observation's sigma changes by more than this fraction."""

MIN_GROUP_REDUNDANCY = 20.0
"""A group's factor is estimated only from at least this much redundancy (sampling error of the
estimated sigma factor ~ 1 / sqrt(2 r) = 16 % at r = 20)."""


@dataclass
class VarianceComponents:
    """The variance components the adjustment used (``stats.variance_components``).

    Attributes
    ----------
    image_floor_px : float
        ``phi``: added in quadrature to every image point's a-priori sigma [px].
    survey_factor : float
        The surveyed coordinates' sigmas were multiplied by this.
    image_redundancy, survey_redundancy : float
        The groups' redundancies (sums of redundancy numbers) in the last estimate.
    rounds : int
        Re-weighted re-solutions made.
    survey_consider : bool
        Targets held fixed: the survey errors are propagated into the covariance
        (:func:`fixed_target_covariance`).
    error_model_factor : float or None
        With ``survey_consider``: the ``sigma0`` of the complete error model (module docstring).
    unit_sigma : float
        The factor of the (re-weighted) a-priori sigmas in the final covariance: the last
        solve's ``sigma0``, or ``error_model_factor``.
    """

    image_floor_px: float = 0.0
    survey_factor: float = 1.0
    image_redundancy: float = float("nan")
    survey_redundancy: float = float("nan")
    rounds: int = 0
    survey_consider: bool = False
    error_model_factor: float | None = None
    unit_sigma: float = 1.0

    def to_dict(self) -> dict:
        def num(v):
            return None if v is None or not np.isfinite(v) else float(v)

        return {"image_floor_px": float(self.image_floor_px), "survey_factor": float(self.survey_factor),
                "image_redundancy": num(self.image_redundancy),
                "survey_redundancy": num(self.survey_redundancy), "rounds": int(self.rounds),
                "survey_consider": bool(self.survey_consider),
                "error_model_factor": num(self.error_model_factor), "unit_sigma": num(self.unit_sigma)}


def image_floor_px(residual_px, sigma_px, redundancy, floor_px: float = 0.0) -> float:
    """The floor ``phi`` [px] that makes the image points' variance factor 1 (module docstring).

    Parameters
    ----------
    residual_px : (m, 2) array_like
        Residuals of the image points [px].
    sigma_px : (m,) array_like
        Their a-priori sigmas, without a floor [px].
    redundancy : (m,) array_like
        Each point's redundancy (the sum of its two redundancy numbers, 0..2) in the fit
        weighted with ``floor_px``.
    floor_px : float
        The floor the fit was weighted with [px].

    Returns
    -------
    float
        The new floor [px] (0 when the residuals are not larger than the sigmas say).
    """
    v2 = np.sum(np.square(np.asarray(residual_px, float)), axis=1)
    s2 = np.square(np.asarray(sigma_px, float))
    rho = np.asarray(redundancy, float)
    w = 1.0 / (s2 + floor_px**2)
    denom = float(np.sum(w * rho))
    if not denom > 0:
        return 0.0
    phi2 = (float(np.sum(w * v2)) - float(np.sum(w * rho * s2))) / denom
    return float(np.sqrt(phi2)) if phi2 > 0 else 0.0


def group_factor(weighted_residuals, redundancy) -> float:
    """``sqrt(r^T r / r_g)``: the sigma factor of a group of unit-weight residuals; NaN below
    :data:`MIN_GROUP_REDUNDANCY`."""
    r = np.asarray(weighted_residuals, float).ravel()
    red = float(np.sum(redundancy))
    if red < MIN_GROUP_REDUNDANCY:
        return float("nan")
    return float(np.sqrt(r @ r / red))


def weight_change(sigma_px, floor_old_px: float, floor_new_px: float) -> float:
    """Largest relative change of an image point's sigma when the floor changes."""
    s2 = np.square(np.asarray(sigma_px, float))
    if not len(s2):
        return 0.0
    ratio = np.sqrt((s2 + floor_new_px**2) / (s2 + floor_old_px**2))
    return float(np.max(np.abs(ratio - 1.0)))


def survey_consider_matrix(d_int, d_ext, image, target, sigma_m, n_images: int, *,
                           implementation: str = "auto"):
    """``M = B S B^T`` and ``tr(J_X S J_X^T)`` of fixed targets' survey errors (module docstring).

    Parameters
    ----------
    d_int : (m, 2, p) ndarray
        Unit-weight derivatives of the image residuals by the interior unknowns.
    d_ext : (m, 2, 6) ndarray
        ... by the image's exterior unknowns (rotation increment, centre [m]); the derivative
        by the target's coordinates is ``-d_ext[:, :, 3:]`` (the ray depends on ``X - C``).
    image, target : (m,) int ndarray
        The image and target of each point.
    sigma_m : (m,) ndarray
        The survey sigma of each point's target [m].
    n_images : int
    implementation : {"auto", "numba", "numpy"}
        The compiled kernel of :mod:`fieldcal.field.consider_kernel` (``"auto"``: where it
        compiles) or the NumPy reference (a sparse ``B`` and ``B @ B.T``).

    Returns
    -------
    M : (p + 6 n_images, p + 6 n_images) ndarray
        Over the reduced unknowns ``[interior | exterior by image]``.
    trace_q : float
        ``tr(J_X S J_X^T)``: the expected sum of squared residuals the survey errors cause
        before the fit absorbs part of them.
    """
    d_int, d_ext = np.asarray(d_int, float), np.asarray(d_ext, float)
    m, _, p = d_int.shape
    n_r = p + 6 * n_images
    sigma_m = np.asarray(sigma_m, float)
    trace_q = float(np.einsum("kab,kab,k->", d_ext[:, :, 3:], d_ext[:, :, 3:], sigma_m**2))   # |J_X S^(1/2)|^2
    kern = None if implementation == "numpy" else consider_kernel.kernel()
    if implementation == "numba" and kern is None:
        raise RuntimeError(consider_kernel.status())
    if kern is not None and m:
        order = np.argsort(np.asarray(target), kind="stable")
        ptr = np.flatnonzero(np.r_[True, np.diff(np.asarray(target)[order]) != 0, True])
        M = np.zeros((n_r, n_r))
        kern(np.ascontiguousarray(d_int), np.ascontiguousarray(d_ext), np.ascontiguousarray(sigma_m),
             np.asarray(image, np.int64), order.astype(np.int64), ptr.astype(np.int64), M)
        return 0.5 * (M + M.T), trace_q
    JX = -d_ext[:, :, 3:] * sigma_m[:, None, None]                           # (m, 2, 3), S^(1/2) in
    D = np.concatenate([d_int, d_ext], axis=2)                               # (m, 2, p + 6)
    P = np.einsum("kai,kaj->kij", D, JX)                                     # (m, p + 6, 3)
    rows = np.concatenate([np.broadcast_to(np.arange(p), (m, p)),
                           p + 6 * np.asarray(image)[:, None] + np.arange(6)], axis=1)  # (m, p + 6)
    _, tpos = np.unique(np.asarray(target), return_inverse=True)
    cols = 3 * tpos[:, None] + np.arange(3)                                  # (m, 3)
    B = scipy.sparse.csr_matrix(
        (P.ravel(), (np.repeat(rows[:, :, None], 3, axis=2).ravel(),
                     np.broadcast_to(cols[:, None, :], P.shape).ravel())),
        shape=(n_r, 3 * (int(tpos.max()) + 1) if m else 0))
    M = (B @ B.T).toarray()
    return 0.5 * (M + M.T), trace_q


def fixed_target_covariance(cov_unit, M, residual_ss: float, dof: int, trace_q: float):
    """The covariance of an adjustment with fixed targets, their survey errors included.

    Parameters
    ----------
    cov_unit : (n_r, n_r) ndarray
        ``N^-1`` over the reduced unknowns (unit weight).
    M : (n_r, n_r) ndarray
        :func:`survey_consider_matrix`.
    residual_ss : float
        ``r^T r`` of the unit-weight image residuals.
    dof : int
        ``m - n``: observations minus unknowns.
    trace_q : float
        From :func:`survey_consider_matrix`.

    Returns
    -------
    cov : (n_r, n_r) ndarray
        ``s^2 (N^-1 + N^-1 M N^-1)``.
    factor : float
        ``s``, the sigma0 of the complete error model, at least 1: the blunder rejection
        tests the residuals as independent errors and trims the points of the worst-surveyed
        targets (2-5 % on the synthetic fields, ``s`` 0.89-0.98), so a factor below 1 is no
        evidence that the stated survey sigmas were pessimistic.
    """
    CM = cov_unit @ M
    expected = dof + trace_q - float(np.trace(CM))
    s2 = residual_ss / expected if expected > 0 else residual_ss / max(dof, 1)
    s2 = max(s2, 1.0)
    cov = s2 * (cov_unit + CM @ cov_unit)
    return 0.5 * (cov + cov.T), float(np.sqrt(s2))
