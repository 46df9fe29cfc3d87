"""Comparing two calibrations of one sensor: where the same ray lands.

For a pixel ``uv`` the calibration B gives a ray in its camera frame
(:func:`fieldcal.camera.unproject`); projecting that ray through calibration A gives the
pixel where A would have seen it. The difference ``uv_A(ray_B(uv)) - uv`` [px] over a grid
on the sensor is the correction-field difference of the two calibrations, in pixels,
independent of how the parameters are split between principal point and distortion.

Where the camera frame itself is not observable (a narrow field of view: a principal-
point shift and a small rotation of the camera are nearly indistinguishable), the best
common rotation of B's rays onto A's (Wahba's problem, solved by SVD) is removed first.
"""

from __future__ import annotations

import numpy as np

from .camera import Camera, project, unproject
from .errors import InputError

__all__ = ["ray_difference_px", "best_rotation"]


def best_rotation(a, b):
    """The rotation ``R`` (3, 3) minimising ``sum |R b_i - a_i|^2`` for unit vectors (n, 3)."""
    H = np.asarray(b, float).T @ np.asarray(a, float)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def ray_difference_px(cam_a: Camera, cam_b: Camera, uv_px=None, *, remove_rotation: bool = False,
                      grid: tuple[int, int] = (41, 31)):
    """Pixel displacement (n, 2) between where A and B map the same rays, over the sensor.

    Parameters
    ----------
    cam_a, cam_b : Camera
        Two calibrations of the same sensor.
    uv_px : (n, 2) array_like, optional
        Pixels to evaluate; default a ``grid`` (columns, rows) spanning the sensor.
    remove_rotation : bool
        Remove the best common rotation of B's camera frame onto A's first.

    Returns
    -------
    uv_px : (n, 2) ndarray
        The pixels evaluated.
    diff_px : (n, 2) ndarray
        ``uv_A(ray_B(uv)) - uv`` [px].
    """
    sa, sb = cam_a.sensor, cam_b.sensor
    if (sa.width_px, sa.height_px) != (sb.width_px, sb.height_px):
        raise InputError(f"the calibrations are of different sensors ({sa.width_px} x {sa.height_px} "
                         f"and {sb.width_px} x {sb.height_px} px)")
    uv = sa.grid_px(*grid) if uv_px is None else np.asarray(uv_px, float)
    ray_b = unproject(uv, cam_b)
    if remove_rotation:
        R = best_rotation(unproject(uv, cam_a), ray_b)
        ray_b = ray_b @ R.T
    uv_a = project(ray_b, np.eye(3), np.zeros(3), cam_a)
    return uv, uv_a - uv
