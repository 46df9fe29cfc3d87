"""Shared fixtures: the S3-compatible server (moto), Prefect's local server and a Dask cluster.

Each is started once per test session, when a test first asks for it.
"""

from tests.conftest_prefect import dask_cluster, prefect_server  # noqa: F401
from tests.conftest_s3 import s3_lake, s3_server  # noqa: F401
