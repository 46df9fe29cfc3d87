"""The LMQN / LM engine on problems with known minima, against SciPy's least_squares."""

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.solver import lsq
from fieldcal.solver.blocksparse import BlockSparseJacobian, ResidualBlock, SingularSystemError
from fieldcal.solver.lsq import STATUS_MESSAGES, _CompactBFGS


class Dense:
    """A small problem with a dense Jacobian: one group over all rows and columns."""

    def __init__(self, fun, jac, m, n):
        self.fun, self.jac, self.m, self.n = fun, jac, m, n
        self.rows, self.cols = np.arange(m)[None, :], np.arange(n)[None, :]
        self.calls = 0

    def evaluate(self, x, jacobian=True):
        self.calls += 1
        r = self.fun(np.asarray(x, float))
        if not jacobian:
            return r, None
        block = ResidualBlock(self.rows, self.cols, self.jac(np.asarray(x, float))[None])
        return r, BlockSparseJacobian(self.m, self.n, self.n, 0, [block])


def madsen(lam, shift=2.0):
    """Madsen et al. (2004) example 3.2/3.12, shifted: r = (t + 1, lam t^2 + t - 1), t = x - shift.

    The minimum is x = shift with F = 1 for |lam| < 1; Gauss-Newton (and LM) converge only
    linearly there, at rate |lam|: the non-zero residual case the hybrid is made for.
    """
    def fun(x):
        t = x[0] - shift
        return np.array([t + 1.0, lam * t * t + t - 1.0])

    def jac(x):
        return np.array([[1.0], [2.0 * lam * (x[0] - shift) + 1.0]])

    return Dense(fun, jac, 2, 1)


ROSENBROCK = Dense(lambda x: np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]]),
                   lambda x: np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]]), 2, 2)


class Network:
    """A toy structure like a bundle, not a camera: "sensors" range "points".

    Two global parameters (range scale ``a`` and bias ``c``), ``S`` sensors with 3-D
    positions (reduced), ``P`` points with 3-D positions (eliminated, b = 3), each point
    measured by ``per_point`` sensors: range ``a |X - p| + c`` and the scaled elevation sine
    ``10 (X - p)_z / |X - p|`` (two rows per group); every point also has a survey prior
    ``(X - X_prior) / sigma_prior`` (three rows). ``col_scale`` multiplies parameters by
    constants (to test the solver's scaling); ``extra`` appends unobserved global columns;
    ``offset`` [m] moves every position (a national grid instead of a local frame).
    """

    def __init__(self, seed=0, S=5, P=30, per_point=4, noise=0.0, sigma_prior=0.5, col_scale=None,
                 extra=0, offset=0.0):
        rng = np.random.default_rng(seed)
        self.S, self.P, self.extra = S, P, extra
        sensors = rng.uniform(-20, 20, (S, 3))
        sensors[:, 2] = rng.uniform(-5, 15, S)
        points = rng.uniform(0, 10, (P, 3))
        sensors, points = sensors + offset, points + offset      # the same network elsewhere
        self.obs_s = np.concatenate([rng.choice(S, per_point, replace=False) for _ in range(P)])
        self.obs_p = np.repeat(np.arange(P), per_point)
        self.k = k = len(self.obs_s)
        self.n_red = 2 + extra + 3 * S
        self.n = self.n_red + 3 * P
        self.m = 2 * k + 3 * P
        self.sigma_prior = sigma_prior
        self.scale = np.ones(self.n) if col_scale is None else np.asarray(col_scale, float)
        x_true = np.concatenate([[1.02, 0.3], np.zeros(extra), sensors.ravel(), points.ravel()])
        self.x_true = x_true * self.scale
        self.z, self.prior = np.zeros(2 * k), points.ravel()
        exact = self.evaluate(self.x_true, False)[0][:2 * k]
        self.z = exact + noise * rng.standard_normal(2 * k)
        self.prior = points.ravel() + noise * sigma_prior * rng.standard_normal(3 * P)
        g0 = np.arange(2 + extra)
        self.obs_block = ResidualBlock.from_parts(np.arange(2 * k).reshape(k, 2), [
            (g0, np.zeros((k, 2, 2 + extra))),
            (2 + extra + 3 * self.obs_s[:, None] + np.arange(3), np.zeros((k, 2, 3))),
            (self.n_red + 3 * self.obs_p[:, None] + np.arange(3), np.zeros((k, 2, 3)))])
        self.prior_rows = 2 * k + np.arange(3 * P).reshape(P, 3)
        self.prior_cols = self.n_red + np.arange(3 * P).reshape(P, 3)
        self.structure = None

    def evaluate(self, x, jacobian=True):
        x = np.asarray(x, float) / self.scale
        a, c, e = x[0], x[1], self.extra
        p = x[2 + e:self.n_red].reshape(-1, 3)[self.obs_s]
        X = x[self.n_red:].reshape(-1, 3)
        u = X[self.obs_p] - p
        rho = np.linalg.norm(u, axis=1)
        r = np.concatenate([np.stack([a * rho + c, 10 * u[:, 2] / rho], 1).ravel() - self.z,
                            (X.ravel() - self.prior) / self.sigma_prior])
        if not jacobian:
            return r, None
        k = self.k
        d_glob = np.zeros((k, 2, 2 + e))
        d_glob[:, 0, 0], d_glob[:, 0, 1] = rho, 1.0
        d_X = np.empty((k, 2, 3))
        d_X[:, 0] = a * u / rho[:, None]
        d_X[:, 1] = -10 * u[:, 2:3] * u / rho[:, None] ** 3
        d_X[:, 1, 2] += 10 / rho
        s = self.scale
        obs = self.obs_block.with_values(
            d_glob / s[:2 + e],
            -d_X / s[self.obs_block.part_cols[1]][:, None, :],
            d_X / s[self.obs_block.part_cols[2]][:, None, :])
        prior = ResidualBlock(self.prior_rows, self.prior_cols,
                              np.eye(3) / self.sigma_prior / s[self.prior_cols][:, None, :])
        J = BlockSparseJacobian(self.m, self.n, self.n_red, 3, [obs, prior],
                                structure=self.structure)
        self.structure = J.structure
        return r, J


def rel_diff(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / np.linalg.norm(b)


def test_network_jacobian_matches_central_differences():
    net = Network(noise=0.05)
    x = net.x_true + 0.1 * np.random.default_rng(1).standard_normal(net.n)
    D = net.evaluate(x)[1].to_csr().toarray()
    num = np.empty_like(D)
    for j in range(net.n):
        e = np.zeros(net.n)
        e[j] = 1e-6
        num[:, j] = (net.evaluate(x + e, False)[0] - net.evaluate(x - e, False)[0]) / 2e-6
    assert np.abs(num - D).max() < 1e-6   # central differences: O(h^2) ~ 1e-12 plus round-off 1e-10


@pytest.mark.parametrize("method", ["lm", "lmqn"])
def test_zero_residual_network_converges_to_the_truth(method):
    net = Network(noise=0.0)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    res = lsq.solve(net, x0, method=method)
    assert res.success and res.status == 1, res.message
    assert np.abs(res.x - net.x_true).max() < 1e-8      # coordinates ~10: 1e-9 relative
    assert res.cost < 1e-15
    assert res.iterations < 15                           # Gauss-Newton-like: quadratic at the end


@pytest.mark.parametrize("noise", [0.05, 3.0])
def test_both_methods_and_scipy_agree_on_a_noisy_network(noise):
    net = Network(noise=noise)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    ref = lsq.scipy_reference(net, x0)
    assert ref.success
    for method in ("lm", "lmqn"):
        res = lsq.solve(net, x0, method=method)
        assert res.success, (method, res.message)
        assert rel_diff(res.x, ref.x) < 1e-6, method
        assert res.cost == pytest.approx(ref.cost, rel=1e-10)
        assert res.cost > 0.1                           # a genuinely non-zero residual
        assert res.evaluations == res.iterations + 1 - (res.status == 2)


def test_rosenbrock_converges_to_one_one():
    for method in ("lm", "lmqn"):
        res = lsq.solve(ROSENBROCK, [-1.2, 1.0], method=method)
        assert res.status == 1, res.message
        # eps1 = 1e-10 on the scaled gradient g/d, d = (24, 10), leaves |x - 1| ~ 1e-9
        assert np.abs(res.x - 1.0).max() < 1e-8
        assert res.qn_iterations == 0                  # zero residual: never leaves LM


def test_lmqn_switches_to_qn_and_beats_linear_lm_on_a_large_residual_problem():
    prob = madsen(0.7)
    lm = lsq.solve(prob, [5.0], method="lm")
    qn = lsq.solve(prob, [5.0], method="lmqn")
    ref = lsq.scipy_reference(prob, [5.0])
    for res in (lm, qn):
        assert res.success, res.message
        assert rel_diff(res.x, [2.0]) < 1e-6 and res.cost == pytest.approx(1.0, rel=1e-12)
    assert rel_diff(ref.x, [2.0]) < 1e-6
    assert lm.qn_iterations == 0
    assert qn.qn_iterations > 0
    first_qn = next(h.k for h in qn.history if h.method == "qn")
    # the switch needs three successful LM steps with ||g||_inf < 0.02 F
    assert first_qn >= 4
    assert all(h.method == "lm" and h.accepted for h in qn.history[first_qn - 4:first_qn - 1])
    assert qn.iterations < lm.iterations / 2


@pytest.mark.parametrize("problem", ["madsen", "network"])
def test_queued_bfgs_updates_are_the_updates_made_at_once(monkeypatch, problem):
    # the updates wait for a QN step (at most _MAX_PENDING_UPDATES); with none allowed to
    # wait every update is made at its iteration, as the book does: the same iterations, bit for bit
    if problem == "madsen":
        prob, x0 = madsen(0.7), [5.0]
    else:
        prob = Network(noise=5.0)
        x0 = prob.x_true + 0.5 * np.random.default_rng(2).standard_normal(prob.n)
    queued = lsq.solve(prob, x0, method="lmqn")
    assert queued.qn_iterations > 0
    monkeypatch.setattr(lsq, "_MAX_PENDING_UPDATES", 0)
    at_once = lsq.solve(prob, x0, method="lmqn")
    assert np.array_equal(queued.x, at_once.x)
    assert [(h.method, h.F, h.mu, h.delta, h.accepted) for h in queued.history] == \
        [(h.method, h.F, h.mu, h.delta, h.accepted) for h in at_once.history]
    monkeypatch.setattr(lsq, "_MAX_PENDING_UPDATES", 1)        # the oldest computed when one more waits
    one = lsq.solve(prob, x0, method="lmqn")
    assert np.array_equal(queued.x, one.x) and len(one.history) == len(queued.history)


def test_compact_bfgs_equals_the_dense_bfgs_sequence():
    rng = np.random.default_rng(0)
    n = 8
    A = rng.standard_normal((n, n))
    A = A @ A.T + n * np.eye(n)
    B, bfgs = np.eye(n), _CompactBFGS(n, memory=50)
    updates = 0
    for i in range(15):
        s = rng.standard_normal(n)
        y = (-1.0 if i % 4 == 3 else 1.0) * A @ s + rng.standard_normal(n)   # s^T y < 0: skipped
        if s @ y > 0:
            Bs = B @ s
            B = B + np.outer(y, y) / (y @ s) - np.outer(Bs, Bs) / (s @ Bs)
            updates += 1
        bfgs.update(s, y)
    assert 0 < updates < 15 and len(bfgs.S) == updates
    g = rng.standard_normal(n)
    assert np.allclose(bfgs.apply_inverse(g), np.linalg.solve(B, g), rtol=1e-10, atol=1e-12)


def _decided_by_the_problem(history, rel=1e-9):
    """How many leading iterations round-off cannot decide: every trial changes F by more than
    ``rel F`` (F is exact to ~1e-16 F, so the gain ratio rho is exact to ~1e-7 or better)."""
    for i in range(1, len(history)):
        F0, trial = history[i - 1].F, history[i].F_trial    # F before iteration i, at its trial
        if not np.isfinite(trial) or abs(F0 - trial) <= rel * F0:
            return i
    return len(history)


@pytest.mark.parametrize("method", ["lm", "lmqn"])
def test_scaling_makes_the_iterations_independent_of_parameter_units(method):
    """Parameters in units 1e-12, 1e8 and 1e3 times others take the same iterates: compared
    step by step for as long as the problem (not round-off) decides the steps, then the
    solutions. (The tail near the optimum, where F changes in its last digits, is decided
    by round-off and may take a different number of rejected steps on another machine.)"""
    scale = np.ones(Network().n)
    scale[0], scale[1], scale[5] = 1e-12, 1e8, 1e3
    plain = Network(noise=3.0)
    scaled = Network(noise=3.0, col_scale=scale)
    x0 = plain.x_true + 0.5 * np.random.default_rng(2).standard_normal(plain.n)
    a, b = lsq.solve(plain, x0, method=method), lsq.solve(scaled, x0 * scale, method=method)
    assert a.success and b.success
    assert a.iterations < 100 and b.iterations < 100        # a bound, not a count round-off decides
    n = _decided_by_the_problem(a.history)
    assert n >= 12                     # F falls by > 1e-9 F on each of the first ~16 steps here
    for ha, hb in zip(a.history[:n], b.history[:n], strict=True):
        assert (ha.method, ha.accepted) == (hb.method, hb.accepted), ha.k
        assert ha.F == pytest.approx(hb.F, rel=1e-12, abs=0)
        assert ha.rho == pytest.approx(hb.rho, rel=1e-5)      # dF / dL, dF exact to ~1e-7 here
        assert ha.mu == pytest.approx(hb.mu, rel=1e-6)
    # both stop within their tolerances of the same optimum (1e-8 of the solution's size)
    assert rel_diff(b.x / scale, a.x) < 1e-7
    ref = lsq.scipy_reference(plain, x0)
    assert rel_diff(a.x, ref.x) < 1e-7


def test_status_codes_and_messages():
    net = Network(noise=0.05)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    res = lsq.solve(net, x0, max_iter=2)
    assert (res.status, res.iterations, res.success) == (0, 2, False)
    assert res.message == STATUS_MESSAGES[0] == "the maximum number of iterations was reached"
    res = lsq.solve(net, x0, eps1=0.0)                 # the gradient never reaches exactly 0
    assert res.status == 2 and res.message.startswith("the step is small")
    res = lsq.solve(net, x0)
    assert res.status == 1 and res.message.startswith("the gradient is small")
    seen = []
    res = lsq.solve(net, x0, callback=lambda it: seen.append(it.k) or it.k == 2)
    assert (res.status, res.iterations, seen) == (3, 2, [1, 2])
    assert res.message == "stopped by the callback"
    res = lsq.solve(net, net.x_true, max_iter=0)
    assert res.status == 0 and res.iterations == 0 and res.evaluations == 1


class FailingTrials:
    """Wraps a problem; the evaluations listed in ``bad`` (1-based) return NaN residuals."""

    def __init__(self, problem, bad):
        self.problem, self.bad, self.calls = problem, set(bad), 0

    def evaluate(self, x, jacobian=True):
        self.calls += 1
        r, J = self.problem.evaluate(x, jacobian)
        return (np.full_like(r, np.nan) if self.calls in self.bad else r), J


def test_a_non_finite_trial_point_is_a_rejected_step():
    net = Network(noise=0.05)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    clean = lsq.solve(net, x0)
    res = lsq.solve(FailingTrials(net, bad=[2, 3]), x0)
    h = res.history
    assert not h[0].accepted and not h[1].accepted and np.isnan(h[0].F_trial)
    assert h[1].mu == pytest.approx(2 * h[0].mu) and h[2].mu == pytest.approx(8 * h[0].mu)
    assert h[2].accepted
    assert res.success and rel_diff(res.x, clean.x) < 1e-9


def test_every_trial_failing_ends_with_a_small_step_not_a_crash():
    prob = FailingTrials(ROSENBROCK, bad=range(2, 10_000))
    res = lsq.solve(prob, [-1.2, 1.0], max_iter=500)
    assert res.status == 2 and res.iterations < 20       # mu grows as 2^(k^2/2): h shrinks fast
    assert np.array_equal(res.x, [-1.2, 1.0]) and not any(h.accepted for h in res.history)


def test_unidentifiable_parameter_converges_but_its_covariance_is_singular():
    net = Network(noise=0.05, extra=1)              # column 2: no residual depends on it
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    res = lsq.solve(net, x0)
    assert res.success
    assert res.x[2] == x0[2]                        # a zero column is never moved
    with pytest.raises(SingularSystemError, match="reduced parameter 2 has no information"):
        lsq.covariance(res)


def test_covariance_at_the_solution_matches_dense():
    net = Network(noise=0.05)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    res = lsq.solve(net, x0)
    cov = lsq.covariance(res)
    D = res.jac.to_csr().toarray()
    Ninv = np.linalg.inv(D.T @ D)
    assert np.allclose(cov.reduced, Ninv[:net.n_red, :net.n_red], rtol=1e-8, atol=1e-12)
    s = slice(net.n_red + 12, net.n_red + 15)                  # point 4
    assert np.allclose(cov.elim_blocks[4], Ninv[s, s], rtol=1e-8, atol=1e-12)
    assert res.sigma0 == pytest.approx(np.sqrt(2 * res.cost / (net.m - net.n)))


def test_bad_arguments_are_rejected():
    with pytest.raises(InputError, match="method must be 'lmqn' or 'lm'"):
        lsq.solve(ROSENBROCK, [0.0, 0.0], method="gn")
    with pytest.raises(InputError, match="not finite"):
        lsq.solve(FailingTrials(ROSENBROCK, bad=[1]), [0.0, 0.0])
    with pytest.raises(InputError, match="x0 must be finite"):
        lsq.solve(ROSENBROCK, [np.nan, 0.0])
    with pytest.raises(InputError, match="eps1 must be"):
        lsq.solve(ROSENBROCK, [0.0, 0.0], eps1=-1.0)


def test_a_warm_start_with_the_returned_damping_reaches_the_cold_solution():
    """A solve that starts at a previous solution with that solution's ``mu`` as ``tau`` (the
    adjustment's blunder rounds) ends where a cold start from far away ends."""
    net = Network(noise=0.05)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    cold = lsq.solve(net, x0, tau=1e-6, sigma_tol=1e-6)
    assert cold.success and 0.0 < cold.mu < 1e-6          # LM lowered its damping on the way
    start = cold.x + 1e-3 * np.random.default_rng(4).standard_normal(net.n)   # a nearby start
    warm = lsq.solve(net, start, tau=cold.mu, sigma_tol=1e-6)
    ref = lsq.scipy_reference(net, x0)
    assert warm.success, warm.message
    assert rel_diff(warm.x, ref.x) < 1e-6 and rel_diff(cold.x, ref.x) < 1e-6
    assert warm.cost == pytest.approx(ref.cost, rel=1e-10)


def test_a_negligible_lm_step_ends_the_solve_without_being_evaluated():
    """Status 5 (sigma_tol): the last LM step is below the tolerance and is neither evaluated nor
    taken; the point returned is within sigma_tol standard deviations of the optimum."""
    net = Network(noise=0.05)
    x0 = net.x_true + 0.5 * np.random.default_rng(2).standard_normal(net.n)
    res = lsq.solve(net, x0, method="lm", sigma_tol=1e-3)
    assert res.status == 5, res.message
    last = res.history[-1]
    assert not last.accepted and np.isnan(last.F_trial)
    assert res.evaluations == res.iterations                # x0, then one per iteration but the last
    ref = lsq.scipy_reference(net, x0)
    cov = lsq.covariance(res)
    sigma = np.sqrt(np.r_[np.diag(cov.reduced), np.einsum("kii->ki", cov.elim_blocks).ravel()]) * res.sigma0
    assert np.max(np.abs(res.x - ref.x) / sigma) < 1e-3
