"""Pose algebra of a rig: a head's exterior orientation from the rig pose and its relative
orientation, and back (CONTRACT section 3, "Rig sessions"; frames of docs/conventions.md).

The rig frame is the reference head's camera frame. Per exposure the rig has a pose
``(R_world_to_rig, C_rig_m)`` (the reference head's exterior orientation); each head a
relative orientation ``(R_camera_to_rig, t_camera_in_rig_m)`` constant over the session::

    R_world_to_camera = R_camera_to_rig^T R_world_to_rig
    C_camera          = C_rig + R_world_to_rig^T t_camera_in_rig

and back, from a head's and the reference's exterior orientations of one exposure::

    R_camera_to_rig   = R_world_to_rig R_world_to_camera^T
    t_camera_in_rig   = R_world_to_rig (C_camera - C_rig)

Every function broadcasts over leading dimensions.
"""

from __future__ import annotations

import numpy as np

from fieldcal.model.rotations import R_from_rotvec, rotvec_from_R

__all__ = ["head_pose", "relative_pose", "median_relative_pose", "rig_pose_from_head"]


def head_pose(R_world_to_rig, C_rig_m, R_camera_to_rig, t_camera_in_rig_m):
    """A head's ``(R_world_to_camera (..., 3, 3), C_camera_m (..., 3))`` (module docstring)."""
    R_wr = np.asarray(R_world_to_rig, float)
    R = np.swapaxes(np.asarray(R_camera_to_rig, float), -1, -2) @ R_wr
    C = np.asarray(C_rig_m, float) + np.einsum("...ba,...b->...a", R_wr, np.asarray(t_camera_in_rig_m, float))
    return R, C


def relative_pose(R_world_to_rig, C_rig_m, R_world_to_camera, C_camera_m):
    """``(R_camera_to_rig (..., 3, 3), t_camera_in_rig_m (..., 3))`` of a head from its exterior
    orientation and the rig's of the same exposure (the inverse of :func:`head_pose`)."""
    R_wr = np.asarray(R_world_to_rig, float)
    R_cr = R_wr @ np.swapaxes(np.asarray(R_world_to_camera, float), -1, -2)
    t = np.einsum("...ab,...b->...a", R_wr, np.asarray(C_camera_m, float) - np.asarray(C_rig_m, float))
    return R_cr, t


def rig_pose_from_head(R_world_to_camera, C_camera_m, R_camera_to_rig, t_camera_in_rig_m):
    """The rig's ``(R_world_to_rig, C_rig_m)`` from one head's exterior orientation and its
    relative orientation (solving :func:`head_pose` for the rig pose)."""
    R_wr = np.asarray(R_camera_to_rig, float) @ np.asarray(R_world_to_camera, float)
    C = np.asarray(C_camera_m, float) - np.einsum("...ba,...b->...a", R_wr, np.asarray(t_camera_in_rig_m, float))
    return R_wr, C


def median_relative_pose(R_camera_to_rig, t_camera_in_rig_m):
    """The median of several estimates (k, 3, 3), (k, 3) of one head's relative orientation.

    Rotation: the component-wise median of the rotation vectors of ``R_k R_0^T`` about the
    estimate ``R_0`` nearest to all others (the medoid), applied to ``R_0``; lever arm: the
    component-wise median. Robust to a minority of bad exposures (a head's single-camera
    solution of an image with few points).
    """
    R = np.asarray(R_camera_to_rig, float).reshape(-1, 3, 3)
    t = np.asarray(t_camera_in_rig_m, float).reshape(-1, 3)
    d = np.linalg.norm(rotvec_from_R(R[:, None] @ np.swapaxes(R[None], -1, -2)), axis=-1)
    R0 = R[int(np.argmin(np.median(d, axis=1)))]
    w = np.median(rotvec_from_R(R @ R0.T), axis=0)
    return R_from_rotvec(w) @ R0, np.median(t, axis=0)
