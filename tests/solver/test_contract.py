"""One contract for every least-squares solver: LMQN, LM and SciPy's least_squares (reference).

Each solver is run through the same adapter on the same problems (the ``Network`` toy of
``test_lsq.py``: two global parameters, sensors, eliminated points with survey priors, and
Rosenbrock) and must meet the same promises: the truth of a zero-residual problem, one
optimum of a noisy one (zero gradient, and the same for all), independence of the units of
the parameters and of where their origin lies (a national grid, 1e6 m, instead of a local
frame), and a stop within a bounded number of evaluations.
"""

import numpy as np
import pytest

from fieldcal.solver import lsq
from tests.solver.test_lsq import ROSENBROCK, Network, rel_diff

SOLVERS = ["lmqn", "lm", "scipy"]


def run(solver, problem, x0):
    """``(x, cost, evaluations)`` of one solver; every solver must say it converged."""
    if solver == "scipy":
        ref = lsq.scipy_reference(problem, x0)
        assert ref.success, ref.message
        return ref.x, float(ref.cost), int(ref.nfev)
    res = lsq.solve(problem, x0, method=solver)
    assert res.success, res.message
    return res.x, res.cost, res.evaluations


def start(net, seed=2, spread=0.5):
    return net.x_true + spread * np.random.default_rng(seed).standard_normal(net.n)


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_zero_residual_problem_gives_the_truth(solver):
    net = Network(noise=0.0)
    x, cost, nfev = run(solver, net, start(net))
    assert np.abs(x - net.x_true).max() < 1e-8        # positions ~10 m: 1e-9 relative
    assert cost < 1e-15
    assert nfev < 100


@pytest.mark.parametrize("solver", SOLVERS)
def test_rosenbrock_gives_one_one(solver):
    x, cost, nfev = run(solver, ROSENBROCK, np.array([-1.2, 1.0]))
    assert np.abs(x - 1.0).max() < 1e-8 and cost < 1e-15 and nfev < 200


@pytest.fixture(scope="module")
def noisy_optimum():
    """The optimum of the noisy network by LMQN, LM and SciPy (computed once for the module)."""
    net = Network(noise=3.0)
    x0 = start(net)
    return net, x0, {s: run(s, net, x0) for s in SOLVERS}


@pytest.mark.parametrize("solver", SOLVERS)
def test_every_solver_reaches_the_same_optimum_with_zero_gradient(solver, noisy_optimum):
    net, _, out = noisy_optimum
    x, cost, _ = out[solver]
    r, J = net.evaluate(x)
    g = J.gradient(r) / J.column_norms()               # the gradient in scaled variables
    assert np.abs(g).max() < 1e-5 * np.sqrt(2 * cost)  # stationary: |J_z^T r| << |r|
    for other, (xo, co, _) in out.items():
        assert rel_diff(x, xo) < 1e-7, other            # one optimum, 1e-7 of its size
        assert cost == pytest.approx(co, rel=1e-10), other
    assert cost > 100.0                                 # a large-residual problem: 3 sigma noise


@pytest.mark.parametrize("solver", SOLVERS)
def test_the_units_of_the_parameters_do_not_matter(solver, noisy_optimum):
    net, x0, out = noisy_optimum
    scale = np.ones(net.n)
    scale[0], scale[1], scale[5] = 1e-12, 1e8, 1e3
    x, _, _ = run(solver, Network(noise=3.0, col_scale=scale), x0 * scale)
    assert rel_diff(x / scale, out[solver][0]) < 1e-7


@pytest.mark.parametrize("solver", SOLVERS)
def test_the_origin_of_the_coordinates_does_not_matter(solver, noisy_optimum):
    """The same network 1e6 m away (a national grid or UTM): the same solution, shifted."""
    net, x0, out = noisy_optimum
    far = Network(noise=3.0, offset=1e6)
    shift = far.x_true - net.x_true                    # 1e6 on every position, 0 on a and c
    x, cost, nfev = run(solver, far, x0 + shift)
    # positions ~10 m from their origin, held to 1e-7 of that (round-off at 1e6 m is ~1e-10 m)
    assert np.abs((x - shift) - out[solver][0]).max() < 1e-6
    assert cost == pytest.approx(out[solver][1], rel=1e-8)
    assert nfev < 200
