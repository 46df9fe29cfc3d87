"""Matching many views at once (fieldcal.field.matching): truth, references, and the contract that
views refined together are refined as each alone."""

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from fieldcal.field.identify import IdentifyOptions, measured_points
from fieldcal.field.matching import (
    ViewMatcher,
    grouped_median,
    pinhole_jacobian,
    refine_poses,
    rotation_exp,
)
from fieldcal.model.opencv_frames import opencv_camera_matrix, pose_from_opencv, pose_to_opencv
from fieldcal.synthetic.field import measurements_of, wide_field


def test_grouped_median_is_numpy_median_per_group():
    rng = np.random.default_rng(0)
    v = rng.normal(size=500)
    g = rng.integers(0, 7, 500)
    g[g == 3] = 4                                       # one empty group
    out = grouped_median(v, g, 8)
    for k in range(8):
        expect = np.median(v[g == k]) if np.any(g == k) else np.nan
        np.testing.assert_allclose(out[k], expect, rtol=0, atol=0, equal_nan=True)


def test_rotation_exp_is_scipys_rotation_vector():
    w = np.random.default_rng(1).normal(size=(50, 3))
    w[0] = 0.0
    np.testing.assert_allclose(rotation_exp(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-14)


def test_pinhole_jacobian_matches_central_differences():
    rng = np.random.default_rng(2)
    sf = wide_field(seed=1)
    R, C = sf.R_world_to_camera[3], sf.center_m[3]
    X = sf.targets_true.xyz_m[rng.choice(len(sf.targets_true), 20, replace=False)]
    Rs, Cs = np.repeat(R[None], 20, axis=0), np.repeat(C[None], 20, axis=0)
    _, J = pinhole_jacobian(24.0, Rs, Cs, X)
    h = 1e-6
    for k in range(6):
        d = np.zeros(6)
        d[k] = h
        plus = pinhole_jacobian(24.0, rotation_exp(d[:3])[None] @ Rs, Cs + d[3:], X)[0]
        minus = pinhole_jacobian(24.0, rotation_exp(-d[:3])[None] @ Rs, Cs - d[3:], X)[0]
        # [mm] per unit: central differences are exact to ~h^2 times the third derivative
        np.testing.assert_allclose(J[:, :, k], (plus - minus) / (2 * h), rtol=1e-6, atol=1e-9)


def _ideal(sf, i):
    """Image i's exact targets and their ideal points [mm]."""
    k = sf.data.obs.image == i
    t = sf.data.obs.target[k]
    q = sf.camera.correct(sf.camera.sensor.pixel_to_mm(sf.uv_true_px[k]))
    return sf.targets_true.xyz_m[t], q, sf.data.obs.uv_px[k]


def test_refine_poses_recovers_the_truth_and_agrees_with_opencv():
    sf = wide_field(seed=1)
    images = [0, 4, 8]
    rng = np.random.default_rng(3)
    R0 = np.stack([rotation_exp(rng.normal(0, 0.02, 3)) @ sf.R_world_to_camera[i] for i in images])
    C0 = np.stack([sf.center_m[i] + rng.normal(0, 0.05, 3) for i in images])
    parts = [_ideal(sf, i) for i in images]
    view = np.concatenate([np.full(len(p[0]), v) for v, p in enumerate(parts)])
    X = np.concatenate([p[0] for p in parts])
    q = np.concatenate([p[1] for p in parts])
    R, C = refine_poses(sf.camera.f_mm, R0, C0, view, X, q, steps=20)
    for v, i in enumerate(images):
        # exact points: the truth to round-off (1e-9 rad, 1e-8 m at 5 m)
        assert np.abs(R[v] - sf.R_world_to_camera[i]).max() < 1e-9
        assert np.abs(C[v] - sf.center_m[i]).max() < 1e-8
    # noisy points: OpenCV's Levenberg-Marquardt on the ideal pixels finds the same pose
    K = opencv_camera_matrix(sf.camera)
    d = sf.camera.sensor.pixel_mm
    for v in range(len(images)):
        Xv, _, uv = parts[v]
        qv = sf.camera.correct(sf.camera.sensor.pixel_to_mm(uv))
        Rn, Cn = refine_poses(sf.camera.f_mm, R0[v:v + 1], C0[v:v + 1], np.zeros(len(Xv), int), Xv, qv, steps=20)
        img = np.stack([K[0, 2] + qv[:, 0] / d, K[1, 2] - qv[:, 1] / d], axis=1)
        rv, tv = pose_to_opencv(R0[v], C0[v])
        rv, tv = cv2.solvePnPRefineLM(Xv.reshape(-1, 1, 3), img.reshape(-1, 1, 2), K, None, rv.reshape(3, 1).copy(),
                                      tv.reshape(3, 1).copy(), (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS,
                                                                100, 1e-14))
        Rcv, Ccv = pose_from_opencv(rv, tv)
        # the same least-squares problem: agreement far below its 0.1 px noise (~1e-4 m here)
        assert np.abs(Rn[0] - Rcv).max() < 1e-7 and np.abs(Cn[0] - Ccv).max() < 1e-6


def test_views_refined_together_are_refined_as_each_alone():
    """The vectorisation over views (one KD-tree, offsets per view) changes nothing."""

    sf = wide_field(seed=1)
    images = [1, 5, 9, 10]
    measured = []
    for i in images:
        kind, _, uv, usable = measured_points(measurements_of(sf, i, coded=False, seed=0)[0])
        measured.append(uv[(kind == "disc") & usable])
    rng = np.random.default_rng(4)
    # a start as a pose prior gives it: ~0.2 degrees and 2 cm off
    R0 = np.stack([rotation_exp(rng.normal(0, 0.003, 3)) @ sf.R_world_to_camera[i] for i in images])
    C0 = np.stack([sf.center_m[i] + rng.normal(0, 0.02, 3) for i in images])
    X = sf.data.targets.xyz_m
    vm = ViewMatcher(X, np.ones(len(X), bool), sf.camera, IdentifyOptions(), measured)
    together = vm.refine(np.arange(4), R0, C0)
    for v in range(4):
        alone = ViewMatcher(X, np.ones(len(X), bool), sf.camera, IdentifyOptions(), [measured[v]])
        one = alone.refine(np.zeros(1, int), R0[v:v + 1], C0[v:v + 1])
        a, b = together.view(v), one.view(0)
        assert np.array_equal(a["tm"], b["tm"]) and np.array_equal(a["jm"], b["jm"])
        assert np.abs(a["R"] - b["R"]).max() < 1e-12 and np.abs(a["C"] - b["C"]).max() < 1e-12
        assert len(a["tm"]) > 0.9 * len(measured[v])           # nearly every disc identified
