"""Figures of a calibration, a comparison, a camera's history and the fleet (matplotlib, Agg).

Every function returns a :class:`matplotlib.figure.Figure` made without pyplot (no global
state, safe in threads and servers); :func:`to_png` renders one to PNG bytes. Pixel
coordinates follow docs/conventions.md section 1 (u right, v down: sensor plots have v increasing
downwards); image-plane quantities are in mm or um as their labels say.

The numbers drawn come from :mod:`fieldcal.analysis.uncertainty` (propagated uncertainty and
distortion curves), :mod:`fieldcal.analysis.compare` (comparison maps) and the lake's tables; this
module only draws.
"""

from __future__ import annotations

import io

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from fieldcal.analysis.uncertainty import Calibration, decentering_curve, radial_curve, uncertainty_map
from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor

__all__ = ["to_png", "to_svg", "certificate_distortion", "residual_vectors", "residuals_per_image", "stations_3d",
           "distortion_curves", "uncertainty_figure", "correlation_figure",
           "goniometer_axes", "compare_figure", "history_plot", "fleet_plot",
           "residual_histogram", "distortion_vectors", "PARAM_UNITS"]

PARAM_UNITS = {"f_mm": "mm", "xp_mm": "mm", "yp_mm": "mm", "k0": "1", "k1": "mm^-2",
               "k2": "mm^-4", "k3": "mm^-6", "p1": "mm^-1", "p2": "mm^-1", "a1": "1", "a2": "1",
               "b1": "1", "b2": "1"}
"""The unit of each camera parameter (docs/conventions.md section 2)."""

DPI = 110
_AXIS_COLORS = {"x": "tab:blue", "y": "tab:orange"}


def to_png(fig: Figure, *, dpi: int = DPI) -> bytes:
    """PNG bytes of a figure."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return buf.getvalue()


def to_svg(fig: Figure) -> str:
    """The figure as an ``<svg>`` element to place inside an HTML page: text kept as text (a
    PDF printed from the page is searchable), no XML prolog, DOCTYPE or namespace declarations
    (an HTML parser does not need them), no date, so the same figure gives the same text."""
    import re

    from matplotlib import rc_context

    buf = io.StringIO()
    with rc_context({"svg.fonttype": "none", "svg.hashsalt": "fieldcal"}):
        fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Date": None, "Creator": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    text = re.sub(r'\s+xmlns(:\w+)?="[^"]*"', "", text, count=0)
    text = re.sub(r"<metadata>.*?</metadata>", "", text, flags=re.S)
    return re.sub(r'<svg ([^>]*?)width="[^"]*" height="[^"]*"', r'<svg \1width="100%"', text, count=1)


def certificate_distortion(theta_deg, diagonals_um, mean_um, U_um, relative_to_f_um, *, labels,
                           focal_label: str, reach_deg: float | None = None) -> Figure:
    """The certificate's distortion plot: radial distortion [µm] against the field angle [°].

    ``diagonals_um`` (4, n) along the four semi-diagonals and their mean (n,) relative to the
    focal length ``focal_label`` names, the band ``mean +- U_um`` (the expanded uncertainty,
    k = 2), and the mean relative to the model's f (dashed); ``reach_deg`` marks how far the
    data reach (beyond: the model's extrapolation)."""
    fig = Figure(figsize=(7.0, 2.7), layout="constrained")
    ax = fig.add_subplot(1, 1, 1)
    th = np.asarray(theta_deg, float)
    ax.fill_between(th, mean_um - U_um, mean_um + U_um, color="tab:blue", alpha=0.25, lw=0,
                    label="mean ± U (k = 2)")
    for d, lab, ls in zip(diagonals_um, labels, (":", "-.", (0, (5, 2)), (0, (1, 2))), strict=True):
        ax.plot(th, d, lw=0.8, ls=ls, color="0.35", label=lab)
    ax.plot(th, mean_um, color="tab:blue", lw=1.8, label=f"mean, relative to {focal_label}")
    ax.plot(th, relative_to_f_um, color="tab:red", lw=1.0, ls="--", label="mean, relative to f")
    ax.axhline(0.0, color="0.5", lw=0.6)
    if reach_deg is not None and 0 < reach_deg < th.max():
        ax.axvline(reach_deg, color="0.3", ls="--", lw=0.8)
        ax.text(reach_deg, 0.04, "the data reach ", va="bottom", ha="right", fontsize=7, color="0.3",
                transform=ax.get_xaxis_transform())
    ax.set_xlabel("field angle [°]")
    ax.set_ylabel("radial distortion [µm]")
    ax.set_xlim(0, th.max())
    ax.legend(fontsize=6.5, loc="best", ncol=2)
    return fig


def _sensor_axes(ax, sensor: Sensor):
    ax.set_xlim(-0.5, sensor.width_px - 0.5)
    ax.set_ylim(sensor.height_px - 0.5, -0.5)          # v down
    ax.set_aspect("equal")
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")


def _nice(x: float) -> float:
    """A round number (1, 2 or 5 times a power of ten) close to ``x`` > 0."""
    if not (x > 0 and np.isfinite(x)):
        return 1.0
    e = np.floor(np.log10(x))
    m = x / 10**e
    return float((1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10**e)


# --------------------------------------------------------------------------------------
# field method: residuals, stations
# --------------------------------------------------------------------------------------
def _cell_means(uv, duv, sensor: Sensor, cells):
    """Mean residual (m, 2), cell centres (m, 2) and counts (m,) over ``cells`` = (nx, ny)."""
    nx, ny = cells
    cw, ch = sensor.width_px / nx, sensor.height_px / ny
    iu = np.clip((uv[:, 0] + 0.5) // cw, 0, nx - 1).astype(int)
    iv = np.clip((uv[:, 1] + 0.5) // ch, 0, ny - 1).astype(int)
    cell = iv * nx + iu
    cnt = np.bincount(cell, minlength=nx * ny)
    mean = np.stack([np.bincount(cell, duv[:, c], nx * ny) for c in (0, 1)], -1)
    mean /= np.maximum(cnt, 1)[:, None]
    centre = np.stack([(np.arange(nx * ny) % nx + 0.5) * cw - 0.5,
                       (np.arange(nx * ny) // nx + 0.5) * ch - 0.5], -1)
    return mean, centre, cnt


def _vectors(ax, xy, vec, length_px: float, color, width):
    """Quiver of ``vec`` [px] at ``xy`` magnified so the 95th percentile is ``length_px`` long."""
    norm = np.hypot(*vec.T) if len(vec) else np.zeros(1)
    typical = float(np.percentile(norm, 95)) if len(vec) else 0.0
    mag = _nice(length_px / max(typical, 1e-9))
    key = _nice(typical) if typical > 0 else 1.0
    q = ax.quiver(xy[:, 0], xy[:, 1], vec[:, 0], vec[:, 1], angles="xy", scale_units="xy",
                  scale=1.0 / mag, color=color, width=width)
    ax.quiverkey(q, 0.98, 1.025, key, f"{key:g} px (magnified x{mag:g})", labelpos="W",
                 coordinates="axes", fontproperties={"size": 8})
    return mag


def residual_vectors(uv_px, duv_px, sensor: Sensor, *, used=None, cells: tuple[int, int] = (16, 12),
                     max_points: int = 2500, seed: int = 0) -> Figure:
    """Residual vectors over the sensor, magnified, with the scale shown.

    Left: individual residuals of the used points (a seeded random subset of at most
    ``max_points``), rejected points as red crosses. Right: the mean residual in each of
    ``cells`` (nx, ny) cells with at least 3 points, at its own magnification: systematic
    errors of the model show there. Each panel's key gives its scale.

    Parameters
    ----------
    uv_px : (n, 2) array_like
        Measured pixels.
    duv_px : (n, 2) array_like
        Residuals, measured minus model [px].
    used : (n,) bool array_like, optional
    """
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    duv = np.asarray(duv_px, float).reshape(-1, 2)
    used = np.ones(len(uv), bool) if used is None else np.asarray(used, bool)
    ok = used & np.isfinite(duv).all(axis=1) & np.isfinite(uv).all(axis=1)
    fig = Figure(figsize=(13.0, 5.6), layout="constrained")
    cw = min(sensor.width_px / cells[0], sensor.height_px / cells[1])
    ax = fig.add_subplot(1, 2, 1)
    _sensor_axes(ax, sensor)
    k = np.flatnonzero(ok)
    if k.size > max_points:
        k = np.sort(np.random.default_rng(seed).choice(k, max_points, replace=False))
    rms = float(np.sqrt(np.mean(np.sum(duv[ok] ** 2, axis=1)))) if ok.any() else float("nan")
    _vectors(ax, uv[k], duv[k], 0.6 * cw, "0.35", 0.0015)
    bad = ~used & np.isfinite(uv).all(axis=1)
    if bad.any():
        ax.plot(uv[bad, 0], uv[bad, 1], "x", color="tab:red", ms=6, mew=1.5,
                label=f"rejected ({int(bad.sum())})")
        ax.legend(loc="lower left", fontsize=8, framealpha=0.9)
    ax.set_title(f"Residuals: {k.size} of {int(ok.sum())} shown, RMS {rms:.3g} px", fontsize=10,
                 loc="left", pad=16)
    ax = fig.add_subplot(1, 2, 2)
    _sensor_axes(ax, sensor)
    mean, centre, cnt = _cell_means(uv[ok], duv[ok], sensor, cells)
    has = cnt >= 3
    if has.any():
        _vectors(ax, centre[has], mean[has], 0.8 * cw, "tab:blue", 0.004)
        largest = float(np.hypot(*mean[has].T).max())
    else:
        largest = float("nan")
    ax.set_title(f"Mean per cell ({cells[0]} x {cells[1]} cells): largest {largest:.3g} px",
                 fontsize=10, loc="left", pad=16)
    return fig


def residuals_per_image(names, mean_abs_u_px, mean_abs_v_px, rmse_px, stations=None, *,
                        left_out=()) -> Figure:
    """Mean absolute residuals in u and v and the RMS per image (the field paper's Fig. 5).

    Parameters
    ----------
    names : sequence of str
        Image names (in document order).
    mean_abs_u_px, mean_abs_v_px, rmse_px : (n,) array_like
        Per image [px]; NaN for an image without used points.
    stations : sequence of str, optional
        Station of each image (shaded groups).
    left_out : sequence of str
        Names of images left out (listed under the plot).
    """
    n = len(names)
    x = np.arange(1, n + 1)
    fig = Figure(figsize=(10.0, 4.2))
    ax = fig.add_subplot()
    if stations is not None and n and len(set(stations)) > 1:
        st = [str(s or "") for s in stations]
        order = list(dict.fromkeys(st))
        start = 0
        for i in range(1, n + 1):           # runs of consecutive images of one station
            if i == n or st[i] != st[start]:
                if order.index(st[start]) % 2 == 0:
                    ax.axvspan(start + 0.5, i + 0.5, color="0.93", zorder=0)
                ax.text((start + i + 1) / 2, 1.0, st[start], transform=ax.get_xaxis_transform(),
                        ha="center", va="bottom", fontsize=8)
                start = i
    ax.plot(x, mean_abs_u_px, "o-", ms=3, lw=1, label="mean |du|")
    ax.plot(x, mean_abs_v_px, "s-", ms=3, lw=1, label="mean |dv|")
    ax.plot(x, rmse_px, "^-", ms=3, lw=1, color="0.3", label="RMS |(du, dv)|")
    ax.set_xlim(0.5, n + 0.5)
    ax.set_ylim(bottom=0)
    ax.set_xlabel("image (document order)")
    ax.set_ylabel("residual [px]")
    ax.legend(fontsize=8, ncol=3, loc="lower right")
    title = "Mean residuals per image"
    if left_out:
        title += f" ({len(left_out)} image(s) left out, see the list)"
    ax.set_title(title, fontsize=10, loc="left", pad=14)
    return fig


def stations_3d(center_m, R_world_to_camera, *, stations=None, targets_xyz_m=None,
                axis_length_m: float | None = None) -> Figure:
    """Camera stations and the target field in 3D (the field paper's Fig. 6).

    Parameters
    ----------
    center_m : (n, 3) array_like
        Camera centres [m].
    R_world_to_camera : (n, 3, 3) array_like
        Their rotations; the viewing direction drawn is the camera's -z axis.
    stations : sequence of str, optional
        Colours the cameras by station.
    targets_xyz_m : (m, 3) array_like, optional
        Adjusted target coordinates [m].
    """
    C = np.asarray(center_m, float).reshape(-1, 3)
    R = np.asarray(R_world_to_camera, float).reshape(-1, 3, 3)
    fig = Figure(figsize=(10.0, 7.5), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    pts = C
    if targets_xyz_m is not None and len(targets_xyz_m):
        T = np.asarray(targets_xyz_m, float)
        T = T[np.isfinite(T).all(axis=1)]            # unsurveyed targets no image placed: NaN
        ax.scatter(T[:, 0], T[:, 1], T[:, 2], s=2, c="0.35", depthshade=False,
                   label=f"targets ({len(T)})")
        pts = np.concatenate([C, T])
    extent = float(np.ptp(pts, axis=0).max()) if len(pts) else 1.0
    L = axis_length_m or 0.12 * extent
    look = -R[:, 2, :]                           # camera -z in the world
    labels = list(stations) if stations is not None else [""] * len(C)
    groups = list(dict.fromkeys(labels))
    colors = [f"C{i % 10}" for i in range(len(groups))]
    for g, col in zip(groups, colors, strict=True):
        k = [i for i, s in enumerate(labels) if s == g]
        ax.scatter(C[k, 0], C[k, 1], C[k, 2], s=18, color=col, depthshade=False,
                   label=f"station {g}" if g else "cameras")
        seg = np.stack([C[k], C[k] + L * look[k]], axis=1)
        for s in seg:
            ax.plot(s[:, 0], s[:, 1], s[:, 2], color=col, lw=0.8)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ax.set_box_aspect(np.maximum(hi - lo, 1e-3 * extent))
    ax.set_xlabel("X [m]")
    ax.set_ylabel("Y [m]")
    ax.set_zlabel("Z [m]")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.set_title(f"Camera stations ({len(C)} images) and the target field; lines: viewing "
                 "directions", fontsize=10, loc="left")
    return fig


# --------------------------------------------------------------------------------------
# the model: distortion, uncertainty, correlation
# --------------------------------------------------------------------------------------
def distortion_curves(calibration: Calibration, *, n: int = 200, r_data_mm: float | None = None
                      ) -> Figure:
    """Radial and decentering distortion curves with their 1- and 3-sigma bands.

    Radial: Brown's correction ``dr(r) = r (k0 + k1 r^2 + k2 r^4 + k3 r^6)`` (ideal minus
    measured, positive outwards); decentering: the profile ``P(r) = sqrt(p1^2 + p2^2) r^2``;
    both from the principal point to the farthest sensor corner, in pixels. ``r_data_mm``,
    the largest radius with measurements, is marked: beyond it the curves are extrapolated.
    """
    cam = calibration.camera
    s = cam.sensor
    corners = s.pixel_to_mm(np.array([[0, 0], [s.width_px - 1, 0], [0, s.height_px - 1],
                                      [s.width_px - 1, s.height_px - 1]], float))
    r_max = float(np.hypot(*(corners - cam.params[1:3]).T).max())
    r = np.linspace(0.0, r_max, n)
    d = s.pixel_mm
    fig = Figure(figsize=(11.0, 4.2), layout="constrained")
    for j, (fn, name, label) in enumerate(((radial_curve, "radial correction dr", "Radial correction dr"),
                                           (decentering_curve, "decentering profile P",
                                            "Decentering profile P"))):
        ax = fig.add_subplot(1, 2, j + 1)
        val, sig = fn(calibration, r)
        val, sig = val / d, sig / d
        ax.fill_between(r, val - 3 * sig, val + 3 * sig, color="tab:blue", alpha=0.15,
                        lw=0, label="3 sigma")
        ax.fill_between(r, val - sig, val + sig, color="tab:blue", alpha=0.35, lw=0,
                        label="1 sigma")
        ax.plot(r, val, color="tab:blue", lw=1.5, label=name)
        ax.axhline(0.0, color="0.5", lw=0.6)
        if r_data_mm is not None and 0 < r_data_mm < r_max:
            ax.axvline(r_data_mm, color="0.3", ls="--", lw=0.8,
                       label=f"measurements reach {r_data_mm:.1f} mm")
        ax.set_xlabel("radius from the principal point [mm]")
        ax.set_ylabel(f"{name} [px]")
        ax.set_xlim(0, r_max)
        ax.legend(fontsize=8, loc="best")
        ax.set_title(f"{label} (3 sigma at most {3 * sig.max():.3g} px)", fontsize=10, loc="left")
        sec = ax.secondary_yaxis("right", functions=(lambda p: p * s.pixel_size_um,
                                                     lambda m: m / s.pixel_size_um))
        sec.set_ylabel("[µm]")
    return fig


def uncertainty_figure(calibration: Calibration, *, grid: tuple[int, int] = (41, 31),
                       points_uv_px=None, max_points: int = 3000, seed: int = 0) -> Figure:
    """Projection-uncertainty maps: 1-sigma of where a ray lands [px] over the sensor.

    Left: propagated from the interior covariance as it is; right: without the part a
    common rotation of the camera frame absorbs (the calibration's shape uncertainty,
    :func:`fieldcal.analysis.uncertainty.uncertainty_map`). The measured points (a seeded subset)
    are dotted on both, so thin data show where the uncertainty grows. The colour scale is
    logarithmic when the map spans more than a factor of 20.
    """
    from matplotlib.colors import LogNorm, Normalize

    s = calibration.sensor
    fig = Figure(figsize=(13.0, 5.2), layout="constrained")
    for j, derot in enumerate((False, True)):
        ax = fig.add_subplot(1, 2, j + 1)
        gu, gv, sig = uncertainty_map(calibration, grid, remove_rotation=derot)
        lo, hi = float(sig.min()), float(sig.max())
        log = lo > 0 and hi / float(np.percentile(sig, 5)) > 20
        norm = LogNorm(lo, hi) if log else Normalize(lo, hi if hi > lo else lo + 1e-12)
        du, dv = (gu[1] - gu[0]) / 2, (gv[1] - gv[0]) / 2
        im = ax.imshow(sig, extent=(gu[0] - du, gu[-1] + du, gv[-1] + dv, gv[0] - dv),
                       origin="upper", cmap="viridis", norm=norm, interpolation="bilinear")
        if hi > lo:
            levels = np.geomspace(lo, hi, 7)[1:-1] if log else np.linspace(lo, hi, 7)[1:-1]
            cs = ax.contour(gu, gv, sig, levels=levels, colors="white", linewidths=0.6)
            ax.clabel(cs, fmt="%.2g", fontsize=7)
        if points_uv_px is not None and len(points_uv_px):
            p = np.asarray(points_uv_px, float)
            if len(p) > max_points:
                p = p[np.random.default_rng(seed).choice(len(p), max_points, replace=False)]
            ax.plot(p[:, 0], p[:, 1], ".", ms=1.5, color="white", alpha=0.5)
        _sensor_axes(ax, s)
        fig.colorbar(im, ax=ax, shrink=0.9).set_label("1 sigma [px]" + (" (log scale)" if log else ""))
        ax.set_title(("As propagated" if not derot else "Without a common camera rotation")
                     + f": {lo:.3g} to {hi:.3g} px", fontsize=10, loc="left")
    fig.suptitle("Projection uncertainty: semi-major axis of the 1-sigma ellipse of where a ray "
                 "lands; dots: measurements", fontsize=10)
    return fig


def correlation_figure(calibration: Calibration, *, threshold: float = 0.95) -> Figure:
    """The correlation matrix of the estimated parameters; |r| above ``threshold`` outlined."""
    names = list(calibration.names)
    corr = calibration.correlation()
    p = len(names)
    fig = Figure(figsize=(1.6 + 0.55 * max(p, 4), 0.8 + 0.5 * max(p, 4)), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    for i in range(p):
        for j in range(p):
            ax.text(j, i, f"{corr[i, j]:.2f}", ha="center", va="center", fontsize=7,
                    color="white" if abs(corr[i, j]) > 0.6 else "black")
            if i != j and abs(corr[i, j]) > threshold:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, ec="black", lw=2))
    ax.set_xticks(range(p), names, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(p), names, fontsize=8)
    fig.colorbar(im, ax=ax, shrink=0.8).set_label("correlation")
    ax.set_title(f"Correlations (|r| > {threshold:g} outlined; source: "
                 f"{calibration.covariance_source})", fontsize=10, loc="left")
    return fig


# --------------------------------------------------------------------------------------
# goniometer method
# --------------------------------------------------------------------------------------
def goniometer_axes(table, *, sigma_fit_px: float | None = None, pixel_size_um: float | None = None
                    ) -> Figure:
    """Distortion along each swept axis before and after the fit (the lab paper's Figs. 4-7).

    Parameters
    ----------
    table : mapping of str to array_like
        Columns ``axis`` ('x' / 'y'), ``position_px`` (along the axis from the sensor
        centre), ``angle_deg``, ``before_px`` (distortion after the interior orientation,
        before the distortion fit), ``fit_px`` and ``after_px`` (the fit's residual).
    sigma_fit_px : float, optional
        Eq. 10's sigma, drawn as a band on the residuals.
    """
    axis = np.asarray(table["axis"])
    fig = Figure(figsize=(11.0, 7.0))
    for row, a in enumerate(("x", "y")):
        k = axis == a
        pos = np.asarray(table["position_px"], float)[k]
        order = np.argsort(pos)
        pos = pos[order]
        before = np.asarray(table["before_px"], float)[k][order]
        fit = np.asarray(table["fit_px"], float)[k][order]
        after = np.asarray(table["after_px"], float)[k][order]
        ax = fig.add_subplot(2, 2, 2 * row + 1)
        ax.plot(pos, before, "o", ms=3.5, color=_AXIS_COLORS[a], label="distortion")
        ax.plot(pos, fit, "-", lw=1, color="0.25", label="fitted model")
        ax.axhline(0, color="0.6", lw=0.6)
        ax.set_xlabel(f"position along {a} from the sensor centre [px]")
        ax.set_ylabel("distortion [px]")
        ax.set_title(f"{a} sweep, before the fit: max |D| {np.abs(before).max() if before.size else 0:.3g} px",
                     fontsize=10, loc="left")
        ax.legend(fontsize=8)
        ax2 = fig.add_subplot(2, 2, 2 * row + 2)
        if sigma_fit_px is not None and np.isfinite(sigma_fit_px):
            ax2.axhspan(-sigma_fit_px, sigma_fit_px, color="0.85", label="±σ_fit (eq. 10)")
        ax2.plot(pos, after, "o", ms=3.5, color=_AXIS_COLORS[a], label="residual")
        ax2.axhline(0, color="0.6", lw=0.6)
        ax2.set_xlabel(f"position along {a} from the sensor centre [px]")
        ax2.set_ylabel("residual [px]")
        rms = float(np.sqrt(np.mean(after**2))) if after.size else float("nan")
        ax2.set_title(f"{a} sweep, after the fit: RMS {rms:.3g} px", fontsize=10, loc="left")
        ax2.legend(fontsize=8)
    fig.subplots_adjust(hspace=0.45, wspace=0.3)
    return fig


# --------------------------------------------------------------------------------------
# comparison, history, fleet
# --------------------------------------------------------------------------------------
def compare_figure(comparison, sensor: Sensor) -> Figure:
    """The difference map of two calibrations beside what their uncertainties explain.

    Left: ``|d|`` where the same ray lands in both [px] with the vectors ``d`` (magnified);
    middle: the 1-sigma that the two uncertainties explain; right: their ratio. The title
    gives the test and the verdict (:class:`fieldcal.analysis.compare.Comparison`).
    """
    import textwrap

    c = comparison
    nx, ny = c.grid
    u = c.uv_px[:nx, 0]
    v = c.uv_px[::nx, 1]
    norm = c.norm_px.reshape(ny, nx)
    sig = c.sigma_px.reshape(ny, nx)
    fig = Figure(figsize=(15.0, 4.9), layout="constrained")
    vmax = float(max(norm.max(), sig.max(), 1e-12))
    du, dv = (u[1] - u[0]) / 2, (v[1] - v[0]) / 2
    ext = (u[0] - du, u[-1] + du, v[-1] + dv, v[0] - dv)
    ax = fig.add_subplot(1, 3, 1)
    im = ax.imshow(norm, extent=ext, origin="upper", vmin=0, vmax=vmax, cmap="magma")
    step = max(1, nx // 12)
    sel = np.zeros((ny, nx), bool)
    sel[step // 2::step, step // 2::step] = True
    sel = sel.ravel()
    _vectors(ax, c.uv_px[sel], c.diff_px[sel], 0.9 * step * (sensor.width_px / nx), "cyan", 0.005)
    _sensor_axes(ax, sensor)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label("|difference| [px]")
    ax.set_title(f"Same ray, difference over the sensor: max {c.sensor_max_px:.3g} px "
                 f"({c.sensor_max_px * c.pixel_size_um:.3g} µm)", fontsize=9,
                 loc="left", pad=16)
    ax = fig.add_subplot(1, 3, 2)
    im = ax.imshow(sig, extent=ext, origin="upper", vmin=0, vmax=vmax, cmap="magma")
    _sensor_axes(ax, sensor)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label("1 sigma [px]")
    ax.set_title(f"Explained by both uncertainties: up to {sig.max():.3g} px", fontsize=9,
                 loc="left", pad=16)
    ax = fig.add_subplot(1, 3, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(sig > 0, norm / sig, np.nan)
    top = max(6.0, float(np.nanmax(ratio)) if np.isfinite(ratio).any() else 6.0)
    im = ax.imshow(ratio, extent=ext, origin="upper", cmap="coolwarm", vmin=0, vmax=top)
    _sensor_axes(ax, sensor)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label("|difference| / sigma")
    ax.set_title(f"map test: chi2 = {c.chi2:.3g} with {c.dof} dof, p = {c.map_p_value:.2g}", fontsize=9,
                 loc="left", pad=16)
    head = (f"B {c.version_b} ({c.method_b}) vs A {c.version_a} ({c.method_a}): {c.verdict}")
    fig.suptitle("\n".join(textwrap.wrap(head, 150)), fontsize=9)
    return fig


def history_plot(history, parameters=("f_mm", "xp_mm", "yp_mm"), *, tolerance=None,
                 reference: int = 0, title: str | None = None) -> Figure:
    """Parameters of one camera over time with their 1-sigma error bars and a tolerance band.

    Parameters
    ----------
    history : pyarrow.Table or mapping of columns
        :func:`fieldcal.lake.history.camera_history`'s table (``acquired`` or ``created``,
        ``method``, each parameter and ``sigma_<parameter>``).
    parameters : sequence of str
        One panel each.
    tolerance : mapping of str to float, optional
        Half-width of the tolerance band per parameter (its unit), drawn around the
        ``reference`` row's value (default the first calibration).
    """
    cols = history.to_pydict() if hasattr(history, "to_pydict") else dict(history)
    n = len(cols.get("version", []))
    if n == 0:
        raise InputError("no calibrations to plot", "history --plot")
    t = [a if a is not None else c for a, c in zip(cols.get("acquired", [None] * n),
                                                    cols.get("created", [None] * n), strict=True)]
    methods = cols.get("method", ["field"] * n)
    fig = Figure(figsize=(9.5, 2.6 * len(parameters) + 0.6))
    axes = [fig.add_subplot(len(parameters), 1, i + 1) for i in range(len(parameters))]
    for ax, name in zip(axes, parameters, strict=True):
        if name not in cols:
            raise InputError(f"the history has no column {name!r}", "history --plot")
        y = np.array([np.nan if v is None else v for v in cols[name]], float)
        s = np.array([np.nan if v is None else v for v in cols.get("sigma_" + name, [None] * n)], float)
        for m, marker in (("field", "o"), ("goniometer", "s")):
            k = [i for i in range(n) if methods[i] == m]
            if k:
                ax.errorbar([t[i] for i in k], y[k], yerr=np.nan_to_num(s[k]), fmt=marker, ms=5,
                            capsize=3, label=f"{m} (±1 σ)")
        ax.plot(t, y, "-", color="0.6", lw=0.8, zorder=0)
        tol = (tolerance or {}).get(name)
        if tol is not None and np.isfinite(y[reference]):
            ax.axhspan(y[reference] - tol, y[reference] + tol, color="tab:green", alpha=0.12,
                       label=f"tolerance ±{tol:.3g} {PARAM_UNITS.get(name, '')}".rstrip())
            ax.axhline(y[reference], color="tab:green", lw=0.8)
        ax.set_ylabel(f"{name} [{PARAM_UNITS[name]}]" if name in PARAM_UNITS else name)
        ax.ticklabel_format(axis="y", useOffset=False, style="sci", scilimits=(-3, 4))
        ax.legend(fontsize=7, loc="best")
    axes[-1].set_xlabel("acquired")
    fig.autofmt_xdate()
    axes[0].set_title(title or "History", fontsize=10, loc="left")
    return fig


def fleet_plot(summary, *, tolerance_um: float) -> Figure:
    """Largest change of each camera's latest calibration against its previous one.

    ``summary`` is :func:`fieldcal.products.report.fleet_summary`'s table (``camera_id``,
    ``max_change_um``, ``significant``, ``flagged``).
    """
    cols = summary.to_pydict() if hasattr(summary, "to_pydict") else dict(summary)
    cams = list(cols["camera_id"])
    val = np.array([np.nan if v is None else v for v in cols["max_change_um"]], float)
    sig = [bool(v) for v in cols["significant"]]
    flag = [bool(v) for v in cols["flagged"]]
    fig = Figure(figsize=(11.0, 1.4 + 0.35 * max(len(cams), 2)), layout="constrained")
    ax = fig.add_subplot()
    y = np.arange(len(cams))
    colors = ["tab:red" if f else ("tab:orange" if s else "tab:gray") for f, s in zip(flag, sig, strict=True)]
    ax.barh(y, np.nan_to_num(val), color=colors)
    for yi, v in zip(y, val, strict=True):
        if not np.isfinite(v):
            ax.text(0, yi, " only one calibration", va="center", fontsize=8, color="0.4")
    ax.axvline(tolerance_um, color="black", ls="--", lw=1, label=f"tolerance {tolerance_um:g} µm")
    ax.set_yticks(y, cams, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("largest change of the latest calibration over the sensor [µm]")
    handles = [Rectangle((0, 0), 1, 1, color=c) for c in ("tab:red", "tab:orange", "tab:gray")]
    ax.legend(handles + ax.get_legend_handles_labels()[0],
              ["flagged (significant and > tolerance)", "significant", "not significant"]
              + ax.get_legend_handles_labels()[1], fontsize=7, loc="upper left",
              bbox_to_anchor=(1.01, 1.0))
    ax.set_title("Fleet: latest vs previous calibration", fontsize=10, loc="left")
    return fig


# --------------------------------------------------------------------------------------
# residual distribution, 2-D distortion
# --------------------------------------------------------------------------------------
def residual_histogram(z, expected_sigma: float, *, what: str = "residual / a-priori sigma",
                       unit: str = "", statistic=None, dof: int = 2) -> Figure:
    """Histogram of residuals ``z`` (n,) with the normal curve they are expected to follow.

    ``expected_sigma`` is the standard deviation the residuals should have (for example
    ``sigma0 sqrt(r / n)``: the a-posteriori unit weight and the share of the observations'
    redundancy; see :mod:`fieldcal.products.report`). With ``statistic`` (m,), a per-point
    test statistic that is chi-square with ``dof`` degrees of freedom (the residual
    weighted by its own redundancy), a second panel shows it against that density.
    """
    from scipy import stats as st

    z = np.asarray(z, float)
    z = z[np.isfinite(z)]
    fig = Figure(figsize=(11.0 if statistic is not None else 8.0, 3.6), layout="constrained")
    ax = fig.add_subplot(1, 2 if statistic is not None else 1, 1)
    if statistic is not None:
        T = np.asarray(statistic, float)
        T = T[np.isfinite(T)]
        ax2 = fig.add_subplot(1, 2, 2)
        top = max(float(st.chi2.isf(0.001, dof)), float(np.percentile(T, 99.5)) if T.size else 1.0)
        ax2.hist(T, bins=np.linspace(0, top, 60), density=True, color="tab:green", alpha=0.6,
                 label=f"{T.size} points (mean {T.mean() if T.size else float('nan'):.3g})")
        x = np.linspace(top / 600, top, 600)
        ax2.plot(x, st.chi2.pdf(x, dof), color="black", lw=1.2, label=f"chi-square, {dof} dof (mean {dof})")
        ax2.set_xlim(0, top)
        ax2.set_xlabel("per-point test statistic (residual over its own sigma, squared)")
        ax2.set_ylabel("density")
        ax2.legend(fontsize=8)
    if z.size == 0:
        ax.text(0.5, 0.5, "no residuals", ha="center", transform=ax.transAxes)
        return fig
    lim = max(4.0 * expected_sigma, float(np.percentile(np.abs(z), 99.5)))
    bins = np.linspace(-lim, lim, int(np.clip(np.sqrt(z.size), 15, 80)))
    ax.hist(z, bins=bins, density=True, color="tab:blue", alpha=0.6,
            label=f"{z.size} residuals (RMS {np.sqrt(np.mean(z**2)):.3g}{' ' + unit if unit else ''})")
    x = np.linspace(-lim, lim, 400)
    if expected_sigma > 0:
        ax.plot(x, np.exp(-0.5 * (x / expected_sigma) ** 2) / (expected_sigma * np.sqrt(2 * np.pi)),
                color="black", lw=1.2, label=f"expected normal, sigma {expected_sigma:.3g}")
    out = int((np.abs(z) > lim).sum())
    ax.set_xlim(-lim, lim)
    ax.set_xlabel(what + (f" [{unit}]" if unit else ""))
    ax.set_ylabel("density")
    ax.legend(fontsize=8, title=f"{out} beyond the axes" if out else None, title_fontsize=7)
    return fig


def distortion_vectors(grid_u_px, grid_v_px, field_px, sensor: Sensor, *, step: int = 3,
                       reach_px=None) -> Figure:
    """The correction field (ny, nx, 2) [px] as vectors over the sensor, its size in colour.

    ``reach_px``: optional (u, v) points whose convex extent marks where the data were.
    """
    gu, gv = np.asarray(grid_u_px, float), np.asarray(grid_v_px, float)
    F = np.asarray(field_px, float)
    mag = np.hypot(F[..., 0], F[..., 1])
    fig = Figure(figsize=(9.0, 6.4), layout="constrained")
    ax = fig.add_subplot()
    du, dv = (gu[1] - gu[0]) / 2 if gu.size > 1 else 0.5, (gv[1] - gv[0]) / 2 if gv.size > 1 else 0.5
    im = ax.imshow(mag, extent=(gu[0] - du, gu[-1] + du, gv[-1] + dv, gv[0] - dv), origin="upper",
                   cmap="viridis")
    uu, vv = np.meshgrid(gu[::step], gv[::step])
    vec = F[::step, ::step].reshape(-1, 2)
    _vectors(ax, np.column_stack([uu.ravel(), vv.ravel()]), vec,
             0.9 * step * 2 * du, "white", 0.004)
    if reach_px is not None and len(reach_px):
        pts = np.asarray(reach_px, float)
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=1.5, color="tab:red", alpha=0.5, label="observations")
        ax.legend(fontsize=8, loc="lower right")
    _sensor_axes(ax, sensor)
    fig.colorbar(im, ax=ax, shrink=0.85).set_label("|correction| [px]")
    ax.set_title(f"Correction (measured -> ideal point) over the sensor: up to {mag.max():.3g} px",
                 fontsize=10, loc="left")
    return fig
