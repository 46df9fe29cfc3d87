r"""The calibration certificate: one printable document per calibration (HTML and PDF, A4).

``fieldcal certificate VERSION --lake LAKE [--out DIR] [--config FILE] [--pdf] [--strict]``
writes ``DIR/certificate.html``, a self-contained page (no external resources; the
distortion plot is inline SVG), and with ``--pdf`` also ``DIR/certificate.pdf``, printed
from that page by headless Chromium (:mod:`fieldcal.products.pdf`): A4, the certificate
number and "page N of M" on every page, table headers repeated where a table continues, the
verdict and the signatures on one page. It follows what a mapping agency's acceptance asks
of a camera calibration report -- the USGS Optical Science Laboratory's "Report of
Calibration of Aerial Mapping Camera", ISO/TS 19159-1 (calibration and validation of remote
sensing imagery sensors, optical sensors) and ISO/IEC 17025's items of a calibration
certificate (identity, conditions, traceability, uncertainty with its coverage factor):

1. identity: certificate number (the version), camera, lens and sensor, method, facility,
   issuer, dates of calibration and issue, valid until; focus and aperture; for a head of a
   rig, the rig (every head's relative orientation to the reference with standard
   uncertainties in arc seconds and mm, and its calibration's version);
2. the calibrated interior orientation with standard uncertainties ``u`` and expanded
   uncertainties ``U = k u``, ``k = 2`` (:data:`COVERAGE_FACTOR`), and the focal lengths a
   user needs (:mod:`fieldcal.products.focal_length`): the model's ``f``, the effective
   focal length ``f / (1 + k0)`` and the calibrated focal length with balanced distortion
   (USGS), each with what it goes with;
3. lens distortion: radial distortion per semi-diagonal relative to the calibrated focal
   length (USGS), a distortion plot, the model's radial distortion and decentering profile
   at round radii relative to ``f``, the coefficients, the model's equations;
4. the correlations of the estimated parameters;
5. the adjustment: sigma0, redundancy, residuals; the sensor's coverage by observations;
6. check points (``stats.check_points``): errors in X, Y and Z and in the image;
7. traceability (how the target field was surveyed or the arm's angles are read: the
   instrument, its date and accuracy; the procedure and its reference) and the
   environmental conditions;
8. the change since the previous calibration of the same camera in the lake, with its
   significance (:func:`fieldcal.analysis.compare.compare_calibrations`);
9. acceptance: each criterion with its threshold, the value and PASS / FAIL / not assessed,
   the verdict (PASS when nothing fails) and the signatures.

Configuration (``--config FILE``, TOML or JSON; every key optional)::

    [certificate]
    organisation = "..."          # who issues the certificate
    facility = "..."              # where the calibration was made
    camera = "..."                # make and model, serial number
    lens = "..."                  # make, model, serial number
    operator = "..."
    validity_years = 3            # the certificate's validity from the calibration date
    strict = false                # true: refuse a certificate without REQUIRED (as --strict)

    [traceability]
    instrument = "..."            # field: how the targets were surveyed (total station, GNSS,
                                  #   sn); goniometer: what reads the arm's angle (encoder, sn)
    date = "..."                  # of the survey / of the instrument's calibration
    accuracy = "..."              # e.g. "1.5 mm (1 sigma) per coordinate", "1 arc second"
    procedure = "..."             # the laboratory's procedure and its reference (the method's
                                  #   paper and fieldcal's version are stated in any case)

    [conditions]
    focus = "..."                 # e.g. "infinity, taped"
    aperture = "..."              # e.g. "f/8"
    temperature_c = 20.0
    humidity_percent = 45.0
    pressure_hpa = 1013.0
    notes = "..."

    [acceptance]                  # thresholds; a criterion set to false is not assessed
    max_sigma0 = 1.5              # a-posteriori sigma0 (field), spot sigma ratio (goniometer)
    max_rmse_px = 0.5             # field: RMS image residual [px]
    max_fit_sigma_px = 0.25       # goniometer: distortion-fit sigma, eq. 10 [px]
    max_sigma_f_um = 10.0         # standard uncertainty of f [um]
    max_sigma_pp_um = 10.0        # of xp and of yp [um]
    max_edge_sigma_px = 0.5       # 1-sigma of where a ray lands at the edge of the data,
                                  #   common camera rotation removed [px]
    min_coverage = 0.5            # field: share of the 10 x 8 sensor cells observed
    max_check_rms_mm = 10.0       # check points, object space (3-D RMS) [mm]
    max_check_rms_px = false      # check points, image space [px]; off by default: the survey's
                                  #   error dominates it (5 mm at 6 m on a 24 mm lens: 5 px)
    min_check_p = 0.01            # check points: chi-square test of their errors against the
                                  #   accuracy the adjustment and the survey predict
    change_tolerance_um = 2.0     # change since the previous certificate: flagged when
    change_alpha = 0.01           #   significant at this level and larger than this

The defaults (:data:`DEFAULT_CONFIG`) are those of the paper-class results the two
methods report (the field paper: sigma f 9.7 um, principal point 4.3 / 3.4 um; the lab
paper: fit sigma 0.17-0.20 px) and of USGS's 3-year certification period. The items of
:data:`REQUIRED` that the configuration leaves out are named in one warning
(:func:`missing_items`); ``--strict`` (or ``strict = true``) refuses the certificate then.
"""

from __future__ import annotations

import copy
import datetime as dt
import json
import math
import os
import tomllib
from pathlib import Path

import numpy as np

from fieldcal.analysis.compare import compare_calibrations
from fieldcal.analysis.uncertainty import Calibration, uncertainty_map
from fieldcal.errors import InputError, LakeError
from fieldcal.products import certificate_sections as sections
from fieldcal.products import content
from fieldcal.products.certificate_sections import COVERAGE_FACTOR

__all__ = ["DEFAULT_CONFIG", "REQUIRED", "COVERAGE_FACTOR", "FILES", "load_config", "missing_items",
           "acceptance", "certificate_html", "write_certificate", "check_outputs"]

DEFAULT_CONFIG: dict = {
    "certificate": {"organisation": None, "facility": None, "camera": None, "lens": None,
                    "operator": None, "validity_years": 3, "strict": False},
    "traceability": {"instrument": None, "date": None, "accuracy": None, "procedure": None},
    "conditions": {"focus": None, "aperture": None, "temperature_c": None, "humidity_percent": None,
                   "pressure_hpa": None, "notes": None},
    "acceptance": {"max_sigma0": 1.5, "max_rmse_px": 0.5, "max_fit_sigma_px": 0.25,
                   "max_sigma_f_um": 10.0, "max_sigma_pp_um": 10.0, "max_edge_sigma_px": 0.5,
                   "min_coverage": 0.5, "max_check_rms_px": False, "max_check_rms_mm": 10.0,
                   "min_check_p": 0.01, "change_tolerance_um": 2.0, "change_alpha": 0.01},
}
"""The configuration's keys and defaults (module docstring)."""

NUMBERS = {("certificate", "validity_years"), ("conditions", "temperature_c"),
           ("conditions", "humidity_percent"), ("conditions", "pressure_hpa")}
"""Keys whose value is a number (besides the acceptance thresholds); the others are text,
``strict`` is true or false."""

REQUIRED = (("certificate", "camera"), ("certificate", "lens"), ("certificate", "facility"),
            ("certificate", "organisation"), ("traceability", "instrument"), ("traceability", "accuracy"),
            ("conditions", "focus"), ("conditions", "aperture"))
"""What an agency's certificate states and only the user knows: warned about when missing,
required with ``--strict``."""

FILES = ("certificate.html", "certificate.pdf")
"""What :func:`write_certificate` writes into its folder (the PDF with ``pdf=True``)."""


# --------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------
def _check_value(section: str, key: str, value, where: str) -> None:
    default = DEFAULT_CONFIG[section][key]
    if section == "acceptance":
        if not (value is False or (isinstance(value, int | float) and not isinstance(value, bool)
                                   and math.isfinite(value))):
            raise InputError(f"[{section}] {key} must be a number (or false), got {value!r}", where)
    elif isinstance(default, bool):
        if not isinstance(value, bool):
            raise InputError(f"[{section}] {key} must be true or false, got {value!r}", where)
    elif (section, key) in NUMBERS:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise InputError(f"[{section}] {key} must be a number, got {value!r}", where)
    elif not isinstance(value, str):
        raise InputError(f"[{section}] {key} must be text, got {value!r}", where)


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
            _check_value(section, key, value, where)
            cfg[section][key] = value
    return cfg


def missing_items(config: dict) -> list[str]:
    """The items of :data:`REQUIRED` the configuration does not state, as ``[section] key``."""
    return [f"[{s}] {k}" for s, k in REQUIRED if not str(config[s].get(k) or "").strip()]


def missing_line(config: dict, config_path=None) -> str | None:
    """One line naming what :func:`missing_items` finds (None when nothing is missing)."""
    missing = missing_items(config)
    if not missing:
        return None
    return (f"not stated: {', '.join(missing)} (give them in {config_path or 'a --config file'}; "
            "they print as 'not stated'; --strict refuses a certificate without them)")


# --------------------------------------------------------------------------------------
# acceptance
# --------------------------------------------------------------------------------------
def _criterion(name: str, limit, value, unit: str, *, upper: bool = True, why: str = "") -> dict:
    if limit is False or limit is None:
        return {"criterion": name, "threshold": "not set", "value": value, "unit": unit,
                "result": "not assessed", "why": why or "no threshold set"}
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return {"criterion": name, "threshold": f"{'≤' if upper else '≥'} {limit:g} {unit}".rstrip(),
                "value": None, "unit": unit, "result": "not assessed", "why": why or "no value"}
    ok = value <= limit if upper else value >= limit
    return {"criterion": name, "threshold": f"{'≤' if upper else '≥'} {limit:g} {unit}".rstrip(),
            "value": value, "unit": unit, "result": "PASS" if ok else "FAIL", "why": why}


def _edge_sigma_px(cal: Calibration, reach_mm: float | None) -> float | None:
    """Largest 1-sigma landing uncertainty within the data's radius, rotation removed [px]."""
    gu, gv, sig = uncertainty_map(cal, (41, 31), remove_rotation=True)
    uu, vv = np.meshgrid(gu, gv)
    xy = cal.sensor.pixel_to_mm(np.column_stack([uu.ravel(), vv.ravel()]))
    r = np.hypot(*(xy - cal.camera.params[1:3]).T).reshape(sig.shape)
    inside = r <= (reach_mm if reach_mm is not None else np.inf)
    return float(sig[inside].max()) if inside.any() else None


def _method_rows(cal: Calibration, residuals, acc: dict, st: dict) -> list[dict]:
    if cal.method == "field":
        cov = content.coverage(cal, residuals)
        limit = acc["min_coverage"]
        return [_criterion("RMS image residual", acc["max_rmse_px"], st.get("rmse_px"), "px"),
                _criterion("sensor coverage (cells with observations)",
                           limit if limit is False else 100 * limit, 100 * cov["fraction"], "%", upper=False)]
    return [_criterion("distortion-fit sigma (eq. 10)", acc["max_fit_sigma_px"], st.get("sigma_fit_px"), "px"),
            {"criterion": "sensor coverage", "threshold": "-", "value": None, "unit": "",
             "result": "not assessed", "why": "a goniometer observes the two scanned axes only, by design"}]


def _check_point_rows(cal: Calibration, acc: dict) -> list[dict]:
    cp = content.check_points(cal) or {}
    why = "" if cp else "no check points"
    rows = []
    for key, unit, limit in (("rms_px", "px", acc["max_check_rms_px"]), ("rms_mm", "mm", acc["max_check_rms_mm"])):
        value = cp.get(key)
        rows.append(_criterion(f"check-point RMS ({unit})", limit, float(value) if isinstance(value, int | float)
                               else None, unit, why=why or ("image space: the survey's error dominates it; judged "
                                                            "by the object-space RMS and the chi-square test"
                                                            if unit == "px" and limit is False else "")))
    p = cp.get("p_value_mm")
    rows.append(_criterion("check points within their predicted accuracy (chi-square p)", acc["min_check_p"],
                           float(p) if isinstance(p, int | float) else None, "", upper=False,
                           why=why or f"chi-square {cp.get('chi2_mm', float('nan')):.4g} on {cp.get('dof_mm')} "
                                      "degrees of freedom"))
    return rows


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
    rows += _method_rows(cal, residuals, acc, st)
    rows.append(_criterion("σ of f", acc["max_sigma_f_um"], None if s_f is None else 1000 * s_f, "µm"))
    pp = None if s_x is None or s_y is None else 1000 * max(s_x, s_y)
    rows.append(_criterion("σ of the principal point (larger of xp, yp)", acc["max_sigma_pp_um"], pp, "µm"))
    rows.append(_criterion("projection uncertainty within the observed radius (1 σ, "
                           "rotation removed)", acc["max_edge_sigma_px"], _edge_sigma_px(cal, reach), "px"))
    rows += _check_point_rows(cal, acc)
    if change is None:
        rows.append({"criterion": "change since the previous certificate", "threshold": "not flagged",
                     "value": None, "unit": "", "result": "not assessed",
                     "why": "no previous calibration of this camera"})
    else:
        rows.append({"criterion": "change since the previous certificate",
                     "threshold": f"not (significant at {change.alpha:g} and > {change.tolerance_um:g} µm)",
                     "value": change.max_um, "unit": "µm", "result": "FAIL" if change.flagged else "PASS",
                     "why": change.verdict})
    verdict = "FAIL" if any(r["result"] == "FAIL" for r in rows) else "PASS"
    return {"rows": rows, "verdict": verdict}


# --------------------------------------------------------------------------------------
# the document
# --------------------------------------------------------------------------------------
def certificate_html(cal: Calibration, residuals, config: dict, *, change=None, previous_label=None,
                     issued: dt.datetime | None = None, rig: dict | None = None) -> str:
    """The certificate's HTML (module docstring); ``change`` a
    :class:`fieldcal.analysis.compare.Comparison` with the previous calibration or None;
    ``rig`` the rig document of the rig version this calibration is a head of, or None."""
    issued = issued or dt.datetime.now(dt.UTC)
    return sections.page(cal, residuals, config, acceptance(cal, residuals, config, change),
                         change=change, previous_label=previous_label, issued=issued, rig=rig)


def check_outputs(out_dir, *, pdf: bool = False) -> None:
    """Refuse, before any work, an output folder that is a file or already holds a certificate
    (fieldcal does not overwrite a document someone may have signed)."""
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", str(out))
    for name in FILES[: 2 if pdf else 1]:
        if (out / name).exists():
            raise InputError(f"{name} exists there: fieldcal does not overwrite a certificate "
                             "(remove it or choose another --out)", str(out))


def _comparison(lake, cal: Calibration, config: dict):
    prev = content.previous_version(lake, cal)
    if prev is None:
        return None, None
    try:
        before = Calibration.from_lake(lake, prev)
        acc = config["acceptance"]
        change = compare_calibrations(before, cal, tolerance_um=float(acc["change_tolerance_um"] or 2.0),
                                      alpha=float(acc["change_alpha"] or 0.01))
        return change, before.label()
    except (InputError, LakeError):
        return None, None


def write_certificate(lake, version: str, out_dir, config_path=None, *, pdf: bool = False,
                      strict: bool = False) -> Path:
    """Write ``out_dir/certificate.html`` (and with ``pdf`` ``certificate.pdf``) for a committed
    version; returns the path of the last file written.

    The configuration and the output folder are checked first (a bad file, a missing item
    under ``strict``, an existing certificate: :class:`InputError` before anything is read
    from the lake or written).
    """
    config = load_config(config_path)
    if (strict or config["certificate"]["strict"]) and missing_items(config):
        raise InputError(f"--strict: not stated: {', '.join(missing_items(config))}",
                         str(config_path) if config_path else "configuration")
    check_outputs(out_dir, pdf=pdf)
    if pdf:
        from fieldcal.products.pdf import chromium

        chromium()                                   # no browser: said before the work
    cal = Calibration.from_lake(lake, version)
    residuals = lake.read_residuals(version)
    change, label = _comparison(lake, cal, config)
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise InputError(f"cannot create the output folder: {e.strerror or e}", str(out)) from None
    page = out / FILES[0]
    tmp = out / f".{FILES[0]}.{os.getpid()}"
    tmp.write_text(certificate_html(cal, residuals, config, change=change, previous_label=label,
                                    rig=lake.rig_of(cal.document)), encoding="utf-8")
    os.replace(tmp, page)
    if not pdf:
        return page
    from fieldcal.products.pdf import html_to_pdf

    return html_to_pdf(page, out / FILES[1])
