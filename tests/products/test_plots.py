"""Figures: each draws the numbers it is given (checked on the artists), and renders to PNG."""

import datetime as dt

import matplotlib.colors as mcolors
import numpy as np
import pyarrow as pa
import pytest

from fieldcal.analysis.uncertainty import Calibration, radial_curve, uncertainty_map
from fieldcal.errors import InputError
from fieldcal.model.camera import PARAM_NAMES, Camera, Sensor
from fieldcal.products import plots
from fieldcal.synthetic.field import IXU150_TABLE1

SENSOR = Sensor(820, 628, 53.0)
CAM = Camera.from_dict(SENSOR, IXU150_TABLE1)
NAMES = ("f_mm", "xp_mm", "yp_mm", "k1", "p1", "p2")


def _cal():
    sd = np.array([3e-3, 3e-3, 2.5e-3, 3e-8, 8e-8, 6e-8])
    corr = np.eye(6)
    corr[1, 4] = corr[4, 1] = -0.98            # xp - p1, as on a long lens
    corr[2, 5] = corr[5, 2] = 0.96
    corr[0, 3] = corr[3, 0] = 0.5
    doc = {"camera_id": "c", "version": "v", "method": "field", "sensor": SENSOR.to_dict(),
           "parameters": CAM.to_dict(), "sigma": dict.fromkeys(PARAM_NAMES)}
    return Calibration(doc, CAM, NAMES, corr * np.outer(sd, sd))


def test_to_png_renders_a_png():
    png = plots.to_png(plots.correlation_figure(_cal()))
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 1000


def test_residual_vectors_show_the_residuals_the_cell_means_and_the_rejected():
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [819, 627], (600, 2))
    duv = rng.normal(0, 0.1, (600, 2)) + [0.05, 0.0]       # a systematic shift of 0.05 px in u
    used = np.ones(600, bool)
    used[:7] = False
    fig = plots.residual_vectors(uv, duv, SENSOR, used=used, cells=(8, 6))
    ax1, ax2 = fig.axes[:2]
    q1 = [c for c in ax1.collections if c.__class__.__name__ == "Quiver"][0]
    assert q1.N == 593                                      # every used point (below max_points)
    np.testing.assert_allclose(q1.U, duv[used, 0])
    rms = np.sqrt(np.mean(np.sum(duv[used] ** 2, axis=1)))
    assert f"RMS {rms:.3g} px" in ax1.get_title(loc="left")
    assert "rejected (7)" in [t.get_text() for t in ax1.get_legend().get_texts()]
    q2 = [c for c in ax2.collections if c.__class__.__name__ == "Quiver"][0]
    assert q2.N == 48                                       # 8 x 6 cells, ~12 points each
    assert abs(np.mean(q2.U) - 0.05) < 0.02                 # the shift survives averaging
    from matplotlib.quiver import QuiverKey

    keys = [k.text.get_text() for a in (ax1, ax2) for k in a.get_children() if isinstance(k, QuiverKey)]
    assert len(keys) == 2 and all("magnified" in k for k in keys)


def test_residuals_per_image_draws_the_given_means():
    names = [f"i{k}" for k in range(6)]
    mu, mv, rms = np.arange(6) * 0.1, np.arange(6) * 0.2, np.arange(6) * 0.3
    fig = plots.residuals_per_image(names, mu, mv, rms, ["A", "A", "B", "B", "C", "C"])
    lines = fig.axes[0].get_lines()
    np.testing.assert_allclose(lines[0].get_ydata(), mu)
    np.testing.assert_allclose(lines[2].get_ydata(), rms)
    assert {t.get_text() for t in fig.axes[0].texts} == {"A", "B", "C"}


def test_stations_3d_draws_every_camera_and_target():
    rng = np.random.default_rng(1)
    C = rng.normal(0, 10, (5, 3))
    R = np.tile(np.eye(3), (5, 1, 1))
    T = rng.normal(0, 5, (40, 3))
    fig = plots.stations_3d(C, R, stations=["S1", "S1", "S2", "S2", "S2"], targets_xyz_m=T)
    ax = fig.axes[0]
    assert ax.name == "3d"
    sizes = sorted(len(c.get_offsets()) for c in ax.collections)
    assert sizes == [2, 3, 40]
    assert len(ax.get_lines()) == 5                         # one viewing direction per camera


def test_distortion_curves_draw_the_radial_correction_in_pixels():
    cal = _cal()
    fig = plots.distortion_curves(cal, n=50)
    line = fig.axes[0].get_lines()[0]
    r = line.get_xdata()
    val, _ = radial_curve(cal, r)
    np.testing.assert_allclose(line.get_ydata(), val / SENSOR.pixel_mm)


def test_uncertainty_figure_shows_the_propagated_maps():
    cal = _cal()
    fig = plots.uncertainty_figure(cal, grid=(11, 9))
    ims = [a.get_images()[0] for a in fig.axes if a.get_images()]
    assert len(ims) == 2
    np.testing.assert_allclose(ims[0].get_array(), uncertainty_map(cal, (11, 9))[2])
    np.testing.assert_allclose(ims[1].get_array(),
                               uncertainty_map(cal, (11, 9), remove_rotation=True)[2])


def test_correlation_figure_outlines_the_high_correlations():
    fig = plots.correlation_figure(_cal(), threshold=0.95)
    rects = [p for p in fig.axes[0].patches if not p.get_fill()]
    assert len(rects) == 4                                  # (xp, p1), (yp, p2) both ways


def test_goniometer_axes_has_before_and_after_panels_per_axis():
    t = {"axis": np.array(["x"] * 5 + ["y"] * 4), "position_px": np.r_[np.arange(5), np.arange(4)] * 100.0,
         "angle_deg": np.zeros(9), "before_px": np.linspace(-1, 1, 9), "fit_px": np.linspace(-1, 1, 9),
         "after_px": np.linspace(-0.1, 0.1, 9)}
    fig = plots.goniometer_axes(t, sigma_fit_px=0.05)
    assert len(fig.axes) == 4
    np.testing.assert_allclose(fig.axes[1].get_lines()[0].get_ydata(), t["after_px"][:5])
    assert "max |D| 1 px" in fig.axes[0].get_title(loc="left")


def _history():
    return pa.table({
        "version": ["v1", "v2", "v3"], "method": ["field", "goniometer", "field"],
        "acquired": [dt.datetime(2026, m, 1, tzinfo=dt.UTC) for m in (1, 4, 8)],
        "created": [dt.datetime(2026, m, 2, tzinfo=dt.UTC) for m in (1, 4, 8)],
        "f_mm": [146.390, 146.391, 146.395], "sigma_f_mm": [0.003, 0.001, 0.003]})


def test_history_plot_draws_a_tolerance_band_around_the_first_value():
    fig = plots.history_plot(_history(), ["f_mm"], tolerance={"f_mm": 0.002})
    ax = fig.axes[0]
    band = [p for p in ax.patches if p.get_label().startswith("tolerance")][0]
    assert band.get_y() == pytest.approx(146.388)
    assert band.get_y() + band.get_height() == pytest.approx(146.392)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any(lab.startswith("field") for lab in labels) and any(lab.startswith("goniometer") for lab in labels)


def test_history_plot_refuses_an_empty_history_and_unknown_columns():
    with pytest.raises(InputError, match="no calibrations to plot"):
        plots.history_plot(_history().slice(0, 0))
    with pytest.raises(InputError, match="has no column 'k1'"):
        plots.history_plot(_history(), ["k1"])


def test_fleet_plot_colours_flagged_cameras_red():
    t = pa.table({"camera_id": ["a", "b", "c"], "max_change_um": [5.0, 1.0, None],
                  "significant": [True, True, False], "flagged": [True, False, False]})
    fig = plots.fleet_plot(t, tolerance_um=2.0)
    bars = [p for p in fig.axes[0].patches if p.__class__.__name__ == "Rectangle"][:3]
    assert mcolors.to_hex(bars[0].get_facecolor()) == mcolors.to_hex("tab:red")
    assert mcolors.to_hex(bars[1].get_facecolor()) == mcolors.to_hex("tab:orange")
    assert bars[0].get_width() == 5.0
    assert any("only one calibration" in t.get_text() for t in fig.axes[0].texts)
