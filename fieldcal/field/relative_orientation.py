"""Relative orientation of an image pair: the start of a network without any survey.

A session whose targets are all unsurveyed (coded targets only, issue 26 goal 3) has no
coordinates to resect an image on. As structure-from-motion does, one pair of images is
oriented relative to each other from the essential matrix (Nister's five-point algorithm
in RANSAC, ``cv2.findEssentialMat``, and ``cv2.recoverPose`` for the one of its four
decompositions that puts the points in front of both cameras), with the nominal camera
(``lens.nominal_focal_mm``, principal point at the sensor centre, no distortion); the
points they share are intersected (:mod:`fieldcal.field.intersection`), and the network
grows by resection and intersection (:func:`fieldcal.field.initial.initial_values`).

Why this and not a DLT on bar-scaled points: a DLT needs six or more points of known
coordinates in one image; a session without a survey has none until a pair is oriented,
while the five-point solution needs only the image points and a rough focal length (its
error moves the start, which the adjustment removes).

The frame is the first image's camera frame (docs/conventions.md section 1: ``x`` right,
``y`` up, looking along ``-z``) with a unit baseline; the datum of the result is then the
free network's (:mod:`fieldcal.field.datum`). OpenCV's camera frame has ``y`` down and
looks along ``+z``: ``D = diag(1, -1, -1)`` maps one to the other, so a relative pose
``X2_cv = R_cv X1_cv + t_cv`` is ``R2 = D R_cv D``, ``C2 = -R2^T D t_cv`` here.
"""

from __future__ import annotations

import cv2
import numpy as np

from fieldcal.errors import GeometryError
from fieldcal.model.camera import Camera
from fieldcal.session.data import FieldData

__all__ = ["orient_pair", "MIN_PAIR_POINTS"]

MIN_PAIR_POINTS = 12
"""Common points a pair needs (five for the solution, the rest to verify it)."""
CANDIDATE_PAIRS = 12
"""The pairs sharing the most points that are tried."""
MIN_ANGLE_DEG = 3.0
"""A pair's median intersection angle must be at least this [deg] (a baseline, not a roll)."""

_D = np.diag([1.0, -1.0, -1.0])


def _normalised(cam: Camera, uv):
    """Ideal image coordinates ``(x / f, y / f)`` in OpenCV's frame (y down)."""
    ray = cam.unproject(uv)                       # (qx, qy, -f) normalised, y up
    return np.column_stack([ray[:, 0] / -ray[:, 2], -ray[:, 1] / -ray[:, 2]])


def _pair(cam: Camera, uv1, uv2, threshold_px: float):
    """``(R2, C2, inliers, median angle [deg])`` of image 2 relative to image 1, or None."""
    p1, p2 = _normalised(cam, uv1), _normalised(cam, uv2)
    f_px = cam.f_mm / cam.sensor.pixel_mm
    E, mask = cv2.findEssentialMat(p1, p2, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                   threshold=threshold_px / f_px)
    if E is None or E.shape != (3, 3):
        return None
    n, R_cv, t_cv, mask2 = cv2.recoverPose(E, p1, p2, np.eye(3), mask=mask.copy())
    inl = mask2.ravel() > 0
    if n < MIN_PAIR_POINTS:
        return None
    R2 = _D @ R_cv @ _D
    C2 = -R2.T @ _D @ t_cv.ravel()
    d1 = cam.unproject(uv1)
    d2 = cam.unproject(uv2) @ R2                  # rows: R2^T d
    cos = np.einsum("ka,ka->k", d1, d2) / np.linalg.norm(d1, axis=1) / np.linalg.norm(d2, axis=1)
    angle = float(np.degrees(np.median(np.arccos(np.clip(cos[inl], -1.0, 1.0)))))
    return R2, C2, inl, angle


def orient_pair(data: FieldData, params, threshold_px: float):
    """The best-founded relative orientation among the pairs that share most points.

    Returns ``(i, j, R (2, 3, 3), C (2, 3))``: image ``i`` at the origin with the identity
    rotation, image ``j`` one unit away (module docstring).

    Raises
    ------
    GeometryError
        No pair shares :data:`MIN_PAIR_POINTS` points at an angle of :data:`MIN_ANGLE_DEG`.
    """
    n_img = len(data.images)
    n_t = len(data.targets)
    seen = np.zeros((n_img, n_t), bool)
    seen[data.obs.image, data.obs.target] = True
    common = seen.astype(np.int32) @ seen.T.astype(np.int32)
    np.fill_diagonal(common, 0)
    iu, ju = np.triu_indices(n_img, 1)
    order = np.argsort(-common[iu, ju], kind="stable")[:CANDIDATE_PAIRS]
    cam = Camera(data.sensor, np.asarray(params, float))
    pos = np.full((n_img, n_t), -1, np.int64)
    pos[data.obs.image, data.obs.target] = np.arange(len(data.obs))
    best = None
    for i, j in zip(iu[order], ju[order], strict=True):
        if common[i, j] < MIN_PAIR_POINTS:
            break
        t = np.flatnonzero(seen[i] & seen[j])
        got = _pair(cam, data.obs.uv_px[pos[i, t]], data.obs.uv_px[pos[j, t]], threshold_px)
        if got is None or got[3] < MIN_ANGLE_DEG:
            continue
        score = got[2].sum() * min(got[3], 20.0)
        if best is None or score > best[0]:
            best = (score, int(i), int(j), got[0], got[1])
    if best is None:
        raise GeometryError(f"no surveyed target, and no two images share {MIN_PAIR_POINTS} points seen "
                            f"at {MIN_ANGLE_DEG:g} degrees or more: the network cannot be started by "
                            "relative orientation (photograph from further apart, or survey four targets)")
    _, i, j, R2, C2 = best
    return i, j, np.stack([np.eye(3), R2]), np.stack([np.zeros(3), C2])
