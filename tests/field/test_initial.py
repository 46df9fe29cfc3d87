"""Initial values of the field adjustment (fieldcal.field.initial)."""

from dataclasses import replace

import numpy as np

from fieldcal.field.initial import refine_poses
from fieldcal.model.rotations import R_from_rotvec
from fieldcal.synthetic.field import paper_field


def test_refine_poses_ends_at_the_same_poses_whatever_its_initial_damping():
    """The initial damping only changes the path (issue 15: 1e-6 instead of 1e-3 saves ~8 of
    19 evaluations on the paper field): the poses it ends at are the same, at the truth within
    the noise (0.1 px image noise, true camera, true targets)."""
    sf = paper_field(seed=0)
    rng = np.random.default_rng(1)
    n = len(sf.data.images)
    R0 = R_from_rotvec(rng.normal(0.0, 2e-3, (n, 3))) @ sf.R_world_to_camera     # ~0.1 degree off
    C0 = sf.center_m + rng.normal(0.0, 0.05, (n, 3))                              # 5 cm off
    data = replace(sf.data, targets=replace(sf.data.targets, xyz_m=sf.targets_true.xyz_m))
    active = np.ones(len(data.obs), bool)
    out = {mu0: refine_poses(data, sf.camera.params, R0, C0, active, mu0=mu0) for mu0 in (1e-3, 1e-6)}
    (Ra, Ca, rms_a), (Rb, Cb, rms_b) = out[1e-3], out[1e-6]
    assert np.abs(Ca - Cb).max() < 1e-6                  # [m]: both converged (tol 1e-10 of the cost)
    assert np.abs(Ra - Rb).max() < 1e-8
    assert np.abs(Cb - sf.center_m).max() < 0.05         # [m]: 0.1 px at ~60 m with a 150 mm lens
    np.testing.assert_allclose(rms_a, rms_b, rtol=1e-6)
