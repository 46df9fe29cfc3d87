"""Point sets and their checks, shared by the DLT, resection and identification.

Coplanarity and collinearity of control points, the best-fit plane frame, and the check
of matched world and image points at the public boundary of the initialisers.
"""

from __future__ import annotations

import numpy as np

from fieldcal.errors import InputError

__all__ = ["COPLANAR_TOL_REL", "at", "check_points", "singular_values_centred", "is_coplanar", "is_collinear",
           "plane_frame"]

COPLANAR_TOL_REL = 1e-3
"""Relative thickness below which a point set counts as coplanar (:func:`is_coplanar`)."""


def at(where: str, message: str) -> str:
    return f"{where}: {message}" if where else message


def singular_values_centred(X):
    """Singular values (3,) of the centred points (n, 3), padded with zeros, largest first."""
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(f"points must have shape (n, 3), got {X.shape}")
    if len(X) < 2:
        return np.zeros(3)
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return np.concatenate([s, np.zeros(3 - len(s))])


def is_coplanar(X, tol_rel: float = COPLANAR_TOL_REL) -> bool:
    """Whether 3-D points lie (nearly) in one plane.

    Parameters
    ----------
    X : (n, 3) array_like
        Points [any length unit].
    tol_rel : float
        The points are coplanar when the smallest singular value of the centred points is at
        most ``tol_rel`` times the largest (the RMS distance from the best-fit plane relative
        to the RMS extent along the main axis). The default 1e-3 is 2 cm of relief on a
        20 m wide field; a DLT on such points is useless anyway.

    Returns
    -------
    bool
        True also for fewer than 4 points and for collinear points.
    """
    s = singular_values_centred(X)
    return bool(len(np.asarray(X)) < 4 or s[2] <= tol_rel * s[0])


def is_collinear(X, tol_rel: float = COPLANAR_TOL_REL) -> bool:
    """Whether 3-D points (n, 3) lie (nearly) on a line: 2nd singular value <= ``tol_rel`` x 1st."""
    s = singular_values_centred(X)
    return bool(len(np.asarray(X)) < 3 or s[1] <= tol_rel * s[0])


def plane_frame(X):
    """The best-fit plane of points (n, 3) as an origin and a right-handed orthonormal basis.

    Returns
    -------
    origin : (3,) ndarray
        The centroid of the points.
    B : (3, 3) ndarray
        Columns ``e1, e2, n``: two in-plane axes (the main directions of the points) and the
        normal, ``det B = +1``. Plane coordinates are ``(X - origin) @ B`` (third ~ 0).
    """
    X = np.asarray(X, dtype=float)
    origin = X.mean(axis=0)
    _, _, Vt = np.linalg.svd(X - origin, full_matrices=len(X) < 3)
    B = Vt.T.copy()
    if np.linalg.det(B) < 0:
        B[:, 2] = -B[:, 2]
    return origin, B


def check_points(X_world_m, uv_px, where: str, what: str):
    X = np.asarray(X_world_m, dtype=float)
    uv = np.asarray(uv_px, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3:
        raise InputError(
            f"{what}: world points must have shape (n, 3), got {X.shape}", where or None
        )
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise InputError(
            f"{what}: image points must have shape (n, 2), got {uv.shape}", where or None
        )
    if len(X) != len(uv):
        raise InputError(f"{what}: {len(X)} world points but {len(uv)} image points", where or None)
    bad = ~(np.isfinite(X).all(axis=1) & np.isfinite(uv).all(axis=1))
    if bad.any():
        rows = np.flatnonzero(bad)
        raise InputError(
            f"{what}: {bad.sum()} point(s) with NaN or infinite coordinates "
            f"(rows {rows[:5].tolist()}{'...' if len(rows) > 5 else ''})",
            where or None,
        )
    return X, uv


