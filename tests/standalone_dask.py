"""A Dask scheduler and worker processes started the way a standing cluster runs (tests only).

:func:`standalone_cluster` starts ``dask scheduler`` and ``n_workers`` ``dask worker``
processes on loopback (one thread each, the preload and thread settings of
``deploy/dask/``) and yields the scheduler's address, the workers' addresses and the
worker processes (so that a test can kill one).
"""

from __future__ import annotations

import contextlib
import json
import os
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


@contextlib.contextmanager
def standalone_cluster(folder: Path, n_workers: int = 2, *, nanny: bool = True):
    """``(scheduler address, [worker addresses], [worker Popen])`` of a scheduler and its workers.

    With ``nanny=False`` each worker process is the worker itself (killing it removes the
    worker for good); with a nanny, a killed worker is restarted.
    """
    import distributed

    sched_file = Path(folder) / "scheduler.json"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=str(ROOT), DASK_LOGGING__DISTRIBUTED="error")
    procs = []

    def start(name, args):
        # stderr to a file: a pipe nobody reads would block a chatty process once it is full
        log = Path(folder) / f"{name}.log"
        with open(log, "wb") as err:
            p = subprocess.Popen([sys.executable, "-m", *args], env=env, cwd=folder,
                                 stdout=subprocess.DEVNULL, stderr=err)
        p.log = log
        procs.append(p)

    start("scheduler", ["distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                        "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file)])
    try:
        wait_for(sched_file.exists, 60, "the scheduler did not write its file", procs)
        for i in range(n_workers):
            start(f"worker-{i}", ["distributed.cli.dask_worker", "--scheduler-file", str(sched_file),
                                  "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                                  "--nanny" if nanny else "--no-nanny",
                                  "--name", f"w{i}", "--preload", "flows.worker", "--memory-limit", "2GiB"])
        address = json.loads(sched_file.read_text())["address"]
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
