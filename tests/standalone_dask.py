"""A Dask scheduler and worker processes started the way a standing cluster runs (tests only).

:func:`standalone_cluster` starts ``dask scheduler`` and ``n_workers`` ``dask worker``
processes on loopback (one thread each, the preload and thread settings of
``deploy/dask/``) and yields the scheduler's address, the workers' addresses and the
worker processes (so that a test can kill one).

With ``hide``, the scheduler and the workers run in a mount namespace of their own
(``unshare --mount``, as root) in which an empty tmpfs lies over each of those folders
(the flow's temporary folder, the test's): the cluster shares no disk with the flow, as on
other machines, and any path of the flow's host that reaches a task fails there.
:func:`isolation_problem` says why that cannot be done on this machine, if it cannot.
"""

from __future__ import annotations

import contextlib
import json
import os
import shlex
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def wait_for(predicate, timeout_s: float, what: str, procs=()) -> None:
    """Poll ``predicate`` every 0.1 s; fail early when one of ``procs`` has exited.

    ``procs`` are :class:`subprocess.Popen` with a ``log`` attribute (their stderr file).
    """
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: a process exited with {p.returncode}: "
                                   f"{Path(p.log).read_text(errors='replace')[-2000:]}")
        time.sleep(0.1)
    raise TimeoutError(f"{what} within {timeout_s} s")


def hidden_folders(paths) -> list[str]:
    """The outermost of ``paths`` (resolved): a tmpfs over each hides the others inside it."""
    real = sorted({os.path.realpath(p) for p in paths})
    return [p for p in real if not any(p != q and p.startswith(q.rstrip("/") + "/") for q in real)]


def _isolated(command: list[str], hide: list[str]) -> list[str]:
    """``command`` in a mount namespace of its own with an empty tmpfs over each of ``hide``."""
    mounts = " && ".join(f"mount -t tmpfs -o size=256m,mode=1777 fieldcal-hidden {shlex.quote(d)}" for d in hide)
    return ["unshare", "--mount", "--propagation", "private", "sh", "-c",
            f"{mounts} && cd / && exec {shlex.join(command)}"]


def isolation_problem(hide) -> str | None:
    """Why processes cannot be started with ``hide`` covered (:func:`standalone_cluster`), or None."""
    if shutil.which("unshare") is None:
        return "unshare(1) is not installed (util-linux)"
    if os.geteuid() != 0:
        return "not root: unshare --mount needs CAP_SYS_ADMIN"
    for what, path in (("the project", ROOT), ("the Python environment", sys.prefix)):
        inside = [h for h in hidden_folders(hide) if os.path.realpath(path).startswith(h.rstrip("/") + "/")]
        if inside:
            return f"{what} ({path}) lies under {inside[0]}, which the workers must not see: run from elsewhere"
    probe = _isolated(["ls", "-A", *hidden_folders(hide)], hidden_folders(hide))
    out = subprocess.run(probe, capture_output=True, text=True, timeout=30)
    if out.returncode != 0:
        return f"unshare --mount failed here: {(out.stderr or out.stdout).strip()[:200]}"
    if out.stdout.strip():
        return f"a tmpfs mounted over {hidden_folders(hide)} did not hide them: {out.stdout.strip()[:200]}"
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def standalone_cluster(folder: Path, n_workers: int = 2, *, nanny: bool = True, hide=(), env: dict | None = None):
    """``(scheduler address, [worker addresses], [worker Popen])`` of a scheduler and its workers.

    With ``nanny=False`` each worker process is the worker itself (killing it removes the
    worker for good); with a nanny, a killed worker is restarted. ``hide``: folders the
    processes must not see (module docstring; call :func:`isolation_problem` first); ``env``:
    more environment variables of the processes.
    """
    import distributed

    sched_file = Path(folder) / "scheduler.json"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=str(ROOT), DASK_LOGGING__DISTRIBUTED="error", **(env or {}))
    hide = hidden_folders(hide) if hide else []
    procs = []

    def start(name, args):
        # stderr to a file: a pipe nobody reads would block a chatty process once it is full
        # (opened here: a process that cannot see the folder still writes to it)
        log = Path(folder) / f"{name}.log"
        command = [sys.executable, "-m", *args]
        with open(log, "wb") as err:
            p = subprocess.Popen(_isolated(command, hide) if hide else command, env=env, cwd=folder,
                                 stdout=subprocess.DEVNULL, stderr=err)
        p.log = log
        procs.append(p)

    # hidden: a fixed port instead of the scheduler's file, which the flow could not read
    port = _free_port() if hide else 0
    where = ["--scheduler-file", str(sched_file)] if not hide else []
    start("scheduler", ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                        "--no-dashboard", "--dashboard-address", "127.0.0.1:0", *where])
    try:
        if hide:
            address = f"tcp://127.0.0.1:{port}"
            target = [address]
        else:
            wait_for(sched_file.exists, 60, "the scheduler did not write its file", procs)
            address = json.loads(sched_file.read_text())["address"]
            target = where
        for i in range(n_workers):
            start(f"worker-{i}", ["distributed.cli.dask_worker", *target,
                                  "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                                  "--nanny" if nanny else "--no-nanny",
                                  "--name", f"w{i}", "--preload", "flows.worker", "--memory-limit", "2GiB"])
        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(n_workers, timeout=120)
            by_pid = {pid: a for a, pid in client.run(os.getpid).items()}
        # without a nanny each process is its worker: list the addresses in process order
        addresses = [by_pid.get(p.pid) for p in procs[1:]] if not nanny else sorted(by_pid.values())
        yield address, addresses, procs[1:]
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
