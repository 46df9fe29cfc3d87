"""Spatial intersection: target coordinates from the rays of oriented images.

The initial coordinates of unsurveyed targets (CONTRACT section 3: empty ``X, Y, Z``, or
ids only the image points name). Each measured pixel of an oriented image is a ray from the
camera centre ``C_i`` along the unit direction ``d_k = R_i^T unproject(uv_k)``
(:func:`fieldcal.model.camera.unproject`, docs/conventions.md section 2). The point nearest
all rays of a target in the least-squares sense solves

    sum_k (I - d_k d_k^T) X = sum_k (I - d_k d_k^T) C_k

(a 3 x 3 system per target, all targets at once). A target is placed when its rays span an
angle of at least ``min_angle_deg``, the point lies in front of every camera, and each ray's
reprojection lies within ``threshold_px`` (rays beyond it are dropped once, and the rest
intersected again: a blunder must not drag the start).
"""

from __future__ import annotations

import numpy as np

from fieldcal.model.camera import Camera
from fieldcal.session.data import FieldData

__all__ = ["intersect_targets"]

MIN_RAYS = 2


def _solve(rays, centers, tgt, n_targets):
    """Least-squares intersection per target: (n_targets, 3), NaN where singular or unseen."""
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    A = np.zeros((n_targets, 3, 3))
    b = np.zeros((n_targets, 3))
    np.add.at(A, tgt, P)
    np.add.at(b, tgt, np.einsum("kab,kb->ka", P, centers))
    X = np.full((n_targets, 3), np.nan)
    ok = np.linalg.det(A) > 1e-12
    X[ok] = np.linalg.solve(A[ok], b[ok][:, :, None])[:, :, 0]
    return X


def _max_angle_deg(rays, tgt, n_targets):
    """Widest angle between a target's rays and their mean direction, doubled [deg] (a cheap
    lower bound of the widest angle between two of its rays)."""
    mean = np.zeros((n_targets, 3))
    np.add.at(mean, tgt, rays)
    norm = np.linalg.norm(mean, axis=1, keepdims=True)
    mean = np.divide(mean, norm, out=np.zeros_like(mean), where=norm > 0)
    cos = np.clip(np.einsum("ka,ka->k", rays, mean[tgt]), -1.0, 1.0)
    widest = np.zeros(n_targets)
    np.maximum.at(widest, tgt, np.degrees(np.arccos(cos)))
    return 2.0 * widest


def intersect_targets(data: FieldData, params, R, C, use, *, threshold_px: float = 8.0,
                      min_angle_deg: float = 2.0):
    """Coordinates of targets from the rays of their image points ``use`` (module docstring).

    Parameters
    ----------
    data : FieldData
    params : (13,) ndarray
        The camera (docs/conventions.md section 2).
    R : (n_images, 3, 3) ndarray
        World-to-camera rotations of the oriented images.
    C : (n_images, 3) ndarray
        Their centres [m].
    use : (m,) bool ndarray
        The observations to intersect (of oriented images).
    threshold_px : float
        A ray whose reprojection misses its pixel by more is dropped [px].
    min_angle_deg : float
        Rays of a target must span at least this angle [deg].

    Returns
    -------
    X : (n_targets, 3) ndarray
        Intersected coordinates [m]; NaN where a target could not be placed.
    inlier : (m,) bool ndarray
        The observations that agree with their target's intersection.
    """
    n_t = len(data.targets)
    cam = Camera(data.sensor, np.asarray(params, float))
    k = np.flatnonzero(use)
    img, tgt = data.obs.image[k], data.obs.target[k]
    rays = np.einsum("kba,kb->ka", R[img], cam.unproject(data.obs.uv_px[k]))
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    keep = np.ones(len(k), bool)
    for _ in range(2):                         # intersect, drop the rays that miss, intersect again
        X = _solve(rays[keep], C[img[keep]], tgt[keep], n_t)
        with np.errstate(invalid="ignore"):
            uv = cam.project(X[tgt], R[img], C[img])
        err = np.hypot(*(uv - data.obs.uv_px[k]).T)
        good = err <= threshold_px                 # NaN (behind a camera, not placed) is not good
        if np.array_equal(good & keep, keep):
            break
        keep &= good
    n_rays = np.bincount(tgt[keep], minlength=n_t)
    wide = _max_angle_deg(rays[keep], tgt[keep], n_t) >= min_angle_deg
    placed = (n_rays >= MIN_RAYS) & wide & np.isfinite(X).all(axis=1)
    X[~placed] = np.nan
    inlier = np.zeros(len(data.obs), bool)
    inlier[k] = keep & placed[tgt]
    return X, inlier
