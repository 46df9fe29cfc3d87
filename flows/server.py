"""The Prefect API a command reports to: the configured one, else a local server kept in the background.

:func:`prefect_api` gives a command its API, in this order:

1. ``PREFECT_API_URL`` (environment or Prefect profile): a ``prefect server start`` or
   Prefect Cloud. fieldcal starts nothing.
2. A local server started by an earlier fieldcal command under the same ``PREFECT_HOME``
   and still running: its address is in ``PREFECT_HOME/fieldcal-server.json``; found in a
   few milliseconds.
3. Otherwise it starts one (8-20 s on a 2-core machine, a SQLite database in
   ``PREFECT_HOME``): ``python -m flows.server`` in a session of its own, so that the next
   command finds it instead of paying for another.

Lifetime of that server. Every command that uses it holds a shared lock on
``PREFECT_HOME/fieldcal-server.clients`` (the kernel drops it when the process ends, also by
``kill -9``). The server checks the lock every second and stops itself ``linger_s`` seconds
after the last command ended (default 600 s, ``FIELDCAL_SERVER_LINGER_S``; 0 = only when
told). ``fieldcal server stop`` stops it at once (it also stops when its state file is
removed); ``fieldcal server start`` starts one ahead of the commands and ``fieldcal server
status`` shows it. No command leaves anything else behind: the server is the only process
that outlives a command, and only for ``linger_s``.

The server is Prefect's own application (:func:`prefect.server.api.server.create_app`)
under uvicorn, with its services (the scheduler of ``fieldcal serve``'s deployment among
them); with the web UI when started by ``fieldcal server start --ui`` (its state's
``ui_url``), else without it (a command that only needs the API starts faster).

Flow-run heartbeats are off for the flows a command runs against that local server.
Prefect's heartbeat thread sleeps in steps of a second and is joined when a flow run ends,
which made every run ~1 s longer (``bench/README_flow.md``), and nothing on the local server
reads the heartbeats (they feed automations that detect crashed runs, which one sets up
on a server of one's own). Against a configured ``PREFECT_API_URL`` they stay on, and so
do the runs of a deployment (``fieldcal serve``), which run in processes of their own.

:func:`prepare_environment` runs first in every command: with an unwritable or missing
``HOME`` it moves Prefect's home and Matplotlib's cache to a private temporary folder and
turns the image-hash cache off, instead of failing later with many lines.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import fcntl
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from fieldcal.errors import FieldcalError, one_line

__all__ = ["prefect_api", "prepare_environment", "quiet_prefect", "prefect_home", "local_server", "env_seconds",
           "start_server", "stop_server", "server_status", "make_private", "ServerError", "DEFAULT_LINGER_S",
           "LINGER_ENV"]

STATE_FILE = "fieldcal-server.json"
CLIENTS_FILE = "fieldcal-server.clients"
START_LOCK = "fieldcal-server.lock"
LOG_FILE = "fieldcal-server.log"
LINGER_ENV = "FIELDCAL_SERVER_LINGER_S"
DEFAULT_LINGER_S = 600.0
START_TIMEOUT_S = 120.0
LOCK_TIMEOUT_S = 180.0


class ServerError(FieldcalError):
    """The local Prefect server cannot be started, reached or stopped."""


# --------------------------------------------------------------------------------------
# the environment: HOME, PREFECT_HOME, caches
# --------------------------------------------------------------------------------------
def _usable_dir(path: Path) -> bool:
    """Whether ``path`` is (or can be made) a folder this process can create files in."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
        return True
    except OSError:
        return False


def _private_tmp(name: str) -> Path:
    return Path(tempfile.gettempdir()) / f"fieldcal-{os.getuid()}" / name


PRIVATE_FILES = ("prefect.db", "prefect.db-wal", "prefect.db-shm", "prefect.db-journal", LOG_FILE, STATE_FILE)
"""Files of Prefect's home that hold the flow runs (parameters, logs): 0600 (:func:`make_private`)."""


def make_private(home: Path) -> None:
    """Make Prefect's home readable by its user only: the folder 0700, its database 0600.

    The database holds every flow run's parameters, logs and artifacts; SQLite creates it
    with the process's umask (0644 under the usual 022). Only a folder this user owns is
    changed (a home someone else prepared is left as it is). The local server itself runs
    with the umask 077 (:func:`_launch`), so that what it creates later is private too."""
    try:
        if home.stat().st_uid != os.getuid():
            return
        os.chmod(home, 0o700)
        for name in PRIVATE_FILES:
            with contextlib.suppress(FileNotFoundError):
                os.chmod(home / name, 0o600)
    except OSError:
        pass                                   # not ours to change (a read-only mount): leave it


def prepare_environment() -> None:
    """Make the per-user folders usable before Prefect, Matplotlib or the hash cache start.

    - ``PREFECT_HOME`` (default ``~/.prefect``) that cannot be written: Prefect's home
      becomes ``$TMPDIR/fieldcal-<uid>/prefect`` (the same for every command, so the local
      server is still shared).
    - ``~/.config/matplotlib`` that cannot be written: ``MPLCONFIGDIR`` in the same place.
    - the image-hash cache folder that cannot be written: the cache is off
      (``FIELDCAL_HASH_CACHE=off``; every image is hashed from its bytes).

    Raises
    ------
    ServerError
        Neither Prefect's home nor the temporary folder can be written.
    """
    home = prefect_home()
    if not _usable_dir(home):
        tmp = _private_tmp("prefect")
        if not _usable_dir(tmp):
            raise ServerError(f"no writable folder for Prefect: {home} and {tmp} cannot be written "
                              "(set PREFECT_HOME)")
        make_private(tmp.parent)
        os.environ["PREFECT_HOME"] = str(tmp)
    if not os.environ.get("MPLCONFIGDIR"):
        mpl = Path(os.path.expanduser("~")) / ".config" / "matplotlib"
        if not _usable_dir(mpl):
            os.environ["MPLCONFIGDIR"] = str(_private_tmp("matplotlib"))
    if not os.environ.get("FIELDCAL_HASH_CACHE"):
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        if not _usable_dir(Path(base) / "fieldcal"):
            os.environ["FIELDCAL_HASH_CACHE"] = "off"


def prefect_home() -> Path:
    """Prefect's home folder: ``PREFECT_HOME``, else ``~/.prefect`` (read without importing Prefect)."""
    return Path(os.path.expanduser(os.environ.get("PREFECT_HOME") or "~/.prefect"))


def quiet_prefect(verbose: bool = False) -> None:
    """Quiet Prefect's and Dask's console (not the logs sent to the API) before Prefect is imported."""
    if not verbose:
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_FLOW_RUNS_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_TASK_RUNS_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "CRITICAL")
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
        os.environ.setdefault("PYTHONWARNINGS", "ignore")      # Dask's worker processes: one line on failure
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


# --------------------------------------------------------------------------------------
# locks and the state file
# --------------------------------------------------------------------------------------
@contextlib.contextmanager
def _flock(path: Path, mode: int, what: str, timeout_s: float = LOCK_TIMEOUT_S):
    """Hold ``flock(mode)`` on ``path`` for the block (released when the process ends, too)."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, mode | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    raise ServerError(f"timed out after {timeout_s:g} s waiting for {what} ({path})") from None
                time.sleep(0.1)
        yield fd
    finally:
        os.close(fd)


def _read_state(home: Path) -> dict | None:
    try:
        state = json.loads((home / STATE_FILE).read_text())
    except (OSError, ValueError):
        return None
    return state if isinstance(state, dict) and isinstance(state.get("pid"), int) else None


def _write_state(home: Path, state: dict) -> None:
    tmp = home / f".{STATE_FILE}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(state, indent=2) + "\n")
    os.replace(tmp, home / STATE_FILE)


def _remove_state(home: Path, pid: int) -> None:
    state = _read_state(home)
    if state is not None and state["pid"] == pid:
        with contextlib.suppress(OSError):
            (home / STATE_FILE).unlink()


def _alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            return f.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except OSError:
        return False


def _is_server_process(pid: int) -> bool:
    """Whether ``pid`` is a live ``flows.server`` process (its command line empties as it exits)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            cmd = f.read().split(b"\0")
    except OSError:
        return False
    return b"flows.server" in cmd and _alive(pid)


def _healthy(url: str, timeout_s: float = 5.0) -> bool:
    import httpx

    try:
        return httpx.get(f"{url}/health", timeout=timeout_s).status_code == 200
    except httpx.HTTPError:
        return False


def _free_port() -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# --------------------------------------------------------------------------------------
# client side
# --------------------------------------------------------------------------------------
def env_seconds(name: str, default: float, *, positive: bool = False, error=None) -> float:
    """A duration [s] from the environment variable ``name``, or ``default`` when unset.

    Raises ``error`` (default :class:`ServerError`) naming the variable when it is not a
    number (or, with ``positive``, not above 0)."""
    text = os.environ.get(name, "").strip()
    if not text:
        return float(default)
    try:
        value = float(text)
    except ValueError:
        value = None
    if value is None or value != value or abs(value) == float("inf") or (positive and not value > 0):
        kind = "a positive number" if positive else "a number"
        raise (error or ServerError)(f"{name} must be {kind} of seconds, got {text!r}")
    return value


def linger_seconds() -> float:
    """``FIELDCAL_SERVER_LINGER_S`` or the default; 0 or less: until ``fieldcal server stop``."""
    return env_seconds(LINGER_ENV, DEFAULT_LINGER_S)


def server_status(home: Path | None = None) -> dict | None:
    """The state of the running local server (``pid``, ``url``, ``started``, ...), or None."""
    home = home or prefect_home()
    state = _read_state(home)
    if state is None or not _is_server_process(state["pid"]) or not _healthy(state["url"]):
        return None
    return state


def _launch(home: Path, port: int, linger_s: float, ui: bool = False) -> int:
    """Start ``python -m flows.server`` detached (its own session, not our child); returns its pid.

    With ``ui`` the server also serves Prefect's web UI at its root, told where its API is
    (``PREFECT_UI_API_URL``: the port is chosen here)."""
    source = str(Path(__file__).resolve().parents[1])          # where `flows` is, installed or not
    env = dict(os.environ, PREFECT_HOME=str(home), PREFECT_UI_ENABLED="true" if ui else "false",
               PREFECT_UI_API_URL=f"http://127.0.0.1:{port}/api",
               PREFECT_SERVER_ANALYTICS_ENABLED="false", PREFECT_SERVER_LOGGING_LEVEL="WARNING",
               PYTHONPATH=os.pathsep.join(p for p in (source, os.environ.get("PYTHONPATH")) if p))
    env.pop("PREFECT_API_URL", None)
    cmd = [sys.executable, "-m", "flows.server", "--port", str(port), "--linger", str(linger_s)]
    cmd += ["--ui"] if ui else []
    launcher = ("import os, subprocess, sys\n"
                "os.umask(0o077)\n"                      # the database, its journal, the log: 0600
                "log = open(sys.argv[1], 'ab')\n"
                "p = subprocess.Popen(sys.argv[2:], stdin=subprocess.DEVNULL, stdout=log, stderr=log,"
                " start_new_session=True, close_fds=True)\n"
                "print(p.pid)\n")
    out = subprocess.run([sys.executable, "-c", launcher, str(home / LOG_FILE), *cmd], env=env,
                         capture_output=True, text=True, check=True, cwd=home)     # holds no user folder
    return int(out.stdout.strip())


def _log_tail(home: Path) -> str:
    try:
        lines = [ln for ln in (home / LOG_FILE).read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return one_line(lines[-1]) if lines else ""


def _start(home: Path, linger_s: float, note, ui: bool = False) -> dict:
    port = _free_port()
    if note:
        kept = f"kept for {linger_s:g} s after the last command" if linger_s > 0 else "kept until stopped"
        note(f"starting a local Prefect server under {home} ({kept}; `fieldcal server stop` stops it, "
             "PREFECT_API_URL uses another)")
    t = time.perf_counter()
    pid = _launch(home, port, linger_s, ui)
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        state = _read_state(home)
        if state is not None and state["pid"] == pid and _healthy(state["url"]):
            if note:
                note(f"Prefect server ready at {state['url']} in {time.perf_counter() - t:.1f} s")
            return state
        if not _alive(pid):
            raise ServerError(f"the local Prefect server stopped while starting: {_log_tail(home)} "
                              f"(log: {home / LOG_FILE})")
        time.sleep(0.1)
    with contextlib.suppress(OSError):
        os.kill(pid, signal.SIGKILL)
    raise ServerError(f"the local Prefect server did not start within {START_TIMEOUT_S:g} s (log: {home / LOG_FILE})")


def local_server(home: Path | None = None, *, note=None, linger_s: float | None = None, ui: bool = False) -> dict:
    """The running local server's state, starting one when there is none (see the module docstring).

    With ``ui`` the server must serve Prefect's UI: a running one without it is an error
    (:class:`ServerError`: stop it first)."""
    home = home or prefect_home()
    home.mkdir(parents=True, exist_ok=True)
    make_private(home)
    with _flock(home / START_LOCK, fcntl.LOCK_EX, "another command starting the local Prefect server"):
        state = server_status(home)
        if state is not None:
            if ui and not state.get("ui_url"):
                raise ServerError(f"the local Prefect server at {state['url']} runs without its UI; "
                                  "`fieldcal server stop`, then `fieldcal server start --ui`")
            return state
        stale = _read_state(home)
        if stale is not None:
            _remove_state(home, stale["pid"])
        return _start(home, linger_seconds() if linger_s is None else float(linger_s), note, ui)


def start_server(linger_s: float | None = None, note=None, ui: bool = False) -> dict:
    """Start the local server now (``fieldcal server start [--ui]``); returns its state
    (``ui_url`` the address of Prefect's UI when it serves it)."""
    return local_server(note=note, linger_s=linger_s, ui=ui)


def stop_server(timeout_s: float = 30.0) -> dict | None:
    """Stop the local server (``fieldcal server stop``); returns the state it had, or None."""
    home = prefect_home()
    if not home.is_dir():
        return None
    with _flock(home / START_LOCK, fcntl.LOCK_EX, "another command starting the local Prefect server"):
        state = _read_state(home)
        if state is None:
            return None
        pid = state["pid"]
        if _is_server_process(pid):
            os.kill(pid, signal.SIGTERM)
            deadline = time.monotonic() + timeout_s
            while _alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
                deadline = time.monotonic() + 10.0
                while _alive(pid) and time.monotonic() < deadline:
                    time.sleep(0.05)
        _remove_state(home, pid)
        return state


@contextlib.contextmanager
def prefect_api(note=None):
    """Make sure flows have a Prefect API for the block (see the module docstring).

    Parameters
    ----------
    note : callable, optional
        Called with a line of text about starting the local server (for a terminal).

    Yields
    ------
    str
        The API URL in use.
    """
    from prefect.settings import (
        PREFECT_API_URL,
        PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
        get_current_settings,
        temporary_settings,
    )

    settings = get_current_settings()
    if settings.api.url:
        yield str(settings.api.url)
        return
    home = Path(settings.home)
    home.mkdir(parents=True, exist_ok=True)
    with _flock(home / CLIENTS_FILE, fcntl.LOCK_SH, "the local Prefect server to stop"):
        url = local_server(home, note=note)["url"]
        with temporary_settings(updates={PREFECT_API_URL: url, PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
            try:
                yield url
            finally:
                _drain_prefect()


def _drain_prefect() -> None:
    """Send the logs and events still queued to the server (else they are lost or exit hangs)."""
    import inspect

    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker
    from prefect.utilities.asyncutils import run_coro_as_sync

    async def drain():
        try:
            result = APILogWorker.instance().drain()
            if inspect.isawaitable(result):
                await result
        except RuntimeError:
            pass
        result = EventsWorker.drain_all()
        if inspect.isawaitable(result):
            await result

    try:
        run_coro_as_sync(drain())
    except Exception:  # noqa: BLE001 - best effort: never turn a finished run into a failure
        pass


# --------------------------------------------------------------------------------------
# the server process: python -m flows.server --port P --linger S
# --------------------------------------------------------------------------------------
def _watch(server, home: Path, port: int, linger_s: float, ui: bool = False) -> None:
    """Publish the server's address once it serves; stop it when nobody has used it for ``linger_s``."""
    while not server.started:
        if server.should_exit:
            return
        time.sleep(0.05)
    pid = os.getpid()
    _write_state(home, {"pid": pid, "url": f"http://127.0.0.1:{port}/api", "port": port,
                        "ui_url": f"http://127.0.0.1:{port}" if ui else None,
                        "started": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                        "linger_s": linger_s, "log": str(home / LOG_FILE)})
    fd = os.open(home / CLIENTS_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    idle_since = time.monotonic()
    while not server.should_exit:
        time.sleep(1.0)
        state = _read_state(home)
        if state is None or state["pid"] != pid:          # removed (`server stop`, the folder deleted)
            server.should_exit = True
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:                            # a command is using the server
            idle_since = None
            continue
        now = time.monotonic()
        idle_since = now if idle_since is None else idle_since
        if linger_s > 0 and now - idle_since >= linger_s:
            _remove_state(home, pid)                       # keep the lock: a new command waits for the exit
            server.should_exit = True
            return
        fcntl.flock(fd, fcntl.LOCK_UN)


def main(argv=None) -> int:
    """Run the local Prefect server until it lingers out or is stopped (module docstring)."""
    ap = argparse.ArgumentParser(prog="python -m flows.server")
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--linger", type=float, default=DEFAULT_LINGER_S)
    ap.add_argument("--ui", action="store_true", help="also serve Prefect's web UI")
    args = ap.parse_args(argv)
    import uvicorn
    from prefect.server.api.server import create_app

    home = prefect_home()
    print(f"{dt.datetime.now(dt.UTC).isoformat(timespec='seconds')} flows.server: pid {os.getpid()}, "
          f"port {args.port}, linger {args.linger:g} s, home {home}", file=sys.stderr, flush=True)
    server = uvicorn.Server(uvicorn.Config(create_app(final=True), host="127.0.0.1", port=args.port,
                                           log_level="error", lifespan="on"))
    threading.Thread(target=_watch, args=(server, home, args.port, args.linger, args.ui), daemon=True).start()
    try:
        server.run()
    finally:
        _remove_state(home, os.getpid())
    return 0


if __name__ == "__main__":
    sys.exit(main())
