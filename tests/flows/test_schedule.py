"""Scheduled recalibration, for real: a standing Prefect server's scheduler starts the fleet flow.

Issue 13, goal 1. One ``prefect server start`` (its own home and SQLite database, all of
its services, as in production) and, against it, both ways of deploying the fleet flow with
a one-minute cron schedule:

- ``fieldcal serve --cron '* * * * *'`` (one process serves the deployment and runs its
  scheduled flow runs);
- ``deploy/prefect.yaml`` (its cron made every minute, nothing else changed) through
  ``prefect work-pool create`` / ``prefect deploy`` / ``prefect worker start`` with a
  process work pool.

The test waits (at most 7 minutes) until each deployment has a flow run that the
*scheduler* created (``auto_scheduled``) and that completed, and a new version is in each
lake. Under SQLAlchemy 2.1.9 the scheduler fails every loop and no run is ever created.
"""

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
PREFECT = str(Path(sys.executable).with_name("prefect"))
WAIT_S = 420.0
pytestmark = pytest.mark.slow


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def standing_server(tmp_path_factory):
    """``(api_url, env)`` of a ``prefect server start`` of the test's own (scheduler included)."""
    tmp = tmp_path_factory.mktemp("standing")
    port = free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "FIELDCAL_"))}
    env.update(PREFECT_HOME=str(tmp / "prefect"), PREFECT_SERVER_ANALYTICS_ENABLED="false",
               PREFECT_UI_ENABLED="false", PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE=str(tmp / "hashes.sqlite"))
    log = open(tmp / "server.log", "w")
    server = subprocess.Popen([PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port)], env=env,
                              stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    url = f"http://127.0.0.1:{port}/api"
    deadline = time.monotonic() + 180
    while True:
        try:
            if httpx.get(f"{url}/health", timeout=5).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        assert server.poll() is None and time.monotonic() < deadline, (tmp / "server.log").read_text()[-2000:]
        time.sleep(0.5)
    yield url, dict(env, PREFECT_API_URL=url), tmp
    os.killpg(server.pid, signal.SIGINT)
    try:
        server.wait(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(server.pid, signal.SIGKILL)
        server.wait()
    log.close()


def scheduled_and_completed(url: str, deployment: str) -> bool:
    """Whether ``recalibrate-fleet/<deployment>`` has a completed flow run made by the scheduler."""
    r = httpx.get(f"{url}/deployments/name/recalibrate-fleet/{deployment}", timeout=10)
    if r.status_code != 200:
        return False
    # (the scheduler keeps up to 100 future runs: ask for the completed ones only)
    runs = httpx.post(f"{url}/flow_runs/filter", timeout=10,
                      json={"deployments": {"id": {"any_": [r.json()["id"]]}},
                            "flow_runs": {"state": {"type": {"any_": ["COMPLETED"]}}}, "limit": 10}).json()
    return any(run["auto_scheduled"] and run["state_type"] == "COMPLETED" for run in runs)


def test_the_schedule_fires_for_fieldcal_serve_and_for_deploy_prefect_yaml(standing_server):
    url, env, tmp = standing_server
    root = tmp / "sessions"
    write_field_session(root / "cam-sched" / "2026-07-01", wide_field(seed=51), images=False, observations_csv=True,
                        camera_id="cam-sched", acquired="2026-07-01")
    lake_serve, lake_yaml = tmp / "lake-serve", tmp / "lake-yaml"
    shutil.copytree(root, lake_yaml / "sessions")               # the yaml's root: <lake>/sessions
    procs = []
    logs = contextlib.ExitStack()
    try:
        procs.append(subprocess.Popen(
            [FIELDCAL, "serve", "--lake", lake_serve, "--root", root, "--cron", "* * * * *", "--name", "every-minute"],
            env=env, cwd=tmp, stdout=logs.enter_context(open(tmp / "serve.log", "w")), stderr=subprocess.STDOUT,
            start_new_session=True))

        spec = (ROOT / "deploy" / "prefect.yaml").read_text()
        assert spec.count('cron: "0 2 * * *"') == 1
        (tmp / "prefect.yaml").write_text(spec.replace('cron: "0 2 * * *"', 'cron: "* * * * *"'))
        yaml_env = dict(env, FIELDCAL_HOME=str(ROOT), FIELDCAL_LAKE=str(lake_yaml))
        for cmd in ([PREFECT, "work-pool", "create", "fieldcal", "--type", "process"],
                    [PREFECT, "--no-prompt", "deploy", "--prefect-file", str(tmp / "prefect.yaml"), "--all"]):
            out = subprocess.run(cmd, env=yaml_env, cwd=ROOT, capture_output=True, text=True, timeout=300)
            assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
        procs.append(subprocess.Popen([PREFECT, "worker", "start", "--pool", "fieldcal"], env=yaml_env, cwd=tmp,
                                      stdout=logs.enter_context(open(tmp / "worker.log", "w")),
                                      stderr=subprocess.STDOUT, start_new_session=True))

        deadline = time.monotonic() + WAIT_S
        done = {}
        while time.monotonic() < deadline and len(done) < 2:
            for name in ("every-minute", "nightly"):
                if name not in done and scheduled_and_completed(url, name):
                    done[name] = time.monotonic()
            assert all(p.poll() is None for p in procs), [p.args for p in procs if p.poll() is not None]
            time.sleep(2)
        assert set(done) == {"every-minute", "nightly"}, ((tmp / "serve.log").read_text()[-3000:]
                                                          + (tmp / "worker.log").read_text()[-3000:])
        for lake in (lake_serve, lake_yaml):
            (row,) = Lake(lake).catalog().to_pylist()             # the scheduled run's new version (the next
            assert (row["camera_id"], row["session_id"]) == ("cam-sched", "2026-07-01")   # runs: calibrated already)
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        logs.close()
    assert procs[0].returncode == 0                               # Ctrl-C stops `fieldcal serve` cleanly
    said = (tmp / "serve.log").read_text()                        # each run it starts and how it ended
    started = re.findall(r"fieldcal serve: run (fleet/cam-sched/\S+|fleet/sessions/\S+): started", said)
    assert started and re.search(rf"fieldcal serve: run {re.escape(started[0])}: completed in [0-9.]+ s: "
                                 r"1 found, 1 committed, 0 failed, 0 skipped", said), said[-3000:]
