r"""The goniometer calibration as one function of the measured coordinates, and its precision.

METHODS.md part B, eq. 8-10, after the per-sweep interior orientation of
:mod:`fieldcal.goniometer.minsum`.

Distortion fit (eq. 8-10)
-------------------------
With ``f`` and the principal point ``(px, py)`` fixed, each angle gives one distortion
value: ``D_i`` is ``dx`` at the measured point of the ``x`` sweep, ``dy`` of the ``y``
sweep. The contract's correction model is linear in ``k0, k1, k2, k3, p1, p2, b1, b2``
(the columns are :func:`fieldcal.model.camera.correct_jacobian`'s) and is fitted by least
squares together with one nuisance unknown per sweep, its *pointing* ``kappa``: a rotation
of the sweep by ``kappa`` moves its ideal image points by ``f sec^2(phi_i) kappa`` (``phi_i``
the angle from the optical axis: ``W_i``, or ``W_i + W0 - atan(p/f)`` in the rigorous
variant). The min-sum step makes every sweep's ``D`` free of constant, ``tan`` and
``tan^2`` components, but the model's terms are not (``p1 (r^2 + 2 xb^2)`` has a mean; a
shifted centre of the radial terms has even parts); without the pointing, the model cannot
follow and leaves systematic residuals (``fit_pointing=False``; on the full-size Canon
scenario, noise-free, 0.11 px RMS instead of 0.005 px: bench/bench_goniometer.py). The
pointing is not a camera parameter -- where the optical axis points is not observed --
and is reported as ``stats["pointing_arcsec"]``.

``sigma_fit = sqrt(sum v_i^2 / (n - t))`` (eq. 10) over the ``n`` distortion values and
``t`` unknowns of the fit (the coefficients and the two pointings). A coefficient that the
two sweeps cannot exercise is held at 0 (:func:`unobserved_coefficients`): this is ``b2``
in practice (the shear moves ``dx`` in proportion to ``yb``, and the ``x`` sweep stays on
the principal point's row, where ``b2 yb`` is a constant that the pointing has).

The chain is solved twice: the second time with the slopes of the fitted correction
along each sweep (:func:`along_slopes`), which the min-sum step needs to keep the
principal point free of the set-up's alignment (:mod:`fieldcal.goniometer.minsum`, eq. 5'').

Precision
---------
The whole chain (per-axis fits, choice of ``f``, distortion values, distortion fit) is a
smooth function of the ``n`` measured along-axis coordinates; its Jacobian ``J`` is taken
by central differences (:func:`chain_jacobian`, the slopes held at their values). With
``v`` the fit residuals and ``R = dv/dL``, the a-posteriori accuracy of one averaged spot
coordinate is ``sigma0 = sqrt(v'v / trace(R'R))`` (unbiased for independent errors), and
the covariance of everything is ``sigma0^2 J J'``. Correlations between the sweeps (the
final ``f``) and the effect of the principal point on the distortion columns are thereby
included.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fieldcal.goniometer.frames import AXES
from fieldcal.goniometer.minsum import min_sum_linear, min_sum_rigorous
from fieldcal.model import camera as cam
from fieldcal.model.camera import Sensor

__all__ = ["FIT_PARAMS", "Sweep", "Chain", "design_matrix", "unobserved_coefficients",
           "along_slopes", "chain_jacobian", "along_axis_difference_px"]

FIT_PARAMS: tuple[str, ...] = ("k0", "k1", "k2", "k3", "p1", "p2", "b1", "b2")
"""The coefficients of the distortion fit (eq. 9), in :data:`fieldcal.model.camera.PARAM_NAMES` order."""
_FIT_IDX = np.array([cam.INDEX[n] for n in FIT_PARAMS])


@dataclass
class Sweep:
    """One sweep's mean spots: ``angle_deg`` (n,) [deg], the measured coordinate along the
    axis ``along_mm`` (n,) and the perpendicular one ``cross_mm`` (n,) [mm]."""

    axis: str
    angle_deg: np.ndarray
    along_mm: np.ndarray
    cross_mm: np.ndarray

    @property
    def span_deg(self) -> float:
        return float(self.angle_deg.max() - self.angle_deg.min())

    def points_mm(self, along=None):
        """The measured image points (n, 2) [mm], with ``along`` replacing ``along_mm``."""
        a = self.along_mm if along is None else along
        return np.column_stack([a, self.cross_mm] if self.axis == "x" else [self.cross_mm, a])


def design_matrix(points_mm, comp, params):
    """Columns of the distortion fit (n, 8): d(correction along ``comp``)/d(coefficient)."""
    _, _, Q = cam.correct_jacobian(points_mm, params)
    return Q[np.arange(len(comp)), comp][:, _FIT_IDX]


@dataclass
class Chain:
    """The calibration as a function of the along-axis coordinates (for its Jacobian).

    ``slopes`` (per axis, (n,)): the correction's slope along the axis at each point,
    passed to the min-sum step (eq. 5''); None for the first pass.
    """

    sweeps: dict
    rigorous: bool
    zero_offset: bool
    f_axis: str
    fit_pointing: bool = True
    fit_mask: np.ndarray = field(default_factory=lambda: np.ones(len(FIT_PARAMS), bool))
    slopes: dict | None = None

    def _axes(self, along: dict, start: dict | None) -> dict:
        axes = {}
        for a, sw in self.sweeps.items():
            slope = None if self.slopes is None else self.slopes[a]
            if self.rigorous:
                st = start["axes"][a] if start else None
                axes[a] = min_sum_rigorous(sw.angle_deg, along[a], sw.cross_mm,
                                           zero_offset=self.zero_offset, start=st, slope=slope)
            else:
                axes[a] = min_sum_linear(sw.angle_deg, along[a], zero_offset=self.zero_offset,
                                         slope=slope)
        return axes

    def _distortions(self, along: dict, axes: dict, f: float):
        """Per point: D (eq. 2 / 2'), sec^2 of the angle from the axis, component, point."""
        D, comp, pts, sec2 = [], [], [], []
        for a, sw in self.sweeps.items():
            W = np.radians(sw.angle_deg)
            s = axes[a]
            if self.rigorous:
                w0 = s["w0_rad"] if self.zero_offset else 0.0
                phi = W + w0 - np.arctan(s["p_mm"] / f)
                D.append(s["p_mm"] + f * np.tan(phi) - s["track_mm"])
            else:
                phi = W
                t = np.tan(W)
                D.append(f * t - s["pprime_mm"] * t * t + s["c_mm"] - along[a])
            sec2.append(1.0 / np.cos(phi) ** 2)
            comp.append(np.full(W.size, 0 if a == "x" else 1))
            pts.append(sw.points_mm(along[a]))
        return (np.concatenate(x) for x in (D, sec2, comp, pts))

    def solve(self, along: dict, start: dict | None = None) -> dict:
        """Interior orientation per sweep, then the distortion fit; everything as a dict."""
        axes = self._axes(along, start)
        f = axes[self.f_axis]["f_mm"]
        D, sec2, comp, pts = self._distortions(along, axes, f)
        params = np.zeros(13)
        params[[cam.F, cam.XP, cam.YP]] = f, axes["x"]["p_mm"], axes["y"]["p_mm"]
        B = design_matrix(pts, comp, params)
        # the sweeps' pointing (nuisance): a rotation by kappa moves the image by f sec^2(phi) kappa
        K = f * sec2[:, None] * np.column_stack([comp == 0, comp == 1]) * float(self.fit_pointing)
        Bm = np.column_stack([B[:, self.fit_mask], K])
        scale = np.abs(Bm).max(axis=0)
        scale[scale == 0] = 1.0
        x = np.linalg.lstsq(Bm / scale, D, rcond=None)[0] / scale
        beta = np.zeros(len(FIT_PARAMS))
        beta[self.fit_mask] = x[:-2]
        params[_FIT_IDX] = beta
        fit = Bm @ x
        return {"axes": axes, "params": params, "D": D, "fit": fit, "v": D - fit,
                "pointing_rad": {"x": float(x[-2]), "y": float(x[-1])},
                "comp": comp, "points": pts}

    def outputs(self, sol: dict) -> np.ndarray:
        """The vector whose Jacobian is taken: f, px, py, fx, fy, fitted coefficients, v."""
        p = sol["params"]
        return np.concatenate([[p[cam.F], p[cam.XP], p[cam.YP], sol["axes"]["x"]["f_mm"],
                                sol["axes"]["y"]["f_mm"]], p[_FIT_IDX][self.fit_mask], sol["v"]])


def along_slopes(sweeps: dict, sol: dict) -> dict:
    """Per axis (n,): the slope ``dD/dL`` of the fitted correction along the axis at each point."""
    _, G, _ = cam.correct_jacobian(sol["points"], sol["params"], columns=[])
    comp = sol["comp"]
    s = G[np.arange(len(comp)), comp, comp] - 1.0
    out, k = {}, 0
    for a, sw in sweeps.items():
        out[a] = s[k:k + sw.along_mm.size].copy()
        k += sw.along_mm.size
    return out


def unobserved_coefficients(points_mm, comp, params, fraction: float) -> dict:
    """Coefficients that the sweeps do not exercise, with why: {name: reason}.

    A coefficient is unobserved when the max |column| over the observations is below
    ``fraction`` of its max over the box the sweeps span (both components). Comparing with
    the spanned box, not the whole sensor, keeps short sweeps from losing their
    higher-order terms (they are exercised, over a shorter range), while ``b2``, which
    moves ``dx`` in proportion to ``yb`` and is observed only on the ``x`` sweep, where
    ``yb`` stays near 0, is caught.
    """
    B = design_matrix(points_mm, comp, params)
    lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 21), np.linspace(lo[1], hi[1], 15))
    _, _, Q = cam.correct_jacobian(np.column_stack([gx.ravel(), gy.ravel()]), params)
    reach = np.abs(Q[:, :, _FIT_IDX]).max(axis=(0, 1))
    seen = np.abs(B).max(axis=0)
    fixed = {}
    for j, name in enumerate(FIT_PARAMS):
        if seen[j] < fraction * reach[j]:
            why = ("the x sweep stays on the principal point's row, where dx = b2 yb is a constant"
                   if name == "b2" else "the sweeps hardly exercise it")
            fixed[name] = (f"not observed: its column reaches {seen[j]:.3g} on the sweeps, "
                           f"{reach[j]:.3g} over the area they span ({why})")
    return fixed


def chain_jacobian(chain: Chain, along: dict, sol: dict, step_mm: float) -> np.ndarray:
    """``d chain.outputs / d along`` (n_out, n) by central differences of step ``step_mm``.

    Columns in :data:`fieldcal.goniometer.frames.AXES` order, points in sweep order.
    """
    n = sum(along[a].size for a in AXES)
    J = np.empty((chain.outputs(sol).size, n))
    col = 0
    for a in AXES:
        for i in range(along[a].size):
            plus = {b: v.copy() for b, v in along.items()}
            minus = {b: v.copy() for b, v in along.items()}
            plus[a][i] += step_mm
            minus[a][i] -= step_mm
            J[:, col] = (chain.outputs(chain.solve(plus, sol))
                         - chain.outputs(chain.solve(minus, sol))) / (2 * step_mm)
            col += 1
    return J


def along_axis_difference_px(params_a, params_b, sensor: Sensor, uv_px, axis) -> np.ndarray:
    """How two camera models differ along the scanned axes, without the common pointing.

    For each measured point, the angle that each model assigns to it along its axis,
    ``atan(q_axis / f)`` with ``q`` the model's ideal point (:func:`fieldcal.model.camera.correct`),
    is compared; the mean difference per axis (where the optical axis points, which the
    goniometer does not observe) is removed, and the rest is expressed as an image
    displacement ``f sec^2(angle) dangle`` of model ``b`` [px].

    Parameters
    ----------
    params_a, params_b : (13,) array_like
        Two camera parameter vectors.
    sensor : Sensor
    uv_px : (n, 2) array_like
        Measured points [px].
    axis : (n,) array_like of {"x", "y"}
        The axis each point was swept along (its component is compared).

    Returns
    -------
    (n,) ndarray [px]
    """
    pa_, pb = np.asarray(params_a, float), np.asarray(params_b, float)
    xy = sensor.pixel_to_mm(np.asarray(uv_px, float))
    comp = np.where(np.asarray(axis) == "x", 0, 1)
    idx = np.arange(len(comp))
    qa, qb = cam.correct(xy, pa_)[idx, comp], cam.correct(xy, pb)[idx, comp]
    ang_a, ang_b = np.arctan(qa / pa_[cam.F]), np.arctan(qb / pb[cam.F])
    diff = ang_a - ang_b
    for c in (0, 1):
        m = comp == c
        if m.any():
            diff[m] -= diff[m].mean()
    return diff * pb[cam.F] / np.cos(ang_b) ** 2 / sensor.pixel_mm
