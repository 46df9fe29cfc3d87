r"""Which focal length to use: the model's ``f``, the effective and the calibrated focal length.

A calibration of ``fieldcal-brown/1`` (docs/conventions.md section 2) gives the principal
distance ``f`` *together with* its correction polynomial. Copied alone into a tool whose
model has no linear radial term (a pinhole, OpenCV, a USGS report), ``f`` is wrong by that
term: the goniometer method estimates ``k0`` (Yuan et al. 2016, eq. 8-10; METHODS B), and
``k0 = -0.0154`` carries a 1.5 % scale. Three focal lengths are therefore stated, each with
the distortion it goes with:

* **f**, the model's principal distance: exact with the model's correction (``k0..k3``,
  ``p1, p2``, ``a1, a2, b1, b2``), for fieldcal's own products and exports.
* **The effective focal length** ``f_e = f / (1 + k0)``: the paraxial focal length, the scale
  of the image near the principal point. A measured point at a small radius ``r`` corrects
  to ``r (1 + k0)``, which the collinearity equations set to ``f tan(theta)``; so
  ``r = f_e tan(theta)``. For the field method (``k0`` held at 0), ``f_e = f``.
* **The calibrated focal length with balanced distortion** ``c`` (the USGS calibration
  report's "calibrated focal length"): the focal length that makes the radial distortion,
  relative to it, smallest in the least-squares sense over the field. With ``rho(theta)``
  the radial distance of the measured image of a ray at field angle ``theta`` from the
  principal point, averaged over the four semi-diagonals, the distortion relative to a
  focal length ``c`` is ``D_c(theta) = rho(theta) - c tan(theta)``, and

      c = sum_i rho(theta_i) tan(theta_i) / sum_i tan^2(theta_i)

  over :data:`BALANCE_ANGLES` field angles evenly spaced from 0 to the radius the data reach
  (the sensor's half diagonal when that is not known). A tool that takes a focal length and
  a table of radial distortion takes ``c`` with :func:`semi_diagonal_table`'s ``D_c``.

The radial distortion along one semi-diagonal (the direction from the principal point to a
sensor corner; USGS reports each of the four and their mean) is the radial component of the
measured image of a ray whose ideal image lies on that diagonal at field angle ``theta``:
``rho_k(theta) = (distort(f tan(theta) e_k) - pp) . e_k``, with the model's full correction
(radial, decentering and affine terms), so the four differ by the decentering and affine
terms. Positive distortion: the image lies farther from the principal point than the
pinhole image of focal length ``c`` (the sign of the USGS reports).

Standard uncertainties are propagated to first order from the interior covariance
(:class:`fieldcal.analysis.uncertainty.Calibration`) through central differences of each
figure with respect to the estimated parameters.
"""

from __future__ import annotations

import math

import numpy as np

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.model.camera import INDEX, distort

__all__ = ["BALANCE_ANGLES", "DIAGONALS", "effective_focal", "balanced_focal", "semi_diagonal_table",
           "distortion_relative", "diagonal_directions"]

BALANCE_ANGLES = 60
"""Field angles over which the calibrated focal length balances the distortion."""
DIAGONALS = ("upper right (+x, +y)", "upper left (-x, +y)", "lower left (-x, -y)", "lower right (+x, -y)")
"""The four semi-diagonals, in the image-plane frame (x right, y up)."""


def _propagate(cal: Calibration, fn) -> tuple[np.ndarray, np.ndarray]:
    """``fn(params)`` (a float array) and its first-order 1-sigma from the interior covariance."""
    p0 = np.asarray(cal.camera.params, float)
    value = np.asarray(fn(p0), float)
    cols = []
    for name in cal.names:
        j = INDEX[name]
        h = 1e-6 * _unit(cal, name)
        up, dn = p0.copy(), p0.copy()
        up[j] += h
        dn[j] -= h
        cols.append((np.asarray(fn(up), float) - np.asarray(fn(dn), float)) / (2 * h))
    if not cols:
        return value, np.zeros_like(value)
    J = np.stack(cols, axis=-1)
    var = np.einsum("...i,ij,...j->...", J, cal.covariance, J)
    return value, np.sqrt(np.clip(var, 0.0, None))


def _unit(cal: Calibration, name: str) -> float:
    """A parameter's natural size: the change that moves an image point at the half diagonal
    ``R`` by about ``R`` (f: f itself; xp, yp: 1 mm; k_n: ``R^-2n``; p1, p2: ``R^-1``)."""
    if name == "f_mm":
        return float(cal.camera.f_mm)
    r = max(cal.sensor.half_diagonal_mm, 1e-3)
    return {"k1": r**-2, "k2": r**-4, "k3": r**-6, "p1": r**-1, "p2": r**-1}.get(name, 1.0)


def effective_focal(cal: Calibration) -> tuple[float, float | None]:
    """``f / (1 + k0)`` [mm] and its 1-sigma (None without a covariance of f)."""
    value, sigma = _propagate(cal, lambda p: np.array([p[INDEX["f_mm"]] / (1.0 + p[INDEX["k0"]])]))
    return float(value[0]), (float(sigma[0]) if "f_mm" in cal.names else None)


def diagonal_directions(cal: Calibration, params=None) -> np.ndarray:
    """Unit vectors (4, 2) from the principal point to the sensor's corner pixel centres, in
    :data:`DIAGONALS` order."""
    p = cal.camera.params if params is None else params
    s = cal.sensor
    hx = (s.width_px - 1) / 2 * s.pixel_mm
    hy = (s.height_px - 1) / 2 * s.pixel_mm
    corners = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
    v = corners - np.asarray(p)[[INDEX["xp_mm"], INDEX["yp_mm"]]]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _rho(cal: Calibration, p, theta_deg) -> np.ndarray:
    """Radial distance (4, n) [mm] of the measured image of rays at ``theta_deg`` on each diagonal."""
    e = diagonal_directions(cal)                          # fixed directions: the table's frame
    t = np.tan(np.radians(np.asarray(theta_deg, float)))
    q = p[INDEX["f_mm"]] * t[None, :, None] * e[:, None, :]           # ideal points, from the pp
    x = distort(q, p, check=False)                                     # measured, from the centre
    pp = p[[INDEX["xp_mm"], INDEX["yp_mm"]]]
    return np.einsum("knj,kj->kn", x - pp, e)


def _corner_angle_deg(cal: Calibration) -> float:
    """The largest field angle of the sensor: the farthest corner's ideal radius over f."""
    p = cal.camera.params
    s = cal.sensor
    hx = (s.width_px - 1) / 2 * s.pixel_mm
    hy = (s.height_px - 1) / 2 * s.pixel_mm
    from fieldcal.model.camera import correct

    q = correct(np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]]), p)
    return float(np.degrees(np.arctan(np.hypot(*q.T).max() / p[INDEX["f_mm"]])))


def _balance_angles(cal: Calibration, reach_mm: float | None) -> np.ndarray:
    theta_max = _corner_angle_deg(cal)
    if reach_mm is not None and reach_mm > 0:
        theta_max = min(theta_max, math.degrees(math.atan(reach_mm / cal.camera.f_mm)))
    return np.linspace(0.0, theta_max, BALANCE_ANGLES + 1)[1:]


def _balanced(cal: Calibration, p, theta_deg) -> float:
    t = np.tan(np.radians(theta_deg))
    rho = _rho(cal, p, theta_deg).mean(axis=0)
    ok = np.isfinite(rho)
    return float(np.sum(rho[ok] * t[ok]) / np.sum(t[ok] ** 2))


def balanced_focal(cal: Calibration, reach_mm: float | None = None) -> dict:
    """The calibrated focal length with balanced distortion (module docstring).

    Returns
    -------
    dict
        ``c_mm, sigma_mm`` (None without a covariance of f), ``theta_max_deg`` (the field angle
        balanced to), ``rms_um, max_um`` (the mean radial distortion relative to ``c`` over
        those angles), ``max_f_um`` (relative to ``f``, for comparison).
    """
    theta = _balance_angles(cal, reach_mm)
    c, s = _propagate(cal, lambda p: np.array([_balanced(cal, p, theta)]))
    c = float(c[0])
    p = cal.camera.params
    t = np.tan(np.radians(theta))
    rho = _rho(cal, p, theta).mean(axis=0)
    d_c = 1000 * (rho - c * t)
    d_f = 1000 * (rho - p[INDEX["f_mm"]] * t)
    return {"c_mm": c, "sigma_mm": float(s[0]) if "f_mm" in cal.names else None,
            "theta_max_deg": float(theta[-1]), "rms_um": float(np.sqrt(np.nanmean(d_c**2))),
            "max_um": float(np.nanmax(np.abs(d_c))), "max_f_um": float(np.nanmax(np.abs(d_f)))}


def _focal_fn(cal: Calibration, focal, reach_mm):
    """``params -> focal length [mm]`` for ``focal`` = ``"f"``, ``"balanced"`` or a number."""
    if focal == "f":
        return lambda p: p[INDEX["f_mm"]]
    if focal == "balanced":
        theta = _balance_angles(cal, reach_mm)
        return lambda p: _balanced(cal, p, theta)
    return lambda p: float(focal)


def distortion_relative(cal: Calibration, theta_deg, focal="balanced", reach_mm: float | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radial distortion [um] relative to a focal length at field angles ``theta_deg`` (n,).

    ``focal``: ``"f"`` (the model's), ``"balanced"`` (:func:`balanced_focal`, to ``reach_mm``)
    or a number [mm]. Returns the distortion on the four diagonals (4, n), the radial distance
    ``rho`` (4, n) [mm] and the 1-sigma (n,) [um] of the diagonals' mean, the focal length's
    own uncertainty included (a number is held).
    """
    theta = np.asarray(theta_deg, float)
    t = np.tan(np.radians(theta))
    fc = _focal_fn(cal, focal, reach_mm)
    p0 = cal.camera.params
    rho = _rho(cal, p0, theta)
    _, sigma = _propagate(cal, lambda p: _rho(cal, p, theta).mean(axis=0) - fc(p) * t)
    return 1000 * (rho - fc(p0) * t), rho, 1000 * sigma


def semi_diagonal_table(cal: Calibration, angles_deg, focal="balanced", reach_mm: float | None = None
                        ) -> list[dict]:
    """Radial distortion relative to a focal length (:func:`distortion_relative`) at field
    angles, per semi-diagonal.

    Returns
    -------
    list of dict
        ``angle_deg, diagonals_um`` (4 values in :data:`DIAGONALS` order, NaN beyond the
        diagonal's corner), ``mean_um, sigma_um`` (1-sigma of the mean), ``r_mm`` (the mean
        radial distance of the measured image from the principal point), ``extrapolated``
        (beyond the radius the data reach).
    """
    angles = np.asarray(angles_deg, float)
    d, rho, sigma = distortion_relative(cal, angles, focal, reach_mm)
    s = cal.sensor
    p = cal.camera.params
    hx = (s.width_px - 1) / 2 * s.pixel_mm
    hy = (s.height_px - 1) / 2 * s.pixel_mm
    pp = p[[INDEX["xp_mm"], INDEX["yp_mm"]]]
    corner = np.hypot(np.array([hx, -hx, -hx, hx]) - pp[0], np.array([hy, hy, -hy, -hy]) - pp[1])
    inside = rho <= corner[:, None] * (1 + 1e-9)
    d = np.where(inside, d, np.nan)
    rows = []
    for j, a in enumerate(angles):
        col = d[:, j]
        rows.append({"angle_deg": float(a), "r_mm": float(np.mean(rho[:, j])),
                     "diagonals_um": [float(x) for x in col],
                     "mean_um": float(np.mean(col)) if inside[:, j].all() else math.nan,
                     "sigma_um": float(sigma[j]),
                     "extrapolated": bool(reach_mm is not None and np.min(rho[:, j]) > reach_mm * (1 + 1e-9))})
    return rows
