"""Rotations: the contract's omega-phi-kappa convention, rotation vectors and J_l."""

import numpy as np
import pytest

from fieldcal.model import rotations as rot


def test_opk_matrix_is_Rz_Ry_Rx_camera_to_world():
    o, p, k = 0.3, -0.4, 1.1
    rx = np.array([[1, 0, 0], [0, np.cos(o), -np.sin(o)], [0, np.sin(o), np.cos(o)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    assert np.allclose(rot.R_camera_to_world_from_opk(o, p, k), rz @ ry @ rx, atol=1e-15)
    assert np.allclose(rot.R_world_to_camera_from_opk(o, p, k), (rz @ ry @ rx).T, atol=1e-15)


def test_opk_round_trip_vectorised():
    rng = np.random.default_rng(0)
    o, k = rng.uniform(-np.pi, np.pi, (2, 500))
    p = rng.uniform(-1.5, 1.5, 500)
    back = rot.opk_from_R_world_to_camera(rot.R_world_to_camera_from_opk(o, p, k))
    assert np.allclose(back, (o, p, k), atol=1e-10)


def test_rotvec_round_trip_and_left_jacobian_by_central_differences():
    rng = np.random.default_rng(1)
    w = rng.normal(size=(20, 3))
    w *= np.minimum(1.0, 3.0 / np.linalg.norm(w, axis=1, keepdims=True))  # |w| < pi: unique
    assert np.allclose(rot.rotvec_from_R(rot.R_from_rotvec(w)), w, atol=1e-12)
    a = rng.normal(size=3)
    for wi in np.concatenate([w, [[1e-6, 0, 0], [0, 0, 0]]]):
        J = -rot.skew(rot.R_from_rotvec(wi) @ a) @ rot.left_jacobian_so3(wi)
        h = 1e-6
        num = np.stack([(rot.R_from_rotvec(wi + h * e) @ a - rot.R_from_rotvec(wi - h * e) @ a) / (2 * h)
                        for e in np.eye(3)], axis=1)
        assert np.allclose(J, num, atol=1e-8)


@pytest.mark.parametrize("v", [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
def test_skew_is_the_cross_product(v):
    w = np.array([-0.5, 0.25, 2.0])
    assert np.allclose(rot.skew(v) @ w, np.cross(v, w))
