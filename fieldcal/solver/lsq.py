r"""The least-squares engine: hybrid Levenberg-Marquardt / quasi-Newton (LMQN) and plain LM.

Minimise ``F(x) = 1/2 ||r(x)||^2`` for a *problem*: any object with a method
``evaluate(x, jacobian: bool) -> (r (m,), BlockSparseJacobian | None)``. The engine knows
nothing about cameras; the normal equations are solved by
:class:`fieldcal.solver.blocksparse.NormalEquations` (Schur complement over eliminated blocks).

Method (Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems",
2nd ed., IMM DTU 2004, section 3.5, Algorithms 3.16 and 3.17; METHODS.md part A)
-----------------------------------------------------------------------------------
Notation: ``g = F'(x) = J^T r``, ``||.||`` the 2-norm, ``||.||_inf`` the max-norm.

Scaled variables. Everything below runs in the variables ``z = D x`` with ``D = diag(d)``,
``d_j`` the norm of column ``j`` of ``J(x0)`` (1 for a zero column), so that parameters of
wildly different magnitudes (1e2 mm next to 1e-12 mm^-6) are equally conditioned. In
``z``: ``J_z = J D^-1``, ``g_z = D^-1 g``, a step ``h_z = D h``. The damping ``mu I``, the
BFGS matrix ``B`` (starting from ``I``), the trust radius ``Delta`` and the stopping tests
all live in ``z``. ``(J_z^T J_z + mu I) h_z = -g_z`` is ``(J^T J + mu D^2) h = -g``, which is
what is handed to the normal equations.

LM step (Algorithm 3.16). Solve ``(J^T J + mu I) h = -g``. The gain ratio is
``rho = (F(x) - F(x + h)) / (L(0) - L(h))`` with ``L(0) - L(h) = 1/2 h^T (mu h - g)``.
If ``rho > 0`` the step is accepted and ``mu := mu max(1/3, 1 - (2 rho - 1)^3)``,
``nu := 2``; otherwise ``mu := mu nu``, ``nu := 2 nu``. ``mu0 = tau max(diag(J^T J))``.

Switch to QN (3.17). After three consecutive successful LM steps with
``||F'(x_new)||_inf < 0.02 F(x_new)`` (the residual is not going to zero and LM is only
linearly convergent) the method becomes QN, with ``Delta := max(1.5 eps2 (||x|| + eps2),
||h||/5)``.

QN step (3.17). Solve ``B h = -g`` and clip ``h`` to ``||h|| <= Delta``. The model is
``L(h) = F + h^T g + 1/2 h^T B h``; with ``rho`` as above ``Delta := Delta/2`` if
``rho < 0.25`` and ``Delta := max(Delta, 3 ||h||)`` if ``rho > 0.75``. The step is taken
("better") if ``F(x_new) < F(x)``, or ``F(x_new) <= (1 + delta) F(x)`` and the gradient
decreased (``delta = sqrt(machine eps)``). When ``||F'(x_new)||_inf >= ||F'(x)||_inf`` the
method goes back to LM (with the current ``mu``).

BFGS update, on every iteration (LM and QN, accepted or not) at the trial point, with
``h = x_new - x`` and ``y = J_new^T J_new h + (J_new - J)^T r(x_new)`` (the book's choice,
which is exact for the Gauss-Newton part of the Hessian), when ``h^T y > 0``. ``B`` is never
stored: the compact representation of Byrd, Nocedal & Schnabel (1994, Theorem 2.2, for
``H = B^-1`` with ``H0 = I``) gives ``H g`` from the stored pairs in ``O(n k)``::

    H g = g + S R^-T ((D + Y^T Y) R^-1 S^T g - Y^T g) - Y R^-1 S^T g

with ``S = [s_i]``, ``Y = [y_i]`` (n, k), ``R = triu(S^T Y)``, ``D = diag(S^T Y)``. With all
pairs kept this is exactly the book's dense ``B``; more than ``memory`` (default 50) pairs
drop the oldest (then it is L-BFGS). ``h^T y > 0`` is tested as
``h^T y > eps ||h|| ||y||``, which differs from ``> 0`` only within round-off. The updates
are computed when a QN step needs ``B`` (up to :data:`_MAX_PENDING_UPDATES` of them wait, in
order, with the Jacobians they need): the same pairs in the same order as updating at once,
without the three products per iteration (``J_new h``, ``J_new^T``, ``J^T r_new``) in the
many solves that end without a QN step.

The actual reduction ``F(x) - F(x_new)`` is computed as ``1/2 (r - r_new)^T (r + r_new)``,
not as the difference of two large sums, so that near the optimum of a large-residual
problem a genuine decrease is not lost to round-off in ``F``.

Stopping. ``||g||_inf <= eps1`` (status 1), ``||h|| <= eps2 (||r|| + eps2)`` (status 2), or
``max_iter`` iterations (status 0); all in scaled variables. The step test departs from
the book's ``eps2 (||x|| + eps2)``: ``||x||`` depends on where the origin of the parameters
lies (a camera centre in UTM coordinates, 5e5 m, makes every step "small"), whereas
``J_z`` has unit columns, so ``h_z`` is in the units of the residuals and ``||r||`` is the
scale-free yardstick. Optionally (``ftol``, ``sigma_tol``) a step whose predicted decrease
is negligible ends the iteration (status 5): ``L(0) - L(h) <= ftol F``, or
``<= sigma_tol^2 F / (m - n)``, i.e. (``L(0) - L(h) ~ 1/2 ||J h||^2``) the step is below
``sigma_tol`` a-posteriori standard deviations in the metric of the normal matrix: a
statistical tolerance that depends neither on units nor on origins. An LM step found
negligible is not taken (nor evaluated: the result is the point where it was computed, within
the tolerance of the optimum); a QN step is tested once it has been accepted. A trial point whose
residuals or Jacobian are not finite is a rejected step (like SciPy), as is an LM system
the Cholesky factorisation finds singular (the damping grows).

``method="lm"`` runs the same loop with the QN branch disabled (Algorithm 3.16).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from fieldcal.errors import InputError
from fieldcal.solver.blocksparse import BlockSparseJacobian, NormalEquations, SingularSystemError

__all__ = [
    "STATUS_MESSAGES",
    "IterationRecord",
    "LsqResult",
    "Covariance",
    "solve",
    "covariance",
    "scipy_reference",
]

STATUS_MESSAGES: dict[int, str] = {
    0: "the maximum number of iterations was reached",
    1: "the gradient is small: ||g||_inf <= eps1 (scaled variables)",
    2: "the step is small: ||h|| <= eps2 (||r|| + eps2) (scaled variables)",
    3: "stopped by the callback",
    4: "no acceptable step: the damping parameter overflowed",
    5: "the predicted decrease of the cost is negligible: L(0) - L(h) <= max(ftol, sigma_tol^2 / (m - n)) F(x)",
}
"""The solver's status codes and their messages (``LsqResult.status``/``.message``)."""

_SWITCH_RATIO = 0.02        # book (3.14): LM -> QN when ||F'||_inf < 0.02 F
_SWITCH_COUNT = 3           # ... on three consecutive successful LM steps
_DELTA = np.sqrt(np.finfo(float).eps)   # QN acceptance slack (book: a small delta)
_MU_MAX = 1e300


@dataclass(frozen=True)
class IterationRecord:
    """One iteration of :func:`solve`.

    Attributes
    ----------
    k : int
        Iteration number (1-based).
    method : str
        ``"lm"`` or ``"qn"``: the step that was tried.
    F : float
        The cost at the current point after the iteration.
    F_trial : float
        The cost at the trial point (``nan`` when not finite or not evaluated).
    mu : float
        The LM damping the step used (scaled variables).
    delta : float
        The QN trust radius the step used (``nan`` for LM steps).
    step_norm : float
        ``||h||`` in scaled variables (``nan`` when no step was computed).
    rho : float
        The gain ratio (``nan`` when not computed).
    grad_inf : float
        ``||g||_inf`` at the current point after the iteration (scaled variables).
    accepted : bool
        Whether ``x`` moved to the trial point.
    """

    k: int
    method: str
    F: float
    F_trial: float
    mu: float
    delta: float
    step_norm: float
    rho: float
    grad_inf: float
    accepted: bool


@dataclass
class LsqResult:
    """The result of :func:`solve`.

    Attributes
    ----------
    x : (n,) ndarray
        The solution.
    r : (m,) ndarray
        Residuals at ``x``.
    jac : BlockSparseJacobian
        The Jacobian at ``x``.
    cost : float
        ``F(x) = 1/2 r^T r``.
    gradient : (n,) ndarray
        ``J^T r`` at ``x`` (unscaled).
    grad_inf : float
        ``||D^-1 J^T r||_inf``, the gradient in scaled variables (the stopping test).
    scale : (n,) ndarray
        ``d``: the variable scaling (column norms of ``J(x0)``, zero columns 1).
    iterations, evaluations : int
        Iterations done, and calls of ``problem.evaluate``.
    status : int
        A key of :data:`STATUS_MESSAGES`; 1 and 2 are convergence.
    message : str
    method : str
        ``"lmqn"`` or ``"lm"``.
    history : list of IterationRecord
    """

    x: np.ndarray
    r: np.ndarray
    jac: BlockSparseJacobian
    cost: float
    gradient: np.ndarray
    grad_inf: float
    scale: np.ndarray
    iterations: int
    evaluations: int
    status: int
    message: str
    method: str
    history: list[IterationRecord] = field(default_factory=list)
    mu: float = float("nan")

    @property
    def success(self) -> bool:
        """Whether the solver converged (status 1, 2 or 5)."""
        return self.status in (1, 2, 5)

    @property
    def sigma0(self) -> float:
        """``sqrt(r^T r / (m - n))``: a-posteriori sigma of unit weight (nan if m <= n)."""
        m, n = self.jac.shape
        return float(np.sqrt(2.0 * self.cost / (m - n))) if m > n else float("nan")

    @property
    def qn_iterations(self) -> int:
        """The number of quasi-Newton steps tried."""
        return sum(1 for h in self.history if h.method == "qn")


@dataclass
class Covariance:
    """Blocks of ``N^-1 = (J^T J)^-1`` at the solution (unit weight: multiply by sigma0^2).

    Attributes
    ----------
    reduced : (n_reduced, n_reduced) ndarray
    elim_blocks : (n_blocks, b, b) ndarray
    normal_equations : NormalEquations
        For more (e.g. ``group_covariance`` for redundancy numbers).
    """

    reduced: np.ndarray
    elim_blocks: np.ndarray
    normal_equations: NormalEquations


class _CompactBFGS:
    """The BFGS matrix from ``B0 = I`` held as (s, y) pairs; applies ``H = B^-1`` (BNS 1994)."""

    def __init__(self, n: int, memory: int):
        self.n, self.memory = n, memory
        self.S: list[np.ndarray] = []
        self.Y: list[np.ndarray] = []

    def update(self, s, y) -> bool:
        sy = float(s @ y)
        if not sy > np.finfo(float).eps * np.linalg.norm(s) * np.linalg.norm(y):
            return False
        self.S.append(s)
        self.Y.append(y)
        if len(self.S) > self.memory:
            self.S.pop(0)
            self.Y.pop(0)
        return True

    def apply_inverse(self, g):
        """``H g = B^-1 g`` (n,)."""
        if not self.S:
            return g.copy()
        S, Y = np.column_stack(self.S), np.column_stack(self.Y)
        StY = S.T @ Y
        R = np.triu(StY)
        Dg = np.diag(StY)
        a = scipy.linalg.solve_triangular(R, S.T @ g, lower=False)
        w = scipy.linalg.solve_triangular(R, Dg * a + Y.T @ (Y @ a) - Y.T @ g, lower=False,
                                          trans="T")
        return g + S @ w - Y @ a


def _evaluate(problem, x, n):
    r, J = problem.evaluate(x, True)
    r = np.asarray(r, dtype=float)
    if J is None or not isinstance(J, BlockSparseJacobian):
        raise InputError("problem.evaluate(x, True) must return (r, BlockSparseJacobian)",
                         "lsq.solve")
    if r.ndim != 1 or J.shape != (len(r), n):
        raise InputError(f"problem.evaluate returned r {r.shape} and J {J.shape} for n = {n}",
                         "lsq.solve")
    finite = bool(np.all(np.isfinite(r))) and J.all_finite()
    return r, J, finite


def solve(problem, x0, *, method: str = "lmqn", eps1: float = 1e-10, eps2: float = 1e-12,
          max_iter: int = 200, tau: float = 1e-3, memory: int = 50, ftol: float = 0.0,
          sigma_tol: float = 0.0, switch_ratio: float = _SWITCH_RATIO,
          callback: Callable[[IterationRecord], bool | None] | None = None) -> LsqResult:
    """Minimise ``1/2 ||r(x)||^2`` by the LMQN hybrid or plain LM (see the module docstring).

    Parameters
    ----------
    problem : object
        ``problem.evaluate(x, jacobian) -> (r (m,), BlockSparseJacobian)``.
    x0 : (n,) array_like
        Starting point; residuals and Jacobian must be finite there.
    method : {"lmqn", "lm"}
        The hybrid of Madsen et al. Algorithm 3.17 (default), or Algorithm 3.16 alone.
    eps1 : float
        Stop when ``||g||_inf <= eps1`` (scaled variables; default 1e-10).
    eps2 : float
        Stop when ``||h|| <= eps2 (||r|| + eps2)`` (scaled variables; default 1e-12).
    max_iter : int
        At most this many iterations (default 200); each costs one evaluation.
    tau : float
        ``mu0 = tau max(diag(J^T J))`` in scaled variables (default 1e-3, the book's for a
        good starting point; a warm start may pass the previous result's ``mu``).
    memory : int
        The most (s, y) pairs kept for the BFGS matrix (default 50); below it the
        quasi-Newton matrix is exactly the book's dense B.
    ftol : float
        Stop (status 5) when a step's predicted decrease of the cost ``L(0) - L(h)`` is at
        most ``ftol F(x)`` (default 0: off; not in the book). Near the optimum in whitened
        units ``L(0) - L(h) = |dx|^2 / 2``: ``ftol = 1e-12`` on a cost of 10^4 stops within
        about 1e-4 standard deviations of the optimum instead of iterating at round-off.
    sigma_tol : float
        Stop (status 5) when a step's predicted decrease is at most ``sigma_tol^2 F / (m - n)``:
        the step is below ``sigma_tol`` a-posteriori standard deviations (default 0: off).
    switch_ratio : float
        LM -> QN after three successful LM steps with ``||g||_inf < switch_ratio F``
        (default 0.02, the book's). The test is not invariant to the residuals' units: with
        unit-weight residuals F is about m/2 at the optimum, so for large m it holds almost
        at once, also on small-residual problems where LM alone converges fast.
    callback : callable, optional
        Called with each :class:`IterationRecord`; returning True stops (status 3).

    Returns
    -------
    LsqResult
    """
    if method not in ("lmqn", "lm"):
        raise InputError(f"method must be 'lmqn' or 'lm', got {method!r}", "lsq.solve")
    for name, val in (("eps1", eps1), ("eps2", eps2), ("tau", tau), ("switch_ratio", switch_ratio),
                      ("ftol", ftol), ("sigma_tol", sigma_tol)):
        if not (np.isfinite(val) and val >= 0):
            raise InputError(f"{name} must be a finite number >= 0, got {val}", "lsq.solve")
    if int(max_iter) < 0 or int(memory) < 1:
        raise InputError(f"need max_iter >= 0 and memory >= 1, got {max_iter}, {memory}",
                         "lsq.solve")
    x = np.array(x0, dtype=float).reshape(-1)
    if not np.all(np.isfinite(x)):
        raise InputError("x0 must be finite", "lsq.solve")
    st = _State(problem, x, tau, int(memory))
    m, n = st.J.shape
    ftol = max(ftol, sigma_tol**2 / (m - n) if m > n else 0.0)
    history: list[IterationRecord] = []
    status = 1 if st.ginf <= eps1 else None
    k = 0
    while status is None and k < max_iter:
        k += 1
        rec = (_step_lm(st, eps2, method, switch_ratio, ftol) if st.step == "lm"
               else _step_qn(st, eps2, ftol))
        if rec.status is None and rec.accepted and st.ginf <= eps1:
            rec.status = 1
        status = rec.status
        out = IterationRecord(k=k, method=rec.method, F=st.F, F_trial=rec.F_trial, mu=rec.mu,
                              delta=rec.delta, step_norm=rec.step_norm, rho=float(rec.rho),
                              grad_inf=st.ginf, accepted=rec.accepted)
        history.append(out)
        if callback is not None and callback(out) and status is None:
            status = 3
    if status is None:
        status = 0
    return LsqResult(x=st.x, r=st.r, jac=st.J, cost=st.F, gradient=st.g, grad_inf=st.ginf,
                     scale=st.d, iterations=k, evaluations=st.nfev, status=status,
                     message=STATUS_MESSAGES[status], method=method, history=history, mu=st.mu)


_MAX_PENDING_UPDATES = 8
"""The most BFGS updates :class:`_State` lets wait for a QN step (each holds its two Jacobians);
beyond it the oldest is computed."""


class _State:
    """The iterate and the method's memory: mu, nu, count, Delta, BFGS pairs."""

    def __init__(self, problem, x, tau, memory):
        self.problem, self.n = problem, len(x)
        r, J, finite = _evaluate(problem, x, self.n)
        self.nfev = 1
        if not finite:
            raise InputError("the residuals or the Jacobian at x0 are not finite", "lsq.solve")
        norms = J.column_norms()
        d = norms.copy()
        d[~(np.isfinite(d) & (d > 0))] = 1.0
        self.d = d
        self._set(x, r, J, J.gradient(r))
        self.mu = tau * float(((norms / d) ** 2).max(initial=0.0))  # tau max diag(N_z)
        if not self.mu > 0:
            self.mu = tau if tau > 0 else 1e-3
        self.nu = 2.0
        self.step, self.count, self.Delta = "lm", 0, np.nan
        self.bfgs = _CompactBFGS(self.n, memory)
        self._pending: list[tuple] = []     # BFGS updates not computed yet, oldest first

    def _set(self, x, r, J, g):
        self.x, self.r, self.J, self.g = x, r, J, g
        self.F = 0.5 * float(r @ r)
        self.gz = g / self.d
        self.ginf = float(np.abs(self.gz).max(initial=0.0))
        self.ne = None

    def small(self, eps2):
        """``eps2 (||r|| + eps2)``: the step-size threshold in scaled variables (see Stopping)."""
        return eps2 * (np.sqrt(2.0 * self.F) + eps2)

    def trial(self, h):
        """Evaluate ``x + h``: (x_new, r_new, J_new, g_new) or None when not finite."""
        x_new = self.x + h
        r_new, J_new, finite = _evaluate(self.problem, x_new, self.n)
        self.nfev += 1
        if not finite:
            return None
        return x_new, r_new, J_new, J_new.gradient(r_new)

    def update_bfgs(self, x_new, r_new, J_new, g_new):
        """BFGS update: ``h = x_new - x``, ``y = J_new^T J_new h + (J_new - J)^T r_new``.

        Queued: computed by :meth:`bfgs_matrix` (the same arithmetic, in the same order)."""
        self._pending.append((x_new - self.x, self.J, r_new, J_new, g_new))
        if len(self._pending) > _MAX_PENDING_UPDATES:
            self._apply_update(*self._pending.pop(0))

    def _apply_update(self, h, J, r_new, J_new, g_new):
        y = J_new.gradient(J_new.matvec(h)) + g_new - J.gradient(r_new)
        self.bfgs.update(self.d * h, y / self.d)

    def bfgs_matrix(self) -> _CompactBFGS:
        """The BFGS matrix with every update so far."""
        for update in self._pending:
            self._apply_update(*update)
        self._pending.clear()
        return self.bfgs

    def lm_fail(self):
        """A rejected LM step: ``mu := mu nu``, ``nu := 2 nu``; status 4 if mu D^2 overflows."""
        self.mu, self.nu, self.count = self.mu * self.nu, self.nu * 2.0, 0
        return 4 if not self.mu * float(self.d.max(initial=1.0)) ** 2 < _MU_MAX else None


@dataclass
class _StepOutcome:
    method: str
    mu: float
    delta: float = np.nan
    F_trial: float = np.nan
    step_norm: float = np.nan
    rho: float = np.nan
    accepted: bool = False
    status: int | None = None


def _step_lm(st: _State, eps2: float, method: str, switch_ratio: float, ftol: float = 0.0) -> _StepOutcome:
    """One LM iteration (Algorithm 3.16; switch to QN as in 3.17)."""
    out = _StepOutcome("lm", st.mu)
    small = st.small(eps2)
    if st.ne is None:
        st.ne = st.J.normal_equations()
    try:
        h = st.ne.solve(st.g, st.mu * st.d * st.d)        # (J^T J + mu D^2) h = -g
    except SingularSystemError:
        h = None
    if h is None or not np.all(np.isfinite(h)):
        out.status = st.lm_fail()
        return out
    hz = st.d * h
    out.step_norm = float(np.linalg.norm(hz))
    if out.step_norm <= small:
        out.status = 2
        return out
    dL = 0.5 * float(hz @ (st.mu * hz - st.gz))          # L(0) - L(h)
    if dL <= ftol * st.F:
        out.status = 5            # converged: not even the model expects a decrease worth having;
        return out                # the step is not taken (nor evaluated: a Jacobian saved per solve)
    new = st.trial(h)
    if new is None:
        out.status = st.lm_fail()
        return out
    x_new, r_new, J_new, g_new = new
    F_new, ginf_new, dF, rho = _trial_gain(st, r_new, g_new, dL, out)
    if method == "lmqn":
        st.update_bfgs(x_new, r_new, J_new, g_new)
    if dL > 0 and dF > 0:
        out.accepted = True
        st.count = st.count + 1 if ginf_new < switch_ratio * F_new else 0
        st.mu *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        st.nu = 2.0
        if method == "lmqn" and st.count >= _SWITCH_COUNT:
            st.step, st.count = "qn", 0
            st.Delta = max(1.5 * small, out.step_norm / 5.0)
        st._set(x_new, r_new, J_new, g_new)
    else:
        out.status = st.lm_fail()
    return out


def _trial_gain(st: _State, r_new: np.ndarray, g_new: np.ndarray, dL: float, out: _StepOutcome):
    """``(F_new, ||g_new||_inf scaled, dF, rho)`` of a trial point; ``out`` records F and rho.

    ``dF = F(x) - F(x_new)`` is computed as ``1/2 (r - r_new) . (r + r_new)``, without the
    cancellation of subtracting two nearly equal sums of squares; ``rho = dF / dL``, the
    gain ratio against the model's predicted decrease ``dL`` (``-inf`` when ``dL <= 0``).
    """
    F_new = 0.5 * float(r_new @ r_new)
    out.F_trial = F_new
    ginf_new = float(np.abs(g_new / st.d).max(initial=0.0))
    dF = 0.5 * float((st.r - r_new) @ (st.r + r_new))
    out.rho = rho = dF / dL if dL > 0 else -np.inf
    return F_new, ginf_new, dF, rho


def _step_qn(st: _State, eps2: float, ftol: float = 0.0) -> _StepOutcome:
    """One quasi-Newton iteration with a trust region (Algorithm 3.17)."""
    out = _StepOutcome("qn", st.mu, st.Delta)
    small = st.small(eps2)
    if st.Delta <= small:
        out.status = 2
        return out
    hz_full = -st.bfgs_matrix().apply_inverse(st.gz)      # B h = -g
    nf = float(np.linalg.norm(hz_full))
    alpha = min(1.0, st.Delta / nf) if nf > 0 else 1.0
    hz = alpha * hz_full
    out.step_norm = alpha * nf
    if out.step_norm <= small:
        out.status = 2
        return out
    # L(0) - L(h) = -h^T g - 1/2 h^T B h, with B h_full = -g for the unclipped step
    dL = -alpha * float(hz_full @ st.gz) * (1.0 - 0.5 * alpha)
    new = st.trial(hz / st.d)
    if new is None:
        st.Delta /= 2.0
        return out
    x_new, r_new, J_new, g_new = new
    F_new, ginf_new, _, rho = _trial_gain(st, r_new, g_new, dL, out)
    if rho < 0.25:
        st.Delta /= 2.0
    elif rho > 0.75:
        st.Delta = max(st.Delta, 3.0 * out.step_norm)
    better = F_new < st.F or (F_new <= (1.0 + _DELTA) * st.F and ginf_new < st.ginf)
    if ginf_new >= st.ginf:
        st.step = "lm"
    st.update_bfgs(x_new, r_new, J_new, g_new)
    if better:
        out.accepted = True
        st._set(x_new, r_new, J_new, g_new)
        if dL <= ftol * st.F:
            out.status = 5        # as in LM: the model expects no decrease worth having
    return out


def covariance(result: LsqResult) -> Covariance:
    """The blocks of ``(J^T J)^-1`` at ``result.x`` (unit weight; scale by ``result.sigma0**2``).

    Raises
    ------
    SingularSystemError
        When ``J^T J`` is singular (a parameter the data do not determine).
    """
    ne = result.jac.normal_equations()
    return Covariance(reduced=ne.covariance_reduced(), elim_blocks=ne.covariance_elim_blocks(),
                      normal_equations=ne)


def scipy_reference(problem, x0, *, ftol: float = 1e-15, xtol: float = 1e-15, gtol: float = 1e-15,
                    max_nfev: int | None = None, dense_max: int = 1000, **kw):
    """Solve the same problem with ``scipy.optimize.least_squares`` (an independent check).

    Trust-region reflective (``method="trf"``) with the Jacobian from
    :meth:`BlockSparseJacobian.to_csr` and ``x_scale="jac"``; ``tr_solver="exact"`` on a dense
    copy when ``n <= dense_max``, ``"lsmr"`` on the sparse matrix otherwise. Tolerances
    default to 1e-15 (tight). Extra keywords go to ``least_squares``.

    Returns
    -------
    scipy.optimize.OptimizeResult
    """
    import scipy.optimize  # only here: an independent check, not worth its import time in every solve

    x0 = np.array(x0, dtype=float).reshape(-1)
    dense = len(x0) <= dense_max
    cache: dict[str, object] = {}

    def at(x):
        if "x" not in cache or not np.array_equal(cache["x"], x):
            r, J = problem.evaluate(np.array(x, dtype=float), True)
            cache.update(x=np.array(x, dtype=float), r=np.asarray(r, dtype=float), J=J)
        return cache["r"], cache["J"]

    def fun(x):
        return at(x)[0]

    def jac(x):
        Jc = at(x)[1].to_csr()
        return Jc.toarray() if dense else Jc

    opts = dict(method="trf", x_scale="jac", tr_solver="exact" if dense else "lsmr",
                ftol=ftol, xtol=xtol, gtol=gtol, max_nfev=max_nfev)
    opts.update(kw)
    return scipy.optimize.least_squares(fun, x0, jac=jac, **opts)
