"""Where the image fan-out runs: a local Dask cluster by default, an existing scheduler when given.

Both are the same code path (DESIGN.md): a :class:`prefect_dask.DaskTaskRunner`, either
making a temporary :class:`distributed.LocalCluster` for the run or connecting to the
scheduler at ``address``. The address comes from the flow's ``dask_address`` parameter,
else from the environment variable ``FIELDCAL_DASK_ADDRESS``.

Local clusters run their workers as threads of the flow's process by default: starting
and stopping worker processes (each importing Prefect, fieldcal and OpenCV) costs 3 s
(quiet) to 8-13 s (loaded) per run on this 2-core machine, which 72 full-size images do not
amortise (bench/README.md: 18-26 % of the wall time outside reading, extraction and
solving, against 8-14 % with in-process workers); the image work is NumPy, OpenCV and
tifffile code that releases the GIL for its heavy parts. ``processes=True`` (``fieldcal run --processes``) gives one
single-threaded worker process each instead, with the BLAS / OpenMP thread counts pinned to
1 in their environment and the preload :mod:`flows.worker`. A deployment points at a
standing cluster (``--dask ADDRESS``); settings for a real cluster are in ``deploy/dask/``.
"""

from __future__ import annotations

import os

__all__ = ["THREAD_ENV", "DEFAULT_WORKERS", "dask_address", "task_runner", "local_cluster_kwargs",
           "in_process", "runner_in_process", "worker_count", "worker_slots"]

ADDRESS_ENV = "FIELDCAL_DASK_ADDRESS"
DEFAULT_WORKERS = 2
PRELOAD = "flows.worker"
"""Module every worker imports at start (:mod:`flows.worker`)."""
THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""Environment of the worker processes: one BLAS / OpenMP thread each."""


def dask_address(address: str | None = None) -> str | None:
    """The scheduler address to use: ``address``, else ``$FIELDCAL_DASK_ADDRESS``, else None (local)."""
    value = address or os.environ.get(ADDRESS_ENV) or None
    return value.strip() if isinstance(value, str) and value.strip() else None


def local_cluster_kwargs(n_workers: int = DEFAULT_WORKERS, extra: dict | None = None) -> dict:
    """Keyword arguments of the temporary :class:`distributed.LocalCluster`."""
    kwargs = {"n_workers": int(n_workers), "threads_per_worker": 1, "processes": False,
              "dashboard_address": None, "env": dict(THREAD_ENV), "preload": [PRELOAD],
              # no dashboard; the scheduler's HTTP server (health, metrics) on a free loopback
              # port instead of 8787, which another cluster on the machine may hold
              "scheduler_kwargs": {"dashboard": False, "dashboard_address": "127.0.0.1:0"}}
    kwargs.update(extra or {})
    if not kwargs.get("processes", False):
        kwargs.pop("env", None)      # in-process workers share this process's environment
        kwargs.pop("preload", None)  # ... and its imports
    return kwargs


def task_runner(address: str | None = None, n_workers: int = DEFAULT_WORKERS,
                cluster_kwargs: dict | None = None):
    """A :class:`prefect_dask.DaskTaskRunner` for the scheduler at ``address`` or a local cluster."""
    from prefect_dask import DaskTaskRunner

    address = dask_address(address)
    if address:
        return DaskTaskRunner(address=address)
    return DaskTaskRunner(cluster_kwargs=local_cluster_kwargs(n_workers, cluster_kwargs))


def in_process(address: str | None = None, cluster_kwargs: dict | None = None) -> bool:
    """Whether :func:`task_runner` would run the workers as threads of this process."""
    return dask_address(address) is None and not (cluster_kwargs or {}).get("processes", False)


def runner_in_process(runner) -> bool:
    """:func:`in_process` asked of a :class:`prefect_dask.DaskTaskRunner` made already (the
    command line hands the flow one): no address, and a local cluster with ``processes=False``
    (``LocalCluster``'s own default is processes)."""
    kwargs = getattr(runner, "cluster_kwargs", None) or {}
    return getattr(runner, "address", None) is None and kwargs.get("processes", True) is False


def worker_count(client, timeout_s: float = 60.0) -> int:
    """Threads available on the cluster behind a Dask ``client`` (waits for a first worker).

    Raises
    ------
    RuntimeError
        No worker joined within ``timeout_s``.
    """
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except TimeoutError:
        raise RuntimeError(f"no Dask worker joined the scheduler at {client.scheduler.address} "
                           f"within {timeout_s:g} s") from None
    return max(1, len(worker_slots(client)))


def worker_slots(client) -> list[str]:
    """The worker threads of the cluster behind a Dask ``client``: each worker's address
    once per thread, sorted (the slots :func:`fieldcal.batch.assign_batches` places batches on)."""
    workers = client.scheduler_info(n_workers=-1).get("workers", {})
    return sorted(addr for addr, info in workers.items() for _ in range(max(1, int(info.get("nthreads", 1)))))
