"""`fieldcal run` on a rig session commits one version of the rig (a calibration version per
head and the rig document, one catalog transaction); `fieldcal compare RIG_V1 RIG_V2` tests
the relative orientations: a boresight moved by 20 arc-seconds is flagged, an unchanged rig not."""

from __future__ import annotations

import json

import pytest

from fieldcal.contract.schemas import validate_json
from fieldcal.lake.store import Lake
from fieldcal.synthetic.rig import two_head_rig, write_rig_session
from flows import cli

NOISE_PX = 0.05      # sigma of a rotation change ~2.6 arcsec about x: 20 arcsec is ~8 sigma


def _run(capsys, *argv) -> tuple[int, str, str]:
    status = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.fixture(scope="module")
def rig_lake(tmp_path_factory):
    root = tmp_path_factory.mktemp("riglake")
    sessions = {"s1": two_head_rig(seed=11, image_noise_px=NOISE_PX),
                "s2": two_head_rig(seed=12, image_noise_px=NOISE_PX),
                "moved": two_head_rig(seed=13, image_noise_px=NOISE_PX, head_rotation_arcsec=(20.0, 0.0, 0.0))}
    folders = {k: write_rig_session(root / f"bar2-{k}", sr) for k, sr in sessions.items()}
    return root / "lake", folders


def test_run_commits_a_rig_version_with_a_calibration_per_head(rig_lake, capsys, tmp_path):
    lake_path, folders = rig_lake
    out_json = tmp_path / "rig.json"
    status, out, err = _run(capsys, "run", folders["s1"], "--lake", lake_path, "--json", out_json)
    assert status == 0, err
    version = out.strip()
    doc = json.loads(out_json.read_text())
    validate_json(doc, "rig", "test")
    assert doc["version"] == version and doc["schema"] == "fieldcal.rig/1" and doc["reference"] == "bar2-left"
    assert [h["camera_id"] for h in doc["heads"]] == ["bar2-left", "bar2-right"]
    assert doc["heads"][0]["sigma_rotation_arcsec"] == [0.0, 0.0, 0.0]
    names = doc["covariance"]["names"]
    assert names[0] == "bar2-right:rot_x_arcsec" and names[5] == "bar2-right:t_z_mm" and len(names) == 6
    assert doc["stats"]["n_exposures"] == 24
    lake = Lake(lake_path)
    cat = lake.catalog()
    assert sorted(cat["version"].to_pylist()) == sorted(h["version"] for h in doc["heads"])
    for h in doc["heads"]:                 # ordinary calibration documents of the heads' cameras
        head = lake.load_document(h["version"])
        validate_json(head, "calibration", "test")
        assert head["camera_id"] == h["camera_id"] and head["rig"]["rig_id"] == "bar2"
        assert len(head["images"]) == 24 and lake.read_residuals(h["version"]).num_rows > 3000
    # the same inputs again: the same rig version, nothing new in the lake
    status, again, _ = _run(capsys, "run", folders["s1"], "--lake", lake_path)
    assert status == 0 and again == out and Lake(lake_path).catalog().num_rows == 2


def _compare(capsys, lake_path, folders, a, b) -> dict:
    versions = []
    for k in (a, b):
        status, out, err = _run(capsys, "run", folders[k], "--lake", lake_path)
        assert status == 0, err
        versions.append(out.strip())
    status, out, err = _run(capsys, "compare", *versions, "--lake", lake_path, "--format", "json")
    assert status == 0, err
    return json.loads(out)


def test_compare_does_not_flag_an_unchanged_rig(rig_lake, capsys):
    c = _compare(capsys, *rig_lake, "s1", "s2")
    assert c["kind"] == "rig" and not c["significant"] and not c["flagged"]
    (head,) = c["heads"]
    assert head["camera_id"] == "bar2-right" and head["rotation_change_angle_arcsec"] < 10.0


def test_compare_flags_a_boresight_moved_by_20_arcsec(rig_lake, capsys):
    c = _compare(capsys, *rig_lake, "s1", "moved")
    assert c["significant"] and c["flagged"] and c["changed"] == ["bar2-right"]
    (head,) = c["heads"]
    assert abs(head["rotation_change_arcsec"][0] - 20.0) < 4 * head["sigma_rotation_change_arcsec"][0]
    assert head["q_rotation"] < 0.01 and head["q_lever_arm"] > 0.01


def test_a_bad_rig_session_is_one_line_exit_2_and_nothing_written(rig_lake, capsys, tmp_path):
    _, folders = rig_lake
    bad = tmp_path / "bad"
    bad.mkdir()
    for name in ("targets.csv", "observations.csv"):
        (bad / name).write_bytes((folders["s1"] / name).read_bytes())
    m = json.loads((folders["s1"] / "session.json").read_text())
    m["rig"]["reference"] = "bar2-middle"
    (bad / "session.json").write_text(json.dumps(m))
    status, out, err = _run(capsys, "run", bad, "--lake", tmp_path / "lake")
    assert status == 2 and out == "" and err.count("\n") == 1
    assert "session.json" in err and "reference 'bar2-middle'" in err
    assert not (tmp_path / "lake").exists()
