"""Perspective eccentricity of circular targets.

Under a central projection the image of a disc is an ellipse, but the centre of that
ellipse is not the image of the disc's centre unless the disc is parallel to the image
plane. Target detection (:mod:`fieldcal.measure.targets`) measures the ellipse's centre; once the
pose of the image is known, :func:`correction_px` gives the offset

    ``e = (centre of the imaged ellipse) - (image of the disc's centre)``  [px]

so that the image of the centre is ``uv_measured - e`` (:func:`remove_eccentricity`).

Derivation
----------
In the camera frame (docs/conventions.md section 1: x right, y up, looking along -z) let the disc
have centre ``P = R (X0 - C)``, unit normal ``n = R n_world`` and in-plane orthonormal
axes ``e1, e2``. A point ``a e1 + b e2`` of the plane maps to the ideal image point
(``q = -f (X, Y) / Z``, relative to the principal point, [mm]) with the homography

    ``q_h ~ H (a, b, 1)^T``,  ``H = diag(-f, -f, 1) [e1 | e2 | P]``.

The rim ``a^2 + b^2 = r^2`` is the conic ``Q0 = diag(1, 1, -r^2)``; its image is
``Q = H^-T Q0 H^-1``. The centre of a conic is the pole of the line at infinity
``l = (0, 0, 1)``: ``c_h ~ Q^-1 l = H Q0^-1 H^T l``, so no inverse of ``H`` is needed:

    ``c_h = H diag(1, 1, -1/r^2) h3``,  ``h3 = (H_31, H_32, H_33)`` (the third row of H),

while the image of the centre is ``H (0, 0, 1)^T = diag(-f, -f, 1) P``. Both ideal points
are mapped to measured pixels with the camera's distortion (:meth:`Camera.distort`) and
the sensor's mm -> pixel mapping. Distortion also bends the ellipse a little: its
curvature across the target moves the figure's area centroid by ~5e-4 px for the paper's
28 px discs (more for larger images of targets), so :func:`correction_px` maps the rim
itself through the distortion and takes the area centroid. For a small target at
distance ``Z`` on the optical axis, ``|e| = f r^2 sin(2 theta) / (2 Z^2)`` [mm] to first
order, ``theta`` the angle between the view ray and the disc's normal: it grows with the
square of the target's angular size (paper: ~0.002 px, wide-angle: up to ~0.016 px).
"""

from __future__ import annotations

import numpy as np

from fieldcal.errors import InputError
from fieldcal.model.camera import Camera

__all__ = ["correction_px", "remove_eccentricity", "ellipse_centre_ideal_mm", "rim_px"]


def _plane_axes(normals):
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    ref = np.where((np.abs(n[:, 0]) > 0.9)[:, None], [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    e1 = ref - np.sum(ref * n, axis=1, keepdims=True) * n
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    return e1, np.cross(n, e1)


def _check(R_world_to_camera, center_m, centers_m, normals, radius_m):
    R = np.asarray(R_world_to_camera, float)
    C = np.asarray(center_m, float).reshape(-1)
    X = np.asarray(centers_m, float)
    N = np.asarray(normals, float)
    if R.shape != (3, 3):
        raise InputError(f"R_world_to_camera must be 3 x 3, got shape {R.shape}")
    if C.shape != (3,):
        raise InputError(f"center_m must have 3 coordinates, got shape {np.shape(center_m)}")
    X = X.reshape(-1, 3) if X.size % 3 == 0 else X
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"centers_m must be (n, 3), got shape {np.shape(centers_m)}")
    N = np.broadcast_to(N, X.shape) if N.size == 3 else N
    if N.shape != X.shape:
        raise InputError(f"normals must be (n, 3) like centers_m {X.shape}, got {np.shape(normals)}")
    if not np.all(np.linalg.norm(N, axis=1) > 0):
        raise InputError("normals: every normal must be a non-zero vector")
    r = np.broadcast_to(np.asarray(radius_m, float), (len(X),))
    if not np.all(np.isfinite(r) & (r > 0)):
        raise InputError(f"radius_m must be positive, got {radius_m!r}")
    return R, C, X, N, r


def ellipse_centre_ideal_mm(f_mm, R_world_to_camera, center_m, centers_m, normals, radius_m):
    """Ideal image points [mm] of the ellipse centres and of the disc centres, each (n, 2).

    Pinhole only (no distortion), relative to the principal point; NaN for a disc whose
    centre is not in front of the camera.
    """
    R, C, X, N, r = _check(R_world_to_camera, center_m, centers_m, normals, radius_m)
    P = (X - C) @ R.T
    n = N @ R.T
    e1, e2 = _plane_axes(n)
    K = np.array([-float(f_mm), -float(f_mm), 1.0])
    H = K[None, :, None] * np.stack([e1, e2, P], axis=2)          # (n, 3, 3), columns e1 e2 P
    h3 = H[:, 2, :] * np.stack([np.ones_like(r), np.ones_like(r), -1.0 / r**2], axis=1)
    c_h = np.einsum("nij,nj->ni", H, h3)
    p_h = K * P
    front = P[:, 2] < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        ell = np.where(front[:, None], c_h[:, :2] / c_h[:, 2:3], np.nan)
        cen = np.where(front[:, None], p_h[:, :2] / p_h[:, 2:3], np.nan)
    return ell, cen


def _polygon_centroid(uv):
    """Area centroids (n, 2) of closed polygons ``uv`` (n, K, 2)."""
    x, y = uv[..., 0], uv[..., 1]
    x1, y1 = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    cross = x * y1 - x1 * y
    area = 0.5 * cross.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cx = ((x + x1) * cross).sum(axis=1) / (6 * area)
        cy = ((y + y1) * cross).sum(axis=1) / (6 * area)
    return np.stack([cx, cy], axis=1)


def correction_px(camera: Camera, R_world_to_camera, center_m, centers_m, normals,
                  radius_m, *, rim_points: int = 256) -> np.ndarray:
    """Perspective eccentricity of circular targets in one image [px].

    The centre of the imaged figure is the area centroid of the disc's rim, ``rim_points``
    points mapped exactly (homography, then the camera's distortion), which is the centre of
    the ellipse of :func:`ellipse_centre_ideal_mm` carried through the distortion, plus the
    distortion's curvature across the target (this term grows with the target's size in
    the image: ~5e-4 px for the paper's 28 px discs, ~2e-3 px for 110 px ones).

    Parameters
    ----------
    camera : Camera
        The camera (``f_mm`` and the distortion map ideal points to pixels).
    R_world_to_camera : (3, 3) array
    center_m : (3,) array
        The image's exterior orientation (docs/conventions.md section 1) [m].
    centers_m : (n, 3) array
        Centres of the discs, world [m].
    normals : (n, 3) or (3,) array
        Normals of the discs' planes (either sign).
    radius_m : float or (n,) array
        Radius of the discs [m].
    rim_points : int
        Points on the rim (the polygon's centroid converges as ``1 / rim_points^2``).

    Returns
    -------
    (n, 2) ndarray
        ``(u, v)`` of the centre of the imaged disc minus ``(u, v)`` of the image of the
        disc's centre [px]; NaN for a disc not wholly in front of the camera.
    """
    uv = _rim_and_centre_px(camera, R_world_to_camera, center_m, centers_m, normals, radius_m, rim_points)
    return _polygon_centroid(uv[:, :-1]) - uv[:, -1]


def rim_px(camera: Camera, R_world_to_camera, center_m, centers_m, normals, radius_m, *,
           rim_points: int = 32) -> np.ndarray:
    """The discs' rims in one image: (n, rim_points, 2) measured pixels (homography, then the
    camera's distortion); NaN for a disc not wholly in front of the camera."""
    return _rim_and_centre_px(camera, R_world_to_camera, center_m, centers_m, normals, radius_m, rim_points)[:, :-1]


def _rim_and_centre_px(camera, R_world_to_camera, center_m, centers_m, normals, radius_m, rim_points):
    R, C, X, N, r = _check(R_world_to_camera, center_m, centers_m, normals, radius_m)
    if not (isinstance(rim_points, (int, np.integer)) and rim_points >= 8):
        raise InputError(f"rim_points must be an integer >= 8, got {rim_points!r}")
    P = (X - C) @ R.T
    e1, e2 = _plane_axes(N @ R.T)
    t = np.linspace(0.0, 2 * np.pi, int(rim_points), endpoint=False)
    rim = (P[:, None, :] + r[:, None, None] * (np.cos(t)[None, :, None] * e1[:, None, :]
                                                + np.sin(t)[None, :, None] * e2[:, None, :]))
    pts = np.concatenate([rim, P[:, None, :]], axis=1)                  # (n, K + 1, 3)
    z = pts[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -camera.f_mm * pts[..., :2] / np.where(z < 0, z, np.nan)[..., None]
    return camera.sensor.mm_to_pixel(camera.distort(q, check=False))


def remove_eccentricity(uv_px, camera: Camera, R_world_to_camera, center_m, centers_m, normals,
                        radius_m) -> np.ndarray:
    """Measured ellipse centres (n, 2) [px] -> images of the discs' centres (n, 2) [px]."""
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    return uv - correction_px(camera, R_world_to_camera, center_m, centers_m, normals, radius_m)
