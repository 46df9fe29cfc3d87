"""Projection, matching, local correction and pose refinement of many views at once.

The identification (:mod:`fieldcal.field.identify`) refines *views*: one image seen from
one pose (a start from its seeds, a pose prior, a hypothesis of the pose-free search, or the
pose of an adjustment). Steps 2-4 of its method (project every target, pair predictions
with measured discs by mutual nearest neighbours inside gates, correct the predictions by
the median residual of their neighbours, re-estimate the pose from the pairs, repeat until
the pairs are stable) are done here for V views together, with one KD-tree query per step
instead of one per view.

Vectorisation over views
------------------------
The predictions and measured points of view ``v`` are moved by ``v * span`` along ``u``
(``span`` four times the larger sensor side), so that one ``scipy.spatial.cKDTree`` over
all views answers each view's nearest-neighbour questions: a gate (at most a fraction of
the target spacing) never reaches into the next view. The prediction spacing, the mutual
nearest neighbours (:func:`fieldcal.field.identify.mutual_nearest`) and the local
correction (:func:`fieldcal.field.identify.local_correction`, leave-one-out over the
``neighbours`` nearest pairs) are computed this way; a view with fewer pairs than
``neighbours + 1`` (rare: it will not identify the image) gets its correction on its own.
The robust scale of each view's residuals is a grouped median.

Pose refinement
---------------
With the camera fixed, the pose of view ``v`` minimises
``sum_k |q_k - pi(R (X_k - C))|^2`` over its pairs ``k``, with ``q_k`` the measured point
corrected to the ideal image plane once (:meth:`Camera.correct`, [mm]) and
``pi(P) = -f (P_x, P_y) / P_z`` the pinhole (docs/conventions.md section 2). Gauss-Newton steps from the
current pose: with ``P = R (X - C)`` the update ``R <- exp([w]x) R``, ``C <- C + dC`` changes
``P`` by ``w x P - R dC``, and

    d pi / d P = (f / P_z^2) [[-P_z, 0, P_x], [0, -P_z, P_y]],
    J = d pi / d P [ -[P]x | -R ],

so each view's 6 x 6 normal equations ``J^T J (w, dC) = J^T r`` are accumulated over its
pairs and all views are solved together. This is the least-squares pose that
:func:`fieldcal.field.resection.resect` finds from the same start, in the ideal plane
instead of measured pixels (the two differ by the distortion's local scale, a few 0.1 %).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fieldcal.model.camera import Camera
from fieldcal.robust import MAD_TO_SIGMA, robust_sigma

__all__ = ["ViewMatcher", "Refined", "mutual_nearest", "local_correction", "grouped_median", "rotation_exp",
           "pinhole_jacobian", "refine_poses"]


def mutual_nearest(pred_px, gate_px, meas_px):
    """Mutual nearest neighbours of predictions and measured points, inside gates.

    Parameters
    ----------
    pred_px : (m, 2) ndarray
        Predicted positions [px] (finite).
    gate_px : float or (m,) ndarray
        Gate of each prediction [px].
    meas_px : (n, 2) ndarray
        Measured positions [px] (finite).

    Returns
    -------
    i_pred, j_meas : (k,) int ndarrays
        The pairs: each is the other's nearest neighbour, closer than the prediction's gate,
        and neither side has a second candidate within the gate (ambiguous pairs are
        dropped, since a wrong identity is worse than a missing one).
    """
    pred = np.asarray(pred_px, float).reshape(-1, 2)
    meas = np.asarray(meas_px, float).reshape(-1, 2)
    m, n = len(pred), len(meas)
    if m == 0 or n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    gate = np.broadcast_to(np.asarray(gate_px, float), (m,))
    d, j = cKDTree(meas).query(pred, k=2)          # inf / n where fewer than 2 points
    e, i = cKDTree(pred).query(meas, k=2)
    j1 = j[:, 0]
    own = np.arange(m)
    mutual = i[j1, 0] == own
    close = d[:, 0] <= gate
    alone_meas = d[:, 1] > gate                    # no second measured point near the prediction
    alone_pred = e[j1, 1] > gate                   # no second prediction near the measured point
    ok = mutual & close & alone_meas & alone_pred
    return own[ok], j1[ok]


def local_correction(at_px, matched_px, residual_px, self_index=None, *, neighbours: int = 8):
    """Median residual of the nearest matched points, and its spread, at given positions.

    Parameters
    ----------
    at_px : (m, 2) ndarray
        Where to evaluate [px].
    matched_px : (k, 2) ndarray
        Positions of the matched points [px].
    residual_px : (k, 2) ndarray
        Their residuals (measured minus projected) [px].
    self_index : (m,) int ndarray, optional
        For each position, the index of the matched point it *is* (-1 for none): that point
        is left out of its own correction (leave-one-out).
    neighbours : int
        Matched points per correction.

    Returns
    -------
    correction : (m, 2) ndarray
        The median of the neighbours' residuals [px] (zero with too few matched points).
    spread : (m,) ndarray
        1.4826 x the median absolute deviation of the neighbours' residuals about it, the
        larger of the two axes [px].
    """
    at = np.asarray(at_px, float).reshape(-1, 2)
    P = np.asarray(matched_px, float).reshape(-1, 2)
    r = np.asarray(residual_px, float).reshape(-1, 2)
    m, k = len(at), len(P)
    K = min(int(neighbours), k - 1)
    if K < 3:
        return np.zeros((m, 2)), np.zeros(m)
    _, idx = cKDTree(P).query(at, k=K + 1)
    me = np.full(m, -1) if self_index is None else np.asarray(self_index)
    is_self = idx == me[:, None]
    # drop the point itself where it is among the K + 1, else the farthest
    drop = np.where(is_self.any(axis=1), np.argmax(is_self, axis=1), K)
    keep = np.ones(idx.shape, bool)
    keep[np.arange(m), drop] = False
    nb = r[idx[keep].reshape(m, K)]                                  # (m, K, 2)
    corr = np.median(nb, axis=1)
    spread = robust_sigma(nb - corr[:, None, :], axis=1).max(axis=1)
    return corr, spread


def grouped_median(values, groups, n_groups: int):
    """Median of ``values`` (m,) within each group (``groups`` (m,) int in [0, n_groups)).

    Returns (n_groups,) with NaN for an empty group (the mean of the two middle values for an
    even count, as :func:`numpy.median`)."""
    values = np.asarray(values, float)
    groups = np.asarray(groups, np.int64)
    out = np.full(n_groups, np.nan)
    if len(values) == 0:
        return out
    order = np.lexsort((values, groups))
    v, g = values[order], groups[order]
    counts = np.bincount(g, minlength=n_groups)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    has = counts > 0
    lo = start[has] + (counts[has] - 1) // 2
    hi = start[has] + counts[has] // 2
    out[has] = 0.5 * (v[lo] + v[hi])
    return out


def rotation_exp(w):
    """Rotation matrices (..., 3, 3) of rotation vectors ``w`` (..., 3) [rad] (Rodrigues)."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=-1)
    small = th < 1e-12
    k = w / np.where(small, 1.0, th)[..., None]
    K = np.zeros(w.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2] = -k[..., 2], k[..., 1]
    K[..., 1, 0], K[..., 1, 2] = k[..., 2], -k[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -k[..., 1], k[..., 0]
    s, c = np.sin(th)[..., None, None], np.cos(th)[..., None, None]
    R = np.eye(3) + s * K + (1 - c) * (K @ K)
    return np.where(small[..., None, None], np.eye(3), R)


def pinhole_jacobian(f_mm: float, R, C, X):
    """Pinhole projections of points and their derivatives by the pose (module docstring).

    Parameters
    ----------
    f_mm : float
    R, C : (P, 3, 3), (P, 3) ndarrays
        The pose of each point's view.
    X : (P, 3) ndarray
        The points [m].

    Returns
    -------
    proj : (P, 2) ndarray
        ``-f (P_x, P_y) / P_z`` [mm] (NaN behind the camera).
    J : (P, 2, 6) ndarray
        Derivatives by ``(w, dC)`` of the update ``R <- exp([w]x) R``, ``C <- C + dC`` [mm/rad, mm/m].
    """
    P = np.einsum("pij,pj->pi", R, X - C)
    z = P[:, 2]
    zs = np.where(z < 0, z, np.nan)
    proj = -f_mm * P[:, :2] / zs[:, None]
    D = np.zeros((len(P), 2, 3))                         # d pi / d P
    g = f_mm / zs**2
    D[:, 0, 0] = D[:, 1, 1] = -g * zs
    D[:, 0, 2] = g * P[:, 0]
    D[:, 1, 2] = g * P[:, 1]
    Px = np.zeros((len(P), 3, 3))                        # [P]x
    Px[:, 0, 1], Px[:, 0, 2] = -P[:, 2], P[:, 1]
    Px[:, 1, 0], Px[:, 1, 2] = P[:, 2], -P[:, 0]
    Px[:, 2, 0], Px[:, 2, 1] = -P[:, 1], P[:, 0]
    return proj, np.concatenate([-D @ Px, -D @ R], axis=2)


def refine_poses(f_mm: float, R, C, view, X, q_mm, *, steps: int = 6, tol: float = 1e-10):
    """Least-squares poses of views from their point pairs (module docstring, Gauss-Newton).

    Parameters
    ----------
    f_mm : float
        Principal distance [mm].
    R, C : (V, 3, 3), (V, 3) ndarrays
        Starting poses (world to camera, centre [m]); not changed.
    view : (P,) int ndarray
        The view of each pair (any order).
    X : (P, 3) ndarray
        Target of each pair [m].
    q_mm : (P, 2) ndarray
        Its measured point in the ideal image plane [mm].
    steps : int
        Gauss-Newton steps at most.
    tol : float
        Stop when no view's step exceeds this (rad and m).

    Returns
    -------
    R, C : (V, 3, 3), (V, 3) ndarrays
        Views without pairs keep their start.
    """
    R = np.array(R, float)
    C = np.array(C, float)
    V = len(R)
    view = np.asarray(view, np.int64)
    if len(view) == 0:
        return R, C
    for _ in range(steps):
        proj, J = pinhole_jacobian(f_mm, R[view], C[view], X)
        ok = np.isfinite(proj).all(axis=1)
        r = np.where(ok[:, None], q_mm - np.where(ok[:, None], proj, 0.0), 0.0)
        J = np.where(ok[:, None, None], J, 0.0)
        JtJ = np.einsum("pki,pkj->pij", J, J).reshape(len(view), 36)
        Jtr = np.einsum("pki,pk->pi", J, r)
        N = np.stack([np.bincount(view, weights=JtJ[:, c], minlength=V) for c in range(36)], axis=1)
        b = np.stack([np.bincount(view, weights=Jtr[:, c], minlength=V) for c in range(6)], axis=1)
        N = N.reshape(V, 6, 6)
        scale = np.sqrt(np.maximum(np.einsum("vii->vi", N), 1e-300))
        Ns = N / scale[:, :, None] / scale[:, None, :] + 1e-12 * np.eye(6)
        try:
            d = np.linalg.solve(Ns, (b / scale)[..., None])[..., 0] / scale
        except np.linalg.LinAlgError:
            break
        d = np.where(np.isfinite(d), d, 0.0)
        R = rotation_exp(d[:, :3]) @ R
        C = C + d[:, 3:]
        if np.abs(d).max() <= tol:
            break
    return R, C


@dataclass
class Refined:
    """The state of V views after refinement (arrays over views, dense over targets).

    Attributes
    ----------
    R, C : (V, 3, 3), (V, 3) ndarrays
        Final poses.
    uv : (V, n, 2) ndarray
        Predicted pixels of every target (NaN where not near the frame) [px].
    inside : (V, n) bool ndarray
    corr : (V, n, 2) ndarray
        Local correction of every prediction [px].
    gate : (V, n) ndarray
        Gate of every prediction [px] (NaN outside the frame).
    spacing : (V, n) ndarray
        Distance to the nearest other prediction in the frame [px] (inf when none).
    s : (V,) ndarray
        Robust scale of each view's corrected residuals [px] (inf with fewer than 4 pairs).
    pair_view, pair_target, pair_meas : (P,) int ndarrays
        The final pairs: view, target, index of the measured disc in its image.
    pair_e : (P,) ndarray
        Their corrected residuals [px]; only pairs within their gate are kept.
    iterations : (V,) int ndarray
    """

    R: np.ndarray
    C: np.ndarray
    uv: np.ndarray
    inside: np.ndarray
    corr: np.ndarray
    gate: np.ndarray
    spacing: np.ndarray
    s: np.ndarray
    pair_view: np.ndarray
    pair_target: np.ndarray
    pair_meas: np.ndarray
    pair_e: np.ndarray
    iterations: np.ndarray
    max_rms_fraction: float

    def view(self, v: int) -> dict:
        """View ``v`` as :func:`fieldcal.field.identify` step 5 reads it."""
        k = self.pair_view == v
        tm, jm, e = self.pair_target[k], self.pair_meas[k], self.pair_e[k]
        sp = self.spacing[v][self.inside[v]]
        spacing = float(np.median(sp)) if len(sp) > 1 else np.inf
        rms = float(np.sqrt(np.mean(e**2))) if len(e) else np.inf
        return dict(R=self.R[v], C=self.C[v], uv=self.uv[v], inside=self.inside[v], corr=self.corr[v],
                    gate=self.gate[v], spacing_t=self.spacing[v], s=float(self.s[v]), tm=tm, jm=jm, e=e,
                    iterations=int(self.iterations[v]), spacing=spacing,
                    fits=bool(rms <= self.max_rms_fraction * spacing))

    def counts(self) -> np.ndarray:
        """Pairs of each view (V,)."""
        return np.bincount(self.pair_view, minlength=len(self.R))


class ViewMatcher:
    """Projection, matching, correction and pose refinement of views of measured images.

    Parameters
    ----------
    X : (n, 3) ndarray
        Targets [m].
    match_target : (n,) bool ndarray
        Targets matched to discs (coded targets are identified by their codes).
    camera : Camera
    options : IdentifyOptions
        Gates and iterations (:class:`fieldcal.field.identify.IdentifyOptions`).
    measured : list of (n_i, 2) ndarrays
        The usable discs of each image [px].
    target_sigma_m : (n,) ndarray, optional
        Coordinate sigma of each target [m]; seen from the pose it widens the gate.
    """

    def __init__(self, X, match_target, camera: Camera, options, measured, target_sigma_m=None):
        self.X = np.asarray(X, float)
        self.n = len(self.X)
        self.match_target = np.asarray(match_target, bool)
        self.camera = camera
        self.opt = options
        self.measured = [np.asarray(m, float).reshape(-1, 2) for m in measured]
        pm = camera.sensor.pixel_mm
        self.ideal = [camera.correct(camera.sensor.pixel_to_mm(m)) if len(m) else np.zeros((0, 2))
                      for m in self.measured]
        self.target_sigma_m = None if target_sigma_m is None else np.asarray(target_sigma_m, float)
        s = camera.sensor
        self.span = 4.0 * max(s.width_px, s.height_px)
        self.reach_mm = 1.5 * 0.5 * np.array([s.width_px, s.height_px]) * pm
        self.hi = np.array([s.width_px - 0.5, s.height_px - 0.5])

    # ------------------------------------------------------------------ building blocks
    def _offset(self, view):
        return np.stack([np.asarray(view, float) * self.span, np.zeros(len(view))], axis=1)

    def project(self, R, C):
        """Predictions (V, n, 2) [px] (NaN away from the frame), in the frame (V, n), and the
        targets' sigma seen from each pose (V, n) [px]."""
        R, C = np.asarray(R, float), np.asarray(C, float)
        V = len(R)
        Xc = np.matmul(self.X[None] - C[:, None], np.swapaxes(R, 1, 2))       # (V, n, 3)
        z = Xc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            q = -self.camera.f_mm * Xc[..., :2] / z[..., None]
        # per coordinate, not .all(axis=2): a reduction over an axis of 2 is ~30x slower than
        # the two comparisons (NaN compares False either way)
        near = (z < 0) & (np.abs(q[..., 0]) <= self.reach_mm[0]) & (np.abs(q[..., 1]) <= self.reach_mm[1])
        uv = np.full((V, self.n, 2), np.nan)
        if near.any():
            xy = self.camera.distort(q[near], check=False)
            uv[near] = self.camera.sensor.mm_to_pixel(xy)
        u, v = uv[..., 0], uv[..., 1]           # NaN (away from the frame) compares False
        inside = (u >= -0.5) & (v >= -0.5) & (u <= self.hi[0]) & (v <= self.hi[1])
        prior = np.zeros((V, self.n))
        if self.target_sigma_m is not None:
            with np.errstate(divide="ignore", invalid="ignore"):
                prior = np.nan_to_num(self.target_sigma_m[None] * self.camera.f_mm / np.abs(z)
                                      / self.camera.sensor.pixel_mm, posinf=0.0)
        return uv, inside, prior

    def spacing(self, uv, inside):
        """Distance (V, n) from each prediction in the frame to the nearest other one of its view
        [px] (inf where alone or outside)."""
        V = len(uv)
        out = np.full((V, self.n), np.inf)
        v, t = np.nonzero(inside)
        if len(v) < 2:
            return out
        P = uv[v, t] + self._offset(v)
        d, _ = cKDTree(P).query(P, k=2)
        d = d[:, 1]
        out[v, t] = np.where(d < 0.5 * self.span, d, np.inf)
        return out

    def first_gates(self, inside, spacing):
        """The wide gates of the first matching (V, n): a fraction of the prediction spacing."""
        gate = np.where(inside, self.opt.first_gate_fraction * spacing, np.nan)
        if self.opt.gate_px is not None:
            gate = np.minimum(gate, self.opt.gate_px)
        return gate

    def measured_of(self, image):
        """The measured discs of the views' images, offset per view: (uv, uv offset, view, index)."""
        parts = [self.measured[i] for i in image]
        n = np.array([len(p) for p in parts], np.int64)
        view = np.repeat(np.arange(len(image)), n)
        local = np.concatenate([np.arange(k) for k in n]) if len(n) else np.zeros(0, np.int64)
        uv = np.concatenate(parts) if parts else np.zeros((0, 2))
        return uv, uv + self._offset(view), view, local.astype(np.int64)

    def match(self, uv, inside, gate, corr, meas_off, meas_tree):
        """Mutual nearest pairs inside the gates: (view, target, row of ``meas_off``)."""
        ok = inside & self.match_target[None] & np.isfinite(gate)
        v, t = np.nonzero(ok)
        if len(v) == 0 or len(meas_off) == 0:
            z = np.zeros(0, np.int64)
            return z, z, z
        pred = uv[v, t] + corr[v, t] + self._offset(v)
        g = gate[v, t]
        d, j = meas_tree.query(pred, k=2)
        e, i = cKDTree(pred).query(meas_off, k=2)
        j1 = np.minimum(j[:, 0], len(meas_off) - 1)
        own = np.arange(len(v))
        keep = (i[j1, 0] == own) & (d[:, 0] <= g) & (d[:, 1] > g) & (e[j1, 1] > g)
        return v[keep], t[keep], j1[keep]

    def local(self, at_view, at_uv, self_index, pair_view, pair_uv, pair_res):
        """Local correction and spread at given positions from their views' pairs.

        As :func:`fieldcal.field.identify.local_correction` per view (``self_index`` the pair
        each position *is*, -1 for none, left out of its own correction)."""
        m = len(at_view)
        corr, spread = np.zeros((m, 2)), np.zeros(m)
        K = int(self.opt.neighbours)
        counts = np.bincount(pair_view, minlength=int(at_view.max()) + 1 if m else 0) if len(pair_view) else \
            np.zeros(int(at_view.max()) + 1 if m else 0, np.int64)
        if m == 0 or len(pair_view) == 0:
            return corr, spread
        n_at = counts[at_view]
        big = n_at >= K + 1
        if big.any():
            rows = np.flatnonzero(big)
            tree = cKDTree(pair_uv + self._offset(pair_view))
            _, idx = tree.query(at_uv[rows] + self._offset(at_view[rows]), k=K + 1)
            me = self_index[rows]
            is_self = idx == me[:, None]
            drop = np.where(is_self.any(axis=1), np.argmax(is_self, axis=1), K)
            keep = np.ones(idx.shape, bool)
            keep[np.arange(len(rows)), drop] = False
            nb = pair_res[idx[keep].reshape(len(rows), K)]
            c = np.median(nb, axis=1)
            corr[rows] = c
            spread[rows] = robust_sigma(nb - c[:, None, :], axis=1).max(axis=1)
        small = (n_at >= 4) & ~big
        for v in np.unique(at_view[small]):
            rows = np.flatnonzero(small & (at_view == v))
            k = np.flatnonzero(pair_view == v)
            pos = np.full(len(pair_view), -1)
            pos[k] = np.arange(len(k))
            si = np.where(self_index[rows] >= 0, pos[np.maximum(self_index[rows], 0)], -1)
            corr[rows], spread[rows] = local_correction(at_uv[rows], pair_uv[k], pair_res[k], si, neighbours=K)
        return corr, spread

    def corrected(self, uv, inside, spacing, prior, pv, pt, res):
        """Local correction (V, n, 2), its spread (V, n), the gates (V, n), the robust scale of
        each view (V,) and the pairs' corrected residuals (P,) (identify step 3)."""
        V = len(uv)
        first = self.first_gates(inside, spacing)
        corr = np.zeros((V, self.n, 2))
        spread = np.zeros((V, self.n))
        counts = np.bincount(pv, minlength=V)
        s = np.full(V, np.inf)
        e = np.hypot(res[:, 0], res[:, 1]) if len(res) else np.zeros(0)
        ok_view = counts >= 4
        if not ok_view.any():
            return corr, spread, first, s, e
        pair_index = np.full((V, self.n), -1, np.int64)
        pair_index[pv, pt] = np.arange(len(pv))
        av, at = np.nonzero(inside & ok_view[:, None])
        c, sp = self.local(av, uv[av, at], pair_index[av, at], pv, uv[pv, pt], res)
        corr[av, at], spread[av, at] = c, sp
        ev = res - corr[pv, pt]
        e = np.hypot(ev[:, 0], ev[:, 1])
        e = np.where(ok_view[pv], e, np.hypot(res[:, 0], res[:, 1]))
        big = ok_view[pv]
        med = grouped_median(np.abs(ev[big]).reshape(-1), np.repeat(pv[big], 2), V)
        s = np.where(ok_view, np.maximum(MAD_TO_SIGMA * med, 1e-3), np.inf)
        s_eff = np.where(ok_view, s, 0.0)
        gate = np.sqrt(s_eff[:, None] ** 2 + spread**2 + prior**2) * self.opt.gate_factor
        with np.errstate(invalid="ignore"):
            gate = np.where(ok_view[:, None], np.minimum(np.maximum(gate, self.opt.min_gate_px), first), first)
        return corr, spread, gate, s, e

    # ------------------------------------------------------------------ the procedure
    def score(self, image, R, C):
        """Targets each view pairs with the first (wide) gates and no correction (V,), and the
        targets it puts in the frame (V,) (identify step 1's verification of a start)."""
        image = np.asarray(image, np.int64)
        uv, inside, _ = self.project(R, C)
        spacing = self.spacing(uv, inside)
        gate = self.first_gates(inside, spacing)
        _, meas_off, _, _ = self.measured_of(image)
        tree = cKDTree(meas_off) if len(meas_off) else None
        pv, _, _ = self.match(uv, inside, gate, np.zeros_like(uv), meas_off, tree)
        return (np.bincount(pv, minlength=len(image)), np.sum(inside & self.match_target[None], axis=1),
                uv, spacing)

    def refine(self, image, R, C, coded=None, *, update_pose: bool = True) -> Refined:
        """Identify steps 2-4 for views of the measured images (module docstring).

        Parameters
        ----------
        image : (V,) int array_like
            The measured image of each view (index into ``measured``).
        R, C : (V, 3, 3), (V, 3) array_like
            Starting poses.
        coded : list of (targets (c,), uv (c, 2)), optional
            Per image, the markers whose code names a target: they join the pose where they
            agree with it.
        update_pose : bool
            Re-estimate the poses from the pairs (False: the poses are an adjustment's, better
            than one image's; only the pairs and gates are iterated).
        """
        image = np.asarray(image, np.int64)
        R, C = np.array(R, float).reshape(-1, 3, 3), np.array(C, float).reshape(-1, 3)
        V = len(image)
        meas_uv, meas_off, meas_view, meas_local = self.measured_of(image)
        tree = cKDTree(meas_off) if len(meas_off) else None
        cv_, ct, cuv = self._coded_of(image, coded)
        cq = (self.camera.correct(self.camera.sensor.pixel_to_mm(cuv)) if len(cuv) else np.zeros((0, 2)))
        uv, inside, prior = self.project(R, C)
        spacing = self.spacing(uv, inside)
        corr = np.zeros_like(uv)
        gate = self.first_gates(inside, spacing)
        active = np.ones(V, bool)
        iterations = np.zeros(V, np.int64)
        prev: list = [None] * V
        meas_ideal = np.concatenate([self.ideal[i] for i in image]) if V else np.zeros((0, 2))
        for _ in range(self.opt.max_iterations):
            if not active.any():
                break
            iterations[active] += 1
            pv, pt, pj = self.match(uv, inside, gate, corr, meas_off, tree)
            bounds = np.searchsorted(pv, np.arange(V + 1))
            for v in np.flatnonzero(active):
                key = (pt[bounds[v]:bounds[v + 1]].tobytes(), pj[bounds[v]:bounds[v + 1]].tobytes())
                if key == prev[v]:
                    active[v] = False
                prev[v] = key
            if not active.any():
                break
            if not update_pose:
                res = meas_uv[pj] - uv[pv, pt]
                corr, _, gate, _, _ = self.corrected(uv, inside, spacing, prior, pv, pt, res)
                continue
            # the markers join the pose where they agree with it (a wrong code must not pull it)
            c_ok = self._markers_agree(cv_, ct, cuv, uv, gate, spacing, pv, pt, meas_uv[pj]) if len(cv_) else \
                np.zeros(0, bool)
            use = active[pv]
            cuse = c_ok & active[cv_] if len(cv_) else c_ok
            view_p = np.concatenate([pv[use], cv_[cuse]])
            Xp = np.concatenate([self.X[pt[use]], self.X[ct[cuse]]])
            qp = np.concatenate([meas_ideal[pj[use]], cq[cuse]])
            movable = self._determined(view_p, Xp, V) & active
            active &= movable
            if not active.any():
                break
            sel = active[view_p]
            R2, C2 = refine_poses(self.camera.f_mm, R, C, view_p[sel], Xp[sel], qp[sel])
            R[active], C[active] = R2[active], C2[active]
            uv, inside, prior = self.project(R, C)
            spacing = self.spacing(uv, inside)
            res = meas_uv[pj] - uv[pv, pt]
            corr, _, gate, _, _ = self.corrected(uv, inside, spacing, prior, pv, pt, res)
        # final pairs with the last poses and gates
        pv, pt, pj = self.match(uv, inside, gate, corr, meas_off, tree)
        res = meas_uv[pj] - uv[pv, pt]
        corr, _, gate, s, e = self.corrected(uv, inside, spacing, prior, pv, pt, res)
        good = e <= gate[pv, pt]
        return Refined(R, C, uv, inside, corr, gate, spacing, s, pv[good], pt[good], meas_local[pj[good]], e[good],
                       iterations, self.opt.max_rms_fraction)

    def _coded_of(self, image, coded):
        if coded is None:
            z = np.zeros(0, np.int64)
            return z, z, np.zeros((0, 2))
        parts = [(np.asarray(coded[i][0], np.int64), np.asarray(coded[i][1], float).reshape(-1, 2)) for i in image]
        n = np.array([len(p[0]) for p in parts], np.int64)
        if n.sum() == 0:
            z = np.zeros(0, np.int64)
            return z, z, np.zeros((0, 2))
        return (np.repeat(np.arange(len(image)), n), np.concatenate([p[0] for p in parts]),
                np.concatenate([p[1] for p in parts]))

    def _markers_agree(self, cv_, ct, cuv, uv, gate, spacing, pv, pt, pair_meas_uv):
        """Markers within their seed tolerance of the corrected prediction of their target."""
        pair_index = np.full((len(uv), self.n), -1, np.int64)
        pair_index[pv, pt] = np.arange(len(pv))
        at = uv[cv_, ct]
        fin = np.isfinite(at).all(axis=1)
        counts = np.bincount(pv, minlength=len(uv))
        c_corr = np.zeros((len(cv_), 2))
        rows = np.flatnonzero(fin & (counts[cv_] >= 4))
        if len(rows):
            c_corr[rows], _ = self.local(cv_[rows], at[rows], pair_index[cv_[rows], ct[rows]], pv,
                                         uv[pv, pt], pair_meas_uv - uv[pv, pt])
        err = np.hypot(*(cuv - at - c_corr).T)
        return np.isfinite(err) & (err <= self.seed_tolerance(gate[cv_, ct], spacing[cv_, ct]))

    def seed_tolerance(self, gate, spacing):
        """How far a seed may be from its target's prediction: 3 gates or a quarter spacing [px]."""
        g = np.where(np.isfinite(gate), gate, self.opt.min_gate_px)
        return np.maximum(3.0 * g, 0.25 * np.where(np.isfinite(spacing), spacing, 0.0))

    @staticmethod
    def _determined(view, X, V):
        """Views with at least 4 points that are not collinear (V,) bool."""
        n = np.bincount(view, minlength=V)
        ok = n >= 4
        if not ok.any():
            return ok
        mean = np.zeros((V, 3))
        np.add.at(mean, view, X)
        mean /= np.maximum(n, 1)[:, None]
        d = X - mean[view]
        S = np.zeros((V, 9))
        np.add.at(S, view, np.einsum("pi,pj->pij", d, d).reshape(-1, 9))
        w = np.linalg.eigvalsh(S.reshape(V, 3, 3))                   # ascending
        sv = np.sqrt(np.maximum(w, 0.0))
        return ok & (sv[:, 1] > 1e-3 * sv[:, 2])
