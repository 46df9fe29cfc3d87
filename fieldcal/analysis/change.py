r"""Has the camera changed? One test per quantity the two calibrations observe, and Holm.

A change of one camera property -- the principal distance, the principal point, the
distortion at the edge of the field -- is a change in one or two numbers. An omnibus
chi-square over the whole correction field (:mod:`fieldcal.analysis.compare`) has as
many degrees of freedom as the model has parameters and spends its power on all of them:
a change of 3.7 sigma in ``f`` alone gave p = 0.008 on 9 degrees of freedom. This module
tests each quantity on its own and combines the tests with Holm's step-down correction,
so that the family of tests keeps the level ``alpha`` (the chance that an unchanged
camera is called changed) while a change in one quantity is judged by its own test.

Quantities
----------
For a quantity ``g(theta)`` of the interior parameters (``k`` numbers), the change is
``Delta = g(theta_B) - g(theta_A)`` and, to first order, its covariance is
``C = G (Sigma_A + Sigma_B) G^T`` with ``G = dg/dtheta`` at A and the two calibrations'
covariances over the union of their estimated parameters (zero where one did not
estimate a parameter). The statistic ``Delta^T C^-1 Delta`` is chi-square with ``k``
degrees of freedom when the camera did not change (a z-test for ``k = 1``).

- ``f``: the principal distance [um].
- ``principal point``: ``(xp, yp)`` [um], 2 degrees of freedom.
- ``edge distortion``: the radial correction ``dr(r_e) = r_e (k0 + k1 r_e^2 + k2 r_e^4 +
  k3 r_e^6)`` [um] at the edge of the field ``r_e`` (:func:`edge_radius_mm`: the sensor's
  half diagonal for the field method, the end of the wider sweep for the goniometer, the
  smaller of the two calibrations' radii).
- the correction field over the region both observe (the omnibus map test of
  :func:`fieldcal.analysis.compare.compare_calibrations`): every other change (decentering,
  affinity, a change the covariance does not allow for).

What a method does not observe is left out, and the comparison says so
(:func:`observed_quantities`): a goniometer does not observe where its optical axis
points (the arm's zero is aligned on the sensor centre; a common rotation is removed),
nor the correction off its two scanned axes (its model there is an extrapolation); its
``f`` absorbs the linear part of the radial distortion and its principal point the even
part of the decentering (the minimum-sum convention, METHODS.md part B), so between a
goniometer and a field calibration only the map along the scanned axes is compared.

Holm's procedure
----------------
With the ``K`` p-values sorted, ``p_(1) <= ... <= p_(K)``, the adjusted p-values are
``q_(i) = max_{j <= i} min(1, (K - j + 1) p_(j))``; a quantity changed significantly when
its ``q < alpha``. It controls the family-wise error rate at ``alpha`` whatever the
dependence between the tests (Holm 1979, Scand. J. Statist. 6, 65-70).

Power: a change of ``delta`` standard deviations of the difference in one quantity is
found with probability about ``Phi(delta - z)``, ``z`` the two-sided critical value at
``alpha / K``: with ``alpha = 0.01`` and ``K = 4``, ``z = 3.02``: 49 % at 3 sigma, 90 % at
4.3 sigma (no level-0.01 test of one quantity exceeds 75 % at 3 sigma: the one-sided
z-test's ``Phi(3 - 2.33)``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy import stats

from fieldcal.model.camera import INDEX

__all__ = ["QuantityTest", "QUANTITIES", "observed_quantities", "edge_radius_mm",
           "quantity_tests", "holm", "chi_square_test"]

QUANTITIES: dict[str, str] = {
    "f": "principal distance",
    "principal_point": "principal point (xp, yp)",
    "edge_distortion": "radial distortion at the edge of the field",
    "map": "correction field where both observe",
}
"""The quantities tested, by key."""


@dataclass(frozen=True)
class QuantityTest:
    """The test of one quantity.

    Attributes
    ----------
    key : str
        One of :data:`QUANTITIES`.
    label : str
        What it is, in words (with where it is evaluated).
    unit : str
        Of ``change`` and ``sigma`` (``um``, or ``px`` for the map).
    change : tuple of float
        ``B - A`` per component.
    sigma : tuple of float
        1-sigma of each component of the difference.
    statistic, dof, p_value : float, int, float
        Chi-square, its degrees of freedom and p-value.
    p_adjusted : float
        Holm-adjusted p-value within the comparison's family.
    """

    key: str
    label: str
    unit: str
    change: tuple
    sigma: tuple
    statistic: float
    dof: int
    p_value: float
    p_adjusted: float = math.nan

    def significant(self, alpha: float) -> bool:
        return bool(self.p_adjusted < alpha)

    @property
    def unit_symbol(self) -> str:
        """The unit as people read it (``µm``; ``unit`` stays ``um`` in the JSON)."""
        return "µm" if self.unit == "um" else self.unit

    def line(self) -> str:
        """One line: the change, its sigma, the test."""
        u = self.unit_symbol
        if self.key == "map":
            size = f"largest change {self.change[0]:.4g} {u} (1 σ up to {self.sigma[0]:.3g} {u})"
        else:
            size = "change " + ", ".join(f"{c:+.4g} ± {s:.3g}" for c, s in
                                         zip(self.change, self.sigma, strict=True)) + f" {u}"
        return (f"{self.label}: {size}; chi2 {self.statistic:.3g} on {self.dof} dof, "
                f"p = {self.p_value:.3g} (Holm-adjusted {self.p_adjusted:.3g})")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["change"], d["sigma"] = list(self.change), list(self.sigma)
        return d


def holm(p_values) -> np.ndarray:
    """Holm-adjusted p-values (module docstring), in the input's order."""
    p = np.asarray(p_values, float)
    k = p.size
    order = np.argsort(p, kind="stable")
    adj = np.minimum(1.0, (k - np.arange(k)) * p[order])
    adj = np.maximum.accumulate(adj)
    out = np.empty(k)
    out[order] = adj
    return out


def chi_square_test(delta, cov, *, rcond: float = 1e-10):
    """``(chi2, rank, p)`` of ``delta`` (k,) against ``N(0, cov)`` by the pseudo-inverse."""
    delta = np.atleast_1d(np.asarray(delta, float))
    w, V = np.linalg.eigh(np.atleast_2d(np.asarray(cov, float)))
    keep = w > rcond * max(w.max(initial=0.0), 1e-300)
    z = (V[:, keep].T @ delta) / np.sqrt(w[keep])
    chi2 = float(z @ z)
    r = int(keep.sum())
    return chi2, r, float(stats.chi2.sf(chi2, r)) if r else 1.0


def edge_radius_mm(cal) -> float:
    """The edge of the field a calibration observes [mm] (module docstring)."""
    s = cal.sensor
    st = cal.document.get("stats") or {}
    if cal.method == "goniometer" and st.get("half_span_deg"):
        axis = st.get("f_axis") or "x"
        span = float(st["half_span_deg"].get(axis, 0.0))
        return float(cal.camera.f_mm * math.tan(math.radians(span)))
    return float(s.half_diagonal_mm)


def _gradient(names, key: str, r_mm: float) -> np.ndarray:
    """``dg/dtheta`` (k, p) of a quantity over ``names`` [um per parameter unit]."""
    pos = {n: i for i, n in enumerate(names)}
    if key == "f":
        rows = [{"f_mm": 1000.0}]
    elif key == "principal_point":
        rows = [{"xp_mm": 1000.0}, {"yp_mm": 1000.0}]
    else:
        rows = [{"k0": 1000.0 * r_mm, "k1": 1000.0 * r_mm**3, "k2": 1000.0 * r_mm**5,
                 "k3": 1000.0 * r_mm**7}]
    G = np.zeros((len(rows), len(names)))
    for i, row in enumerate(rows):
        for n, g in row.items():
            if n in pos:
                G[i, pos[n]] = g
    return G


def _value(params, key: str, r_mm: float) -> np.ndarray:
    p = np.asarray(params, float)
    if key == "f":
        return np.array([1000.0 * p[INDEX["f_mm"]]])
    if key == "principal_point":
        return 1000.0 * p[[INDEX["xp_mm"], INDEX["yp_mm"]]]
    k = p[[INDEX["k0"], INDEX["k1"], INDEX["k2"], INDEX["k3"]]]
    return np.array([1000.0 * r_mm * (k[0] + k[1] * r_mm**2 + k[2] * r_mm**4 + k[3] * r_mm**6)])


def observed_quantities(a, b) -> tuple[list[str], list[str]]:
    """``(keys, left_out)``: the parameter quantities compared and, in words, what is not.

    ``map`` is always compared (by :mod:`fieldcal.analysis.compare`); ``keys`` lists the
    others (module docstring).
    """
    methods = {a.method, b.method}
    left = []
    if "goniometer" in methods:
        left.append("where the optical axis points (a goniometer aligns its arm's zero on the "
                    "sensor centre and does not observe it): the best common rotation is removed")
        left.append("the correction off the two scanned axes (a goniometer's model there is an "
                    "extrapolation): the map is tested at the measured spots along the axes")
    if len(methods) > 1:
        left.append("f, the principal point and the radial distortion as numbers: the goniometer's "
                    "f absorbs the linear part of the radial distortion and its principal point "
                    "the even part of the decentering (the minimum-sum convention); compared "
                    "through the map along the scanned axes only")
        return [], left
    if "goniometer" in methods:
        left.append("k0, b1, p1, p2 one by one (their split against f and the principal point "
                    "is the method's convention): they enter through the map")
    keys = [k for k in ("f", "principal_point", "edge_distortion")
            if all(n in a.names and n in b.names for n in _needs(k))]
    return keys, left


def _needs(key: str) -> tuple[str, ...]:
    return {"f": ("f_mm",), "principal_point": ("xp_mm", "yp_mm"),
            "edge_distortion": ("k1",)}[key]


def quantity_tests(a, b, names, cov, keys) -> list[QuantityTest]:
    """The tests of ``keys`` (see :func:`observed_quantities`) for calibrations ``a``, ``b``.

    Parameters
    ----------
    a, b : fieldcal.analysis.uncertainty.Calibration
    names : sequence of str
        The union of their estimated parameters
        (:data:`fieldcal.model.camera.PARAM_NAMES` order).
    cov : (p, p) ndarray
        ``Sigma_A + Sigma_B`` over ``names``.
    keys : sequence of str

    Returns
    -------
    list of QuantityTest
        Not yet Holm-adjusted (``p_adjusted`` NaN).
    """
    r_e = min(edge_radius_mm(a), edge_radius_mm(b))
    out = []
    for key in keys:
        G = _gradient(names, key, r_e)
        delta = _value(b.camera.params, key, r_e) - _value(a.camera.params, key, r_e)
        C = G @ cov @ G.T
        chi2, r, p = chi_square_test(delta, C)
        label = QUANTITIES[key] + (f" (r = {r_e:.2f} mm)" if key == "edge_distortion" else "")
        out.append(QuantityTest(key, label, "um", tuple(float(x) for x in delta),
                                tuple(float(x) for x in np.sqrt(np.clip(np.diag(C), 0, None))),
                                chi2, r, p))
    return out

