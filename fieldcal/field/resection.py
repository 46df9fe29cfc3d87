"""Single-image resection: the pose of one image from known targets and a known camera.

Method
------
With the interior orientation known (a full :class:`fieldcal.model.camera.Camera`, distortion
included), the measured pixels are corrected to ideal points ``q`` [mm]
(:func:`fieldcal.model.camera.correct`) and mapped to the distortion-free pixels of OpenCV's
intrinsic matrix ``K = [[f/d, 0, cx], [0, f/d, cy], [0, 0, 1]]`` with
``cx = (W-1)/2 + xp/d``, ``cy = (H-1)/2 - yp/d`` (:func:`fieldcal.model.opencv_frames.ideal_pixels`).
On those, OpenCV solves the perspective-n-point problem in its own camera frame
(x right, y down, z forward):

- coplanar targets: IPPE (infinitesimal plane-based pose; both candidate poses are
  scored, the better is kept), with the points in their plane's own frame;
- targets in 3-D: SQPnP (globally optimal for n >= 3);
- ``ransac=True``: ``cv2.solvePnPRansac`` with AP3P minimal sets finds the consensus
  set (EPnP minimal sets, OpenCV's default, fail on planar targets), and the pose is
  re-estimated from the inliers by the solver above;

followed by Levenberg-Marquardt refinement (``cv2.solvePnPRefineLM``). The pose is
converted back to fieldcal's frame (``R_world_to_camera = diag(1, -1, -1) R_cv``,
``C = -R_cv^T t``; docs/conventions.md section 1). Residuals and their RMS are computed with
fieldcal's own :func:`fieldcal.model.camera.project` (distortion included), and with
``ransac=True`` the inliers are re-selected from those residuals and the pose refitted
until the set is stable, so a wrong point near the threshold in ideal pixels is judged
in measured pixels.

World coordinates are shifted to the points' centroid before OpenCV sees them, so
survey coordinates of hundreds of kilometres lose no precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fieldcal.errors import GeometryError
from fieldcal.field.geometry import COPLANAR_TOL_REL, at, check_points, is_collinear, is_coplanar, plane_frame
from fieldcal.model.camera import Camera
from fieldcal.model.opencv_frames import FLIP_YZ, ideal_pixels, opencv_camera_matrix, pose_to_opencv

__all__ = ["Resection", "resect", "planar_pose"]


@dataclass(frozen=True)
class Resection:
    """The pose of one image.

    Attributes
    ----------
    R_world_to_camera : (3, 3) ndarray
        World -> camera rotation (fieldcal's camera frame: x right, y up, z backwards).
    center_m : (3,) ndarray
        Camera centre [m].
    rms_px : float
        ``sqrt(mean(du^2 + dv^2))`` over the inliers, residuals from
        :func:`fieldcal.model.camera.project` [px].
    inliers : (n,) bool ndarray
        Points used for the pose (all of them without RANSAC).
    residuals_px : (n, 2) ndarray
        Measured minus projected pixel for every point (NaN behind the camera).
    """

    R_world_to_camera: np.ndarray
    center_m: np.ndarray
    rms_px: float
    inliers: np.ndarray
    residuals_px: np.ndarray


def _local_frame(X, planar: bool):
    """Origin and rotation B (3, 3) so that OpenCV sees ``(X - origin) @ B`` (z = 0 when planar)."""
    if planar:
        return plane_frame(X)
    return X.mean(axis=0), np.eye(3)


def _cv(a, k):
    return np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 1, k)


def _solve(Xl, uvi, K, planar: bool):
    """Global PnP on local coordinates, returning OpenCV (rvec, tvec) of the best solution."""
    if planar:
        n_sol, rvecs, tvecs, errs = cv2.solvePnPGeneric(
            _cv(Xl, 3), _cv(uvi, 2), K, None, flags=cv2.SOLVEPNP_IPPE
        )
        if not n_sol:
            raise GeometryError("IPPE found no pose")
        k = int(np.argmin(np.asarray(errs).ravel()))
        return rvecs[k], tvecs[k]
    ok, rvec, tvec = cv2.solvePnP(_cv(Xl, 3), _cv(uvi, 2), K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise GeometryError("SQPnP found no pose")
    return rvec, tvec


_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
"""OpenCV's default (20 iterations, FLT_EPSILON) stops short of the optimum by ~1e-6 rad."""


def _refine(Xl, uvi, K, rvec, tvec, polish_steps: int = 5):
    """``cv2.solvePnPRefineLM``, then Gauss-Newton steps with ``cv2.projectPoints``' Jacobian.

    OpenCV's LM stops up to ~1e-7 rad short of the least-squares optimum when started far
    from it; a few Gauss-Newton steps from there converge quadratically to round-off.
    """
    obj, img = _cv(Xl, 3), uvi.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(
        obj,
        _cv(uvi, 2),
        K,
        None,
        np.array(rvec, np.float64).reshape(3, 1),
        np.array(tvec, np.float64).reshape(3, 1),
        _LM_CRITERIA,
    )
    x = best = np.concatenate([rvec.ravel(), tvec.ravel()])
    cost = np.inf
    for _ in range(polish_steps):
        proj, jac = cv2.projectPoints(obj, x[:3], x[3:], K, None)
        r = proj.reshape(-1) - img
        if not r @ r < cost:  # no further decrease: at the optimum to round-off
            break
        cost, best = r @ r, x
        x = x + np.linalg.lstsq(jac[:, :6], -r, rcond=None)[0]
    return best[:3].reshape(3, 1), best[3:].reshape(3, 1)


def _to_fieldcal(rvec, tvec, origin, B):
    """OpenCV pose of local coordinates ``(X - origin) @ B`` -> (R_world_to_camera, C)."""
    R_l, _ = cv2.Rodrigues(np.asarray(rvec, np.float64).reshape(3, 1))
    R_cv = R_l @ B.T  # x_cv = R_l B^T (X - origin) + t
    C = origin - R_cv.T @ np.asarray(tvec, np.float64).ravel()
    return FLIP_YZ @ R_cv, C


def _from_fieldcal(R_world_to_camera, C, origin, B):
    """fieldcal pose -> OpenCV (rvec, tvec) of the local coordinates."""
    rvec, _ = pose_to_opencv(np.asarray(R_world_to_camera, float) @ B, np.zeros(3))
    R_cv_l, _ = cv2.Rodrigues(rvec)
    t = -R_cv_l @ (B.T @ (np.asarray(C, float) - origin))
    return rvec.reshape(3, 1), t.reshape(3, 1)


def _residuals(X, uv, camera, R, C):
    res = uv - camera.project(X, R, C)
    e = np.linalg.norm(res, axis=1)
    return res, np.where(np.isfinite(e), e, np.inf)


def _candidates(X, uv, Xl, uvi, K, camera, origin, B, planar, ransac, init, need, threshold_px,
                max_iterations, confidence, tol_rel):
    """Candidate poses (OpenCV rvec, tvec of the local coordinates), each with the points it
    is to be refined on: the global (or RANSAC) solution, and the given approximate pose."""
    n = len(X)
    candidates = []
    if ransac:
        # minimal sets by AP3P (EPnP minimal sets fail on planar targets in OpenCV 5)
        ok, rvec, tvec, idx = cv2.solvePnPRansac(
            _cv(Xl, 3), _cv(uvi, 2), K, None, iterationsCount=int(max_iterations),
            reprojectionError=float(threshold_px), confidence=float(confidence), flags=cv2.SOLVEPNP_AP3P,
        )
        if ok and idx is not None and len(idx) >= need:
            consensus = np.zeros(n, bool)
            consensus[np.asarray(idx).ravel()] = True
            candidates.append((rvec, tvec, consensus))
            if not is_collinear(X[consensus], tol_rel):  # the global solver on the consensus set
                candidates.append((*_solve(Xl[consensus], uvi[consensus], K, planar), consensus))
    else:
        candidates.append((*_solve(Xl, uvi, K, planar), np.ones(n, bool)))
    if init is not None:
        rvec, tvec = _from_fieldcal(init[0], init[1], origin, B)
        near = np.ones(n, bool)
        if ransac:  # the points the approximate pose already explains
            near = _residuals(X, uv, camera, *_to_fieldcal(rvec, tvec, origin, B))[1] <= threshold_px
        if near.sum() >= need:
            candidates.append((rvec, tvec, near))
    return candidates


def _best_candidate(candidates, X, uv, Xl, uvi, K, camera, origin, B, refine, ransac, threshold_px):
    """Each candidate refined on its points and scored: the truncated quadratic cost (MSAC) with
    RANSAC, the median residual otherwise; the best as (rvec, tvec, R, C, residuals, |residuals|, used)."""
    best = None
    for rvec, tvec, use in candidates:
        if refine:
            rvec, tvec = _refine(Xl[use], uvi[use], K, rvec, tvec)
        R, C = _to_fieldcal(rvec, tvec, origin, B)
        res, e = _residuals(X, uv, camera, R, C)
        score = np.sum(np.minimum(e, threshold_px) ** 2) if ransac else np.median(e)
        if best is None or score < best[0]:
            best = (score, rvec, tvec, R, C, res, e, use)
    return best[1:]


def _reselect(X, uv, Xl, uvi, K, camera, origin, B, rvec, tvec, e, inliers, need, threshold_px, tol_rel,
              where):
    """RANSAC's inliers re-selected in measured pixels and the pose refitted until stable."""
    n = len(X)
    R, C = _to_fieldcal(rvec, tvec, origin, B)
    res = _residuals(X, uv, camera, R, C)[0]
    for _ in range(10):
        new = e <= threshold_px
        if new.sum() < need:
            raise GeometryError(
                at(where, f"resection: only {new.sum()} of {n} points within {threshold_px} px of a common pose")
            )
        if is_collinear(X[new], tol_rel):
            raise GeometryError(at(where, "resection: the inliers are collinear"))
        if np.array_equal(new, inliers):
            break
        inliers = new
        rvec, tvec = _refine(Xl[inliers], uvi[inliers], K, rvec, tvec)
        R, C = _to_fieldcal(rvec, tvec, origin, B)
        res, e = _residuals(X, uv, camera, R, C)
    return R, C, res, e, inliers


def resect(
    X_world_m,
    uv_px,
    camera: Camera,
    *,
    ransac: bool = False,
    where: str = "",
    init=None,
    threshold_px: float = 4.0,
    max_iterations: int = 2000,
    confidence: float = 0.9999,
    min_inliers: int = 6,
    refine: bool = True,
    tol_rel: float = COPLANAR_TOL_REL,
) -> Resection:
    """Pose of one image from n >= 4 known points and a known camera (planar or 3-D points).

    Parameters
    ----------
    X_world_m : (n, 3) array_like
        Control points [m].
    uv_px : (n, 2) array_like
        Their measured pixels [px] (docs/conventions.md section 1), distortion not removed.
    camera : Camera
        The interior orientation, distortion included.
    ransac : bool
        Find the pose robustly and flag wrong points (needs n >= ``min_inliers``). The
        threshold is ``threshold_px`` on the reprojection error [px]; ``max_iterations``
        and ``confidence`` go to ``cv2.solvePnPRansac``; a pose supported by fewer than
        ``min_inliers`` points (default 6: three beyond a minimal set) is refused.
    where : str
        The image's name, quoted in error messages.
    init : (R_world_to_camera, center_m), optional
        An approximate pose. It is refined as a further candidate next to OpenCV's global
        (or RANSAC) solution, with RANSAC on the points within ``threshold_px`` of it; the
        candidate with the smaller median residual (RANSAC: truncated squared residual)
        wins, so a wrong ``init`` does no harm.
    refine : bool
        Levenberg-Marquardt refinement of the pose on the (inlier) points (default).
    tol_rel : float
        Coplanarity tolerance (:func:`fieldcal.field.geometry.is_coplanar`): IPPE for coplanar points.

    Returns
    -------
    Resection

    Raises
    ------
    InputError
        Wrong shapes, NaN or infinite coordinates.
    GeometryError
        Too few points, collinear points, no pose found, fewer than ``min_inliers``
        inliers with RANSAC, or points behind the camera.
    """
    X, uv = check_points(X_world_m, uv_px, where, "resection")
    n = len(X)
    need = max(4, int(min_inliers)) if ransac else 4
    if n < need:
        raise GeometryError(at(where, f"resection{' with RANSAC' if ransac else ''} needs at least {need} points, "
                                      f"got {n}"))
    if is_collinear(X, tol_rel):
        raise GeometryError(at(where, f"resection: the {n} world points are collinear"))
    planar = is_coplanar(X, tol_rel)
    origin, B = _local_frame(X, planar)
    Xl = (X - origin) @ B
    if planar:
        Xl[:, 2] = 0.0
    K = opencv_camera_matrix(camera)
    uvi = ideal_pixels(uv, camera)

    try:
        candidates = _candidates(X, uv, Xl, uvi, K, camera, origin, B, planar, ransac, init, need,
                                 threshold_px, max_iterations, confidence, tol_rel)
        if not candidates:
            raise GeometryError(at(where, f"resection: RANSAC found no pose consistent with {need} or more of "
                                          f"the {n} points (threshold {threshold_px} px)"))
        rvec, tvec, R, C, res, e, inliers = _best_candidate(candidates, X, uv, Xl, uvi, K, camera, origin, B,
                                                            refine or ransac, ransac, threshold_px)
        if ransac:  # re-select the inliers in measured pixels and refit until stable
            R, C, res, e, inliers = _reselect(X, uv, Xl, uvi, K, camera, origin, B, rvec, tvec, e, inliers,
                                              need, threshold_px, tol_rel, where)
    except cv2.error as exc:
        raise GeometryError(
            at(where, f"resection: OpenCV failed: {str(exc).strip().splitlines()[-1]}")
        ) from exc

    if not np.all(np.isfinite(e[inliers])):
        raise GeometryError(
            at(
                where,
                "resection: points come out behind the camera; "
                "the correspondences or the camera are wrong",
            )
        )
    rms = float(np.sqrt(np.mean(e[inliers] ** 2)))
    return Resection(R_world_to_camera=R, center_m=C, rms_px=rms, inliers=inliers, residuals_px=res)


def planar_pose(
    X_world_m, uv_px, camera: Camera, *, where: str = "", tol_rel: float = COPLANAR_TOL_REL
):
    """Pose of one image of a flat field with known interior orientation (the DLT's stand-in).

    The measured pixels are corrected for the distortion of ``camera``
    (:func:`fieldcal.model.camera.correct`), the points are expressed in their plane's own frame,
    and OpenCV's IPPE (infinitesimal plane-based pose) gives the two candidate poses, of
    which the one with the smaller reprojection error is refined by Levenberg-Marquardt
    (this is :func:`fieldcal.field.resection.resect` restricted to coplanar points).

    Parameters
    ----------
    X_world_m : (n, 3) array_like
        Coplanar control points [m] (any plane, not only Z = 0), n >= 4, not collinear.
    uv_px : (n, 2) array_like
        Measured pixels [px].
    camera : Camera
        Interior orientation, e.g. the nominal focal length with the principal point at
        the sensor centre and no distortion.
    where : str
        The image's name for error messages.

    Returns
    -------
    R_world_to_camera : (3, 3) ndarray
    center_m : (3,) ndarray
    rms_px : float
        Reprojection RMS through :func:`fieldcal.model.camera.project` [px].
    """
    X, uv = check_points(X_world_m, uv_px, where, "planar pose")
    if len(X) < 4:
        raise GeometryError(at(where, f"planar pose needs at least 4 points, got {len(X)}"))
    if is_collinear(X, tol_rel):
        raise GeometryError(at(where, f"planar pose: the {len(X)} world points are collinear"))
    if not is_coplanar(X, tol_rel):
        raise GeometryError(
            at(
                where,
                "planar pose: the world points are not coplanar; use dlt() or resection.resect()",
            )
        )
    res = resect(X, uv, camera, where=where, tol_rel=tol_rel)
    return res.R_world_to_camera, res.center_m, res.rms_px
