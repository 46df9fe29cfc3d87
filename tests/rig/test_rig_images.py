"""A rig session from rendered images (no observations.csv): every head measured and identified
as a single camera is; the images of a head that show no code (it cannot start them alone) are
started from the rig's other heads; the rig's relative orientation and the heads' principal
distances against the renderer's truth; `fieldcal run` commits it as one version of the rig."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fieldcal import rig_run
from fieldcal.lake.store import Lake
from fieldcal.model.rotations import rotvec_from_R
from fieldcal.rig.from_images import REASON_FROM_RIG
from fieldcal.synthetic.rig import two_head_rig, write_rig_image_session
from flows import cli

EXPOSURES = range(0, 24, 3)          # 8 exposures, 16 images of 1200 x 800 and 1000 x 700 px
PLAIN = [(1, 3), (1, 9)]             # the right head's images of E004 and E010 show no code
ARCSEC_PER_RAD = 180 * 3600 / np.pi


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    sr = two_head_rig(seed=7)
    info = write_rig_image_session(tmp_path_factory.mktemp("rigimg") / "bar2-img", sr, scale=0.2,
                                   exposures=EXPOSURES, plain=PLAIN, seed=3)
    return sr, info


@pytest.fixture(scope="module")
def solved(session):
    sr, info = session
    prepared = rig_run.prepare_rig(info["folder"])
    assert prepared.data is None and len(prepared.to_measure) == 16
    rig_run.measure_rig(prepared, target_normals=sr.targets_true.normals)   # the eccentricity correction
    return prepared, rig_run.solve_rig(prepared)


def test_images_a_head_cannot_start_alone_are_started_from_the_rig(session, solved):
    sr, info = session
    prepared, outcome = solved
    report = {r["image"]: r for r in prepared.report}
    plain = {f"images/{sr.data.exposures[e]}_right.tif" for _, e in PLAIN}
    assert {n for n, r in report.items() if r["started_from"] == REASON_FROM_RIG} == plain
    assert all(r["status"] == "ok" for r in report.values())
    right = prepared.data.head_data[1]
    fld = info["scaled"][1]                     # the truth of the scaled right head
    files = [im.file for im in fld.data.images]
    for name in plain:                          # identified right: every point on its true target's image
        i = [im.file for im in right.images].index(name)
        k = right.obs.image == i
        j = files.index(name)
        true_uv = fld.camera.project(sr.targets_true.xyz_m[right.obs.target[k]], fld.R_world_to_camera[j],
                                     fld.center_m[j])
        assert k.sum() >= 50 and np.max(np.linalg.norm(right.obs.uv_px[k] - true_uv, axis=1)) < 0.5
        used = outcome.result.obs_used[1][k]
        assert used.mean() > 0.9                # and they are used by the rig adjustment


def test_the_rig_from_images_against_the_truth(session, solved):
    sr, _ = session
    res = solved[1].result
    d_rot = rotvec_from_R(res.state.R_camera_to_rig[1] @ sr.R_camera_to_rig[1].T) * ARCSEC_PER_RAD
    assert np.all(np.abs(d_rot) < 3 * res.sigma_rotation_arcsec[1]), (d_rot, res.sigma_rotation_arcsec[1])
    d_t_mm = 1000 * (res.state.t_camera_in_rig_m[1] - sr.t_camera_in_rig_m[1])
    assert np.all(np.abs(d_t_mm) < 3 * res.sigma_t_mm[1]), (d_t_mm, res.sigma_t_mm[1])
    assert 0.8 < res.sigma0 < 1.5
    for h, cam in enumerate(sr.cameras):
        assert abs(res.state.params[h][0] - cam.f_mm) < 3 * res.sigma[h]["f_mm"]


def test_fieldcal_run_commits_a_rig_session_of_images(session, tmp_path, capsys):
    _, info = session
    lake = tmp_path / "lake"
    out_json = tmp_path / "rig.json"
    assert cli.main(["run", info["folder"], "--lake", str(lake), "--json", str(out_json)]) == 0
    version = capsys.readouterr().out.strip()
    doc = json.loads(out_json.read_text())
    assert doc["version"] == version and doc["stats"]["n_images"] == 16 and doc["stats"]["n_exposures"] == 8
    heads = [Lake(lake).load_document(h["version"]) for h in doc["heads"]]
    assert [len(h["images"]) for h in heads] == [8, 8] and all(h["rig"]["rig_id"] == "bar2" for h in heads)


def test_a_rig_session_of_images_with_an_unsurveyed_target_is_refused(session, tmp_path):
    import shutil

    from fieldcal.errors import InputError

    folder = tmp_path / "bar2-unsurveyed"
    shutil.copytree(session[1]["folder"], folder)
    rows = (folder / "targets.csv").read_text().splitlines()
    first = rows[1].split(",")
    rows[1] = ",".join([first[0], "", "", ""] + first[4:])        # its coordinates not surveyed
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match=rf"1 unsurveyed target\(s\) \({first[0]}\): a rig session of images needs"):
        rig_run.prepare_rig(folder)
