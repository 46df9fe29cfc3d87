"""The calibration report (one self-contained HTML file plus PNGs) and the fleet summary.

:func:`write_report` reads one committed version from the lake and writes
``<out>/report.html`` (plots embedded as base64 PNG, no external resources) and each plot
as ``<out>/<name>.png``. The report holds:

- what the calibration is (camera, session, version, method, dates, inputs' fingerprint);
- for a head of a rig, the rig: every head's relative orientation with its sigmas [arcsec,
  mm] and calibration version (:func:`fieldcal.products.report_sections.rig_section`);
- what went in and what was left out, and why (images, frames, observations rejected as
  blunders, surveyed coordinates rejected, parameters held fixed);
- the parameter table: values, a-posteriori sigmas, units, ``|value| / sigma``; parameters
  not significant at 3 sigma marked, correlations above 0.95 highlighted (and the whole
  correlation matrix);
- plots (:mod:`fieldcal.products.plots`): field method -- residual vectors over the sensor
  (magnified, with the scale), mean residuals per image (the field paper's Fig. 5), camera
  stations and the target field in 3D (its Fig. 6); both methods -- radial and
  decentering distortion curves with their uncertainty bands, the projection-uncertainty
  map (:mod:`fieldcal.analysis.uncertainty`), the correlation matrix; goniometer method -- the
  distortion along each swept axis before and after the fit (the lab paper's Figs. 4-7).

:func:`fleet_summary` gives every camera's latest calibration against its previous one (the
change test the commit stored, :mod:`fieldcal.products.status`) and flags those that moved
significantly and by more than a tolerance; :func:`parameter_tolerance` turns an image-plane tolerance
into one per parameter for history plots.
"""

from __future__ import annotations

import base64
import datetime as dt
import html
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM, check_level, compare_calibrations, judge
from fieldcal.analysis.uncertainty import Calibration, uncertainty_map
from fieldcal.errors import InputError, LakeError
from fieldcal.model.camera import INDEX, PARAM_NAMES, correction
from fieldcal.products import content, plots
from fieldcal.products import report_sections as sections

__all__ = ["FIELD_FIGURES", "GONIOMETER_FIGURES", "UNITS", "ReportFiles", "parameter_rows",
           "inputs_summary", "goniometer_axis_table", "image_table", "build_figures",
           "render_html", "write_report", "parameter_tolerance", "fleet_summary", "residual_statistics",
           "CORRELATION_THRESHOLD", "SIGNIFICANCE_SIGMAS"]

FIELD_FIGURES = ("residual_vectors", "residual_histogram", "residuals_per_image", "stations_3d",
                 "distortion_curves", "distortion_vectors", "uncertainty_map", "correlation")
GONIOMETER_FIGURES = ("axis_distortion", "residual_histogram", "distortion_curves", "distortion_vectors",
                      "uncertainty_map", "correlation")
UNITS = {"f_mm": "mm", "xp_mm": "mm", "yp_mm": "mm", "k0": "1", "k1": "mm^-2", "k2": "mm^-4",
         "k3": "mm^-6", "p1": "mm^-1", "p2": "mm^-1", "a1": "1", "a2": "1", "b1": "1", "b2": "1"}
CORRELATION_THRESHOLD = 0.95
SIGNIFICANCE_SIGMAS = 3.0
COVARIANCE_SOURCES = {"covariance": "propagated from the version's stored covariance of the parameters",
                      "sigmas": "from the parameters' sigmas only: this version stores no covariance, "
                                "so their correlations are unknown"}
"""How the report names :attr:`fieldcal.analysis.uncertainty.Calibration.covariance_source`."""
METHOD_SETS = {"field": ("f_mm", "xp_mm", "yp_mm", "k1", "k2", "k3", "p1", "p2", "a1", "a2"),
               "goniometer": ("f_mm", "xp_mm", "yp_mm", "k0", "k1", "k2", "k3", "p1", "p2",
                              "b1", "b2")}


# --------------------------------------------------------------------------------------
# tables
# --------------------------------------------------------------------------------------
def parameter_rows(cal: Calibration, *, threshold: float = CORRELATION_THRESHOLD,
                   n_sigma: float = SIGNIFICANCE_SIGMAS) -> list[dict]:
    """One row per parameter: ``name, value, sigma, unit, t, estimated, significant,
    status, correlated`` (a list of ``(other, r)`` with ``|r| > threshold``)."""
    doc = cal.document
    fixed = (doc.get("stats") or {}).get("fixed_parameters") or {}
    method_set = METHOD_SETS.get(cal.method, ())
    corr = cal.correlation()
    rows = []
    for name in PARAM_NAMES:
        value = float(cal.camera.params[INDEX[name]])
        sigma = doc["sigma"].get(name)
        estimated = sigma is not None
        t = abs(value) / sigma if estimated and sigma > 0 else (math.inf if estimated else None)
        significant = bool(t is not None and t >= n_sigma)
        if estimated:
            status = "estimated" if significant else f"not significant at {n_sigma:g} sigma"
        elif name in fixed:
            status = f"held fixed: {fixed[name]}"
        elif name in method_set:
            status = "held fixed"
        else:
            status = f"fixed by the {cal.method} method"
        correlated = []
        if name in cal.names:
            i = cal.names.index(name)
            for j, other in enumerate(cal.names):
                if j != i and abs(corr[i, j]) > threshold:
                    correlated.append((other, float(corr[i, j])))
        rows.append({"name": name, "value": value, "sigma": sigma, "unit": UNITS[name], "t": t,
                     "estimated": estimated, "significant": significant, "status": status,
                     "correlated": correlated})
    return rows


def _residual_columns(residuals: pa.Table) -> dict:
    cols = {}
    for name in ("image", "target_id", "u_px", "v_px", "du_px", "dv_px", "used", "reason",
                 "normalized_residual", "axis", "angle_deg", "sigma_px"):
        if name in residuals.column_names:
            cols[name] = residuals[name].to_numpy(zero_copy_only=False)
    for name in ("distortion_px", "fit_px"):
        if name in residuals.column_names:
            cols[name] = residuals[name].to_numpy(zero_copy_only=False)
    return cols


def image_table(cal: Calibration, residuals: pa.Table) -> list[dict]:
    """Field method, per image of the document: ``file, station, n_used, n_rejected,
    mean_abs_u_px, mean_abs_v_px, rmse_px`` from the residual table."""
    r = _residual_columns(residuals)
    images = cal.document.get("images") or []
    out = []
    img = r.get("image", np.array([], object)).astype(str) if len(residuals) else np.array([], str)
    used = r.get("used", np.zeros(0, bool)).astype(bool)
    for im in images:
        k = img == im["file"]
        ku = k & used
        du = r["du_px"][ku] if ku.any() else np.zeros(0)
        dv = r["dv_px"][ku] if ku.any() else np.zeros(0)
        out.append({"file": im["file"], "station": im.get("station"), "n_used": int(ku.sum()),
                    "n_rejected": int((k & ~used).sum()),
                    "mean_abs_u_px": float(np.mean(np.abs(du))) if du.size else math.nan,
                    "mean_abs_v_px": float(np.mean(np.abs(dv))) if dv.size else math.nan,
                    "rmse_px": float(np.sqrt(np.mean(du**2 + dv**2))) if du.size else math.nan})
    return out


def residual_statistics(residuals: pa.Table) -> list[dict]:
    """Per image (or frame) of a residual table, either method: ``image, n_used,
    n_rejected, rmse_px`` (over the used rows, ``sqrt(mean(du^2 + dv^2))``), ``max_px``."""
    import pyarrow.compute as pc

    t = residuals.select(["image", "du_px", "dv_px", "used"])
    sq = pc.add(pc.multiply(t["du_px"], t["du_px"]), pc.multiply(t["dv_px"], t["dv_px"]))
    used_sq = pc.if_else(t["used"], sq, pa.scalar(None, pa.float64()))
    g = pa.table({"image": t["image"], "used": pc.cast(t["used"], pa.int64()), "sq": used_sq,
                  "rejected": pc.cast(pc.invert(t["used"]), pa.int64())}).group_by("image")
    agg = g.aggregate([("used", "sum"), ("rejected", "sum"), ("sq", "mean"), ("sq", "max")]).sort_by("image")
    return [{"image": r["image"], "n_used": int(r["used_sum"] or 0), "n_rejected": int(r["rejected_sum"] or 0),
             "rmse_px": math.sqrt(r["sq_mean"]) if r["sq_mean"] is not None else math.nan,
             "max_px": math.sqrt(r["sq_max"]) if r["sq_max"] is not None else math.nan}
            for r in agg.to_pylist()]


def inputs_summary(cal: Calibration, residuals: pa.Table) -> dict:
    """What went in and what was left out, and why.

    Returns
    -------
    dict
        ``went_in`` (list of str), ``left_out`` (list of ``{"what", "item", "why"}``),
        ``rejected_by_reason`` ({reason: count}), ``notes`` (list of str).
    """
    doc = cal.document
    st = doc.get("stats") or {}
    r = _residual_columns(residuals)
    used = r.get("used", np.zeros(0, bool)).astype(bool)
    reasons = r.get("reason", np.zeros(0, object))
    by_reason: dict[str, int] = {}
    for why in reasons[~used]:
        key = str(why) if why is not None else "no reason recorded"
        key = key.split(" w=")[0] if key.startswith("blunder") else key
        by_reason[key] = by_reason.get(key, 0) + 1
    went_in, left_out, notes = [], [], []
    fixed = st.get("fixed_parameters") or {}
    if cal.method == "field":
        images = doc.get("images") or []
        went_in.append(f"{st.get('n_images', len(images))} images ({len(images)} listed in the "
                       f"document), {st.get('n_observations')} image points of "
                       f"{st.get('n_targets')} targets in the final adjustment")
        went_in.append("surveyed target coordinates entered as weighted observations"
                       if st.get("targets_adjusted") else "surveyed target coordinates held fixed")
        if (ecc := content.eccentricity_text(cal)) is not None:
            went_in.append(ecc)
        if (board := content.board_text(cal)) is not None:
            went_in.append(board)
        detailed = st.get("left_out") if isinstance(st.get("left_out"), list) else None
        named = set()
        for item in detailed or []:
            if isinstance(item, dict):
                name = item.get("image") or item.get("file")
                named.add(name)
                left_out.append({"what": "image", "item": name,
                                 "why": item.get("reason") or item.get("status") or "left out"})
        for name in st.get("left_out_images") or []:
            if name not in named:
                named.add(name)
                left_out.append({"what": "image", "item": name,
                                 "why": "left out before the adjustment (no reason recorded in "
                                        "the document)"})
        for im in images:
            if im.get("n_observations") == 0 and im["file"] not in named:
                left_out.append({"what": "image", "item": im["file"],
                                 "why": "no usable image points"})
        if used.size:
            n_bad = int((~used).sum())
            img = r.get("image")
            tgt = r.get("target_id")
            w = r.get("normalized_residual")
            for k in np.flatnonzero(~used):
                left_out.append({"what": "image point", "item": f"{img[k]} / {tgt[k]}",
                                 "why": str(reasons[k]) + (f" (|w| = {abs(w[k]):.1f})"
                                                          if w is not None and w[k] is not None
                                                          and np.isfinite(w[k])
                                                          and " w=" not in str(reasons[k]) else "")})
            went_in.append(f"{int(used.sum())} of {used.size} measured image points used, "
                           f"{n_bad} rejected")
        for t in st.get("rejected_surveys") or []:
            left_out.append({"what": "surveyed coordinates", "item": str(t),
                             "why": "rejected by the survey test (the target's images agree, "
                                    "its surveyed position does not)"})
    else:
        went_in.append(f"{st.get('n_frames')} frames at {st.get('n_angles')} angles "
                       f"(x sweep ±{(st.get('half_span_deg') or {}).get('x', float('nan')):.1f}°, "
                       f"y sweep ±{(st.get('half_span_deg') or {}).get('y', float('nan')):.1f}°)")
        went_in.append(f"interior orientation by {st.get('solver')}; f from the "
                       f"{st.get('f_axis', '?')} sweep")
        img = r.get("image")
        for k in np.flatnonzero(~used):
            left_out.append({"what": "frame", "item": str(img[k]) if img is not None else "?",
                             "why": str(reasons[k])})
        notes.extend(str(n) for n in st.get("notes") or [])
    for name, why in fixed.items():
        left_out.append({"what": "parameter", "item": name, "why": f"held fixed: {why}"})
    if cal.covariance_source != "covariance":
        notes.append("this version has no stored covariance: uncertainties use the sigmas only "
                     "(correlations unknown)")
    return {"went_in": went_in, "left_out": left_out, "rejected_by_reason": by_reason,
            "notes": notes}


def goniometer_axis_table(cal: Calibration, residuals: pa.Table) -> dict:
    """Distortion along the swept axes before and after the fit, per angle.

    The lake's residual table holds, per angle, the mean spot ``(u, v)`` and the fit
    residual ``v`` along the axis (``du_px`` for the x sweep, ``dv_px`` for the y sweep:
    measured minus model). Before the fit the distortion is ``D = fit + v`` with the
    fitted model along the axis (:mod:`fieldcal.goniometer.method`, eq. 8-10)::

        fit = correction(x')_axis + f sec^2(phi) kappa_axis

    (``kappa``: the sweep's pointing, ``stats.pointing_arcsec``; ``phi = W`` for the
    linearised interior orientation, ``W + W0 - atan(p/f)`` for the rigorous one). When the
    table carries ``distortion_px`` and ``fit_px`` columns they are used as they are.

    Returns
    -------
    dict of (n,) arrays
        ``axis, angle_deg, position_px, before_px, fit_px, after_px``.
    """
    st = cal.document.get("stats") or {}
    r = _residual_columns(residuals)
    used = r["used"].astype(bool)
    used &= np.isin(r.get("axis", np.full(len(used), None, object)), ["x", "y"])
    axis = r["axis"][used].astype(str)
    W = np.radians(r["angle_deg"][used].astype(float))
    uv = np.column_stack([r["u_px"][used], r["v_px"][used]]).astype(float)
    s = cal.sensor
    d = s.pixel_mm
    xy = s.pixel_to_mm(uv)
    comp = np.where(axis == "x", 0, 1)
    idx = np.arange(len(comp))
    du = r["du_px"][used].astype(float)
    dv = r["dv_px"][used].astype(float)
    after_mm = np.where(axis == "x", -du * d, dv * d)          # v = D - fit, image-plane axis
    if "distortion_px" in r and "fit_px" in r:
        before = r["distortion_px"][used].astype(float)
        fit = r["fit_px"][used].astype(float)
    else:
        p = cal.camera.params
        f = p[INDEX["f_mm"]]
        pointing = st.get("pointing_arcsec") or {}
        kappa = np.array([math.radians(float(pointing.get(a, 0.0)) / 3600.0) for a in axis])
        phi = W
        if "rigorous" in str(st.get("solver", "")):
            mis = st.get("misalignment") or {}
            w0 = np.array([math.radians(float((mis.get(a) or {}).get("w0_arcsec", 0.0)) / 3600.0)
                           for a in axis])
            pp = np.where(axis == "x", p[INDEX["xp_mm"]], p[INDEX["yp_mm"]])
            phi = W + w0 - np.arctan(pp / f)
        fit_mm = correction(xy, p)[idx, comp] + f / np.cos(phi) ** 2 * kappa
        fit = fit_mm / d
        before = (fit_mm + after_mm) / d
    position = np.where(axis == "x", uv[:, 0] - (s.width_px - 1) / 2, (s.height_px - 1) / 2 - uv[:, 1])
    return {"axis": axis, "angle_deg": np.degrees(W), "position_px": position,
            "before_px": before, "fit_px": fit, "after_px": after_mm / d}


# --------------------------------------------------------------------------------------
# figures
# --------------------------------------------------------------------------------------
def _residual_histogram(cal: Calibration, r: dict, used):
    """The residuals against the normal distribution they should follow (figure, caption).

    Field method: each component divided by its a-priori sigma; expected sigma
    ``sigma0 sqrt(redundancy / equations)`` (the mean redundancy number; the targets' survey
    equations count when the targets were adjusted). Goniometer: the fit residuals along the
    axes [px]; expected ``sigma_fit sqrt((n - t) / n)`` (eq. 10).
    """
    st = cal.document.get("stats") or {}
    adj = content.adjustment_figures(cal)
    if cal.method == "field":
        sig = np.asarray(r.get("sigma_px", np.ones(len(used))), float)[used]
        z = np.concatenate([np.asarray(r["du_px"], float)[used] / sig, np.asarray(r["dv_px"], float)[used] / sig])
        n_eq = adj["n_equations"] + (3 * int(st.get("n_targets") or 0) if st.get("targets_adjusted") else 0)
        expected = float(st.get("sigma0") or 1.0) * math.sqrt(max(adj["redundancy"], 0) / max(n_eq, 1))
        T = np.asarray(r.get("normalized_residual", np.full(len(used), np.nan)), float)[used]
        fig = plots.residual_histogram(z, expected, what="image residual / its a-priori sigma",
                                       statistic=T if np.isfinite(T).any() else None)
        cap = ("Left: image residual components (u and v) over their a-priori sigmas, with the "
               "normal curve they should follow, sigma0 x sqrt(redundancy / equations) (the mean "
               "redundancy number: approximate, since a target seen in few images keeps less of "
               "its error in the residuals). Right: each point's residual over its own "
               "sigma (its redundancy included), squared, against the chi-square density with 2 "
               "degrees of freedom it follows exactly when the a-priori sigmas are right.")
    else:
        axis = np.asarray(r.get("axis", np.full(len(used), None, object)))
        z = np.where(axis == "x", np.asarray(r["du_px"], float), np.asarray(r["dv_px"], float))[used]
        n = int(np.isfinite(z).sum())
        t = int(st.get("n_fitted") or 0)
        expected = float(st.get("sigma_fit_px") or 0.0) * math.sqrt(max(n - t, 0) / max(n, 1))
        fig = plots.residual_histogram(z, expected, what="fit residual along the axis", unit="px")
        cap = ("Residuals of the distortion fit along the swept axes, with the normal curve "
               "they should follow: sigma_fit (eq. 10) x sqrt((n - t) / n).")
    return fig, cap


def _distortion_vectors(cal: Calibration, points_uv):
    """The 2-D correction field of the Zarr group (or of the parameters) (figure, caption)."""
    F = cal.arrays.get("correction_field")
    gu, gv = cal.arrays.get("grid_u_px"), cal.arrays.get("grid_v_px")
    if F is None or gu is None or gv is None:
        gu, gv = cal.sensor.grid_px(41, 31)[:41, 0], cal.sensor.grid_px(41, 31)[::41, 1]
        uu, vv = np.meshgrid(gu, gv)
        F = correction(cal.sensor.pixel_to_mm(np.column_stack([uu.ravel(), vv.ravel()])),
                       cal.camera.params) / cal.sensor.pixel_mm
        F[:, 1] *= -1.0
        F = F.reshape(len(gv), len(gu), 2)
    fig = plots.distortion_vectors(gu, gv, F, cal.sensor, reach_px=points_uv)
    cap = ("The model's correction (from the measured to the ideal point, in pixels along u and v) "
           "over the sensor: vectors magnified as the key says, the size in colour; red dots are the "
           "observations" + (" (off the two scanned axes the goniometer's model is an extrapolation)"
                             if cal.method == "goniometer" else "") + ".")
    return fig, cap


def build_figures(cal: Calibration, residuals: pa.Table) -> dict:
    """``{name: (Figure, caption)}`` for the report, in :data:`FIELD_FIGURES` or
    :data:`GONIOMETER_FIGURES` order."""
    r = _residual_columns(residuals)
    s = cal.sensor
    figs = {}
    uv = np.column_stack([r.get("u_px", np.zeros(0)), r.get("v_px", np.zeros(0))]).astype(float)
    used = r.get("used", np.zeros(0, bool)).astype(bool)
    if cal.method == "field":
        duv = np.column_stack([r["du_px"], r["dv_px"]]).astype(float)
        figs["residual_vectors"] = (
            plots.residual_vectors(uv, duv, s, used=used),
            "Residual vectors (measured minus adjusted model) over the sensor, magnified as the "
            "key says; bold arrows are the mean residual per cell, red crosses rejected points.")
        rows = image_table(cal, residuals)
        left = [x["item"] for x in inputs_summary(cal, residuals)["left_out"] if x["what"] == "image"]
        figs["residuals_per_image"] = (
            plots.residuals_per_image([x["file"] for x in rows], [x["mean_abs_u_px"] for x in rows],
                                      [x["mean_abs_v_px"] for x in rows], [x["rmse_px"] for x in rows],
                                      [x["station"] for x in rows], left_out=left),
            "Mean absolute residuals in u and v and the RMS per image (as in the field paper's "
            "Fig. 5), stations shaded.")
        C = cal.arrays.get("exterior/center_m")
        R = cal.arrays.get("exterior/rotation_world_to_camera")
        if C is None:
            images = cal.document.get("images") or []
            C = np.array([im["center_m"] for im in images], float)
            R = np.array([im["rotation_world_to_camera"] for im in images], float)
        T = cal.arrays.get("targets/xyz_m")
        figs["stations_3d"] = (
            plots.stations_3d(C, R, stations=[im.get("station") for im in cal.document.get("images") or []],
                              targets_xyz_m=T),
            "Camera stations and the adjusted target field (as in the field paper's Fig. 6)."
            + ("" if T is not None else " This version stores no target coordinates "
               "(they were held fixed), so only the cameras are drawn."))
    else:
        table = goniometer_axis_table(cal, residuals)
        figs["axis_distortion"] = (
            plots.goniometer_axes(table, sigma_fit_px=(cal.document.get("stats") or {}).get("sigma_fit_px")),
            "Distortion along each swept axis after the interior orientation (left) and the "
            "residuals after the distortion fit (right), as in the lab paper's Figs. 4-7.")
    figs["residual_histogram"] = _residual_histogram(cal, r, used)
    ordered = {}
    for name in ("residual_vectors", "axis_distortion", "residual_histogram", "residuals_per_image",
                 "stations_3d"):
        if name in figs:
            ordered[name] = figs[name]
    figs = ordered
    reach = None
    if used.any():
        ok = used & np.isfinite(uv).all(axis=1)
        if ok.any():
            reach = float(np.hypot(*(s.pixel_to_mm(uv[ok]) - cal.camera.params[1:3]).T).max())
    figs["distortion_curves"] = (
        plots.distortion_curves(cal, r_data_mm=reach),
        "Radial correction and decentering profile from the principal point to the farthest "
        "corner, with 1- and 3-sigma bands propagated from the covariance; the dashed line is "
        "the largest radius with measurements (beyond it the model is extrapolated).")
    figs["distortion_vectors"] = _distortion_vectors(cal, uv[used] if used.any() else None)
    figs["uncertainty_map"] = (
        plots.uncertainty_figure(cal, points_uv_px=uv[used] if used.any() else None),
        "Projection uncertainty: 1 sigma of where a ray lands [px], propagated from the "
        "interior parameters' covariance (left), and without the part a common rotation of the "
        "camera absorbs, i.e. the calibration's shape (right); dots are the measurements.")
    figs["correlation"] = (
        plots.correlation_figure(cal),
        f"Correlations of the estimated parameters; |r| > {CORRELATION_THRESHOLD:g} outlined.")
    return figs


# --------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------
_CSS = """
body { font-family: "DejaVu Sans", Helvetica, Arial, sans-serif; margin: 0 auto; max-width: 1200px;
       padding: 1em 2em; color: #222; line-height: 1.4; font-size: 14px; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; } h2 { font-size: 1.25em; margin-top: 1.6em;
     border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
td.num { text-align: right; font-family: "DejaVu Sans Mono", monospace; white-space: nowrap; }
tr.insig td { background: #fff4d6; } tr.fixed td { color: #777; }
td.hicorr, span.hicorr { background: #ffd0d0; font-weight: bold; }
figure { margin: 1.2em 0; } figure img { max-width: 100%; height: auto; border: 1px solid #eee; }
figcaption { font-size: 12px; color: #555; margin-top: 0.3em; }
.meta td:first-child { font-weight: bold; } .note { color: #8a4b00; }
ul.compact { margin: 0.2em 0; }
"""


def _fmt(x, digits: int = 6) -> str:
    if x is None:
        return "&mdash;"
    if isinstance(x, float) and not math.isfinite(x):
        return "&infin;" if x > 0 else "&mdash;"
    return html.escape(f"{x:.{digits}g}")


def _meta_section(cal: Calibration) -> list[str]:
    doc = cal.document
    st = doc.get("stats") or {}
    e = html.escape
    s = doc["sensor"]
    meta = [("camera", doc.get("camera_id")), ("session", doc.get("session_id")),
            ("version", cal.version), ("method", cal.method), ("acquired", doc.get("acquired")),
            ("computed", doc.get("created")), ("code version", doc.get("code_version")),
            ("sensor", f"{s['width_px']} × {s['height_px']} px, {s['pixel_size_um']} µm"),
            ("inputs' fingerprint", (doc.get("inputs") or {}).get("fingerprint"))]
    if cal.method == "field":
        meta += [("RMS residual", f"{st.get('rmse_px', float('nan')):.4g} px (max "
                                  f"{st.get('max_px', float('nan')):.4g} px; mean |du| "
                                  f"{st.get('mean_abs_u_px', float('nan')):.4g}, mean |dv| "
                                  f"{st.get('mean_abs_v_px', float('nan')):.4g} px)"),
                 ("sigma0", f"{st.get('sigma0', float('nan')):.4g}"),
                 ("solver", f"{st.get('solver')}, {st.get('iterations')} iterations")]
    else:
        meta += [("sigma of the distortion fit (eq. 10)", f"{st.get('sigma_fit_px', float('nan')):.4g} px"),
                 ("fx, fy", f"{st.get('fx_mm', float('nan')):.6g}, {st.get('fy_mm', float('nan')):.6g} mm"),
                 ("solver", st.get("solver"))]
    adj = content.adjustment_figures(cal)
    meta.append(("redundancy", f"{adj['redundancy']} ({adj['n_equations']} equations, "
                               f"{adj['n_unknowns']} unknowns)"))
    return (['<table class="meta">'] + [f"<tr><td>{e(k)}</td><td>{e(str(v))}</td></tr>" for k, v in meta]
            + ["</table>"])


def _inputs_section(cal: Calibration, residuals: pa.Table) -> list[str]:
    e = html.escape
    inp = inputs_summary(cal, residuals)
    out = ['<h2 id="inputs">What went in, what was left out</h2>',
           '<ul class="compact">' + "".join(f"<li>{e(x)}</li>" for x in inp["went_in"]) + "</ul>"]
    if inp["rejected_by_reason"]:
        out.append("<p>Rejected measurements by reason: "
                   + ", ".join(f"{e(k)}: {v}" for k, v in inp["rejected_by_reason"].items()) + ".</p>")
    left = inp["left_out"]
    if left:
        out.append(f"<p>Left out ({len(left)} item(s)" + (", first 200 shown" if len(left) > 200 else "")
                   + "):</p>")
        out.append('<table id="left-out"><tr><th>what</th><th>item</th><th>why</th></tr>')
        out += [f"<tr><td>{e(x['what'])}</td><td>{e(str(x['item']))}</td><td>{e(str(x['why']))}</td></tr>"
                for x in left[:200]]
        out.append("</table>")
    else:
        out.append("<p>Nothing was left out.</p>")
    out += [f'<p class="note">Note: {e(n)}</p>' for n in inp["notes"]]
    return out


def _parameters_section(cal: Calibration) -> list[str]:
    e = html.escape
    out = ['<h2 id="parameters">Parameters</h2>',
           f"<p>A-posteriori sigmas. Rows shaded yellow are not significant at "
           f"{SIGNIFICANCE_SIGMAS:g} sigma (|value| &lt; {SIGNIFICANCE_SIGMAS:g} sigma); "
           f'<span class="hicorr">red</span> marks correlations above {CORRELATION_THRESHOLD:g}.</p>',
           '<table id="parameter-table"><tr><th>parameter</th><th>value</th><th>sigma</th>'
           "<th>unit</th><th>|value|/sigma</th><th>status</th><th>correlated (|r| &gt; "
           f"{CORRELATION_THRESHOLD:g})</th></tr>"]
    for r in parameter_rows(cal):
        cls = "fixed" if not r["estimated"] else ("" if r["significant"] else "insig")
        corr = ", ".join(f"{o} ({c:+.3f})" for o, c in r["correlated"])
        out.append(f'<tr class="{cls}"><td>{e(r["name"])}</td><td class="num">{_fmt(r["value"], 8)}'
                   f'</td><td class="num">{_fmt(r["sigma"], 3)}</td><td>{e(r["unit"])}</td>'
                   f'<td class="num">{_fmt(r["t"], 3)}</td><td>{e(r["status"])}</td>'
                   f'<td{" class=" + chr(34) + "hicorr" + chr(34) if corr else ""}>{e(corr)}</td></tr>')
    out.append("</table>")
    out.append(sections.interior_px(cal))
    corr = cal.correlation()
    names = list(cal.names)
    out.append("<h3>Correlation matrix of the estimated parameters</h3>")
    out.append('<table id="correlation-table"><tr><th></th>' + "".join(f"<th>{e(n)}</th>" for n in names)
               + "</tr>")
    for i, a in enumerate(names):
        cells = [f'<td class="num{" hicorr" if i != j and abs(corr[i, j]) > CORRELATION_THRESHOLD else ""}">'
                 f"{corr[i, j]:+.3f}</td>" for j in range(len(names))]
        out.append(f"<tr><th>{e(a)}</th>{''.join(cells)}</tr>")
    out.append("</table>")
    return out


def _uncertainty_section(cal: Calibration) -> list[str]:
    _, _, sig = uncertainty_map(cal, (41, 31))
    _, _, sig_r = uncertainty_map(cal, (41, 31), remove_rotation=True)
    return ['<h2 id="uncertainty">Projection uncertainty</h2>',
            f"<p>1 sigma of where a ray lands: {sig[15, 20]:.3g} px at the centre, "
            f"{max(sig[0, 0], sig[0, -1], sig[-1, 0], sig[-1, -1]):.3g} px in the worst corner, "
            f"{sig.max():.3g} px at most; without a common camera rotation {sig_r[15, 20]:.3g} px "
            f"at the centre and {sig_r.max():.3g} px at most "
            f"({COVARIANCE_SOURCES.get(cal.covariance_source, html.escape(cal.covariance_source))}).</p>"]


def _figures_section(figures_png: dict, captions: dict) -> list[str]:
    e = html.escape
    out = ['<h2 id="plots">Plots</h2>']
    for name, png in figures_png.items():
        b64 = base64.b64encode(png).decode("ascii")
        out.append(f'<figure id="fig-{e(name)}"><img src="data:image/png;base64,{b64}" '
                   f'alt="{e(name)}"><figcaption>{e(captions.get(name, ""))} '
                   f"(<code>{e(name)}.png</code>)</figcaption></figure>")
    return out


def render_html(cal: Calibration, residuals: pa.Table, figures_png: dict, captions: dict, *,
                previous: Calibration | None = None, change=None, rig: dict | None = None) -> str:
    """The report's HTML (self-contained: PNGs as data URIs); ``previous`` the camera's
    calibration before this one and ``change`` the comparison with it (or None); ``rig`` the
    rig document of the rig version this calibration is a head of (or None)."""
    doc = cal.document
    e = html.escape
    title = f"fieldcal report: {doc.get('camera_id')} / {doc.get('session_id')}"
    out = ["<!DOCTYPE html>", '<html lang="en">', "<head>", '<meta charset="utf-8">',
           f"<title>{e(title)}</title>", f"<style>{_CSS}</style>", "</head>", "<body>",
           f"<h1>{e(title)}</h1>",
           f"<p>Version <code>{e(cal.version)}</code>, {e(cal.method)} method, model "
           f"{e(str(doc.get('model')))}.</p>"]
    out += _meta_section(cal)
    out.append(sections.rig_section(cal, rig))
    out += _inputs_section(cal, residuals)
    out += _parameters_section(cal)
    out.append(sections.model_equations())
    out += _uncertainty_section(cal)
    if cal.method == "field":
        out.append(sections.exterior_table(cal, image_table(cal, residuals)))
        out.append(sections.targets_section(cal))
        out.append(sections.validation_section(cal))
    out.append(sections.previous_section(cal, previous, change))
    out += _figures_section(figures_png, captions)
    out.append(f"<p><small>Written by fieldcal {e(str(doc.get('code_version', '')))} on "
               f"{dt.datetime.now(dt.UTC).strftime('%Y-%m-%dT%H:%M:%SZ')}.</small></p>")
    out += ["</body>", "</html>"]
    return "\n".join(out) + "\n"


@dataclass
class ReportFiles:
    """What :func:`write_report` wrote."""

    html: Path
    pngs: dict


def _previous(lake, cal: Calibration):
    """``(previous calibration, comparison)`` of the same camera, or ``(None, None)``."""
    prev = content.previous_version(lake, cal)
    if prev is None:
        return None, None
    try:
        before = Calibration.from_lake(lake, prev)
        return before, compare_calibrations(before, cal)
    except (InputError, LakeError):
        return None, None


def write_report(lake, version: str, out_dir) -> ReportFiles:
    """Write ``report.html`` and one PNG per plot of a committed version into ``out_dir``."""
    cal = Calibration.from_lake(lake, version)
    residuals = lake.read_residuals(version)
    previous, change = _previous(lake, cal)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the output folder: {e.strerror or e}", str(out)) from None
    figs = build_figures(cal, residuals)
    pngs, paths, captions = {}, {}, {}
    for name, (fig, caption) in figs.items():
        pngs[name] = plots.to_png(fig)
        captions[name] = caption
        paths[name] = out / f"{name}.png"
        paths[name].write_bytes(pngs[name])
    page = out / "report.html"
    page.write_text(render_html(cal, residuals, pngs, captions, previous=previous, change=change,
                                rig=lake.rig_of(cal.document)), encoding="utf-8")
    return ReportFiles(page, paths)


# --------------------------------------------------------------------------------------
# tolerance and the fleet
# --------------------------------------------------------------------------------------
def parameter_tolerance(name: str, tolerance_um: float, sensor) -> float:
    """A parameter change that moves an image point by about ``tolerance_um`` [um].

    ``f, xp, yp``: the tolerance itself (in mm). The others: the change whose correction
    term reaches the tolerance at the sensor's half diagonal ``r`` [mm]: ``k0, a1, a2, b1,
    b2``: ``t / r``; ``k1, k2, k3``: ``t / r^3, t / r^5, t / r^7``; ``p1, p2``:
    ``t / (3 r^2)`` (``r^2 + 2 x^2`` reaches ``3 r^2``).
    """
    if name not in UNITS:
        raise InputError(f"unknown parameter {name!r}; allowed: {list(PARAM_NAMES)}", "tolerance")
    t = tolerance_um / 1000.0
    r = sensor.half_diagonal_mm
    return {"f_mm": t, "xp_mm": t, "yp_mm": t, "k0": t / r, "a1": t / r, "a2": t / r,
            "b1": t / r, "b2": t / r, "k1": t / r**3, "k2": t / r**5, "k3": t / r**7,
            "p1": t / (3 * r**2), "p2": t / (3 * r**2)}[name]


FLEET_SCHEMA = pa.schema([
    ("camera_id", pa.string()), ("version", pa.string()), ("method", pa.string()),
    ("acquired", pa.timestamp("us", tz="UTC")), ("previous_version", pa.string()),
    ("previous_method", pa.string()), ("previous_acquired", pa.timestamp("us", tz="UTC")),
    ("region", pa.string()), ("max_change_px", pa.float64()), ("max_change_um", pa.float64()),
    ("rms_change_px", pa.float64()), ("rms_change_um", pa.float64()), ("chi2", pa.float64()),
    ("dof", pa.int32()), ("p_value", pa.float64()), ("changed", pa.string()),
    ("significant", pa.bool_()), ("exceeds_tolerance", pa.bool_()),
    ("flagged", pa.bool_()), ("tolerance_um", pa.float64()), ("verdict", pa.string())])
"""One row per camera. The change columns are all of the region tested (``region``:
``sensor``, or ``axes`` when a goniometer calibration is involved) and in both units of the
same numbers; ``chi2, dof`` are the map test's, ``p_value`` the family's (Holm) and
``changed`` the quantities that changed significantly
(:class:`fieldcal.analysis.compare.Comparison`)."""


def _fleet_columns(record: dict, tolerance_um: float, alpha: float) -> dict:
    """The fleet columns of a stored change test (:func:`fieldcal.analysis.compare.judge`)."""
    if "error" in record:
        return {"significant": False, "exceeds_tolerance": False, "flagged": False,
                "verdict": f"cannot compare: {record['error']}"}
    j = judge(record, tolerance_um, alpha)
    return {"region": record["region"], "max_change_px": record["max_px"], "max_change_um": record["max_um"],
            "rms_change_px": record["rms_px"], "rms_change_um": record["rms_um"], "chi2": record["chi2"],
            "dof": record["dof"], "p_value": record["p_value"], "changed": ", ".join(j["changed"]) or "none",
            "significant": j["significant"], "exceeds_tolerance": j["exceeds_tolerance"],
            "flagged": j["flagged"], "verdict": j["verdict"]}


def fleet_summary(lake, *, tolerance_um: float = DEFAULT_TOLERANCE_UM, alpha: float = DEFAULT_ALPHA,
                  start=None, end=None, as_of=None) -> pa.Table:
    """Every camera's latest calibration against its previous one, flagged when it moved.

    ``as_of`` (a time): the catalog as it was then (:func:`fieldcal.lake.history.fleet_pairs`;
    issue 24: ``history --fleet --as-of`` answered with today's catalog).

    For each camera, the latest calibration acquired in ``[start, end]`` and the previous
    one (:mod:`fieldcal.lake.order`) come from one read of the catalog
    (:func:`fieldcal.lake.history.fleet_pairs`); their change test is read from the lake's
    ``comparisons`` table, where the commit put it (:mod:`fieldcal.products.status`); a pair
    the table lacks (a lake made before, two commits that raced) is compared now and
    remembered. The verdict at ``alpha`` and ``tolerance_um`` is derived from the stored test:
    a camera is *flagged* when the change is significant at ``alpha`` and its largest
    image-plane change exceeds ``tolerance_um``.

    Returns
    -------
    pyarrow.Table
        :data:`FLEET_SCHEMA`, one row per camera ordered by ``camera_id``; the comparison
        columns are null for a camera with a single calibration.
    """
    from fieldcal.lake import history
    from fieldcal.products import status

    check_level(tolerance_um, alpha)                     # bad settings: refused before any work
    pairs = history.fleet_pairs(lake, start, end, as_of=as_of).to_pylist()
    records = status.changes(lake, [(r["previous_version"], r["version"]) for r in pairs
                                    if r["previous_version"] is not None])
    rows = []
    for row in pairs:
        out = dict(row, tolerance_um=float(tolerance_um))
        prev = row["previous_version"]
        if prev is None:
            out.update(verdict="only one calibration", significant=False, exceeds_tolerance=False,
                       flagged=False)
        else:
            out.update(_fleet_columns(records[(prev, row["version"])], tolerance_um, alpha))
        rows.append(out)
    return pa.Table.from_pylist(rows, schema=FLEET_SCHEMA)
