"""Unsurveyed targets in rig sessions (issue 27, goal 2: "the targets, surveyed or not, as for one
camera"): targets with empty X, Y, Z and ids targets.csv does not list are estimated by the rig
adjustment (started where the heads alone placed them), the surveyed ones are the datum
(weighted control) with their own variance component, the survey factor; against exact
synthetic truth (fieldcal.synthetic.rig)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from fieldcal.errors import GeometryError, InputError
from fieldcal.lake.store import Lake
from fieldcal.model.rotations import rotvec_from_R
from fieldcal.rig import adjust_rig
from fieldcal.rig.adjustment import ARCSEC_PER_RAD
from fieldcal.rig_run import prepare_rig, run_rig
from fieldcal.synthetic.rig import two_head_rig, write_rig_session

CORE = ("f_mm", "xp_mm", "yp_mm")


def _z_relative(sr, res, h=1):
    st = res.state
    e_rot = rotvec_from_R(st.R_camera_to_rig[h] @ sr.R_camera_to_rig[h].T) * ARCSEC_PER_RAD
    e_t = (st.t_camera_in_rig_m[h] - sr.t_camera_in_rig_m[h]) * 1000.0
    return np.r_[e_rot / res.sigma_rotation_arcsec[h], e_t / res.sigma_t_mm[h]]


def _z_interior(sr, res):
    return np.array([(res.state.params[h][i] - cam.params[i]) / res.sigma[h][p]
                     for h, cam in enumerate(sr.cameras) for i, p in enumerate(CORE)])


def _without_survey(folder, blank, drop):
    """targets.csv of ``folder`` with the X, Y, Z of ids ``blank`` emptied and the rows of ``drop`` removed."""
    path = folder / "targets.csv"
    lines = path.read_text().splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        cells = line.split(",")
        if cells[0] in drop:
            continue
        if cells[0] in blank:
            cells[1:4] = ["", "", ""]
        out.append(",".join(cells))
    path.write_text("\n".join(out) + "\n")


@pytest.fixture(scope="module")
def unsurveyed_run(tmp_path_factory):
    """The two-head rig with a fifth of its targets' X, Y, Z left empty and a tenth not listed,
    through `run_rig` into a lake."""
    root = tmp_path_factory.mktemp("riguns")
    sr = two_head_rig(seed=5)
    folder = write_rig_session(root / "bar2-u1", sr)
    ids = np.asarray(sr.data.targets.ids).astype(str)
    pick = np.random.default_rng(5).permutation(len(ids))
    blank, drop = set(ids[pick[: len(ids) // 5]]), set(ids[pick[len(ids) // 5: len(ids) // 5 + len(ids) // 10]])
    _without_survey(folder, blank, drop)
    prepared = prepare_rig(folder)
    lake = Lake(root / "lake")
    version, heads, outcome = run_rig(folder, lake, prepared=prepared)
    return sr, prepared, outcome.result, lake, version, heads, blank, drop


def test_a_rig_with_unsurveyed_and_unlisted_targets_is_calibrated_within_its_sigmas(unsurveyed_run):
    sr, prepared, res, _, _, _, blank, drop = unsurveyed_run
    z_rel, z_int = _z_relative(sr, res), _z_interior(sr, res)
    assert np.all(np.abs(z_rel) < 4.0) and np.all(np.abs(z_int) < 4.0), (z_rel, z_int)   # one fixed-seed draw
    assert np.sqrt(np.mean(np.r_[z_rel, z_int] ** 2)) < 2.0
    st = res.stats()
    t = res.data.targets
    ids = np.asarray(t.ids).astype(str)
    observed = {str(sr.data.targets.ids[j]) for d in sr.data.head_data for j in np.unique(d.obs.target)}
    unlisted = sorted(drop & observed)
    assert sorted(st["unlisted_targets"]) == unlisted and st["n_unlisted_targets"] == len(unlisted)
    estimated = {u["id"]: u for u in st["unsurveyed_targets"]}
    assert set(estimated) <= blank | drop and len(estimated) >= 0.9 * len((blank | drop) & observed)
    truth = {str(i): x for i, x in zip(np.asarray(sr.targets_true.ids).astype(str), sr.targets_true.xyz_m,
                                       strict=True)}
    z = np.array([(np.array(u["xyz_m"]) - truth[k]) * 1000.0 / np.array(u["sigma_mm"]) for k, u in estimated.items()])
    assert np.all(np.abs(z) < 4.5) and 0.6 < np.sqrt(np.mean(z**2)) < 1.4      # ~200 coordinates
    surveyed = t.surveyed[np.concatenate([d.obs.target for d in res.data.head_data])]
    n_uns_points = int((~surveyed).sum())
    assert n_uns_points > 0.2 * len(surveyed)                               # the unsurveyed carry many points
    used_uns = sum(int((u & ~t.surveyed[d.obs.target]).sum()) for d, u in zip(res.data.head_data, res.obs_used,
                                                                                 strict=True))
    assert used_uns > 0.95 * n_uns_points
    assert {"survey_factor", "survey_redundancy"} <= set(st["variance_components"])
    assert all(k not in ids[t.surveyed] for k in estimated)


def test_the_heads_documents_list_their_unsurveyed_targets(unsurveyed_run):
    _, _, res, lake, version, heads, _, drop = unsurveyed_run
    rig = lake.load_rig_document(version)
    assert rig["stats"]["n_unsurveyed_targets"] == res.stats()["n_unsurveyed_targets"]
    for h, v in enumerate(heads):
        doc = lake.load_document(v)
        ids = {u["id"] for u in doc["stats"]["unsurveyed_targets"]}
        seen = {str(res.data.targets.ids[j]) for j in res.data.head_data[h].obs.target[res.obs_used[h]]}
        assert ids == {i for i in seen if not res.data.targets.surveyed[list(res.data.targets.ids).index(i)]}
        assert doc["stats"]["unlisted_targets"] == rig["stats"]["unlisted_targets"] and len(drop) > 10


def test_the_survey_factor_of_a_survey_3x_worse_than_stated_is_near_3():
    sr = two_head_rig(seed=13, survey_noise_mm=6.0)
    t = replace(sr.data.targets, sigma_mm=np.full(len(sr.data.targets), 2.0))    # stated 2 mm, drawn 6 mm
    data = replace(sr.data, head_data=[replace(d, targets=t) for d in sr.data.head_data])
    res = adjust_rig(data)
    vc = res.stats()["variance_components"]
    # band: the factor's sampling error ~1/sqrt(2 r) (r ~ 600: 3 %) plus the linearised redundancies
    assert vc["survey_redundancy"] > 300
    assert 2.6 < vc["survey_factor"] < 3.4
    assert all(0.85 < h["image_factor"] < 1.15 for h in vc["heads"].values())
    z = np.r_[_z_relative(sr, res), _z_interior(sr, res)]
    assert np.all(np.abs(z) < 4.0) and np.sqrt(np.mean(z**2)) < 2.0


def test_a_rig_needs_surveyed_control_and_adjusted_unsurveyed_targets():
    sr = two_head_rig(seed=5)
    t = sr.data.targets
    xyz = np.full_like(t.xyz_m, np.nan)
    xyz[:3] = t.xyz_m[:3]                                    # 3 surveyed targets: fewer than the datum needs
    few = replace(sr.data, head_data=[replace(d, targets=replace(t, xyz_m=xyz)) for d in sr.data.head_data])
    with pytest.raises((GeometryError, InputError), match="surveyed"):
        adjust_rig(few)
    xyz = t.xyz_m.copy()
    xyz[5] = np.nan
    one = replace(sr.data, head_data=[replace(d, targets=replace(t, xyz_m=xyz)) for d in sr.data.head_data])
    from fieldcal.rig.adjustment import RigOptions

    with pytest.raises(InputError, match="cannot be held fixed"):
        adjust_rig(one, RigOptions(targets_adjusted=False))


def test_a_strict_rig_session_refuses_unlisted_ids_and_free_datum_and_scale_bars_are_single_camera_only(tmp_path):
    sr = two_head_rig(seed=5)
    folder = write_rig_session(tmp_path / "bar2-s", sr)
    _without_survey(folder, set(), {str(sr.data.targets.ids[0])})
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["strict_targets"] = True
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=str(sr.data.targets.ids[0])):
        prepare_rig(folder)
    manifest["field"].pop("strict_targets")
    manifest["field"]["datum"] = "free"
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="single cameras only"):
        prepare_rig(folder)
    manifest["field"].pop("datum")
    (folder / "session.json").write_text(json.dumps(manifest))
    (folder / "scale_bars.csv").write_text("a,b,length_m,sigma_mm\n")
    with pytest.raises(InputError, match="scale bars"):
        prepare_rig(folder)
