"""Scale bars as observations of the adjustment (issue 26; CONTRACT section 3; fieldcal.field.scale_bars).

Truth: the synthetic wide-angle field (fieldcal.synthetic.field.wide_field, seed 3), four
control points near the wall's middle, the other targets unsurveyed, as in test_unsurveyed.py.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.special import chdtri

from fieldcal.field.adjustment import AdjustmentOptions, FieldProblem, adjust_field
from fieldcal.field.bundle import BundleModel
from fieldcal.field.scale_bars import BarObservations, bar_ends, usable
from fieldcal.model.camera import INDEX
from fieldcal.session.data import ScaleBars
from fieldcal.synthetic.field import wide_field, with_control_points

CORE = ("f_mm", "xp_mm", "yp_mm", "k1")


@pytest.fixture(scope="module")
def field():
    sf = wide_field(seed=3)
    data, control = with_control_points(sf)
    return sf, data, control


def _bars(sf, pairs, error_mm=None, sigma_mm=0.02):
    Xt = sf.targets_true.xyz_m
    a, b = np.array(pairs).T
    length = np.linalg.norm(Xt[b] - Xt[a], axis=1) * 1e3
    if error_mm is not None:
        length = length + np.asarray(error_mm)
    return ScaleBars(a, b, length, np.full(len(a), sigma_mm))


@pytest.fixture(scope="module")
def results(field):
    sf, data, c = field
    free = AdjustmentOptions(datum="free")
    two = _bars(sf, [(c[0], c[1]), (c[2], c[3])])
    return {"free": adjust_field(data, free),
            "free, 1 bar": adjust_field(replace(data, scale_bars=_bars(sf, [(c[0], c[1])])), free),
            "free, 2 bars": adjust_field(replace(data, scale_bars=two), free),
            "control, 2 bars": adjust_field(replace(data, scale_bars=two)),
            "control": adjust_field(data)}


def test_jacobian_with_bar_ends_carried_as_global_targets_matches_central_differences(field):
    """The whole problem's Jacobian (image points of bar ends and others, surveys, bar rows) at a
    perturbed point, against central differences, column by column."""
    sf, data, c = field
    data = replace(sf.data, scale_bars=_bars(sf, [(c[0], c[1]), (c[1], c[3])]))
    seen = np.zeros(len(data.targets), bool)
    seen[data.obs.target] = True
    active = np.ones(2, bool)
    model = BundleModel(data, sf.camera.params, ("f_mm", "xp_mm", "yp_mm", "k1", "p1"), sf.R_world_to_camera,
                        global_targets=bar_ends(data.scale_bars, active, seen))
    assert model.n_global == 3 and set(model.target_index[:3]) == {c[0], c[1], c[3]}
    bars = BarObservations(data.scale_bars, usable(data.scale_bars, active, seen), model)
    problem = FieldProblem(model, bars=bars)
    rng = np.random.default_rng(0)
    x = model.pack(sf.camera.params, sf.center_m, sf.targets_true.xyz_m)
    x = x + rng.normal(0, 1e-4, len(x)) * np.maximum(np.abs(x), 1e-3)
    r, J = problem.evaluate(x, True)
    assert J.shape == (model.n_rows + 2, model.n_params) and len(r) == J.shape[0]
    assert problem.n_dense == model.n_reduced + 9               # the bar ends are dense unknowns
    Jd = J.to_csr()
    nr = model.n_reduced
    cols = np.concatenate([np.arange(model.n_int), model.n_int + np.arange(12), nr + np.arange(9),
                           nr + 9 + rng.choice(model.n_params - nr - 9, 12, replace=False)])
    for j in cols:
        h = 1e-6 * max(abs(x[j]), 1e-3)
        e = np.zeros(len(x))
        e[j] = h
        num = (problem.evaluate(x + e, False)[0] - problem.evaluate(x - e, False)[0]) / (2 * h)
        ana = Jd[:, j].toarray().ravel()
        assert np.abs(num - ana).max() <= 1e-5 * max(np.abs(ana).max(), 1.0), j
    # the bar rows: measured minus adjusted over sigma
    Xs = x[nr:].reshape(-1, 3)
    d = np.linalg.norm(Xs[model.t_slot[c[1]]] - Xs[model.t_slot[c[0]]]) * 1e3
    assert r[model.n_rows] == pytest.approx((data.scale_bars.length_mm[0] - d) / 0.02, rel=1e-12)


def test_one_bar_is_a_minimal_scale_two_bars_are_observations_that_reshape_the_network(results):
    one, two = results["free, 1 bar"].stats()["datum"], results["free, 2 bars"].stats()["datum"]
    b1 = one["scale_bars"][0]
    assert b1["redundancy"] < 1e-6 and abs(b1["residual_mm"]) < 1e-6          # no redundancy: fits exactly
    red = [b["redundancy"] for b in two["scale_bars"]]
    # one length more: its redundancy is shared with the image points, which hold the network's
    # shape to about the bars' 0.02 mm here (bars far weaker than the shape: test below)
    assert 0.05 < sum(red) < 0.95 and all(0 < r < 1 for r in red)
    assert all(abs(b["residual_mm"]) > 1e-5 for b in two["scale_bars"])    # not fitted exactly any more
    assert all(b["normalized_residual"] < 3.3 for b in two["scale_bars"])
    # reshaped: the 2-bar network is not a similarity of the 1-bar one
    X1, X2 = results["free, 1 bar"].targets_m, results["free, 2 bars"].targets_m
    ok = np.isfinite(X1).all(axis=1) & np.isfinite(X2).all(axis=1)
    P, Q = X1[ok], X2[ok]
    mp, mq = P.mean(0), Q.mean(0)
    U, s, Vt = np.linalg.svd((Q - mq).T @ (P - mp))
    R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    k = np.sum(s * [1, 1, np.sign(np.linalg.det(U @ Vt))]) / np.sum((P - mp) ** 2)
    assert np.abs(k * (P - mp) @ R.T + mq - Q).max() > 1e-8           # m: more than round-off


def test_two_weak_bars_share_their_one_redundancy(field):
    """Bars of 2 mm, far weaker than the images' shape: the network fixes their ratio, each bar's
    redundancy is then the share of the scale it does not determine, summing to one."""
    sf, data, c = field
    res = adjust_field(replace(data, scale_bars=_bars(sf, [(c[0], c[1]), (c[2], c[3])], sigma_mm=2.0)),
                       AdjustmentOptions(datum="free"))
    red = [b["redundancy"] for b in res.stats()["datum"]["scale_bars"]]
    assert sum(red) == pytest.approx(1.0, abs=0.02) and all(0.3 < r < 0.7 for r in red)


def test_interior_orientation_is_datum_invariant_with_bars_in_the_adjustment(results):
    free = results["free"]
    for name in CORE:
        j = INDEX[name]
        one = results["free, 1 bar"]
        # one bar: a minimal scale, the same image points; another solve, which stops within
        # sigma_tol (1e-3) of a sigma of the optimum
        assert abs(one.params[j] - free.params[j]) < AdjustmentOptions().sigma_tol * free.sigma[name], name
        assert one.sigma[name] == pytest.approx(free.sigma[name], rel=1e-6), name
        # two bars: one length more, information on the shape: the unit-weight sigma can only
        # shrink, and the estimate moves by about the information gained, sqrt(s_before^2 - s_after^2)
        for before, after in (("free", "free, 2 bars"), ("control", "control, 2 bars")):
            b, a = results[before], results[after]
            unit_b, unit_a = b.sigma[name] / b.sigma0, a.sigma[name] / a.sigma0
            assert unit_a <= unit_b * (1 + 1e-9), (after, name)
            gained = np.sqrt(max(b.sigma[name] ** 2 - (unit_a * b.sigma0) ** 2, 0.0))
            assert abs(a.params[j] - b.params[j]) < 4 * gained + 1e-3 * b.sigma[name], (after, name)
    stats = results["control, 2 bars"].stats()["datum"]
    assert stats["type"] == "weighted control" and len(stats["scale_bars"]) == 2


def test_a_bar_with_a_wrong_length_shows_in_its_residual_and_is_rejected(field, results):
    sf, data, c = field
    free = AdjustmentOptions(datum="free")
    # two bars, one 1 mm long: both test statistics show it, neither is rejected (two lengths
    # cannot tell which one is wrong)
    res2 = adjust_field(replace(data, scale_bars=_bars(sf, [(c[0], c[1]), (c[2], c[3])], [1.0, 0.0])), free)
    rows = res2.stats()["datum"]["scale_bars"]
    assert len(rows) == 2 and res2.stats()["datum"]["rejected_scale_bars"] == []
    limit = np.sqrt(chdtri(1, AdjustmentOptions().snoop_alpha))
    assert all(r["normalized_residual"] > 2 * limit for r in rows)
    assert rows[0]["residual_mm"] > 0 > rows[1]["residual_mm"]       # the first too long, the second too short
    # three bars, the first 1 mm long: rejected by data snooping, the other two scale the network
    pairs = [(c[0], c[1]), (c[2], c[3]), (c[0], c[3])]
    res3 = adjust_field(replace(data, scale_bars=_bars(sf, pairs, [1.0, 0.0, 0.0])), free)
    d = res3.stats()["datum"]
    ids = sf.data.targets.ids
    assert d["rejected_scale_bars"] == [f"{ids[c[0]]}-{ids[c[1]]}"]
    assert len(d["scale_bars"]) == 2 and d["scale"] == "2 scale bar(s)"
    Xt = sf.targets_true.xyz_m
    true = np.linalg.norm(Xt[c[1]] - Xt[c[0]])
    got = np.linalg.norm(res3.targets_m[c[1]] - res3.targets_m[c[0]])
    assert abs(got - true) < 0.1e-3          # m: the rejected bar's length is the images' and the others'
    for name in CORE:
        j = INDEX[name]
        ref = results["free"]
        assert abs(res3.params[j] - ref.params[j]) < 0.05 * ref.sigma[name], name
