"""The bundle model: analytic Jacobian against central differences, residuals at the truth, and the
compiled kernel against the NumPy reference (one contract over both implementations)."""

import os
import subprocess
import sys

import numpy as np
import pytest

from fieldcal.field import bundle_kernel
from fieldcal.field.bundle import BundleModel, image_residuals
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


# ---------------------------------------------------------------------------- the compiled kernel
@pytest.mark.parametrize("adjusted", [True, False])
@pytest.mark.parametrize("estimate", [FIELD_PARAMS, ("f_mm", "k0", "k1", "k2", "k3", "p1", "p2", "a1", "a2",
                                                     "b1", "b2", "xp_mm", "yp_mm"), ()],
                         ids=["field", "all13", "exterior-only"])
def test_compiled_kernel_and_numpy_reference_agree(adjusted, estimate):
    """The contract of the two implementations of the residuals and blocks: the same numbers
    (to round-off) on a wide-angle problem with rotation increments, NaN where a point is behind."""
    if bundle_kernel.kernel() is None:
        pytest.skip(bundle_kernel.status())
    sf = wide_field(seed=0)
    params = sf.camera.params.copy()
    params[[3, 11, 12]] = (1e-4, 2e-5, -3e-5)             # k0, b1, b2 non-zero: every column is live
    m = BundleModel(sf.data, params, estimate, sf.R_world_to_camera, targets_adjusted=adjusted)
    x = m.pack(params, sf.center_m, sf.targets_true.xyz_m)
    x[m.n_int:m.n_reduced] += np.random.default_rng(3).normal(0, 0.01, 6 * m.n_images)
    x[m.n_int + 6 * 4 + 3: m.n_int + 6 * 4 + 6] = [0.0, 5.0, 2.0]   # image 4 behind the wall: NaN
    a = m.residuals_and_blocks(x, implementation="numpy")
    b = m.residuals_and_blocks(x, implementation="numba")
    nan_a, nan_b = np.isnan(a[0]), np.isnan(b[0])
    assert nan_a.any() and np.array_equal(nan_a, nan_b)
    # residuals are in sigmas of 0.1 px: 1e-9 of a sigma is far below any decision
    assert np.allclose(a[0][~nan_a], b[0][~nan_b], rtol=0, atol=1e-9)
    ok = ~nan_a[: m.n_rows_image].reshape(-1, 2).any(axis=1)
    for name in ("d_int", "d_ext", "d_tgt"):
        A, B = getattr(a[1], name)[ok], getattr(b[1], name)[ok]
        assert A.shape == B.shape and np.all(np.isfinite(B))
        if A.size:   # relative to the largest entry of the block: round-off of ~40 flops
            assert np.abs(A - B).max() <= 1e-12 * np.abs(A).max(), name
    assert np.array_equal(a[2], b[2])


def test_image_residuals_kernel_and_numpy_reference_agree():
    """The residuals of every observation (readmission, the result's table): the compiled loop
    and the NumPy reference, on a distorted wide-angle camera, with a pose put behind the wall
    (NaN) and a point far outside the invertible region (Newton does not converge: NaN)."""
    if bundle_kernel.residuals_kernel() is None:
        pytest.skip(bundle_kernel.status())
    sf = wide_field(seed=0)
    params = sf.camera.params.copy()
    params[[3, 11, 12]] = (1e-4, 2e-5, -3e-5)
    R, C = sf.R_world_to_camera, sf.center_m.copy()
    C[4] = [0.0, 5.0, 2.0]                                   # image 4 behind the wall
    X = sf.targets_true.xyz_m + np.random.default_rng(4).normal(0, 0.01, sf.targets_true.xyz_m.shape)
    a = image_residuals(sf.data, params, R, C, X, implementation="numpy")
    b = image_residuals(sf.data, params, R, C, X, implementation="numba")
    assert np.isnan(a).any()
    # the same arithmetic; equal to round-off (not asserted bit for bit: the reference's
    # order of the sums is NumPy's einsum's, which a NumPy release may change)
    assert np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True)
    # beyond the invertible region of a strong barrel: both give NaN
    wild = params.copy()
    wild[4] = -5e-3
    a = image_residuals(sf.data, wild, R, C, implementation="numpy")
    b = image_residuals(sf.data, wild, R, C, implementation="numba")
    assert np.isnan(a).any() and np.array_equal(np.isnan(a), np.isnan(b))
    assert np.allclose(a, b, rtol=0, atol=1e-9, equal_nan=True)
    # the default targets are the surveyed ones
    assert np.array_equal(image_residuals(sf.data, params, R, C, implementation="numba"),
                          image_residuals(sf.data, params, R, C, sf.data.targets.xyz_m, implementation="numba"),
                          equal_nan=True)


@pytest.mark.parametrize("implementation", ["numpy", "numba"])
@pytest.mark.parametrize("adjusted", [False, True])
def test_a_restricted_model_evaluates_exactly_the_kept_rows(implementation, adjusted):
    if implementation == "numba" and bundle_kernel.kernel() is None:
        pytest.skip(bundle_kernel.status())
    sf = wide_field(seed=0)
    m = BundleModel(sf.data, sf.camera.params, FIELD_PARAMS, sf.R_world_to_camera, targets_adjusted=adjusted)
    x = m.pack(sf.camera.params, sf.center_m, sf.data.targets.xyz_m)
    x[m.n_int:m.n_reduced] += np.random.default_rng(5).normal(0, 1e-3, 6 * m.n_images)
    keep = np.isin(m.img, [1, 4, 5, 17])
    r, jb, sd = m.residuals_and_blocks(x, implementation=implementation)
    rs, jbs, sds = m.restricted(keep).residuals_and_blocks(x, implementation=implementation)
    n_img = m.n_rows_image
    assert np.array_equal(rs[: 2 * keep.sum()], r[:n_img].reshape(-1, 2)[keep].ravel())
    assert np.array_equal(rs[2 * keep.sum():], r[n_img:]) and np.array_equal(sds, sd)
    for name in ("d_int", "d_ext", "d_tgt"):
        assert np.array_equal(getattr(jbs, name), getattr(jb, name)[keep]), name


def test_without_numba_the_numpy_reference_runs_and_says_so():
    """FIELDCAL_NUMBA=0 (as on a platform where the kernel cannot be compiled): same result."""
    code = ("from fieldcal.field import bundle_kernel as k; print(k.kernel() is None); print(k.status())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "FIELDCAL_NUMBA": "0"})
    assert out.stdout.splitlines() == ["True", "switched off by FIELDCAL_NUMBA=0"]
