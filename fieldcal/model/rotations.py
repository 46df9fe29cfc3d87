"""Rotations: omega-phi-kappa angles, rotation vectors, and the SO(3) Jacobian.

Conventions (docs/conventions.md section 1): the exterior orientation of an image is the camera
centre ``C`` and the matrix ``R_world_to_camera`` that maps world vectors into the camera
frame (x right, y up, z backwards; the camera looks along -z). Angles are
``(omega, phi, kappa)`` with ``R_camera_to_world = Rz(kappa) @ Ry(phi) @ Rx(omega)``, so
``R_world_to_camera`` is its transpose. Angles here are in radians unless a name ends
in ``_deg``. All functions broadcast over leading dimensions.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "R_camera_to_world_from_opk",
    "R_world_to_camera_from_opk",
    "opk_from_R_world_to_camera",
    "R_from_rotvec",
    "rotvec_from_R",
    "skew",
    "left_jacobian_so3",
]


def _rx(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def _ry(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def R_camera_to_world_from_opk(omega, phi, kappa):
    """``Rz(kappa) @ Ry(phi) @ Rx(omega)`` [rad] -> (..., 3, 3) camera-to-world rotation."""
    omega, phi, kappa = np.broadcast_arrays(*(np.asarray(a, dtype=float) for a in (omega, phi, kappa)))
    return _rz(kappa) @ _ry(phi) @ _rx(omega)


def R_world_to_camera_from_opk(omega, phi, kappa):
    """The transpose of :func:`R_camera_to_world_from_opk`: maps world vectors into the camera frame."""
    return np.swapaxes(R_camera_to_world_from_opk(omega, phi, kappa), -1, -2)


def opk_from_R_world_to_camera(R_world_to_camera):
    """(omega, phi, kappa) [rad] of a world-to-camera rotation, phi in [-pi/2, pi/2].

    With ``M = R_camera_to_world = Rz(k) Ry(p) Rx(o)``: ``M[2,0] = -sin p``,
    ``M[2,1] = cos p sin o``, ``M[2,2] = cos p cos o``, ``M[1,0] = sin k cos p``,
    ``M[0,0] = cos k cos p``. At phi = +-pi/2 (gimbal lock) kappa is set to 0.
    """
    M = np.swapaxes(np.asarray(R_world_to_camera, dtype=float), -1, -2)
    phi = np.arcsin(np.clip(-M[..., 2, 0], -1.0, 1.0))
    cos_phi = np.cos(phi)
    locked = cos_phi < 1e-9
    omega = np.where(locked, np.arctan2(-M[..., 1, 2], M[..., 1, 1]), np.arctan2(M[..., 2, 1], M[..., 2, 2]))
    kappa = np.where(locked, 0.0, np.arctan2(M[..., 1, 0], M[..., 0, 0]))
    return omega, phi, kappa


def R_from_rotvec(rotvec):
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) [rad] (Rodrigues)."""
    rotvec = np.asarray(rotvec, dtype=float)
    flat = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix()
    return flat.reshape(rotvec.shape[:-1] + (3, 3))


def rotvec_from_R(R):
    """Rotation vectors (..., 3) [rad] of rotation matrices (..., 3, 3)."""
    R = np.asarray(R, dtype=float)
    flat = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec()
    return flat.reshape(R.shape[:-2] + (3,))


def skew(v):
    """The cross-product matrix ``[v]x`` (..., 3, 3) with ``skew(v) @ w == cross(v, w)``."""
    v = np.asarray(v, dtype=float)
    z = np.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2
    )


def left_jacobian_so3(rotvec):
    """Left Jacobian ``J_l(w)`` of SO(3), shape (..., 3, 3).

    For ``R(w) = exp([w]x)`` and any vector ``a``: ``d(R(w) a)/dw = -[R(w) a]x J_l(w)``, with
    ``J_l(w) = I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2`` and ``t = |w|``
    (series expansion below t = 1e-4).
    """
    w = np.asarray(rotvec, dtype=float)
    t2 = np.sum(w * w, axis=-1)
    t = np.sqrt(t2)
    small = t < 1e-4
    ts = np.where(small, 1.0, t)
    c1 = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    c2 = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    K = skew(w)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)
