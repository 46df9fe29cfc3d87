"""The datum of the field adjustment: weighted control, or a free network with inner constraints.

With three or more surveyed targets the surveyed coordinates are weighted observations
(:mod:`fieldcal.field.adjustment`, today's datum). Otherwise (or with ``field.datum``
``"free"``) the network is **free** (CONTRACT section 3): image points alone leave seven
unknowns undetermined, a similarity transform of the whole network (translation ``t``,
small rotation ``theta``, scale ``s``), whose directions in the parameter vector are the
columns of ``E`` (n, 7)::

    interior          0                0            0
    rotation w_i      0              -R_i           0        (R_i = exp([w_i]x) R0_i, world to camera)
    centre C_i        I          -[C_i]x            C_i
    target X_t        I          -[X_t]x            X_t

Solve. The adjustment is solved with a minimal constraint that the block-sparse normal
equations can carry (seven pseudo-observations on reduced columns: the pose of the image with
the most points and its baseline to the image farthest from it, :class:`MinimalConstraints`).
Any minimal constraint gives the same image residuals, the same interior orientation and the
same interior covariance: ``E`` has no interior rows.

Report (:func:`to_minimum_trace`). The solution is moved by the similarity that fits its
targets best (least squares) onto their initial coordinates ``X0``: the inner constraints
``K^T (X - X0) = 0`` with ``K`` the target rows of ``E`` (the minimum-trace datum over the
targets, Fraser 1982; Granshaw 1980), and the covariance follows by the S-transformation
``Q' = S Q S^T``, ``S = I - E (K^T E)^-1 K^T`` (Baarda 1973), evaluated for the blocks the
result reports (interior and exterior, each target's 3 x 3) from ``Q K``, seven solves with
the factorised normal equations.

Scale bars (``scale_bars.csv``) are observations of the adjustment
(:mod:`fieldcal.field.scale_bars`): they fix the scale, so a free network with bars in use has
six defects (translation, rotation), six minimal constraints (the reference image's pose) and
six inner constraints, the report moves it rigidly (``s = 1``) and the S-transformation uses
the first six columns of ``E``. One bar is a minimal scale (its residual is zero); more bars
are redundant lengths that reshape the network like any observation, with residuals and data
snooping of their own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fieldcal.field.scale_bars import covariance_blocks
from fieldcal.solver.blocksparse import ResidualBlock

__all__ = ["MIN_CONTROL_POINTS", "MinimalConstraints", "minimal_constraints", "null_space", "to_minimum_trace"]

MIN_CONTROL_POINTS = 3
"""Surveyed targets (observed, survey in use) the weighted-control datum needs."""
CONSTRAINT_SIGMA = 1e-6
"""Sigma of the minimal-constraint pseudo-observations [rad, m per m of baseline]. Any value
gives the same solution (they are minimal: at the optimum their residuals vanish) and, after
the S-transformation, the same covariance (``(N + C^T W C)^-1`` differs from a constrained
inverse only along ``E``, which ``S`` removes); a weight near the data's keeps the solves with
the factorised normal equations accurate (a weight 10^10 above it cost 10 digits)."""


@dataclass
class MinimalConstraints:
    """Seven pseudo-observations ``D (x[cols] - x0)`` on reduced columns (module docstring)."""

    cols: np.ndarray      # (9,) columns: w of the reference image, its centre, the other's centre
    D: np.ndarray         # (7, 9)
    x0: np.ndarray        # (9,) the values held

    def residuals(self, x):
        return self.D @ (np.asarray(x)[self.cols] - self.x0)

    def block(self, first_row: int) -> ResidualBlock:
        return ResidualBlock.from_parts((first_row + np.arange(len(self.D)))[None], [(self.cols, self.D[None])])


def minimal_constraints(model, x, counts, scale: bool = True) -> MinimalConstraints:
    """The pose of the image with most points ``counts`` and its baseline to the farthest image.

    ``scale=False`` (scale bars in the adjustment fix the scale): the pose alone, six rows."""
    n_int = model.n_int
    C = x[n_int:model.n_reduced].reshape(-1, 6)[:, 3:]
    i = int(np.argmax(counts))
    j = int(np.argmax(np.linalg.norm(C - C[i], axis=1)))
    base = C[j] - C[i]
    length = float(np.linalg.norm(base))
    u = base / length
    cols = np.concatenate([n_int + 6 * i + np.arange(6), n_int + 6 * j + 3 + np.arange(3)])
    D = np.zeros((7, 9))
    D[:3, :3] = np.eye(3) / CONSTRAINT_SIGMA
    D[3:6, 3:6] = np.eye(3) / (CONSTRAINT_SIGMA * length)
    D[6, 3:6], D[6, 6:9] = -u / (CONSTRAINT_SIGMA * length), u / (CONSTRAINT_SIGMA * length)
    if not scale:
        cols, D = cols[:6], D[:6, :6]
    return MinimalConstraints(cols, D, np.asarray(x, float)[cols].copy())


def _cross(v):
    """``[v]x`` (k, 3, 3)."""
    z = np.zeros(len(v))
    return np.stack([np.stack([z, -v[:, 2], v[:, 1]], 1), np.stack([v[:, 2], z, -v[:, 0]], 1),
                     np.stack([-v[:, 1], v[:, 0], z], 1)], 1)


def null_space(model, R, C, X_adj) -> np.ndarray:
    """``E`` (n, 7) of the model's parameter vector (module docstring): translation, rotation, scale."""
    n_img = model.n_images
    E = np.zeros((model.n_params, 7))
    ext = np.zeros((n_img, 6, 7))
    ext[:, 0:3, 3:6] = -R
    ext[:, 3:6, 0:3] = np.eye(3)
    ext[:, 3:6, 3:6] = -_cross(C)
    ext[:, 3:6, 6] = C
    E[model.n_int:model.n_reduced] = ext.reshape(-1, 7)
    tgt = np.zeros((len(X_adj), 3, 7))
    tgt[:, :, 0:3] = np.eye(3)
    tgt[:, :, 3:6] = -_cross(X_adj)
    tgt[:, :, 6] = X_adj
    E[model.n_reduced:] = tgt.reshape(-1, 7)
    return E


def _similarity(P, Q, with_scale: bool):
    """``(s, Rm, t)`` minimising ``sum |s Rm P + t - Q|^2`` (Umeyama 1991); ``s = 1`` without scale."""
    mp, mq = P.mean(0), Q.mean(0)
    A, B = P - mp, Q - mq
    U, sv, Vt = np.linalg.svd(B.T @ A)
    d = np.sign(np.linalg.det(U @ Vt))
    Dm = np.diag([1.0, 1.0, d])
    Rm = U @ Dm @ Vt
    s = float(np.trace(np.diag(sv) @ Dm) / np.sum(A**2)) if with_scale else 1.0
    return s, Rm, mq - s * Rm @ mp


@dataclass
class FreeNetwork:
    """The reported solution of a free network: moved, and its covariance blocks."""

    R: np.ndarray
    C: np.ndarray
    X: np.ndarray
    cov_reduced: np.ndarray        # unit weight
    cov_targets: np.ndarray        # (n_adjusted, 3, 3) unit weight
    info: dict


def to_minimum_trace(model, result, R, C, X, X0, bars, sigma0) -> FreeNetwork:
    """The free network's solution in the minimum-trace datum, scaled by ``bars`` (module docstring).

    ``R, C, X``: the solution (rotations, centres, all targets [m]); ``X0`` the targets'
    initial coordinates; ``bars``: the :class:`fieldcal.field.scale_bars.BarObservations` of the
    adjustment, or None. With bars the scale is theirs (six datum defects, six inner
    constraints, a rigid motion); without, the initial values' (seven).
    """
    ne = result.jac.normal_equations()
    idx = model.target_index
    X_adj = X[idx]
    info: dict = {}
    nd = 6 if bars is not None and len(bars) else 7          # datum defects
    # the point estimate: rigid motion (bars) or similarity onto the initial coordinates
    ok = np.isfinite(X0[idx]).all(axis=1)
    s_tot, Rm, t = _similarity(X_adj[ok], X0[idx][ok], with_scale=nd == 7)
    new_X = X.copy()
    new_X[idx] = s_tot * X_adj @ Rm.T + t
    new_C = s_tot * C @ Rm.T + t
    new_R = R @ Rm.T
    # the covariance: A Q A^T (A: the similarity's Jacobian), then S (.) S^T, S = I - E (K^T E)^-1 K^T
    E = null_space(model, new_R, new_C, new_X[idx])[:, :nd]
    K = np.zeros_like(E)
    K[model.n_reduced:] = E[model.n_reduced:]
    nr, n_int = model.n_reduced, model.n_int

    def positions(v):            # (n, ...) -> views of the centre rows and the target rows
        ext = v[n_int:nr].reshape(model.n_images, 6, *v.shape[1:])
        return ext[:, 3:], v[nr:].reshape(-1, 3, *v.shape[1:])

    def apply(v, M3):            # A v (M3 = s Rm) or A^T v (M3 = s Rm^T), v (n,) or (n, k)
        out = np.array(v, float)
        for part in positions(out):
            part[...] = np.einsum("ab,kb...->ka...", M3, part)
        return out

    A3 = s_tot * Rm
    W = np.column_stack([apply(-ne.solve(apply(K[:, j], A3.T)), A3) for j in range(nd)])   # Q K
    M = np.linalg.inv(K.T @ E)
    EM = E @ M
    KW = K.T @ W
    Qr, Qt = covariance_blocks(model, ne)
    Qr = apply(apply(Qr, A3).T, A3).T
    Er, Wr = EM[:nr], W[:nr]
    cov_r = Qr - Er @ Wr.T - Wr @ Er.T + Er @ KW @ Er.T
    Qt = np.einsum("ab,kbc,dc->kad", A3, Qt, A3)
    Et, Wt = EM[nr:].reshape(-1, 3, nd), W[nr:].reshape(-1, 3, nd)
    cov_t = (Qt - np.einsum("kai,kbi->kab", Et, Wt) - np.einsum("kai,kbi->kab", Wt, Et)
             + np.einsum("kai,ij,kbj->kab", Et, KW, Et))
    info["similarity"] = {"scale": s_tot, "rotation_deg": float(np.degrees(np.arccos(
        np.clip((np.trace(Rm) - 1) / 2, -1, 1)))), "translation_m": t.tolist()}
    return FreeNetwork(new_R, new_C, new_X, cov_r, cov_t, info)
