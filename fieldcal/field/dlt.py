"""Initial exterior and interior orientation of one image: DLT, planar pose, Zhang's focal length.

Method (METHODS part A, step 1, eq. 1-6)
---------------------------------------
The direct linear transformation models an image as a projective camera

    lambda [u, v, 1]^T = P [X, Y, Z, 1]^T,        P = K [R_cv | -R_cv C]        (eq. 1)

with pixel coordinates ``(u, v)`` (docs/conventions.md section 1), world points ``X`` [m] and the
3x4 matrix ``P`` [px] known up to scale (11 parameters). Each point gives two linear
equations in the 12 entries ``m`` of ``P`` (eq. 2):

    [X^T  0^T  -u X^T] m = 0,      [0^T  X^T  -v X^T] m = 0        (X homogeneous)

and with n >= 6 points in general (non-coplanar) position the least-squares ``m`` is the
right singular vector of the stacked 2n x 12 matrix ``G`` with the smallest singular value.
Both point sets are first normalised (Hartley): translated to their centroid and scaled
isotropically to a mean distance of sqrt(2) (image) and sqrt(3) (world), which makes
``G`` well conditioned at the magnitudes of a field calibration (thousands of pixels,
tens of metres); ``P`` is de-normalised afterwards.

Decomposition. ``P`` is scaled so that ``det P[:, :3] > 0`` and ``|P[2, :3]| = 1``
(the paper's lambda); then the depth of a point in front of the camera is the positive
third homogeneous coordinate. The RQ decomposition ``P[:, :3] = K R_cv`` with the
diagonal of ``K`` made positive gives a proper rotation ``R_cv``. The camera centre is
the null vector of ``P``. ``K`` and ``R_cv`` are in OpenCV's camera frame (x right,
y down, z forward); fieldcal's frame (x right, y up, z backwards, docs/conventions.md section 1) is

    R_world_to_camera = diag(1, -1, -1) R_cv,    f = (alpha + beta)/2 d,
    xp = (cx - (W-1)/2) d,    yp = -(cy - (H-1)/2) d

with ``K = [[alpha, s, cx], [0, beta, cy], [0, 0, 1]]`` [px] and ``d`` the pixel pitch [mm].
(The paper's ``xp = (u0 - W/2) d`` is its own convention; fieldcal follows the contract.)
The DLT has no distortion model: on distorted images its ``K`` absorbs the linear part of
the distortion, and :mod:`fieldcal.field.distortion_init` fits the rest (METHODS step 2).

Flat fields have no DLT (the 2n x 12 system has a 4-dimensional null space); for them
:func:`planar_pose` finds the pose with known intrinsics (OpenCV's IPPE), and
:func:`zhang_focal` estimates the principal distance from several views of the plane
(Zhang's method, with the principal point at the sensor centre and square pixels).

The OpenCV interop helpers (:func:`opencv_camera_matrix`, :func:`ideal_pixels`,
:func:`pose_to_opencv`, :func:`pose_from_opencv`) convert between the two frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.linalg
import scipy.spatial

from fieldcal.errors import GeometryError
from fieldcal.field.geometry import (
    COPLANAR_TOL_REL,
    at,
    check_points,
    is_collinear,
    is_coplanar,
    plane_frame,
    singular_values_centred,
)
from fieldcal.model.camera import Sensor, principal_point_mm
from fieldcal.model.opencv_frames import FLIP_YZ
from fieldcal.robust import MAD_TO_SIGMA, robust_sigma

__all__ = [
    "DltResult",
    "dlt",
    "dlt_robust",
    "dlt_robust_many",
    "zhang_focal",
]

# ---------------------------------------------------------------------------------------
# DLT
# ---------------------------------------------------------------------------------------
MAX_FAST_PATH_AFFINE = 0.02
"""The fast path of :func:`dlt_robust` takes the least-squares DLT of all points only when its
``|aspect - 1|`` and ``|skew|`` are below this (a camera; the DLTs of the synthetic lenses
show at most 0.003). Its inlier test cannot see blunders that pulled the fit: the noise scale
is taken from the same fit's residuals and grows with the pull (wide_field(0), 8 swapped ids
of 125: a robust sigma of 1260 px, every point within 5 sigma, aspect 6, skew 3.5, f 13.7
instead of 24 mm)."""

@dataclass(frozen=True)
class DltResult:
    """One image's DLT: the projective camera and its decomposition (fieldcal's conventions).

    Attributes
    ----------
    f_mm, xp_mm, yp_mm : float
        Principal distance ``(alpha + beta)/2 d`` and principal point [mm] (docs/conventions.md section 1).
    aspect : float
        ``beta / alpha`` (1 for square pixels and no affine distortion).
    skew : float
        ``K[0, 1] / alpha``, dimensionless (0 for perpendicular axes).
    R_world_to_camera : (3, 3) ndarray
        Proper rotation, world -> fieldcal camera frame (x right, y up, z backwards).
    center_m : (3,) ndarray
        Camera centre [m], the null vector of ``P``.
    P : (3, 4) ndarray
        The projection matrix [px], pixel convention of docs/conventions.md section 1, scaled so that
        ``det P[:, :3] > 0`` and ``|P[2, :3]| = 1``.
    K_px : (3, 3) ndarray
        OpenCV-style intrinsic matrix [px] (x right, y down, z forward frame).
    residuals_px : (n, 2) ndarray
        Measured minus DLT-projected pixel, for every input point.
    inliers : (n,) bool ndarray
        Points the estimate used (all of them for :func:`dlt`).
    rms_px : float
        ``sqrt(mean(du^2 + dv^2))`` over the inliers.
    """

    f_mm: float
    xp_mm: float
    yp_mm: float
    aspect: float
    skew: float
    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    P: np.ndarray
    K_px: np.ndarray
    residuals_px: np.ndarray
    inliers: np.ndarray
    rms_px: float


def _normaliser(points):
    """Hartley's similarity (k+1, k+1) taking (n, k) points to centroid 0, mean distance sqrt(k)."""
    k = points.shape[1]
    c = points.mean(axis=0)
    mean_dist = np.linalg.norm(points - c, axis=1).mean()
    s = np.sqrt(k) / mean_dist if mean_dist > 0 else 1.0
    T = np.eye(k + 1)
    T[:k, :k] *= s
    T[:k, k] = -s * c
    return T


def _design(Xh, uv):
    """DLT matrix G (..., 2n, 12) of eq. 2; homogeneous points (..., n, 4), pixels (..., n, 2)."""
    z = np.zeros_like(Xh)
    r1 = np.concatenate([Xh, z, -uv[..., 0:1] * Xh], axis=-1)
    r2 = np.concatenate([z, Xh, -uv[..., 1:2] * Xh], axis=-1)
    G = np.stack([r1, r2], axis=-2)  # (..., n, 2, 12)
    return G.reshape(G.shape[:-3] + (-1, 12))


def _homogeneous(X):
    return np.concatenate([X, np.ones(X.shape[:-1] + (1,))], axis=-1)


def _solve_P(X, uv, normalize: bool = True):
    """Least-squares P (3, 4) [px] from all points; Hartley-normalised unless told not to."""
    if normalize:
        Tw, Ti = _normaliser(X), _normaliser(uv)
    else:
        Tw, Ti = np.eye(4), np.eye(3)
    Xn = _homogeneous(X) @ Tw.T
    uvn = _homogeneous(uv) @ Ti.T
    G = _design(Xn, uvn[:, :2])
    _, _, Vt = np.linalg.svd(G, full_matrices=False)
    Pn = Vt[-1].reshape(3, 4)
    return np.linalg.solve(Ti, Pn) @ Tw


def _project_P(P, X):
    """Pixels (..., n, 2) and depths (..., n) of points (n, 3) through cameras P (..., 3, 4)."""
    h = np.einsum("...ij,nj->...ni", P, _homogeneous(X))
    with np.errstate(divide="ignore", invalid="ignore"):
        return h[..., :2] / h[..., 2:3], h[..., 2]


def _decompose(P, X, uv, sensor: Sensor, inliers, where: str) -> DltResult:
    M = P[:, :3]
    det = np.linalg.det(M)
    if not np.isfinite(det) or abs(det) < 1e-300:
        raise GeometryError(
            at(where, "DLT: the 3x3 part of P is singular (degenerate point configuration)")
        )
    P = P * (np.sign(det) / np.linalg.norm(P[2, :3]))
    K, R_cv = scipy.linalg.rq(P[:, :3])
    D = np.diag(np.sign(np.diag(K)))
    K, R_cv = K @ D, D @ R_cv
    K = K / K[2, 2]
    _, _, Vt = np.linalg.svd(P)
    c_h = Vt[-1]
    if abs(c_h[3]) < 1e-12 * np.linalg.norm(c_h[:3]):
        raise GeometryError(
            at(
                where,
                "DLT: camera centre at infinity (affine camera); the points need more depth relief",
            )
        )
    center = c_h[:3] / c_h[3]
    uv_hat, depth = _project_P(P, X)
    if np.count_nonzero(depth[inliers] > 0) < 0.5 * np.count_nonzero(inliers):
        raise GeometryError(
            at(
                where,
                "DLT: the points come out behind the camera: blunders "
                "in the data, a left-handed world frame or a mirrored image",
            )
        )
    res = uv - uv_hat
    rms = float(np.sqrt(np.mean(np.sum(res[inliers] ** 2, axis=1))))
    d = sensor.pixel_mm
    alpha, beta = K[0, 0], K[1, 1]
    xp_mm, yp_mm = principal_point_mm(sensor, K[0, 2], K[1, 2])
    return DltResult(
        f_mm=float(0.5 * (alpha + beta) * d),
        xp_mm=float(xp_mm),
        yp_mm=float(yp_mm),
        aspect=float(beta / alpha),
        skew=float(K[0, 1] / alpha),
        R_world_to_camera=FLIP_YZ @ R_cv,
        center_m=center,
        P=P,
        K_px=K,
        residuals_px=res,
        inliers=np.asarray(inliers, dtype=bool).copy(),
        rms_px=rms,
    )


def _check_dlt_geometry(X, where: str, what: str, tol_rel: float):
    n = len(X)
    if n < 6:
        raise GeometryError(at(where, f"{what} needs at least 6 points, got {n}"))
    if is_collinear(X, tol_rel):
        raise GeometryError(
            at(
                where,
                f"{what}: the {n} world points are collinear; the DLT needs points spread in 3-D",
            )
        )
    if is_coplanar(X, tol_rel):
        s = singular_values_centred(X)
        raise GeometryError(
            at(
                where,
                f"{what}: the {n} world points are coplanar (relative relief "
                f"{s[2] / s[0]:.1e} <= {tol_rel:g}); the DLT needs non-coplanar "
                "points, use planar_pose for a flat field",
            )
        )


def dlt(
    X_world_m,
    uv_px,
    sensor: Sensor,
    *,
    where: str = "",
    normalize: bool = True,
    tol_rel: float = COPLANAR_TOL_REL,
) -> DltResult:
    """The 11-parameter DLT of one image (METHODS A, eq. 1-6), decomposed in fieldcal's frames.

    Parameters
    ----------
    X_world_m : (n, 3) array_like
        Control points [m], n >= 6, not coplanar.
    uv_px : (n, 2) array_like
        Their measured image points [px] (docs/conventions.md section 1).
    sensor : Sensor
        Pixel grid (pitch and size), for the conversion to mm.
    where : str
        The image's name, quoted in error messages.
    normalize : bool
        Hartley normalisation (default). ``False`` only exists to show why it is needed.
    tol_rel : float
        Coplanarity / collinearity tolerance of :func:`is_coplanar`.

    Returns
    -------
    DltResult

    Raises
    ------
    InputError
        Wrong shapes, NaN or infinite coordinates.
    GeometryError
        Fewer than 6 points, coplanar or collinear points, a singular or mirrored solution.
    """
    X, uv = check_points(X_world_m, uv_px, where, "DLT")
    _check_dlt_geometry(X, where, "DLT", tol_rel)
    P = _solve_P(X, uv, normalize=normalize)
    return _decompose(P, X, uv, sensor, np.ones(len(X), bool), where)


def _robust_sigma(res):
    """1.4826 x MAD of the residual components (n, 2) [px]: the noise sigma of one coordinate."""
    r = res.ravel()
    return robust_sigma(r - np.median(r))


def dlt_robust(
    X_world_m,
    uv_px,
    sensor: Sensor,
    *,
    where: str = "",
    k_sigma: float = 5.0,
    floor_px: float = 2.0,
    detrend_degree: int = 3,
    n_trials: int | None = None,
    max_outlier_fraction: float = 0.3,
    confidence: float = 0.999,
    max_rounds: int = 20,
    seed: int = 0,
    tol_rel: float = COPLANAR_TOL_REL,
) -> DltResult:
    """The DLT with blunder rejection: LMedS on minimal 6-point sets, then iterative rejection.

    0. Fast path: the least-squares DLT of all points; when step 2 keeps every point
       with it and its ``K`` is that of a camera (:data:`MAX_FAST_PATH_AFFINE`), that is
       the answer (a fixed point of step 2, which is where the sampled start ends too on
       data without blunders), and the sampling is skipped.
    1. Hypotheses: ``n_trials`` random 6-point samples (default: enough to draw one clean
       sample with probability ``confidence`` at ``max_outlier_fraction`` blunders), each
       solved in Hartley-normalised coordinates (batched SVD); the one with the least median
       reprojection error wins (least median of squares: no threshold needed).
    2. Rejection: the DLT has no distortion model, so on a real lens its residuals are a
       smooth field of up to several pixels (in the corners) plus the noise. A polynomial
       of degree ``detrend_degree`` in the image coordinates (default 3, the order of the
       leading radial term; 10 coefficients per coordinate) is fitted to the residuals of
       the current inliers and removed; what remains is the noise and the blunders. The
       noise sigma of one coordinate is ``1.4826 MAD`` of these detrended residuals; a
       point is an inlier when its detrended residual is below
       ``max(k_sigma sigma, floor_px)``. The DLT is refitted on the inliers and the inliers
       re-selected from all points until the set stops changing. With fewer than three
       inliers per polynomial coefficient (or ``detrend_degree=0``) the raw residuals are
       used, and the floor alone must absorb the distortion.

    Parameters as :func:`dlt`; ``seed`` makes the sampling repeatable.

    Returns
    -------
    DltResult
        With ``inliers`` the points kept; ``residuals_px`` are given for all points.

    Raises
    ------
    GeometryError
        As :func:`dlt`, or fewer than 6 inliers (or a coplanar inlier set) remain.
    """
    X, uv = check_points(X_world_m, uv_px, where, "robust DLT")
    _check_dlt_geometry(X, where, "robust DLT", tol_rel)
    n = len(X)
    Tw, Ti = _normaliser(X), _normaliser(uv)
    uvn = (_homogeneous(uv) @ Ti.T)[:, :2]
    M = _detrend_basis(uvn, detrend_degree)
    select = _InlierRule(X, uv, M, k_sigma, floor_px)
    # fast path: the least-squares DLT of all points, kept when it rejects none of them (a
    # fixed point of step 2, where the sampled start would end too on clean data)
    P_all = _solve_P(X, uv)
    if select(P_all, np.ones(n, bool)).all():
        fast = _camera_like(P_all, X, uv, sensor, where)
        if fast is not None:
            return fast
    P = _lmeds(X, uv, Tw, Ti, uvn, n_trials, max_outlier_fraction, confidence, seed)
    inliers = np.ones(n, bool)
    for _ in range(max_rounds):
        new = select(P, inliers)
        if new.sum() < 6 or is_coplanar(X[new], tol_rel):
            raise GeometryError(
                at(
                    where,
                    f"robust DLT: only {new.sum()} of {n} points fit one "
                    "projective camera in non-coplanar position",
                )
            )
        P = _solve_P(X[new], uv[new])
        if np.array_equal(new, inliers):
            break
        inliers = new
    return _decompose(P, X, uv, sensor, inliers, where)


def _camera_like(P, X, uv, sensor: Sensor, where: str) -> DltResult | None:
    """The decomposition of the fast path's ``P`` (all points inliers), or None when it is not
    a camera: a singular or mirrored ``P``, or an affine part beyond :data:`MAX_FAST_PATH_AFFINE`."""
    try:
        res = _decompose(P, X, uv, sensor, np.ones(len(X), bool), where)
    except GeometryError:
        return None
    if abs(res.aspect - 1.0) > MAX_FAST_PATH_AFFINE or abs(res.skew) > MAX_FAST_PATH_AFFINE:
        return None
    return res


def _lmeds(X, uv, Tw, Ti, uvn, n_trials, max_outlier_fraction, confidence, seed):
    """Step 1 of :func:`dlt_robust`: the least-median-of-squares P (3, 4) [px] of 6-point samples."""
    n = len(X)
    if n_trials is None:
        p_clean = (1.0 - max_outlier_fraction) ** 6
        n_trials = int(np.ceil(np.log(1.0 - confidence) / np.log1p(-p_clean))) if p_clean < 1 else 1
    rng = np.random.default_rng(seed)
    Xn = _homogeneous(X) @ Tw.T
    best_P, best_med = None, np.inf
    if n > 6:
        for start in range(0, n_trials, 256):  # batches bound the (batch, n, 2) residual array
            m = min(256, n_trials - start)
            idx = np.argpartition(rng.random((m, n)), 6, axis=1)[:, :6]
            G = _design(Xn[idx], uvn[idx])  # (m, 12, 12)
            _, _, Vt = np.linalg.svd(G)
            Pn = Vt[:, -1, :].reshape(m, 3, 4)
            hat, _ = _project_P(Pn, Xn[:, :3] / Xn[:, 3:4])
            err = np.sum((hat - uvn) ** 2, axis=-1)
            med = np.median(np.where(np.isfinite(err), err, np.inf), axis=1)
            k = int(np.argmin(med))
            if med[k] < best_med:
                best_med, best_P = med[k], Pn[k]
    if best_P is None:  # exactly 6 points: nothing to vote with
        return _solve_P(X, uv)
    return np.linalg.solve(Ti, best_P) @ Tw


def _detrend_basis(uvn, degree):
    """Monomials ``x^i y^j`` (i + j <= degree) of the normalised pixels (n, n_terms), or None."""
    if degree <= 0:
        return None
    ij = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    return np.stack([uvn[:, 0] ** i * uvn[:, 1] ** j for i, j in ij], axis=1)


class _InlierRule:
    """Step 2 of :func:`dlt_robust`: the points whose detrended residual is within the limit."""

    def __init__(self, X, uv, M, k_sigma, floor_px):
        self.X, self.uv, self.M, self.k_sigma, self.floor_px = X, uv, M, k_sigma, floor_px

    def __call__(self, P, inliers):
        hat, _ = _project_P(P, self.X)
        res = self.uv - hat
        finite = np.all(np.isfinite(res), axis=1)
        res = np.where(finite[:, None], res, 0.0)
        local = res
        use = inliers & finite
        if self.M is not None and np.count_nonzero(use) >= 3 * self.M.shape[1]:
            coef, *_ = np.linalg.lstsq(self.M[use], res[use], rcond=None)
            local = res - self.M @ coef
        e = np.linalg.norm(local, axis=1)
        sigma = _robust_sigma(local[finite])
        return finite & (e <= max(self.k_sigma * sigma, self.floor_px))


# ---------------------------------------------------------------------------------------
# many images at once
# ---------------------------------------------------------------------------------------
DECISION_MARGIN_REL = 1e-6
""":func:`dlt_robust_many` takes a fast path itself only when none of the path's decisions
(coplanarity, collinearity, the inlier limit, :data:`MAX_FAST_PATH_AFFINE`) is within this
relative distance of its limit; closer calls go to :func:`dlt_robust`, so that the batch's
round-off (a different order of the sums) cannot change a decision."""

MAX_DETREND_CONDITION = 1e8
"""Largest condition number of the detrend basis the batched fast path solves by QR; beyond
it the image goes to :func:`dlt_robust` (whose least squares are SVD-based, minimum-norm)."""

MIN_EIGEN_GAP_REL = 1e-6
"""The batched fast path takes the least-squares DLT as the eigenvector of the smallest
eigenvalue of the normal matrix ``G^T G`` only when the gap to the next eigenvalue is above
this fraction of the largest (the eigenvector's round-off is about 1e-16 over this gap:
1e-10 at the limit, ~1e-12 on the paper field); otherwise the image goes to
:func:`dlt_robust`, which takes the SVD of ``G`` itself (squaring ``G`` doubles the condition
number's exponent)."""


def dlt_robust_many(
    views,
    sensor: Sensor,
    *,
    wheres=None,
    seeds=None,
    fallback: bool = True,
    k_sigma: float = 5.0,
    floor_px: float = 2.0,
    detrend_degree: int = 3,
    n_trials: int | None = None,
    max_outlier_fraction: float = 0.3,
    confidence: float = 0.999,
    max_rounds: int = 20,
    tol_rel: float = COPLANAR_TOL_REL,
) -> list:
    """:func:`dlt_robust` of many images, the fast path (step 0) batched over the images.

    The fast path of every image (the geometry checks, Hartley normalisation, the
    least-squares DLT, the detrended inlier test with all points, the decomposition and the
    camera test) is computed for all images at once: images padded to the same point count
    with zero rows, which change neither a least-squares DLT (zero rows of ``G``) nor the
    detrend fit (zero rows of the basis and the residuals), and are left out of every mean and
    median. The DLT is the eigenvector of the smallest eigenvalue of the normal matrices
    ``G^T G`` (12 x 12, summed from the points' outer products without forming ``G``; only
    with the eigenvalue gap of :data:`MIN_EIGEN_GAP_REL`), the detrend the QR of
    ``[M | r]``: the same solutions as :func:`dlt_robust`'s SVD and ``lstsq`` up to round-off
    (1e-12 relative in ``f`` on the paper field, 1e-11 in the principal point). Images with
    fewer than three points per detrend coefficient (raw residuals), whose fast path is not
    taken, or is within :data:`DECISION_MARGIN_REL` of one of its decisions, go to
    :func:`dlt_robust` itself (bad inputs, too few, coplanar or collinear points, blunders:
    the same result or the same error as one call of it).

    Parameters
    ----------
    views : sequence of (X_world_m (n_i, 3), uv_px (n_i, 2))
        Each image's control points [m] and pixels (as :func:`dlt_robust`).
    sensor : Sensor
    wheres : sequence of str, optional
        Each image's name for the error messages (default ``""``).
    seeds : sequence of int, optional
        Each image's ``seed`` of :func:`dlt_robust` (default 0).
    fallback : bool
        ``False``: images whose fast path the batch does not take are ``None`` in the result
        (the caller handles them; nothing is raised).
    k_sigma, floor_px, detrend_degree, n_trials, max_outlier_fraction, confidence, max_rounds, tol_rel
        As :func:`dlt_robust`.

    Returns
    -------
    list
        Per image, the :class:`DltResult` of :func:`dlt_robust` (up to round-off), or the
        :class:`~fieldcal.errors.GeometryError` it raised (or ``None``, ``fallback=False``).

    Raises
    ------
    InputError
        As :func:`dlt_robust` (wrong shapes, NaN or infinite coordinates), for the first such image.
    """
    views = list(views)
    m = len(views)
    wheres = [""] * m if wheres is None else list(wheres)
    seeds = [0] * m if seeds is None else list(seeds)
    out: list = list(_fast_paths(views, sensor, k_sigma, floor_px, detrend_degree, tol_rel))
    if not fallback:
        return out
    for i in range(m):
        if out[i] is not None:
            continue
        X, uv = views[i]
        try:
            out[i] = dlt_robust(
                X, uv, sensor, where=wheres[i], k_sigma=k_sigma, floor_px=floor_px,
                detrend_degree=detrend_degree, n_trials=n_trials,
                max_outlier_fraction=max_outlier_fraction, confidence=confidence,
                max_rounds=max_rounds, seed=seeds[i], tol_rel=tol_rel,
            )
        except GeometryError as err:
            out[i] = err
    return out


def _batch_normaliser(P, w, n):
    """:func:`_normaliser` of padded point sets (B, n_max, k): valid rows ``w`` (B, n_max), counts ``n``."""
    B, _, k = P.shape
    c = (P * w[..., None]).sum(axis=1) / n[:, None]
    mean_dist = (np.linalg.norm(P - c[:, None, :], axis=-1) * w).sum(axis=1) / n
    pos = mean_dist > 0
    s = np.where(pos, np.sqrt(k) / np.where(pos, mean_dist, 1.0), 1.0)
    T = np.zeros((B, k + 1, k + 1))
    T[:, np.arange(k), np.arange(k)] = s[:, None]
    T[:, :k, k] = -s[:, None] * c
    T[:, k, k] = 1.0
    return T


def _batch_median(values, valid, counts):
    """``np.median`` of each row's valid entries (B, L); ``counts`` (B,) >= 1 of them per row."""
    s = np.sort(np.where(valid, values, np.inf), axis=1)
    rows = np.arange(len(s))
    lo, hi = s[rows, (counts - 1) // 2], s[rows, counts // 2]
    return np.where(counts % 2 == 1, hi, (lo + hi) / 2.0)


def _normal_matrix(Xh, uv):
    """``G^T G`` (B, 12, 12) of :func:`_design`'s G, from weighted sums of the points' outer products."""
    B = Xh.shape[0]
    u, v = uv[..., 0], uv[..., 1]
    wts = np.stack([np.ones_like(u), u, v, u * u + v * v], axis=-1)        # (B, n, 4)
    outer = (Xh[..., :, None] * Xh[..., None, :]).reshape(Xh.shape[:-1] + (16,))
    S = (np.swapaxes(wts, -1, -2) @ outer).reshape(B, 4, 4, 4)
    N = np.zeros((B, 12, 12))
    N[:, 0:4, 0:4] = N[:, 4:8, 4:8] = S[:, 0]
    N[:, 0:4, 8:12] = N[:, 8:12, 0:4] = -S[:, 1]
    N[:, 4:8, 8:12] = N[:, 8:12, 4:8] = -S[:, 2]
    N[:, 8:12, 8:12] = S[:, 3]
    return N


def _monomials(uvn, degree):
    """:func:`_detrend_basis` of (..., n, 2) points, the same column order (powers by products)."""
    x, y = [np.ones(uvn.shape[:-1])], [np.ones(uvn.shape[:-1])]
    for _ in range(degree):
        x.append(x[-1] * uvn[..., 0])
        y.append(y[-1] * uvn[..., 1])
    return np.stack([x[i] * y[j] for i in range(degree + 1) for j in range(degree + 1 - i)], axis=-1)


def _rq3(A):
    """RQ decomposition of 3x3 matrices (B, 3, 3): ``A = R Q``, R upper triangular, Q orthogonal.

    From the QR of the row-reversed transpose (``J A`` with ``J`` the exchange matrix:
    ``(J A)^T = Q0 R0`` gives ``A = (J R0^T J)(J Q0^T)``). The signs are LAPACK's; the caller
    makes the diagonal of R positive, which makes the decomposition unique.
    """
    Q0, R0 = np.linalg.qr(np.swapaxes(A[:, ::-1, :], -1, -2))
    return np.swapaxes(R0, -1, -2)[:, ::-1, ::-1], np.swapaxes(Q0, -1, -2)[:, ::-1, :]


def _near(a, limit):
    """Whether ``a`` is within :data:`DECISION_MARGIN_REL` of ``limit`` (elementwise)."""
    return np.abs(a - limit) <= DECISION_MARGIN_REL * np.abs(limit)


def _all_points_kept(P, Xh, uvp, uvn, w, n, k_sigma, floor_px, detrend_degree, n_terms):
    """The inlier rule (:class:`_InlierRule`) with every point an inlier, for padded images
    (B, n_max, .): whether it keeps all of each image's points, clearly (no point within
    :data:`DECISION_MARGIN_REL` of the limit, a detrend basis of condition below
    :data:`MAX_DETREND_CONDITION`, every residual finite)."""
    B, w3 = len(P), w[:, :, None]
    h = Xh @ np.swapaxes(P, -1, -2)
    with np.errstate(divide="ignore", invalid="ignore"):
        res = uvp - h[..., :2] / h[..., 2:3]
    finite = np.all(np.isfinite(res), axis=-1)
    ok = np.all(finite | ~w, axis=1)
    res = np.where(w3 & finite[..., None], res, 0.0)
    local = res
    if n_terms:
        M = _monomials(uvn, detrend_degree) * w3
        Rm = np.linalg.qr(np.concatenate([M, res], axis=-1), mode="r")
        R11 = Rm[:, :n_terms, :n_terms]
        s11 = np.linalg.svd(R11, compute_uv=False)
        well = s11[:, -1] * MAX_DETREND_CONDITION > s11[:, 0]
        ok &= well
        R11 = np.where(well[:, None, None], R11, np.eye(n_terms))
        coef = np.linalg.solve(R11, Rm[:, :n_terms, n_terms:])
        local = res - M @ coef
    e = np.sqrt(local[..., 0] ** 2 + local[..., 1] ** 2)
    comp, valid2 = local.reshape(B, -1), np.repeat(w, 2, axis=1)
    med = _batch_median(comp, valid2, 2 * n)
    sigma = MAD_TO_SIGMA * _batch_median(np.abs(comp - med[:, None]), valid2, 2 * n)
    limit = np.maximum(k_sigma * sigma, floor_px)
    ok &= np.all((e <= limit[:, None]) | ~w, axis=1)
    ok &= ~np.any(_near(e, limit[:, None]) & w, axis=1)
    return ok


def _fast_paths(views, sensor: Sensor, k_sigma, floor_px, detrend_degree, tol_rel):
    """Step 0 of :func:`dlt_robust` for many images at once: a DltResult per image, or None."""
    out = [None] * len(views)
    n_terms = 0 if detrend_degree <= 0 else (detrend_degree + 1) * (detrend_degree + 2) // 2
    idx, Xs, uvs = [], [], []
    for i, (X, uv) in enumerate(views):
        X, uv = np.asarray(X, dtype=float), np.asarray(uv, dtype=float)
        if X.ndim != 2 or X.shape[1] != 3 or uv.ndim != 2 or uv.shape[1] != 2 or len(X) != len(uv):
            continue
        if len(X) < max(6, 3 * n_terms) or not (np.isfinite(X).all() and np.isfinite(uv).all()):
            continue
        idx.append(i)
        Xs.append(X)
        uvs.append(uv)
    if not idx:
        return out
    n = np.array([len(X) for X in Xs])
    B, n_max = len(idx), int(n.max())
    w = np.arange(n_max) < n[:, None]                                  # (B, n_max) valid rows
    rows, cols = np.nonzero(w)
    Xp, uvp = np.zeros((B, n_max, 3)), np.zeros((B, n_max, 2))
    Xp[rows, cols], uvp[rows, cols] = np.concatenate(Xs), np.concatenate(uvs)
    w3 = w[:, :, None]
    # the geometry checks of _check_dlt_geometry: clearly neither collinear nor coplanar
    cX = Xp.sum(axis=1) / n[:, None]
    sv = np.linalg.svd((Xp - cX[:, None, :]) * w3, compute_uv=False)     # (B, 3)
    ok = (sv[:, 1] > tol_rel * sv[:, 0]) & (sv[:, 2] > tol_rel * sv[:, 0])
    ok &= ~(_near(sv[:, 1], tol_rel * sv[:, 0]) | _near(sv[:, 2], tol_rel * sv[:, 0]))
    # the least-squares DLT of all points (_solve_P), Hartley-normalised
    Tw, Ti = _batch_normaliser(Xp, w, n), _batch_normaliser(uvp, w, n)
    Xh = _homogeneous(Xp)
    Xn = (Xh @ np.swapaxes(Tw, -1, -2)) * w3
    uvn = (_homogeneous(uvp) @ np.swapaxes(Ti, -1, -2))[..., :2] * w3
    lam, V = np.linalg.eigh(_normal_matrix(Xn, uvn))                   # ascending
    ok &= lam[:, 1] - lam[:, 0] > MIN_EIGEN_GAP_REL * lam[:, -1]
    P = np.linalg.solve(Ti, V[:, :, 0].reshape(B, 3, 4)) @ Tw
    ok &= _all_points_kept(P, Xh, uvp, uvn, w, n, k_sigma, floor_px, detrend_degree, n_terms)
    # the decomposition (_decompose) and the camera test (_camera_like)
    det = np.linalg.det(P[:, :, :3])
    ok &= np.isfinite(det) & (np.abs(det) >= 1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        P = P * (np.sign(det) / np.linalg.norm(P[:, 2, :3], axis=-1))[:, None, None]
    P = np.where(ok[:, None, None], P, np.eye(3, 4))                    # keep the rest finite
    K, R_cv = _rq3(P[:, :, :3])
    D = np.sign(np.einsum("bii->bi", K))
    K, R_cv = K * D[:, None, :], D[:, :, None] * R_cv
    K = K / K[:, 2:3, 2:3]
    c_h = np.linalg.svd(P)[2][:, -1, :]
    ok &= ~(np.abs(c_h[:, 3]) < 1e-12 * np.linalg.norm(c_h[:, :3], axis=-1))
    h = Xh @ np.swapaxes(P, -1, -2)
    with np.errstate(divide="ignore", invalid="ignore"):
        center = c_h[:, :3] / c_h[:, 3:4]
        uv_hat = h[..., :2] / h[..., 2:3]
    ok &= np.count_nonzero((h[..., 2] > 0) & w, axis=1) >= 0.5 * n
    resid = uvp - uv_hat
    rms = np.sqrt(np.sum(np.where(w3, resid, 0.0) ** 2, axis=(1, 2)) / n)
    alpha, beta = K[:, 0, 0], K[:, 1, 1]
    aspect, skew = beta / alpha, K[:, 0, 1] / alpha
    ok &= (np.abs(aspect - 1.0) <= MAX_FAST_PATH_AFFINE) & (np.abs(skew) <= MAX_FAST_PATH_AFFINE)
    ok &= ~(_near(np.abs(aspect - 1.0), MAX_FAST_PATH_AFFINE) | _near(np.abs(skew), MAX_FAST_PATH_AFFINE))
    d = sensor.pixel_mm
    R_world = FLIP_YZ @ R_cv
    solved = np.flatnonzero(ok)
    pp_mm = principal_point_mm(sensor, K[solved, 0, 2], K[solved, 1, 2])
    for j, b in enumerate(solved):
        k = n[b]
        out[idx[b]] = DltResult(
            f_mm=float(0.5 * (alpha[b] + beta[b]) * d),
            xp_mm=float(pp_mm[j, 0]),
            yp_mm=float(pp_mm[j, 1]),
            aspect=float(aspect[b]),
            skew=float(skew[b]),
            R_world_to_camera=R_world[b],
            center_m=center[b],
            P=P[b],
            K_px=K[b],
            residuals_px=resid[b, :k],
            inliers=np.ones(k, bool),
            rms_px=float(rms[b]),
        )
    return out


# ---------------------------------------------------------------------------------------
# flat fields
# ---------------------------------------------------------------------------------------
def zhang_focal(
    views, sensor: Sensor, *, where: str = "", tol_rel: float = COPLANAR_TOL_REL
) -> float:
    """Principal distance from homographies of a plane seen in several images (Zhang's method).

    With the principal point at the sensor centre, square pixels and no skew, pixel
    coordinates relative to the centre and divided by a scale ``s`` (half the larger sensor
    side [px]) have the intrinsic matrix ``K = diag(a, a, 1)`` with ``a = f / (d s)``. For
    a homography ``H = [h1 h2 h3]`` from the plane's own metric 2-D frame to those image
    coordinates, ``h1 ~ K r1``, ``h2 ~ K r2`` with ``r1 . r2 = 0`` and ``|r1| = |r2|``; with
    ``w = 1/a^2`` (the image of the absolute conic, ``diag(w, w, 1)``) that is two linear
    equations per view:

        w (h11 h21 + h12 h22) = -h13 h23
        w (h11^2 + h12^2 - h21^2 - h22^2) = h23^2 - h13^2

    (``hji`` the i-th entry of column j), solved for ``w`` by least squares over all views.
    Reference: Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI
    22(11), 2000, section 3.1, here with three of the five intrinsics fixed.

    Parameters
    ----------
    views : sequence of (X_plane (n, 3), uv_px (n, 2))
        Coplanar points [m] (any plane in 3-D; each view is transformed to the plane's own
        2-D frame) and their pixels, n >= 4 per view, at least 2 views (3+ recommended),
        preferably with distortion already removed.
    sensor : Sensor
    where : str
        Named in error messages (e.g. the session).

    Returns
    -------
    float
        ``f_mm`` [mm].

    Raises
    ------
    GeometryError
        Fewer than 2 views, a view with < 4, collinear or non-coplanar points, or views that
        do not determine the focal length (all fronto-parallel, or so degenerate or noisy
        that no positive ``w`` fits).
    """
    views = list(views)
    if len(views) < 2:
        raise GeometryError(
            at(where, f"zhang_focal needs at least 2 views of the plane, got {len(views)}")
        )
    centre = np.array([(sensor.width_px - 1) / 2.0, (sensor.height_px - 1) / 2.0])
    s = max(sensor.width_px, sensor.height_px) / 2.0
    A, b, persp = [], [], []
    for i, (Xv, uvv) in enumerate(views):
        label = f"zhang_focal view {i}"
        X, uv = check_points(Xv, uvv, where, label)
        if len(X) < 4 or is_collinear(X, tol_rel) or not is_coplanar(X, tol_rel):
            raise GeometryError(at(where, f"{label}: needs >= 4 coplanar, non-collinear points"))
        origin, B = plane_frame(X)
        p2 = np.ascontiguousarray(((X - origin) @ B)[:, :2])
        H, _ = cv2.findHomography(p2, np.ascontiguousarray((uv - centre) / s), 0)
        if H is None or not np.all(np.isfinite(H)):
            raise GeometryError(at(where, f"{label}: no homography could be estimated"))
        H = H / np.linalg.norm(H[:, :2])
        h1, h2 = H[:, 0], H[:, 1]
        persp.append(np.hypot(h1[2], h2[2]))
        A += [h1[0] * h2[0] + h1[1] * h2[1], h1[0] ** 2 + h1[1] ** 2 - h2[0] ** 2 - h2[1] ** 2]
        b += [-h1[2] * h2[2], h2[2] ** 2 - h1[2] ** 2]
    A, b = np.asarray(A), np.asarray(b)
    # the focal length enters only through the perspective terms h13, h23 (|H[:, :2]| = 1 here;
    # about the tilt of the plane [rad] divided by sqrt(2 + 2 a^2))
    if max(persp) < 1e-4:
        raise GeometryError(
            at(
                where,
                "zhang_focal: the views are fronto-parallel; tilt the plane relative to the camera",
            )
        )
    w = float(A @ b / (A @ A))
    if not w > 0:
        raise GeometryError(
            at(
                where,
                f"zhang_focal: no real focal length fits these views "
                f"(w = {w:.3g}); the views are nearly degenerate",
            )
        )
    return float(s / np.sqrt(w) * sensor.pixel_mm)
