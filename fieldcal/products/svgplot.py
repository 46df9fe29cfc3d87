"""Small inline SVG plots for the dashboard: series over time with sigma bands and a tolerance.

The dashboard draws four plots for each of hundreds of cameras; drawing them with
Matplotlib took 0.1-0.3 s each (a figure per plot), here a plot is a few string
operations over NumPy arrays (~1 ms). Matplotlib still picks the tick positions
(:class:`matplotlib.ticker.MaxNLocator`), so the axes read as in the reports.

:func:`series_plot` returns one ``<svg>`` element: each series as a line (markers up to
:data:`MARKERS_UP_TO` points) and a band of +-1 sigma around it; ``tolerance`` draws dashed
lines at +-tolerance around zero (the series are changes since the first calibration).
"""

from __future__ import annotations

import functools
import html

import numpy as np
from matplotlib.dates import AutoDateLocator, num2date
from matplotlib.ticker import MaxNLocator

__all__ = ["series_plot", "COLOURS"]

COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")
W, H = 420, 236
LEFT, RIGHT, TOP, BOTTOM = 56, 26, 24, 46
MARKERS_UP_TO = 60
"""A series of more points is drawn as a line only."""


def _ticks(lo: float, hi: float, n: int = 5) -> np.ndarray:
    if not np.isfinite(lo) or not np.isfinite(hi):
        return np.zeros(0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    t = MaxNLocator(n).tick_values(lo, hi)
    return t[(t >= lo - 1e-9 * abs(hi - lo)) & (t <= hi + 1e-9 * abs(hi - lo))]


def _range(values: list[np.ndarray]) -> tuple[float, float]:
    v = np.concatenate([np.ravel(a) for a in values]) if values else np.zeros(0)
    v = v[np.isfinite(v)]
    if not v.size:
        return -1.0, 1.0
    lo, hi = float(v.min()), float(v.max())
    pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo), 1.0) * 0.5
    return lo - pad, hi + pad


def _points(xs: np.ndarray, ys: np.ndarray) -> str:
    return " ".join(map("{:.1f},{:.1f}".format, xs.tolist(), ys.tolist()))


@functools.lru_cache(maxsize=256)
def _date_ticks(x_lo: float, x_hi: float) -> tuple:
    """Date ticks of a time axis (one camera's plots share them: computed once)."""
    ticks = AutoDateLocator(maxticks=5).tick_values(num2date(x_lo), num2date(x_hi))
    return tuple((float(t), f"{num2date(t):%Y-%m-%d}") for t in ticks if x_lo <= t <= x_hi)


def series_plot(x, series, *, title: str, tolerance: float | None = None) -> str:
    """One SVG plot (module docstring).

    Parameters
    ----------
    x : (n,) array_like
        Positions on the time axis: Matplotlib date numbers (days, :func:`matplotlib.dates.date2num`).
    series : list of (label, y (n,), sigma (n,))
        Values and their 1-sigma (NaN: no band at that point).
    title : str
    tolerance : float, optional
        Dashed lines at +-tolerance.
    """
    x = np.asarray(x, float)
    ys = [(label, np.asarray(y, float), np.asarray(s, float)) for label, y, s in series]
    spans = [y + np.nan_to_num(s) for _, y, s in ys] + [y - np.nan_to_num(s) for _, y, s in ys]
    lo, hi = _range(spans + ([np.array([-tolerance, tolerance])] if tolerance else []))
    x_lo, x_hi = (float(x.min()), float(x.max())) if x.size else (0.0, 1.0)
    if x_hi - x_lo < 1.0:
        x_lo, x_hi = x_lo - 15.0, x_hi + 15.0          # one calibration: a month around it
    pad = 0.04 * (x_hi - x_lo)
    x_lo, x_hi = x_lo - pad, x_hi + pad

    def px(v):
        return LEFT + (np.asarray(v) - x_lo) / (x_hi - x_lo) * (W - LEFT - RIGHT)

    def py(v):
        return TOP + (hi - np.asarray(v)) / (hi - lo) * (H - TOP - BOTTOM)

    e = html.escape
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" '
             f'role="img" aria-label="{e(title)}"><title>{e(title)}</title>',
             f'<text x="{LEFT}" y="15" font-size="12">{e(title)}</text>',
             f'<rect x="{LEFT}" y="{TOP}" width="{W - LEFT - RIGHT}" height="{H - TOP - BOTTOM}" fill="none" '
             'stroke="#999"/>']
    for t in _ticks(lo, hi):
        parts.append(f'<line x1="{LEFT}" x2="{W - RIGHT}" y1="{py(t):.1f}" y2="{py(t):.1f}" stroke="#eee"/>'
                     f'<text x="{LEFT - 4}" y="{py(t) + 4:.1f}" font-size="10" text-anchor="end">{t:g}</text>')
    for t, label in _date_ticks(x_lo, x_hi):
        parts.append(f'<text x="{px(t):.1f}" y="{H - BOTTOM + 14}" font-size="10" text-anchor="middle">'
                     f"{label}</text>")
    if tolerance:
        for t in (-tolerance, tolerance):
            parts.append(f'<line x1="{LEFT}" x2="{W - RIGHT}" y1="{py(t):.1f}" y2="{py(t):.1f}" '
                         'stroke="#555" stroke-dasharray="4 3"/>')
    for k, (label, y, s) in enumerate(ys):
        c = COLOURS[k % len(COLOURS)]
        ok = np.isfinite(y) & np.isfinite(s)
        if ok.sum() >= 1:
            xb = np.concatenate([px(x[ok]), px(x[ok])[::-1]])
            yb = np.concatenate([py(y[ok] + s[ok]), py((y - s)[ok])[::-1]])
            parts.append(f'<polygon points="{_points(xb, yb)}" fill="{c}" fill-opacity="0.18" stroke="none"/>')
        good = np.isfinite(y)
        parts.append(f'<polyline points="{_points(px(x[good]), py(y[good]))}" fill="none" stroke="{c}"/>')
        if good.sum() <= MARKERS_UP_TO:
            parts += [f'<circle cx="{a:.1f}" cy="{b:.1f}" r="2.2" fill="{c}"/>'
                      for a, b in zip(px(x[good]), py(y[good]), strict=True)]
        parts.append(f'<text x="{LEFT + (k % 2) * 180}" y="{H - 18 + 12 * (k // 2)}" font-size="10" '
                     f'fill="{c}">&#9632; {e(label)}</text>')
    parts.append("</svg>")
    return "".join(parts)
