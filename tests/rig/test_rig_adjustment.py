"""The rig adjustment against exact synthetic truth (fieldcal.synthetic.rig): the pose algebra
round-trips, the Jacobian is the derivative, relative orientations come back within their
sigmas, every head at least as accurate as alone, and an exposure in which a head saw too
little is still used through the other head."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fieldcal.model.rotations import R_from_rotvec, rotvec_from_R
from fieldcal.rig import adjust_rig
from fieldcal.rig.adjustment import ARCSEC_PER_RAD, LEFT_OUT, RigProblem, initial_rig
from fieldcal.rig.poses import head_pose, median_relative_pose, relative_pose, rig_pose_from_head
from fieldcal.synthetic.rig import oblique_rig, two_head_rig


def test_head_pose_and_relative_pose_are_inverse():
    rng = np.random.default_rng(3)
    R_wr, C_r = R_from_rotvec(rng.normal(size=(5, 3))), rng.normal(size=(5, 3)) * 10
    R_cr, t = R_from_rotvec(rng.normal(size=3)), rng.normal(size=3)
    R, C = head_pose(R_wr, C_r, R_cr, t)
    R_cr2, t2 = relative_pose(R_wr, C_r, R, C)
    np.testing.assert_allclose(R_cr2, np.broadcast_to(R_cr, (5, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(t2, np.broadcast_to(t, (5, 3)), atol=1e-12)
    R_wr2, C_r2 = rig_pose_from_head(R, C, R_cr, t)
    np.testing.assert_allclose(R_wr2, R_wr, atol=1e-12)
    np.testing.assert_allclose(C_r2, C_r, atol=1e-12)
    # the camera centre is the lever arm, seen from the rig: C = C_rig + R_world_to_rig^T t
    np.testing.assert_allclose(np.einsum("kab,kb->ka", R_wr, C - C_r), np.broadcast_to(t, (5, 3)), atol=1e-12)


def test_the_median_relative_pose_ignores_a_bad_minority():
    R_true, t_true = R_from_rotvec([0.1, -0.7, 0.2]), np.array([0.5, 0.0, -0.1])
    rng = np.random.default_rng(1)
    Rs = R_from_rotvec(rng.normal(0, 1e-5, (9, 3))) @ R_true
    ts = t_true + rng.normal(0, 1e-4, (9, 3))
    Rs[:3] = R_from_rotvec(rng.normal(0, 0.3, (3, 3))) @ R_true          # three exposures gone wrong
    ts[:3] += 1.0
    R, t = median_relative_pose(Rs, ts)
    assert np.linalg.norm(rotvec_from_R(R @ R_true.T)) < 5e-5              # 10 arcsec, the good ones' scatter
    assert np.abs(t - t_true).max() < 3e-4


@pytest.fixture(scope="module")
def two_head():
    sr = two_head_rig(seed=7)
    return sr, adjust_rig(sr.data)


def test_the_rig_jacobian_is_the_derivative_of_its_residuals(two_head):
    sr, res = two_head
    data = sr.data
    active = [np.ones(len(d.obs), bool) for d in data.head_data]
    problem = RigProblem(data, res.state, active, np.ones(len(data.exposures), bool))
    x = problem.pack(res.state)
    rng = np.random.default_rng(0)
    x[problem.rel_off[1]:problem.rel_off[1] + 3] += rng.normal(0, 1e-3, 3)   # away from the references
    x[problem.rig_off:problem.n_reduced].reshape(-1, 6)[:, :3] += rng.normal(0, 1e-3, (len(data.exposures), 3))
    r, J = problem.evaluate(x, True)
    Jd = J.to_csr()
    n_tgt = problem.n_params - problem.n_reduced
    cols = np.concatenate([np.arange(problem.n_reduced), problem.n_reduced + rng.choice(n_tgt, 30)])
    for j in cols:
        ana = Jd[:, j].toarray().ravel()
        h = 1e-4 / np.abs(ana).max()          # a step that moves the residuals by 1e-4 (they are ~1)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        num = (problem.evaluate(xp, False)[0] - problem.evaluate(xm, False)[0]) / (2 * h)
        # central differences: round-off 1e-12 / 1e-4 and truncation h^2 of the scale
        assert np.abs(num - ana).max() < 1e-5 * np.abs(ana).max(), f"column {j}"


def test_two_heads_relative_orientation_is_recovered_within_its_sigmas(two_head):
    sr, res = two_head
    st = res.state
    err_arcsec = rotvec_from_R(st.R_camera_to_rig[1] @ sr.R_camera_to_rig[1].T) * ARCSEC_PER_RAD
    err_mm = (st.t_camera_in_rig_m[1] - sr.t_camera_in_rig_m[1]) * 1000.0
    assert np.all(np.abs(err_arcsec) < 4.0 * res.sigma_rotation_arcsec[1])      # 4 sigma: one draw
    assert np.all(np.abs(err_mm) < 4.0 * res.sigma_t_mm[1])
    assert np.all(res.sigma_rotation_arcsec[1] < 10.0) and np.all(res.sigma_t_mm[1] < 0.2)
    assert np.all(res.sigma_rotation_arcsec[0] == 0.0) and 0.9 < res.sigma0 < 1.1
    k = res.covariance_names.index("bar2-right:rot_x")
    assert np.isclose(np.sqrt(res.covariance[k, k]) * ARCSEC_PER_RAD, res.sigma_rotation_arcsec[1, 0])
    assert res.relative_names() == [f"bar2-right:{c}" for c in ("rot_x", "rot_y", "rot_z", "t_x_m", "t_y_m", "t_z_m")]


def test_every_head_is_as_accurate_in_the_rig_as_alone_or_better(two_head):
    sr, res = two_head
    for h, cam in enumerate(sr.cameras):
        solo = res.state.solo[h]
        for j, p in enumerate(("f_mm", "xp_mm", "yp_mm")):
            assert abs(res.state.params[h][j] - cam.params[j]) < 4.0 * res.sigma[h][p]
            assert res.sigma[h][p] <= solo.sigma[p] * 1.001, (h, p)


def test_an_exposure_where_a_head_saw_too_little_is_used_through_the_other_head():
    sr = two_head_rig(seed=2)
    d = sr.data.head_data[1]
    i = 4                                                     # head 1's image of one exposure: 3 points left
    k_img = np.flatnonzero(d.obs.image == i)
    keep = np.ones(len(d.obs), bool)
    keep[k_img[3:]] = False
    head_data = list(sr.data.head_data)
    head_data[1] = d.with_obs(d.obs.take(keep))
    data = replace(sr.data, head_data=head_data)
    res = adjust_rig(data)
    solo_files = [im.file for im in res.state.solo[1].data.images]
    assert d.images[i].file not in solo_files                 # too few for the head alone
    o = data.head_data[1].obs
    used = res.obs_used[1][o.image == i]
    assert len(used) == 3 and used.all()                      # but in the rig
    assert np.all(np.abs(res.residual_px[1][o.image == i]) < 5 * 0.1)
    assert res.stats()["heads"]["bar2-right"]["n_images"] == 24


def test_an_exposure_with_too_few_points_is_left_out_with_its_reason():
    sr = two_head_rig(seed=3)
    head_data, e = [], 5
    for h, d in enumerate(sr.data.head_data):
        i = int(np.flatnonzero(sr.data.image_exposure[h] == e)[0])
        k = np.flatnonzero(d.obs.image == i)
        keep = np.ones(len(d.obs), bool)
        keep[k[2:]] = False
        head_data.append(d.with_obs(d.obs.take(keep)))
    res = adjust_rig(replace(sr.data, head_data=head_data))
    assert not res.exposure_used[e] and res.exposure_used.sum() == 23
    for h, d in enumerate(head_data):
        i = int(np.flatnonzero(sr.data.image_exposure[h] == e)[0])
        assert set(res.obs_reason[h][d.obs.image == i]) == {LEFT_OUT}


def test_a_five_head_oblique_rig_is_recovered_within_its_sigmas():
    sr = oblique_rig(seed=5, heights_m=(20.0, 28.0), grid_m=(-10.0, 10.0))
    start = initial_rig(sr.data)
    res = adjust_rig(sr.data, start=start)
    st = res.state
    z = []
    for h in range(1, 5):
        e_rot = rotvec_from_R(st.R_camera_to_rig[h] @ sr.R_camera_to_rig[h].T) * ARCSEC_PER_RAD
        e_t = (st.t_camera_in_rig_m[h] - sr.t_camera_in_rig_m[h]) * 1000.0
        z += list(e_rot / res.sigma_rotation_arcsec[h]) + list(e_t / res.sigma_t_mm[h])
        assert res.sigma[h]["f_mm"] <= st.solo[h].sigma["f_mm"]
    assert np.all(np.abs(z) < 4.5)                              # 24 values of one draw
    assert 0.4 < np.sqrt(np.mean(np.square(z))) < 1.6            # a loose check of one draw; the bench has the MC


def test_blunders_in_one_head_are_rejected():
    sr = two_head_rig(seed=4)
    d = sr.data.head_data[1]
    rng = np.random.default_rng(4)
    bad = rng.choice(len(d.obs), 12, replace=False)
    uv = d.obs.uv_px.copy()
    uv[bad] += rng.choice([-1.0, 1.0], (12, 2)) * 3.0            # 3 px: 30 sigma of the 0.1 px points
    head_data = list(sr.data.head_data)
    head_data[1] = d.with_obs(replace(d.obs, uv_px=uv))
    res = adjust_rig(replace(sr.data, head_data=head_data))
    assert set(np.flatnonzero(res.obs_reason[1] == "blunder")) == set(bad.tolist())
    assert not (res.obs_reason[0] == "blunder").any()
    err = rotvec_from_R(res.state.R_camera_to_rig[1] @ sr.R_camera_to_rig[1].T) * ARCSEC_PER_RAD
    assert np.all(np.abs(err) < 4.0 * res.sigma_rotation_arcsec[1]) and 0.9 < res.sigma0 < 1.1
