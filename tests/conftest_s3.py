"""pytest fixtures for an object-store lake: a moto S3 server on loopback.

Import the fixtures into a conftest or test module (``from tests.conftest_s3 import
s3_server, s3_lake``). The server runs in a thread of the test process on a free port
(``ThreadedMotoServer(port=0)``), so nothing leaves the machine; one bucket is made per
test session and every test gets its own prefix in it.
"""

from __future__ import annotations

import logging
import uuid
from dataclasses import dataclass

import pytest

REGION = "us-east-1"


@dataclass(frozen=True)
class S3Server:
    """A running moto S3 server and what clients need to reach it."""

    endpoint_url: str
    bucket: str

    @property
    def storage_options(self) -> dict:
        """s3fs options (dummy credentials; moto accepts any)."""
        return {"endpoint_url": self.endpoint_url, "key": "testing", "secret": "testing",
                "client_kwargs": {"region_name": REGION}}

    def client(self):
        """A boto3 S3 client of this server."""
        import boto3

        return boto3.client("s3", endpoint_url=self.endpoint_url, region_name=REGION,
                            aws_access_key_id="testing", aws_secret_access_key="testing")

    def url(self, prefix: str) -> str:
        return f"s3://{self.bucket}/{prefix}"


@pytest.fixture(scope="session")
def s3_server():
    """A moto S3 server on 127.0.0.1 (random free port) with one empty bucket."""
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # one log line per request otherwise
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        s3 = S3Server(endpoint_url=f"http://{host}:{port}", bucket="fieldcal-test-lake")
        s3.client().create_bucket(Bucket=s3.bucket)
        yield s3
    finally:
        server.stop()


@pytest.fixture
def s3_lake(s3_server):
    """``(url, storage_options)`` of a fresh, empty lake prefix in the moto bucket."""
    return s3_server.url(f"lake-{uuid.uuid4().hex[:12]}"), s3_server.storage_options
