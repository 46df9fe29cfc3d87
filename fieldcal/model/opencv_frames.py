"""The bridge between fieldcal's camera frames and OpenCV's (docs/conventions.md).

fieldcal's camera frame has ``y`` up and looks along ``-z``; OpenCV's has ``y`` down and
looks along ``+z``: ``R_cv = FLIP_YZ @ R_world_to_camera``. OpenCV's intrinsic matrix
describes the *ideal* (distortion-free) image; :func:`ideal_pixels` maps measured pixels
into it through fieldcal's correction.
"""

from __future__ import annotations

import cv2
import numpy as np

from fieldcal.model.camera import Camera

__all__ = ["FLIP_YZ", "opencv_camera_matrix", "ideal_pixels", "pose_to_opencv", "pose_from_opencv"]

FLIP_YZ = np.diag([1.0, -1.0, -1.0])
"""fieldcal camera frame <-> OpenCV camera frame: ``R_cv = FLIP_YZ @ R_world_to_camera``."""

def opencv_camera_matrix(camera: Camera) -> np.ndarray:
    """OpenCV's 3x3 intrinsic matrix [px] of the *ideal* (distortion-free) image of ``camera``.

    ``fx = fy = f/d``, ``cx = (W-1)/2 + xp/d``, ``cy = (H-1)/2 - yp/d`` (docs/conventions.md section 1).
    Use it with :func:`ideal_pixels` and no distortion coefficients.
    """
    fx = camera.f_mm / camera.sensor.pixel_mm
    cx, cy = camera.principal_point_px
    return np.array([[fx, 0.0, cx], [0.0, fx, cy], [0.0, 0.0, 1.0]])


def ideal_pixels(uv_px, camera: Camera) -> np.ndarray:
    """Measured pixels (..., 2) -> distortion-free pixels (..., 2) of :func:`opencv_camera_matrix`.

    The measured points are corrected with :func:`fieldcal.model.camera.correct` to ideal points
    ``q`` [mm] (relative to the principal point) and mapped with ``u = cx + qx/d``,
    ``v = cy - qy/d``. Without distortion this is the identity.
    """
    s = camera.sensor
    q = camera.correct(s.pixel_to_mm(uv_px))
    K = opencv_camera_matrix(camera)
    d = s.pixel_mm
    return np.stack([K[0, 2] + q[..., 0] / d, K[1, 2] - q[..., 1] / d], axis=-1)


def pose_to_opencv(R_world_to_camera, center_m):
    """fieldcal pose -> OpenCV ``(rvec (3,), tvec (3,))`` with ``x_cv = R_cv X + tvec``."""
    R_cv = FLIP_YZ @ np.asarray(R_world_to_camera, dtype=float)
    rvec, _ = cv2.Rodrigues(R_cv)
    return rvec.ravel(), -R_cv @ np.asarray(center_m, dtype=float)


def pose_from_opencv(rvec, tvec):
    """OpenCV ``(rvec, tvec)`` -> fieldcal ``(R_world_to_camera (3, 3), center_m (3,))``."""
    R_cv, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))
    C = -R_cv.T @ np.asarray(tvec, dtype=float).ravel()
    return FLIP_YZ @ R_cv, C


