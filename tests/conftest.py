"""Shared fixtures: the S3-compatible server (moto) for lake tests on an object store."""

from tests.conftest_s3 import s3_lake, s3_server  # noqa: F401
