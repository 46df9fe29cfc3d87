"""The calibration certificate's HTML, section by section (:mod:`fieldcal.products.certificate`).

Each function returns an HTML fragment; :func:`page` puts them together with the print
style sheet: A4 pages whose margins carry the certificate number and "page N of M"
(CSS ``@page`` margin boxes, printed by Chromium), tables whose header rows repeat on the
next page (``<thead>``) and small tables that do not split, the verdict and the signatures
kept on one page. Units are written with their symbols (µm, °); every standard uncertainty
``u`` is shown with its expanded uncertainty ``U = k u`` (:data:`COVERAGE_FACTOR`).
"""

from __future__ import annotations

import datetime as dt
import html
import math

import numpy as np

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.model.camera import INDEX, PARAM_NAMES
from fieldcal.products import content, plots
from fieldcal.products import focal_length as fl

__all__ = ["page", "UNITS", "COVERAGE_FACTOR", "focal_lengths"]

COVERAGE_FACTOR = 2.0
"""The coverage factor k of the expanded uncertainties U = k u (about 95 % for a normal distribution)."""

UNITS = {"f_mm": "mm", "xp_mm": "mm", "yp_mm": "mm", "k0": "1", "k1": "mm⁻²", "k2": "mm⁻⁴",
         "k3": "mm⁻⁶", "p1": "mm⁻¹", "p2": "mm⁻¹", "a1": "1", "a2": "1", "b1": "1", "b2": "1"}
K = COVERAGE_FACTOR
E = html.escape
SEMI_DIAGONAL_ROWS = 12
"""About this many round field angles in the semi-diagonal table (5° steps to a 42° corner)."""

_CSS = """
@page { size: A4; margin: 19mm 14mm 17mm 14mm;
  @top-left { content: "Camera calibration certificate"; font: 8pt "DejaVu Sans", sans-serif; color: #444; }
  @top-right { content: "Certificate No. __ID__"; font: 8pt "DejaVu Sans Mono", monospace; color: #222; }
  @bottom-left { content: "__ISSUER__"; font: 7.5pt "DejaVu Sans", sans-serif; color: #444; }
  @bottom-right { content: "Page " counter(page) " of " counter(pages); font: 8pt "DejaVu Sans", sans-serif; } }
body { font-family: "DejaVu Sans", Helvetica, Arial, sans-serif; font-size: 9.5pt; color: #111;
       max-width: 182mm; margin: 0 auto; line-height: 1.32; }
h1 { font-size: 17pt; margin: 0 0 1mm 0; }
.certno { font-size: 10.5pt; margin: 0 0 3mm 0; white-space: nowrap; }
.certno span { font-family: "DejaVu Sans Mono", monospace; font-weight: bold; }
h2 { font-size: 12pt; margin: 5mm 0 2mm 0; border-bottom: 0.4mm solid #333; break-after: avoid; }
h3 { font-size: 10pt; margin: 3mm 0 1mm 0; break-after: avoid; }
p { margin: 1mm 0 1.5mm 0; orphans: 3; widows: 3; }
table { border-collapse: collapse; margin: 1mm 0 2mm 0; font-size: 8.5pt; }
table.keep, .keep { break-inside: avoid; }
thead { display: table-header-group; } tr { break-inside: avoid; }
th, td { border: 0.2mm solid #888; padding: 0.5mm 1.4mm; text-align: left; vertical-align: top; }
th { background: #eee; } td.num { text-align: right; font-family: "DejaVu Sans Mono", monospace;
     white-space: nowrap; }
td.PASS { background: #d9f2d9; font-weight: bold; } td.FAIL { background: #f6c9c9; font-weight: bold; }
td.na { color: #666; } tr.extra td { color: #777; font-style: italic; }
.verdict { font-size: 13pt; font-weight: bold; padding: 1mm 3mm; border: 0.5mm solid #333;
           display: inline-block; } .PASSv { background: #d9f2d9; } .FAILv { background: #f6c9c9; }
table.ident td:first-child { font-weight: bold; width: 50mm; }
table.corr { font-size: 7pt; } table.corr td, table.corr th { padding: 0.3mm 0.8mm; }
pre { font-size: 8pt; background: #f6f6f6; padding: 1.5mm; border: 0.2mm solid #ccc; break-inside: avoid; }
.small { font-size: 8pt; color: #333; } .sign td { height: 16mm; width: 88mm; }
table.cover td { width: 7mm; height: 3.6mm; text-align: center; font-size: 6.5pt; padding: 0; }
.summary { border: 0.4mm solid #333; padding: 2mm 3mm; margin: 2mm 0 3mm 0; break-inside: avoid; }
figure { margin: 1mm 0; break-inside: avoid; } figure svg { width: 100%; height: auto; }
figcaption { font-size: 8pt; color: #333; }
.final { break-inside: avoid; }
@media screen { body { padding: 8mm; } }
"""


def _f(x, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "&mdash;"
    return E(format(x, fmt))


def _u(sigma, scale: float = 1.0, fmt: str = ".2f") -> tuple[str, str]:
    """``(u, U)`` cells' text of a standard uncertainty times ``scale``."""
    if sigma is None:
        return "&mdash;", "&mdash;"
    return _f(scale * sigma, fmt), _f(K * scale * sigma, fmt)


def _table(headers, rows, cls: str = "keep") -> str:
    """A table; each row a list of ``<td>`` strings, or a ``(row_class, cells)`` pair; the
    header row in ``<thead>`` (repeated on the next page when the table continues)."""
    out = [f'<table class="{cls}">']
    if headers:
        out.append("<thead><tr>" + "".join(f"<th>{h}</th>" for h in headers) + "</tr></thead>")
    out.append("<tbody>")
    for row in rows:
        rc, cells = row if isinstance(row, tuple) else ("", row)
        out.append(f'<tr class="{rc}">' + "".join(cells) + "</tr>")
    return "\n".join(out) + "</tbody></table>"


def _num(x, fmt: str) -> str:
    return f'<td class="num">{_f(x, fmt)}</td>'


def _stated(value) -> str:
    return str(value) if value not in (None, "") else "not stated"


# --------------------------------------------------------------------------------------
# 1. identity
# --------------------------------------------------------------------------------------
def _identity(cal: Calibration, cfg: dict, issued: dt.datetime) -> str:
    doc, c, cond = cal.document, cfg["certificate"], cfg["conditions"]
    s = cal.sensor
    acquired = content.parse_time(doc.get("acquired")) or content.parse_time(doc.get("created"))
    years = c.get("validity_years")
    valid = (acquired.replace(year=acquired.year + int(years)) if acquired and years else None)
    rows = [("certificate number", cal.version), ("camera", doc.get("camera_id")),
            ("camera make / model / serial", _stated(c.get("camera"))),
            ("lens", _stated(c.get("lens"))),
            ("focus / aperture", f"{_stated(cond.get('focus'))} / {_stated(cond.get('aperture'))}"),
            ("sensor", f"{s.width_px} × {s.height_px} px, pixel pitch {s.pixel_size_um:g} µm "
                       f"({s.width_px * s.pixel_size_um / 1000:.2f} × {s.height_px * s.pixel_size_um / 1000:.2f} mm)"),
            ("method", content.METHOD_NAMES.get(cal.method, cal.method)),
            ("facility", _stated(c.get("facility"))),
            ("issued by", _stated(c.get("organisation"))),
            ("calibration session", doc.get("session_id")),
            ("date of calibration", acquired.strftime("%Y-%m-%d") if acquired else "unknown"),
            ("date of issue", issued.strftime("%Y-%m-%d")),
            ("valid until", valid.strftime("%Y-%m-%d") + f" ({years} years from the calibration)"
             if valid else "not stated"),
            ("model", f"{doc.get('model')} (equations in section 3)"),
            ("computed by", f"fieldcal {doc.get('code_version') or ''} on {doc.get('created')}"),
            ("inputs' fingerprint", (doc.get("inputs") or {}).get("fingerprint"))]
    return _table(["item", "value"], [[f"<td>{E(k)}</td>", f"<td>{E(str(v))}</td>"] for k, v in rows],
                  "keep ident")


# --------------------------------------------------------------------------------------
# 2. interior orientation and focal lengths
# --------------------------------------------------------------------------------------
def _interior(cal: Calibration) -> str:
    rows = []
    for r in content.interior_rows(cal):
        um = _u(r["sigma_mm"], 1000.0)
        px = _u(r["sigma_px"], 1.0, ".3g")
        rows.append([f"<td>{E(r['name'])}</td>", _num(r["mm"], ".6f"), f'<td class="num">{um[0]}</td>',
                     f'<td class="num">{um[1]}</td>', _num(r["px"], ".3f"), f'<td class="num">{px[0]}</td>',
                     f'<td class="num">{px[1]}</td>', f"<td>{E(r['note'])}</td>"])
    return _table(["", "value [mm]", "u [µm]", f"U (k = {K:g}) [µm]", "value [px]", "u [px]",
                   f"U (k = {K:g}) [px]", ""], rows)


def focal_lengths(cal: Calibration, reach_mm: float | None) -> dict:
    """The three focal lengths (:mod:`fieldcal.products.focal_length`) and the balance."""
    fe, s_fe = fl.effective_focal(cal)
    bal = fl.balanced_focal(cal, reach_mm)
    return {"f": (cal.camera.f_mm, cal.sigma_of("f_mm")), "effective": (fe, s_fe),
            "balanced": (bal["c_mm"], bal["sigma_mm"]), "balance": bal}


def _focal_table(cal: Calibration, foc: dict) -> str:
    k0 = float(cal.camera.params[INDEX["k0"]])
    bal = foc["balance"]
    items = [("principal distance f (the model's)", foc["f"],
              "the model's whole correction (section 3), k0 included: fieldcal's own products and exports"),
             ("effective focal length f / (1 + k0)", foc["effective"],
              "a model without a linear radial term (a pinhole, OpenCV, COLMAP): the scale of the image "
              "at the principal point; fit that model's distortion to it (fieldcal export)"),
             (f"calibrated focal length c, distortion balanced to {bal['theta_max_deg']:.1f}°", foc["balanced"],
              "a focal length with a table of radial distortion (USGS practice): the semi-diagonal "
              "table of section 3 is relative to c")]
    rows = []
    for name, (value, sigma), use in items:
        u, U = _u(sigma, 1000.0)
        rows.append([f"<td>{E(name)}</td>", _num(value, ".6f"), f'<td class="num">{u}</td>',
                     f'<td class="num">{U}</td>', _num(100 * (value / foc["f"][0] - 1), "+.3f"),
                     f'<td class="small">{E(use)}</td>'])
    table = _table(["", "value [mm]", "u [µm]", f"U (k = {K:g}) [µm]", "vs f [%]", "use it with"], rows)
    if "k0" in cal.names:
        k0_text = (f"with a linear radial term k0 = {k0:+.6g}, a scale of {100 * abs(k0):.2f} %. f is exact "
                   "only with that term; a tool that has no such term needs the effective focal length "
                   f"(f alone would put points {100 * abs(k0):.2f} % off).")
    else:
        k0_text = (f"with its linear radial term k0 held at {k0:g} ({cal.method} method): f is also the "
                   "effective focal length.")
    note = (f"<p>Which focal length to copy: fieldcal's model corrects a measured point to the ideal one "
            f"(docs/conventions.md section 2) {k0_text} The "
            f"calibrated focal length c balances the radial distortion over the field (least squares over "
            f"field angles 0&ndash;{bal['theta_max_deg']:.1f}°, the data's reach): relative to c the mean "
            f"radial distortion is at most {bal['max_um']:.1f} µm (RMS {bal['rms_um']:.1f} µm) there, "
            f"relative to f {bal['max_f_um']:.1f} µm.</p>")
    return table + note


# --------------------------------------------------------------------------------------
# 3. distortion
# --------------------------------------------------------------------------------------
def _semi_diagonals(cal: Calibration, reach: float | None) -> str:
    rows = []
    for r in fl.semi_diagonal_table(cal, content.field_angles_deg(cal, SEMI_DIAGONAL_ROWS), "balanced", reach):
        u, U = _u(r["sigma_um"], 1.0)
        cells = [_num(r["angle_deg"], ".2f"), _num(r["r_mm"], ".3f"),
                 *(_num(d, "+.2f") for d in r["diagonals_um"]), _num(r["mean_um"], "+.2f"),
                 f'<td class="num">{u}</td>', f'<td class="num">{U}</td>']
        rows.append(("extra" if r["extrapolated"] else "", cells))
    heads = ["field angle [°]", "radius [mm]"] + [E(d) + " [µm]" for d in fl.DIAGONALS]
    return _table(heads + ["mean [µm]", "u [µm]", f"U (k = {K:g}) [µm]"], rows)


def _distortion_figure(cal: Calibration, foc: dict, reach: float | None) -> str:
    theta_max = float(content.field_angles_deg(cal)[-1])
    theta = np.linspace(theta_max / 100, theta_max, 100)
    d_c, _, s_c = fl.distortion_relative(cal, theta, "balanced", reach)
    d_f, _, _ = fl.distortion_relative(cal, theta, "f")
    reach_deg = None if reach is None else math.degrees(math.atan(reach / cal.camera.f_mm))
    fig = plots.certificate_distortion(theta, d_c, d_c.mean(axis=0), K * s_c, d_f.mean(axis=0),
                                       labels=fl.DIAGONALS, focal_label=f"c = {foc['balanced'][0]:.4f} mm",
                                       reach_deg=reach_deg)
    return (f"<figure>{plots.to_svg(fig)}<figcaption>Radial distortion along the four semi-diagonals "
            f"and their mean, relative to the calibrated focal length c (band: the mean ± U, k = {K:g}); "
            "dashed: the mean relative to f. Positive: the image lies farther from the principal point "
            "than the pinhole image.</figcaption></figure>")


def _distortion_radii(cal: Calibration, reach: float | None) -> str:
    rows = []
    for r in content.distortion_table(cal, by="radius", reach_mm=reach):
        ur, Ur = _u(r["sigma_radial_um"])
        ud, Ud = _u(r["sigma_decentering_um"])
        cells = [_num(r["r_mm"], ".3f"), _num(r["angle_deg"], ".2f"), _num(r["radial_um"], "+.2f"),
                 f'<td class="num">{ur}</td>', f'<td class="num">{Ur}</td>', _num(r["decentering_um"], ".2f"),
                 f'<td class="num">{ud}</td>', f'<td class="num">{Ud}</td>']
        rows.append(("extra" if r["extrapolated"] else "", cells))
    return _table(["radius [mm]", "field angle [°]", "radial distortion [µm]", "u [µm]", f"U (k = {K:g})",
                   "decentering profile [µm]", "u [µm]", f"U (k = {K:g})"], rows)


def _coefficients(cal: Calibration) -> str:
    doc = cal.document
    fixed = (doc.get("stats") or {}).get("fixed_parameters") or {}
    rows = []
    for n in PARAM_NAMES:
        s = (doc.get("sigma") or {}).get(n)
        note = "estimated" if s is not None else ("held: " + str(fixed[n]) if n in fixed else "fixed by the method")
        u, U = _u(s, 1.0, ".2e")
        rows.append([f"<td>{n}</td>", _num(float(doc["parameters"][n]), ".6e"), f'<td class="num">{u}</td>',
                     f'<td class="num">{U}</td>', f"<td>{UNITS[n]}</td>", f'<td class="small">{E(note)}</td>'])
    return _table(["parameter", "value", "u", f"U (k = {K:g})", "unit", ""], rows)


def _distortion_section(cal: Calibration, foc: dict, reach: float | None) -> list[str]:
    reach_txt = ("" if reach is None else
                 f" Rows in grey italics lie beyond {reach:.2f} mm, the farthest observation from the "
                 "principal point: there the values are the model's extrapolation.")
    gonio = (" A goniometer observes the two scanned axes only: along the diagonals the values are the "
             "model's." if cal.method == "goniometer" else "")
    return [
        "<h2>3. Lens distortion</h2>",
        "<h3>Radial distortion per semi-diagonal, relative to the calibrated focal length c</h3>",
        "<p>For a ray at the field angle given, the distance of its measured image from the principal "
        "point along each semi-diagonal (towards a sensor corner) minus c tan(angle): the model's whole "
        "correction (radial, decentering, affine terms), hence four columns; positive when the image "
        "lies farther out than the pinhole image (the sign of USGS reports)." + E(reach_txt + gonio) + "</p>",
        _semi_diagonals(cal, reach), _distortion_figure(cal, foc, reach),
        "<h3>The model's radial distortion and decentering profile at radii, relative to f</h3>",
        "<p>Radial distortion &minus;dr(r) = &minus;r (k0 + k1 r² + k2 r⁴ + k3 r⁶) (measured minus ideal "
        "radius, relative to the model's f) and the decentering profile √(p1² + p2²) r², at measured "
        "radii r from the principal point.</p>",
        _distortion_radii(cal, reach),
        "<h3>Coefficients</h3>", _coefficients(cal),
        "<h3>The model (fieldcal-brown/1)</h3>", f"<pre>{E(content.MODEL_EQUATIONS)}</pre>",
        "<p class=\"small\">(x', y') measured image point [mm]; the correction (dx, dy) moves it to the "
        "ideal point (the opposite direction of OpenCV's, which distorts an ideal point); R1..R3 the "
        "rows of the world-to-camera rotation, C the camera centre.</p>"]


# --------------------------------------------------------------------------------------
# 4-6. correlations, adjustment, check points
# --------------------------------------------------------------------------------------
def _correlations(cal: Calibration) -> str:
    corr = cal.correlation()
    names = list(cal.names)
    rows = []
    for i, a in enumerate(names):
        cells = [f"<th>{a}</th>"]
        for j in range(len(names)):
            hi = i != j and abs(corr[i, j]) > 0.95
            cells.append(f'<td class="num"{" style=font-weight:bold" if hi else ""}>{corr[i, j]:+.2f}</td>')
        rows.append(cells)
    return _table([""] + names, rows, "keep corr")


def _coverage(cal: Calibration, residuals) -> str:
    cov = content.coverage(cal, residuals)
    counts = cov["counts"]
    top = max(int(counts.max()), 1)
    rows = [[f'<td style="background: rgba(30, 90, 200, {0.15 + 0.85 * c / top if c else 0:.2f})">'
             f"{c if c else ''}</td>" for c in row] for row in counts]
    rf = cov["radius_fraction"]
    text = (f"<p>{100 * cov['fraction']:.0f} % of the {counts.shape[1]} × {counts.shape[0]} cells of the "
            f"sensor hold observations (number per cell below, the sensor as seen on its pixel grid, "
            f"row 0 at the top); the observations reach "
            f"{'&mdash;' if rf is None else f'{100 * rf:.0f} %'} of the half diagonal from the principal point.</p>")
    return '<div class="keep">' + text + _table([], rows, "keep cover") + "</div>"


def _adjustment(cal: Calibration, residuals) -> list[str]:
    adj = content.adjustment_figures(cal)
    fig = content.residual_format(adj["rmse_px"], adj["max_px"])
    return ["<h2>5. Adjustment and coverage</h2>",
            _table(["σ0", "redundancy", "equations", "unknowns", E(adj["what"])],
                   [[_num(adj["sigma0"], ".4g"), f'<td class="num">{adj["redundancy"]}</td>',
                     f'<td class="num">{adj["n_equations"]}</td>', f'<td class="num">{adj["n_unknowns"]}</td>',
                     f'<td class="num">{E(fig)}</td>']]),
            *([f'<p id="eccentricity">{E(ecc[0].upper() + ecc[1:])}.</p>']
              if (ecc := content.eccentricity_text(cal)) else []),
            *([f'<p id="board">{E(board[0].upper() + board[1:])}.</p>']
              if (board := content.board_text(cal)) else []),
            _coverage(cal, residuals)]


def _checks(cal: Calibration) -> str:
    cp = content.check_points(cal)
    if cp is None:
        return "<p>No check points: this calibration withheld no surveyed targets from the adjustment.</p>"
    if "rms_x_mm" not in cp:                  # figures stored by another step: shown as they are
        rows = [[f"<td>{E(str(k))}</td>",
                 f'<td class="num">{_f(v) if isinstance(v, int | float) else E(str(v))}</td>'] for k, v in cp.items()]
        return _table(["figure", "value"], rows)
    rows = [[f"<td>{a.upper()}</td>", _num(cp.get(f"rms_{a}_mm"), ".2f"), _num(cp.get(f"mean_{a}_mm"), "+.2f"),
             _num(cp.get(f"max_{a}_mm"), ".2f"), _num(cp.get(f"rms_{a}_mm_predicted"), ".2f")] for a in "xyz"]
    rows.append(["<td>3-D</td>", _num(cp.get("rms_mm"), ".2f"), "<td></td>", "<td></td>",
                 _num(cp.get("rms_mm_predicted"), ".2f")])
    text = (f"<p>{cp.get('n_withheld')} surveyed targets withheld from the adjustment "
            f"(chosen by: {E(str(cp.get('selection') or 'not recorded'))}); {cp.get('n')} of them seen in two "
            "or more images and intersected with the calibrated camera and the adjusted orientations. Their "
            "errors (intersected minus surveyed) in the world frame, against the RMS the adjustment's and the survey's "
            f"uncertainties predict; chi-square {_f(cp.get('chi2_mm'), '.4g')} on {cp.get('dof_mm')} degrees "
            f"of freedom, p = {_f(cp.get('p_value_mm'), '.3g')}. In the image: RMS {_f(cp.get('rms_px'), '.3g')} px "
            f"over {cp.get('n_observations')} image points (predicted {_f(cp.get('rms_px_predicted'), '.3g')} px, "
            f"the survey's error included), {cp.get('n_rejected', 0)} rejected as blunders.</p>")
    return text + _table(["axis", "RMS [mm]", "mean [mm]", "largest |error| [mm]", "predicted RMS [mm]"], rows)


# --------------------------------------------------------------------------------------
# 7. traceability and conditions
# --------------------------------------------------------------------------------------
PROCEDURES = {
    "field": "self-calibrating bundle adjustment of photographs of a surveyed target field (Wang et al. "
             "2018; fieldcal's METHODS part A): DLT and least-squares initial values, Levenberg-Marquardt / "
             "quasi-Newton adjustment with the surveyed coordinates as weighted observations, data "
             "snooping, automatic parameter selection",
    "goniometer": "laboratory goniometer (Yuan et al. 2016; fieldcal's METHODS part B): sub-pixel spot "
                  "centroids of a collimated point along the sensor's centre row and column, principal "
                  "distance and point by the minimum sum of squared distortion, distortion fit (eq. 8-10)",
}


def _traceability(cal: Calibration, cfg: dict) -> list[str]:
    t, c = cfg["traceability"], cfg["conditions"]
    doc = cal.document
    what = ("the surveyed coordinates of the target field: they enter the adjustment as observations "
            "weighted by their stated accuracy (targets.csv sigma_mm)" if cal.method == "field" else
            "the arm's encoder angles: the method takes them as exact; their error appears in the fit's "
            "residuals and in the frame-to-frame scatter that scales the uncertainties")
    rows = [("reference of the scale", what),
            ("instrument" if cal.method == "field" else "angle reference", _stated(t.get("instrument"))),
            ("date of the survey" if cal.method == "field" else "its calibration date", _stated(t.get("date"))),
            ("its accuracy", _stated(t.get("accuracy"))),
            ("procedure", (t.get("procedure") + "; " if t.get("procedure") else "")
             + PROCEDURES.get(cal.method, cal.method)),
            ("computation", f"fieldcal {doc.get('code_version') or ''}, model {doc.get('model')} "
                            "(docs/conventions.md), the calibration document of the version above")]
    cond = [("focus", _stated(c.get("focus"))), ("aperture", _stated(c.get("aperture"))),
            ("temperature", "not stated" if c.get("temperature_c") is None else f"{c['temperature_c']:g} °C"),
            ("relative humidity", "not stated" if c.get("humidity_percent") is None
             else f"{c['humidity_percent']:g} %"),
            ("air pressure", "not stated" if c.get("pressure_hpa") is None else f"{c['pressure_hpa']:g} hPa"),
            ("notes", _stated(c.get("notes")))]
    return ["<h2>7. Traceability, procedure and conditions</h2>",
            _table(["item", "value"], [[f"<td>{E(k)}</td>", f"<td>{E(str(v))}</td>"] for k, v in rows], "keep ident"),
            "<h3>Environmental conditions during the calibration</h3>",
            _table(["item", "value"], [[f"<td>{E(k)}</td>", f"<td>{E(str(v))}</td>"] for k, v in cond], "keep ident"),
            f'<p class="small">Uncertainty: the expanded uncertainties U are the standard uncertainties u '
            f"multiplied by the coverage factor k = {K:g}, which for a normal distribution corresponds to a "
            "coverage probability of about 95 %. The standard uncertainties are the adjustment's "
            "a-posteriori ones (scaled by σ0), propagated to first order; they cover the errors the data "
            "and the model show, not a change of the camera after the calibration (docs/uncertainty.md: "
            "Monte Carlo checks of their honesty).</p>"]


# --------------------------------------------------------------------------------------
# 8-9. change and acceptance
# --------------------------------------------------------------------------------------
def _change(change, prev_label: str | None) -> str:
    if change is None:
        return "<p>No previous calibration of this camera in the lake: nothing to compare.</p>"
    rows = [[f"<td>{E(t.label)}</td>",
             f'<td class="num">{", ".join(f"{c:.3g}" if t.key == "map" else f"{c:+.3g}" for c in t.change)} '
             f'{E(t.unit_symbol)}</td>',
             f'<td class="num">{", ".join(f"{s:.3g}" for s in t.sigma)} {E(t.unit_symbol)}</td>',
             f'<td class="num">{t.p_value:.3g}</td>', f'<td class="num">{t.p_adjusted:.3g}</td>',
             f"<td>{'yes' if t.significant(change.alpha) else 'no'}</td>"] for t in change.tests]
    out = [f"<p>Against {E(prev_label or '')}: tested {E(change.where)}; largest change "
           f"{change.max_um:.3g} µm ({change.max_px:.3g} px), RMS {change.rms_um:.3g} µm "
           f"({change.rms_px:.3g} px). Each quantity is tested against the two calibrations' "
           f"uncertainties; Holm's correction keeps the family at the level {change.alpha:g} "
           f"(for the map row the change is the largest, the sigma the largest 1 σ).</p>",
           _table(["quantity", "change (B &minus; A)", "1 σ", "p", "p (Holm)", "significant"], rows)]
    out += [f'<p class="small">Not tested: {E(x)}.</p>' for x in change.left_out]
    out.append(f"<p><b>Verdict:</b> {E(change.verdict)}</p>")
    return "\n".join(out)


def _acceptance(acc: dict, cfg: dict, issued: dt.datetime) -> str:
    rows = []
    for r in acc["rows"]:
        cls = r["result"] if r["result"] in ("PASS", "FAIL") else "na"
        v = f'{_f(r["value"])} {E(r["unit"])}' if isinstance(r["value"], int | float) else "&mdash;"
        rows.append([f"<td>{E(r['criterion'])}</td>", f"<td>{E(r['threshold'])}</td>",
                     f'<td class="num">{v}</td>', f'<td class="{cls}">{E(r["result"])}</td>',
                     f'<td class="small">{E(r["why"])}</td>'])
    return ('<div class="final"><h2>9. Acceptance</h2>'
            + _table(["criterion", "threshold", "value", "result", "note"], rows)
            + f'<p>Verdict: <span class="verdict {acc["verdict"]}v">{acc["verdict"]}</span></p>'
            '<table class="keep sign"><thead><tr><th>calibrated by</th><th>approved by</th></tr></thead>'
            f"<tbody><tr><td>{E(cfg['certificate'].get('operator') or '')}</td><td></td></tr></tbody></table>"
            f'<p class="small">Issued {issued.strftime("%Y-%m-%dT%H:%M:%SZ")} by fieldcal from the lake '
            "version above; every number can be traced to that version's document and arrays.</p></div>")


# --------------------------------------------------------------------------------------
# the page
# --------------------------------------------------------------------------------------
def _css(cal: Calibration, cfg: dict) -> str:
    def css_text(s: str) -> str:
        return "".join(ch if ch.isalnum() or ch in " .,:;-_/()&+" else " " for ch in s)[:90]
    issuer = cfg["certificate"].get("organisation") or "fieldcal"
    return _CSS.replace("__ID__", css_text(cal.version)).replace("__ISSUER__", "Issued by " + css_text(issuer))


def _summary(cal: Calibration, foc: dict, acc: dict) -> str:
    doc = cal.document
    f, s_f = foc["f"]
    fe = foc["effective"][0]
    c = foc["balanced"][0]
    U = "" if s_f is None else f" (U = {K * 1000 * s_f:.2f} µm, k = {K:g})"
    return (f'<div class="summary">Camera <b>{E(str(doc.get("camera_id")))}</b> &middot; {E(cal.method)} method '
            f"&middot; calibrated {E(str(doc.get('acquired') or '')[:10])} &middot; acceptance: "
            f'<span class="verdict {acc["verdict"]}v">{acc["verdict"]}</span><br>'
            f"principal distance f = {f:.4f} mm{E(U)}; effective focal length f / (1 + k0) = {fe:.4f} mm; "
            f"calibrated focal length (balanced distortion) c = {c:.4f} mm &mdash; which to use: section 2.</div>")


def _rig(cal: Calibration, rig: dict | None) -> str:
    """Section 1's rig (a head of a rig): each head's relative orientation, ``u`` in arcsec and mm."""
    if rig is None:
        return ""
    rows = []
    for r in content.rig_rows(rig):
        ref = r["role"] == "reference"
        me = " (this certificate)" if r["version"] == cal.version else ""
        rows.append([f"<td>{E(r['camera_id'] + me)}</td>", f"<td>{E(r['role'])}</td>",
                     f"<td>{E(r['version'])}</td>",
                     *(_num(a, ".5f") for a in r["opk_deg"]),
                     *(("<td>&mdash;</td>",) * 3 if ref else (_num(v, ".2f") for v in r["sigma_rotation_arcsec"])),
                     *(_num(v, ".2f") for v in r["t_mm"]),
                     *(("<td>&mdash;</td>",) * 3 if ref else (_num(v, ".2f") for v in r["sigma_t_mm"]))])
    return (f"<h3>The rig</h3><p>A head of rig <b>{E(str(rig['rig_id']))}</b> (rig version {E(str(rig['version']))}, "
            f"reference head {E(str(rig['reference']))}): every head calibrated in one adjustment with its "
            "relative orientation to the reference, R_camera_to_rig = Rz(κ) Ry(φ) Rx(ω) and the lever arm t; u of "
            "a small rotation about the rig frame's x, y, z axes [arcsec] and of t [mm].</p>"
            + _table(["head", "role", "calibration version", "ω [°]", "φ [°]", "κ [°]", "u x ['']",
                      "u y ['']", "u z ['']", "t x [mm]", "t y [mm]", "t z [mm]", "u x [mm]", "u y [mm]",
                      "u z [mm]"], rows, "keep corr"))


def page(cal: Calibration, residuals, config: dict, acc: dict, *, change, previous_label,
         issued: dt.datetime, rig: dict | None = None) -> str:
    """The whole certificate (:mod:`fieldcal.products.certificate`)."""
    reach = content.data_radius_mm(cal, residuals)
    foc = focal_lengths(cal, reach)
    title = "Camera calibration certificate"
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{E(title)} {E(cal.version)}</title>", f"<style>{_css(cal, config)}</style></head><body>",
        f"<h1>{E(title)}</h1>", f'<p class="certno">Certificate No. <span>{E(cal.version)}</span></p>',
        _summary(cal, foc, acc),
        "<h2>1. Identity</h2>", _identity(cal, config, issued), _rig(cal, rig),
        "<h2>2. Calibrated interior orientation</h2>", _interior(cal),
        '<p class="small">Image-plane frame: origin at the sensor centre, x right, y up; pixel frame: '
        "u right, v down, the centre of the top-left pixel at (0, 0) (docs/conventions.md). u: standard "
        f"uncertainty (a-posteriori, scaled by σ0); U = {K:g} u, the expanded uncertainty (section 7).</p>",
        "<h3>Focal lengths</h3>", _focal_table(cal, foc),
        *_distortion_section(cal, foc, reach),
        "<h2>4. Correlations of the estimated parameters</h2>", _correlations(cal),
        *_adjustment(cal, residuals),
        "<h2>6. Check points</h2>", _checks(cal),
        *_traceability(cal, config),
        "<h2>8. Change since the previous calibration</h2>", _change(change, previous_label),
        _acceptance(acc, config, issued),
        "</body></html>"]
    return "\n".join(parts) + "\n"
