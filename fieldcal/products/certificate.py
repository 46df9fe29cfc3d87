r"""The calibration certificate: one printable page set per calibration (HTML, A4).

``fieldcal certificate VERSION --lake LAKE [--out DIR] [--config FILE]`` writes
``DIR/certificate.html``: a self-contained document (no images, no external resources)
that prints cleanly on A4 (print it to PDF from any browser). It follows what a mapping
agency's acceptance asks of a camera calibration report -- the USGS Optical Science
Laboratory's "Report of Calibration of Aerial Mapping Camera" and ISO/TS 19159-1
(calibration and validation of remote sensing imagery sensors, optical sensors):

1. identity: certificate number (the version), camera, lens and sensor, method and
   facility, date of calibration, date of issue, valid until;
2. calibrated interior orientation: principal distance and principal point in mm and in
   pixels, with standard deviations (:func:`fieldcal.products.content.interior_rows`);
3. lens distortion: radial distortion and the decentering profile at round field angles
   and at round radii, in um with standard deviations, marked where extrapolated beyond
   the observations; all coefficients of the model with their sigmas; the model's
   equations;
4. the correlations of the estimated parameters;
5. the adjustment: sigma0, redundancy, residuals; the sensor's coverage by observations;
6. check-point accuracy when the version has check points (``stats.check_points``), else
   "no check points";
7. the change since the previous calibration of the same camera in the lake, with its
   significance (:func:`fieldcal.products.compare.compare_calibrations`);
8. acceptance: each criterion with its threshold, the value and PASS / FAIL / not
   assessed, and the verdict (PASS when nothing fails).

Configuration (``--config FILE``, TOML or JSON; every key optional)::

    [certificate]
    organisation = "..."          # who issues the certificate
    facility = "..."              # where the calibration was made
    camera = "..."                # make and model, serial number
    lens = "..."                  # make, model, serial number
    operator = "..."
    validity_years = 3            # the certificate's validity from the calibration date

    [acceptance]                  # thresholds; a criterion set to false is not assessed
    max_sigma0 = 1.5              # a-posteriori sigma0 (field), spot sigma ratio (goniometer)
    max_rmse_px = 0.5             # field: RMS image residual [px]
    max_fit_sigma_px = 0.25       # goniometer: distortion-fit sigma, eq. 10 [px]
    max_sigma_f_um = 10.0         # standard deviation of f [um]
    max_sigma_pp_um = 10.0        # of xp and of yp [um]
    max_edge_sigma_px = 0.5       # 1-sigma of where a ray lands at the edge of the data,
                                  #   common camera rotation removed [px]
    min_coverage = 0.5            # field: share of the 10 x 8 sensor cells observed
    max_check_rms_px = 0.5        # check points, image space [px]
    max_check_rms_mm = 10.0       # check points, object space [mm]
    change_tolerance_um = 2.0     # change since the previous certificate: flagged when
    change_alpha = 0.01           #   significant at this level and larger than this

The defaults (:data:`DEFAULT_CONFIG`) are those of the paper-class results the two
methods report (the field paper: sigma f 9.7 um, principal point 4.3 / 3.4 um; the lab
paper: fit sigma 0.17-0.20 px) and of USGS's 3-year certification period.
"""

from __future__ import annotations

import copy
import datetime as dt
import html
import json
import math
import tomllib
from pathlib import Path

import numpy as np

from fieldcal.errors import InputError, LakeError
from fieldcal.model.camera import PARAM_NAMES
from fieldcal.products import content
from fieldcal.products.compare import compare_calibrations
from fieldcal.products.uncertainty import Calibration, uncertainty_map

__all__ = ["DEFAULT_CONFIG", "load_config", "acceptance", "certificate_html", "write_certificate"]

DEFAULT_CONFIG: dict = {
    "certificate": {"organisation": None, "facility": None, "camera": None, "lens": None,
                    "operator": None, "validity_years": 3},
    "acceptance": {"max_sigma0": 1.5, "max_rmse_px": 0.5, "max_fit_sigma_px": 0.25,
                   "max_sigma_f_um": 10.0, "max_sigma_pp_um": 10.0, "max_edge_sigma_px": 0.5,
                   "min_coverage": 0.5, "max_check_rms_px": 0.5, "max_check_rms_mm": 10.0,
                   "change_tolerance_um": 2.0, "change_alpha": 0.01},
}
"""The configuration's keys and defaults (module docstring)."""

UNITS = {"f_mm": "mm", "xp_mm": "mm", "yp_mm": "mm", "k0": "1", "k1": "mm^-2", "k2": "mm^-4",
         "k3": "mm^-6", "p1": "mm^-1", "p2": "mm^-1", "a1": "1", "a2": "1", "b1": "1", "b2": "1"}


# --------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------
def load_config(path=None) -> dict:
    """The configuration: :data:`DEFAULT_CONFIG` updated from a TOML or JSON file.

    Raises
    ------
    InputError
        The file cannot be read or parsed, has an unknown section or key, or a value of the
        wrong type; the message names the file.
    """
    cfg = copy.deepcopy(DEFAULT_CONFIG)
    if path is None:
        return cfg
    where = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read the configuration: {getattr(e, 'strerror', None) or e}", where) from None
    try:
        given = json.loads(text) if where.endswith(".json") else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"not valid {'JSON' if where.endswith('.json') else 'TOML'}: {e}", where) from None
    if not isinstance(given, dict):
        raise InputError("the configuration must be a table of sections", where)
    for section, values in given.items():
        if section not in cfg or not isinstance(values, dict):
            raise InputError(f"unknown section [{section}]; allowed: {', '.join(cfg)}", where)
        for key, value in values.items():
            if key not in cfg[section]:
                raise InputError(f"unknown key {key!r} in [{section}]; allowed: "
                                 f"{', '.join(cfg[section])}", where)
            default = DEFAULT_CONFIG[section][key]
            numeric = isinstance(default, int | float) and not isinstance(default, bool)
            if numeric and not (value is False or (isinstance(value, int | float)
                                                   and not isinstance(value, bool) and math.isfinite(value))):
                raise InputError(f"[{section}] {key} must be a number (or false), got {value!r}", where)
            if default is None and not isinstance(value, str):
                raise InputError(f"[{section}] {key} must be text, got {value!r}", where)
            cfg[section][key] = value
    return cfg


# --------------------------------------------------------------------------------------
# acceptance
# --------------------------------------------------------------------------------------
def _criterion(name: str, limit, value, unit: str, *, upper: bool = True, why: str = "") -> dict:
    if limit is False or limit is None:
        return {"criterion": name, "threshold": "not set", "value": value, "unit": unit,
                "result": "not assessed", "why": why or "no threshold set"}
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return {"criterion": name, "threshold": f"{'<=' if upper else '>='} {limit:g} {unit}",
                "value": None, "unit": unit, "result": "not assessed", "why": why or "no value"}
    ok = value <= limit if upper else value >= limit
    return {"criterion": name, "threshold": f"{'<=' if upper else '>='} {limit:g} {unit}",
            "value": value, "unit": unit, "result": "PASS" if ok else "FAIL", "why": why}


def _edge_sigma_px(cal: Calibration, reach_mm: float | None) -> float | None:
    """Largest 1-sigma landing uncertainty within the data's radius, rotation removed [px]."""
    gu, gv, sig = uncertainty_map(cal, (41, 31), remove_rotation=True)
    uu, vv = np.meshgrid(gu, gv)
    xy = cal.sensor.pixel_to_mm(np.column_stack([uu.ravel(), vv.ravel()]))
    r = np.hypot(*(xy - cal.camera.params[1:3]).T).reshape(sig.shape)
    inside = r <= (reach_mm if reach_mm is not None else np.inf)
    return float(sig[inside].max()) if inside.any() else None


def acceptance(cal: Calibration, residuals, config: dict, change=None) -> dict:
    """Every criterion of ``config["acceptance"]`` against this calibration.

    Returns
    -------
    dict
        ``rows`` (``criterion, threshold, value, unit, result, why``) and ``verdict``
        (``PASS`` when none fails, else ``FAIL``).
    """
    acc = config["acceptance"]
    st = cal.document.get("stats") or {}
    adj = content.adjustment_figures(cal)
    reach = content.data_radius_mm(cal, residuals)
    s_f, s_x, s_y = (cal.sigma_of(n) for n in ("f_mm", "xp_mm", "yp_mm"))
    rows = [_criterion("sigma0", acc["max_sigma0"], adj["sigma0"], "",
                       why="" if cal.method == "field" else
                       "goniometer: a-posteriori spot accuracy / frame-to-frame scatter")]
    if cal.method == "field":
        rows.append(_criterion("RMS image residual", acc["max_rmse_px"], st.get("rmse_px"), "px"))
        cov = content.coverage(cal, residuals)
        limit = acc["min_coverage"]
        rows.append(_criterion("sensor coverage (cells with observations)",
                               limit if limit is False else 100 * limit, 100 * cov["fraction"], "%",
                               upper=False))
    else:
        rows.append(_criterion("distortion-fit sigma (eq. 10)", acc["max_fit_sigma_px"],
                               st.get("sigma_fit_px"), "px"))
        rows.append({"criterion": "sensor coverage", "threshold": "-", "value": None, "unit": "",
                     "result": "not assessed",
                     "why": "a goniometer observes the two scanned axes only, by design"})
    rows.append(_criterion("sigma of f", acc["max_sigma_f_um"], None if s_f is None else 1000 * s_f, "um"))
    pp = None if s_x is None or s_y is None else 1000 * max(s_x, s_y)
    rows.append(_criterion("sigma of the principal point (larger of xp, yp)", acc["max_sigma_pp_um"], pp, "um"))
    rows.append(_criterion("projection uncertainty within the observed radius (1 sigma, "
                           "rotation removed)", acc["max_edge_sigma_px"], _edge_sigma_px(cal, reach), "px"))
    cp = content.check_points(cal) or {}
    for key, unit, limit in (("rms_px", "px", acc["max_check_rms_px"]), ("rms_mm", "mm", acc["max_check_rms_mm"])):
        value = next((float(v) for k, v in cp.items() if k.endswith(key) and isinstance(v, int | float)), None)
        rows.append(_criterion(f"check-point RMS ({unit})", limit, value, unit,
                               why="" if cp else "no check points"))
    if change is None:
        rows.append({"criterion": "change since the previous certificate", "threshold": "not flagged",
                     "value": None, "unit": "", "result": "not assessed",
                     "why": "no previous calibration of this camera"})
    else:
        rows.append({"criterion": "change since the previous certificate",
                     "threshold": f"not (significant at {change.alpha:g} and > {change.tolerance_um:g} um)",
                     "value": change.max_um, "unit": "um", "result": "FAIL" if change.flagged else "PASS",
                     "why": change.verdict})
    verdict = "FAIL" if any(r["result"] == "FAIL" for r in rows) else "PASS"
    return {"rows": rows, "verdict": verdict}


# --------------------------------------------------------------------------------------
# HTML
# --------------------------------------------------------------------------------------
_CSS = """
@page { size: A4; margin: 16mm 14mm 16mm 14mm; }
body { font-family: "DejaVu Sans", Helvetica, Arial, sans-serif; font-size: 10pt; color: #111;
       max-width: 182mm; margin: 0 auto; line-height: 1.35; }
h1 { font-size: 17pt; margin: 0 0 2mm 0; } h2 { font-size: 12pt; margin: 6mm 0 2mm 0;
     border-bottom: 0.4mm solid #333; page-break-after: avoid; break-after: avoid; }
h3 { font-size: 10.5pt; margin: 3mm 0 1mm 0; page-break-after: avoid; }
table { border-collapse: collapse; margin: 1mm 0 2mm 0; font-size: 9pt; page-break-inside: auto; }
tr { page-break-inside: avoid; break-inside: avoid; }
th, td { border: 0.2mm solid #888; padding: 0.6mm 1.6mm; text-align: left; vertical-align: top; }
th { background: #eee; } td.num { text-align: right; font-family: "DejaVu Sans Mono", monospace;
     white-space: nowrap; }
td.PASS { background: #d9f2d9; font-weight: bold; } td.FAIL { background: #f6c9c9; font-weight: bold; }
td.na { color: #666; } tr.extra td { color: #777; font-style: italic; }
.verdict { font-size: 13pt; font-weight: bold; padding: 1.5mm 3mm; border: 0.5mm solid #333;
           display: inline-block; } .PASSv { background: #d9f2d9; } .FAILv { background: #f6c9c9; }
table.ident td:first-child { font-weight: bold; width: 48mm; }
pre { font-size: 8.5pt; background: #f6f6f6; padding: 2mm; border: 0.2mm solid #ccc; }
.small { font-size: 8.5pt; color: #333; } .sign td { height: 14mm; width: 88mm; }
table.cover td { width: 7mm; height: 4mm; text-align: center; font-size: 7pt; padding: 0; }
section { page-break-inside: auto; }
@media screen { body { padding: 8mm; } }
"""


def _f(x, fmt: str = ".4g") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "&mdash;"
    return html.escape(format(x, fmt))


def _table(headers, rows, cls: str = "") -> str:
    """A table; each row a list of ``<td>`` strings, or a ``(row_class, cells)`` pair."""
    out = [f'<table class="{cls}">']
    if headers:
        out.append("<tr>" + "".join(f"<th>{h}</th>" for h in headers) + "</tr>")
    for row in rows:
        rc, cells = row if isinstance(row, tuple) else ("", row)
        out.append(f'<tr class="{rc}">' + "".join(cells) + "</tr>")
    return "\n".join(out) + "</table>"


def _identity(cal: Calibration, cfg: dict, issued: dt.datetime) -> str:
    doc, c = cal.document, cfg["certificate"]
    e = html.escape
    s = cal.sensor
    acquired = content.parse_time(doc.get("acquired")) or content.parse_time(doc.get("created"))
    years = c.get("validity_years")
    valid = (acquired.replace(year=acquired.year + int(years)) if acquired and years else None)
    rows = [("certificate number", cal.version), ("camera", doc.get("camera_id")),
            ("camera make / model / serial", c.get("camera") or "not stated"),
            ("lens", c.get("lens") or "not stated"),
            ("sensor", f"{s.width_px} x {s.height_px} px, pixel pitch {s.pixel_size_um:g} um "
                       f"({s.width_px * s.pixel_size_um / 1000:.2f} x {s.height_px * s.pixel_size_um / 1000:.2f} mm)"),
            ("method", content.METHOD_NAMES.get(cal.method, cal.method)),
            ("facility", c.get("facility") or "not stated"),
            ("issued by", c.get("organisation") or "not stated"),
            ("calibration session", doc.get("session_id")),
            ("date of calibration", acquired.strftime("%Y-%m-%d") if acquired else "unknown"),
            ("date of issue", issued.strftime("%Y-%m-%d")),
            ("valid until", valid.strftime("%Y-%m-%d") + f" ({years} years from the calibration)"
             if valid else "not stated"),
            ("model", f"{doc.get('model')} (equations in section 3)"),
            ("computed by", f"fieldcal {doc.get('code_version') or ''} on {doc.get('created')}"),
            ("inputs' fingerprint", (doc.get("inputs") or {}).get("fingerprint"))]
    return _table(["item", "value"], [[f"<td>{e(k)}</td>", f"<td>{e(str(v))}</td>"] for k, v in rows], "ident")


def _interior(cal: Calibration) -> str:
    rows = [[f"<td>{html.escape(r['name'])}</td>", f'<td class="num">{_f(r["mm"], ".6f")}</td>',
             f'<td class="num">{_f(None if r["sigma_mm"] is None else 1000 * r["sigma_mm"], ".2f")}</td>',
             f'<td class="num">{_f(r["px"], ".3f")}</td>', f'<td class="num">{_f(r["sigma_px"], ".3f")}</td>',
             f"<td>{html.escape(r['note'])}</td>"] for r in content.interior_rows(cal)]
    return _table(["", "value [mm]", "sigma [um]", "value [px]", "sigma [px]", ""], rows)


def _distortion(cal: Calibration, reach: float | None, by: str) -> str:
    rows = []
    for r in content.distortion_table(cal, by=by, reach_mm=reach):
        cells = [f'<td class="num">{r["angle_deg"]:.2f}</td>', f'<td class="num">{r["r_mm"]:.3f}</td>',
                 f'<td class="num">{r["radial_um"]:+.2f}</td>', f'<td class="num">{r["sigma_radial_um"]:.2f}</td>',
                 f'<td class="num">{r["decentering_um"]:.2f}</td>',
                 f'<td class="num">{r["sigma_decentering_um"]:.2f}</td>']
        rows.append(("extra" if r["extrapolated"] else "", cells))
    return _table(["field angle [deg]", "radius [mm]", "radial distortion [um]", "sigma [um]",
                   "decentering profile [um]", "sigma [um]"], rows)


def _coefficients(cal: Calibration) -> str:
    doc = cal.document
    fixed = (doc.get("stats") or {}).get("fixed_parameters") or {}
    rows = []
    for n in PARAM_NAMES:
        s = (doc.get("sigma") or {}).get(n)
        note = "estimated" if s is not None else ("held: " + str(fixed[n]) if n in fixed else "fixed by the method")
        rows.append([f"<td>{n}</td>", f'<td class="num">{_f(float(doc["parameters"][n]), ".6e")}</td>',
                     f'<td class="num">{_f(s, ".2e")}</td>', f"<td>{UNITS[n]}</td>",
                     f'<td class="small">{html.escape(note)}</td>'])
    return _table(["parameter", "value", "sigma", "unit", ""], rows)


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
    return _table([""] + names, rows)


def _coverage(cal: Calibration, residuals) -> str:
    cov = content.coverage(cal, residuals)
    counts = cov["counts"]
    top = max(int(counts.max()), 1)
    rows = []
    for row in counts:
        rows.append([f'<td style="background: rgba(30, 90, 200, {0.15 + 0.85 * c / top if c else 0:.2f})">'
                     f"{c if c else ''}</td>" for c in row])
    rf = cov["radius_fraction"]
    text = (f"<p>{100 * cov['fraction']:.0f} % of the {counts.shape[1]} x {counts.shape[0]} cells of the "
            f"sensor hold observations (number per cell below, the sensor as seen on its pixel grid, "
            f"row 0 at the top); the observations reach "
            f"{'&mdash;' if rf is None else f'{100 * rf:.0f} %'} of the half diagonal from the principal point.</p>")
    return text + _table([], rows, "cover")


def _checks(cal: Calibration) -> str:
    cp = content.check_points(cal)
    if cp is None:
        return "<p>No check points: this calibration withheld no surveyed targets from the adjustment.</p>"
    rows = [[f"<td>{html.escape(str(k))}</td>",
             f'<td class="num">{_f(v) if isinstance(v, int | float) else html.escape(str(v))}</td>']
            for k, v in cp.items()]
    return _table(["figure", "value"], rows)


def _change(change, prev_label: str | None) -> str:
    if change is None:
        return "<p>No previous calibration of this camera in the lake: nothing to compare.</p>"
    rows = [[f"<td>{html.escape(t.label)}</td>",
             f'<td class="num">{", ".join(f"{c:.3g}" if t.key == "map" else f"{c:+.3g}" for c in t.change)} '
             f'{t.unit}</td>',
             f'<td class="num">{", ".join(f"{s:.3g}" for s in t.sigma)} {t.unit}</td>',
             f'<td class="num">{t.p_value:.3g}</td>', f'<td class="num">{t.p_adjusted:.3g}</td>',
             f"<td>{'yes' if t.significant(change.alpha) else 'no'}</td>"] for t in change.tests]
    out = [f"<p>Against {html.escape(prev_label or '')}: tested {html.escape(change.where)}; largest change "
           f"{change.max_um:.3g} um ({change.max_px:.3g} px), RMS {change.rms_um:.3g} um "
           f"({change.rms_px:.3g} px). Each quantity is tested against the two calibrations' "
           f"uncertainties; Holm's correction keeps the family at the level {change.alpha:g} "
           f"(for the map row the change is the largest, the sigma the largest 1-sigma).</p>",
           _table(["quantity", "change (B - A)", "1 sigma", "p", "p (Holm)", "significant"], rows)]
    out += [f'<p class="small">Not tested: {html.escape(x)}.</p>' for x in change.left_out]
    out.append(f"<p><b>Verdict:</b> {html.escape(change.verdict)}</p>")
    return "\n".join(out)


def _acceptance(acc: dict) -> str:
    rows = []
    for r in acc["rows"]:
        cls = r["result"] if r["result"] in ("PASS", "FAIL") else "na"
        v = _f(r["value"]) if isinstance(r["value"], int | float) else "&mdash;"
        rows.append([f"<td>{html.escape(r['criterion'])}</td>", f"<td>{html.escape(r['threshold'])}</td>",
                     f'<td class="num">{v} {html.escape(r["unit"])}</td>',
                     f'<td class="{cls}">{html.escape(r["result"])}</td>',
                     f'<td class="small">{html.escape(r["why"])}</td>'])
    return (_table(["criterion", "threshold", "value", "result", "note"], rows)
            + f'<p>Verdict: <span class="verdict {acc["verdict"]}v">{acc["verdict"]}</span></p>')


def certificate_html(cal: Calibration, residuals, config: dict, *, change=None, previous_label=None,
                     issued: dt.datetime | None = None) -> str:
    """The certificate's HTML (module docstring); ``change`` a
    :class:`fieldcal.products.compare.Comparison` with the previous calibration or None."""
    issued = issued or dt.datetime.now(dt.UTC)
    reach = content.data_radius_mm(cal, residuals)
    adj = content.adjustment_figures(cal)
    acc = acceptance(cal, residuals, config, change)
    e = html.escape
    title = f"Camera calibration certificate {cal.version}"
    reach_txt = ("" if reach is None else
                 f" Rows in grey italics lie beyond {reach:.2f} mm, the farthest observation from the "
                 f"principal point: there the values are the model's extrapolation.")
    parts = [
        "<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">', f"<title>{e(title)}</title>",
        f"<style>{_CSS}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        f'<p>Camera <b>{e(str(cal.document.get("camera_id")))}</b> &middot; {e(cal.method)} method &middot; '
        f'acceptance: <span class="verdict {acc["verdict"]}v">{acc["verdict"]}</span></p>',
        "<h2>1. Identity</h2>", _identity(cal, config, issued),
        "<h2>2. Calibrated interior orientation</h2>", _interior(cal),
        '<p class="small">Image-plane frame: origin at the sensor centre, x right, y up; pixel frame: '
        "u right, v down, the centre of the top-left pixel at (0, 0) (docs/conventions.md). "
        "Standard deviations are a-posteriori (scaled by sigma0).</p>",
        "<h2>3. Lens distortion</h2>",
        "<p>Radial distortion (measured minus ideal radius; positive: the image lies farther from "
        "the principal point than the ideal pinhole image) and the decentering profile "
        "sqrt(p1^2 + p2^2) r^2, with standard deviations propagated from the covariance."
        f"{e(reach_txt)}</p>",
        "<h3>At field angles</h3>", _distortion(cal, reach, "angle"),
        "<h3>At radii</h3>", _distortion(cal, reach, "radius"),
        "<h3>Coefficients</h3>", _coefficients(cal),
        "<h3>The model (fieldcal-brown/1)</h3>", f"<pre>{e(content.MODEL_EQUATIONS)}</pre>",
        '<p class="small">(x\', y\') measured image point [mm]; the correction (dx, dy) moves it to the '
        "ideal point; R1..R3 the rows of the world-to-camera rotation, C the camera centre.</p>",
        "<h2>4. Correlations of the estimated parameters</h2>", _correlations(cal),
        "<h2>5. Adjustment and coverage</h2>",
        _table(["sigma0", "redundancy", "equations", "unknowns", adj["what"]],
               [[f'<td class="num">{_f(adj["sigma0"])}</td>', f'<td class="num">{adj["redundancy"]}</td>',
                 f'<td class="num">{adj["n_equations"]}</td>', f'<td class="num">{adj["n_unknowns"]}</td>',
                 f'<td class="num">{_f(adj["rmse_px"])} px, max {_f(adj["max_px"])} px</td>']]),
        _coverage(cal, residuals),
        "<h2>6. Check points</h2>", _checks(cal),
        "<h2>7. Change since the previous calibration</h2>", _change(change, previous_label),
        "<h2>8. Acceptance</h2>", _acceptance(acc),
        '<table class="sign"><tr><th>calibrated by</th><th>approved by</th></tr>'
        f"<tr><td>{e(config['certificate'].get('operator') or '')}</td><td></td></tr></table>",
        f'<p class="small">Issued {issued.strftime("%Y-%m-%dT%H:%M:%SZ")} by fieldcal from the lake '
        "version above; every number can be traced to that version's document and arrays.</p>",
        "</body></html>"]
    return "\n".join(parts) + "\n"


def write_certificate(lake, version: str, out_dir, config_path=None) -> Path:
    """Write ``out_dir/certificate.html`` for a committed version; returns its path.

    The configuration is read first (a bad file is reported before anything is read from
    the lake or written).
    """
    config = load_config(config_path)
    cal = Calibration.from_lake(lake, version)
    residuals = lake.read_residuals(version)
    change, label = None, None
    prev = content.previous_version(lake, cal)
    if prev is not None:
        try:
            before = Calibration.from_lake(lake, prev)
            acc = config["acceptance"]
            change = compare_calibrations(before, cal, tolerance_um=float(acc["change_tolerance_um"] or 2.0),
                                          alpha=float(acc["change_alpha"] or 0.01))
            label = before.label()
        except (InputError, LakeError):
            change = None
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the output folder: {e.strerror or e}", str(out)) from None
    page = out / "certificate.html"
    page.write_text(certificate_html(cal, residuals, config, change=change, previous_label=label),
                    encoding="utf-8")
    return page
