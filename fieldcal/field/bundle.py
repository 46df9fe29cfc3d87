"""The self-calibrating bundle model of the field method: residuals and analytic Jacobian.

Unknowns (the layout of the parameter vector ``x``)::

    x = [ interior (the estimated subset of PARAM_NAMES)      n_cam
          board warp (fieldcal.field.board, fixed targets)    n_warp    (n_int = n_cam + n_warp)
          exterior: per image  w (3, rotation increment) C (3, m)   6 n_images
          targets: per adjusted target  X (3, m)               3 n_adjusted ]

Adjusted targets are those that some active image point sees (``target_index``); the
others keep their coordinates.

The rotation of image i is ``R_i = exp([w_i]x) R0_i`` with a reference ``R0_i`` held by the
model (the increments stay small; :meth:`BundleModel.rebase` folds them in). Targets come
last so that the least-squares engine can eliminate them (3x3 blocks, Schur complement).

Residuals (weighted, dimensionless):

- image point k of image i and target t, in **image space** (docs/conventions.md section 4):
  ``r_k = (uv_measured - uv(x)) / sigma_px`` where ``uv(x)`` is the pixel at which the
  adjusted target lands through the adjusted camera: ``Xc = R_i (X_t - C_i)``,
  ``q = -f (Xc, Yc)/Zc``, ``x' = distort(q)``, ``uv = pixel(x')``. The printed objective of
  the field paper (eq. 10-11, corrected-plane residuals) is not scale invariant (METHODS
  part A); this one is.
- surveyed coordinate of target t (when targets are adjusted): ``(X_t - X_surveyed)/sigma``.

Jacobian of ``x' = distort(q)``: with ``g(x'; p) = correct(x')``, the predicted point solves
``g(x'; p) = q``, so ``dx' = G^-1 (dq - dg/dp dp)`` with ``G = dg/dx'``
(:func:`fieldcal.model.camera.correct_jacobian`). Then ``dq/dXc = -f/Zc [[1, 0, -Xc/Zc], [0, 1, -Yc/Zc]]``,
``dXc/dw = -[Xc]x J_l(w)``, ``dXc/dC = -R``, ``dXc/dX = R``, ``dq/df = q/f``.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from fieldcal.field import bundle_kernel
from fieldcal.model.camera import (
    INDEX,
    NEWTON_MAX_ITER,
    NEWTON_TOL_MM,
    Camera,
    correction_terms,
    distort,
    ideal_point_columns,
)
from fieldcal.model.rotations import R_from_rotvec, left_jacobian_so3
from fieldcal.session.data import FieldData

__all__ = ["BundleModel", "ObservationJacobian", "image_residuals"]


def image_residuals(data: FieldData, params, R, C, X=None, *, implementation: str = "auto"):
    """Measured minus predicted pixels (m, 2) [px] of every observation (active or not).

    ``Xc = R_i (X_t - C_i)``, ``q = -f (Xc, Yc)/Zc``, :func:`fieldcal.model.camera.distort`
    (Newton from ``q``), the pixel; NaN behind the camera (``Zc >= 0``) or where Newton does
    not converge. ``R`` (n_images, 3, 3) world to camera, ``C`` (n_images, 3) [m], ``X``
    (n_targets, 3) [m] (default: the surveyed coordinates). ``implementation``: ``"numba"``
    (:func:`fieldcal.field.bundle_kernel.residuals_kernel`, the same arithmetic point by
    point), ``"numpy"`` (the reference, here) or ``"auto"``.
    """
    d = data.obs
    X = data.targets.xyz_m if X is None else X
    kern = None if implementation == "numpy" else bundle_kernel.residuals_kernel()
    if implementation == "numba" and kern is None:
        raise RuntimeError(bundle_kernel.status())
    if kern is not None:
        s = data.sensor
        out = np.empty((len(d.image), 2))
        kern(np.ascontiguousarray(params, dtype=float), np.ascontiguousarray(R, dtype=float),
             np.ascontiguousarray(C, dtype=float), np.ascontiguousarray(X, dtype=float),
             np.ascontiguousarray(d.image, dtype=np.int64), np.ascontiguousarray(d.target, dtype=np.int64),
             np.ascontiguousarray(d.uv_px, dtype=float), float(s.width_px), float(s.height_px),
             float(s.pixel_mm), NEWTON_TOL_MM, NEWTON_MAX_ITER, out)
        return out
    Xc = np.einsum("kab,kb->ka", R[d.image], X[d.target] - C[d.image])
    cam = Camera(data.sensor, params)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -cam.f_mm * Xc[:, :2] / np.where(Xc[:, 2] < 0, Xc[:, 2], np.nan)[:, None]
    uv = data.sensor.mm_to_pixel(cam.distort(q, check=False))
    return d.uv_px - uv


@dataclass
class ObservationJacobian:
    """Per-observation derivative blocks of the weighted image residuals (rows u, v).

    ``d_int`` (m, 2, n_int), ``d_ext`` (m, 2, 6), ``d_tgt`` (m, 2, 3); columns of image
    ``image[k]`` and target ``target[k]``.
    """

    d_int: np.ndarray
    d_ext: np.ndarray
    d_tgt: np.ndarray
    combined: np.ndarray | None = None    # (m, 2, n_int + 6 [+ 3]): the blocks side by side, if so made


class BundleModel:
    """Residuals and Jacobian of the field adjustment for one set of active observations.

    Parameters
    ----------
    data : FieldData
        Targets, images, observations.
    params0 : (13,) ndarray
        Camera parameters; the ones not in ``estimate`` stay at these values.
    estimate : sequence of str
        Names (PARAM_NAMES) of the interior parameters to estimate.
    R0 : (n_images, 3, 3) ndarray
        Reference rotations (world to camera).
    targets_adjusted : bool
        Whether target coordinates are unknowns (weighted by their survey sigma) or fixed.
    obs_active : (m,) bool, optional
        Image observations in use (others are ignored, e.g. rejected blunders).
    survey_active : (n_targets,) bool, optional
        Survey observations in use (a rejected survey leaves the target to the images).
    global_targets : (g,) int array_like, optional
        Targets whose slots come first (``n_global`` of them, those adjusted): the ends of
        scale bars, which the solver keeps among its dense unknowns
        (:mod:`fieldcal.field.scale_bars`).
    warp : fieldcal.field.board.BoardWarp, optional
        A planar board's warp model (fixed targets only): its coefficients [mm] are unknowns
        after the camera's, inside the interior block (``n_int = n_cam + n_warp``); the
        targets are ``X0 + n 1e-3 (B c)`` (:mod:`fieldcal.field.board`). The derivative of an
        image residual by ``c_j`` is its derivative by the target times ``1e-3 n B_j``.
    """

    def __init__(self, data: FieldData, params0, estimate, R0, *, targets_adjusted=True,
                 obs_active=None, survey_active=None, global_targets=None, warp=None):
        self.data = data
        self.params0 = np.asarray(params0, dtype=float).copy()
        self.estimate = tuple(estimate)
        self.int_index = np.array([INDEX[n] for n in self.estimate], dtype=np.int64)
        self.R0 = np.array(R0, dtype=float)
        self.targets_adjusted = bool(targets_adjusted)
        if warp is not None and self.targets_adjusted:
            raise ValueError("a board warp is estimated with the targets held fixed")
        self.warp = warp
        m = len(data.obs)
        self.obs_active = np.ones(m, bool) if obs_active is None else np.asarray(obs_active, bool)
        n_t = len(data.targets)
        self.survey_active = (np.ones(n_t, bool) if survey_active is None
                              else np.asarray(survey_active, bool))
        self.n_images = len(data.images)
        self.n_targets = n_t
        self.n_cam = len(self.estimate)
        self.n_warp = len(warp.names) if warp is not None else 0
        self.n_int = self.n_cam + self.n_warp
        self.n_reduced = self.n_int + 6 * self.n_images
        k = np.flatnonzero(self.obs_active)
        k = k[np.argsort(data.obs.image[k], kind="stable")]   # grouped by image (contiguous slices)
        self.k = k
        self.img = data.obs.image[k]
        self.tgt = data.obs.target[k]
        self.uv = data.obs.uv_px[k]
        self.sigma_px = data.obs.sigma_px[k]
        # adjusted targets: those some active image point sees (a target seen by none adds
        # nothing to the camera); slot t_slot[t] in the parameter vector, -1 when not adjusted
        self.target_index = np.unique(self.tgt) if self.targets_adjusted else np.zeros(0, np.int64)
        g = np.isin(self.target_index, np.zeros(0, np.int64) if global_targets is None else global_targets)
        self.n_global = int(g.sum())            # bar ends first (fieldcal.field.scale_bars)
        self.target_index = np.concatenate([self.target_index[g], self.target_index[~g]])
        self.t_slot = np.full(n_t, -1, np.int64)
        self.t_slot[self.target_index] = np.arange(len(self.target_index))
        self.tgt_slot = self.t_slot[self.tgt]
        self.n_params = self.n_reduced + 3 * len(self.target_index)
        self.X_base = data.targets.xyz_m.copy()       # coordinates of the targets not adjusted
        self._warp_basis = (1e-3 * warp.basis(self.X_base)[:, None, :] * warp.normal[None, :, None]
                            if warp is not None else None)            # (n_t, 3, n_warp) [m/mm]
        self.survey_k = (self.target_index[self.survey_active[self.target_index]] if self.targets_adjusted
                         else np.zeros(0, np.int64))
        self.sigma_m = data.targets.sigma_mm / 1000.0
        self.n_rows_image = 2 * len(k)
        self._start_mm = data.sensor.pixel_to_mm(self.uv)  # Newton starts at the measured points
        bounds = np.searchsorted(self.img, np.arange(self.n_images + 1))
        self._image_slices = [(i, slice(bounds[i], bounds[i + 1])) for i in range(self.n_images)
                              if bounds[i + 1] > bounds[i]]
        self.n_rows = self.n_rows_image + 3 * len(self.survey_k)

    def restricted(self, keep) -> BundleModel:
        """A copy that evaluates only the active observations ``keep`` ((m_active,) bool, in this
        model's order): the same unknowns, parameter layout and reference rotations, so
        :meth:`residuals_and_blocks` gives exactly this model's rows ``keep`` (each point is
        computed on its own). For evaluation only (e.g. images still iterating)."""
        keep = np.asarray(keep, bool)
        sub = copy.copy(self)
        for name in ("k", "img", "tgt", "uv", "sigma_px", "_start_mm", "tgt_slot"):
            setattr(sub, name, getattr(self, name)[keep])
        sub.n_rows_image = 2 * len(sub.k)
        sub.n_rows = sub.n_rows_image + 3 * len(sub.survey_k)
        bounds = np.searchsorted(sub.img, np.arange(sub.n_images + 1))
        sub._image_slices = [(i, slice(bounds[i], bounds[i + 1])) for i in range(sub.n_images)
                             if bounds[i + 1] > bounds[i]]
        return sub

    # ------------------------------------------------------------------ packing
    def pack(self, params, center_m, targets_m=None, warp_mm=None):
        """The parameter vector for camera params (13,), centres (n_images, 3), targets (n, 3)
        and (with a board warp) its coefficients (n_warp,) [mm] (default 0).

        ``targets_m`` holds all targets; the ones not adjusted keep these coordinates.
        """
        parts = [np.asarray(params, float)[self.int_index], np.zeros((self.n_images, 6))]
        parts[1][:, 3:] = center_m
        warp = np.zeros(self.n_warp) if warp_mm is None else np.asarray(warp_mm, float).reshape(self.n_warp)
        x = [parts[0], warp, parts[1].ravel()]
        if self.targets_adjusted:
            self.X_base = np.array(targets_m, float).reshape(-1, 3)
            x.append(self.X_base[self.target_index].ravel())
        return np.concatenate(x)

    def unpack(self, x):
        """``(params (13,), R_world_to_camera (n_images,3,3), center_m (n_images,3), targets_m (n,3))``."""
        x = np.asarray(x, float)
        params = self.params0.copy()
        params[self.int_index] = x[: self.n_cam]
        ext = x[self.n_int:self.n_reduced].reshape(self.n_images, 6)
        R = R_from_rotvec(ext[:, :3]) @ self.R0
        C = ext[:, 3:].copy()
        X = self.X_base.copy()
        if self.targets_adjusted:
            X[self.target_index] = x[self.n_reduced:].reshape(-1, 3)
        if self.warp is not None:
            X = X + self._warp_basis @ self.warp_mm(x)
        return params, R, C, X

    def warp_mm(self, x):
        """The board warp's coefficients (n_warp,) [mm] in ``x`` (empty without a warp)."""
        return np.asarray(x, float)[self.n_cam:self.n_int]

    def rebase(self, x):
        """Fold the rotation increments of ``x`` into ``R0`` and return the equivalent ``x``."""
        x = np.array(x, float)
        ext = x[self.n_int:self.n_reduced].reshape(self.n_images, 6)
        self.R0 = R_from_rotvec(ext[:, :3]) @ self.R0
        ext[:, :3] = 0.0
        x[self.n_int:self.n_reduced] = ext.ravel()
        return x

    def camera(self, x) -> Camera:
        return Camera(self.data.sensor, self.unpack(x)[0])

    # ------------------------------------------------------------------ model
    def predict(self, x):
        """Predicted pixels (m_active, 2) of the active image observations (NaN if behind)."""
        return self._predict(x, jacobian=False)[0]

    def _predict_kernel(self, x, jacobian, kern):
        """:meth:`_predict` by the compiled kernel (:mod:`fieldcal.field.bundle_kernel`): weighted
        residuals (m, 2) and the blocks, in one pass."""
        params, _, C, X = self.unpack(x)
        ext = x[self.n_int:self.n_reduced].reshape(self.n_images, 6)
        R = np.ascontiguousarray(R_from_rotvec(ext[:, :3]) @ self.R0)
        Jl = np.ascontiguousarray(left_jacobian_so3(ext[:, :3]))
        m, s = len(self.img), self.data.sensor
        res = np.empty((m, 2))
        combined = None
        if jacobian:   # one array, the blocks side by side (the order of FieldProblem's columns)
            n_int, n_cam = self.n_int, self.n_cam
            combined = np.empty((m, 2, n_int + 6 + (3 if self.targets_adjusted else 0)))
            d_int, d_ext = combined[:, :, :n_int], combined[:, :, n_int:n_int + 6]
            d_tgt = combined[:, :, n_int + 6:] if self.targets_adjusted else np.empty((m, 2, 3))
            d_cam = d_int[:, :, :n_cam] if self.n_warp else d_int
        else:
            d_int = d_ext = d_tgt = d_cam = np.empty((0, 2, 0))
        kern(params, self.int_index, R, Jl, np.ascontiguousarray(C), np.ascontiguousarray(X), self.img,
             self.tgt, self.uv, self.sigma_px, self._start_mm, float(s.width_px), float(s.height_px),
             float(s.pixel_mm), NEWTON_TOL_MM, NEWTON_MAX_ITER, bool(jacobian), res, d_cam, d_ext, d_tgt)
        if jacobian and self.n_warp:
            d_int[:, :, self.n_cam:] = self._warp_columns(d_tgt)
        return res, (ObservationJacobian(d_int, d_ext, d_tgt, combined) if jacobian else None)

    def _warp_columns(self, d_tgt):
        """``d r / d c`` (m, 2, n_warp): the residuals' derivative by the target (m, 2, 3) times
        ``dX/dc = 1e-3 n B`` (module docstring of :mod:`fieldcal.field.board`)."""
        return np.einsum("kab,kbj->kaj", d_tgt, self._warp_basis[self.tgt])

    def _predict(self, x, jacobian):
        params, _, C, X = self.unpack(x)
        ext = x[self.n_int:self.n_reduced].reshape(self.n_images, 6)
        R = R_from_rotvec(ext[:, :3]) @ self.R0
        Ri = R[self.img]
        d = X[self.tgt] - C[self.img]
        Xc = np.einsum("kab,kb->ka", Ri, d)
        z = Xc[:, 2]
        f = params[INDEX["f_mm"]]
        with np.errstate(divide="ignore", invalid="ignore"):
            zs = np.where(z < 0, z, np.nan)
            q = -f * Xc[:, :2] / zs[:, None]
        s = self.data.sensor
        xy = distort(q, params, check=False, start_mm=self._start_mm)
        uv = s.mm_to_pixel(xy)
        if not jacobian:
            return uv, None
        xb, yb = xy[:, 0] - params[INDEX["xp_mm"]], xy[:, 1] - params[INDEX["yp_mm"]]
        _, _, g00, g01, g10, g11, r2, xy_ = correction_terms(xb, yb, params)
        # A = dr/dq at fixed p: r = (uv_meas - uv)/sigma, d(uv)/d(x') = diag(1/d, -1/d), dx'/dq = G^-1
        w = -1.0 / (self.sigma_px * s.pixel_mm * (g00 * g11 - g01 * g10))
        a00, a01, a10, a11 = w * g11, -w * g01, w * g10, -w * g00
        # interior: dx'/dp = G^-1 (dq/dp - Q), with dq/df = q/f
        cols_t = np.empty((self.n_cam, 2, len(z)))      # filled column by column (contiguous rows)
        cols = ideal_point_columns(xb, yb, params, (g00, g01, g10, g11), r2, xy_, self.int_index)
        for j, (c0, c1) in enumerate(cols):
            e0, e1 = -c0, -c1
            if self.estimate[j] == "f_mm":
                e0, e1 = q[:, 0] / f, q[:, 1] / f
            cols_t[j, 0] = a00 * e0 + a01 * e1
            cols_t[j, 1] = a10 * e0 + a11 * e1
        d_int = cols_t.transpose(2, 1, 0)
        # exterior and target through Xc: dq/dXc = -f/Zc [[1, 0, -Xc/Zc], [0, 1, -Yc/Zc]]
        fz = -f / zs
        B = np.empty((len(z), 2, 3))
        B[:, 0, 0], B[:, 0, 1] = a00 * fz, a01 * fz
        B[:, 1, 0], B[:, 1, 1] = a10 * fz, a11 * fz
        B[:, 0, 2] = -(a00 * q[:, 0] + a01 * q[:, 1]) / zs
        B[:, 1, 2] = -(a10 * q[:, 0] + a11 * q[:, 1]) / zs
        # dXc/dw = -[Xc]x J_l(w): a row b of B gives b (-[Xc]x) = cross(Xc, b)
        X0, X1, X2 = Xc[:, 0, None], Xc[:, 1, None], Xc[:, 2, None]
        bw = np.empty_like(B)
        bw[:, :, 0] = X1 * B[:, :, 2] - X2 * B[:, :, 1]
        bw[:, :, 1] = X2 * B[:, :, 0] - X0 * B[:, :, 2]
        bw[:, :, 2] = X0 * B[:, :, 1] - X1 * B[:, :, 0]
        Jl = left_jacobian_so3(ext[:, :3])
        d_ext = np.empty((len(z), 2, 6))
        d_tgt = np.empty((len(z), 2, 3))
        # per image: (2 k_i, 3) @ (3, 3) products (BLAS) on the observations sorted by image
        for i, sl in self._image_slices:
            n2 = 2 * (sl.stop - sl.start)
            d_ext[sl, :, :3] = (bw[sl].reshape(n2, 3) @ Jl[i]).reshape(-1, 2, 3)
            d_tgt[sl] = (B[sl].reshape(n2, 3) @ R[i]).reshape(-1, 2, 3)
        d_ext[:, :, 3:] = -d_tgt
        if self.n_warp:
            d_int = np.concatenate([d_int, self._warp_columns(d_tgt)], axis=2)
        return uv, ObservationJacobian(d_int, d_ext, d_tgt)

    def residuals_and_blocks(self, x, jacobian=True, *, implementation: str = "auto"):
        """Weighted residuals (n_rows,) and the derivative blocks.

        ``implementation``: ``"numba"`` (the compiled kernel of
        :mod:`fieldcal.field.bundle_kernel`), ``"numpy"`` (the reference, this module) or
        ``"auto"`` (the kernel where it compiles).

        Returns
        -------
        r : (n_rows,) ndarray
            Image rows first (u, v interleaved per observation), then survey rows
            (X, Y, Z per active survey).
        obs_jac : ObservationJacobian or None
        survey_diag : (n_survey,) ndarray
            ``1/sigma`` [1/m] of each active survey (its Jacobian is ``I / sigma``).
        """
        kern = None if implementation == "numpy" else bundle_kernel.kernel()
        if implementation == "numba" and kern is None:
            raise RuntimeError(bundle_kernel.status())
        if kern is not None:
            res, jac = self._predict_kernel(np.asarray(x, float), jacobian, kern)
            r_img = res.ravel()
        else:
            uv, jac = self._predict(x, jacobian)
            r_img = ((self.uv - uv) / self.sigma_px[:, None]).ravel()
        if self.targets_adjusted and len(self.survey_k):
            X = x[self.n_reduced:].reshape(-1, 3)
            t = self.survey_k
            r_sur = ((X[self.t_slot[t]] - self.data.targets.xyz_m[t]) / self.sigma_m[t, None]).ravel()
            r = np.concatenate([r_img, r_sur])
        else:
            r = r_img
        return r, jac, 1.0 / self.sigma_m[self.survey_k]

    def column_names(self) -> list[str]:
        """Names of the columns of ``x`` (for covariance/correlation tables)."""
        names = list(self.estimate) + (list(self.warp.names) if self.warp is not None else [])
        for im in self.data.images:
            names += [f"{im.file}:{c}" for c in ("w_x", "w_y", "w_z", "X_m", "Y_m", "Z_m")]
        for t in self.data.targets.ids[self.target_index]:
            names += [f"{t}:X_m", f"{t}:Y_m", f"{t}:Z_m"]
        return names

