"""HTML sections of the calibration report that come straight from the version's arrays.

Each function returns an HTML fragment (``<h2>`` and its tables) for
:func:`fieldcal.products.report.render_html`: the interior orientation in pixels and the
model's equations (:mod:`fieldcal.products.content`), the exterior orientations with their
sigmas, the precision of the adjusted targets and the survey residuals (field method), and
the previous calibration of the same camera with the change test, and the rig the camera
was calibrated in (a head of a rig).
"""

from __future__ import annotations

import html
import math

import numpy as np

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.model.rotations import opk_from_R_world_to_camera
from fieldcal.products import content

__all__ = ["interior_px", "model_equations", "exterior_table", "targets_section", "previous_section",
           "table", "validation_section", "rig_section"]


def _num(x, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "&mdash;"
    return html.escape(format(x, fmt))


def table(headers, rows, *, table_id: str | None = None) -> str:
    """An HTML table; ``rows`` of already formatted cells (strings, ``<td>`` added)."""
    out = [f'<table{f" id={chr(34)}{table_id}{chr(34)}" if table_id else ""}><tr>'
           + "".join(f"<th>{html.escape(h)}</th>" for h in headers) + "</tr>"]
    for row in rows:
        out.append("<tr>" + "".join(c if c.startswith("<td") else f'<td class="num">{c}</td>' for c in row)
                   + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def interior_px(cal: Calibration) -> str:
    """Principal distance and point in mm and in pixels, with sigmas."""
    rows = [[f"<td>{html.escape(r['name'])}</td>", _num(r["mm"], ".6f"),
             _num(None if r["sigma_mm"] is None else 1000 * r["sigma_mm"], ".3g"),
             _num(r["px"], ".3f"), _num(r["sigma_px"], ".3g"), f"<td>{html.escape(r['note'])}</td>"]
            for r in content.interior_rows(cal)]
    return ('<h3>Interior orientation in millimetres and pixels</h3>'
            + table(["", "value [mm]", "σ [µm]", "value [px]", "σ [px]", ""], rows,
                    table_id="interior-px"))


def model_equations() -> str:
    """The camera model's equations (docs/conventions.md section 2)."""
    return ('<h2 id="model">The model</h2><p>fieldcal-brown/1: a measured image point (x\', y\') '
            "[mm] (origin at the sensor centre, x right, y up) is corrected to the ideal point, "
            "which obeys the collinearity equations (R1..R3 the rows of the world-to-camera "
            "rotation, C the camera centre, X a world point):</p>"
            f"<pre>{html.escape(content.MODEL_EQUATIONS)}</pre>")


def _attitude_sigmas(cal: Calibration, files) -> np.ndarray:
    """Per image the sigmas (3,) [rad] of the small attitude rotation, NaN when not stored."""
    names = (cal.array_attrs.get("covariance") or {}).get("names")
    cov = cal.arrays.get("covariance")
    out = np.full((len(files), 3), np.nan)
    if names is None or cov is None:
        return out
    pos = {str(n): i for i, n in enumerate(names)}
    for k, f in enumerate(files):
        for j, c in enumerate(("w_x", "w_y", "w_z")):
            i = pos.get(f"{f}:{c}")
            if i is not None:
                out[k, j] = math.sqrt(max(float(cov[i, i]), 0.0))
    return out


def exterior_table(cal: Calibration, per_image: list[dict]) -> str:
    """Field method: per image its centre and attitude with sigmas, and its residual figures."""
    images = cal.document.get("images") or []
    if not images:
        return ""
    files = [im["file"] for im in images]
    R = np.array([im["rotation_world_to_camera"] for im in images], float)
    opk = np.degrees(np.stack(opk_from_R_world_to_camera(R), axis=-1))
    s_att = np.degrees(_attitude_sigmas(cal, files)) * 1000
    stats = {r["file"]: r for r in per_image}
    rows = []
    for k, im in enumerate(images):
        c = im["center_m"]
        sc = im.get("sigma_center_m") or [None] * 3
        st = stats.get(im["file"], {})
        rows.append([f"<td>{html.escape(im['file'])}</td>", f"<td>{html.escape(str(im.get('station') or ''))}</td>",
                     *(_num(x, ".3f") for x in c),
                     *(_num(None if x is None else 1000 * x, ".1f") for x in sc),
                     *(_num(x, ".3f") for x in opk[k]), *(_num(x, ".1f") for x in s_att[k]),
                     _num(st.get("n_used"), "d"), _num(st.get("n_rejected"), "d"),
                     _num(st.get("mean_abs_u_px"), ".3g"), _num(st.get("mean_abs_v_px"), ".3g"),
                     _num(st.get("rmse_px"), ".3g")])
    return ('<h2 id="exterior">Exterior orientation and per-image figures</h2>'
            "<p>Camera centre [m] and attitude (ω, φ, κ [°], R = Rz(kappa) Ry(phi) "
            "Rx(omega) camera-to-world) with 1-sigma: of the centre [mm], of the attitude as a "
            "small rotation about the camera's x, y, z axes [mdeg]; then the image's used and "
            "rejected points and its mean absolute and RMS residuals [px].</p>"
            + table(["image", "station", "X", "Y", "Z", "sX", "sY", "sZ", "omega", "phi", "kappa",
                     "s_x", "s_y", "s_z", "used", "rejected", "mean |du|", "mean |dv|", "RMS"],
                    rows, table_id="exterior-table"))


def targets_section(cal: Calibration, *, largest: int = 15) -> str:
    """Field method: the adjusted targets' precision and the survey residuals."""
    sig = cal.arrays.get("targets/sigma_m")
    if sig is None:
        return ('<h2 id="targets">Targets</h2><p>The surveyed coordinates were held fixed: no '
                "target precision or survey residuals (their errors enter the image residuals).</p>")
    sig_mm = 1000 * np.asarray(sig, float)
    ids = [str(x) for x in (cal.array_attrs.get("targets/xyz_m") or {}).get("ids", range(len(sig_mm)))]
    ok = np.isfinite(sig_mm).all(axis=1)
    summaries = (("median", np.median), ("RMS", lambda x: np.sqrt(np.mean(x**2))), ("max", np.max))
    rows = [[f"<td>{a}</td>", *(_num(float(f(sig_mm[ok][:, j])), ".2f") for j in range(3))]
            for a, f in summaries] if ok.any() else []
    out = ['<h2 id="targets">Targets</h2>',
           f"<p>{int(ok.sum())} adjusted targets. Their 1-sigma [mm] (a-posteriori):</p>",
           table(["", "X", "Y", "Z"], rows, table_id="target-precision")]
    res = cal.arrays.get("targets/survey_residual_mm")
    if res is None:
        out.append("<p>This version stores no survey residuals.</p>")
        return "\n".join(out)
    res = np.asarray(res, float)
    used = np.asarray(cal.arrays.get("targets/survey_used", np.ones(len(res))), bool)
    fin = np.isfinite(res).all(axis=1)
    if len(ok) == len(fin):
        fin &= ok                                     # targets observed in the adjustment only
    norm = np.linalg.norm(np.where(fin[:, None], res, 0.0), axis=1)
    k = used & fin
    rms = np.sqrt(np.mean(res[k] ** 2, axis=0)) if k.any() else np.full(3, np.nan)
    out.append(f"<p>Survey residuals (surveyed minus adjusted) of the {int(k.sum())} observed targets' "
               f"surveys used: RMS "
               f"{_num(rms[0], '.2f')}, {_num(rms[1], '.2f')}, {_num(rms[2], '.2f')} mm in X, Y, Z; "
               f"{int((fin & ~used).sum())} surveys rejected. The {largest} largest:</p>")
    order = np.argsort(-np.where(fin, norm, -1.0))[:largest]
    out.append(table(["target", "dX [mm]", "dY [mm]", "dZ [mm]", "|d| [mm]", "survey"],
                     [[f"<td>{html.escape(ids[i] if i < len(ids) else str(i))}</td>",
                       *(_num(x, ".2f") for x in res[i]), _num(norm[i], ".2f"),
                       f"<td>{'used' if used[i] else 'rejected'}</td>"] for i in order if fin[i]],
                     table_id="survey-residuals"))
    return "\n".join(out)


def previous_section(cal: Calibration, previous: Calibration | None, change) -> str:
    """The previous calibration of the camera and the change test against it."""
    head = '<h2 id="previous">The previous calibration of this camera</h2>'
    if previous is None:
        return head + "<p>This is the camera's first calibration in the lake.</p>"
    rows = []
    for c in (previous, cal):
        d = c.document
        rows.append([f"<td>{html.escape(c.version)}</td>", f"<td>{html.escape(str(d.get('session_id')))}</td>",
                     f"<td>{html.escape(str(d.get('acquired')))}</td>", f"<td>{html.escape(c.method)}</td>",
                     *(_num(float(c.camera.params[i]), ".6f") for i in range(3)),
                     *(_num(None if c.sigma_of(n) is None else 1000 * c.sigma_of(n), ".3g")
                       for n in ("f_mm", "xp_mm", "yp_mm"))])
    out = [head, table(["version", "session", "acquired", "method", "f [mm]", "xp [mm]", "yp [mm]",
                        "σ f [µm]", "σ xp [µm]", "σ yp [µm]"], rows, table_id="previous-table")]
    if change is not None:
        out.append(f"<p>Change, tested {html.escape(change.where)}: largest {change.max_um:.3g} µm "
                   f"({change.max_px:.3g} px), RMS {change.rms_um:.3g} µm ({change.rms_px:.3g} px).</p>")
        out.append('<ul class="compact">' + "".join(f"<li>{html.escape(t.line())}</li>" for t in change.tests)
                   + "".join(f"<li>not tested: {html.escape(x)}</li>" for x in change.left_out) + "</ul>")
        out.append(f"<p><b>Verdict:</b> {html.escape(change.verdict)}</p>")
    return "\n".join(out)


def validation_section(cal: Calibration) -> str:
    """Variance components, independent check points and the cross-validation by station
    (``stats.variance_components``, ``stats.check_points``, ``stats.cross_validation``;
    docs/uncertainty.md)."""
    st = cal.document.get("stats") or {}
    out = ['<h2 id="validation">How far the uncertainty can be trusted</h2>']
    vc = st.get("variance_components") or {}
    if vc:
        if vc.get("survey_consider"):
            out.append("<p>Targets held fixed: their survey errors are propagated into the covariance "
                       f"(error-model factor {_num(vc.get('error_model_factor'), '.3g')}).</p>")
        else:
            out.append(f"<p>Variance components: {_num(vc.get('image_floor_px'), '.3g')} px added in quadrature "
                       f"to every image point's a-priori sigma, survey sigmas times "
                       f"{_num(vc.get('survey_factor'), '.3g')} ({vc.get('rounds', 0)} re-weighted "
                       "adjustments).</p>")
    cp = st.get("check_points")
    if cp:
        rows = [["<td>object space (intersected &minus; surveyed)</td>", str(cp.get("n")),
                 _num(cp.get("rms_mm"), ".3g") + " mm", _num(cp.get("rms_mm_predicted"), ".3g") + " mm",
                 f"{_num(cp.get('chi2_mm'), '.4g')} / {cp.get('dof_mm')}", _num(cp.get("p_value_mm"), ".3g")],
                ["<td>image space (measured &minus; projected survey)</td>", str(cp.get("n_observations")),
                 _num(cp.get("rms_px"), ".3g") + " px", _num(cp.get("rms_px_predicted"), ".3g") + " px", "", ""]]
        out.append(f"<h3>Independent check points</h3><p>{cp.get('n_withheld')} surveyed targets withheld "
                   f"from the adjustment ({html.escape(str(cp.get('selection') or ''))}); "
                   f"{cp.get('n_rejected', 0)} of their image points rejected as blunders.</p>")
        out.append(table(["", "n", "RMS", "predicted RMS", "chi2 / dof", "p"], rows, table_id="check-points"))
    else:
        out.append("<p>No check points: this calibration withheld no surveyed targets.</p>")
    cv = st.get("cross_validation")
    if cv:
        rows = [[f"<td>{html.escape(str(s['station']))}</td>", str(s["n_images"]),
                 _num(s.get("rms_px"), ".3g"), _num(s.get("max_px"), ".3g"), _num(s.get("sigma_rms_px"), ".3g"),
                 f"{_num(s.get('chi2'), '.3g')} / {s.get('dof')}", _num(s.get("p_value"), ".3g"),
                 f"<td>{html.escape(s.get('error') or '')}</td>"] for s in cv.get("stations", [])]
        out.append("<h3>Cross-validation by station</h3><p>The calibration without each station's images, "
                   "compared with the calibration from all: how far the correction field moves over the "
                   "sensor [px], against the 1-sigma its covariance predicts for that difference "
                   "(the two calibrations share data: the covariance of the difference is the "
                   "difference of the covariances).</p>")
        out.append(table(["station", "images", "RMS move [px]", "max move [px]", "predicted RMS [px]",
                          "chi2 / dof", "p", ""], rows, table_id="cross-validation"))
    return "\n".join(out)


def rig_section(cal: Calibration, rig: dict | None) -> str:
    """The rig this calibration is a head of (its rig version's relative orientations, with
    sigmas, and every head's calibration version); empty for a single camera."""
    if rig is None:
        return ""
    e = html.escape

    def three(v, fmt):
        return ", ".join(format(x, fmt) for x in v)

    rows = []
    for r in content.rig_rows(rig):
        me = " (this calibration)" if r["version"] == cal.version else ""
        ref = r["role"] == "reference"
        rows.append([f"<td>{e(r['camera_id'])}{e(me)}</td>", f"<td><code>{e(r['version'])}</code></td>",
                     f"<td>{e(r['role'])}</td>", e(three(r["opk_deg"], ".5f")),
                     "&mdash;" if ref else e(three(r["sigma_rotation_arcsec"], ".2g")),
                     e(three(r["t_mm"], ".2f")), "&mdash;" if ref else e(three(r["sigma_t_mm"], ".2g")),
                     _num(r["rmse_px"], ".3g")])
    return (f'<h2 id="rig">The rig</h2><p>This camera is a head of rig <b>{e(str(rig["rig_id"]))}</b>, '
            f"calibrated together with its other heads (rig version <code>{e(str(rig['version']))}</code>, "
            f"session {e(str(rig['session_id']))}, reference head {e(str(rig['reference']))}, "
            f"{rig['stats'].get('n_exposures')} exposures). Relative orientation of each head to the "
            "reference: <code>R_camera_to_rig</code> as ω, φ, κ (R = Rz(κ) Ry(φ) Rx(ω)) with the sigmas "
            "of a small rotation about the rig frame's x, y, z axes, and the lever arm "
            "<code>t_camera_in_rig</code> (docs/conventions.md).</p>"
            + table(["head", "calibration version", "role", "ω, φ, κ [deg]", "σ rotation x, y, z [arcsec]",
                     "lever arm x, y, z [mm]", "σ lever arm [mm]", "rmse [px]"], rows, table_id="rig"))
