"""Ids and names are what the schema says, exactly (issue 17); session folders are never patterns.

The definitions live once, in ``schemas/session.schema.json`` ``$defs`` (``id``, ``label``,
``file``, ``glob``), and serve both the manifest and the CSV tables
(:mod:`fieldcal.contract.names`). Hostile values (control characters, a trailing newline that
a ``$`` would let through, glob metacharacters, path separators, invisible and bidirectional
characters, very long values) are refused with one line naming the file and the row or the
JSON pointer.
"""

import json
import re
import shutil
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fieldcal import pipeline
from fieldcal.contract import names
from fieldcal.contract.schemas import json_schema, schema_dir, validate_json
from fieldcal.errors import InputError
from fieldcal.session.loader import load_session
from fieldcal.session.tables import read_targets_csv
from tests.field.test_bad_geometry import CONVERGENT, wall, write_obs_session

HOSTILE = {
    "newline at the end": "cam-1\n", "newline inside": "cam\n1", "carriage return": "cam\r1",
    "NUL": "cam\x001", "escape": "cam\x1b[31m", "DEL": "cam\x7f", "C1 control": "cam\x851",
    "tab": "cam\t1", "line separator": "cam\u2028", "bidi override": "cam\u202e1", "zero width": "ca\u200bm",
    "byte-order mark": "\ufeffcam", "lone surrogate": "cam\udcff", "star": "cam*", "question mark": "cam?",
    "brackets": "cam[1]", "slash": "a/b", "backslash": "a\\b", "too long": "c" * 129,
}


def _patterns(node):
    if isinstance(node, dict):
        for k, v in node.items():
            if k == "pattern" and isinstance(v, str):
                yield v
            else:
                yield from _patterns(v)
    elif isinstance(node, list):
        for v in node:
            yield from _patterns(v)


def test_every_pattern_that_ends_the_text_refuses_a_final_newline():
    """Python's ``$`` (the jsonschema package uses ``re``) matches before a final newline."""
    found = []
    for path in sorted(schema_dir().glob("*.schema.json")):
        for p in _patterns(json.loads(path.read_text())):
            if "$" in p:
                found.append(p)
                assert p.endswith("$(?!\\n)"), f"{path.name}: {p}"
    assert len(found) >= 6


@pytest.mark.parametrize("what", sorted(HOSTILE))
@pytest.mark.parametrize("key", ["camera_id", "session_id"])
def test_hostile_ids_in_session_json_are_refused(key, what):
    manifest = {"schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-1", "acquired": "2026-11-20",
                "sensor": {"width_px": 10, "height_px": 10, "pixel_size_um": 5.0}, "field": {"targets": "t.csv"},
                "images": "images/*.tif", key: HOSTILE[what]}
    with pytest.raises(InputError, match=rf"S/session\.json: .* is not an id: 1 to 128 characters .* "
                                         rf"\(at /{key}\)$") as info:
        validate_json(manifest, "session", "S/session.json")
    assert "\n" not in str(info.value) and "\r" not in str(info.value)
    assert len(str(info.value)) < 300


def test_the_calibration_schema_refuses_an_id_with_a_final_newline():
    schema = json_schema("calibration")
    id_pattern = schema["$defs"]["id"]["pattern"]
    assert re.search(id_pattern, "cam-1") and not re.search(id_pattern, "cam-1\n")
    fp = schema["properties"]["inputs"]["properties"]["fingerprint"]["pattern"]
    assert not re.search(fp, "sha256:" + "0" * 64 + "\n")


@pytest.mark.parametrize("what", sorted(set(HOSTILE) - {"newline at the end", "tab"}))
def test_hostile_target_ids_are_refused_naming_the_row(tmp_path, what):
    """(A newline or tab at either end of a cell is white space, trimmed like a space.)"""
    p = tmp_path / "targets.csv"
    p.write_bytes(('id,X,Y,Z\nA,0,0,0\n"' + HOSTILE[what] + '",1,1,1\n').encode("utf-8", "surrogatepass"))
    with pytest.raises(InputError) as info:
        read_targets_csv(p)
    text = str(info.value)
    assert "\n" not in text and "\r" not in text and len(text) < 400
    assert text.startswith(str(p))
    assert re.search(r"targets\.csv:3: target id .* is not a name \(target id, station\)", text) \
        or "not UTF-8" in text, text


@pytest.mark.parametrize("value", ["a/b", "a\\b", "T\t1", "T" * 129])
def test_target_ids_with_separators_tabs_or_too_long_are_refused(tmp_path, value):
    p = tmp_path / "targets.csv"
    p.write_text(f'id,X,Y,Z\nA,0,0,0\n"{value}",1,1,1\n')
    with pytest.raises(InputError, match=r"targets\.csv:3: target id .* is not a name"):
        read_targets_csv(p)


def test_ordinary_target_ids_and_stations_are_accepted(tmp_path):
    p = tmp_path / "targets.csv"
    ids = ["1001", "T-7", "CP 12", "P.3_a", "Mire#4", "é2", "x" * 128]
    p.write_text("id,X,Y,Z\n" + "".join(f"{t},{k},0,0\n" for k, t in enumerate(ids)))
    assert read_targets_csv(p).ids.tolist() == ids
    assert names.is_valid("Roof (north)", "label") and not names.is_valid("", "label")


@pytest.mark.parametrize("station, ok", [("S1", True), ("roof/1", False), ("S\n", False), ("S*", False),
                                         ("s" * 129, False)])
def test_station_names(tmp_path, station, ok):
    folder = write_obs_session(tmp_path / "s", wall(relief_m=1.0), CONVERGENT)
    m = json.loads((folder / "session.json").read_text())
    files = sorted({r.split(",")[0] for r in (folder / "observations.csv").read_text().splitlines()[1:]})
    m["images"] = [{"file": f, "station": station} for f in files]
    (folder / "session.json").write_text(json.dumps(m))
    if ok:
        assert load_session(folder).images[0].station == station
    else:
        with pytest.raises(InputError, match=r"is not a name \(target id, station\).* \(at /images/0/station\)"):
            load_session(folder)


@pytest.mark.parametrize("name, match", [
    ("images/a*.tif", r"observations\.csv:2: image 'images/a\*\.tif' is not a file of the session"),
    ("images/a\x1b.tif", r"observations\.csv:2: image 'images/a\\x1b\.tif' is not a file of the session"),
    ("../a.tif", r"observations\.csv:2: image '\.\./a\.tif' leaves the session folder"),
    ("/abs/a.tif", r"observations\.csv:2: image '/abs/a\.tif' must be relative to the session folder"),
    ("i" * 1025, r"observations\.csv:2: image 'i{60}'\.\.\. \(1025 characters\) is not a file"),
])
def test_hostile_image_names_in_observations_are_refused(tmp_path, name, match):
    folder = write_obs_session(tmp_path / "s", wall(relief_m=1.0), CONVERGENT)
    head, first, *rows = (folder / "observations.csv").read_text().splitlines()
    (folder / "observations.csv").write_text("\n".join([head, name + "," + first.split(",", 1)[1], *rows]) + "\n")
    with pytest.raises(InputError, match=match) as info:
        pipeline.prepare(folder)
    assert "\n" not in str(info.value)


def test_a_file_matched_by_the_glob_with_a_hostile_name_is_refused(tmp_path):
    folder = write_obs_session(tmp_path / "s", wall(relief_m=1.0), CONVERGENT)
    (folder / "observations.csv").unlink()
    (folder / "images").mkdir()
    (folder / "images" / "IMG[1].tif").write_bytes(b"x")
    with pytest.raises(InputError, match=r"session\.json: image 'images/IMG\[1\]\.tif' is not a file of the "
                                         r"session: .* none of \* \? \[ \]"):
        pipeline.prepare(folder)


# --------------------------------------------------------------------------------------
# session folders are never glob patterns
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["g[1]", "g*", "g?", "run [2026]"])
def test_a_session_folder_with_glob_characters_lists_its_own_images(tmp_path, name):
    """`run 'g[1]'` beside `g1` failed with a ValueError: the folder was part of the pattern."""
    template = write_obs_session(tmp_path / "t", wall(relief_m=1.0), CONVERGENT)
    (template / "observations.csv").unlink()
    (template / "images").mkdir()
    (template / "marks.csv").write_text("image,target_id,u,v\n")
    parent = tmp_path / name
    decoy = tmp_path / "g1" / "s"                  # what the folder's name would match as a pattern
    for folder, files in ((parent / "s", ["mine.tif"]), (decoy, ["decoy.tif"])):
        shutil.copytree(template, folder)
        for f in files:
            (folder / "images" / f).write_bytes(f.encode())
        m = json.loads((folder / "session.json").read_text())
        (folder / "session.json").write_text(json.dumps({**m, "session_id": "s-1"}))
    sess = load_session(parent / "s")
    assert [im.file for im in sess.images] == ["images/mine.tif"]
    assert load_session(Path(str(parent / "s"))).session_id == "s-1"


@settings(max_examples=300)
@given(values=st.lists(st.one_of(st.text(max_size=12), st.sampled_from(sorted(HOSTILE.values()))), max_size=8),
       kind=st.sampled_from(names.KINDS))
def test_the_bulk_check_finds_the_first_invalid_name_as_the_single_check_does(values, kind):
    expect = next((k for k, v in enumerate(values) if not names.is_valid(v, kind)), None)
    assert names.first_invalid(values, kind) == expect
