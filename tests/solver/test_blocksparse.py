"""Block-sparse Jacobian and normal equations against dense numpy on small random problems."""

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.solver.blocksparse import (
    BlockSparseJacobian,
    NormalEquations,
    ResidualBlock,
    SingularSystemError,
)

N_SHARED, N_SENSORS, SENSOR_W, N_PTS, B = 3, 3, 2, 6, 3
N_RED = N_SHARED + N_SENSORS * SENSOR_W
N_PAR = N_RED + N_PTS * B
# every product is a short sum of O(1) terms; 1e-10 relative leaves room for summation order
RTOL = 1e-10


def random_problem(seed=0, k_obs=14, all_points_seen=True, interleaved=False):
    """A toy structure: shared columns, per-"sensor" columns, eliminated 3-vectors ("points").

    Block 0 (from parts): two-row groups depending on the 3 shared columns, one sensor's 2
    columns and one point's 3 columns in a shuffled order; with ``interleaved`` the parts
    come as (shared, point, sensor), the point's columns in order. Block 1 (generic form): three-row
    groups on 2 of a point's 3 columns (a partial block). Block 2 (generic form): one-row
    groups on a shared column and two varying reduced columns, no eliminated column.
    Two residual rows belong to no group.
    """
    rng = np.random.default_rng(seed)
    k1, k2 = 4, 5
    m = 2 * k_obs + 3 * k1 + k2 + 2
    rows = rng.permutation(m)
    r0 = rows[:2 * k_obs].reshape(k_obs, 2)
    r1 = rows[2 * k_obs:2 * k_obs + 3 * k1].reshape(k1, 3)
    r2 = rows[2 * k_obs + 3 * k1:2 * k_obs + 3 * k1 + k2].reshape(k2, 1)

    twice = np.repeat(np.arange(N_PTS), 2)
    pts = (np.concatenate([twice, rng.integers(0, N_PTS, k_obs - 2 * N_PTS)])
           if all_points_seen else rng.integers(1, N_PTS, k_obs))
    pts = rng.permutation(pts)
    sensor = rng.integers(0, N_SENSORS, k_obs)
    sensor_cols = N_SHARED + SENSOR_W * sensor[:, None] + np.arange(SENSOR_W)
    local = np.argsort(rng.random((k_obs, B)), axis=1)          # shuffled order within the point
    pt_cols = N_RED + B * pts[:, None] + (np.arange(B) if interleaved else local)
    parts = [(np.arange(N_SHARED), rng.standard_normal((k_obs, 2, N_SHARED))),
             (sensor_cols, rng.standard_normal((k_obs, 2, SENSOR_W))),
             (pt_cols, rng.standard_normal((k_obs, 2, B)))]
    order = (0, 2, 1) if interleaved else (0, 1, 2)
    block0 = ResidualBlock.from_parts(r0, [parts[i] for i in order])
    p1 = rng.choice(N_PTS, k1, replace=False)
    sub = np.stack([rng.choice(B, 2, replace=False) for _ in range(k1)])
    block1 = ResidualBlock(r1, N_RED + B * p1[:, None] + sub, rng.standard_normal((k1, 3, 2)))
    var = np.stack([rng.choice(np.arange(N_SHARED, N_RED), 2, replace=False) for _ in range(k2)])
    cols2 = np.concatenate([np.full((k2, 1), 1), var], axis=1)
    block2 = ResidualBlock(r2, cols2, rng.standard_normal((k2, 1, 3)))
    return BlockSparseJacobian(m, N_PAR, N_RED, B, [block0, block1, block2]), rng


def dense_from_blocks(J):
    """The dense Jacobian assembled group by group (independent of to_csr)."""
    D = np.zeros(J.shape)
    for blk in J.blocks:
        cols, vals = blk.cols, blk.values
        for g in range(blk.n_groups):
            for i, row in enumerate(blk.rows[g]):
                D[row, cols[g]] += vals[g, i]
    return D


@pytest.fixture(params=[14, 64], ids=["per-group-shuffled", "per-key-interleaved"])
def problem(request):
    # k = 14: U from per-group products, points' columns shuffled (expanded to the block);
    # k = 64: U from one product per distinct column set, parts (shared, point, sensor)
    k = request.param
    J, rng = random_problem(seed=k, k_obs=k, interleaved=k == 64)
    D = dense_from_blocks(J)
    assert np.linalg.matrix_rank(D) == N_PAR          # the checks below need a regular N
    return J, D, rng


def test_to_csr_matvec_gradient_and_column_norms_match_dense(problem):
    J, D, rng = problem
    assert np.array_equal(J.to_csr().toarray(), D)
    h, r = rng.standard_normal(N_PAR), rng.standard_normal(J.n_rows)
    assert np.allclose(J.matvec(h), D @ h, rtol=RTOL, atol=RTOL)
    assert np.allclose(J.gradient(r), D.T @ r, rtol=RTOL, atol=RTOL)
    assert np.allclose(J.column_norms(), np.linalg.norm(D, axis=0), rtol=RTOL)


def test_normal_equation_blocks_match_dense(problem):
    J, D, _ = problem
    N = D.T @ D
    ne = J.normal_equations()
    assert isinstance(ne, NormalEquations)
    assert np.allclose(ne.U, N[:N_RED, :N_RED], rtol=RTOL, atol=RTOL)
    for e in range(N_PTS):
        s = slice(N_RED + B * e, N_RED + B * (e + 1))
        assert np.allclose(ne.V[e], N[s, s], rtol=RTOL, atol=RTOL)
    assert np.allclose(ne.coupling().toarray(), N[:N_RED, N_RED:], rtol=RTOL, atol=RTOL)


def test_damped_solve_and_schur_complement_match_dense(problem):
    J, D, rng = problem
    N = D.T @ D
    ne = J.normal_equations()
    g = rng.standard_normal(N_PAR)
    for damping in (None, 0.3, rng.uniform(0, 2, N_PAR)):
        d = np.zeros(N_PAR) if damping is None else np.broadcast_to(damping, (N_PAR,))
        Nd = N + np.diag(d)
        h = ne.solve(g, damping)
        h_ref = np.linalg.solve(Nd, -g)
        assert np.allclose(h, h_ref, rtol=1e-8, atol=1e-8 * np.abs(h_ref).max())
        A, Bc, C = Nd[:N_RED, :N_RED], Nd[:N_RED, N_RED:], Nd[N_RED:, N_RED:]
        S_ref = A - Bc @ np.linalg.solve(C, Bc.T)
        assert np.allclose(ne.schur_complement(damping), S_ref, rtol=1e-9,
                           atol=1e-9 * np.abs(S_ref).max())


def test_covariances_match_the_dense_inverse(problem):
    J, D, _ = problem
    Ninv = np.linalg.inv(D.T @ D)
    ne = J.normal_equations()
    tol = 1e-8 * np.abs(Ninv).max()   # inverse of a random, moderately conditioned N
    assert np.allclose(ne.covariance_reduced(), Ninv[:N_RED, :N_RED], atol=tol)
    Cee = ne.covariance_elim_blocks()
    assert Cee.shape == (N_PTS, B, B)
    for e in range(N_PTS):
        s = slice(N_RED + B * e, N_RED + B * (e + 1))
        assert np.allclose(Cee[e], Ninv[s, s], atol=tol)
    for i, blk in enumerate(J.blocks):
        Q = ne.group_covariance(i)
        assert Q.shape == (blk.n_groups, blk.r_rows, blk.r_rows)
        for g in range(blk.n_groups):
            Jg = D[blk.rows[g]]
            assert np.allclose(Q[g], Jg @ Ninv @ Jg.T, atol=tol), (i, g)


def test_redundancy_numbers_sum_to_the_redundancy(problem):
    # sum of diag(I - J_g N^-1 J_g^T) over all rows = m - n (rows in no group count 1)
    J, _, _ = problem
    ne = J.normal_equations()
    used = sum(blk.n_groups * blk.r_rows for blk in J.blocks)
    h = sum(np.trace(ne.group_covariance(i), axis1=1, axis2=2).sum() for i in range(len(J.blocks)))
    assert used - h + (J.n_rows - used) == pytest.approx(J.n_rows - N_PAR, abs=1e-9)


def test_without_eliminated_blocks_the_solve_is_dense_cholesky():
    rng = np.random.default_rng(5)
    k = 40
    rows = np.arange(2 * k).reshape(k, 2)
    cols = np.stack([rng.choice(7, 4, replace=False) for _ in range(k)])
    block = ResidualBlock(rows, cols, rng.standard_normal((k, 2, 4)))
    J = BlockSparseJacobian(2 * k, 7, 7, 0, [block])
    D = J.to_csr().toarray()
    ne = J.normal_equations()
    assert J.n_elim_blocks == 0 and ne.V.shape == (0, 1, 1)
    g = rng.standard_normal(7)
    assert np.allclose(ne.solve(g, 0.1), np.linalg.solve(D.T @ D + 0.1 * np.eye(7), -g), rtol=1e-9)
    assert np.allclose(ne.covariance_reduced(), np.linalg.inv(D.T @ D), rtol=1e-8)
    Q = ne.group_covariance(0)
    assert np.allclose(Q[3], D[rows[3]] @ np.linalg.inv(D.T @ D) @ D[rows[3]].T, rtol=1e-8)


def test_structure_is_reused_for_new_values_and_rebuilt_for_new_columns():
    J, rng = random_problem(seed=3)
    blocks2 = [blk.with_values(*[rng.standard_normal(v.shape) for v in blk.part_values])
               for blk in J.blocks]
    J2 = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, blocks2, structure=J.structure)
    assert J2.structure is J.structure
    assert np.array_equal(J2.to_csr().toarray(), dense_from_blocks(J2))
    N2 = dense_from_blocks(J2).T @ dense_from_blocks(J2)
    assert np.allclose(J2.normal_equations().U, N2[:N_RED, :N_RED], rtol=RTOL, atol=RTOL)
    # equal (not identical) index arrays are recognised too
    b0 = J.blocks[0]
    copies = [(c.copy(), v) for c, v in zip(b0.part_cols, b0.part_values, strict=True)]
    same = ResidualBlock.from_parts(b0.rows.copy(), copies)
    J3 = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, [same, *J.blocks[1:]],
                             structure=J.structure)
    assert J3.structure is J.structure
    # other columns: a fresh analysis
    cols = b0.part_cols[1].copy()
    cols[0] = N_SHARED + (cols[0] - N_SHARED + SENSOR_W) % (N_SENSORS * SENSOR_W)   # other sensor
    moved = ResidualBlock.from_parts(b0.rows, [(b0.part_cols[0], b0.part_values[0]),
                                               (cols, b0.part_values[1]),
                                               (b0.part_cols[2], b0.part_values[2])])
    J4 = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, [moved, *J.blocks[1:]],
                             structure=J.structure)
    assert J4.structure is not J.structure
    D4 = dense_from_blocks(J4)
    assert np.allclose(J4.normal_equations().U, (D4.T @ D4)[:N_RED, :N_RED], rtol=RTOL, atol=RTOL)


def test_singular_reduced_system_raises_and_damping_regularises():
    rng = np.random.default_rng(2)
    k = 30
    rows = np.arange(k).reshape(k, 1)
    vals = rng.standard_normal((k, 1, 3))
    vals[:, :, 2] = 2.0 * vals[:, :, 1]                           # columns 1 and 2 are dependent
    J = BlockSparseJacobian(k, 3, 3, 0, [ResidualBlock(rows, np.tile([0, 1, 2], (k, 1)), vals)])
    ne = J.normal_equations()
    with pytest.raises(SingularSystemError,
                       match="reduced Schur complement is (singular|not positive)"):
        ne.covariance_reduced()
    with pytest.raises(SingularSystemError, match="reduced"):
        ne.solve(np.ones(3))
    assert np.all(np.isfinite(ne.solve(np.ones(3), 1e-3)))


def test_unobserved_eliminated_block_raises_unless_damped():
    J, rng = random_problem(seed=4, all_points_seen=False)
    # point 0 appears in neither block 0 (points 1..5 only) nor, possibly, block 1: drop block 1
    J = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, [J.blocks[0], J.blocks[2]])
    ne = J.normal_equations()
    with pytest.raises(SingularSystemError,
                       match="eliminated block 0 .* has no information") as err:
        ne.solve(np.zeros(N_PAR))
    assert err.value.where == "eliminated" and err.value.index == N_RED
    assert np.all(np.isfinite(ne.solve(rng.standard_normal(N_PAR), 1e-6)))


def test_bad_structures_are_rejected_with_the_reason():
    rows = np.arange(4).reshape(2, 2)
    v = np.ones((2, 2, 3))
    with pytest.raises(InputError, match="more than one group"):
        BlockSparseJacobian(4, 9, 3, 3, [ResidualBlock([[0, 1], [1, 2]], [[0, 3, 4]] * 2, v)])
    with pytest.raises(InputError, match="more than one block"):
        BlockSparseJacobian(4, 9, 3, 3, [ResidualBlock(rows, [[0, 3, 6], [1, 3, 4]], v)])
    with pytest.raises(InputError, match="position 1 is a reduced column in some groups"):
        BlockSparseJacobian(4, 9, 3, 3, [ResidualBlock(rows, [[0, 1, 4], [0, 3, 4]], v)])
    with pytest.raises(InputError, match=r"columns must lie in \[0, 9\)"):
        BlockSparseJacobian(4, 9, 3, 3, [ResidualBlock(rows, [[0, 1, 9], [0, 1, 2]], v)])
    with pytest.raises(InputError, match="repeats a column"):
        BlockSparseJacobian(4, 9, 3, 3, [ResidualBlock(rows, [[0, 0, 2], [0, 1, 2]], v)])
    with pytest.raises(InputError, match="do not form blocks of elim_block_size=4"):
        BlockSparseJacobian(4, 9, 3, 4, [ResidualBlock(rows, [[0, 1, 2]] * 2, v)])
    with pytest.raises(InputError, match=r"values must have shape \(2, 2, 3\)"):
        ResidualBlock(rows, [[0, 1, 2]] * 2, np.ones((2, 3, 3)))
    with pytest.raises(InputError, match="damping must be"):
        BlockSparseJacobian(4, 3, 3, 0, [ResidualBlock(rows, [[0, 1, 2]] * 2, v)]
                            ).normal_equations().solve(np.zeros(3), -1.0)


def test_covariances_match_the_dense_inverse_with_blocks_of_six():
    """Eliminated blocks of 6 (the exterior orientations when a bundle holds its targets fixed):
    the kernels' general block size, against the dense inverse."""
    rng = np.random.default_rng(11)
    n_red, b, n_blk, k = 4, 6, 5, 60
    n = n_red + b * n_blk
    blk_of = np.concatenate([np.arange(n_blk), rng.integers(0, n_blk, k - n_blk)])
    cols = np.concatenate([np.broadcast_to(np.arange(n_red), (k, n_red)),
                           n_red + b * blk_of[:, None] + np.arange(b)], axis=1)
    rows = ResidualBlock(np.arange(2 * k).reshape(k, 2), cols, rng.standard_normal((k, 2, n_red + b)))
    J = BlockSparseJacobian(2 * k, n, n_red, b, [rows])
    D = dense_from_blocks(J)
    Ninv = np.linalg.inv(D.T @ D)
    ne = J.normal_equations()
    tol = 1e-8 * np.abs(Ninv).max()
    assert np.allclose(ne.covariance_reduced(), Ninv[:n_red, :n_red], atol=tol)
    Cee = ne.covariance_elim_blocks()
    for e in range(n_blk):
        s = slice(n_red + b * e, n_red + b * (e + 1))
        assert np.allclose(Cee[e], Ninv[s, s], atol=tol)
    Q = ne.group_covariance(0)
    for g in range(k):
        Jg = D[2 * g:2 * g + 2]
        assert np.allclose(Q[g], Jg @ Ninv @ Jg.T, atol=tol), g


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_all_finite_sees_a_bad_number_in_any_part_combined_or_not(bad):
    J, _ = random_problem(seed=4)
    assert J.all_finite()
    b0 = J.blocks[0]
    for part in range(len(b0.part_values)):
        for combined in (False, True):
            vals = [v.copy() for v in b0.part_values]
            vals[part][-1, 1, -1] = bad
            glued = np.concatenate(vals, axis=2)
            views, at = [], 0                    # the parts as views of one array, as the bundle makes them
            for v in vals:
                views.append(glued[:, :, at:at + v.shape[2]])
                at += v.shape[2]
            blk = b0.with_values(*views, combined=glued) if combined else b0.with_values(*vals)
            J2 = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, [blk, *J.blocks[1:]], structure=J.structure)
            assert not J2.all_finite(), (part, combined)
    vals = [v.copy() for v in J.blocks[1].part_values]
    vals[0][0, 0, 0] = bad
    J3 = BlockSparseJacobian(J.n_rows, N_PAR, N_RED, B, [b0, J.blocks[1].with_values(*vals), J.blocks[2]],
                             structure=J.structure)
    assert not J3.all_finite()


def test_repeated_columns_across_parts_are_found():
    # the quick pre-check (_may_repeat_a_column) may only skip the full check when no group
    # repeats a column: against brute force on random parts, shared and per group
    from fieldcal.solver.blocksparse import _may_repeat_a_column

    rng = np.random.default_rng(7)
    for _ in range(400):
        k, n = int(rng.integers(1, 6)), int(rng.integers(4, 12))
        parts = []
        for _ in range(int(rng.integers(1, 4))):
            c = int(rng.integers(1, 4))
            parts.append(rng.choice(n, c, replace=False) if rng.random() < 0.4
                         else np.stack([rng.choice(n, c, replace=False) for _ in range(k)]))
        full = np.concatenate([np.broadcast_to(p, (k, p.shape[-1])) for p in parts], axis=1)
        repeats = any(len(set(row)) < len(row) for row in full.tolist())
        if repeats:
            assert _may_repeat_a_column(parts, n)
    # and through the Jacobian: a group's own column that is also a shared one
    rows = np.arange(4).reshape(2, 2)
    blk = ResidualBlock.from_parts(rows, [(np.array([0, 1]), np.ones((2, 2, 2))),
                                          (np.array([[3], [1]]), np.ones((2, 2, 1)))])
    with pytest.raises(InputError, match=r"group 1 repeats a column \(\[0, 1, 1\]\)"):
        BlockSparseJacobian(4, 6, 3, 3, [blk])


def test_two_row_gradient_and_matvec_loops_sum_in_the_generic_order():
    # the kernels' two-row paths (image points) keep the generic loop's order of the sums:
    # bit-identical J^T r and J h (the generic loop here, in plain Python)
    from fieldcal.solver import blocksparse_kernels as K

    gr, mv = K.gradient(), K.matvec()
    if gr is None:
        pytest.skip("no compiled kernels")
    rng = np.random.default_rng(11)
    k, c, n = 50, 7, 30
    v = rng.standard_normal((k, 2, c)) * 10.0 ** rng.integers(-8, 8, (k, 2, c))
    rows = rng.permutation(2 * k).reshape(k, 2)
    cols = np.stack([rng.choice(n, c, replace=False) for _ in range(k)])
    res, h = rng.standard_normal(2 * k), rng.standard_normal(n)
    g_ref, out_ref = np.zeros(n), np.zeros(2 * k)
    for gi in range(k):
        for j in range(c):
            s = 0.0
            for q in range(2):
                s += v[gi, q, j] * res[rows[gi, q]]
            g_ref[cols[gi, j]] += s
        for q in range(2):
            s = 0.0
            for j in range(c):
                s += v[gi, q, j] * h[cols[gi, j]]
            out_ref[rows[gi, q]] = s
    g, out = np.zeros(n), np.zeros(2 * k)
    gr(v, rows, cols, res, g)
    mv(v, rows, cols, h, out)
    assert np.array_equal(g, g_ref) and np.array_equal(out, out_ref)


def test_dense_covariance_is_made_once_and_handed_out_as_copies(problem):
    J, D, _ = problem
    ne = J.normal_equations()
    a = ne.covariance_dense()
    assert np.allclose(a, np.linalg.inv(D.T @ D), rtol=1e-8, atol=1e-10)
    a[:] = 0.0                                   # a caller's change does not reach the next caller
    b = ne.covariance_dense()
    assert np.allclose(b, np.linalg.inv(D.T @ D), rtol=1e-8, atol=1e-10)
    assert b is not ne.covariance_dense() and np.array_equal(b, ne.covariance_dense())
