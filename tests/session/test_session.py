"""Session loading: the manifest schema, safe paths, and the CSV tables of CONTRACT section 3."""

import json

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.session.loader import field_data_from_observations, load_session, read_targets_csv

MANIFEST = {
    "schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-1",
    "acquired": "2026-11-20T09:30:00Z",
    "sensor": {"width_px": 100, "height_px": 80, "pixel_size_um": 5.0},
    "lens": {"nominal_focal_mm": 20.0},
    "field": {"targets": "targets.csv", "target_diameter_mm": 60.0, "target_polarity": "dark"},
    "images": "images/*.tif",
}
TARGETS = "id,X,Y,Z,sigma_mm,code\nA,0,0,0,,\nB,1,0,0,2,\nC,0,1,0.5,,7\n"
OBS = "image,target_id,u,v,sigma_px\nimages/a.tif,A,10,20,\nimages/a.tif,B,30,40,0.2\nimages/b.tif,C,1,2,\n"


def make(tmp_path, manifest=None, targets=TARGETS, obs=OBS, name="s1"):
    d = tmp_path / name
    d.mkdir()
    (d / "session.json").write_text(json.dumps(manifest or MANIFEST))
    (d / "targets.csv").write_text(targets)
    if obs is not None:
        (d / "observations.csv").write_text(obs)
    return d


def test_observation_only_session_loads(tmp_path):
    sess = load_session(make(tmp_path))
    assert sess.session_id == "s1" and sess.acquired.year == 2026 and sess.sensor.width_px == 100
    data = field_data_from_observations(sess)
    assert [im.file for im in data.images] == ["images/a.tif", "images/b.tif"]
    assert np.allclose(data.obs.sigma_px, [0.1, 0.2, 0.1])        # empty sigma: the default 0.1
    assert np.allclose(data.targets.sigma_mm, [5.0, 2.0, 5.0])    # empty sigma_mm: 5 mm
    assert list(data.targets.codes) == [-1, -1, 7]
    assert data.observation_table().num_rows == 3


@pytest.mark.parametrize("patch, match", [
    ({"schema": "fieldcal.session/2"}, r"at /schema"),
    ({"sensor": {"width_px": -5, "height_px": 80, "pixel_size_um": 5.0}}, r"at /sensor/width_px"),
    ({"method": "lab"}, r"at /method"),
    ({"images": "../other/*.tif"}, "leaves the session folder"),
    ({"images": [{"file": "/etc/passwd"}]}, "must be relative"),
    ({"field": {"targets": "../t.csv"}}, "leaves the session folder"),
    ({"acquired": "yesterday"}, "not an ISO 8601"),
    ({"estimate": ["f_mm", "b1"]}, "not estimable by the field method"),
    ({"camera_id": "a/b"}, r"at /camera_id"),
])
def test_manifest_errors_name_the_field(tmp_path, patch, match):
    d = make(tmp_path, {**MANIFEST, **patch})
    with pytest.raises(InputError, match=match) as info:
        load_session(d)
    assert "session.json" in str(info.value)


def test_invalid_json_and_missing_manifest(tmp_path):
    d = make(tmp_path)
    (d / "session.json").write_text("{not json")
    with pytest.raises(InputError, match=r"session.json: invalid JSON"):
        load_session(d)
    (d / "session.json").unlink()
    with pytest.raises(InputError, match="missing"):
        load_session(d)


def test_link_out_of_the_folder_is_refused(tmp_path):
    outside = tmp_path / "outside.csv"
    outside.write_text(TARGETS)
    d = make(tmp_path, {**MANIFEST, "field": {"targets": "t.csv"}})
    (d / "t.csv").symlink_to(outside)
    with pytest.raises(InputError, match="outside the session folder"):
        load_session(d)


@pytest.mark.parametrize("text, match", [
    ("", "empty file"),
    ("id,X,Y\nA,0,0\n", r"missing column\(s\) \['Z'\]"),
    ("id,X,Y,Z\nA,0,0,0\nA,1,1,1\n", r":3: duplicate target id 'A' \(first on line 2\)"),
    ("id,X,Y,Z\nA,0,nan,0\n", r":2: 'Y' is not finite"),
    ("id,X,Y,Z\nA,0,inf,0\n", r":2: 'Y' is not finite"),
    ("id,X,Y,Z\nA,0,abc,0\n", r":2: 'Y' is not a number: 'abc'"),
    ("id,X,Y,Z,sigma_mm,code\nA,0,0,0,,x\n", r"'code' must be an ArUco id"),
    ("id,X,Y,Z,sigma_mm,code\nA,0,0,0,,99999999999999999999\n",      # was an OverflowError in numpy
     r":2: 'code' must be an ArUco id \(a whole number from 0 to 2147483647\), got '9+'"),
    ("id,X,Y,Z\nA,1_000,0,0\n", r":2: 'X' is not a number: '1_000'"),
    ("id,X,Y,Z\nA,0x10,0,0\n", r":2: 'X' is not a number: '0x10'"),
    ('id,X,Y,Z\nA,0,0,0\n"B\n",0,0,0\n\nC,0,0,0\n"B",1,1,1\n',           # a row is named by its first line
     r":7: duplicate target id 'B' \(first on line 3\)"),
    ("id,X,Y,Z\n", "no data rows"),
])
def test_targets_csv_errors_name_file_and_row(tmp_path, text, match):
    p = tmp_path / "targets.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as info:
        read_targets_csv(p)
    assert "targets.csv" in str(info.value)


@pytest.mark.parametrize("obs, match", [
    ("image,target_id,u,v\nimages/a.tif,A,1,2\nimages/a.tif,A,3,4\n", "observed twice"),
    ("image,target_id,u\nimages/a.tif,A,1\n", r"missing column\(s\) \['v'\]"),
    ("image,target_id,u,v,sigma_px\nimages/a.tif,A,1,2,-1\n", "sigma_px must be positive"),
])
def test_observation_csv_errors(tmp_path, obs, match):
    sess = load_session(make(tmp_path, obs=obs))
    with pytest.raises(InputError, match=match):
        field_data_from_observations(sess)


def test_unlisted_target_id_is_unsurveyed_unless_the_session_is_strict(tmp_path):
    """CONTRACT section 3: an id targets.csv does not list is an unsurveyed target (reported);
    ``field.strict_targets`` refuses it, naming the file and line."""
    folder = make(tmp_path, obs="image,target_id,u,v\nimages/a.tif,A,1,2\nimages/a.tif,Z,1,2\n")
    data = field_data_from_observations(load_session(folder))
    assert data.meta["unlisted_targets"] == ["Z"]
    j = data.targets.index()["Z"]
    assert not data.targets.surveyed[j] and data.obs.target[1] == j
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["strict_targets"] = True
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"observations.csv:3: target_id 'Z' is not in targets.csv"):
        field_data_from_observations(load_session(folder))
