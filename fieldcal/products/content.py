r"""The numbers a calibration report and a certificate show, as plain rows.

Computed from a :class:`fieldcal.analysis.uncertainty.Calibration` (the document, its
covariance and arrays) and the version's residual table; :mod:`fieldcal.products.report`
and :mod:`fieldcal.products.certificate` only lay them out.

- :func:`interior_rows`: principal distance and principal point in mm and in pixels,
  with sigmas. The principal point in pixel coordinates is
  ``u0 = (W - 1)/2 + xp / d``, ``v0 = (H - 1)/2 - yp / d`` (docs/conventions.md).
- :func:`distortion_table`: the radial distortion and the decentering profile at field
  angles or radii, with 1-sigma from the covariance
  (:func:`fieldcal.analysis.uncertainty.radial_curve`, ``decentering_curve``). Tabulated as
  *distortion*, ``Delta r = -dr`` (measured minus ideal radius, positive away from the
  principal point), the sign of USGS calibration reports; the model's correction ``dr`` is
  its negative (docs/conventions.md section 2).
- :func:`adjustment_figures`: sigma0, redundancy (equations minus unknowns) and residuals.
- :func:`coverage`: which cells of the sensor hold observations.
- :func:`data_radius_mm`: how far from the principal point the data reach (beyond, the
  model is extrapolated).
- :func:`previous_version`: the calibration of the same camera acquired before this one.
- :func:`rig_rows`: the rig a head's calibration belongs to (its rig document, CONTRACT
  section 3 "Rig sessions"): per head its calibration's version, ``R_camera_to_rig`` as
  ``omega, phi, kappa`` [deg] (``R = Rz(kappa) Ry(phi) Rx(omega)``), the sigmas of a small
  rotation about the rig frame's axes [arcsec], the lever arm and its sigmas [mm].
- :func:`eccentricity_text`: the perspective eccentricity of the discs (``stats.eccentricity``):
  the largest correction applied [px] and how the targets' normals were obtained.
- :data:`MODEL_EQUATIONS`: the camera model ``fieldcal-brown/1`` in text.
"""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pyarrow as pa

from fieldcal.analysis.uncertainty import Calibration, decentering_curve, radial_curve
from fieldcal.model.camera import INDEX

__all__ = ["MODEL_EQUATIONS", "METHOD_NAMES", "interior_rows", "distortion_table", "field_angles_deg",
           "radii_mm", "adjustment_figures", "coverage", "data_radius_mm", "previous_version",
           "check_points", "parse_time", "residual_format", "sig", "rig_rows", "eccentricity_text",
           "board_text", "BOARD_MODEL_TEXT"]

MODEL_EQUATIONS = """\
xb = x' - xp        yb = y' - yp        r^2 = xb^2 + yb^2
radial = k0 + k1 r^2 + k2 r^4 + k3 r^6
dx = xb radial + p1 (r^2 + 2 xb^2) + 2 p2 xb yb + b1 xb + b2 yb
dy = yb radial + p2 (r^2 + 2 yb^2) + 2 p1 xb yb + a1 xb + a2 yb
xb + dx = -f R1 (X - C) / R3 (X - C)
yb + dy = -f R2 (X - C) / R3 (X - C)"""
"""The model fieldcal-brown/1 (docs/conventions.md section 2): ``(x', y')`` a measured image point [mm]
(x right, y up, origin at the sensor centre), ``R1..R3`` the rows of the world-to-camera
rotation, ``C`` the camera centre, ``X`` a world point [m]."""

METHOD_NAMES = {
    "field": "field calibration: an outdoor field of surveyed targets photographed from "
             "several stations, bundle adjustment (Wang et al. 2018)",
    "goniometer": "laboratory goniometer: a collimated point target on a turning arm, "
                  "minimum sum of squared distortion and distortion fit (Yuan et al. 2016)",
}


def _sigma(cal: Calibration, name: str) -> float | None:
    s = (cal.document.get("sigma") or {}).get(name)
    return None if s is None else float(s)


def interior_rows(cal: Calibration) -> list[dict]:
    """``name, mm, sigma_mm, px, sigma_px, note`` for f, xp, yp and the principal point in
    pixel coordinates (u0, v0)."""
    s = cal.sensor
    d = s.pixel_mm
    p = cal.camera.params
    f, xp, yp = (float(p[INDEX[n]]) for n in ("f_mm", "xp_mm", "yp_mm"))
    sf, sx, sy = (_sigma(cal, n) for n in ("f_mm", "xp_mm", "yp_mm"))
    u0, v0 = cal.camera.principal_point_px

    def px(v):
        return None if v is None else v / d
    return [
        {"name": "principal distance f", "mm": f, "sigma_mm": sf, "px": f / d, "sigma_px": px(sf),
         "note": "f / pixel pitch"},
        {"name": "principal point xp", "mm": xp, "sigma_mm": sx, "px": xp / d, "sigma_px": px(sx),
         "note": "from the sensor centre, x right"},
        {"name": "principal point yp", "mm": yp, "sigma_mm": sy, "px": yp / d, "sigma_px": px(sy),
         "note": "from the sensor centre, y up"},
        {"name": "principal point u0", "mm": None, "sigma_mm": None,
         "px": float(u0), "sigma_px": px(sx), "note": "pixel column"},
        {"name": "principal point v0", "mm": None, "sigma_mm": None,
         "px": float(v0), "sigma_px": px(sy), "note": "pixel row (down)"},
    ]


def _nice_step(span: float, n: int) -> float:
    """A round step (1, 2, 2.5 or 5 times a power of ten) giving about ``n`` steps over ``span``."""
    raw = span / max(n, 1)
    e = math.floor(math.log10(raw))
    for m in (1.0, 2.0, 2.5, 5.0, 10.0):
        if m * 10**e >= raw:
            return m * 10**e
    return 10.0 ** (e + 1)


def field_angles_deg(cal: Calibration, n: int = 8) -> np.ndarray:
    """Round field angles [deg] from one step out to the sensor's corner (about ``n``)."""
    theta_max = math.degrees(math.atan(cal.sensor.half_diagonal_mm / cal.camera.f_mm))
    step = _nice_step(theta_max, n)
    out = np.arange(step, theta_max + 1e-9, step)
    return np.append(out, theta_max) if theta_max - out[-1] > 0.25 * step else out


def radii_mm(cal: Calibration, n: int = 8) -> np.ndarray:
    """Round radii [mm] from one step out to the sensor's half diagonal (about ``n``)."""
    r_max = cal.sensor.half_diagonal_mm
    step = _nice_step(r_max, n)
    out = np.arange(step, r_max + 1e-9, step)
    return np.append(out, r_max) if r_max - out[-1] > 0.25 * step else out


def data_radius_mm(cal: Calibration, residuals: pa.Table | None) -> float | None:
    """The largest distance from the principal point of a used observation [mm], or None."""
    if residuals is None or residuals.num_rows == 0 or "u_px" not in residuals.column_names:
        return None
    uv = np.column_stack([residuals["u_px"].to_numpy(zero_copy_only=False),
                          residuals["v_px"].to_numpy(zero_copy_only=False)]).astype(float)
    used = (residuals["used"].to_numpy(zero_copy_only=False).astype(bool)
            if "used" in residuals.column_names else np.ones(len(uv), bool))
    ok = used & np.isfinite(uv).all(axis=1)
    if not ok.any():
        return None
    xy = cal.sensor.pixel_to_mm(uv[ok])
    pp = cal.camera.params[[INDEX["xp_mm"], INDEX["yp_mm"]]]
    return float(np.hypot(*(xy - pp).T).max())


def distortion_table(cal: Calibration, *, by: str = "angle", reach_mm: float | None = None,
                     n: int = 8) -> list[dict]:
    """Radial and decentering distortion at round field angles (``by="angle"``) or radii.

    Returns
    -------
    list of dict
        ``angle_deg, r_mm, radial_um, sigma_radial_um, decentering_um,
        sigma_decentering_um, extrapolated`` (beyond ``reach_mm``, the data's radius).
        ``radial_um`` is the distortion ``-dr`` (module docstring).
    """
    f = cal.camera.f_mm
    if by == "angle":
        ang = field_angles_deg(cal, n)
        r = f * np.tan(np.radians(ang))
    else:
        r = radii_mm(cal, n)
        ang = np.degrees(np.arctan(r / f))
    dr, s_dr = radial_curve(cal, r)
    dec, s_dec = decentering_curve(cal, r)
    return [{"angle_deg": float(a), "r_mm": float(x), "radial_um": float(-1000 * v),
             "sigma_radial_um": float(1000 * s), "decentering_um": float(1000 * dv),
             "sigma_decentering_um": float(1000 * sd),
             "extrapolated": bool(reach_mm is not None and x > reach_mm * (1 + 1e-9))}
            for a, x, v, s, dv, sd in zip(ang, r, dr, s_dr, dec, s_dec, strict=True)]


def adjustment_figures(cal: Calibration) -> dict:
    """``sigma0, redundancy, n_equations, n_unknowns, rmse_px, max_px, what`` of the adjustment.

    Field method: ``2 n_observations`` image equations (and three per surveyed target, which
    add as many unknowns); unknowns six per image, three per target whose survey was
    rejected, and the interior parameters. Goniometer: one equation per angle; unknowns the
    fitted coefficients, the two pointings and three (two with the paper's eq. 5) per sweep.
    """
    st = cal.document.get("stats") or {}
    p = len(cal.names)
    if cal.method == "goniometer":
        n_eq = int(st.get("n_angles") or st.get("n_observations") or 0)
        per_sweep = 2 if "eq. 5)" in str(st.get("solver", "")) else 3
        n_unk = int(st.get("n_fitted") or 0) + 2 * per_sweep
        return {"sigma0": st.get("sigma0"), "redundancy": n_eq - n_unk, "n_equations": n_eq,
                "n_unknowns": n_unk, "rmse_px": st.get("sigma_fit_px"), "max_px": st.get("max_px"),
                "what": "distortion-fit residual sigma (eq. 10) and largest residual along the axes"}
    n_obs = int(st.get("n_observations") or 0)
    n_img = int(st.get("n_images") or 0)
    n_free = int(st.get("n_surveys_rejected") or 0)
    n_eq = 2 * n_obs
    n_unk = 6 * n_img + 3 * n_free + p
    return {"sigma0": st.get("sigma0"), "redundancy": n_eq - n_unk, "n_equations": n_eq,
            "n_unknowns": n_unk, "rmse_px": st.get("rmse_px"), "max_px": st.get("max_px"),
            "what": "RMS and largest image residual"}


def coverage(cal: Calibration, residuals: pa.Table | None, cells: tuple[int, int] = (10, 8)) -> dict:
    """Which cells of a ``cells = (nx, ny)`` grid over the sensor hold used observations.

    Returns
    -------
    dict
        ``counts`` (ny, nx) int array, ``fraction`` of cells with at least one,
        ``radius_fraction`` (the data's radius over the half diagonal), ``cells``.
    """
    nx, ny = cells
    s = cal.sensor
    counts = np.zeros((ny, nx), int)
    if residuals is not None and residuals.num_rows and "u_px" in residuals.column_names:
        uv = np.column_stack([residuals["u_px"].to_numpy(zero_copy_only=False),
                              residuals["v_px"].to_numpy(zero_copy_only=False)]).astype(float)
        used = (residuals["used"].to_numpy(zero_copy_only=False).astype(bool)
                if "used" in residuals.column_names else np.ones(len(uv), bool))
        uv = uv[used & np.isfinite(uv).all(axis=1)]
        iu = np.clip(((uv[:, 0] + 0.5) * nx // s.width_px).astype(int), 0, nx - 1)
        iv = np.clip(((uv[:, 1] + 0.5) * ny // s.height_px).astype(int), 0, ny - 1)
        np.add.at(counts, (iv, iu), 1)
    reach = data_radius_mm(cal, residuals)
    return {"counts": counts, "fraction": float((counts > 0).mean()), "cells": cells,
            "radius_fraction": None if reach is None else float(reach / s.half_diagonal_mm)}


def sig(x, digits: int = 3) -> str:
    """A number with ``digits`` significant digits (``0.0412``, ``1.23``, ``123``): residuals of a
    good calibration are hundredths of a pixel, which three decimals print as ``0.000``."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return f"{x:#.{digits}g}".rstrip(".") if abs(x) < 10 ** digits else f"{x:.0f}"


def residual_format(rmse_px, max_px) -> str:
    """``"0.0412 px RMS, max 0.213 px"``: the adjustment's residual figures (:func:`sig`)."""
    return f"{sig(rmse_px)} px RMS, max {sig(max_px)} px"


def check_points(cal: Calibration) -> dict | None:
    """The document's check-point figures (``stats.check_points``), or None when it has none.

    Independent check points are withheld from the adjustment by another step of fieldcal;
    whatever figures it stored are shown as they are (a mapping of name to number or text).
    """
    cp = (cal.document.get("stats") or {}).get("check_points")
    if not cp:
        return None
    return dict(cp) if isinstance(cp, dict) else {"check points": cp}


def eccentricity_text(cal: Calibration) -> str | None:
    """One sentence on the perspective eccentricity of the discs (field method; docs/uncertainty.md
    section 2): the largest correction applied and how the normals were obtained (given,
    planar fit, estimated, none); None for a document without ``stats.eccentricity``."""
    ecc = (cal.document.get("stats") or {}).get("eccentricity")
    if cal.method != "field" or not isinstance(ecc, dict):
        return None
    counts = ecc.get("n_targets") or {}
    how = ", ".join(f"{k} ({v} targets)" for k, v in counts.items()) if counts else str(ecc.get("normals", "none"))
    if not ecc.get("applied"):
        why = ecc.get("reason") or "no target normal determined"
        text = f"perspective eccentricity of the discs not corrected ({why}); target normals: {how}"
    else:
        text = (f"perspective eccentricity of the discs corrected: largest correction {sig(ecc.get('max_px'))} px; "
                f"target normals: {how}")
    bound = ecc.get("uncorrected_bound_max_px")
    if ecc.get("n_left_out"):
        text += (f"; {ecc['n_left_out']} disc centres of undetermined normal (eccentricity up to {sig(bound)} px) "
                 "left out")
    elif isinstance(ecc.get("bias_bound"), dict) and ecc["bias_bound"].get("f_mm") is not None:
        text += (f"; discs of undetermined normal (eccentricity up to {sig(bound)} px) not corrected: the bias "
                 f"they can cause, up to {sig(1000 * ecc['bias_bound']['f_mm'])} µm in f, is in the sigmas")
    return text


BOARD_MODEL_TEXT = {
    "warp": "the board's nominal coordinates held fixed up to a low-order warp estimated in the adjustment",
    "rigid": "the board's nominal coordinates held fixed (a rigid, flat board)",
    "points": "every board point adjusted, its nominal coordinates weighted by their sigma",
}
"""How each board model (:mod:`fieldcal.field.board`) is named in the report and certificate."""


def board_text(cal: Calibration) -> str | None:
    """One sentence on a planar board's model (docs/uncertainty.md section 2c) and, for the warp
    model, its fitted shape with sigmas; None when the field is not a planar board."""
    b = (cal.document.get("stats") or {}).get("board")
    if cal.method != "field" or not isinstance(b, dict) or b.get("model") not in BOARD_MODEL_TEXT:
        return None
    text = f"planar board, board model '{b['model']}': {BOARD_MODEL_TEXT[b['model']]}"
    c, s = b.get("coefficients_mm") or {}, b.get("sigma_mm") or {}
    if b["model"] == "warp" and c:
        terms = {"warp_uu_mm": "bow along the first axis", "warp_vv_mm": "bow along the second axis",
                 "warp_uv_mm": "twist"}
        shape = "; ".join(f"{terms.get(k, k)} {sig(1000 * v)} ± {sig(1000 * s.get(k, float('nan')), 2)} µm"
                          for k, v in c.items())
        text += f" ({shape}; peak to valley over the targets {sig(1000 * b.get('peak_to_valley_mm', float('nan')))} µm)"
    return text


def parse_time(value) -> dt.datetime | None:
    if value is None:
        return None
    if isinstance(value, dt.datetime):
        return value if value.tzinfo else value.replace(tzinfo=dt.UTC)
    try:
        t = dt.datetime.fromisoformat(str(value).replace("Z", "+00:00"))
    except ValueError:
        return None
    return t if t.tzinfo else t.replace(tzinfo=dt.UTC)


def previous_version(lake, cal: Calibration) -> str | None:
    """The calibration of the same camera before this one, None for a camera's first.

    By :func:`fieldcal.lake.order.previous`: the latest version of the session just before
    this one's, by acquisition time, ties by commit order (two sessions acquired the same day
    are each other's neighbours)."""
    from fieldcal.lake import order

    return order.previous(lake.camera_rows(str(cal.document.get("camera_id"))), cal.version)


def rig_rows(rig: dict) -> list[dict]:
    """One row per head of a rig document (module docstring), the reference first as listed."""
    from fieldcal.model.rotations import opk_from_R_world_to_camera

    rows = []
    for h in rig["heads"]:
        R = np.asarray(h["R_camera_to_rig"], float)
        rows.append({"camera_id": h["camera_id"], "version": h["version"],
                     "role": "reference" if h["camera_id"] == rig["reference"] else "head",
                     "opk_deg": [float(a) for a in np.degrees(opk_from_R_world_to_camera(R.T))],
                     "sigma_rotation_arcsec": [float(v) for v in h["sigma_rotation_arcsec"]],
                     "t_mm": [1000.0 * float(v) for v in h["t_camera_in_rig_m"]],
                     "sigma_t_mm": [float(v) for v in h["sigma_t_mm"]], "rmse_px": h.get("rmse_px")})
    return rows
