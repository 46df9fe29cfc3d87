"""The rig adjustment's blunder rejection (data snooping, as the single camera's) and variance
components (every head's image floor), against exact synthetic truth (fieldcal.synthetic.rig)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from fieldcal.model.rotations import rotvec_from_R
from fieldcal.rig import adjust_rig
from fieldcal.rig.adjustment import ARCSEC_PER_RAD, RigOptions, initial_rig
from fieldcal.synthetic.rig import two_head_rig


def _with_head_uv(sr, h, uv):
    d = sr.data.head_data[h]
    heads = list(sr.data.head_data)
    heads[h] = d.with_obs(replace(d.obs, uv_px=uv))
    return replace(sr.data, head_data=heads)


def _z_relative(sr, res, h=1):
    st = res.state
    e_rot = rotvec_from_R(st.R_camera_to_rig[h] @ sr.R_camera_to_rig[h].T) * ARCSEC_PER_RAD
    e_t = (st.t_camera_in_rig_m[h] - sr.t_camera_in_rig_m[h]) * 1000.0
    return np.r_[e_rot / res.sigma_rotation_arcsec[h], e_t / res.sigma_t_mm[h]]


def test_moderate_blunders_only_snooping_can_see_are_rejected():
    # 0.72 px on 0.1 px points: 7.2 sigma, under the 8-robust-sigma gate of the norm, so only data
    # snooping can find them (T ~ 52 times the redundancy, against chdtri(2, 1e-6) = 27.6). The
    # start is the clean session's initial values without the heads' own calibrations, so no
    # head's solo snooping has marked them beforehand: the rig's snooping must find them.
    sr = two_head_rig(seed=11)
    start = replace(initial_rig(sr.data), solo=[])
    d = sr.data.head_data[1]
    rng = np.random.default_rng(11)
    bad = rng.choice(len(d.obs), 6, replace=False)
    uv = d.obs.uv_px.copy()
    uv[bad] += rng.choice([-1.0, 1.0], (6, 2)) * np.array([0.6, 0.4])
    without = adjust_rig(_with_head_uv(sr, 1, uv), RigOptions(snoop_alpha=0.0), start=start)
    assert not (without.obs_reason[1] == "blunder").any()          # the 8-sigma gate alone misses them
    res = adjust_rig(_with_head_uv(sr, 1, uv), start=start)
    assert set(np.flatnonzero(res.obs_reason[1] == "blunder")) == set(bad.tolist())
    assert not (res.obs_reason[0] == "blunder").any()
    assert np.all(np.abs(_z_relative(sr, res)) < 4.0)
    assert res.stats()["n_rejected"] == 6


def test_a_head_with_3x_noisier_points_gets_a_factor_near_3_and_honest_sigmas():
    sr = two_head_rig(seed=12)
    d = sr.data.head_data[1]
    rng = np.random.default_rng(12)
    # head 1's points: 0.1 px drawn by the synth plus sqrt(8) * 0.1 px more = 0.3 px, stated 0.1 px
    uv = d.obs.uv_px + rng.normal(0.0, np.sqrt(8.0) * 0.1, d.obs.uv_px.shape)
    res = adjust_rig(_with_head_uv(sr, 1, uv))
    vc = res.stats()["variance_components"]
    f0, f1 = (vc["heads"][hd.camera_id]["image_factor"] for hd in sr.data.heads)
    red1 = vc["heads"][sr.data.heads[1].camera_id]["image_redundancy"]
    # band: the factor's sampling error is ~1/sqrt(2 r) (under 3 % at r > 500) on top of the
    # redundancy numbers' linearisation; 2.7-3.3 is 10 %, several sampling sigmas
    assert red1 > 500
    assert 2.7 < f1 < 3.3
    assert 0.85 < f0 < 1.15
    assert vc["rounds"] >= 1 and vc["heads"][sr.data.heads[1].camera_id]["image_floor_px"] > 0.25
    assert 0.9 < res.sigma0 < 1.1                                  # the re-weighted sigmas are right
    z = _z_relative(sr, res)
    assert np.all(np.abs(z) < 4.0)                                 # 6 values of one fixed-seed draw
    assert np.sqrt(np.mean(z**2)) < 2.0
    assert not any((r == "blunder").sum() > 0.01 * len(r) for r in res.obs_reason)
