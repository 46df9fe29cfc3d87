"""The fleet dashboard: a static site of every camera's state, written from the lake.

``fieldcal dashboard --lake LAKE --out DIR`` writes ``DIR/index.html`` and one page per
camera, ``DIR/cameras/<camera_id>.html``: plain HTML with inline SVG plots, CSS and a few
lines of JavaScript for the filters; no server, no external resource (open ``index.html``
from disk, or serve ``DIR`` behind any web server).

- **index.html**: one row per camera: its latest calibration (session, acquisition time,
  method, ``f`` with its sigma), the verdict of the certificate's acceptance criteria (the
  change since the previous calibration included), the certificate's validity (valid until
  acquisition + ``validity_years``, days left, expired), the last change test (largest change,
  p-value, FLAGGED) and links to the camera's page and to the latest report and certificate.
  Filters: *moved* (flagged), *expired*, *failed* (verdict FAIL); the counts are shown;
  ``index.html#moved,failed`` opens with those filters on.
- **cameras/<id>.html**: history plots of ``f``, ``xp``, ``yp`` and the radial distortion at
  :data:`fieldcal.products.status.RADII_FRACTIONS` of the half diagonal, over the
  acquisition time, with 1-sigma bands and the tolerance (a band of +-``tolerance_um``
  around the first calibration); the list of versions with links to their reports and
  certificates (written by the runs into ``LAKE/reports/``; :mod:`flows.publish`).

Everything is read from the lake in a few table scans: the catalog, the stored change tests
and assessments (:mod:`fieldcal.products.status`; a latest pair or version they lack is
computed and remembered). Order and "previous" follow :mod:`fieldcal.lake.order`.
"""

from __future__ import annotations

import datetime as dt
import html
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM, check_level, judge
from fieldcal.errors import InputError
from fieldcal.lake import order
from fieldcal.products import status
from fieldcal.products.certificate import load_config
from fieldcal.products.svgplot import series_plot

__all__ = ["CameraState", "fleet_state", "write_dashboard", "COLUMNS"]

COLUMNS = ["camera_id", "session_id", "version", "method", "acquired", "created", "committed", "f_mm",
           "sigma_f_mm", "xp_mm", "sigma_xp_mm", "yp_mm", "sigma_yp_mm", "rmse_px", "n_images"]
"""Catalog columns the dashboard reads."""


@dataclass
class CameraState:
    """One camera on the dashboard: its calibrations in order and what they say."""

    camera_id: str
    history: list = field(default_factory=list)      # catalog rows, latest of each session, in order
    versions: list = field(default_factory=list)     # every catalog row, in order
    change: dict | None = None                       # judged change test of the latest pair
    assessment: dict | None = None                   # stored assessment of the latest
    valid_until: dt.datetime | None = None
    days_left: int | None = None

    @property
    def latest(self) -> dict:
        return self.history[-1]

    @property
    def moved(self) -> bool:
        return bool(self.change and self.change.get("flagged"))

    @property
    def expired(self) -> bool:
        return self.days_left is not None and self.days_left < 0

    @property
    def verdict(self) -> str:
        """PASS / FAIL of the acceptance (a flagged change fails it), or "not assessed"."""
        a = self.assessment or {}
        if "verdict" not in a:
            return "FAIL" if self.moved else "not assessed"
        return "FAIL" if a["verdict"] == "FAIL" or self.moved else "PASS"


def _valid_until(row: dict, years) -> dt.datetime | None:
    when = row.get("acquired") or row.get("created")
    if when is None or not years:
        return None
    try:
        return when.replace(year=when.year + int(years))
    except ValueError:                                    # 29 February
        return when.replace(year=when.year + int(years), day=28)


def fleet_state(lake, *, config: dict | None = None, today: dt.date | None = None,
                tolerance_um: float = DEFAULT_TOLERANCE_UM, alpha: float = DEFAULT_ALPHA) -> list[CameraState]:
    """Every camera's state (:class:`CameraState`), ordered by camera id."""
    check_level(tolerance_um, alpha)
    config = config or load_config()
    today = today or dt.datetime.now(dt.UTC).date()
    by_camera: dict = {}
    for row in lake.tables.scan("catalog", columns=COLUMNS).to_pylist():
        by_camera.setdefault(row["camera_id"], []).append(row)
    cams = []
    for camera in sorted(by_camera):
        rows = sorted(by_camera[camera], key=order.order_key)
        cams.append(CameraState(camera, order.session_latest(rows), rows))
    pairs = {c.camera_id: (c.history[-2]["version"], c.latest["version"]) for c in cams if len(c.history) > 1}
    records = status.changes(lake, list(pairs.values()))
    stored = status.assessments(lake, [c.latest["version"] for c in cams], config, brief=True)
    years = config["certificate"].get("validity_years")
    for c in cams:
        rec = records.get(pairs.get(c.camera_id))
        if rec is not None:
            c.change = dict(rec, **judge(rec, tolerance_um, alpha)) if "error" not in rec else rec
        c.assessment = stored.get(c.latest["version"])
        c.valid_until = _valid_until(c.latest, years)
        if c.valid_until is not None:
            c.days_left = (c.valid_until.date() - today).days
    return cams


# --------------------------------------------------------------------------------------
# the pages
# --------------------------------------------------------------------------------------
_CSS = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 1.5em; color: #222; }
table { border-collapse: collapse; } th, td { padding: 3px 8px; border-bottom: 1px solid #ddd; white-space: nowrap; }
th { text-align: left; background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
.FAIL, .moved, .expired { color: #b00020; font-weight: 600; } .PASS { color: #1b7f3b; }
.filters label { margin-right: 1.2em; } .counts { margin: .6em 0; } .plots svg { margin: 0 1em 1em 0; }
.small { color: #666; font-size: 12px; }
"""

_FILTER_JS = """
function applyFilters() {
  const on = [...document.querySelectorAll('.filters input:checked')].map(x => x.value);
  let shown = 0;
  document.querySelectorAll('#fleet tbody tr').forEach(tr => {
    const keep = on.every(f => tr.dataset[f] === 'yes');
    tr.hidden = !keep; if (keep) shown += 1;
  });
  document.getElementById('shown').textContent = shown;
}
document.querySelectorAll('.filters input').forEach(x => {
  x.checked = x.checked || location.hash.slice(1).split(',').includes(x.value);   // index.html#moved,failed
  x.addEventListener('change', applyFilters);
});
applyFilters();
"""


def _e(x) -> str:
    return html.escape("" if x is None else str(x))


def _when(t) -> str:
    return "" if t is None else t.astimezone(dt.UTC).strftime("%Y-%m-%d")


def _page(title: str, body: list[str], script: str = "") -> str:
    return "\n".join(["<!DOCTYPE html>", '<html lang="en"><head><meta charset="utf-8">',
                      f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>", *body,
                      f"<script>{script}</script>" if script else "", "</body></html>"]) + "\n"


def _page_name(camera_id: str) -> str:
    return f"cameras/{camera_id}.html"


def _links(version: str, reports: dict, prefix: str) -> str:
    got = reports.get(version, {})
    parts = [f'<a href="{_e(prefix + got[k])}">{k}</a>' for k in ("report", "certificate") if k in got]
    return " ".join(parts) or '<span class="small">none</span>'


def _row(c: CameraState, reports: dict) -> str:
    lt = c.latest
    ch = c.change or {}
    change = ("" if not ch else f"cannot compare: {_e(ch['error'])}" if "error" in ch else
              f"{ch['max_um']:.3g} um, p = {ch['p_value']:.2g}" + (' <span class="moved">MOVED</span>'
                                                                    if c.moved else ""))
    days = "" if c.days_left is None else (f'<span class="expired">expired {-c.days_left} d ago</span>'
                                           if c.expired else f"{c.days_left} d")
    sigma = "" if lt["sigma_f_mm"] is None else f" &plusmn; {1000 * lt['sigma_f_mm']:.2g} um"
    flags = {"moved": c.moved, "expired": c.expired, "failed": c.verdict == "FAIL"}
    data = " ".join(f'data-{k}="{"yes" if v else "no"}"' for k, v in flags.items())
    cells = [f'<a href="{_page_name(c.camera_id)}">{_e(c.camera_id)}</a>', _e(lt["session_id"]),
             _when(lt["acquired"] or lt["created"]), _e(lt["method"]), f"{lt['f_mm']:.6f} mm{sigma}",
             f'<span class="{_e(c.verdict)}">{_e(c.verdict)}</span>', _when(c.valid_until), days, change,
             _links(lt["version"], reports, "")]
    nums = {4, 7}
    return (f"<tr {data}>" + "".join(f'<td class="num">{x}</td>' if i in nums else f"<td>{x}</td>"
                                      for i, x in enumerate(cells)) + "</tr>")


def index_html(cams: list[CameraState], reports: dict, *, tolerance_um: float, alpha: float, built: str) -> str:
    """The fleet page (module docstring)."""
    n = {"moved": sum(c.moved for c in cams), "expired": sum(c.expired for c in cams),
         "failed": sum(c.verdict == "FAIL" for c in cams)}
    head = ["camera", "latest session", "acquired", "method", "f", "verdict", "valid until", "days left",
            "last change test", "latest"]
    body = [f"<h1>Fleet: {len(cams)} cameras</h1>",
            f'<p class="counts"><span id="n-moved">{n["moved"]}</span> moved, <span id="n-expired">'
            f'{n["expired"]}</span> expired, <span id="n-failed">{n["failed"]}</span> failed; showing '
            f'<span id="shown">{len(cams)}</span></p>',
            '<p class="filters">' + "".join(f'<label><input type="checkbox" value="{k}" id="only-{k}"> {k}</label>'
                                            for k in n) + "</p>",
            '<table id="fleet"><thead><tr>' + "".join(f"<th>{h}</th>" for h in head) + "</tr></thead><tbody>",
            *[_row(c, reports) for c in cams], "</tbody></table>",
            f'<p class="small">Change test at alpha {alpha:g}, tolerance {tolerance_um:g} um; verdict: the '
            f"certificate's acceptance criteria. Built {_e(built)} from the lake.</p>"]
    return _page("fieldcal fleet", body, _FILTER_JS)


def _days(rows) -> np.ndarray:
    """Acquisition times as Matplotlib date numbers (the plots' x axis)."""
    from matplotlib.dates import date2num

    return np.asarray(date2num([r["acquired"] or r["created"] for r in rows]), float)


def _plots(c: CameraState, assessed: dict, tolerance_um: float) -> list[str]:
    h = c.history
    x = _days(h)
    out = []
    for name, label in (("f_mm", "f"), ("xp_mm", "xp"), ("yp_mm", "yp")):
        y = 1000 * (np.asarray([r[name] for r in h], float) - h[0][name])
        s = 1000 * np.asarray([np.nan if r[f"sigma_{name}"] is None else r[f"sigma_{name}"] for r in h], float)
        out.append(series_plot(x, [(label, y, s)], title=f"{label}: change since the first [um]",
                               tolerance=tolerance_um))
    radial = [assessed.get(r["version"], {}).get("radial") for r in h]
    if any(radial):
        keep = [i for i, r in enumerate(radial) if r]
        series = []
        for k, frac in enumerate(status.RADII_FRACTIONS):
            y = np.asarray([radial[i]["dr_um"][k] for i in keep])
            series.append((f"r = {radial[keep[0]]['r_mm'][k]:.1f} mm ({frac:.0%})", y - y[0],
                           np.asarray([radial[i]["sigma_um"][k] for i in keep])))
        out.append(series_plot(x[keep], series, title="radial distortion: change since the first [um]",
                               tolerance=tolerance_um))
    return out


def camera_html(c: CameraState, assessed: dict, reports: dict, *, tolerance_um: float) -> str:
    """A camera's page (module docstring)."""
    head = ["version", "session", "acquired", "method", "f [mm]", "rmse [px]", "criteria (change aside)", "files"]
    rows = []
    for r in reversed(c.versions):
        a = assessed.get(r["version"], {})
        rows.append("<tr>" + "".join(f"<td>{x}</td>" for x in (
            _e(r["version"]), _e(r["session_id"]), _when(r["acquired"] or r["created"]), _e(r["method"]),
            f"{r['f_mm']:.6f}", "" if r["rmse_px"] is None else f"{r['rmse_px']:.3f}",
            _e(a.get("verdict", "")), _links(r["version"], reports, "../"))) + "</tr>")
    ch = c.change or {}
    body = ['<p><a href="../index.html">fleet</a></p>', f"<h1>{_e(c.camera_id)}</h1>",
            f"<p>Latest: {_e(c.latest['session_id'])} ({_when(c.latest['acquired'] or c.latest['created'])}), "
            f'verdict <span class="{_e(c.verdict)}">{_e(c.verdict)}</span>; certificate valid until '
            f"{_when(c.valid_until) or 'not stated'}.</p>",
            f"<p>Last change test: {_e(ch.get('verdict') or ch.get('error') or 'none (one calibration)')}</p>",
            '<div class="plots">', *_plots(c, assessed, tolerance_um), "</div>",
            f'<p class="small">Bands: 1 sigma of each calibration; dashed: +-{tolerance_um:g} um around the '
            "first (the tolerance).</p>",
            f"<h2>Versions ({len(c.versions)})</h2>", "<table><thead><tr>"
            + "".join(f"<th>{x}</th>" for x in head) + "</tr></thead><tbody>", *rows, "</tbody></table>"]
    return _page(f"{c.camera_id}: fieldcal", body)


def _report_files(lake) -> list[str]:
    """Lake-relative paths of every ``*.html`` under ``LAKE/reports`` (one listing of the tree)."""
    base = lake.storage.path("reports")
    if lake.is_local:
        return [os.path.relpath(os.path.join(d, f), lake.storage.path("")).replace(os.sep, "/")
                for d, _, files in os.walk(base) for f in files if f.endswith(".html")]
    try:
        found = lake.fs.find(base)
    except FileNotFoundError:
        return []
    root = lake.storage.path("")
    return [p[len(root):].lstrip("/") for p in found if p.endswith(".html")]


def _published(lake, out: Path, reports_url: str | None) -> dict:
    """``{version: {"report": href, "certificate": href}}`` of the files the runs wrote into
    ``LAKE/reports/<camera>/<session>/<version>/`` (hrefs relative to ``out`` for a local
    lake, else the lake's URL; under ``reports_url`` when given)."""
    found: dict = {}
    for rel in _report_files(lake):
        parts = rel.split("/")
        kind = parts[-1][:-len(".html")]
        if len(parts) != 5 or kind not in ("report", "certificate"):
            continue
        if reports_url:
            href = f"{reports_url.rstrip('/')}/{rel}"
        elif lake.is_local:
            href = os.path.relpath(lake.uri(rel), out).replace(os.sep, "/")
        else:
            href = lake.uri(rel)
        found.setdefault(parts[3], {})[kind] = href
    return found


def write_dashboard(lake, out_dir, *, config_path=None, today: dt.date | None = None,
                    tolerance_um: float = DEFAULT_TOLERANCE_UM, alpha: float = DEFAULT_ALPHA,
                    reports_url: str | None = None) -> dict:
    """Write the dashboard (module docstring) into ``out_dir``.

    Returns ``index`` (its path), ``cameras`` (how many), ``moved``, ``expired``, ``failed``.
    """
    config = load_config(config_path)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", str(out))
    cams = fleet_state(lake, config=config, today=today, tolerance_um=tolerance_um, alpha=alpha)
    shown = [r["version"] for c in cams for r in c.history]
    assessed = status.assessments(lake, shown, config, compute=False, brief=True)
    (out / "cameras").mkdir(parents=True, exist_ok=True)
    reports = _published(lake, out, reports_url)
    built = dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%MZ")
    for c in cams:
        (out / _page_name(c.camera_id)).write_text(camera_html(c, assessed, reports, tolerance_um=tolerance_um),
                                                   encoding="utf-8")
    index = out / "index.html"
    index.write_text(index_html(cams, reports, tolerance_um=tolerance_um, alpha=alpha, built=built),
                     encoding="utf-8")
    return {"index": index, "cameras": len(cams), "moved": sum(c.moved for c in cams),
            "expired": sum(c.expired for c in cams), "failed": sum(c.verdict == "FAIL" for c in cams)}
