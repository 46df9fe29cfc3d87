"""Shared fixtures: the S3-compatible server (moto), Prefect's local server and a Dask cluster.

Each is started once per test session, when a test first asks for it.

Hypothesis runs derandomised (the profile ``ci``, the default): the same commit draws the
same examples on every machine, so a verdict never depends on chance. To search further
(new examples every run, many more of them), run with ``HYPOTHESIS_PROFILE=explore``.
"""

import os

from hypothesis import settings

from tests.conftest_prefect import dask_cluster, prefect_server  # noqa: F401
from tests.conftest_s3 import s3_lake, s3_server  # noqa: F401

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", derandomize=False, database=None, deadline=None, max_examples=5000,
                          print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
