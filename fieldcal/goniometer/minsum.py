r"""Principal distance and point of one sweep: minimum sum of squared distortion.

METHODS.md part B, eq. 1-7 (Yuan et al. 2016). Along one sweep let ``L_i`` be the spot's
measured coordinate [mm] along the axis (x for the ``x`` sweep, y -- up -- for the ``y``
sweep; docs/conventions.md) and ``t_i = tan W_i``. With principal distance ``f`` and
principal-point offset ``p`` along the axis, the ideal image of the target is
``p + f tan(W_i - dW)`` (eq. 1) and its distortion

    D_i = f tan(W_i - dW) - L_i + p                                        (eq. 2)

is the contract's correction along the axis (ideal minus measured; ``D = dx`` of
:func:`fieldcal.model.camera.correction` with ``xp = p``). The paper aligns the arm's zero on
the sensor centre, so the zero ray makes the angle ``dW = atan(p/f)`` with the optical
axis, and linearises ``tan(W - dW) ~ tan W - sec^2 W dW`` (eq. 3-4):

    D_i = f t_i - p t_i^2 - L_i                                            (eq. 5)

``f, p`` minimise ``sum D_i^2``: a linear least-squares problem (eq. 6-7).

Zero offset
-----------
The alignment is never perfect: the zero lands at ``c`` (a fraction of a pixel) instead
of the centre, i.e. its ray is turned by ``w = -c/f`` more. Linearising
``L - p = f tan(W - dW - w)`` gives ``L_i ~ c + f t_i - p' t_i^2`` with ``p' = p - c``.
Fitted without ``c``, the constant is partly taken up by the ``t`` and ``t^2`` columns,
so ``f`` and ``p`` carry the alignment error; by default (``zero_offset=True``) eq. 6-7
therefore have the third unknown ``c``:

    D_i = f t_i - p' t_i^2 + c - L_i,      p = c + p'                      (eq. 5')

which is eq. 5 when the alignment is perfect. ``zero_offset=False`` is eq. 5 verbatim.

The distortion's slope
----------------------
A turn of the arm's zero by ``w`` moves the *ideal* image by ``f sec^2 W w``, but the
measured point by that divided by ``1 + s_i``, ``s_i = dD/dL`` the slope of the
correction along the axis at the point (a lens with 20 px of barrel distortion has
``|s| ~ 0.1`` at the end of a sweep). Eq. 5' models the ideal shift, so the difference
``m_i f sec^2 W_i w`` (``m = s / (1 + s)``) is left in ``D``; its even part moves ``p'``
and hence ``p`` by about ``3 k1 f^2 c`` (0.2 ``c`` for the Canon 24 mm lens): the principal
point would follow the alignment of each session. With the slopes known (from the
distortion fit of a first pass: ``slope``), the minimised quantity is the distortion
without that modulation of the zero offset,

    rho_i = D_i - m_i sec^2 W_i c                                          (eq. 5'')

i.e. eq. 5' with the column of ``c`` replaced by ``1 - m_i sec^2 W_i``: a turn of the
zero now changes only ``c``. ``rho = D`` for a set-up aligned as the paper asks
(``c = 0``) and for ``slope = 0``, so the convention -- which ``f`` and ``p`` the method
calls the camera's -- is the paper's.

Rigorous variant
----------------
The exact eq. 1-2 with the set-up's small misalignments instead of the linearisation: a
tilt ``tau`` of the spot's track (a line fitted through the measured points; ``L`` is
then the coordinate along that line) and an angle offset ``W0`` of the arm (its zero
need not point at the sensor centre):

    D_i = p + f tan(phi_i) - L_i,      phi_i = W_i + W0 - atan(p/f)        (eq. 2')

minimised (as ``rho_i = D_i - m_i f sec^2(phi_i) W0``, the same correction of the
slope) over ``f, p, W0`` by non-linear least squares (SciPy, from the linear solution).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import least_squares

__all__ = ["min_sum_linear", "min_sum_rigorous", "track_coordinate", "slope_weight"]


def slope_weight(slope) -> np.ndarray:
    """``m = s / (1 + s)`` (n,) of the distortion's slope ``s`` (module docstring); 0 if None."""
    s = np.asarray(0.0 if slope is None else slope, float)
    return s / (1.0 + s)


def min_sum_linear(angle_deg, along_mm, *, zero_offset: bool = True, slope=None) -> dict:
    """Principal distance and point of one sweep by eq. 5-7 (module docstring).

    Parameters
    ----------
    angle_deg : (n,) array_like
        Encoder angles W [deg].
    along_mm : (n,) array_like
        Measured coordinates L along the swept axis [mm].
    zero_offset : bool
        Add the unknown ``c`` (where the arm's zero lands) to eq. 5.
    slope : (n,) array_like, optional
        The slope ``s_i = dD/dL`` of the correction along the axis at each point
        (eq. 5''); default 0 (eq. 5').

    Returns
    -------
    dict
        ``f_mm``, ``p_mm`` (principal-point offset along the axis), ``pprime_mm``
        (coefficient of ``-tan^2 W``), ``c_mm`` (0 without ``zero_offset``) and
        ``distortion_mm`` (n,), the ``D_i`` of eq. 5 / 5'.
    """
    t = np.tan(np.radians(np.asarray(angle_deg, float)))
    L = np.asarray(along_mm, float)
    m = np.broadcast_to(slope_weight(slope), t.shape)
    cols = [t, -t * t] + ([1.0 - m * (1.0 + t * t)] if zero_offset else [])
    A = np.column_stack(cols)
    theta = np.linalg.lstsq(A, L, rcond=None)[0]
    f, pp = theta[0], theta[1]
    c = theta[2] if zero_offset else 0.0
    return {"f_mm": float(f), "p_mm": float(c + pp), "pprime_mm": float(pp), "c_mm": float(c),
            "distortion_mm": f * t - pp * t * t + c - L}


def track_coordinate(along, cross):
    """Tilt [rad] of the line through the points and their coordinate along it [mm]."""
    slope = np.polyfit(along, cross, 1)[0] if along.size >= 2 else 0.0
    tau = math.atan(slope)
    return tau, along * math.cos(tau) + cross * math.sin(tau)


def _rigorous_residual(theta, W, L, zero_offset, m):
    f, p = theta[0], theta[1]
    w0 = theta[2] if zero_offset else 0.0
    phi = W + w0 - np.arctan(p / f)
    return p + f * np.tan(phi) - L - m * f / np.cos(phi) ** 2 * w0


def min_sum_rigorous(angle_deg, along_mm, cross_mm=None, *, zero_offset: bool = True,
                     start: dict | None = None, slope=None) -> dict:
    """Principal distance and point of one sweep from the exact eq. 2' (module docstring).

    Parameters
    ----------
    angle_deg, along_mm : (n,) array_like
        As :func:`min_sum_linear`.
    cross_mm : (n,) array_like, optional
        The perpendicular coordinates [mm]; with them the track's tilt is fitted and ``L``
        is the coordinate along the tilted track.
    zero_offset : bool
        Estimate the arm's angle offset ``W0`` (else 0: eq. 1-2 verbatim).
    start : dict, optional
        A :func:`min_sum_linear` or :func:`min_sum_rigorous` result to start from.
    slope : (n,) array_like, optional
        As :func:`min_sum_linear`.

    Returns
    -------
    dict
        ``f_mm``, ``p_mm``, ``w0_rad``, ``tilt_rad``, ``distortion_mm`` (n,) (eq. 2') and the
        track coordinate ``track_mm`` (n,).
    """
    W = np.radians(np.asarray(angle_deg, float))
    along = np.asarray(along_mm, float)
    if cross_mm is None:
        tau, L = 0.0, along
    else:
        tau, L = track_coordinate(along, np.asarray(cross_mm, float))
    m = np.broadcast_to(slope_weight(slope), W.shape)
    if start is None:
        start = min_sum_linear(angle_deg, along, zero_offset=zero_offset, slope=slope)
    f0, p0 = start["f_mm"], start["p_mm"]
    w00 = start.get("w0_rad", start.get("c_mm", 0.0) / f0)
    x0 = np.array([f0, p0, w00] if zero_offset else [f0, p0])
    scale = np.array([abs(f0), 0.01, 1e-3] if zero_offset else [abs(f0), 0.01])
    sol = least_squares(_rigorous_residual, x0, args=(W, L, zero_offset, m), method="lm",
                        x_scale=scale, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
    f, p = sol.x[0], sol.x[1]
    w0 = sol.x[2] if zero_offset else 0.0
    phi = W + w0 - np.arctan(p / f)
    return {"f_mm": float(f), "p_mm": float(p), "w0_rad": float(w0), "tilt_rad": float(tau),
            "distortion_mm": p + f * np.tan(phi) - L, "track_mm": L}
