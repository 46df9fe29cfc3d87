"""The local Prefect server that commands share, with real processes (issue 13 goal 2, issue 17).

Every command here runs as ``fieldcal`` in a process of its own, in the default mode (no
``PREFECT_API_URL``), with an unusable ``HOME`` (its parent is a regular file, so nothing
can be created under it, even by root): Prefect's home moves to a private temporary
folder, the hash cache is off, and everything works. The server they share is started by
the first command that needs one and stops by itself ``FIELDCAL_SERVER_LINGER_S`` seconds
after its last command ended, also when that command was killed with SIGKILL.
"""

import contextlib
import json
import os
import re
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
LINGER_S = 5
pytestmark = pytest.mark.slow


def wait_for(predicate, timeout_s: float, what: str, poll_s: float = 0.2):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll_s)
    raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}")


def alive(pid: int) -> bool:
    """A live process (not a zombie waiting to be reaped)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except OSError:
        return False


def server_pids(home: Path) -> list[int]:
    """Live ``flows.server`` processes whose Prefect home is ``home``."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            cmd = (d / "cmdline").read_bytes()
            env = (d / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"flows.server" in cmd and f"PREFECT_HOME={home}".encode() in env and alive(int(d.name)):
            out.append(int(d.name))
    return out


def _in_session(sid: int) -> list[int]:
    """Pids of the live processes in session ``sid``."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            with contextlib.suppress(OSError):
                if os.getsid(int(d.name)) == sid:
                    out.append(int(d.name))
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """Sessions, a lake, and the environment of a user whose HOME cannot be written."""
    tmp = tmp_path_factory.mktemp("server")
    (tmp / "file").write_text("a regular file where HOME's parent should be\n")
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PREFECT_", "FIELDCAL_", "MPLCONFIGDIR", "XDG_"))}
    env.update(HOME=str(tmp / "file" / "home"), TMPDIR=str(tmp / "tmp"), PYTHONPATH=str(ROOT),
               FIELDCAL_SERVER_LINGER_S=str(LINGER_S))
    (tmp / "tmp").mkdir()
    for k, seed in (("wall-a", 1), ("wall-b", 2)):
        write_field_session(tmp / k, wide_field(seed=seed), images=False, observations_csv=True, camera_id="cam-srv")
    write_session(tmp / "lab", "canon5d2", seed=3, raster_scale=0.25, frames_per_angle=1, camera_id="cam-lab")
    home = tmp / "tmp" / f"fieldcal-{os.getuid()}" / "prefect"   # where Prefect's home moves
    yield tmp, env, home
    subprocess.run([FIELDCAL, "server", "stop"], env=env, capture_output=True, timeout=120)


def test_two_commands_at_once_share_one_server_in_a_temporary_prefect_home(world):
    tmp, env, home = world
    procs = [subprocess.Popen([FIELDCAL, "run", tmp / k, "--lake", tmp / "lake"], env=env, cwd=tmp,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for k in ("wall-a", "wall-b")]
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0 and err == "", err
    versions = {out.strip() for out, _ in outs}
    assert versions == set(Lake(tmp / "lake").catalog()["version"].to_pylist()) and len(versions) == 2
    # one server started, in the temporary Prefect home; the hash cache was off (no image anyway)
    log = (home / "fieldcal-server.log").read_text()
    assert log.count("flows.server: pid") == 1, log
    assert (home / "prefect.db").is_file()
    # private to its user: the database holds every flow run's parameters and logs (issue 24)
    assert stat.S_IMODE(home.stat().st_mode) == 0o700 and stat.S_IMODE(home.parent.stat().st_mode) == 0o700
    for f in home.iterdir():
        if f.name.startswith("prefect.db") or f.name == "fieldcal-server.log":
            assert stat.S_IMODE(f.stat().st_mode) == 0o600, f
    assert not (tmp / "file").is_dir()
    status = subprocess.run([FIELDCAL, "server", "status"], env=env, capture_output=True, text=True, timeout=120)
    assert status.returncode == 0
    if status.stdout.startswith("http"):  # still lingering: it is the one of the log
        pid = json.loads((home / "fieldcal-server.json").read_text())["pid"]
        assert f"pid {pid}" in status.stdout and f"pid {pid}," in log
    else:                                # lingered out already (a slow machine): it is stopping or gone
        wait_for(lambda: server_pids(home) == [], 60, "the lingered-out server to exit")


def test_kill_9_of_a_run_leaves_no_process_behind(world):
    tmp, env, home = world
    lake = tmp / "lake-killed"
    run = subprocess.Popen([FIELDCAL, "run", tmp / "lab", "--lake", lake, "--batch-size", "2"], env=env, cwd=tmp,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    # the run is measuring: its server is up and frames' observations are being written
    wait_for(lambda: any(lake.glob("observations_goniometer/**/*.parquet")), 300, "the run to measure frames")
    state = json.loads((home / "fieldcal-server.json").read_text())
    assert alive(state["pid"]) and run.poll() is None
    os.killpg(run.pid, signal.SIGKILL)
    run.wait(timeout=60)
    # nothing of the run's process group is left, and the server stops LINGER_S after its last command
    wait_for(lambda: not [p for p in Path("/proc").iterdir() if p.name.isdigit() and _pgid(int(p.name)) == run.pid],
             60, "the run's process group to be gone")
    wait_for(lambda: not alive(state["pid"]), LINGER_S + 60, "the server to stop after its last command")
    assert server_pids(home) == [] and not (home / "fieldcal-server.json").exists()
    assert Lake(lake).catalog().num_rows == 0                     # killed before its commit


def _pgid(pid: int) -> int | None:
    try:
        return os.getpgid(pid) if alive(pid) else None
    except OSError:
        return None


def test_server_start_status_stop(world):
    tmp, env, home = world
    start = subprocess.run([FIELDCAL, "server", "start", "--linger", "0"], env=env, capture_output=True, text=True,
                           timeout=300)
    assert start.returncode == 0, start.stderr
    url = start.stdout.strip()
    assert url.startswith("http://127.0.0.1:") and url.endswith("/api")
    status = subprocess.run([FIELDCAL, "server", "status"], env=env, capture_output=True, text=True, timeout=120)
    assert status.returncode == 0 and status.stdout.startswith(url) and "linger 0 s" in status.stdout
    pid = json.loads((home / "fieldcal-server.json").read_text())["pid"]
    stop = subprocess.run([FIELDCAL, "server", "stop"], env=env, capture_output=True, text=True, timeout=120)
    assert stop.returncode == 0 and stop.stdout == f"stopped the local Prefect server at {url} (pid {pid})\n"
    assert not alive(pid) and server_pids(home) == []
    status = subprocess.run([FIELDCAL, "server", "status"], env=env, capture_output=True, text=True, timeout=120)
    assert status.returncode == 0 and status.stdout == f"no local Prefect server under {home}\n"


def test_flows_against_the_local_server_have_no_heartbeat_thread_a_configured_api_keeps_it(monkeypatch, tmp_path):
    """Prefect joins a flow run's heartbeat thread at its end (~1 s, the thread sleeps in steps
    of a second); nothing reads heartbeats on fieldcal's local server, so they are off there
    and stay on against a configured ``PREFECT_API_URL``. (The local server is replaced by its
    address: what is tested is the settings of the block.)"""
    from prefect.settings import PREFECT_API_URL, PREFECT_HOME, get_current_settings, temporary_settings

    from flows import server

    monkeypatch.setattr(server, "local_server", lambda home, note=None: {"url": "http://127.0.0.1:9/api"})
    default = get_current_settings().flows.heartbeat_frequency
    assert default is not None
    with temporary_settings(updates={PREFECT_API_URL: None, PREFECT_HOME: str(tmp_path)}):
        with server.prefect_api() as url:
            assert url == "http://127.0.0.1:9/api"
            assert get_current_settings().flows.heartbeat_frequency is None
        assert get_current_settings().flows.heartbeat_frequency == default
    with temporary_settings(updates={PREFECT_API_URL: "http://127.0.0.1:9/api"}):
        with server.prefect_api():
            assert get_current_settings().flows.heartbeat_frequency == default


def test_ctrl_c_stops_serve_even_when_the_server_no_longer_answers(world):
    # Prefect's shutdown pauses the served schedule on the API; against a server that does
    # not answer it used to wait without end (CI saw `fieldcal serve` ignore Ctrl-C)
    import httpx

    tmp, env, home = world
    err_file = tmp / "serve-stuck.err"
    with open(err_file, "wb") as err_out:     # a file, not a pipe: an orphan holding it cannot hang the test
        serve = subprocess.Popen([FIELDCAL, "serve", "--lake", tmp / "lake-serve", "--root", tmp, "--name", "stuck"],
                                 env=dict(env, FIELDCAL_SERVE_STOP_S="3"), cwd=tmp, stdout=subprocess.DEVNULL,
                                 stderr=err_out, start_new_session=True)
    server_pid = None
    try:
        def registered() -> bool:
            state_file = home / "fieldcal-server.json"
            if not state_file.exists():
                return False
            state = json.loads(state_file.read_text())
            deps = httpx.post(f"{state['url']}/deployments/filter", json={"limit": 50}, timeout=10).json()
            return any(d["name"] == "stuck" for d in deps)

        wait_for(registered, 300, "the served deployment to be registered")
        server_pid = json.loads((home / "fieldcal-server.json").read_text())["pid"]
        os.kill(server_pid, signal.SIGSTOP)                 # the API stops answering
        t = time.monotonic()
        os.killpg(serve.pid, signal.SIGINT)
        serve.wait(timeout=60)
        waited_s = time.monotonic() - t
        left = _in_session(serve.pid)                       # what serve left behind (its own session)
    finally:
        if server_pid is not None:
            os.kill(server_pid, signal.SIGCONT)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(serve.pid, signal.SIGKILL)
        serve.wait()
    err = err_file.read_text()
    # Ctrl-C before Prefect's runner has started needs no answer from the API and ends at
    # once; after it, the shutdown waits for the API and gives up after 3 s (both end, and
    # leave no process of theirs behind)
    assert serve.returncode == 0 and waited_s < 30.0, (waited_s, err)
    assert left == [], (left, err)
    if "did not finish" in err:
        assert waited_s >= 3.0 and "fieldcal serve: stopped (Prefect's shutdown did not finish within 3 s" in err


def test_the_ctrl_c_deadline_ends_the_children_that_hold_standard_error(tmp_path):
    # CI saw `fieldcal serve` exit on its deadline while a child kept its standard error
    # open (the test reading it hung, and the child outlived serve)
    script = ("import subprocess, sys, time\n"
              "from flows.cli import _stop_within\n"
              "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(300)'])\n"
              "_stop_within(1.0)\n"
              "try:\n"
              "    print(child.pid, flush=True)\n"
              "    time.sleep(300)\n"
              "except KeyboardInterrupt:\n"
              "    pass\n"
              "while True:\n"               # a shutdown that never finishes
              "    time.sleep(300)\n")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, start_new_session=True)
    try:
        child = int(proc.stdout.readline())
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)          # EOF: no process holds the pipes any more
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert proc.returncode == 0 and "did not finish within 1 s" in err, err
    assert not Path(f"/proc/{child}").exists() or _in_session(proc.pid) == []


def test_server_start_ui_serves_prefects_ui_pointed_at_its_own_api(tmp_path):
    import httpx

    env = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "FIELDCAL_"))}
    env.update(PREFECT_HOME=str(tmp_path / "prefect"), PYTHONPATH=str(ROOT))
    out = subprocess.run([FIELDCAL, "server", "start", "--ui", "--linger", "0"], env=env, capture_output=True,
                         text=True, timeout=300)
    try:
        assert out.returncode == 0, out.stderr
        api = out.stdout.strip()
        ui = re.search(r"Prefect UI: (\S+)", out.stderr).group(1)
        assert api == f"{ui}/api"
        assert "<!DOCTYPE html>" in httpx.get(ui, timeout=30).text
        assert httpx.get(f"{ui}/ui-settings", timeout=30).json()["api_url"] == api
        status = subprocess.run([FIELDCAL, "server", "status"], env=env, capture_output=True, text=True, timeout=60)
        assert f"UI {ui}" in status.stdout
    finally:
        subprocess.run([FIELDCAL, "server", "stop"], env=env, capture_output=True, timeout=120)
