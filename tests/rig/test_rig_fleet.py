"""`fieldcal fleet` calibrates a rig session among single-camera sessions like any other: one
version of the rig (its heads' calibrations and the rig document), the summary listing the
heads with their versions; the next night the rig is "calibrated already" with the same
versions."""

from __future__ import annotations

import json

import pytest

from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.rig import two_head_rig, write_rig_session
from fieldcal.synthetic.session_writer import write_field_session
from flows import cli, server

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture
def root(tmp_path):
    """A single-camera observation-only session and a two-head rig session."""
    root = tmp_path / "sessions"
    write_field_session(root / "cam-w0" / "2026-05-01", wide_field(seed=20), images=False, observations_csv=True,
                        camera_id="cam-w0", acquired="2026-05-01")
    write_rig_session(root / "bar2" / "bar2-s1", two_head_rig(seed=31, image_noise_px=0.05), acquired="2026-05-02")
    return root


def test_fleet_calibrates_a_rig_session_and_lists_its_heads(root, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(server, "quiet_prefect", lambda verbose: None)
    lake_path = tmp_path / "lake"
    assert cli.main(["fleet", str(root), "--lake", str(lake_path), "--workers", "1", "--format", "json"]) == 0
    first = json.loads(capsys.readouterr().out)
    by = {s["camera_id"]: s for s in first["sessions"]}
    assert set(by) == {"cam-w0", "bar2"} and all(s["status"] == "committed" for s in by.values()), by
    assert (first["n_found"], first["n_committed"], first["n_failed"]) == (2, 2, 0)
    rig, single = by["bar2"], by["cam-w0"]
    assert rig["rig"] and not single["rig"] and single["heads"] is None
    lake = Lake(lake_path)
    (row,) = lake.rig_catalog(rig_id="bar2").to_pylist()
    assert rig["version"] == row["version"] and rig["session_id"] == "bar2-s1" and rig["n_images"] == 48
    assert rig["heads"] == [{"camera_id": c, "version": v} for c, v in zip(row["camera_ids"], row["head_versions"],
                                                                          strict=True)]
    assert [h["camera_id"] for h in rig["heads"]] == ["bar2-left", "bar2-right"]
    catalog = set(lake.catalog()["version"].to_pylist())
    assert {single["version"], *row["head_versions"]} == catalog
    assert [h["version"] for h in lake.load_rig_document(row["version"])["heads"]] == row["head_versions"]

    # the next night: nothing to do; the table lists the rig's heads under it
    assert cli.main(["fleet", str(root), "--lake", str(lake_path), "--workers", "1"]) == 0
    text = capsys.readouterr().out
    lines = text.splitlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("bar2 "))
    assert "rig: calibrated already" in lines[k] and row["version"] in lines[k]
    for i, (cam, v) in enumerate(zip(row["camera_ids"], row["head_versions"], strict=True)):
        assert lines[k + 1 + i].split()[:4] == [cam, "bar2-s1", "head", v]
    assert "2 found, 0 committed, 0 failed, 2 skipped" in text
