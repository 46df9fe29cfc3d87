"""One meaning of "latest" and "previous" in every command (issue 24, class 4).

The rule (:mod:`fieldcal.lake.order`): acquisition time, ties by commit order; a session is
its ``session_id`` with its acquisition time. The lake here has one camera with three
sessions committed out of order (a backfill after a newer session):

    committed 1st   ROOT/2026-03/wall   acquired 2026-03-01   the latest
    committed 2nd   ROOT/2026-01/wall   acquired 2026-01-01   same folder name, no session_id
    committed 3rd   ROOT/2026-02/other  acquired 2026-02-01   the previous (the last commit)

Every command that takes ``latest`` must name the March version (the last commit would be
February's), ``previous`` February's, and both sessions named ``wall`` stay two. Also: an
``acquired`` more than a day after now is refused (one line, exit 2, nothing written); two
sessions acquired the same day are each other's previous (the certificate's change).
"""

import datetime as dt
import json
import shutil

import pytest
import tifffile

from fieldcal import fleet as fleet_lib
from fieldcal import pipeline
from fieldcal.analysis.uncertainty import Calibration
from fieldcal.errors import InputError
from fieldcal.lake import order
from fieldcal.lake.store import Lake
from fieldcal.products import content
from flows.cli import main
from tests.field.test_bad_geometry import CONVERGENT, SENSOR, wall, write_obs_session

UNREACHABLE = "http://127.0.0.1:9/api"
CAMERA = "cam-order"


def make_session(folder, camera, acquired, seed, session_id=None):
    write_obs_session(folder, wall(relief_m=1.0), CONVERGENT, seed=seed)
    m = json.loads((folder / "session.json").read_text())
    m.update(camera_id=camera, acquired=acquired)
    if session_id:
        m["session_id"] = session_id
    (folder / "session.json").write_text(json.dumps(m))
    return folder


def commit(folder, lake) -> str:
    prepared = pipeline.prepare(folder)
    fp = pipeline.input_fingerprint(prepared, {})
    outcome = pipeline.solve(prepared, {}, fingerprint_=fp)
    return str(lake.commit(outcome.document, outcome.arrays, outcome.residuals, array_attrs=outcome.array_attrs))


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("latest")
    root = tmp / "ROOT"
    lake = Lake(str(tmp / "lake"))
    v = {}
    for key, rel, acquired, seed in (("mar", "2026-03/wall", "2026-03-01T10:00:00Z", 1),
                                     ("jan", "2026-01/wall", "2026-01-01T10:00:00Z", 2),
                                     ("feb", "2026-02/other", "2026-02-01T10:00:00Z", 3)):
        v[key] = commit(make_session(root / rel, CAMERA, acquired, seed), lake)
    # a second camera: two sessions acquired the same day, committed a then b
    for key, name, seed in (("day_a", "a", 4), ("day_b", "b", 5)):
        v[key] = commit(make_session(tmp / "day" / name, "cam-day", "2026-05-01", seed), lake)
    return {"tmp": tmp, "root": root, "lake": lake, "v": v}


@pytest.fixture
def env(world, monkeypatch):
    monkeypatch.setenv("FIELDCAL_LAKE", world["lake"].url)
    monkeypatch.setenv("PREFECT_API_URL", UNREACHABLE)
    monkeypatch.delenv("FIELDCAL_STORAGE_OPTIONS", raising=False)
    return world


def test_the_rule_in_the_library(world):
    lake, v = world["lake"], world["v"]
    commits = lake.catalog().to_pylist()
    assert [r["version"] for r in commits if r["camera_id"] == CAMERA] == [v["mar"], v["jan"], v["feb"]]
    assert lake.latest(CAMERA) == v["mar"]                       # not the last commit (feb)
    assert lake.latest(CAMERA, "wall") == v["mar"]
    rows = lake.camera_rows(CAMERA)
    assert [r["version"] for r in order.session_latest(rows)] == [v["jan"], v["feb"], v["mar"]]
    assert order.previous(rows, v["mar"]) == v["feb"] and order.previous(rows, v["feb"]) == v["jan"]
    assert order.previous(rows, v["jan"]) is None
    assert order.neighbours(rows, v["feb"]) == (v["jan"], v["mar"])


def _show(args, capsys):
    assert main(["show", *args, "--format", "json"]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)["version"]


def _export(args, capsys, tmp_path):
    out = tmp_path / "doc.json"
    assert main(["export", *args, "--format", "json", "--out", str(out)]) == 0, capsys.readouterr().err
    return json.loads(out.read_text())["version"]


def _undistort(args, capsys, tmp_path):
    import numpy as np

    src, out = tmp_path / "raw.tif", tmp_path / "out.tif"
    tifffile.imwrite(src, np.zeros((SENSOR.height_px, SENSOR.width_px), np.uint8))
    assert main(["undistort", *args[:1], str(src), str(out), *args[1:]]) == 0, capsys.readouterr().err
    with tifffile.TiffFile(out) as t:
        return json.loads(t.pages[0].description)["provenance"]["version"]


def _report(args, capsys, tmp_path):
    out = tmp_path / "rep"
    assert main(["report", *args, "--out", str(out)]) == 0, capsys.readouterr().err
    return (out / "report.html").read_text()


def _certificate(args, capsys, tmp_path):
    out = tmp_path / "cert"
    assert main(["certificate", *args, "--out", str(out)]) == 0, capsys.readouterr().err
    return (out / "certificate.html").read_text()


@pytest.mark.parametrize("command", ["show", "export", "undistort", "certificate"])
def test_every_command_takes_latest_by_acquisition_not_by_commit(env, command, capsys, tmp_path):
    v = env["v"]
    args = ["latest", "--camera", CAMERA]
    if command == "show":
        assert _show(args, capsys) == v["mar"]
        assert _show(["latest", "--camera", CAMERA, "--session", "wall"], capsys) == v["mar"]
    elif command == "export":
        assert _export(args, capsys, tmp_path) == v["mar"]
    elif command == "undistort":
        assert _undistort(args, capsys, tmp_path) == v["mar"]
    else:
        html = _certificate(args, capsys, tmp_path)
        assert v["mar"] in html
        section = html[html.index("8. Change since the previous calibration"):]
        assert v["feb"] in section and v["jan"] not in section


@pytest.mark.heavy
def test_report_takes_latest_by_acquisition(env, capsys, tmp_path):
    html = _report(["latest", "--camera", CAMERA], capsys, tmp_path)
    assert env["v"]["mar"] in html and env["v"]["feb"] in html   # the report's previous calibration too


def test_compare_previous_latest_and_history(env, capsys, tmp_path):
    v = env["v"]
    out = tmp_path / "c.json"
    assert main(["compare", "previous", "latest", "--camera", CAMERA, "--format", "json", "--out", str(out)]) == 0
    s = json.loads(out.read_text())
    assert (s["version_a"], s["version_b"]) == (v["feb"], v["mar"])
    capsys.readouterr()
    assert main(["history", "--fleet", "--format", "json"]) == 0
    fleet = {r["camera_id"]: r for r in json.loads(capsys.readouterr().out)}
    assert (fleet[CAMERA]["version"], fleet[CAMERA]["previous_version"]) == (v["mar"], v["feb"])
    assert (fleet["cam-day"]["version"], fleet["cam-day"]["previous_version"]) == (v["day_b"], v["day_a"])
    # both sessions named "wall" are listed: session identity survives same-named folders
    assert main(["history", "--camera", CAMERA, "--format", "json"]) == 0
    hist = json.loads(capsys.readouterr().out)
    assert [r["version"] for r in hist] == [v["jan"], v["feb"], v["mar"]]
    assert [r["session_id"] for r in hist] == ["wall", "other", "wall"]
    assert main(["history", "--format", "json"]) == 0
    latest = {r["camera_id"]: r["version"] for r in json.loads(capsys.readouterr().out)}
    assert latest[CAMERA] == v["mar"]


def test_two_sessions_on_one_day_are_each_others_previous(env, capsys, tmp_path):
    lake, v = env["lake"], env["v"]
    b, a = Calibration.from_lake(lake, v["day_b"]), Calibration.from_lake(lake, v["day_a"])
    assert content.previous_version(lake, b) == v["day_a"]           # ties by commit order
    assert content.previous_version(lake, a) is None
    html = _certificate(["latest", "--camera", "cam-day"], capsys, tmp_path)
    section = html[html.index("8. Change since the previous calibration"):]
    assert v["day_a"] in section and "No previous calibration" not in section


def test_same_named_folders_are_two_sessions_for_the_fleet(world, tmp_path):
    root = tmp_path / "ROOT"
    shutil.copytree(world["root"] / "2026-01" / "wall", root / "2026-01" / "wall")
    make_session(root / "2026-04" / "wall", CAMERA, "2026-04-01T10:00:00Z", seed=6)
    found = fleet_lib.scan_sessions(str(root))
    todo = fleet_lib.select_sessions(found, world["lake"])
    assert [s.folder for s in todo] == [str(root / "2026-04" / "wall")]        # not "calibrated already"
    done = [s for s in found if s not in todo]
    assert [s.version for s in done] == [world["v"]["jan"]]                   # its own version, not March's


@pytest.mark.parametrize("ahead, refused", [(dt.timedelta(days=400 * 70), True), (dt.timedelta(days=2), True),
                                            (dt.timedelta(hours=23), False)])
def test_an_acquired_time_after_now_plus_a_day_is_refused(env, tmp_path, capsys, ahead, refused):
    when = (dt.datetime.now(dt.UTC) + ahead).strftime("%Y-%m-%dT%H:%M:%SZ")
    folder = make_session(tmp_path / "future", "cam-future", when, seed=7)
    lake = tmp_path / "lake"
    if not refused:
        assert pipeline.prepare(folder).session.acquired.year >= 2026
        return
    assert main(["run", str(folder), "--lake", str(lake)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "session.json" in err and "'acquired'" in err and "a typo?" in err, err
    assert not lake.exists()
    # the library's commit refuses it too (a document made elsewhere)
    prepared = pipeline.prepare(make_session(tmp_path / "now", "cam-future", "2026-01-01", seed=7))
    doc = pipeline.solve(prepared, {}, fingerprint_=pipeline.input_fingerprint(prepared, {}))
    document = dict(doc.document, acquired=when)
    with pytest.raises(InputError, match=r"'acquired' .* is after now .* plus 1 day"):
        Lake(str(lake)).commit(document, doc.arrays, doc.residuals, array_attrs=doc.array_attrs)
    assert Lake(str(lake)).catalog().num_rows == 0
