"""Every option and input validated at the boundary: one line, exit 2, nothing written (issue 24, class 8).

Each case runs the command in this process (:func:`flows.cli.main`) with a Prefect API where
nothing listens, so a command that got past its checks to the server would fail otherwise:
bad levels and tolerances (``history --fleet`` as ``compare``), empty or huge grids, times
beyond the calendar, counts below one, non-finite seconds, an empty ``estimate``, a
``--lake`` that is a file or a folder that is not a lake (even ``/``), and outputs that
exist (never written over without ``--overwrite``; with it, replaced, never written into:
a hard link to the old file, a photograph's, keeps its bytes).
"""

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import tifffile

from fieldcal.lake.store import Lake
from fieldcal.lake.tables import TABLES
from flows import cli_common
from flows.cli import main
from tests.field.test_bad_geometry import SENSOR
from tests.flows.test_latest import commit, make_session

UNREACHABLE = "http://127.0.0.1:9/api"
CAMERA = "cam-bad"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("badopts")
    lake = Lake(str(tmp / "lake"))
    for rel, acquired, seed in (("root/2026-01/wall", "2026-01-01", 1), ("root/2026-02/wall", "2026-02-01", 2)):
        commit(make_session(tmp / rel, CAMERA, acquired, seed), lake)
    for name, estimate in (("empty-estimate", []), ("twice-estimate", ["f_mm", "xp_mm", "f_mm"])):
        folder = make_session(tmp / name, CAMERA, "2026-03-01", 3)
        m = json.loads((folder / "session.json").read_text())
        m["estimate"] = estimate
        (folder / "session.json").write_text(json.dumps(m))
    absurd = make_session(tmp / "absurd-pitch", CAMERA, "2026-03-01", 3)
    m = json.loads((absurd / "session.json").read_text())
    m["sensor"]["pixel_size_um"] = 1e-9
    (absurd / "session.json").write_text(json.dumps(m))
    for name, table, col, value in (("absurd-sigma-px", "observations.csv", 4, "1e-30"),
                                    ("absurd-sigma-mm", "targets.csv", 4, "1e-12")):
        folder = make_session(tmp / name, CAMERA, "2026-03-01", 3)
        head, first, *rest = (folder / table).read_text().splitlines()
        cells = first.split(",")
        cells[col] = value
        (folder / table).write_text("\n".join([head, ",".join(cells), *rest]) + "\n")
    tifffile.imwrite(tmp / "photo.tif", np.zeros((SENSOR.height_px, SENSOR.width_px), np.uint8))
    (tmp / "notalake").mkdir()
    (tmp / "notalake" / "holiday.jpg").write_bytes(b"not a lake")
    (tmp / "afile").write_text("a file\n")
    (tmp / "existing").write_text("keep me\n")
    (tmp / "report").mkdir()
    (tmp / "report" / "report.html").write_text("keep me\n")
    return tmp


@pytest.fixture
def env(world, monkeypatch):
    monkeypatch.chdir(world)
    monkeypatch.setenv("FIELDCAL_LAKE", str(world / "lake"))
    monkeypatch.setenv("PREFECT_API_URL", UNREACHABLE)
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", "off")
    monkeypatch.delenv("FIELDCAL_STORAGE_OPTIONS", raising=False)
    return world


PV = ["previous", "latest", "--camera", CAMERA]
CASES = {
    # levels and tolerances: history --fleet and dashboard refuse what compare refuses
    "fleet alpha 2": (["history", "--fleet", "--alpha", "2"], r"alpha must be in \(0, 1\), got 2"),
    "fleet alpha 0": (["history", "--fleet", "--alpha", "0"], r"alpha must be in \(0, 1\)"),
    "fleet alpha nan": (["history", "--fleet", "--alpha", "nan"], r"alpha must be in \(0, 1\), got nan"),
    "fleet tolerance -1": (["history", "--fleet", "--tolerance-um", "-1"], r"tolerance_um must be positive and finite"),
    "fleet tolerance inf": (["history", "--fleet", "--tolerance-um", "inf"], r"positive and finite, got inf"),
    "fleet tolerance nan": (["history", "--fleet", "--tolerance-um", "nan"], r"positive and finite, got nan"),
    "dashboard tolerance inf": (["dashboard", "--out", "site", "--tolerance-um", "inf"], r"positive and finite"),
    "compare alpha 1": (["compare", *PV, "--alpha", "1"], r"alpha must be in \(0, 1\)"),
    "compare tolerance 0": (["compare", *PV, "--tolerance-um", "0"], r"tolerance_um must be positive and finite"),
    # grids: empty, negative, one point, 10^10 points (was: ValueError / MemoryError, exit 1)
    "grid 0 0": (["compare", *PV, "--grid", "0", "0"], r"grid must have 2 to 1000 points along each axis, got 0 x 0"),
    "grid -3 5": (["compare", *PV, "--grid", "-3", "5"], r"got -3 x 5"),
    "grid 1 1": (["compare", *PV, "--grid", "1", "1"], r"got 1 x 1"),
    "grid 1e5": (["compare", *PV, "--grid", "100000", "100000"], r"got 100000 x 100000"),
    # times beyond the calendar (was: OverflowError, exit 1)
    "as-of after 9999 in UTC": (["history", "--as-of", "9999-12-31T23:59:59-23:00"], r"--as-of: out of range in UTC"),
    "from after 9999 in UTC": (["history", "--from", "9999-12-31T23:59:59-23:00"], r"out of range in UTC"),
    "as-of year 99999": (["history", "--camera", CAMERA, "--as-of", "99999-01-01"], r"not an ISO 8601"),
    # counts and seconds
    "max-sessions 0": (["fleet", "root", "--max-sessions", "0"], r"--max-sessions must be at least 1, got 0"),
    "max-sessions -1": (["fleet", "root", "--max-sessions", "-1"], r"--max-sessions must be at least 1"),
    "workers 0": (["run", "root/2026-01/wall", "--workers", "0"], r"--workers must be at least 1"),
    "batch-size -5": (["run", "root/2026-01/wall", "--batch-size", "-5"], r"--batch-size must be at least 1"),
    "seed -1": (["synth", "synth-out", "--seed", "-1"], r"--seed must be a non-negative integer"),
    "linger nan": (["server", "start", "--linger", "nan"], r"--linger must be a number of seconds"),
    "linger inf": (["server", "start", "--linger", "inf"], r"--linger must be a number of seconds"),
    # the session
    "estimate []": (["run", "empty-estimate"], r"estimate is empty: a calibration must estimate some of"),
    "estimate twice": (["run", "twice-estimate"], r"\['f_mm', 'xp_mm', 'f_mm'\] has non-unique elements"),
    "absurd pixel pitch": (["run", "absurd-pitch"], r"1e-09 is less than the minimum of 0\.1 \(at /sensor/pixel_size"),
    "absurd sigma_px": (["run", "absurd-sigma-px"], r"observations\.csv:2: sigma_px 1e-30 px is not a plausible"),
    "absurd sigma_mm": (["run", "absurd-sigma-mm"], r"targets\.csv:2: sigma_mm 1e-12 mm is not a plausible"),
    # a lake that is not one, refused before any work
    "run --lake FILE": (["run", "root/2026-01/wall", "--lake", "afile"], r"no lake at .*afile: it is a file"),
    "run --lake not a lake": (["run", "root/2026-01/wall", "--lake", "notalake"],
                              r"notalake is a folder that is not a lake \(it holds holiday\.jpg"),
    "run --lake a sessions folder": (["run", "root/2026-01/wall", "--lake", "root"], r"is a folder that is not a lake"),
    "fleet --lake not a lake": (["fleet", "root", "--lake", "notalake"], r"is a folder that is not a lake"),
    "show --lake /": (["show", "latest", "--camera", CAMERA, "--lake", "/"], r"^fieldcal show: / is a folder that is"),
    "history --lake not a lake": (["history", "--lake", "notalake"], r"is a folder that is not a lake"),
    "export --lake FILE": (["export", "latest", "--camera", CAMERA, "--format", "json", "--lake", "afile"],
                           r"it is a file"),
    # outputs that exist
    "run --json": (["run", "root/2026-01/wall", "--json", "existing"], r"--json existing: exists; fieldcal does not"),
    "export --out": (["export", "latest", "--camera", CAMERA, "--format", "json", "--out", "existing"],
                     r"--out existing: exists; fieldcal does not write over a file \(--overwrite replaces it\)"),
    "compare --out": (["compare", *PV, "--out", "existing"], r"--out existing: exists"),
    "compare --plot": (["compare", *PV, "--plot", "existing"], r"--plot existing: exists"),
    "history --plot": (["history", "--camera", CAMERA, "--plot", "existing"], r"--plot existing: exists"),
    "history --fleet --plot": (["history", "--fleet", "--plot", "existing"], r"--plot existing: exists"),
    "undistort OUT": (["undistort", "latest", "photo.tif", "existing", "--camera", CAMERA], r"OUT existing: exists"),
    "report --out": (["report", "latest", "--camera", CAMERA, "--out", "report"], r"has a report\.html"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_options_are_one_line_exit_2_and_nothing_written(env, capsys, case):
    argv, match = CASES[case]
    before = {p: p.stat().st_mtime_ns for p in env.rglob("*") if p.is_file()}
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith(f"fieldcal {argv[0]}"), captured.err
    assert re.search(match, captured.err.strip()), captured.err
    assert "Traceback" not in captured.err and "Error:" not in captured.err
    after = {p: p.stat().st_mtime_ns for p in env.rglob("*") if p.is_file()}
    assert after == before                                     # nothing written, nothing touched
    assert not (env / "site").exists() and not (env / "synth-out").exists()


def test_overwrite_replaces_the_file_and_leaves_its_hard_links_alone(env, tmp_path, capsys):
    out = tmp_path / "cam.json"
    photo = tmp_path / "photo.tif"
    photo.write_bytes(b"the photograph's bytes")
    os.link(photo, out)                                        # the export's path is a photograph's hard link
    argv = ["export", "latest", "--camera", CAMERA, "--format", "json", "--out", str(out)]
    assert main(argv) == 2 and photo.read_bytes() == b"the photograph's bytes"
    capsys.readouterr()
    assert main([*argv, "--overwrite"]) == 0
    assert json.loads(out.read_text())["camera_id"] == CAMERA
    assert photo.read_bytes() == b"the photograph's bytes"      # replaced by name, not written into
    assert main(["history", "--camera", CAMERA, "--plot", str(out), "--overwrite"]) == 0
    assert out.read_bytes()[:4] == b"\x89PNG" and photo.read_bytes() == b"the photograph's bytes"


def test_an_empty_folder_and_a_new_path_are_lakes_to_write_into(env, tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "lakeish").mkdir()
    (tmp_path / "lakeish" / "sessions").mkdir()                # the fleet's root inside a new lake
    (tmp_path / "lakeish" / ".DS_Store").write_text("")
    for path in (tmp_path / "empty", tmp_path / "new", tmp_path / "lakeish", env / "lake"):
        cli_common.check_lake_target(Lake(str(path)))
    assert set(TABLES) <= set(cli_common.LAKE_DATA)            # every table marks a lake


def test_extreme_range_bounds_are_answered(env, capsys):
    assert main(["history", "--from", "0001-01-01", "--to", "9999-12-31", "--format", "json"]) == 0
    assert {r["camera_id"] for r in json.loads(capsys.readouterr().out)} == {CAMERA}
    assert Path(env / "lake").is_dir()


def test_json_on_a_full_device_prints_the_version_and_names_the_file(env, tmp_path):
    """The write fails as on a full disk (the kernel's file size limit: EFBIG); the answer (an
    unchanged rerun: no server) is still printed, and the line names the output, not a temporary."""
    import resource
    import subprocess
    import sys

    (version,) = [r["version"] for r in Lake(str(env / "lake")).catalog().to_pylist() if r["acquired"].month == 1]
    out = tmp_path / "doc.json"
    fieldcal = str(Path(sys.executable).with_name("fieldcal"))
    proc = subprocess.run([fieldcal, "run", "root/2026-01/wall", "--lake", str(env / "lake"), "--json", str(out)],
                          cwd=env, env=dict(os.environ), capture_output=True, text=True, timeout=300,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (512, 512)))
    assert proc.returncode == 1 and proc.stdout == version + "\n", proc.stderr
    assert proc.stderr == f"fieldcal run: committed {version}, but --json {out}: File too large\n"
    assert not out.exists() and list(tmp_path.iterdir()) == []          # no temporary left either
