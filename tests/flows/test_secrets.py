"""No storage credential reaches Prefect (flow-run parameters, logs, artifacts) or the lake (issue 24, class 2).

The unit tests cover which options are secrets and how their values come back on the
worker (:mod:`fieldcal.lake.secrets`). The end-to-end test plants a secret in
``--storage-options`` of ``fieldcal run`` and ``fieldcal fleet`` (real subprocesses) against a
lake on the moto S3 server, then looks for its bytes in Prefect's database file, in what
any client reads from the API (flow runs, task runs, logs, artifacts), and in every object
of the lake (commit metadata included): absent. The redaction marker, by contrast, is in
the flow runs' parameters (so the search looks where the secret used to be).
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from fieldcal.errors import InputError
from fieldcal.lake import secrets
from fieldcal.lake.storage import Storage
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
PLANTED = "planted-Secret-7f3c9e"


@pytest.mark.parametrize("options, path", [
    ({"secret": PLANTED}, ("secret",)),
    ({"key": PLANTED}, ("key",)),
    ({"token": PLANTED}, ("token",)),
    ({"password": PLANTED}, ("password",)),
    ({"AWS_SECRET_ACCESS_KEY": PLANTED}, ("AWS_SECRET_ACCESS_KEY",)),
    ({"aws_access_key_id": PLANTED}, ("aws_access_key_id",)),
    ({"account_key": PLANTED}, ("account_key",)),
    ({"connection_string": PLANTED}, ("connection_string",)),
    ({"client_kwargs": {"aws_session_token": PLANTED, "region_name": "eu"}}, ("client_kwargs", "aws_session_token")),
])
def test_every_kind_of_credential_is_redacted_and_comes_back_from_the_environment(options, path):
    red = secrets.redact(options)
    assert PLANTED not in json.dumps(red)
    inner = red
    for k in path:
        inner = inner[k]
    assert inner == secrets.REDACTED
    assert secrets.secret_values(options) == [PLANTED] and secrets.secret_values(red) == []
    env = {secrets.OPTIONS_ENV: json.dumps(options)}
    assert secrets.resolve(red, env) == options                   # the worker's environment gives it back
    assert PLANTED not in json.dumps(secrets.resolve(red, {}))    # else it is left out (the storage's own config)


def test_what_is_not_a_secret_is_kept_and_a_bad_environment_is_one_line():
    options = {"endpoint_url": "http://127.0.0.1:9", "anon": False, "use_ssl": True, "skip_signature": True,
               "client_kwargs": {"region_name": "us-east-1"}, "requester_pays": "yes"}
    assert secrets.redact(options) == options
    assert secrets.resolve(options, {}) is options
    with pytest.raises(InputError, match=r"FIELDCAL_STORAGE_OPTIONS is not JSON"):
        secrets.resolve({"secret": secrets.REDACTED}, {secrets.OPTIONS_ENV: "{nope"})
    with pytest.raises(InputError, match=r"must be a JSON object"):
        secrets.resolve({"secret": secrets.REDACTED}, {secrets.OPTIONS_ENV: "[1]"})


def test_a_lake_opened_with_redacted_options_uses_the_environments_values(monkeypatch):
    full = {"endpoint_url": "http://127.0.0.1:9", "key": "k", "secret": PLANTED}
    monkeypatch.setenv(secrets.OPTIONS_ENV, json.dumps(full))
    store = Storage("s3://bucket/lake", secrets.redact(full))
    assert store.storage_options == full
    assert store.delta_options["AWS_SECRET_ACCESS_KEY"] == PLANTED


def test_exported_holds_the_values_for_the_block_only(monkeypatch):
    monkeypatch.setenv(secrets.OPTIONS_ENV, '{"endpoint_url": "http://before"}')
    full = {"endpoint_url": "http://x", "secret": PLANTED}
    with secrets.exported(full) as red:
        assert red == {"endpoint_url": "http://x", "secret": secrets.REDACTED}
        assert secrets.resolve(red) == full                       # what a lake opened inside finds
    assert os.environ[secrets.OPTIONS_ENV] == '{"endpoint_url": "http://before"}'
    with secrets.exported(red):                                   # already redacted: nothing changes
        assert os.environ[secrets.OPTIONS_ENV] == '{"endpoint_url": "http://before"}'


def _database_file() -> Path:
    from prefect.settings import PREFECT_API_DATABASE_CONNECTION_URL

    url = PREFECT_API_DATABASE_CONNECTION_URL.value()
    assert url and url.startswith("sqlite"), url
    return Path(url.split(":///", 1)[1])


def _api_texts(api: str) -> dict[str, str]:
    out = {}
    for what in ("flow_runs", "task_runs", "logs", "artifacts", "deployments", "variables", "block_documents"):
        r = httpx.post(f"{api}/{what}/filter", json={"limit": 200}, timeout=30)
        assert r.status_code == 200, (what, r.text)
        out[what] = r.text
    return out


def _lake_objects(s3_server, prefix: str) -> dict[str, bytes]:
    client = s3_server.client()
    keys = [o["Key"] for page in client.get_paginator("list_objects_v2").paginate(Bucket=s3_server.bucket,
                                                                                   Prefix=prefix)
            for o in page.get("Contents", [])]
    return {k: client.get_object(Bucket=s3_server.bucket, Key=k)["Body"].read() for k in keys}


@pytest.mark.slow
def test_a_planted_secret_reaches_neither_prefect_nor_the_lake(prefect_server, s3_server, tmp_path):
    prefix = "lake-secret"
    lake = s3_server.url(prefix)
    options = dict(s3_server.storage_options, secret=PLANTED)      # moto accepts any secret
    write_field_session(tmp_path / "one" / "2026-05-01", wide_field(seed=3), images=False, observations_csv=True,
                        camera_id="cam-secret-a", acquired="2026-05-01")
    write_field_session(tmp_path / "root" / "cam-b" / "2026-05-02", wide_field(seed=4), images=False,
                        observations_csv=True, camera_id="cam-secret-b", acquired="2026-05-02")
    env = {k: v for k, v in os.environ.items() if not k.startswith(("FIELDCAL_LAKE", "FIELDCAL_STORAGE"))}
    env.update(PREFECT_API_URL=prefect_server, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE="off")
    text = json.dumps(options)
    run = subprocess.run([FIELDCAL, "run", tmp_path / "one" / "2026-05-01", "--lake", lake, "--storage-options",
                          text], capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert run.returncode == 0, run.stderr
    fleet = subprocess.run([FIELDCAL, "fleet", tmp_path / "root", "--lake", lake, "--storage-options", text],
                           capture_output=True, text=True, env=env, cwd=tmp_path, timeout=600)
    assert fleet.returncode == 0, fleet.stdout + fleet.stderr
    assert "1 committed" in fleet.stdout

    api = _api_texts(prefect_server)
    for what, body in api.items():
        assert PLANTED not in body, what
    runs = [r for r in json.loads(api["flow_runs"]) if r["parameters"].get("lake") == lake]
    assert {r["flow_id"] for r in runs} and len(runs) >= 3     # the run, the fleet and its session's subflow
    for r in runs:
        assert r["parameters"]["storage_options"]["secret"] == secrets.REDACTED
        assert r["parameters"]["storage_options"]["endpoint_url"] == s3_server.endpoint_url
    db = _database_file()
    for f in db.parent.glob(db.name + "*"):                       # the database, its WAL and journal
        assert PLANTED.encode() not in f.read_bytes(), f
    objects = _lake_objects(s3_server, prefix + "/")
    assert any("/_delta_log/" in k for k in objects) and len(objects) > 10
    for k, data in objects.items():
        assert PLANTED.encode() not in data, k


def test_an_existing_prefect_home_is_made_private(tmp_path):
    import stat

    from flows import server

    home = tmp_path / "prefect"
    home.mkdir(mode=0o755)
    for name in ("prefect.db", "prefect.db-wal", "fieldcal-server.log"):
        (home / name).write_bytes(b"x")
        os.chmod(home / name, 0o644)
    (home / "profiles.toml").write_text("")
    server.make_private(home)
    assert stat.S_IMODE(home.stat().st_mode) == 0o700
    for name in ("prefect.db", "prefect.db-wal", "fieldcal-server.log"):
        assert stat.S_IMODE((home / name).stat().st_mode) == 0o600
