"""The ``fieldcal`` command line: run (CONTRACT section 5), history, show, fleet, serve, synth, demo.

``fieldcal run`` is exercised as a real subprocess (piped: stdout must be the version and
nothing else) against the test session's Prefect server; the other commands run in this
process through :func:`flows.cli.main`.
"""

import csv
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fieldcal.lake.store import Lake
from fieldcal.progress import TerminalProgress, emit, listening
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session
from flows import cli

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def env_for(prefect_server, tmp_path, **extra):
    env = dict(os.environ, PREFECT_API_URL=prefect_server, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE=str(tmp_path / "hashes.sqlite"), PYTHONPATH=str(ROOT))
    env.pop("FIELDCAL_LAKE", None)
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def cli_run(prefect_server, tmp_path_factory):
    """``fieldcal run`` in a subprocess, piped, the lake from FIELDCAL_LAKE: (lake, process, json path)."""
    tmp = tmp_path_factory.mktemp("cli")
    folder = tmp / "sessions" / "2026-04-01-wall"
    write_field_session(folder, wide_field(seed=7), images=False, observations_csv=True, camera_id="cam-cli",
                        acquired="2026-04-01T10:00:00Z")
    lake = tmp / "lake"
    out_json = tmp / "doc.json"
    proc = subprocess.run([FIELDCAL, "run", str(folder), "--json", str(out_json)], capture_output=True, text=True,
                          env=env_for(prefect_server, tmp, FIELDCAL_LAKE=str(lake)), cwd=tmp, timeout=300)
    return lake, proc, out_json, folder


def test_run_prints_only_the_version_when_piped_and_writes_the_document(cli_run):
    lake, proc, out_json, _ = cli_run
    assert proc.returncode == 0, proc.stderr
    version = proc.stdout.strip()
    assert proc.stdout == version + "\n"                         # the version and nothing else
    assert proc.stderr == ""                                     # no progress, no logs on a pipe
    doc = json.loads(out_json.read_text())
    assert doc["version"] == version and doc == Lake(lake).load_document(version)
    assert doc["camera_id"] == "cam-cli" and doc["schema"] == "fieldcal.calibration/1"


def test_bad_input_is_one_line_naming_the_file_exit_2_and_nothing_in_the_lake(prefect_server, tmp_path):
    folder = tmp_path / "bad"
    write_field_session(folder, wide_field(seed=8), images=False, observations_csv=True)
    lines = (folder / "targets.csv").read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + ",not-a-number,1,2,,"
    (folder / "targets.csv").write_text("\n".join(lines) + "\n")
    lake = tmp_path / "lake"
    proc = subprocess.run([FIELDCAL, "run", str(folder), "--lake", str(lake)], capture_output=True, text=True,
                          env=env_for(prefect_server, tmp_path), cwd=tmp_path, timeout=300)
    assert proc.returncode == 2
    assert proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line.startswith("fieldcal run: ") and "targets.csv" in line and "not-a-number" in line
    assert not lake.exists()


def test_run_without_a_lake_is_a_usage_error(monkeypatch, capsys, tmp_path):
    monkeypatch.delenv("FIELDCAL_LAKE", raising=False)
    assert cli.main(["run", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == "fieldcal run: no lake: give --lake LAKE or set FIELDCAL_LAKE"


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_run_on_a_terminal_shows_the_extraction_progress(prefect_server, tmp_path, monkeypatch, capsys):
    from fieldcal.synthetic.goniometer import write_session

    write_session(tmp_path / "lab", "canon5d2", seed=9, raster_scale=0.25, frames_per_angle=1, camera_id="cam-t")
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    monkeypatch.setattr(cli, "_prefect_env", lambda verbose: None)     # keep this process's environment
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    # the default local cluster: in-process workers of this run's own, started in no time
    status = cli.main(["run", str(tmp_path / "lab"), "--lake", str(tmp_path / "lake"),
                       "--batch-size", "20"])
    out = capsys.readouterr().out
    assert status == 0
    version = out.strip()
    assert out == version + "\n" and Lake(tmp_path / "lake").row(version)["camera_id"] == "cam-t"
    text = term.getvalue()
    assert "measuring images [" in text and "60/60" in text and "validating" in text
    assert "starting the Dask cluster" in text
    assert "new version" in text and "goniometer calibration" in text


# --------------------------------------------------------------------------------------
# history and show
# --------------------------------------------------------------------------------------
def test_history_of_a_camera_as_table_csv_and_json(cli_run, capsys):
    lake, proc, _, _ = cli_run
    version = proc.stdout.strip()
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-cli", "--param", "f_mm", "--param", "k1"]) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].split()[:3] == ["camera_id", "session_id", "version"] and "sigma_k1" in text[0]
    assert version in text[2]
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-cli", "--format", "csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["version"] for r in rows] == [version] and float(rows[0]["delta_f_mm"]) == 0.0
    assert cli.main(["history", "--lake", str(lake), "--from", "2026-04-01", "--to", "2026-04-30",
                     "--format", "json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["camera_id"] == "cam-cli" and row["acquired"] == "2026-04-01T10:00:00Z"
    assert cli.main(["history", "--lake", str(lake), "--from", "2026-05-01", "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == []


def test_history_sql_and_its_errors(cli_run, capsys, monkeypatch):
    lake, _, _, _ = cli_run
    monkeypatch.setenv("FIELDCAL_LAKE", str(lake))
    assert cli.main(["history", "--sql", "SELECT camera_id, n_images FROM catalog", "--format", "csv"]) == 0
    assert capsys.readouterr().out == "camera_id,n_images\ncam-cli,24\n"
    assert cli.main(["history", "--sql", "SELECT nope FROM catalog"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fieldcal history: sql: ") and "nope" in err and err.count("\n") == 1
    assert cli.main(["history", "--sql", "SELECT 1", "--camera", "x"]) == 2


def test_show_a_version_and_the_latest_of_a_camera(cli_run, capsys):
    lake, proc, _, _ = cli_run
    version = proc.stdout.strip()
    assert cli.main(["show", version, "--lake", str(lake)]) == 0
    text = capsys.readouterr().out
    assert f"version   {version}" in text and "f_mm" in text and "rmse_px" in text
    assert cli.main(["show", "latest", "--camera", "cam-cli", "--lake", str(lake), "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == Lake(lake).load_document(version)
    assert cli.main(["show", "latest", "--camera", "nobody", "--lake", str(lake)]) == 1
    assert "no calibration of camera 'nobody'" in capsys.readouterr().err
    assert cli.main(["show", "latest", "--lake", str(lake)]) == 2


# --------------------------------------------------------------------------------------
# fleet, serve, synth, demo
# --------------------------------------------------------------------------------------
def test_fleet_command_reports_each_session(cli_run, capsys, monkeypatch):
    lake, _, _, folder = cli_run
    monkeypatch.setattr(cli, "_prefect_env", lambda verbose: None)
    assert cli.main(["fleet", str(folder.parent), "--lake", str(lake), "--format", "json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert [(s["camera_id"], s["status"]) for s in summary["sessions"]] == [("cam-cli", "calibrated already")]


def test_serve_builds_the_scheduled_deployment(monkeypatch, tmp_path):
    import flows.fleet

    seen = {}
    monkeypatch.setattr(cli, "_prefect_env", lambda verbose: None)
    monkeypatch.setattr(flows.fleet, "serve_fleet", lambda lake, root, **kw: seen.update(lake=lake, root=root, **kw))
    assert cli.main(["serve", "--lake", str(tmp_path), "--cron", "30 1 * * *", "--workers", "3"]) == 0
    assert seen == {"lake": str(tmp_path), "root": None, "name": "nightly", "cron": "30 1 * * *",
                    "parameters": {"n_workers": 3}}


def test_synth_writes_a_valid_session_and_its_truth(tmp_path, capsys):
    from fieldcal.pipeline import prepare

    assert cli.main(["synth", str(tmp_path / "g"), "--seed", "4"]) == 0
    assert cli.main(["synth", str(tmp_path / "f"), "--method", "field", "--scenario", "wide"]) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / "g"), str(tmp_path / "f")]
    g, f = prepare(tmp_path / "g"), prepare(tmp_path / "f")
    assert g.method == "goniometer" and len(g.to_measure) == 180
    assert f.method == "field" and f.to_measure == []                # observations.csv only
    truth = json.loads((tmp_path / "g" / "truth.json").read_text())
    assert truth["parameters"]["f_mm"] == 24.31 and abs(truth["noise_free"]["f_mm"] - 24.31) < 0.5
    assert cli.main(["synth", str(tmp_path / "x"), "--method", "field", "--scenario", "canon5d2"]) == 2


def test_demo_shows_versions_history_and_the_truth_and_its_rerun_is_recognised(dask_cluster, tmp_path,
                                                                               monkeypatch):
    from flows.demo import run_demo

    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    out = io.StringIO()
    assert run_demo(tmp_path / "demo", dask_address=dask_cluster, with_images="no", stream=out,
                    note_stream=io.StringIO()) == 0
    text = out.getvalue()
    for part in ("== 1. synthetic sessions", "== 2. fieldcal run", "== 3. fieldcal show", "== 4. fieldcal history",
                 "calibration next to the truth", "canon5d2-demo", "ixu150-demo"):
        assert part in text, part
    assert text.count(": committed ") == 2
    again = io.StringIO()
    assert run_demo(tmp_path / "demo", dask_address=dask_cluster, with_images="no", stream=again,
                    note_stream=io.StringIO()) == 0
    assert again.getvalue().count(": unchanged ") == 2 and "reused" in again.getvalue()
    assert len(Lake(tmp_path / "demo" / "lake").catalog()) == 2


# --------------------------------------------------------------------------------------
# progress display
# --------------------------------------------------------------------------------------
def test_progress_goes_to_a_terminal_and_nowhere_else():
    term = Terminal()
    with listening(TerminalProgress(term)):
        emit("stage", text="measuring 4 image(s)")
        emit("images", done=2, total=4, cached=1, bad=0)
        emit("images", done=4, total=4, cached=1, bad=1)
    emit("images", done=1, total=1)                   # nobody listening: nothing happens
    text = term.getvalue()
    assert "measuring 4 image(s) ..." in text
    assert "[###############...............] 2/4 (1 cached)" in text
    assert "4/4 (1 cached, 1 bad)" in text and text.endswith("\n")
    assert cli._progress_sink(io.StringIO()) is None
    assert isinstance(cli._progress_sink(Terminal()), TerminalProgress)
