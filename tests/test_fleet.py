"""A fleet of session folders: scanned with the session loader, selected against the lake (fieldcal/fleet.py)."""

import json

import pytest

from fieldcal import fleet, pipeline
from fieldcal.errors import InputError
from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session


@pytest.fixture
def root(tmp_path):
    root = tmp_path / "root"
    write_field_session(root / "cam-a" / "wall-1", wide_field(seed=1), images=False, observations_csv=True,
                        camera_id="cam-a")
    write_field_session(root / "wall-2", wide_field(seed=2), images=False, observations_csv=True, camera_id="cam-b",
                        session_id="given-id")
    (root / "bad").mkdir()
    (root / "bad" / "session.json").write_text(json.dumps({"schema": "fieldcal.session/1", "method": "field"}))
    (root / "g[1]").mkdir()                    # a name with glob characters holds no session
    return root


def test_scan_loads_every_session_as_a_run_would_and_reports_the_bad_one(root):
    found = fleet.scan_sessions(str(root))
    by_folder = {f.folder.rsplit("/", 1)[-1]: f for f in found}
    assert sorted(by_folder) == ["bad", "wall-1", "wall-2"]
    assert (by_folder["wall-1"].camera_id, by_folder["wall-1"].session_id) == ("cam-a", "wall-1")
    assert (by_folder["wall-2"].camera_id, by_folder["wall-2"].session_id) == ("cam-b", "given-id")
    assert by_folder["wall-2"].has_images is False                   # observations.csv: nothing to measure
    bad = by_folder["bad"]
    assert bad.camera_id is None and "session.json" in bad.error and "camera_id" in bad.error


def test_select_keeps_the_sessions_without_a_version_and_names_the_others_versions(root, tmp_path):
    lake = Lake(tmp_path / "lake")
    prepared = pipeline.prepare(root / "cam-a" / "wall-1")
    outcome = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
    version = lake.commit(outcome.document, outcome.arrays, outcome.residuals, array_attrs=outcome.array_attrs)
    found = fleet.scan_sessions(str(root))
    todo = fleet.select_sessions(found, lake)
    assert [(s.camera_id, s.session_id) for s in todo] == [("cam-b", "given-id")]
    summary = fleet.summarize(str(lake.url), str(root), found)
    assert [(e["camera_id"], e["status"], e["version"]) for e in summary["sessions"]] == [
        (None, "failed", None), ("cam-a", "calibrated already", version), ("cam-b", "to calibrate", None)]


def test_a_root_that_does_not_exist_is_an_error(tmp_path):
    with pytest.raises(InputError, match="no folder of sessions there"):
        fleet.scan_sessions(str(tmp_path / "nowhere"))
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        fleet.scan_sessions(str(tmp_path / "file"))


def test_a_committed_session_with_images_left_out_says_so():
    from fieldcal.fleet import status_text

    base = {"status": "committed", "n_images": 6, "n_left_out": 0}
    assert status_text(base) == "committed"
    assert status_text(dict(base, n_left_out=2)) == "committed, 2 of 6 images left out"
    assert status_text(dict(base, status="failed", n_left_out=2)) == "failed"
