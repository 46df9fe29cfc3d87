"""The ``fieldcal`` command line: run (CONTRACT section 5), history, show, fleet, serve, synth.

``fieldcal run`` is exercised as a real subprocess (piped: stdout must be the version and
nothing else) against the test session's Prefect server; the other commands run in this
process through :func:`flows.cli.main`. "Input first": the commands that must not reach a
server are given an API address where nothing listens (``UNREACHABLE``), so any attempt to
use Prefect would fail them.
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
from flows import cli, cli_common, server

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
UNREACHABLE = "http://127.0.0.1:9/api"          # the discard port: nothing listens there
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def env_for(prefect_server, tmp_path, **extra):
    env = dict(os.environ, PREFECT_API_URL=prefect_server, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE=str(tmp_path / "hashes.sqlite"), PYTHONPATH=str(ROOT))
    env.pop("FIELDCAL_LAKE", None)
    env.update(extra)
    return env


def fieldcal(*args, env, cwd, timeout=300):
    return subprocess.run([FIELDCAL, *map(str, args)], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=timeout)


@pytest.fixture(scope="module")
def cli_run(prefect_server, tmp_path_factory):
    """``fieldcal run`` in a subprocess, piped, the lake from FIELDCAL_LAKE: (lake, process, json path)."""
    tmp = tmp_path_factory.mktemp("cli")
    folder = tmp / "sessions" / "2026-04-01-wall"
    write_field_session(folder, wide_field(seed=7), images=False, observations_csv=True, camera_id="cam-cli",
                        acquired="2026-04-01T10:00:00Z")
    lake = tmp / "lake"
    out_json = tmp / "doc.json"
    proc = fieldcal("run", folder, "--json", out_json, env=env_for(prefect_server, tmp, FIELDCAL_LAKE=str(lake)),
                    cwd=tmp)
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


def test_bad_input_is_one_line_naming_the_file_exit_2_and_nothing_in_the_lake(tmp_path):
    folder = tmp_path / "bad"
    write_field_session(folder, wide_field(seed=8), images=False, observations_csv=True)
    lines = (folder / "targets.csv").read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + ",not-a-number,1,2,,"
    (folder / "targets.csv").write_text("\n".join(lines) + "\n")
    lake = tmp_path / "lake"
    # no Prefect server can be reached: the session is refused before one is looked for
    proc = fieldcal("run", folder, "--lake", lake, env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line.startswith("fieldcal run: ") and "targets.csv" in line and "not-a-number" in line
    assert not lake.exists()


@pytest.mark.parametrize("what", ["missing folder", "empty folder"])
def test_a_session_that_is_not_there_is_refused_without_a_server(tmp_path, what):
    folder = tmp_path / "nothing"
    if what == "empty folder":
        folder.mkdir()
    proc = fieldcal("run", folder, "--lake", tmp_path / "lake", env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line.startswith(f"fieldcal run: {folder}") and ("not found" in line or "session.json" in line)
    assert not (tmp_path / "lake").exists()


def test_a_missing_images_folder_is_bad_input(tmp_path):
    """One image's file missing leaves that image out; the session's whole images/ folder missing
    is bad input: exit 2, one line naming the folder, nothing written (issue 30)."""
    folder = tmp_path / "noimages"
    write_field_session(folder, wide_field(seed=8), images=False, image_indices=range(5))   # listed, not written
    proc = fieldcal("run", folder, "--lake", tmp_path / "lake", env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    (line,) = proc.stderr.splitlines()
    assert line == (f"fieldcal run: {folder / 'images'}{os.sep}: no such folder; the session lists 5 image(s) "
                    "in it (images/wide_001.tif, ...)")
    assert not (tmp_path / "lake").exists()


def test_version_and_an_unknown_option_with_the_commands_usage(capsys):
    from fieldcal.contract.fingerprint import code_version

    with pytest.raises(SystemExit) as done:
        cli.main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out == f"fieldcal {code_version()}\n"
    with pytest.raises(SystemExit) as done:
        cli.main(["history", "--lake", "x", "--cammera", "y"])
    err = capsys.readouterr().err
    assert done.value.code == 2 and err.startswith("usage: fieldcal history ")
    assert err.strip().endswith("fieldcal history: error: unrecognized arguments: --cammera y "
                                "(did you mean --camera?)")
    with pytest.raises(SystemExit):
        cli.main(["--bogus"])
    assert capsys.readouterr().err.startswith("usage: fieldcal [-h] [--version]")


def test_an_output_path_that_cannot_be_written_is_refused_before_any_work(cli_run, tmp_path):
    _, _, _, folder = cli_run
    lake = tmp_path / "lake"
    proc = fieldcal("run", folder, "--lake", lake, "--json", tmp_path / "missing" / "out.json",
                    env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    missing = tmp_path / "missing"
    assert proc.stderr == f"fieldcal run: --json {missing / 'out.json'}: no folder {missing}\n"
    assert not lake.exists()                         # nothing committed


def test_a_rerun_of_unchanged_inputs_is_answered_from_the_lake_without_a_server(cli_run, tmp_path):
    lake, proc, _, folder = cli_run
    out_json = tmp_path / "again.json"
    again = fieldcal("run", folder, "--lake", lake, "--json", out_json, env=env_for(UNREACHABLE, tmp_path),
                     cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    assert again.stdout == proc.stdout and again.stderr == ""
    assert json.loads(out_json.read_text())["version"] == proc.stdout.strip()
    assert len(Lake(lake).catalog()) == 1


def test_run_without_a_lake_is_a_usage_error(monkeypatch, capsys, tmp_path):
    monkeypatch.delenv("FIELDCAL_LAKE", raising=False)
    assert cli.main(["run", str(tmp_path)]) == 2
    assert capsys.readouterr().err == "fieldcal run: no lake: give --lake LAKE or set FIELDCAL_LAKE\n"


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_run_on_a_terminal_shows_the_extraction_progress(tmp_path, monkeypatch, capsys):
    from fieldcal.synthetic.goniometer import write_session

    write_session(tmp_path / "lab", "canon5d2", seed=9, raster_scale=0.25, frames_per_angle=1, camera_id="cam-t")
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    monkeypatch.setattr(server, "quiet_prefect", lambda verbose: None)     # keep this process's environment
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    # the default local cluster: in-process workers of this run's own, started in no time
    status = cli.main(["run", str(tmp_path / "lab"), "--lake", str(tmp_path / "lake"), "--batch-size", "20"])
    out = capsys.readouterr().out
    assert status == 0
    version = out.strip()
    assert out == version + "\n" and Lake(tmp_path / "lake").row(version)["camera_id"] == "cam-t"
    text = term.getvalue()
    assert "measuring images [" in text and "60/60" in text and "validating" in text
    assert "starting the Dask cluster" in text
    assert "new version" in text and "goniometer calibration" in text


# --------------------------------------------------------------------------------------
# history and show; no silent empty answers
# --------------------------------------------------------------------------------------
def test_history_of_a_camera_as_table_csv_and_json(cli_run, capsys):
    lake, proc, _, _ = cli_run
    version = proc.stdout.strip()
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-cli", "--param", "f_mm", "--param", "k1"]) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].split() == ["session_id", "acquired", "f_mm", "sigma_f_mm", "k1", "sigma_k1"]
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-cli", "--param", "k1", "--wide"]) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0].split()[:3] == ["camera_id", "session_id", "version"] and "delta_k1" in text[0]
    assert version in text[2]
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-cli", "--format", "csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["version"] for r in rows] == [version] and float(rows[0]["delta_f_mm"]) == 0.0
    assert cli.main(["history", "--lake", str(lake), "--from", "2026-04-01", "--to", "2026-04-30",
                     "--format", "json"]) == 0
    (row,) = json.loads(capsys.readouterr().out)
    assert row["camera_id"] == "cam-cli" and row["acquired"] == "2026-04-01T10:00:00Z"
    assert cli.main(["history", "--lake", str(lake), "--from", "2026-05-01", "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == []                # a date range may be empty


def test_history_sql_and_its_errors(cli_run, capsys, monkeypatch):
    lake, _, _, _ = cli_run
    monkeypatch.setenv("FIELDCAL_LAKE", str(lake))
    assert cli.main(["history", "--sql", "SELECT camera_id, n_images FROM catalog", "--format", "csv"]) == 0
    assert capsys.readouterr().out == "camera_id,n_images\ncam-cli,24\n"
    assert cli.main(["history", "--sql", "SELECT nope FROM catalog"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fieldcal history: ") and "nope" in err and err.count("\n") == 1
    assert "sql:" not in err                                         # no internal context word
    assert cli.main(["history", "--sql", "SELECT 1", "--camera", "cam-cli"]) == 2


def test_unknown_camera_version_and_lake_are_errors_that_say_what_exists(cli_run, capsys, tmp_path):
    lake, proc, _, _ = cli_run
    version = proc.stdout.strip()
    assert cli.main(["history", "--lake", str(lake), "--camera", "cam-clj"]) == 2
    assert capsys.readouterr().err == (f"fieldcal history: camera 'cam-clj' has no calibration in {lake}; "
                                       "closest: cam-cli\n")
    assert cli.main(["show", "latest", "--camera", "nobody", "--lake", str(lake)]) == 2
    assert capsys.readouterr().err == (f"fieldcal show: camera 'nobody' has no calibration in {lake}; "
                                       "1 camera(s): cam-cli\n")
    typo = version[:-1] + ("0" if version[-1] != "0" else "1")
    assert cli.main(["show", typo, "--lake", str(lake)]) == 2
    assert capsys.readouterr().err == f"fieldcal show: no version '{typo}' in {lake}; closest: {version}\n"
    for argv in (["history", "--camera", "cam-cli"], ["show", "latest", "--camera", "cam-cli"],
                 ["history", "--sql", "SELECT 1"]):
        assert cli.main([*argv, "--lake", str(tmp_path / "nolake")]) == 2
        assert capsys.readouterr().err == f"fieldcal {argv[0]}: no lake at {tmp_path / 'nolake'}\n"


def test_show_a_version_and_the_latest_of_a_camera(cli_run, capsys):
    lake, proc, _, _ = cli_run
    version = proc.stdout.strip()
    assert cli.main(["show", version, "--lake", str(lake)]) == 0
    text = capsys.readouterr().out
    assert f"version   {version}" in text and "f_mm" in text and "rmse_px" in text
    assert cli.main(["show", "latest", "--camera", "cam-cli", "--lake", str(lake), "--format", "json"]) == 0
    assert json.loads(capsys.readouterr().out) == Lake(lake).load_document(version)
    assert cli.main(["show", "latest", "--lake", str(lake)]) == 2


def test_a_closed_pipe_ends_a_command_quietly(cli_run, tmp_path):
    lake, _, _, _ = cli_run
    # the reader is gone before the command writes (`fieldcal history ... | head -1` once head has exited)
    proc = subprocess.Popen([FIELDCAL, "history", "--lake", lake, "--sql", "SELECT range AS n FROM range(1000)",
                             "--format", "csv"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    proc.stdout.close()
    with proc.stderr:
        err = proc.stderr.read()
    assert proc.wait(timeout=300) == 141                          # as a command killed by SIGPIPE
    assert err == b""                                             # no BrokenPipeError, no traceback


def test_one_line_messages_name_the_command_once_and_no_internal_function():
    from fieldcal.errors import InputError, LakeError

    assert cli_common.error_line("compare", InputError("'latest' needs --camera ID", "fieldcal")) == \
        ("fieldcal compare: 'latest' needs --camera ID", 2)
    assert cli_common.error_line("history", InputError("end '1' is before start '2'", "fleet")) == \
        ("fieldcal history: end '1' is before start '2'", 2)
    assert cli_common.error_line("run", InputError("empty value in column 'X'", "/s/targets.csv:4")) == \
        ("fieldcal run: /s/targets.csv:4: empty value in column 'X'", 2)
    assert cli_common.error_line("show", LakeError("cannot read /l/catalog: Permission denied")) == \
        ("fieldcal show: cannot read /l/catalog: Permission denied", 1)
    assert cli_common.error_line("run", ValueError("boom\nsecond line")) == \
        ("fieldcal run: ValueError: boom second line (--verbose for details)", 1)


# --------------------------------------------------------------------------------------
# fleet, serve, synth
# --------------------------------------------------------------------------------------
def test_fleet_of_calibrated_sessions_answers_from_the_lake_with_their_versions(cli_run, tmp_path):
    lake, proc, _, folder = cli_run
    out = fieldcal("fleet", folder.parent, "--lake", lake, "--format", "json", env=env_for(UNREACHABLE, tmp_path),
                   cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    (entry,) = json.loads(out.stdout)["sessions"]
    assert (entry["camera_id"], entry["status"], entry["version"]) == ("cam-cli", "calibrated already",
                                                                       proc.stdout.strip())


def test_fleet_root_that_does_not_exist_or_holds_no_session_is_an_error(cli_run, capsys, tmp_path):
    lake, _, _, _ = cli_run
    assert cli.main(["fleet", str(tmp_path / "nowhere"), "--lake", str(lake)]) == 2
    assert capsys.readouterr().err == f"fieldcal fleet: {tmp_path / 'nowhere'}: no folder of sessions there\n"
    (tmp_path / "empty").mkdir()
    assert cli.main(["fleet", str(tmp_path / "empty"), "--lake", str(lake)]) == 2
    assert "no session under" in capsys.readouterr().err


def test_serve_checks_its_input_and_builds_the_scheduled_deployment(monkeypatch, tmp_path, capsys):
    import flows.fleet

    seen = {}
    monkeypatch.setattr(server, "quiet_prefect", lambda verbose: None)
    monkeypatch.setattr(flows.fleet, "serve_fleet", lambda lake, root, **kw: seen.update(lake=lake, root=root, **kw))
    assert cli.main(["serve", "--lake", str(tmp_path), "--cron", "61 1 * * *"]) == 2
    assert "is not a cron schedule" in capsys.readouterr().err and not seen
    assert cli.main(["serve", "--lake", str(tmp_path), "--cron", "30 1 * * *"]) == 2     # no tmp_path/sessions
    assert "no folder of sessions there" in capsys.readouterr().err and not seen
    (tmp_path / "sessions").mkdir()
    assert cli.main(["serve", "--lake", str(tmp_path), "--cron", "30 1 * * *", "--workers", "3"]) == 0
    report = seen.pop("report")                      # told each run it starts and how it ended
    report("run fleet/x: completed in 1.0 s")
    assert "fieldcal serve: run fleet/x: completed in 1.0 s" in capsys.readouterr().err
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
    assert capsys.readouterr().err == ("fieldcal synth: field scenario must be 'paper' or 'wide', "
                                       "got 'canon5d2'\n")
    assert not (tmp_path / "x").exists()


def test_synth_of_images_shows_the_rendering_progress_on_a_terminal(tmp_path, monkeypatch, capsys):
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    assert cli.main(["synth", str(tmp_path / "img"), "--method", "field", "--scenario", "wide", "--images",
                     "--n-images", "3", "--scale", "0.1"]) == 0
    assert "rendering images [" in term.getvalue() and "3/3" in term.getvalue()


def test_synth_refuses_fewer_images_than_calibrate(tmp_path, capsys):
    assert cli.main(["synth", str(tmp_path / "two"), "--method", "field", "--images", "--n-images", "2"]) == 2
    assert capsys.readouterr().err == ("fieldcal synth: --n-images must be at least 3 (the field method "
                                       "calibrates from 3 or more images sharing targets), got 2\n")
    assert not (tmp_path / "two").exists()


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
    assert cli_common.progress_sink(io.StringIO()) is None
    assert isinstance(cli_common.progress_sink(Terminal()), TerminalProgress)


def test_ctrl_c_ends_serve_within_its_grace_even_when_the_shutdown_hangs(tmp_path):
    # flows.cli._stop_within, which `fieldcal serve` installs: a shutdown that never
    # finishes (here: the KeyboardInterrupt handler sleeps) is cut after the grace period
    import signal
    import time

    script = ("import time\n"
              "from flows.cli import _stop_within\n"
              "_stop_within(1.0)\n"
              "try:\n"
              "    print('ready', flush=True)     # inside the try: the parent's Ctrl-C may come at once\n"
              "    time.sleep(120)\n"
              "except KeyboardInterrupt:\n"
              "    time.sleep(120)          # Prefect's shutdown waiting for an API that does not answer\n")
    proc = subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline() == "ready\n"
        t = time.monotonic()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        waited_s = time.monotonic() - t
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and 1.0 <= waited_s < 60.0
    assert err == ("fieldcal serve: stopped (Prefect's shutdown did not finish within 1 s; "
                   "the served schedule may still be active on the server)\n")


def test_run_keeps_freed_frame_memory_only_with_its_workers_in_its_own_process(monkeypatch):
    import argparse

    from fieldcal.measure import heap

    calls = []
    monkeypatch.delenv("FIELDCAL_DASK_ADDRESS", raising=False)
    monkeypatch.setattr(heap, "keep_freed_memory", lambda: calls.append(1) or True)
    assert cli._keep_frame_memory(argparse.Namespace(dask=None, processes=False)) is True
    assert cli._keep_frame_memory(argparse.Namespace(dask="tcp://10.0.0.1:8786", processes=False)) is False
    assert cli._keep_frame_memory(argparse.Namespace(dask=None, processes=True)) is False
    assert calls == [1]
