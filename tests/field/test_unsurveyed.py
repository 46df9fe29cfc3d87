"""Unsurveyed targets, free networks and scale bars (issue 26; CONTRACT section 3).

Truth: the synthetic wide-angle field (fieldcal.synthetic.field.wide_field, 326 targets, 24
images, 0.1 px noise, surveys 5 mm). Four targets near the middle of the wall keep their
(noisy) survey; the other ~320 are unsurveyed.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.model.camera import INDEX
from fieldcal.session.data import ScaleBars
from fieldcal.session.loader import field_data_from_observations, load_session
from fieldcal.synthetic.field import wide_field, with_control_points
from fieldcal.synthetic.session_writer import write_field_session

CORE = ("f_mm", "xp_mm", "yp_mm", "k1")


@pytest.fixture(scope="module")
def field():
    sf = wide_field(seed=3)
    data, control = with_control_points(sf)
    return sf, data, control


@pytest.fixture(scope="module")
def results(field):
    sf, data, control = field
    Xt = sf.targets_true.xyz_m
    a, b, c = control[0], control[1], control[3]
    bar1 = ScaleBars([a], [b], [np.linalg.norm(Xt[b] - Xt[a]) * 1e3], [0.02])
    bar2 = ScaleBars([a, b], [b, c], [np.linalg.norm(Xt[b] - Xt[a]) * 1e3, np.linalg.norm(Xt[c] - Xt[b]) * 1e3],
                     [0.02, 0.02])
    free = AdjustmentOptions(datum="free")
    return {"surveyed": adjust_field(sf.data),
            "control": adjust_field(data),
            "free": adjust_field(data, free),
            "free, 1 bar": adjust_field(replace(data, scale_bars=bar1), free),
            "free, 2 bars": adjust_field(replace(data, scale_bars=bar2), free)}


def test_four_control_points_and_unsurveyed_targets_give_the_surveyed_cases_camera(field, results):
    sf, data, _ = field
    res, ref = results["control"], results["surveyed"]
    stats = res.stats()
    assert stats["n_unsurveyed_targets"] >= 200          # the tie points entered (and are reported)
    assert stats["datum"]["type"] == "weighted control" and stats["datum"]["n_control"] == 4
    row = stats["unsurveyed_targets"][0]
    assert len(row["xyz_m"]) == 3 and all(0 < s < 50 for s in row["sigma_mm"])   # the datum: 4 points at 5 mm
    truth = sf.camera.params
    for name in res.estimate:
        z = (res.params[INDEX[name]] - truth[INDEX[name]]) / res.sigma[name]
        assert abs(z) < 4.0, (name, z)                    # honest sigma: within 4 sigma of the truth
        # the surveyed field's 5 mm surveys add next to nothing: the same precision within 10 %
        assert res.sigma[name] == pytest.approx(ref.sigma[name], rel=0.10), name


def test_interior_orientation_does_not_depend_on_the_datum(results):
    free = results["free"]
    for label in ("free, 1 bar",):       # two bars are one length more: tests/field/test_scale_bars.py
        res = results[label]
        for name in CORE:
            j = INDEX[name]
            # the same image points, another datum (a minimal scale): another solve, which stops
            # within sigma_tol (1e-3) of a sigma of the optimum; the sigmas to 1e-6
            assert abs(res.params[j] - free.params[j]) < 1e-3 * free.sigma[name], (label, name)
            assert res.sigma[name] == pytest.approx(free.sigma[name], rel=1e-6), (label, name)
    control = results["control"]
    for name in CORE:
        # weighted control of 4 points at 5 mm is not a minimal datum: it adds (a little) shape
        assert abs(control.params[INDEX[name]] - free.params[INDEX[name]]) < 0.01 * free.sigma[name], name
        assert control.sigma[name] == pytest.approx(free.sigma[name], rel=0.01), name
    assert free.stats()["datum"]["type"] == "free network"
    assert free.stats()["datum"]["scale"].startswith("the initial values")


def _helmert_errors(res, truth_xyz):
    """Adjusted minus true coordinates after the best similarity onto the truth [m], and sigmas."""
    ok = np.isfinite(res.sigma_targets_m).all(axis=1)
    P, Q = res.targets_m[ok], truth_xyz[ok]
    mp, mq = P.mean(0), Q.mean(0)
    U, s, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    scale = np.sum(s * [1, 1, np.sign(np.linalg.det(U @ Vt))]) / np.sum((P - mp) ** 2)
    return scale * (P - mp) @ R.T + mq - Q, res.sigma_targets_m[ok], scale


def test_free_network_targets_have_honest_minimum_trace_sigmas(field, results):
    sf, _, _ = field
    err, sigma, _ = _helmert_errors(results["free"], sf.targets_true.xyz_m)
    z = err / sigma
    # the minimum-trace sigmas describe the shape: |error| / sigma about 1 (not the 5 mm of the survey)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6
    assert np.median(sigma) < 0.5e-3


def test_scale_bar_scales_the_free_network(field, results):
    sf, data, control = field
    res = results["free, 1 bar"]
    Xt = sf.targets_true.xyz_m
    a, b = control[0], control[3]                      # a distance the bar does not measure
    true = np.linalg.norm(Xt[b] - Xt[a])
    got = np.linalg.norm(res.targets_m[b] - res.targets_m[a])
    assert abs(got - true) < 4 * np.hypot(*res.sigma_targets_m[[a, b]].max(axis=1)) + 0.1e-3
    bars = res.stats()["datum"]["scale_bars"]
    assert bars[0]["adjusted_mm"] == pytest.approx(bars[0]["length_mm"], abs=1e-6)   # one bar: exact
    two = results["free, 2 bars"].stats()["datum"]["scale_bars"]
    assert all(abs(r["adjusted_mm"] - r["length_mm"]) < 4 * np.hypot(r["sigma_mm"], r["sigma_adjusted_mm"])
               for r in two)


def test_photomodeler_style_export_with_points_not_in_the_control_list(tmp_path, field):
    """An observations-only session whose targets.csv lists the 4 control points and a few
    unsurveyed ids, while observations.csv also names ids it does not list."""
    sf, _, control = field
    folder = tmp_path / "pm"
    write_field_session(folder, sf, images=False, observations_csv=True, coded=False)
    t = sf.data.targets
    listed = set(control) | set(range(10, 20))
    lines = ["id,X,Y,Z,sigma_mm,code"]
    for j in sorted(listed):
        xyz = ",".join(f"{v:.6f}" for v in t.xyz_m[j]) if j in control else ",,"
        lines.append(f"{t.ids[j]},{xyz},5,")
    (folder / "targets.csv").write_text("\n".join(lines) + "\n")
    data = field_data_from_observations(load_session(folder))
    n_unlisted = len(set(np.unique(sf.data.obs.target)) - listed)
    assert len(data.meta["unlisted_targets"]) == n_unlisted > 200
    assert int(data.targets.surveyed.sum()) == 4
    res = adjust_field(data)
    stats = res.stats()
    assert stats["n_unlisted_targets"] == n_unlisted
    assert stats["n_unsurveyed_targets"] > 200
    for name in CORE:
        assert abs(res.params[INDEX[name]] - sf.camera.params[INDEX[name]]) < 4 * res.sigma[name], name
    # the session asks for strictness: the first unlisted id is refused, naming file and line
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["strict_targets"] = True
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"observations\.csv:\d+: target_id '\w+' is not in targets\.csv"):
        field_data_from_observations(load_session(folder))


def test_scale_bars_csv_names_targets_of_the_session(tmp_path, field):
    sf, _, control = field
    folder = tmp_path / "bars"
    write_field_session(folder, sf, images=False, observations_csv=True, coded=False)
    ids = sf.data.targets.ids
    (folder / "scale_bars.csv").write_text(f"from_id,to_id,length_mm,sigma_mm\n{ids[0]},{ids[1]},1000.0,0.02\n")
    data = field_data_from_observations(load_session(folder))
    assert len(data.scale_bars) == 1 and data.scale_bars.length_mm[0] == 1000.0
    (folder / "scale_bars.csv").write_text(f"from_id,to_id,length_mm,sigma_mm\n{ids[0]},nosuch,1000.0,0.02\n")
    with pytest.raises(InputError, match=r"scale_bars\.csv:2: to_id 'nosuch' is not a target"):
        field_data_from_observations(load_session(folder))


def test_unsurveyed_targets_cannot_be_held_fixed(field):
    _, data, _ = field
    with pytest.raises(InputError, match="unsurveyed.*cannot be held fixed"):
        adjust_field(data, AdjustmentOptions(targets_adjusted=False))


def test_minimum_trace_covariance_equals_the_bordered_inner_constraint_system(field, monkeypatch):
    """An independent reference: the inverse of the bordered normal equations
    ``[[N, K], [K^T, 0]]`` (dense, the data rows only) has the inner-constraint covariance in its
    top-left block; the S-transformation of the minimal-constraint solve must give it."""
    import fieldcal.field.adjustment as adjustment
    import fieldcal.field.datum as datum

    _, data, _ = field
    seen = {}

    def spy(model, result, R, C, X, X0, bars, sigma0):
        out = datum.to_minimum_trace(model, result, R, C, X, X0, bars, sigma0)
        seen.update(model=model, result=result, R=R, C=C, X=X, out=out)
        return out

    monkeypatch.setattr(adjustment, "to_minimum_trace", spy)
    adjust_field(data, AdjustmentOptions(datum="free"))
    m, out = seen["model"], seen["out"]
    J = seen["result"].jac.to_csr()[:-7].toarray()          # without the 7 minimal-constraint rows
    E = datum.null_space(m, seen["R"], seen["C"], seen["X"][m.target_index])
    assert np.abs(J @ E).max() < 1e-9 * np.abs(J).max()    # E is the null space of the image points
    K = np.zeros_like(E)
    K[m.n_reduced:] = E[m.n_reduced:]
    n = J.shape[1]
    Q = np.linalg.inv(np.block([[J.T @ J, K], [K.T, np.zeros((7, 7))]]))[:n, :n]
    s = out.info["similarity"]["scale"]
    nt = len(m.target_index)
    blocks = Q[m.n_reduced:, m.n_reduced:].reshape(nt, 3, nt, 3)[np.arange(nt), :, np.arange(nt), :]
    # traces: invariant under the similarity's rotation; lengths scale by s
    np.testing.assert_allclose(np.einsum("kii->k", out.cov_targets), np.einsum("kii->k", blocks) * s**2, rtol=1e-6)
    io = slice(0, m.n_int)
    np.testing.assert_allclose(out.cov_reduced[io, io], Q[io, io], rtol=1e-6, atol=0)


def test_a_survey_that_dominates_the_uncertainty_is_named_with_its_remedy(field):
    """Issue 26 goal 4: targets held fixed, four of them with a dummy survey sigma (545 mm, as
    PhotoModeler writes for points the user called unknown): f's sigma is then the survey's,
    not the geometry's, and the diagnosis says so, naming the targets and the remedies."""
    sf, _, _ = field
    t = sf.data.targets
    busiest = np.argsort(np.bincount(sf.data.obs.target, minlength=len(t)), kind="stable")[::-1][:4]
    sigma = t.sigma_mm.copy()
    sigma[busiest] = 545.0
    data = replace(sf.data, targets=replace(t, sigma_mm=sigma))
    with pytest.raises(GeometryError, match=r"survey of the fixed targets makes it so \(the image geometry alone "
                                        r"gives 0\.\d+ %\).*" + str(t.ids[busiest[0]]) +
                                        r".*sigma_mm 545.*adjust the targets.*realistic sigma_mm.*unsurveyed"):
        adjust_field(data, AdjustmentOptions(targets_adjusted=False))
    res = adjust_field(data)                    # the first remedy: the targets adjusted
    assert abs(res.params[INDEX["f_mm"]] - sf.camera.params[INDEX["f_mm"]]) < 4 * res.sigma["f_mm"]


def test_a_session_with_unsurveyed_targets_and_scale_bars_runs_through_the_pipeline(tmp_path, field):
    """prepare + solve of an observations-only session: 4 surveyed targets, the rest unlisted,
    a free network (session.json field.datum) scaled by scale_bars.csv; the document validates."""
    from fieldcal import pipeline
    from fieldcal.contract.schemas import validate_json

    sf, _, control = field
    folder = tmp_path / "free"
    write_field_session(folder, sf, images=False, observations_csv=True, coded=False)
    t = sf.data.targets
    rows = [f"{t.ids[j]},{t.xyz_m[j, 0]:.6f},{t.xyz_m[j, 1]:.6f},{t.xyz_m[j, 2]:.6f},5," for j in control]
    (folder / "targets.csv").write_text("id,X,Y,Z,sigma_mm,code\n" + "\n".join(rows) + "\n")
    Xt = sf.targets_true.xyz_m
    length = np.linalg.norm(Xt[control[1]] - Xt[control[0]]) * 1e3
    (folder / "scale_bars.csv").write_text(f"from_id,to_id,length_mm,sigma_mm\n{t.ids[control[0]]},"
                                           f"{t.ids[control[1]]},{length:.4f},0.02\n")
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["datum"] = "free"
    (folder / "session.json").write_text(json.dumps(manifest))
    prepared = pipeline.prepare(folder)
    assert "scale_bars.csv" in prepared.tables                  # in the inputs' fingerprint
    outcome = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
    doc = outcome.document
    validate_json(dict(doc, version="20261204T000000Z-0123abcd-0001"), "calibration", "document")   # version: at commit
    stats = doc["stats"]
    assert stats["datum"]["type"] == "free network" and stats["datum"]["scale"] == "1 scale bar(s)"
    assert stats["n_unlisted_targets"] > 200
    assert abs(doc["parameters"]["f_mm"] - sf.camera.f_mm) < 4 * doc["sigma"]["f_mm"]


def test_a_network_without_any_survey_starts_by_relative_orientation_and_is_scaled_by_two_bars(field, results):
    """Issue 26 goals 3 and 5: no target surveyed; the network starts from the relative
    orientation of a pair, is a free network, and two scale bars give it its scale."""
    sf, _, _ = field
    d = sf.data
    Xt = sf.targets_true.xyz_m
    busy = np.argsort(-np.bincount(d.obs.target, minlength=len(Xt)), kind="stable")
    a, b, c, e = busy[:4]
    bars = ScaleBars([a, c], [b, e], [np.linalg.norm(Xt[b] - Xt[a]) * 1e3, np.linalg.norm(Xt[e] - Xt[c]) * 1e3],
                     [0.02, 0.02])
    data = replace(d, targets=replace(d.targets, xyz_m=np.full_like(d.targets.xyz_m, np.nan)), scale_bars=bars)
    res = adjust_field(data)
    assert "relative orientation" in res.initial.how
    stats = res.stats()
    assert stats["datum"]["type"] == "free network" and stats["datum"]["scale"] == "2 scale bar(s)"
    ref = results["surveyed"]
    for name in CORE:
        j = INDEX[name]
        assert abs(res.params[j] - sf.camera.params[j]) < 4 * res.sigma[name], name
        assert res.sigma[name] == pytest.approx(ref.sigma[name], rel=0.05), name
    # the bars' scale: a distance no bar measures, against the truth (within 4 sigma + 0.05 mm)
    f, g = busy[4], busy[5]
    got = np.linalg.norm(res.targets_m[g] - res.targets_m[f])
    true = np.linalg.norm(Xt[g] - Xt[f])
    assert abs(got - true) < 4 * np.linalg.norm(res.sigma_targets_m[[f, g]]) + 0.05e-3
    with pytest.raises(GeometryError, match="no surveyed target and no nominal focal length"):
        adjust_field(replace(data, nominal_focal_mm=None))


def test_intersection_of_exact_rays_is_the_truth(field):
    """fieldcal.field.intersection on noise-free points through the true cameras."""
    from fieldcal.field.intersection import intersect_targets

    sf, _, _ = field
    data = replace(sf.data, obs=replace(sf.data.obs, uv_px=sf.uv_true_px))
    X, inlier = intersect_targets(data, sf.camera.params, sf.R_world_to_camera, sf.center_m,
                                  np.ones(len(data.obs), bool))
    placed = np.isfinite(X).all(axis=1)
    assert placed.sum() > 200
    np.testing.assert_allclose(X[placed], sf.targets_true.xyz_m[placed], atol=1e-7)   # 0.1 um: Newton's tolerance
    assert inlier[placed[data.obs.target]].all()


def test_dbat_sheet_with_four_control_points_is_datum_invariant():
    """The real DBAT sheet (PhotoModeler's marks): 1001-1004 surveyed (0.001 units), 96 targets
    unsurveyed; the free network scaled by one side gives the same camera; two sides are one
    length more, which the photographs agree with (not rejected)."""
    from tests.realdata import dbat_field_data

    pm = dbat_field_data()
    t = pm.targets
    corners = {"1001": (0, 1, 0), "1002": (1, 1, 0), "1003": (0, 0, 0), "1004": (1, 0, 0)}
    xyz = np.array([corners.get(str(i), (np.nan,) * 3) for i in t.ids], float)
    data = replace(pm, targets=replace(t, xyz_m=xyz, sigma_mm=np.where(np.isfinite(xyz[:, 0]), 1.0, t.sigma_mm)))
    k = data.targets.index()
    bars = ScaleBars([k["1001"], k["1003"]], [k["1002"], k["1001"]], [1000.0, 1000.0], [0.1, 0.1])
    control = adjust_field(data)
    one = ScaleBars(bars.from_target[:1], bars.to_target[:1], bars.length_mm[:1], bars.sigma_mm[:1])
    free = adjust_field(replace(data, scale_bars=one), AdjustmentOptions(datum="free"))
    two = adjust_field(replace(data, scale_bars=bars), AdjustmentOptions(datum="free"))
    assert control.stats()["n_unsurveyed_targets"] == 96
    for name in CORE:
        assert abs(control.params[INDEX[name]] - free.params[INDEX[name]]) < 0.05 * free.sigma[name], name
        assert control.sigma[name] == pytest.approx(free.sigma[name], rel=0.02), name
    assert control.sigma["f_mm"] < 0.002                  # mm: 0.6 px of 3.19 um
    assert two.stats()["datum"]["rejected_scale_bars"] == []
    for bar in two.stats()["datum"]["scale_bars"]:
        assert abs(bar["adjusted_mm"] - bar["length_mm"]) < 4 * np.hypot(bar["sigma_mm"], bar["sigma_adjusted_mm"])


def test_three_control_points_that_no_image_sees_four_of_start_by_relative_orientation(field):
    """No image sees four surveyed targets: the network starts from a pair's relative
    orientation, is moved onto the three surveyed targets, and they are its weighted datum."""
    sf, _, _ = field
    X = sf.data.targets.xyz_m
    control = [int(np.argmin(np.hypot(X[:, 0] - a, X[:, 2] - b))) for a, b in [(-1.5, 1.0), (1.5, 1.0), (0.0, 3.0)]]
    xyz = np.full_like(X, np.nan)
    xyz[control] = X[control]
    res = adjust_field(replace(sf.data, targets=replace(sf.data.targets, xyz_m=xyz)))
    assert "relative orientation" in res.initial.how and "moved onto 3 surveyed targets" in res.initial.how
    assert res.stats()["datum"] == {"type": "weighted control", "n_control": 3}
    for name in CORE:
        assert abs(res.params[INDEX[name]] - sf.camera.params[INDEX[name]]) < 4 * res.sigma[name], name
    # in the survey's frame: an unsurveyed target lies where the truth is, within the datum's few mm
    other = int(np.argmax(np.isfinite(res.sigma_targets_m).all(axis=1) & ~np.isin(np.arange(len(X)), control)))
    assert np.linalg.norm(res.targets_m[other] - sf.targets_true.xyz_m[other]) < 0.05
