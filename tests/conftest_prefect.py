"""Session-scoped fixtures for the flow tests: one Prefect server, one local Dask cluster.

Import them into ``tests/conftest.py``::

    from tests.conftest_prefect import dask_cluster, prefect_server  # noqa: F401

- ``prefect_server``: Prefect's local server in a subprocess with a temporary SQLite
  database (:func:`prefect.testing.utilities.prefect_test_harness`), started once per test
  session (10-15 s) and shared by every flow test. Its API URL is in Prefect's settings
  for the whole session (and in the fixture's value, for subprocesses: ``PREFECT_API_URL``).
- ``dask_cluster``: a :class:`distributed.LocalCluster` of two single-threaded worker
  processes with fieldcal's worker settings (:func:`flows.cluster.local_cluster_kwargs`);
  its scheduler address is the fixture's value. Tests pass it as ``dask_address`` so that
  only the test of the default path pays for starting a cluster inside the flow. It
  depends on ``prefect_server`` (flows need both; the server outlives the cluster).
"""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def prefect_server():
    """The API URL of a Prefect server that lives for the test session."""
    from prefect.settings import PREFECT_API_URL
    from prefect.testing.utilities import prefect_test_harness

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("PREFECT_SERVER_ANALYTICS_ENABLED", "false")   # no telemetry from the test server
        mp.setenv("DO_NOT_TRACK", "1")
        with prefect_test_harness(server_startup_timeout=120):
            yield PREFECT_API_URL.value()


@pytest.fixture(scope="session")
def dask_cluster(prefect_server):
    """Scheduler address of a two-worker local Dask cluster (fieldcal's worker settings)."""
    import distributed

    from flows.cluster import local_cluster_kwargs

    with distributed.LocalCluster(**local_cluster_kwargs(2, {"processes": True})) as cluster:
        yield cluster.scheduler_address
