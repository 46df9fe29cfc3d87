r"""The laboratory goniometer method (METHODS.md part B; Yuan et al. 2016, eq. 1-10).

A collimated point target on a turning arm is photographed at known arm angles ``W_i``
while its image sweeps the sensor's centre row (``x`` sweep) and, with the camera turned,
its centre column (``y`` sweep); several frames per angle (docs/conventions.md section 3, frames.csv).
:func:`calibrate` runs the method's steps in order, each in its module:

1. :mod:`fieldcal.goniometer.frames`: ``frames.csv``, the spot of each frame (fan-out
   friendly: :func:`~fieldcal.goniometer.frames.measure_frame`), and the mean of the
   usable frames of each angle with its standard error (the paper's multi-frame
   statistics).
2. :mod:`fieldcal.goniometer.minsum`: principal distance and point of each sweep by the
   minimum sum of squared distortion (eq. 1-7; linearised, or the rigorous eq. 2').
   The final ``f`` is that of the sweep spanning the wider angle; the other sweep's
   distortions use it too, so its scale difference is carried by ``k0`` (and ``b1``), as
   docs/conventions.md section 4 says.
3. :mod:`fieldcal.goniometer.chain`: the distortion values and the distortion fit with the
   sweeps' pointing (eq. 8-10), solved twice (the second time with the slopes of the
   fitted correction, which keep the principal point free of the set-up's alignment),
   and the precision of everything by propagating the a-posteriori accuracy of the spots
   through the whole chain.
4. :mod:`fieldcal.goniometer.result`: the calibration with its statistics and tables.

This module re-exports the public names of those modules for existing callers
(``from fieldcal.goniometer import method as gon; gon.measure_session(...)``). The session's
``frames.csv`` is read by :func:`fieldcal.session.frames.read_frames_csv`; the method is handed
the table.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

from fieldcal.errors import GeometryError
from fieldcal.goniometer.chain import (
    FIT_PARAMS,
    Chain,
    Sweep,
    along_axis_difference_px,
    along_slopes,
    chain_jacobian,
    unobserved_coefficients,
)
from fieldcal.goniometer.frames import (
    AXES,
    FRAME_FLAGS,
    MEASUREMENT_SCHEMA,
    average_frames,
    measure_frame,
    measure_session,
    measurements_table,
)
from fieldcal.goniometer.minsum import min_sum_linear, min_sum_rigorous
from fieldcal.goniometer.result import RESIDUAL_SCHEMA, GoniometerResult
from fieldcal.model import camera as cam
from fieldcal.model.camera import PARAM_NAMES, Sensor

__all__ = [
    "FRAME_FLAGS", "MEASUREMENT_SCHEMA", "FIT_PARAMS", "RESIDUAL_SCHEMA", "GoniometerResult",
    "measure_frame", "measurements_table", "measure_session",
    "average_frames", "min_sum_linear", "min_sum_rigorous", "calibrate",
    "along_axis_difference_px",
]


# --------------------------------------------------------------------------- the steps
def _rejected_summary(rejected: list) -> tuple[dict, str]:
    by_flag: dict[str, int] = {}
    for r in rejected:
        by_flag[r["flag"]] = by_flag.get(r["flag"], 0) + 1
    return by_flag, ", ".join(f"{n} {k}" for k, n in sorted(by_flag.items())) or "none rejected"


def _sweeps(sensor: Sensor, means: list, min_angles: int, zero_offset: bool, why: str) -> dict:
    """The two sweeps' mean spots in mm; a :class:`GeometryError` if one is too short."""
    sweeps = {}
    for a in AXES:
        ms = [m for m in means if m["axis"] == a]
        W = np.array([m["angle_deg"] for m in ms])
        if len(ms) < min_angles or not ((W > 0).any() and (W < 0).any()):
            raise GeometryError(
                f"the {a} sweep has {len(ms)} usable angle(s) "
                f"({int((W > 0).sum()) if len(ms) else 0} positive, "
                f"{int((W < 0).sum()) if len(ms) else 0} negative); need at least "
                f"{min_angles} on both sides of zero (frames rejected: {why})")
        xy = sensor.pixel_to_mm(np.array([m["uv"] for m in ms]))
        c = 0 if a == "x" else 1
        sweeps[a] = Sweep(a, W, xy[:, c].copy(), xy[:, 1 - c].copy())
    for a, sw in sweeps.items():
        f_a = min_sum_linear(sw.angle_deg, sw.along_mm, zero_offset=zero_offset)["f_mm"]
        if not f_a > 0:
            raise GeometryError(f"the {a} sweep gives f = {f_a:.3f} mm: the sign of angle_deg or "
                                f"the axis label in frames.csv is wrong")
    return sweeps


def _solve(sweeps: dict, f_axis: str, rigorous: bool, zero_offset: bool, fit_pointing: bool,
           observable_fraction: float):
    """Both variants, the unobserved coefficients held at 0, the slopes of the second pass.

    Returns ``(chains, sols, fixed, mask)``; ``chains`` and ``sols`` keyed by ``rigorous``.
    """
    along0 = {a: sw.along_mm for a, sw in sweeps.items()}
    chains = {r: Chain(sweeps, r, zero_offset, f_axis, fit_pointing) for r in (False, True)}
    sols = {r: chains[r].solve(along0) for r in (False, True)}
    # coefficients that the sweeps cannot determine are held at 0, the same for both variants
    sol = sols[rigorous]
    fixed = unobserved_coefficients(sol["points"], sol["comp"], sol["params"], observable_fraction)
    mask = np.array([n not in fixed for n in FIT_PARAMS])
    for r in (False, True):
        chains[r].fit_mask = mask
        sols[r] = chains[r].solve(along0)
        chains[r].slopes = along_slopes(sweeps, sols[r])           # eq. 5'': the second pass
        sols[r] = chains[r].solve(along0, sols[r])
    return chains, sols, fixed, mask


def _covariance(chain: Chain, sweeps: dict, sol: dict, mask, step_mm: float):
    """``(cov13, sigma, sd_out, sigma0_mm)``: the chain's covariance (module docstring of
    :mod:`fieldcal.goniometer.chain`) mapped onto the 13 parameters."""
    along0 = {a: sw.along_mm for a, sw in sweeps.items()}
    n = sum(sw.along_mm.size for sw in sweeps.values())
    J = chain_jacobian(chain, along0, sol, step_mm)
    v = sol["v"]
    R = J[-n:, :]
    dof_eff = float(np.sum(R * R))
    sigma0_mm = float(np.sqrt(v @ v / dof_eff)) if dof_eff > 0 else math.nan
    cov_out = sigma0_mm ** 2 * (J[:-n] @ J[:-n].T)
    idx13 = [cam.F, cam.XP, cam.YP] + [cam.INDEX[nm] for nm, k in zip(FIT_PARAMS, mask, strict=True) if k]
    rows = [0, 1, 2] + list(range(5, 5 + int(mask.sum())))
    cov13 = np.full((13, 13), np.nan)
    cov13[np.ix_(idx13, idx13)] = cov_out[np.ix_(rows, rows)]
    sd = np.sqrt(np.clip(np.diag(cov_out), 0, None))
    sigma = dict.fromkeys(PARAM_NAMES)
    for k, j in zip(rows, idx13, strict=True):
        sigma[PARAM_NAMES[j]] = float(sd[k])
    return cov13, sigma, sd, sigma0_mm


def _linearisation(sensor: Sensor, sols: dict, means: list) -> dict:
    """What the linearisation changes: rigorous minus linearised."""
    lin, rig = sols[False], sols[True]
    uv_all = np.array([m["uv"] for a in AXES for m in means if m["axis"] == a])
    axis_all = np.array([a for a in AXES for m in means if m["axis"] == a])
    dl = along_axis_difference_px(rig["params"], lin["params"], sensor, uv_all, axis_all)
    return {
        "df_mm": float(rig["params"][cam.F] - lin["params"][cam.F]),
        "dxp_mm": float(rig["params"][cam.XP] - lin["params"][cam.XP]),
        "dyp_mm": float(rig["params"][cam.YP] - lin["params"][cam.YP]),
        "dfx_mm": rig["axes"]["x"]["f_mm"] - lin["axes"]["x"]["f_mm"],
        "dfy_mm": rig["axes"]["y"]["f_mm"] - lin["axes"]["y"]["f_mm"],
        "rms_px": float(np.sqrt(np.mean(dl ** 2))), "max_px": float(np.abs(dl).max()),
    }


def _frame_scatter_px(means: list) -> float:
    """RMS standard error of the mean along the axes [px] (NaN with single frames)."""
    se = np.array([m["se"][0 if a == "x" else 1] for a in AXES for m in means if m["axis"] == a])
    se = se[np.isfinite(se)]
    return float(np.sqrt(np.mean(se ** 2))) if se.size else math.nan


def _stats(sensor, sweeps, means, rejected, sols, f_axis, rigorous, zero_offset, fixed, n_fit,
           sd, sigma0_mm, nominal_focal_mm) -> dict:
    """The result's ``stats`` (see :func:`calibrate`)."""
    sol, lin, rig = sols[rigorous], sols[False], sols[True]
    d = sensor.pixel_mm
    params, v = sol["params"], sol["v"]
    n = v.size
    by_flag, _ = _rejected_summary(rejected)
    se_rms = _frame_scatter_px(means)
    sigma0_px = sigma0_mm / d
    notes = []
    if nominal_focal_mm is not None and abs(params[cam.F] / nominal_focal_mm - 1) > 0.1:
        notes.append(f"f = {params[cam.F]:.3f} mm is more than 10% from the nominal "
                     f"{nominal_focal_mm:g} mm")
    n_frames = int(sum(len(m["files"]) for m in means))
    return {
        "n_frames": n_frames, "n_angles": len(means), "n_rejected": len(rejected),
        "rejected_by_flag": by_flag,
        "fx_mm": float(sol["axes"]["x"]["f_mm"]), "fy_mm": float(sol["axes"]["y"]["f_mm"]),
        "px_mm": float(params[cam.XP]), "py_mm": float(params[cam.YP]),
        "sigma_axes": {"fx_mm": float(sd[3]), "fy_mm": float(sd[4]),
                       "px_mm": float(sd[1]), "py_mm": float(sd[2])},
        "sigma_fit_px": float(np.sqrt(v @ v / (n - n_fit)) / d) if n > n_fit else math.nan,
        "n_fitted": n_fit,
        "sigma0_px": float(sigma0_px),
        "sigma0": float(sigma0_px / se_rms) if np.isfinite(se_rms) and se_rms > 0 else None,
        "rmse_px": float(np.sqrt(np.mean(v ** 2)) / d),
        "max_px": float(np.abs(v).max() / d),
        "max_distortion_px": float(np.abs(sol["D"]).max() / d),
        "f_axis": f_axis,
        "half_span_deg": {a: float(np.abs(sweeps[a].angle_deg).max()) for a in AXES},
        "zero_offset_px": {a: float(lin["axes"][a]["c_mm"] / d) for a in AXES},
        "pointing_arcsec": {a: float(np.degrees(sol["pointing_rad"][a]) * 3600) for a in AXES},
        "misalignment": {a: {"w0_arcsec": float(np.degrees(rig["axes"][a]["w0_rad"]) * 3600),
                             "tilt_mrad": float(1e3 * rig["axes"][a]["tilt_rad"])} for a in AXES},
        "linearisation": _linearisation(sensor, sols, means),
        "fixed_parameters": fixed,
        "solver": "min-sum rigorous (eq. 2')" if rigorous else
                  ("min-sum linear (eq. 5')" if zero_offset else "min-sum linear (eq. 5)"),
        "notes": notes,
        "n_images": n_frames,
        "n_observations": len(means),
    }


def _tables(sensor: Sensor, sweeps: dict, means: list, sol: dict):
    """``(images, residuals)``: the frames used and the per-angle residual table."""
    d = sensor.pixel_mm
    images, rows = [], []
    off = 0
    for a in AXES:
        ms = [m for m in means if m["axis"] == a]
        sw = sweeps[a]
        for i, m in enumerate(ms):
            for f, (u, vv) in zip(m["files"], m["frames_uv"], strict=True):
                images.append({"file": f, "axis": a, "angle_deg": m["angle_deg"],
                               "u_px": float(u), "v_px": float(vv)})
            rows.append({"axis": a, "angle_deg": m["angle_deg"], "n_frames": len(m["files"]),
                         "u_px": float(m["uv"][0]), "v_px": float(m["uv"][1]),
                         "se_u_px": float(m["se"][0]), "se_v_px": float(m["se"][1]),
                         "along_mm": float(sw.along_mm[i]), "cross_mm": float(sw.cross_mm[i]),
                         "distortion_px": float(sol["D"][off + i] / d),
                         "fit_px": float(sol["fit"][off + i] / d),
                         "residual_px": float(sol["v"][off + i] / d)})
        off += len(ms)
    return images, pa.Table.from_pylist(rows, schema=RESIDUAL_SCHEMA)


# --------------------------------------------------------------------------- calibrate
def calibrate(sensor: Sensor, frames: pa.Table, measurements: pa.Table, *,
              nominal_focal_mm: float | None = None, rigorous: bool = False,
              zero_offset: bool = True, min_angles_per_axis: int = 5,
              max_frame_spread_px: float = 2.0, observable_fraction: float = 0.05,
              fit_pointing: bool = True, jacobian_step_mm: float = 1e-6) -> GoniometerResult:
    """Calibrate a camera from a goniometer session (the module docstring's steps).

    Parameters
    ----------
    sensor : Sensor
    frames : pyarrow.Table
        ``file, axis, angle_deg`` (as :func:`read_frames_csv` returns; a ``problem`` column,
        if present, marks rows to report and skip).
    measurements : pyarrow.Table
        :data:`MEASUREMENT_SCHEMA` rows (at least ``file, u_px, v_px, flag, reason``).
    nominal_focal_mm : float, optional
        For a plausibility note in ``stats["notes"]`` (more than 10% off).
    rigorous : bool
        Take f and the principal point from the exact eq. 2' rather than eq. 5'.
    zero_offset : bool
        Estimate where the arm's zero landed (eq. 5' / ``W0`` in eq. 2'); False: the
        paper's equations verbatim.
    min_angles_per_axis : int
        Fewer usable angles on a sweep is a :class:`GeometryError`.
    max_frame_spread_px : float
        With 3 or more frames at an angle, a frame this far from their median is rejected.
    observable_fraction : float
        See :func:`fieldcal.goniometer.chain.unobserved_coefficients` (held at 0).
    fit_pointing : bool
        Fit the sweeps' pointing with the distortion (:mod:`fieldcal.goniometer.chain`);
        False only to show what it is for.
    jacobian_step_mm : float
        Central-difference step of the precision estimate [mm].

    Returns
    -------
    GoniometerResult
        ``stats`` holds: ``n_frames, n_angles, n_rejected, rejected_by_flag, fx_mm, fy_mm,
        px_mm, py_mm, sigma_axes, sigma_fit_px`` (eq. 10), ``n_fitted``, ``sigma0_px`` (the
        a-posteriori accuracy of one averaged spot coordinate) and ``sigma0`` (its ratio to
        the RMS frame-to-frame standard error; None with single frames), ``rmse_px`` and
        ``max_px`` of the fit residuals, ``max_distortion_px`` before the fit, ``f_axis``,
        ``half_span_deg``, ``zero_offset_px`` (where the arm's zero landed, eq. 5'),
        ``pointing_arcsec`` (the sweeps' fitted pointing), ``misalignment`` (rigorous: ``w0_arcsec``,
        ``tilt_mrad`` per axis), ``linearisation`` (rigorous minus linearised: ``df_mm,
        dxp_mm, dyp_mm``, per axis ``dfx_mm`` ..., and along the axes ``rms_px, max_px``),
        ``fixed_parameters``, ``solver``, ``notes``; for the lake catalog also
        ``n_images`` (= n_frames), ``n_observations`` (= n_angles), ``sigma0``.
        ``residuals`` columns: ``axis, angle_deg, n_frames, u_px, v_px, se_u_px, se_v_px,
        along_mm, cross_mm, distortion_px`` (before the fit), ``fit_px``, ``residual_px``.

    Raises
    ------
    GeometryError
        A sweep has fewer than ``min_angles_per_axis`` usable angles, or no angle on one
        side of zero, or gives a non-positive f (angle sign or axis label wrong).
    InputError
        A table lacks a required column.
    """
    means, rejected = average_frames(frames, measurements, max_frame_spread_px)
    _, why = _rejected_summary(rejected)
    sweeps = _sweeps(sensor, means, min_angles_per_axis, zero_offset, why)
    f_axis = max(AXES, key=lambda a: (sweeps[a].span_deg, a == "x"))
    chains, sols, fixed, mask = _solve(sweeps, f_axis, rigorous, zero_offset, fit_pointing,
                                       observable_fraction)
    n = sum(sw.along_mm.size for sw in sweeps.values())
    n_fit = int(mask.sum()) + 2 * fit_pointing     # the coefficients and the sweeps' pointing
    n_unknown = n_fit + 2 * (3 if zero_offset else 2)
    if n < n_unknown + 2:
        raise GeometryError(f"{n} usable angles for {n_unknown} unknowns (interior orientation "
                            f"per sweep and the distortion fit); need at least {n_unknown + 2} "
                            f"(frames rejected: {why})")
    sol = sols[rigorous]
    cov13, sigma, sd, sigma0_mm = _covariance(chains[rigorous], sweeps, sol, mask, jacobian_step_mm)
    stats = _stats(sensor, sweeps, means, rejected, sols, f_axis, rigorous, zero_offset, fixed,
                   n_fit, sd, sigma0_mm, nominal_focal_mm)
    images, residuals = _tables(sensor, sweeps, means, sol)
    return GoniometerResult(sensor, sol["params"].copy(), sigma, cov13, stats, images, rejected,
                            residuals)
