"""A rig in the lake's history and products: `fieldcal history --rig` (the relative orientations
over time, their sigmas and changes, from the rigs table and the rig documents), the rig in a
head's report and certificate, `gc` of a rig document an interrupted commit left, and
`fieldcal lake check` of the rig versions."""

from __future__ import annotations

import datetime as dt
import json
import os

import numpy as np
import pytest

from fieldcal.lake.gc import gc
from fieldcal.lake.ids import new_version
from fieldcal.lake.store import Lake
from fieldcal.model.rotations import opk_from_R_world_to_camera
from fieldcal.synthetic.rig import two_head_rig, write_rig_session
from flows import cli

NOISE_PX = 0.05      # sigma of the rotation about x ~1.8 arcsec per session: 20 arcsec is ~8 sigma of a change
MOVED_ARCSEC = 20.0


def _run(capsys, *argv) -> tuple[int, str, str]:
    status = cli.main([str(a) for a in argv])
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.fixture(scope="module")
def rig_lake(tmp_path_factory):
    """Two sessions of the bar2 rig, the second with the right head's boresight turned by
    20 arcsec about the rig's x axis, committed in this order (acquired a day apart)."""
    root = tmp_path_factory.mktemp("righist")
    lake_path = root / "lake"
    truths, versions = [], []
    for k, (seed, moved) in enumerate(((21, 0.0), (22, MOVED_ARCSEC))):
        sr = two_head_rig(seed=seed, image_noise_px=NOISE_PX, head_rotation_arcsec=(moved, 0.0, 0.0))
        folder = write_rig_session(root / f"bar2-s{k + 1}", sr, acquired=f"2026-11-{20 + k}T09:00:00Z")
        status = cli.main(["run", str(folder), "--lake", str(lake_path)])
        assert status == 0
        truths.append(sr)
    lake = Lake(lake_path)
    versions = lake.rig_catalog(rig_id="bar2")["version"].to_pylist()
    return lake_path, truths, versions


def test_history_of_a_rig_shows_each_heads_relative_orientation_and_its_change(rig_lake, capsys):
    lake_path, truths, versions = rig_lake
    status, out, err = _run(capsys, "history", "--lake", lake_path, "--rig", "bar2", "--format", "json")
    assert status == 0, err
    rows = json.loads(out)
    assert [r["version"] for r in rows] == versions and [r["camera_id"] for r in rows] == ["bar2-right"] * 2
    assert [r["session_id"] for r in rows] == ["bar2-s1", "bar2-s2"]
    first, second = rows
    assert [first[f"delta_rot_{c}_arcsec"] for c in "xyz"] == [0.0, 0.0, 0.0]
    sig = np.hypot([first[f"sigma_rot_{c}_arcsec"] for c in "xyz"], [second[f"sigma_rot_{c}_arcsec"] for c in "xyz"])
    d = np.array([second[f"delta_rot_{c}_arcsec"] for c in "xyz"])
    assert np.all(np.abs(d - [MOVED_ARCSEC, 0.0, 0.0]) < 4 * sig)       # the moved boresight, within 4 sigma
    assert 0.2 < sig[0] < 5.0
    for r, sr in zip(rows, truths, strict=True):                        # against the truth
        t_mm = np.array([r[f"t_{c}_mm"] for c in "xyz"])
        s_t = np.array([r[f"sigma_t_{c}_mm"] for c in "xyz"])
        assert np.all(np.abs(t_mm - 1000 * sr.t_camera_in_rig_m[1]) < 4 * s_t)
        opk = np.degrees(opk_from_R_world_to_camera(sr.R_camera_to_rig[1].T))
        assert np.allclose([r["omega_deg"], r["phi_deg"], r["kappa_deg"]], opk, atol=20 / 3600)
    status, text, _ = _run(capsys, "history", "--lake", lake_path, "--rig", "bar2")
    assert status == 0 and text.splitlines()[0].split() == [
        "session_id", "acquired", "camera_id", "delta_rot_x_arcsec", "delta_rot_y_arcsec", "delta_rot_z_arcsec",
        "delta_t_x_mm", "delta_t_y_mm", "delta_t_z_mm"]


def test_history_of_an_unknown_rig_is_one_line_exit_2(rig_lake, capsys):
    status, out, err = _run(capsys, "history", "--lake", rig_lake[0], "--rig", "bar3")
    assert status == 2 and out == "" and err.count("\n") == 1 and "'bar3'" in err and "bar2" in err
    status, _, err = _run(capsys, "history", "--lake", rig_lake[0], "--rig", "bar2", "--camera", "bar2-left")
    assert status == 2 and "--rig cannot be combined" in err


def test_the_rigs_table_is_a_history_view(rig_lake, capsys):
    status, out, err = _run(capsys, "history", "--lake", rig_lake[0], "--format", "json", "--sql",
                            "SELECT rig_id, version, head_versions FROM rigs ORDER BY committed")
    assert status == 0, err
    rows = json.loads(out)
    assert [r["version"] for r in rows] == rig_lake[2] and all(len(r["head_versions"]) == 2 for r in rows)


def test_a_heads_report_and_certificate_show_its_rig(rig_lake, capsys, tmp_path):
    lake_path, _, versions = rig_lake
    lake = Lake(lake_path)
    rig = lake.load_rig_document(versions[1])
    right = rig["heads"][1]
    for command, name in (("report", "report.html"), ("certificate", "certificate.html")):
        out_dir = tmp_path / command
        status, _, err = _run(capsys, command, right["version"], "--lake", lake_path, "--out", out_dir)
        assert status == 0, err
        page = (out_dir / name).read_text()
        assert "bar2" in page and versions[1] in page and rig["heads"][0]["version"] in page
        assert f"{right['sigma_rotation_arcsec'][0]:.2g}" in page or f"{right['sigma_rotation_arcsec'][0]:.2f}" in page
        assert f"{1000 * right['t_camera_in_rig_m'][0]:.2f}" in page


def test_a_single_cameras_report_has_no_rig(rig_lake):
    lake = Lake(rig_lake[0])
    assert lake.rig_of({"camera_id": "x", "version": "v"}) is None
    assert lake.rig_of({"camera_id": "x", "version": "v", "rig": {"rig_id": "bar2"}}) is None


def test_gc_removes_an_orphaned_rig_document_and_keeps_committed_ones(rig_lake, tmp_path):
    import shutil

    lake_path, _, versions = rig_lake
    copy = tmp_path / "lake"
    shutil.copytree(lake_path, copy)
    lake = Lake(copy)
    doc = lake.load_rig_document(versions[0])
    old = new_version(doc["inputs"]["fingerprint"], dt.datetime(2026, 1, 1, tzinfo=dt.UTC))
    recent = new_version(doc["inputs"]["fingerprint"])
    for v in (old, recent):                  # a crash between the rig document and its rigs row
        rel = lake.rig_path("bar2", doc["session_id"], v)
        (copy / rel).write_text(json.dumps(dict(doc, version=v)))
    orphan = lake.rig_path("bar2", doc["session_id"], old)
    two_days_ago = dt.datetime.now(dt.UTC).timestamp() - 2 * 86400   # gc goes by the files' times (issue 24)
    os.utime(copy / orphan, (two_days_ago, two_days_ago))
    assert gc(lake, dry_run=True) == [orphan] and (copy / orphan).exists()
    assert gc(lake) == [orphan]
    assert not (copy / orphan).exists() and (copy / lake.rig_path("bar2", doc["session_id"], recent)).exists()
    for v in versions:                       # committed rig documents stay
        assert lake.load_rig_document(v)["version"] == v


def test_lake_check_reports_a_missing_or_wrong_rig_document(rig_lake, capsys, tmp_path):
    import shutil

    lake_path, _, versions = rig_lake
    status, out, err = _run(capsys, "lake", "check", "--lake", lake_path)
    assert status == 0, out + err
    copy = tmp_path / "lake"
    shutil.copytree(lake_path, copy)
    row = Lake(copy).rig_catalog().to_pylist()
    (copy / row[0]["document_path"]).unlink()
    doc = json.loads((copy / row[1]["document_path"]).read_text())
    doc["heads"][1]["version"] = doc["heads"][0]["version"]
    (copy / row[1]["document_path"]).write_text(json.dumps(doc))
    status, out, err = _run(capsys, "lake", "check", "--lake", copy)
    assert status == 1
    text = out + err
    assert f"{row[0]['document_path']}: missing" in text and f"rig version {versions[0]}" in text
    assert f"{row[1]['document_path']}: its heads' versions differ" in text
