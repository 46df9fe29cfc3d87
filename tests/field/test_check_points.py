"""Independent check points (issue 16, goal 2): chosen, withheld, measured against synthetic truth."""

import json
from dataclasses import replace

import numpy as np
import pytest

from fieldcal import pipeline
from fieldcal.errors import InputError
from fieldcal.field.adjustment import CHECK_POINT, AdjustmentOptions, adjust_field
from fieldcal.field.check_points import check_point_mask, stratified_check_points
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session

FP = "sha256:" + "0" * 64


def test_stratified_choice_covers_the_field_and_prefers_plain_targets():
    t = wide_field(seed=0).targets_true
    a = stratified_check_points(t, 0.1, seed=3)
    assert a.sum() == round(0.1 * len(t))
    assert np.array_equal(a, stratified_check_points(t, 0.1, seed=3))
    assert not np.array_equal(a, stratified_check_points(t, 0.1, seed=4))
    assert np.all(t.codes[a] < 0)                     # enough plain targets: no marker withheld
    # every quarter of the wall (X, Z halves) holds its share (~1/4 of 34), give or take a cell's
    X = t.xyz_m
    q = (X[:, 0] > np.median(X[:, 0])) * 2 + (X[:, 2] > np.median(X[:, 2]))
    counts = np.bincount(q[a], minlength=4)
    assert counts.min() >= 5, counts
    with pytest.raises(InputError, match="fraction must lie in"):
        stratified_check_points(t, 1.0)
    with pytest.raises(InputError, match=r"\['nope'\] are not in targets.csv"):
        check_point_mask(t, ids=["W0001", "nope"])


def _truth_errors(sf, res):
    """Intersected check points against the true coordinates [mm], and the image points of
    the check points against where the calibration lands the true targets [px]."""
    cp = res.check_points
    index = res.data.targets.index()
    t = np.array([index[i] for i in cp.ids])
    X_hat = res.data.targets.xyz_m[t] + cp.error_mm / 1000.0
    err_mm = (X_hat - sf.targets_true.xyz_m[t]) * 1000.0
    o = res.data.obs
    k = cp.obs_index[cp.used]
    uv = np.stack([res.camera.project(sf.targets_true.xyz_m[o.target[j]], res.R_world_to_camera[o.image[j]],
                                      res.center_m[o.image[j]]) for j in k])
    return err_mm, o.uv_px[k] - uv


@pytest.fixture(scope="module")
def precise_survey():
    """A survey 100 times better than the images resolve (0.05 mm): what the check points
    measure is the calibration's own error."""
    sf = wide_field(seed=3, survey_noise_mm=0.05)
    return sf, adjust_field(sf.data, AdjustmentOptions(check_fraction=0.15, check_seed=1))


def test_check_point_rms_agrees_with_the_truth_error_of_those_targets(precise_survey):
    sf, res = precise_survey
    st = res.stats()["check_points"]
    err_mm, err_px = _truth_errors(sf, res)
    truth_mm = np.sqrt(np.mean(np.sum(err_mm**2, axis=1)))
    truth_px = np.sqrt(np.mean(np.sum(err_px**2, axis=1)))
    print(f"\n{st}\ntruth: {truth_mm:.4f} mm, {truth_px:.4f} px")
    assert st["n"] >= 30 and st["n_withheld"] == round(0.15 * len(sf.data.targets))
    # the survey's 0.05 mm adds sqrt(3) x 0.05 mm in quadrature to the truth error: 10 %
    assert st["rms_mm"] == pytest.approx(np.hypot(truth_mm, np.sqrt(3) * 0.05), rel=0.1)
    assert st["rms_px"] == pytest.approx(truth_px, rel=0.1)
    # and the covariance predicted them (37 points x 3: the RMS's sampling error is ~7 %)
    assert st["rms_mm"] == pytest.approx(st["rms_mm_predicted"], rel=0.2)
    assert st["rms_px"] == pytest.approx(st["rms_px_predicted"], rel=0.2)
    assert st["p_value_mm"] > 0.01
    # per world axis (the certificate's X / Y / Z): they add up to the 3-D RMS, each agrees
    # with the truth error on that axis (survey noise added) and with its prediction
    assert sum(st[f"rms_{a}_mm"] ** 2 for a in "xyz") == pytest.approx(st["rms_mm"] ** 2)
    for j, a in enumerate("xyz"):
        print(a, st[f"rms_{a}_mm"], np.sqrt(np.mean(err_mm[:, j] ** 2)), st[f"rms_{a}_mm_predicted"])
        assert st[f"rms_{a}_mm"] == pytest.approx(np.hypot(np.sqrt(np.mean(err_mm[:, j] ** 2)), 0.05), rel=0.15)
        assert st[f"rms_{a}_mm"] == pytest.approx(st[f"rms_{a}_mm_predicted"], rel=0.3)
        assert abs(st[f"mean_{a}_mm"]) <= st[f"max_{a}_mm"] and st[f"max_{a}_mm"] >= st[f"rms_{a}_mm"]


def test_check_points_are_withheld_from_the_adjustment(precise_survey):
    sf, res = precise_survey
    check = np.isin(sf.data.targets.ids, res.check_points.ids)
    withheld = res.obs_reason == CHECK_POINT
    assert np.array_equal(withheld, np.isin(sf.data.targets.ids[sf.data.obs.target],
                                            sf.data.targets.ids[stratified_check_points(sf.data.targets, 0.15, 1)]))
    assert not res.obs_used[withheld].any() and check.any()
    # the same calibration as from the data without those targets' image points
    keep = ~withheld
    alone = adjust_field(replace(sf.data, obs=sf.data.obs.take(keep)))
    np.testing.assert_allclose(res.params, alone.params, rtol=0, atol=1e-12)
    assert res.stats()["n_left_out"] == 0


def test_with_the_usual_survey_the_check_points_see_the_survey_noise():
    sf = wide_field(seed=3)                               # 5 mm survey noise
    st = adjust_field(sf.data, AdjustmentOptions(check_fraction=0.15, check_seed=1)).stats()["check_points"]
    print(st)
    # intersected minus surveyed: sqrt(3) x 5 mm = 8.7 mm and a little for the intersection
    assert st["rms_mm"] == pytest.approx(st["rms_mm_predicted"], rel=0.2)
    assert 7.0 < st["rms_mm_predicted"] < 10.0
    assert st["rms_px"] == pytest.approx(st["rms_px_predicted"], rel=0.2)


def test_a_session_names_its_check_points_and_the_document_carries_them(tmp_path):
    sf = wide_field(seed=1)
    write_field_session(tmp_path, sf, images=False, observations_csv=True)
    manifest = json.loads((tmp_path / "session.json").read_text())
    ids = [str(t) for t in sf.data.targets.ids[sf.data.targets.codes < 0][::12]]
    manifest["check_points"] = ids
    (tmp_path / "session.json").write_text(json.dumps(manifest))
    prepared = pipeline.prepare(tmp_path)
    out = pipeline.solve(prepared, {}, fingerprint_=FP)
    cp = out.document["stats"]["check_points"]
    assert cp["n_withheld"] == len(ids) and cp["selection"] == f"session ({len(ids)})"
    assert cp["rms_px"] > 0 and cp["rms_mm"] > 0
    assert any(line.startswith("check points:") for line in out.summary)
    reasons = out.residuals["reason"].to_pylist()
    assert reasons.count(CHECK_POINT) == cp["n_observations"] + cp["n_rejected"]
    assert out.arrays["check_points/error_mm"].shape == (cp["n"], 3)
    named = out.array_attrs["check_points/error_mm"]["ids"]
    assert len(named) == cp["n"] and set(named) <= set(ids)
    # a fraction from the settings, and an id that targets.csv does not hold
    frac = pipeline.solve(pipeline.prepare(tmp_path, pipeline.Settings(check_fraction=0.1)), {}, fingerprint_=FP)
    assert frac.document["stats"]["check_points"]["n_withheld"] > len(ids)
    manifest["check_points"] = ["W0001", "X999"]
    (tmp_path / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"check_points \['X999'\] are not in targets.csv"):
        pipeline.prepare(tmp_path)
    manifest["check_points"] = [1, 2]
    (tmp_path / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="is not of type 'string'"):
        pipeline.prepare(tmp_path)


def test_the_report_and_the_certificate_show_check_points_and_the_cross_validation(tmp_path):
    from fieldcal.analysis.uncertainty import Calibration
    from fieldcal.products.certificate import acceptance, load_config
    from fieldcal.products.report_sections import validation_section
    from tests.products.test_report import check_html

    sf = wide_field(seed=2)
    write_field_session(tmp_path, sf, images=False, observations_csv=True)
    settings = pipeline.Settings(check_fraction=0.1, cross_validate=True)
    assert pipeline.Settings().to_dict() == {"targets_adjusted": True, "solver": "lmqn",
                                             "rigorous_goniometer": False}     # other fingerprints stay
    assert settings.to_dict()["check_fraction"] == 0.1 and settings.to_dict()["cross_validate"] is True
    out = pipeline.solve(pipeline.prepare(tmp_path, settings), {}, fingerprint_=FP)
    st = out.document["stats"]
    assert [s["station"] for s in st["cross_validation"]["stations"]] == [f"S{i}" for i in range(1, 9)]
    cal = Calibration.from_document(out.document)
    rows = {r["criterion"]: r for r in acceptance(cal, None, load_config())["rows"]}
    assert rows["check-point RMS (px)"]["value"] == pytest.approx(st["check_points"]["rms_px"])
    assert rows["check-point RMS (mm)"]["value"] == pytest.approx(st["check_points"]["rms_mm"])
    html = validation_section(cal)
    c = check_html(html)
    assert c.errors == [] and c.stack == []
    assert 'id="check-points"' in html and 'id="cross-validation"' in html
    assert f"{st['check_points']['rms_px']:.3g} px" in html
