"""Target identification: which surveyed target each measured blob of one image is.

Method
------
The measurements of an image (:func:`fieldcal.measure.targets.measure_image`: discs and ArUco
markers) carry no identities except the markers' codes. A few *seeds* give the first
correspondences: the coded targets (a marker's code names its target through
``targets.codes``; its measured centre is that target's observation) and, for fields
without coded targets, the hand marks of ``marks.csv`` (CONTRACT section 3). Then:

1. **Pose from the seeds.** Candidate poses: the given approximate pose (``init_pose``,
   e.g. from an adjustment), OpenCV's SQPnP of all seeds, and their resection
   (:func:`fieldcal.field.resection.resect`, with RANSAC from 6 seeds on); when none of these is
   convincing (most of the expected targets matched, every seed near its target), also the
   resections of the seeds without one of them and the P3P poses of every triple (so one
   wrong mark among four cannot spoil the start). P3P is Grunert's solution with the real
   part of every root of its quartic (:func:`_grunert_distances`): near the "danger
   cylinder" a little noise turns the right pair of roots complex, and OpenCV's P3P then
   loses the right pose. Each candidate is scored by the number of targets it pairs (step
   2 with the wide first gate).
2. **Projection and matching.** All surveyed targets are projected with the pose
   (:meth:`Camera.project`); a prediction and a measured point are paired when each is the
   other's nearest neighbour (``scipy.spatial.cKDTree``), they are within the prediction's
   gate, and no second candidate lies within the gate on either side (ambiguous pairs stay
   unidentified). Plain targets are matched to discs; coded targets only through their
   markers' codes (``codes_are_markers``).
3. **Local correction and gates.** The residuals of the paired points (measured minus
   projected) contain what the camera model does not yet know: with the nominal camera of
   a first pass, the whole lens distortion, smooth over the image. Each prediction is
   moved by the median residual of its ``neighbours`` nearest paired points (its own
   residual left out), and the gate of each prediction is
   ``gate_factor * sqrt(s^2 + spread^2 + prior^2)``, ``s`` the robust (MAD) scale of the
   paired points' corrected residuals, ``spread`` the MAD of the neighbours' residuals (large
   where the distortion changes fast, e.g. extrapolating into a corner) and ``prior`` the
   target's coordinate sigma seen from the camera (``target_sigma_m``), clipped to
   ``[min_gate_px, first gate]``. The first gate is ``first_gate_fraction`` (0.3) of the
   distance from a prediction to its nearest neighbouring prediction (at most
   ``gate_px``): half of that would already be ambiguous.
4. **Iteration.** The pose is re-resected from the pairs (and the markers that agree with
   it), the targets re-projected and re-matched, until the set of pairs is stable
   (``max_iterations``). The best-scored candidate is refined first; when it does not end
   in a fit (step 5), the next ones (up to ``max_starts``).
5. **Checks.** A seed whose target ends up farther than ``max(3 gate, 0.25 spacing)`` from
   the seed's point is *wrong* (a mark with a wrong id, a marker whose code is wrong in
   targets.csv): it is reported and not used. The image is not usable (``reason``) when
   fewer than ``min_identified`` targets are identified, or the start was wrong: the pairs'
   residuals after the local correction exceed ``max_rms_fraction`` of the target spacing
   (a right identification fits to the noise, a chance one to a good part of the spacing),
   fewer than ``min_fraction`` of the targets expected in the frame are paired, or most
   seeds disagree. After a wrong start no identity is kept.

Everything per image is vectorised (projections, KD-tree queries, corrections); the only
loops are over candidate poses and iterations.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import cv2
import numpy as np
import pyarrow as pa
from scipy.spatial import cKDTree

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.data import TargetField
from fieldcal.field.geometry import is_collinear
from fieldcal.field.resection import resect
from fieldcal.model.camera import Camera
from fieldcal.model.opencv_frames import FLIP_YZ, ideal_pixels, opencv_camera_matrix, pose_from_opencv
from fieldcal.robust import robust_sigma

__all__ = ["ImageIdentification", "IdentifyOptions", "identify_image", "mutual_nearest", "local_correction",
           "measured_points", "DEFAULT_MIN_IDENTIFIED"]

DEFAULT_MIN_IDENTIFIED = 8
"""Fewer identified targets than this and an image is left out (the adjustment needs 6)."""

_MAX_TRIPLES = 200


@dataclass
class ImageIdentification:
    """The identification of one image.

    Attributes
    ----------
    target : (n_rows,) int ndarray
        Target index (into the :class:`TargetField`) of every row of the measurement table,
        -1 where the row is not identified. When the start was wrong (``reason`` says the
        points do not fit, too few of the expected targets were found, or the seeds disagree)
        every row is -1.
    R_world_to_camera : (3, 3) ndarray or None
        The image's pose from the identified points (None when no pose was found).
    center_m : (3,) ndarray or None
        Camera centre [m].
    n_identified : int
        Rows identified (discs and markers).
    n_coded : int
        Markers whose code names a surveyed target.
    n_seeds : int
        Seeds used to start: coded targets plus marks.
    gate_px : float
        Median gate of the last matching [px].
    rms_px : float
        RMS of the identified points' residuals after the local correction [px]
        (``sqrt(mean(du^2 + dv^2))``).
    residual_px : (n_rows, 2) ndarray
        Measured minus projected pixel of every identified row (before the local
        correction; NaN elsewhere) [px].
    wrong_marks : (k,) int ndarray
        Target indices of marks that disagree with the identification.
    wrong_codes : (k,) int ndarray
        Codes of markers that disagree with the identification (their target's survey or
        code is wrong, or the marker is a false detection).
    iterations : int
        Rounds of resection and matching.
    reason : str
        Empty when the image is usable; otherwise why it is not.
    """

    target: np.ndarray
    R_world_to_camera: np.ndarray | None
    center_m: np.ndarray | None
    n_identified: int
    n_coded: int
    n_seeds: int
    gate_px: float
    rms_px: float
    residual_px: np.ndarray
    wrong_marks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    wrong_codes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    iterations: int = 0
    reason: str = ""

    @property
    def ok(self) -> bool:
        """Whether the image is usable for the adjustment."""
        return self.reason == ""


# ---------------------------------------------------------------------------- building blocks
def measured_points(measurements: pa.Table):
    """Columns of a ``measurements`` table as arrays: ``kind`` (str), ``code`` (-1 for
    discs), ``uv`` (n, 2) [px], ``usable`` (finite and not truncated at the border)."""
    n = measurements.num_rows
    names = measurements.column_names
    for c in ("kind", "u_px", "v_px"):
        if c not in names:
            raise InputError(f"measurements table lacks the column {c!r}")
    kind = np.asarray(measurements.column("kind").to_pylist(), dtype=object).astype(str) if n else np.zeros(0, str)
    code = (np.asarray(measurements.column("code").fill_null(-1).to_numpy(zero_copy_only=False), np.int64)
            if "code" in names else np.full(n, -1, np.int64))
    uv = np.stack([measurements.column("u_px").to_numpy(zero_copy_only=False).astype(float),
                   measurements.column("v_px").to_numpy(zero_copy_only=False).astype(float)], axis=1)
    usable = np.isfinite(uv).all(axis=1)
    if "truncated" in names:
        usable &= ~np.asarray(measurements.column("truncated").fill_null(False)
                              .to_numpy(zero_copy_only=False), bool)
    return kind, code, uv.reshape(n, 2), usable


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


def _prediction_spacing(pred):
    """Distance from each prediction to the nearest other one [px] (inf when alone)."""
    if len(pred) < 2:
        return np.full(len(pred), np.inf)
    d, _ = cKDTree(pred).query(pred, k=2)
    return d[:, 1]


def _opencv_inputs(X, uv, camera):
    origin = X.mean(axis=0)
    obj = np.ascontiguousarray(X - origin, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(ideal_pixels(uv, camera), np.float64).reshape(-1, 1, 2)
    return origin, obj, img, opencv_camera_matrix(camera)


def _grunert_distances(X, rays):
    """Distances ``(s1, s2, s3)`` along unit ``rays`` (3, 3) to world points ``X`` (3, 3).

    Grunert's P3P solution (as reviewed by Haralick et al., IJCV 13(3), 1994): with
    ``s2 = u s1``, ``s3 = v s1`` the law of cosines in the three triangles through the
    centre gives a quartic in ``v``. Near the "danger cylinder" two of its real roots merge
    and a little noise turns them into a complex pair; OpenCV's P3P then drops both and
    with them the right pose. Here every root contributes its real part (the pose is then
    refined by least squares), so the candidate survives. Returns an (k, 3) array.
    """
    a2 = np.sum((X[1] - X[2]) ** 2)
    b2 = np.sum((X[0] - X[2]) ** 2)
    c2 = np.sum((X[0] - X[1]) ** 2)
    ca, cb, cg = rays[1] @ rays[2], rays[0] @ rays[2], rays[0] @ rays[1]
    p, q = (a2 - c2) / b2, (a2 + c2) / b2
    A4 = (p - 1) ** 2 - 4 * c2 / b2 * ca**2
    A3 = 4 * (p * (1 - p) * cb - (1 - q) * ca * cg + 2 * c2 / b2 * ca**2 * cb)
    A2 = 2 * (p**2 - 1 + 2 * p**2 * cb**2 + 2 * (b2 - c2) / b2 * ca**2 - 4 * q * ca * cb * cg
              + 2 * (b2 - a2) / b2 * cg**2)
    A1 = 4 * (-p * (1 + p) * cb + 2 * a2 / b2 * cg**2 * cb - (1 - q) * ca * cg)
    A0 = (1 + p) ** 2 - 4 * a2 / b2 * cg**2
    coef = np.array([A4, A3, A2, A1, A0])
    if not np.all(np.isfinite(coef)) or np.all(coef == 0):
        return np.zeros((0, 3))
    v = np.roots(coef).real
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((p - 1) * v**2 - 2 * p * cb * v + 1 + p) / (2 * (cg - v * ca))
        s1 = np.sqrt(b2 / (1 + v**2 - 2 * v * cb))
    s = np.stack([s1, u * s1, v * s1], axis=1)
    return s[np.isfinite(s).all(axis=1) & (s > 0).all(axis=1)]


def _p3p_poses(X, uv, camera):
    """Poses (fieldcal convention) that fit three points (:func:`_grunert_distances`, the
    points in the camera frame aligned with the world by Kabsch's rotation, then refined by
    ``cv2.solvePnPRefineLM``)."""
    rays = camera.unproject(uv)                      # fieldcal camera frame
    origin, obj, img, K = _opencv_inputs(X, uv, camera)
    Xl = X - origin
    out = []
    for s in _grunert_distances(Xl, rays):
        Pc = rays * s[:, None]
        H = (Xl - Xl.mean(axis=0)).T @ (Pc - Pc.mean(axis=0))
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T                           # Pc = R (Xl - Cl)
        Cl = Xl.mean(axis=0) - R.T @ Pc.mean(axis=0)
        R_cv = FLIP_YZ @ R
        rv, _ = cv2.Rodrigues(R_cv)
        tv = -R_cv @ Cl
        try:
            rv, tv = cv2.solvePnPRefineLM(obj, img, K, None, rv.reshape(3, 1), tv.reshape(3, 1).copy())
        except cv2.error:
            pass
        R2, C2 = pose_from_opencv(rv, tv)
        if np.all(np.isfinite(R2)) and np.all(np.isfinite(C2)):
            out.append((R2, C2 + origin))
    return out


# ---------------------------------------------------------------------------- the matcher
class _Matcher:
    """Projection, matching and local correction for one image (shared by all candidates)."""

    def __init__(self, X, match_target, meas_uv, camera, opt: IdentifyOptions, target_sigma_m=None):
        self.X = X
        self.target_sigma_m = target_sigma_m  # (n_t,) or None
        self.prior_px = np.zeros(len(X))
        self.match_target = match_target      # (n_t,) bool: targets matched to discs
        self.meas = meas_uv                   # (n_m, 2) usable discs
        self.camera = camera
        self.gate_px = opt.gate_px
        self.factor = opt.gate_factor
        self.min_gate = opt.min_gate_px
        self.first_fraction = opt.first_gate_fraction
        self.neighbours = opt.neighbours
        s = camera.sensor
        self.reach_mm = 1.5 * 0.5 * np.array([s.width_px, s.height_px]) * s.pixel_mm
        self.lo = np.array([-0.5, -0.5])
        self.hi = np.array([s.width_px - 0.5, s.height_px - 0.5])

    def project(self, R, C):
        """Predicted pixels (n, 2) of every target (NaN where not imaged) and which are in the frame.

        Only the targets within 1.5 times the frame's half-size (ideal image) are carried through
        the distortion: a hundredth of a large field is in view."""
        R, C = np.asarray(R, float), np.asarray(C, float)
        Xc = (self.X - C) @ R.T
        with np.errstate(divide="ignore", invalid="ignore"):
            q = -self.camera.f_mm * Xc[:, :2] / Xc[:, 2:3]
        near = (Xc[:, 2] < 0) & (np.abs(q) <= self.reach_mm).all(axis=1)
        uv = np.full((len(self.X), 2), np.nan)
        uv[near] = self.camera.project(self.X[near], R, C)
        if self.target_sigma_m is not None:     # the survey's uncertainty seen from this pose [px]
            depth = np.abs((self.X - np.asarray(C)) @ np.asarray(R)[2])
            with np.errstate(divide="ignore", invalid="ignore"):
                self.prior_px = np.nan_to_num(self.target_sigma_m * self.camera.f_mm / depth
                                              / self.camera.sensor.pixel_mm, posinf=0.0)
        inside = np.isfinite(uv).all(axis=1) & (uv >= self.lo).all(axis=1) & (uv <= self.hi).all(axis=1)
        return uv, inside

    def first_gates(self, uv, inside):
        """The wide gate of the first matching: a fraction of the local prediction spacing."""
        gate = np.full(len(uv), np.nan)
        k = np.flatnonzero(inside)
        gate[k] = self.first_fraction * _prediction_spacing(uv[k])
        if self.gate_px is not None:
            gate[k] = np.minimum(gate[k], self.gate_px)
        return gate

    def match(self, uv, inside, gate, corr):
        """Pairs (target indices, measured indices) of the predicted points ``uv + corr``."""
        t = np.flatnonzero(inside & self.match_target & np.isfinite(gate))
        i, j = mutual_nearest(uv[t] + corr[t], gate[t], self.meas)
        return t[i], j

    def corrected(self, uv, inside, tm, jm):
        """Local correction, its spread and the gates, from the pairs ``(tm, jm)``."""
        n = len(uv)
        corr, spread = np.zeros((n, 2)), np.zeros(n)
        first = self.first_gates(uv, inside)
        res = self.meas[jm] - uv[tm]
        if len(tm) < 4:       # too few pairs for a correction: the first gates and raw residuals
            return corr, spread, first, np.inf, np.hypot(res[:, 0], res[:, 1])
        self_index = np.full(n, -1)
        self_index[tm] = np.arange(len(tm))
        k = np.flatnonzero(inside)
        corr[k], spread[k] = local_correction(uv[k], uv[tm], res, self_index[k], neighbours=self.neighbours)
        e = res - corr[tm]                                     # leave-one-out corrected residuals
        s = max(float(robust_sigma(e)), 1e-3)
        gate = np.clip(self.factor * np.sqrt(s**2 + spread**2 + self.prior_px**2), self.min_gate, first)
        return corr, spread, gate, s, np.hypot(e[:, 0], e[:, 1])


def _score(matcher, R, C):
    """Targets a pose identifies with the first gate (the verification of a candidate)."""
    uv, inside = matcher.project(R, C)
    tm, _ = matcher.match(uv, inside, matcher.first_gates(uv, inside), np.zeros_like(uv))
    return len(tm)


def _candidate_poses(seed_X, seed_uv, camera, init_pose, threshold_px, where):
    """The first candidates: the given pose and the resection of all seeds."""
    cands = []
    if init_pose is not None:
        cands.append((np.asarray(init_pose[0], float), np.asarray(init_pose[1], float)))
    n = len(seed_X)
    if n >= 3 and not is_collinear(seed_X):
        # SQPnP's global optimum of all seeds, unchecked (resect refuses a pose that puts a
        # wrong seed behind the camera; as a start for the triples it is still useful)
        origin, obj, img, K = _opencv_inputs(seed_X, seed_uv, camera)
        try:
            ok, rv, tv = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                R, C = pose_from_opencv(rv, tv)
                cands.append((R, C + origin))
        except cv2.error:
            pass
    if n >= 4 and not is_collinear(seed_X):
        for ransac in ((False, True) if n >= 6 else (False,)):
            try:
                r = resect(seed_X, seed_uv, camera, ransac=ransac, where=where,
                           threshold_px=threshold_px, min_inliers=min(6, n))
                cands.append((r.R_world_to_camera, r.center_m))
            except GeometryError:
                pass
    return cands


def _subset_poses(seed_X, seed_uv, camera, where, rng):
    """Fallback candidates: the seeds less one (resection), and every triple (P3P)."""
    n = len(seed_X)
    cands = []
    if n >= 5:
        for k in range(n):
            keep = np.arange(n) != k
            if is_collinear(seed_X[keep]):
                continue
            try:
                r = resect(seed_X[keep], seed_uv[keep], camera, where=where)
                cands.append((r.R_world_to_camera, r.center_m))
            except GeometryError:
                pass
    triples = list(itertools.combinations(range(n), 3))
    if len(triples) > _MAX_TRIPLES:
        triples = [triples[i] for i in rng.choice(len(triples), _MAX_TRIPLES, replace=False)]
    for tri in triples:
        tri = list(tri)
        if is_collinear(seed_X[tri]):
            continue
        cands.extend(_p3p_poses(seed_X[tri], seed_uv[tri], camera))
    return cands


@dataclass(frozen=True)
class IdentifyOptions:
    """Settings of :func:`identify_image` (module docstring, steps 1-5).

    Attributes
    ----------
    gate_px : float, optional
        Upper bound of the gate [px]; default ``first_gate_fraction`` of the local spacing of
        the predictions only.
    min_identified : int
        Fewer identified targets and the image is not usable (``reason`` says so); >= 4.
    gate_factor, min_gate_px, first_gate_fraction, neighbours, max_iterations
        The matcher's settings (module docstring, steps 2-4).
    min_fraction : float
        The image is not usable when fewer than this fraction of the plain targets the final
        pose puts well inside the frame (at most the number of measured discs) are
        identified: a pose from wrong seeds matches only a few by chance.
    max_rms_fraction : float
        The image is not usable when the RMS of the identified points' residuals, after the
        local correction, exceeds this fraction of the targets' spacing in the image (a right
        identification fits to the measurement noise, a wrong one to a good part of the spacing).
    max_starts : int
        When the best-scored start is not convincing (step 1), up to this many of the best
        candidate poses are refined, and the first that fits is kept.
    """

    gate_px: float | None = None
    min_identified: int = DEFAULT_MIN_IDENTIFIED
    gate_factor: float = 5.0
    min_gate_px: float = 1.0
    first_gate_fraction: float = 0.3
    neighbours: int = 8
    max_iterations: int = 12
    min_fraction: float = 0.3
    max_rms_fraction: float = 0.05
    max_starts: int = 3

    def __post_init__(self):
        if self.min_identified < 4:
            raise InputError(f"min_identified must be at least 4, got {self.min_identified}")


@dataclass
class _Seeds:
    """The seeds of one image: coded targets (marker rows whose code names a target) and marks."""

    coded_rows: np.ndarray     # (c,) rows of the measurement table
    coded_t: np.ndarray        # (c,) their targets
    t: np.ndarray              # (s,) targets of all seeds, markers first
    uv: np.ndarray             # (s, 2) [px]
    is_mark: np.ndarray        # (s,) bool
    n_marks: int


def _seeds_of(kind, code, uv_all, usable, tcodes, n_targets, marks, where) -> _Seeds:
    code_to_target = {int(c): k for k, c in enumerate(tcodes) if c >= 0}
    marker_rows = np.flatnonzero((kind == "aruco") & usable)
    marker_t = np.array([code_to_target.get(int(c), -1) for c in code[marker_rows]], np.int64)
    coded_rows, coded_t = marker_rows[marker_t >= 0], marker_t[marker_t >= 0]
    seed_t, seed_uv, n_marks = [coded_t], [uv_all[coded_rows]], 0
    if marks is not None:
        mt, muv = np.asarray(marks[0], np.int64).reshape(-1), np.asarray(marks[1], float).reshape(-1, 2)
        if len(mt) != len(muv):
            raise InputError(f"marks: {len(mt)} target indices but {len(muv)} points", where or None)
        if len(mt) and (mt.min() < 0 or mt.max() >= n_targets):
            raise InputError("marks: target index out of range", where or None)
        new = ~np.isin(mt, coded_t)               # a marked coded target: the marker is better
        seed_t.append(mt[new])
        seed_uv.append(muv[new])
        n_marks = int(new.sum())
    t = np.concatenate(seed_t).astype(np.int64)
    return _Seeds(coded_rows, coded_t, t, np.concatenate(seed_uv).reshape(-1, 2),
                  np.arange(len(t)) >= len(coded_t), n_marks)


def identify_image(measurements: pa.Table, targets: TargetField, camera: Camera, *,
                   marks=None, init_pose=None, target_sigma_m=None, codes_are_markers: bool = True,
                   options: IdentifyOptions | None = None, where: str = "",
                   seed: int = 0) -> ImageIdentification:
    """Identify the measured targets of one image (see the module docstring).

    Parameters
    ----------
    measurements : pyarrow.Table
        The image's ``measurements`` table (:func:`fieldcal.measure.targets.measure_image`).
    targets : TargetField
        The surveyed targets (or adjusted coordinates in a second pass); ``codes`` names the
        coded targets.
    camera : Camera
        The interior orientation to project with: the nominal one (principal point at the
        centre, no distortion) in a first pass, the calibrated one afterwards.
    marks : (target indices (k,), uv (k, 2) [px]), optional
        Hand-identified targets of this image (``marks.csv``, as
        :func:`fieldcal.session.loader.read_marks_csv` returns them per image).
    init_pose : (R_world_to_camera (3, 3), center_m (3,)), optional
        An approximate pose (e.g. from an adjustment, or a pose prior); tried as a candidate.
        Without it at least 3 seeds are needed.
    target_sigma_m : float or (n,) array_like, optional
        One-sigma uncertainty of each target's coordinates [m] (survey, or adjustment). Seen
        from the pose it widens the target's gate (in quadrature with the residual scale),
        so that a target known worse than its neighbours is not missed.
    codes_are_markers : bool
        Coded targets are seen as ArUco markers and identified by their codes only (the
        session has ``field.coded``); ``False`` matches every target to discs.
    options : IdentifyOptions, optional
        The matcher's settings and the checks' limits.
    where : str
        The image's name, for messages.
    seed : int
        Seeds the choice of triples when there are many seeds.

    Returns
    -------
    ImageIdentification
    """
    opt = options or IdentifyOptions()
    kind, code, uv_all, usable = measured_points(measurements)
    n_rows = len(kind)
    X = np.asarray(targets.xyz_m, float)
    tcodes = np.asarray(targets.codes, np.int64)
    sd = _seeds_of(kind, code, uv_all, usable, tcodes, len(X), marks, where)
    n_seeds = len(sd.t)

    def failed(reason):
        return ImageIdentification(np.full(n_rows, -1, np.int64), None, None, 0, len(sd.coded_t), n_seeds,
                                   np.nan, np.nan, np.full((n_rows, 2), np.nan), reason=reason)

    if init_pose is None and n_seeds < 3:
        if n_seeds == 0:
            return failed("no coded targets seen and no marks: nothing to start the identification from")
        return failed(f"only {n_seeds} seed(s) (coded targets and marks); at least 3 (better 4) are needed")

    match_target = tcodes < 0 if codes_are_markers else np.ones(len(X), bool)
    disc_rows = np.flatnonzero((kind == "disc") & usable)
    if target_sigma_m is not None:
        target_sigma_m = np.broadcast_to(np.asarray(target_sigma_m, float), (len(X),))
    matcher = _Matcher(X, match_target, uv_all[disc_rows], camera, opt, target_sigma_m)
    cands, scores, convincing = _starting_poses(matcher, sd, X, init_pose, opt, where, seed)
    if not cands:
        return failed("no pose could be computed from the seeds (collinear or inconsistent)")
    best = _best_refined(matcher, cands, scores, convincing, sd, X, uv_all, opt, where)
    return _finish(matcher, best, sd, n_rows, disc_rows, kind, code, uv_all, init_pose, opt)


def _starting_poses(matcher, sd: _Seeds, X, init_pose, opt: IdentifyOptions, where, seed):
    """Step 1: candidate poses, their scores, and whether the best is convincing."""
    meas = matcher.meas
    # a generous threshold for the seeds' RANSAC: the nominal camera's distortion is in them
    disc_spacing = np.median(_prediction_spacing(meas)) if len(meas) >= 2 else np.inf
    seed_thr = float(np.clip(0.3 * disc_spacing, 4.0, 1e4)) if np.isfinite(disc_spacing) else 50.0
    sX, suv = X[sd.t], sd.uv
    if init_pose is not None:   # a convincing approximate pose needs no seeds' candidates
        pose = (np.asarray(init_pose[0], float), np.asarray(init_pose[1], float))
        score = _score(matcher, *pose)
        _, inside0 = matcher.project(*pose)
        if score >= max(opt.min_identified, 0.5 * int(np.sum(inside0 & matcher.match_target))) and \
                (len(sd.t) == 0 or _seeds_agree(matcher, pose, sX, suv)):
            return [pose], [score], True
    cands = _candidate_poses(sX, suv, matcher.camera, init_pose, seed_thr, where)
    scores = [_score(matcher, R, C) for R, C in cands]
    convincing = False
    if cands:
        best = cands[int(np.argmax(scores))]
        _, inside0 = matcher.project(*best)
        expected0 = int(np.sum(inside0 & matcher.match_target))
        convincing = (max(scores) >= max(opt.min_identified, 0.5 * expected0)
                      and _seeds_agree(matcher, best, sX, suv))
    if not convincing and len(sd.t) >= 3:
        more = _subset_poses(sX, suv, matcher.camera, where, np.random.default_rng(seed))
        cands += more
        scores += [_score(matcher, R, C) for R, C in more]
    return cands, scores, convincing


def _refine(matcher, R, C, sd: _Seeds, X, uv_all, opt: IdentifyOptions, where) -> dict:
    """Steps 2-4 from one starting pose: match, correct, re-resect until the pairs are stable."""
    uv, inside = matcher.project(R, C)
    corr = np.zeros_like(uv)
    gate = matcher.first_gates(uv, inside)
    pairs = None
    iterations = 0
    for _ in range(opt.max_iterations):
        iterations += 1
        tm, jm = matcher.match(uv, inside, gate, corr)
        key = (tuple(tm), tuple(jm))
        if key == pairs:
            break
        pairs = key
        # the markers join the pose where they agree with it (a wrong code must not pull it)
        c_ok = np.zeros(len(sd.coded_t), bool)
        if len(sd.coded_t):
            c_corr, _ = _correction_at(matcher, uv, tm, jm, sd.coded_t)
            c_err = np.hypot(*(uv_all[sd.coded_rows] - uv[sd.coded_t] - c_corr).T)
            c_ok = np.isfinite(c_err) & (c_err <= _seed_tolerance(matcher, uv, sd.coded_t, gate))
        if len(tm) + c_ok.sum() < 4:
            break
        Xp = np.concatenate([X[tm], X[sd.coded_t[c_ok]]])
        uvp = np.concatenate([matcher.meas[jm], uv_all[sd.coded_rows[c_ok]]])
        if is_collinear(Xp):
            break
        try:
            r = resect(Xp, uvp, matcher.camera, init=(R, C), where=where)
        except GeometryError:
            break
        R, C = r.R_world_to_camera, r.center_m
        uv, inside = matcher.project(R, C)
        corr, _, gate, _, _ = matcher.corrected(uv, inside, tm, jm)
    # final pairs with the last pose and gates
    tm, jm = matcher.match(uv, inside, gate, corr)
    corr, _, gate, s, e = matcher.corrected(uv, inside, tm, jm)
    good = e <= gate[tm]
    spacing = float(np.median(_prediction_spacing(uv[inside]))) if inside.sum() > 1 else np.inf
    rms = float(np.sqrt(np.mean(e[good] ** 2))) if good.any() else np.inf
    return dict(R=R, C=C, uv=uv, inside=inside, corr=corr, gate=gate, s=s, tm=tm[good], jm=jm[good],
                e=e[good], iterations=iterations, spacing=spacing, fits=rms <= opt.max_rms_fraction * spacing)


def _best_refined(matcher, cands, scores, convincing, sd, X, uv_all, opt: IdentifyOptions, where) -> dict:
    """Step 4's choice: refine the best-scored start, or up to ``max_starts`` until one fits."""
    order = np.argsort(scores, kind="stable")[::-1]
    tried, best = [], None
    for k in order[: 1 if convincing else opt.max_starts]:
        R, C = cands[k]
        if any(np.linalg.norm(C - C2) < 1e-6 * (1 + np.linalg.norm(C)) for C2 in tried):
            continue
        tried.append(C)
        st = _refine(matcher, R, C, sd, X, uv_all, opt, where)
        if best is None or (st["fits"], len(st["tm"])) > (best["fits"], len(best["tm"])):
            best = st
        if st["fits"] and len(st["tm"]) >= max(opt.min_identified, 0.5 * scores[k]):
            break
    return best


def _finish(matcher, best, sd: _Seeds, n_rows, disc_rows, kind, code, uv_all, init_pose,
            opt: IdentifyOptions) -> ImageIdentification:
    """The identities of the rows, the markers and marks checked against the pose (step 5)."""
    R, C, uv, gate, s = best["R"], best["C"], best["uv"], best["gate"], best["s"]
    tm, jm, e = best["tm"], best["jm"], best["e"]
    target = np.full(n_rows, -1, np.int64)
    target[disc_rows[jm]] = tm
    residual = np.full((n_rows, 2), np.nan)
    residual[disc_rows[jm]] = matcher.meas[jm] - uv[tm]
    wrong_codes, e_codes = np.zeros(0, np.int64), np.zeros(0)
    if len(sd.coded_t):     # markers: identified by code, kept when they agree with the pose
        # a coded target's correction comes from the discs around it
        c_corr, c_spread = _correction_at(matcher, uv, tm, jm, sd.coded_t)
        cres = uv_all[sd.coded_rows] - uv[sd.coded_t]
        ce = np.hypot(*(cres - c_corr).T)
        cgate = np.clip(opt.gate_factor * np.hypot(s if np.isfinite(s) else 0.0, c_spread), opt.min_gate_px,
                        np.inf)
        cgate = np.maximum(cgate, _seed_tolerance(matcher, uv, sd.coded_t, gate))
        agree = np.isfinite(ce) & (ce <= cgate)
        # a coded target matched as a disc too (codes_are_markers=False): the marker wins
        twice = np.isin(target, sd.coded_t[agree]) & (kind == "disc")
        target[twice] = -1
        residual[twice] = np.nan
        target[sd.coded_rows[agree]] = sd.coded_t[agree]
        residual[sd.coded_rows[agree]] = cres[agree]
        wrong_codes, e_codes = code[sd.coded_rows[~agree]], ce[agree]
    wrong_marks = np.zeros(0, np.int64)
    if sd.n_marks:          # marks: compared with the prediction of their target
        mt, muv = sd.t[sd.is_mark], sd.uv[sd.is_mark]
        m_corr, _ = _correction_at(matcher, uv, tm, jm, mt)
        d = np.hypot(*(muv - uv[mt] - m_corr).T)
        wrong_marks = mt[~(np.isfinite(d) & (d <= _seed_tolerance(matcher, uv, mt, gate)))]
    n_id = int(np.sum(target >= 0))
    e_all = np.concatenate([e, e_codes])
    rms = float(np.sqrt(np.mean(e_all**2))) if len(e_all) else np.nan
    gate_med = float(np.median(gate[tm])) if len(tm) else np.nan
    n_wrong = len(wrong_marks) + len(wrong_codes)
    reason = _verdict(matcher, best, n_id, rms, len(disc_rows), n_wrong, len(sd.t), init_pose, opt)
    if reason and n_id >= opt.min_identified:      # a wrong start: none of its identities is trusted
        target[:] = -1
        residual[:] = np.nan
        n_id = 0
    return ImageIdentification(target, R, C, n_id, len(sd.coded_t), len(sd.t), gate_med, rms, residual,
                               wrong_marks=np.asarray(wrong_marks, np.int64),
                               wrong_codes=np.asarray(wrong_codes, np.int64), iterations=best["iterations"],
                               reason=reason)


def _verdict(matcher, best, n_id, rms, n_discs, n_wrong, n_seeds, init_pose, opt: IdentifyOptions) -> str:
    """Why the image is not usable ("" when it is): step 5's checks."""
    uv, inside, tm = best["uv"], best["inside"], best["tm"]
    # targets the pose puts in the frame, away from the border, that could have been matched
    s_ = matcher.camera.sensor
    margin = 0.5 * float(np.median(_prediction_spacing(uv[inside]))) if inside.sum() > 1 else 0.0
    margin = min(margin, 0.1 * min(s_.width_px, s_.height_px))
    well_inside = inside & (uv[:, 0] > margin) & (uv[:, 1] > margin) & \
        (uv[:, 0] < s_.width_px - 1 - margin) & (uv[:, 1] < s_.height_px - 1 - margin)
    expected = min(int(np.sum(well_inside & matcher.match_target)), n_discs)
    if n_id < opt.min_identified:
        return f"only {n_id} target(s) identified, at least {opt.min_identified} needed"
    if not best["fits"]:
        return (f"the identified points do not fit one pose (RMS {rms:.3g} px after the local "
                f"correction, spacing of the targets {best['spacing']:.3g} px): the start (marks, "
                "codes or nominal focal length) is probably wrong")
    if len(tm) < opt.min_fraction * expected:
        return (f"only {len(tm)} of about {expected} targets expected in the frame identified: the "
                "start (marks, codes or nominal focal length) is probably wrong")
    if n_seeds and init_pose is None and n_wrong > 0.5 * n_seeds:
        return (f"{n_wrong} of the {n_seeds} seeds (marks and coded targets) disagree with the "
                "identification: the marks or codes are unreliable")
    return ""


def _correction_at(matcher, uv, tm, jm, t):
    """Local correction and spread at the predictions of targets ``t`` from the pairs."""
    if len(tm) < 4:
        return np.zeros((len(t), 2)), np.zeros(len(t))
    res = matcher.meas[jm] - uv[tm]
    self_index = np.full(len(t), -1)
    pos = {int(a): k for k, a in enumerate(tm)}
    self_index[:] = [pos.get(int(a), -1) for a in t]
    at = np.where(np.isfinite(uv[t]), uv[t], 0.0)
    return local_correction(at, uv[tm], res, self_index, neighbours=matcher.neighbours)


def _seed_tolerance(matcher, uv, t, gate):
    """How far a seed may be from its target's prediction: 3 gates or a quarter spacing."""
    finite = np.isfinite(uv).all(axis=1)
    spacing = np.full(len(uv), np.inf)
    k = np.flatnonzero(finite)
    spacing[k] = _prediction_spacing(uv[k])
    g = np.where(np.isfinite(gate[t]), gate[t], matcher.min_gate)
    return np.maximum(3.0 * g, 0.25 * np.where(np.isfinite(spacing[t]), spacing[t], 0.0))


def _seeds_agree(matcher, pose, sX, suv) -> bool:
    """Do all seeds lie within a quarter spacing of their targets' projections?"""
    uv, inside = matcher.project(*pose)
    finite = np.isfinite(uv).all(axis=1)
    k = np.flatnonzero(finite)
    if len(k) < 2:
        return False
    tree = cKDTree(uv[k])
    pred = matcher.camera.project(sX, *pose)
    if not np.isfinite(pred).all():
        return False
    d_nb, _ = tree.query(pred, k=2)
    return bool(np.all(np.hypot(*(suv - pred).T) <= 0.25 * d_nb[:, 1]))
