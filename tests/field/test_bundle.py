"""The bundle model: analytic Jacobian against central differences, residuals at the truth."""

import numpy as np
import pytest

from fieldcal.field.bundle import BundleModel
from fieldcal.model.camera import FIELD_PARAMS
from fieldcal.synthetic.field import paper_field, wide_field

# central-difference steps for the interior columns, by magnitude of each parameter's effect
INT_STEPS = [1e-6, 1e-6, 1e-6, 1e-9, 1e-12, 1e-15, 1e-9, 1e-9, 1e-7, 1e-7]


def dense_jacobian(m, x):
    r, J, sd = m.residuals_and_blocks(x)
    Jd = np.zeros((m.n_rows, m.n_params))
    k = np.arange(len(m.img))
    rows = np.stack([2 * k, 2 * k + 1], axis=1)
    for a in range(2):
        Jd[rows[:, a, None], np.arange(m.n_int)[None, :]] = J.d_int[:, a, :]
        Jd[rows[:, a, None], m.n_int + 6 * m.img[:, None] + np.arange(6)] = J.d_ext[:, a, :]
        if m.targets_adjusted:
            Jd[rows[:, a, None], m.n_reduced + 3 * m.tgt_slot[:, None] + np.arange(3)] = J.d_tgt[:, a, :]
    for i, t in enumerate(m.survey_k):
        for a in range(3):
            Jd[m.n_rows_image + 3 * i + a, m.n_reduced + 3 * m.t_slot[t] + a] = sd[i]
    return Jd


@pytest.mark.parametrize("scenario", [wide_field, paper_field])
@pytest.mark.parametrize("adjusted", [True, False])
def test_analytic_jacobian_matches_central_differences(scenario, adjusted):
    sf = scenario(seed=0)
    d = sf.data
    data = d.with_obs(d.obs.take(np.isin(d.obs.image, [0, 1, 5])))
    m = BundleModel(data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera, targets_adjusted=adjusted)
    rng = np.random.default_rng(0)
    x = m.pack(sf.camera.params, sf.center_m, sf.targets_true.xyz_m)
    x[m.n_int:m.n_reduced] += rng.normal(0, 0.01, 6 * m.n_images)   # rotation increments != 0
    Jd = dense_jacobian(m, x)
    used = np.flatnonzero(np.abs(Jd).sum(axis=0) > 0)
    if adjusted:  # check every interior and exterior column and a sample of target columns
        used = np.concatenate([used[used < m.n_reduced], rng.choice(used[used >= m.n_reduced], 30)])
    steps = np.full(m.n_params, 1e-7)
    steps[:m.n_int] = INT_STEPS
    for j in used:
        e = np.zeros(m.n_params)
        e[j] = steps[j]
        num = (m.residuals_and_blocks(x + e, False)[0] - m.residuals_and_blocks(x - e, False)[0]) / (2 * e[j])
        scale = np.abs(num).max()
        assert np.abs(num - Jd[:, j]).max() <= 1e-5 * scale, m.column_names()[j]


def test_residuals_vanish_at_the_truth_without_noise():
    sf = paper_field(seed=2, image_noise_px=0.0, survey_noise_mm=0.0)
    m = BundleModel(sf.data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera)
    x = m.pack(sf.camera.params, sf.center_m, sf.targets_true.xyz_m)
    r, _, _ = m.residuals_and_blocks(x, jacobian=False)
    assert np.abs(r).max() < 1e-6    # sigma floor 1e-3 px: residuals below 1e-9 px


def test_rebase_keeps_the_model_and_zeroes_the_increments():
    sf = wide_field(seed=0)
    m = BundleModel(sf.data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera)
    x = m.pack(sf.camera.params, sf.center_m, sf.targets_true.xyz_m)
    x[m.n_int:m.n_reduced] += np.random.default_rng(1).normal(0, 0.05, 6 * m.n_images)
    before = m.predict(x)
    x2 = m.rebase(x)
    assert np.allclose(m.predict(x2), before, atol=1e-9)
    assert np.all(x2[m.n_int:m.n_reduced].reshape(-1, 6)[:, :3] == 0)
