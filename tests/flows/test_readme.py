"""Every command line of the README's "Command line" section runs as written (issue 13, goal 6).

The lines are read from README.md (the indented ``fieldcal ...`` lines of the section), their
capitalised placeholders filled in (a small observations-only session and its root, a lake,
the versions the first lines print, a photograph of the session's size, output paths), and
each runs as the real ``fieldcal`` console script against the test session's Prefect
server, in the README's order. Each must exit 0. ``serve`` runs until its deployment is
registered and is then stopped with Ctrl-C (SIGINT), which must also give exit status 0.
"""

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
import tifffile

from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def readme_lines() -> list[str]:
    """The ``fieldcal`` command lines of the README's "Command line" section, in order."""
    text = (ROOT / "README.md").read_text()
    start = text.index("\n## Command line\n")
    end = text.index("\n## ", start + 1)
    return [ln.strip() for ln in text[start:end].splitlines() if ln.startswith("    fieldcal ")]


def readme_env(prefect_server, tmp_path) -> dict:
    """The environment of the README's commands: the test session's Prefect server, own caches."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "FIELDCAL_"))}
    env.update(PREFECT_API_URL=prefect_server, PREFECT_HOME=str(tmp_path / "prefect"), PYTHONPATH=str(ROOT),
               FIELDCAL_HASH_CACHE=str(tmp_path / "hashes.sqlite"))
    return env


def test_the_readme_lists_every_command():
    from flows.cli import build_parser

    commands = {shlex.split(ln)[1] for ln in readme_lines()}
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert commands == set(sub.choices)


def test_every_command_line_of_the_readme_runs_as_written(prefect_server, tmp_path):
    root = tmp_path / "sessions"
    session = root / "cam-readme" / "2026-06-01"
    write_field_session(session, wide_field(seed=61), images=False, observations_csv=True, camera_id="cam-readme",
                        acquired="2026-06-01")
    write_field_session(root / "cam-readme" / "2026-06-02", wide_field(seed=62), images=False,
                        observations_csv=True, camera_id="cam-readme", acquired="2026-06-02")
    sensor = json.loads((session / "session.json").read_text())["sensor"]
    photo = np.random.default_rng(0).integers(0, 255, (sensor["height_px"], sensor["width_px"]), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "photo.tif", photo)
    values = {"SESSION": session, "ROOT": root, "LAKE": tmp_path / "lake", "ID": "cam-readme",
              "OUT.json": tmp_path / "doc.json", "FILE.png": tmp_path / "history.png", "FILE": tmp_path / "export.txt",
              "DIR": tmp_path / "out", "OUT": tmp_path / "synth", "OUT2": tmp_path / "synth2",
              "IMAGE.tif": tmp_path / "photo.tif", "OUT.tif": tmp_path / "undistorted.tif"}
    env = readme_env(prefect_server, tmp_path)
    versions, synthesised = [], []
    for line in readme_lines():
        values.update(VERSION=versions[-1] if versions else "", V1=versions[0] if versions else "",
                      V2=versions[-1] if versions else "")
        argv = [FIELDCAL] + [str(values.get(a, a)) for a in shlex.split(line, comments=True)[1:]]
        assert not [a for a in argv if re.fullmatch(r"[A-Z][A-Z0-9]*(\.[a-z]+)?", a)], f"unfilled: {line}"
        if argv[1] == "serve":
            run_serve(argv, env, tmp_path, prefect_server, values["LAKE"])
            continue
        if argv[1] == "demo":            # its own test (test_readme_demo.py), beside this one
            continue
        if "--pdf" in argv and not chromium_available():
            print(f"README line without --pdf: Chromium is not installed (apt-get install chromium): {line}")
            argv.remove("--pdf")
        out = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=900)
        assert out.returncode == 0, f"{line}\n{out.stderr[-2000:]}"
        if argv[1] == "run":
            versions.append(out.stdout.strip())
        if argv[1] == "synth":           # what synth writes calibrates, end to end (issue 30)
            made = Path(out.stdout.strip())
            run = subprocess.run([FIELDCAL, "run", str(made), "--lake", str(tmp_path / "synth-lake")], env=env,
                                 cwd=tmp_path, capture_output=True, text=True, timeout=900)
            assert run.returncode == 0, f"fieldcal run of {line}\n{run.stderr[-2000:]}"
            synthesised.append(run.stdout.strip())
    lake = Lake(values["LAKE"])
    assert len(versions) == 2 and set(versions) < set(lake.catalog()["version"].to_pylist())
    assert len(lake.catalog()) == 3                      # run, run --force, and the fleet's other session
    for made in ("doc.json", "history.png", "export.txt", "out/report.html", "undistorted.tif", "synth/session.json",
                 "out/certificate.html") + (("out/certificate.pdf",) if chromium_available() else ()):
        assert (tmp_path / made).exists(), made
    synth_lines = [ln for ln in readme_lines() if ln.split()[1] == "synth"]
    assert len(synthesised) == len(synth_lines) >= 2
    synth_lake = Lake(tmp_path / "synth-lake")
    assert set(synthesised) == set(synth_lake.catalog()["version"].to_pylist())
    checked = [synth_lake.load_document(v)["stats"].get("check_points") for v in synthesised]
    assert any(cp and cp["n_withheld"] == 20 for cp in checked)


def chromium_available() -> bool:
    from fieldcal.products.pdf import PdfError, chromium

    try:
        chromium()
    except PdfError:
        return False
    return True


def run_serve(argv, env, tmp_path, api, lake):
    """Run ``fieldcal serve ...`` until its deployment is registered, then Ctrl-C: exit status 0."""
    proc = subprocess.Popen(argv, env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    deadline = time.monotonic() + 300
    registered = False
    try:
        while not registered and time.monotonic() < deadline and proc.poll() is None:
            deps = httpx.post(f"{api}/deployments/filter", json={"limit": 200}, timeout=10).json()
            registered = any(d["parameters"].get("lake") == str(lake) for d in deps)
            time.sleep(1)
    finally:
        os.killpg(proc.pid, signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=120)
        except subprocess.TimeoutExpired:        # fail, but leave no process behind for later tests
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
            raise
    assert registered, err[-2000:]
    assert proc.returncode == 0, err[-2000:]
    assert "serving recalibrate-fleet/nightly on cron '0 2 * * *'" in err
