"""The calibration report and the fleet summary, on versions made from synthetic sessions.

:func:`reports_lake` builds (once per test session, under pytest's base temporary folder)
a lake with versions made by the real pipeline from seeded synthetic sessions; the other
report/compare/export/CLI test files import it:

- ``cam-f``: two field calibrations of the same true camera (independent noise, the first
  with survey and identification blunders), acquired in January and June;
- ``cam-d``: a field calibration and, in June, one of a camera that drifted (f + 20 um,
  k1 + 3 %);
- ``cam-g``: a goniometer calibration (Hasselblad scenario on a 4x coarser raster, one
  frame without a spot).
"""

import datetime as dt
import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest

from fieldcal import pipeline
from fieldcal.analysis.uncertainty import Calibration
from fieldcal.errors import InputError
from fieldcal.lake.store import Lake
from fieldcal.model.camera import INDEX, PARAM_NAMES, Camera, Sensor, correction
from fieldcal.products.report import (
    FIELD_FIGURES,
    GONIOMETER_FIGURES,
    fleet_summary,
    goniometer_axis_table,
    image_table,
    inputs_summary,
    parameter_rows,
    parameter_tolerance,
    write_report,
)
from fieldcal.synthetic.field import IXU150_TABLE1, add_blunders, paper_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session

DRIFT = {"f_mm": 0.020, "k1_factor": 1.03}


# --------------------------------------------------------------------------------------
# the shared lake
# --------------------------------------------------------------------------------------
def _field_version(lake, root, name, camera_id, acquired, *, seed, camera=None, blunders=False):
    sf = paper_field(seed=seed, n_attitudes=3, camera=camera)
    if blunders:
        sf, _ = add_blunders(sf, fraction=0.003, seed=seed + 1)
    write_field_session(root / name, sf, images=False, observations_csv=True, camera_id=camera_id,
                        session_id=name, acquired=acquired)
    p = pipeline.prepare(root / name)
    out = pipeline.solve(p, {}, fingerprint_=pipeline.input_fingerprint(p, {}))
    return lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)


def build_reports_lake(root: Path) -> dict:
    """Make the lake of the module docstring in ``root``; returns its description."""
    lake = Lake(root / "lake")
    truth = Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1)
    drifted = truth.params.copy()
    drifted[INDEX["f_mm"]] += DRIFT["f_mm"]
    drifted[INDEX["k1"]] *= DRIFT["k1_factor"]
    v = {
        "f1": _field_version(lake, root, "f-jan", "cam-f", "2026-01-10T09:00:00Z", seed=1,
                             blunders=True),
        "f2": _field_version(lake, root, "f-jun", "cam-f", "2026-06-10T09:00:00Z", seed=11),
        "d1": _field_version(lake, root, "d-jan", "cam-d", "2026-01-12T09:00:00Z", seed=21),
        "d2": _field_version(lake, root, "d-jun", "cam-d", "2026-06-12T09:00:00Z", seed=31,
                             camera=Camera(truth.sensor, drifted)),
    }
    g = root / "g-lab"
    write_session(g, "h3d", seed=1, raster_scale=0.25, frames_per_angle=2, faults=("no_spot",),
                  camera_id="cam-g", session_id="g-lab")
    p = pipeline.prepare(g)
    meas = {n: pipeline.measure(p, n) for n in p.to_measure}
    out = pipeline.solve(p, meas, fingerprint_=pipeline.input_fingerprint(
        p, {n: pipeline.image_hash(p, n) for n in p.to_measure}))
    v["g"] = lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs)
    res = out.result.residuals
    info = {"lake": str(root / "lake"), "versions": {k: str(x) for k, x in v.items()},
            "truth": truth.params.tolist(), "drifted": drifted.tolist(),
            "gonio_truth": {"axis": res["axis"].to_pylist(), "angle_deg": res["angle_deg"].to_pylist(),
                            "distortion_px": res["distortion_px"].to_pylist(),
                            "fit_px": res["fit_px"].to_pylist(),
                            "residual_px": res["residual_px"].to_pylist()},
            "gonio_rejected": [r["file"] for r in out.result.rejected]}
    (root / "lake.json").write_text(json.dumps(info))
    return info


def reports_lake(tmp_path_factory) -> dict:
    """The shared lake (built on first use in this pytest session): ``{"lake", "versions", ...}``."""
    root = tmp_path_factory.getbasetemp() / "reports_lake"
    marker = root / "lake.json"
    if not marker.exists():
        root.mkdir(exist_ok=True)
        build_reports_lake(root)
    info = json.loads(marker.read_text())
    info["lake_obj"] = Lake(info["lake"])
    return info


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return reports_lake(tmp_path_factory)


# --------------------------------------------------------------------------------------
# HTML structure
# --------------------------------------------------------------------------------------
VOID = {"meta", "img", "br", "hr", "link", "input", "col", "area", "base", "wbr", "source"}


class _Checker(HTMLParser):
    """Well-formedness (every element closed in order) and the report's pieces."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack, self.errors, self.figures, self.ids, self.imgs = [], [], [], set(), {}
        self.doctype = False
        self._in_figure = None

    def handle_decl(self, decl):
        self.doctype = self.doctype or decl.lower() == "doctype html"

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            if a["id"] in self.ids:
                self.errors.append(f"duplicate id {a['id']}")
            self.ids.add(a["id"])
        if tag == "figure":
            self._in_figure = a.get("id")
            self.figures.append(a.get("id"))
        if tag == "img" and self._in_figure:
            self.imgs[self._in_figure] = a.get("src", "")
        if tag not in VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.handle_starttag(tag, attrs)
        if tag not in VOID:
            self.stack.pop()

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes <{self.stack[-1] if self.stack else None}>")
            return
        self.stack.pop()
        if tag == "figure":
            self._in_figure = None


def check_html(text: str) -> _Checker:
    c = _Checker()
    c.feed(text)
    c.close()
    return c


def _assert_report(files, names):
    text = files.html.read_text(encoding="utf-8")
    c = check_html(text)
    assert c.doctype
    assert c.errors == [] and c.stack == []
    assert c.figures == [f"fig-{n}" for n in names]
    for n in names:
        src = c.imgs[f"fig-{n}"]
        assert src.startswith("data:image/png;base64,")
        import base64

        png = base64.b64decode(src.split(",", 1)[1])
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert files.pngs[n].read_bytes() == png        # the PNG files are the embedded plots
    assert "http://" not in text and "https://" not in text   # self-contained
    return text, c


def test_field_report_has_every_plot_and_is_well_formed(shared, tmp_path):
    lake = shared["lake_obj"]
    files = write_report(lake, shared["versions"]["f1"], tmp_path / "rep")
    text, c = _assert_report(files, FIELD_FIGURES)
    assert {"inputs", "parameters", "parameter-table", "correlation-table", "left-out"} <= c.ids
    # the blunders are listed as left out, with their reasons
    assert "blunder" in text and "image point" in text


def test_goniometer_report_has_every_plot_and_lists_the_rejected_frame(shared, tmp_path):
    lake = shared["lake_obj"]
    files = write_report(lake, shared["versions"]["g"], tmp_path / "rep")
    text, _ = _assert_report(files, GONIOMETER_FIGURES)
    assert shared["gonio_rejected"] and all(f in text for f in shared["gonio_rejected"])
    assert "no spot" in text


def test_html_checker_catches_a_misnested_tag():
    c = check_html("<!DOCTYPE html><html><body><p><b>x</p></b></body></html>")
    assert c.errors


# --------------------------------------------------------------------------------------
# parameter table and inputs
# --------------------------------------------------------------------------------------
def _doc(values, sigma, method="field", fixed=None):
    params = dict.fromkeys(PARAM_NAMES, 0.0)
    params.update(values)
    sig = dict.fromkeys(PARAM_NAMES)
    sig.update(sigma)
    return {"camera_id": "c", "session_id": "s", "version": "", "method": method,
            "sensor": {"width_px": 800, "height_px": 600, "pixel_size_um": 5.0},
            "parameters": params, "sigma": sig,
            "stats": {"fixed_parameters": fixed or {}}, "images": []}


def test_parameter_rows_mark_insignificant_parameters_and_high_correlations():
    values = {"f_mm": 50.0, "xp_mm": 0.01, "k1": 2.0e-6, "p1": 1.0e-7}
    sigma = {"f_mm": 0.001, "xp_mm": 0.002, "k1": 1.0e-7, "p1": 1.0e-7}
    names = ["f_mm", "xp_mm", "k1", "p1"]
    sd = np.array([sigma[n] for n in names])
    corr = np.eye(4)
    corr[1, 3] = corr[3, 1] = 0.97           # xp - p1: above 0.95
    corr[0, 2] = corr[2, 0] = 0.90           # f - k1: below
    cal = Calibration.from_document(_doc(values, sigma, fixed={"a1": "session"}), names,
                                    corr * np.outer(sd, sd))
    rows = {r["name"]: r for r in parameter_rows(cal)}
    assert rows["xp_mm"]["significant"]               # 0.01 / 0.002 = 5 sigma
    assert not rows["p1"]["significant"]              # 1 sigma
    assert rows["p1"]["status"] == "not significant at 3 sigma"
    assert rows["k1"]["t"] == pytest.approx(20.0)
    assert [o for o, _ in rows["xp_mm"]["correlated"]] == ["p1"]
    assert rows["p1"]["correlated"][0][1] == pytest.approx(0.97)
    assert rows["f_mm"]["correlated"] == []
    assert rows["a1"]["status"] == "held fixed: session"
    assert rows["b1"]["status"] == "fixed by the field method"


def test_inputs_summary_lists_rejected_points_surveys_and_fixed_parameters(shared):
    lake = shared["lake_obj"]
    v = shared["versions"]["f1"]
    cal = Calibration.from_lake(lake, v)
    res = lake.read_residuals(v)
    s = inputs_summary(cal, res)
    n_bad = int((~res["used"].to_numpy(zero_copy_only=False)).sum())
    points = [x for x in s["left_out"] if x["what"] == "image point"]
    assert n_bad > 0 and len(points) == n_bad
    assert sum(s["rejected_by_reason"].values()) == n_bad
    st = cal.document["stats"]
    surveys = [x["item"] for x in s["left_out"] if x["what"] == "surveyed coordinates"]
    assert surveys == st["rejected_surveys"]
    params = {x["item"] for x in s["left_out"] if x["what"] == "parameter"}
    assert params == set(st["fixed_parameters"])


# --------------------------------------------------------------------------------------
# goniometer: distortion before the fit, rebuilt from the lake
# --------------------------------------------------------------------------------------
def test_goniometer_axis_table_rebuilds_the_distortion_before_the_fit(shared):
    lake = shared["lake_obj"]
    v = shared["versions"]["g"]
    cal = Calibration.from_lake(lake, v)
    t = goniometer_axis_table(cal, lake.read_residuals(v))
    truth = shared["gonio_truth"]
    key = {(a, round(w, 6)): i for i, (a, w) in enumerate(zip(truth["axis"], truth["angle_deg"],
                                                               strict=True))}
    idx = [key[(a, round(w, 6))] for a, w in zip(t["axis"], t["angle_deg"], strict=True)]
    assert len(idx) == len(truth["axis"])
    # the method's own numbers (GoniometerResult.residuals), which the lake does not store:
    # 1e-9 px is rounding, the reconstruction is exact
    np.testing.assert_allclose(t["before_px"], np.array(truth["distortion_px"])[idx], atol=1e-9)
    np.testing.assert_allclose(t["fit_px"], np.array(truth["fit_px"])[idx], atol=1e-9)
    np.testing.assert_allclose(t["after_px"], np.array(truth["residual_px"])[idx], atol=1e-9)


# --------------------------------------------------------------------------------------
# tolerance and the fleet
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["k0", "k1", "k2", "k3", "a1", "a2", "b1", "b2"])
def test_parameter_tolerance_moves_the_corner_by_the_tolerance(name):
    sensor = Sensor(8208, 6280, 5.3)
    tol = parameter_tolerance(name, 2.0, sensor)
    p = np.zeros(13)
    p[INDEX["f_mm"]] = 146.0
    p[INDEX[name]] = tol
    corner = sensor.pixel_to_mm(np.array([[8207.0, 0.0]]))
    # the term's largest component at the half diagonal is the tolerance (2 um) for radial
    # and affine terms whose basis reaches r there: |d| along the radius for k, the
    # component for the affine ones
    d = np.hypot(*correction(corner, p)[0])
    r = sensor.half_diagonal_mm
    expected = {"a1": abs(corner[0, 0]) / r, "a2": abs(corner[0, 1]) / r,
                "b1": abs(corner[0, 0]) / r, "b2": abs(corner[0, 1]) / r}.get(name, 1.0)
    assert d * 1000 == pytest.approx(2.0 * expected, rel=1e-9)


def test_parameter_tolerance_rejects_unknown_names():
    with pytest.raises(InputError, match="unknown parameter 'k9'"):
        parameter_tolerance("k9", 2.0, Sensor(10, 10, 5.0))


def test_fleet_summary_flags_the_drifted_camera_only(shared):
    lake = shared["lake_obj"]
    t = fleet_summary(lake, tolerance_um=2.0)
    rows = {r["camera_id"]: r for r in t.to_pylist()}
    assert set(rows) == {"cam-f", "cam-d", "cam-g"}
    d = rows["cam-d"]
    assert d["version"] == shared["versions"]["d2"] and d["previous_version"] == shared["versions"]["d1"]
    assert d["flagged"] and d["significant"] and d["exceeds_tolerance"]
    # f + 20 um and k1 + 3 %: the largest change is at least the f change at the corner,
    # 20 um x r/f, far above 2 um
    assert d["max_change_um"] > 2.0
    f = rows["cam-f"]
    assert f["previous_version"] == shared["versions"]["f1"]
    assert not f["significant"] and not f["flagged"]        # same camera, independent noise
    assert f["p_value"] > 0.01
    g = rows["cam-g"]
    assert g["previous_version"] is None and not g["flagged"]
    assert g["verdict"] == "only one calibration"


def test_fleet_summary_respects_the_date_range(shared):
    lake = shared["lake_obj"]
    t = fleet_summary(lake, end=dt.date(2026, 3, 1))
    rows = {r["camera_id"]: r for r in t.to_pylist()}
    assert rows["cam-d"]["version"] == shared["versions"]["d1"]
    assert rows["cam-d"]["verdict"] == "only one calibration"


def test_fleet_summary_of_an_empty_lake_is_an_empty_table(tmp_path):
    t = fleet_summary(Lake(tmp_path / "empty"))
    assert t.num_rows == 0 and "flagged" in t.column_names
    assert isinstance(t, pa.Table)


def test_inputs_summary_gives_the_reasons_images_were_left_out():
    doc = _doc({"f_mm": 50.0}, {"f_mm": 1e-3})
    doc["stats"].update(left_out=[{"image": "images/a.tif", "reason": "unreadable: truncated TIFF"}],
                        left_out_images=["images/a.tif", "images/b.tif"], n_images=1,
                        targets_adjusted=True)
    doc["images"] = [{"file": "images/c.tif", "n_observations": 0}]
    res = pa.table({"image": pa.array([], pa.string()), "target_id": pa.array([], pa.string()),
                    "u_px": pa.array([], pa.float64()), "v_px": pa.array([], pa.float64()),
                    "du_px": pa.array([], pa.float64()), "dv_px": pa.array([], pa.float64()),
                    "used": pa.array([], pa.bool_()), "reason": pa.array([], pa.string())})
    s = inputs_summary(Calibration.from_document(doc), res)
    why = {x["item"]: x["why"] for x in s["left_out"] if x["what"] == "image"}
    assert why == {"images/a.tif": "unreadable: truncated TIFF",
                   "images/b.tif": "left out before the adjustment (no reason recorded in the document)",
                   "images/c.tif": "no usable image points"}


# --------------------------------------------------------------------------------------
# what a calibration engineer looks for (issue 16)
# --------------------------------------------------------------------------------------
def _text_of(page: str) -> str:
    import re

    return " ".join(re.sub(r"<[^>]+>", " ", page).split())


def test_field_report_has_the_engineers_tables(shared, tmp_path):
    lake, v = shared["lake_obj"], shared["versions"]
    files = write_report(lake, v["f2"], tmp_path / "rep")
    text, c = _assert_report(files, FIELD_FIGURES)
    assert {"interior-px", "model", "exterior", "exterior-table", "targets", "target-precision",
            "survey-residuals", "previous", "previous-table"} <= c.ids
    words = _text_of(text)
    cal = Calibration.from_lake(lake, v["f2"])
    d = cal.sensor.pixel_mm
    # f and the principal point in pixels
    assert f"{cal.camera.f_mm / d:.3f}" in words
    assert f"{(cal.sensor.width_px - 1) / 2 + cal.camera.params[INDEX['xp_mm']] / d:.3f}" in words
    # the model's equations
    assert "dx = xb radial + p1 (r^2 + 2 xb^2)" in words
    # one exterior-orientation row per image, its centre to the mm
    for im in cal.document["images"]:
        assert im["file"] in words and f"{im['center_m'][0]:.3f}" in words
    # the previous calibration of cam-f (January) with the change test
    assert v["f1"] in words and "Holm" in words and "principal distance: change" in words
    # survey residuals: surveyed minus adjusted, the largest first
    res = np.asarray(cal.arrays["targets/survey_residual_mm"])
    assert res.shape == np.asarray(cal.arrays["targets/xyz_m"]).shape
    assert "Survey residuals (surveyed minus adjusted)" in words
    # what a careful reader tripped on (issue 30): how the uncertainty was propagated, unit
    # symbols, and residuals with significant digits (0.0x px printed as 0.0x, not 0.000)
    assert "propagated from the version's stored covariance" in words and "covariance: covariance" not in words
    assert " um" not in words and "+-" not in words and "σ [µm]" in words
    rows = image_table(cal, shared["lake_obj"].read_residuals(v["f2"]))
    assert f"{rows[0]['rmse_px']:.3g}" in words


def test_report_of_a_camera_first_calibration_says_so(shared, tmp_path):
    files = write_report(shared["lake_obj"], shared["versions"]["g"], tmp_path / "rep")
    text, c = _assert_report(files, GONIOMETER_FIGURES)
    assert "first calibration in the lake" in _text_of(text)
    assert "exterior" not in c.ids                  # a goniometer has no exterior orientation


def test_residual_histogram_expected_curve_matches_a_correct_adjustment(shared):
    """The per-point statistic of a correct adjustment follows chi-square(2): mean 2 +- 5 %."""
    res = shared["lake_obj"].read_residuals(shared["versions"]["f2"])
    used = res["used"].to_numpy(zero_copy_only=False).astype(bool)
    T = res["normalized_residual"].to_numpy(zero_copy_only=False).astype(float)[used]
    # 3300 points: the mean of chi-square(2) has sigma 2 / sqrt(3300) = 0.035
    assert abs(T.mean() - 2.0) < 0.15


def test_history_plot_tolerance_has_a_unit():
    from fieldcal.products.plots import history_plot

    fig = history_plot({"version": ["a", "b"], "acquired": [dt.datetime(2026, 1, 1), dt.datetime(2026, 6, 1)],
                        "method": ["field", "field"], "f_mm": [146.39, 146.40],
                        "sigma_f_mm": [0.01, 0.01]}, ["f_mm"], tolerance={"f_mm": 0.002})
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert any(lab.startswith("tolerance ±0.002 mm") for lab in labels), labels
    assert fig.axes[0].get_ylabel() == "f_mm [mm]"
