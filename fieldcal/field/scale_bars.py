"""Scale bars as observations of the field adjustment (CONTRACT section 3, ``scale_bars.csv``).

A bar ``b`` between targets ``a`` and ``c`` measured ``L_b`` [mm] with sigma ``s_b`` [mm] is
one weighted residual, measured minus adjusted like the image points' (bundle module)::

    d_b = |X_c - X_a| * 1000          [mm]
    r_b = (L_b - d_b) / s_b
    dr_b / dX_a =  1000 u / s_b,   dr_b / dX_c = -1000 u / s_b,   u = (X_c - X_a) / |X_c - X_a|

Where it goes in the solver. The block-sparse normal equations
(:mod:`fieldcal.solver.blocksparse`) eliminate the targets block by block: a residual row may
touch at most one eliminated block, and a bar touches two. The end points of the bars in use are
therefore carried as *global* targets: their slots come first among the targets
(:class:`fieldcal.field.bundle.BundleModel`, ``global_targets``) and the solver keeps them in
its dense part (``[interior | exterior | bar ends]``), the other targets stay eliminated. A
bar row then touches dense columns only; the image points and surveys of a bar end are their
own residual blocks (a block's column positions are dense in every group or eliminated in every
group). A session has a few bars: a few dozen dense columns more.

With bars, a free network has six datum defects, not seven (the bars fix the scale;
:mod:`fieldcal.field.datum`), and the bars reshape the network as any observation does.
"""

from __future__ import annotations

import numpy as np

from fieldcal.solver.blocksparse import ResidualBlock

__all__ = ["BarObservations", "bar_ends", "covariance_blocks", "usable"]


def bar_ends(bars, active, adjusted) -> np.ndarray:
    """Targets at an end of a bar in use: ``active`` (b,) bool and both ends ``adjusted`` (n,) bool."""
    if bars is None or not len(bars):
        return np.zeros(0, np.int64)
    ok = usable(bars, active, adjusted)
    return np.unique(np.concatenate([bars.from_target[ok], bars.to_target[ok]]))


def usable(bars, active, adjusted) -> np.ndarray:
    """(b,) bool: the bar is active and both its ends are adjusted targets."""
    return np.asarray(active, bool) & adjusted[bars.from_target] & adjusted[bars.to_target]


class BarObservations:
    """The residual rows of the bars in use (module docstring).

    Parameters
    ----------
    bars : fieldcal.session.data.ScaleBars
    used : (b,) bool
        The bars that enter (both ends global targets of ``model``).
    model : fieldcal.field.bundle.BundleModel
    """

    def __init__(self, bars, used, model):
        self.index = np.flatnonzero(used)
        self.from_target, self.to_target = a, c = bars.from_target[self.index], bars.to_target[self.index]
        self.slot_a, self.slot_c = model.t_slot[a], model.t_slot[c]
        if np.any(self.slot_a < 0) or np.any(self.slot_c < 0) or \
                np.any(np.maximum(self.slot_a, self.slot_c) >= model.n_global):
            raise ValueError("a bar's ends must be global targets of the model")
        self.length_mm = bars.length_mm[self.index]
        self.sigma_mm = bars.sigma_mm[self.index]
        nr = model.n_reduced
        self.cols = np.concatenate([nr + 3 * self.slot_a[:, None] + np.arange(3),
                                    nr + 3 * self.slot_c[:, None] + np.arange(3)], axis=1)   # (nb, 6)
        self.n_reduced = nr

    def __len__(self) -> int:
        return len(self.index)

    def _geometry(self, x):
        X = np.asarray(x, float)[self.n_reduced:].reshape(-1, 3)
        diff = X[self.slot_c] - X[self.slot_a]
        d_m = np.linalg.norm(diff, axis=1)
        return diff, d_m

    def adjusted_mm(self, x) -> np.ndarray:
        """(nb,) ``d_b`` [mm] at ``x``."""
        return self._geometry(x)[1] * 1000.0

    def residuals(self, x) -> np.ndarray:
        """(nb,) ``r_b`` (dimensionless)."""
        return (self.length_mm - self.adjusted_mm(x)) / self.sigma_mm

    def gradient_mm(self, x) -> np.ndarray:
        """(nb, 6) ``d d_b / d [X_a, X_c]`` [mm/m] on :attr:`cols`."""
        diff, d_m = self._geometry(x)
        u = diff / d_m[:, None]
        return np.concatenate([-u, u], axis=1) * 1000.0

    def block(self, first_row: int, x) -> ResidualBlock:
        """The bars' rows ``first_row ...`` of the Jacobian (one group per bar)."""
        values = -self.gradient_mm(x) / self.sigma_mm[:, None]
        rows = (first_row + np.arange(len(self)))[:, None]
        return ResidualBlock(rows, self.cols, values[:, None, :])

    def report(self, x, cov_dense, sigma0, ids) -> list[dict]:
        """Per bar: ids, measured, adjusted length and its sigma [mm] (``cov_dense``: the unit-weight
        covariance of the dense columns; a length does not depend on the datum), residual."""
        g = self.gradient_mm(x)
        d = self.adjusted_mm(x)
        Q = cov_dense[self.cols[:, :, None], self.cols[:, None, :]]              # (nb, 6, 6)
        var_d = np.einsum("ki,kij,kj->k", g, Q, g) * sigma0**2
        rows = []
        for k in range(len(self)):
            row = {"from_id": str(ids[self.from_target[k]]), "to_id": str(ids[self.to_target[k]]),
                   "length_mm": float(self.length_mm[k]), "sigma_mm": float(self.sigma_mm[k]),
                   "adjusted_mm": float(d[k]), "sigma_adjusted_mm": float(np.sqrt(max(var_d[k], 0.0))),
                   "residual_mm": float(self.length_mm[k] - d[k])}
            rows.append(row)
        return rows


def covariance_blocks(model, ne):
    """``(Q_rr, Q_tt)``: the unit-weight covariance over ``[interior | exterior]`` (n_reduced,
    n_reduced) and each adjusted target's 3 x 3 block in slot order (n_adjusted, 3, 3), from
    the normal equations ``ne`` whose dense part holds the bar ends after the exteriors."""
    nr, ng = model.n_reduced, model.n_global
    Q = ne.covariance_reduced()
    Qt = ne.covariance_elim_blocks()
    if ng:
        Qg = Q[nr:, nr:].reshape(ng, 3, ng, 3)[np.arange(ng), :, np.arange(ng), :]
        Qt = np.concatenate([Qg, Qt]) if len(Qt) else Qg
    return Q[:nr, :nr], Qt
