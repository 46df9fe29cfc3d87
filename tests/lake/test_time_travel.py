"""``--as-of`` by the commit timestamps the Delta log records, not by file times (issue 24, class 5).

A lake copied with ``cp -r`` (or synced, restored from a backup, re-uploaded to S3) has
every file modified at the time of the copy; delta-rs's own time travel by timestamp uses
those times, so an ``--as-of`` before the copy read an empty lake. The commits' own
timestamps (``commitInfo.timestamp``) travel with the files.
"""

import datetime as dt
import json
import os
import subprocess
import time

import pytest

from fieldcal.lake import history
from fieldcal.lake.store import Lake
from tests import conftest_s3
from tests.lake.test_lake import field_document, residual_table
from tests.lake.test_lake_faults import cli

s3_server = conftest_s3.s3_server
UTC = dt.UTC


def two_batches(root):
    """cam-a s1 and cam-b s1 committed, then the time ``then``, then cam-a s2."""
    lake = Lake(root)
    first = [lake.commit(field_document(c, "s1", seed=i), {}, residual_table(10))
             for i, c in enumerate(("cam-a", "cam-b"))]
    time.sleep(0.05)                    # commit timestamps are milliseconds: keep them apart
    then = dt.datetime.now(UTC)
    time.sleep(0.05)
    later = lake.commit(field_document("cam-a", "s2", seed=5, f_mm=50.1), {}, residual_table(12))
    return [str(v) for v in first], str(later), then


def answers_as_of(lake, first, later, then):
    assert sorted(lake.catalog(as_of=then)["version"].to_pylist()) == sorted(first)
    assert sorted(history.fleet(lake, as_of=then)["version"].to_pylist()) == sorted(first)
    assert history.camera_history(lake, "cam-a", as_of=then)["version"].to_pylist() == [first[0]]
    assert history.sql(lake, "SELECT count(*) AS n FROM residuals", as_of=then)["n"].to_pylist() == [20]
    assert lake.catalog(as_of=then - dt.timedelta(days=1)).num_rows == 0
    assert sorted(lake.catalog(as_of=dt.datetime.now(UTC))["version"].to_pylist()) == sorted(first + [later])


def test_as_of_on_a_lake_copied_with_cp_r(tmp_path):
    first, later, then = two_batches(tmp_path / "lake")
    time.sleep(0.05)
    subprocess.run(["cp", "-r", str(tmp_path / "lake"), str(tmp_path / "copy")], check=True)
    log = tmp_path / "copy" / "catalog" / "_delta_log"
    assert min(os.path.getmtime(p) for p in log.glob("*.json")) > then.timestamp()   # file times say: after
    answers_as_of(Lake(tmp_path / "copy"), first, later, then)
    out = cli("history", "--fleet", "--lake", tmp_path / "copy", "--as-of", then.isoformat(), "--format", "json")
    assert out.returncode == 0, out.stderr
    assert sorted(r["version"] for r in json.loads(out.stdout)) == sorted(first)


def test_as_of_on_a_lake_re_uploaded_to_s3(tmp_path, s3_server):
    import s3fs

    first, later, then = two_batches(tmp_path / "lake")
    time.sleep(1.1)                     # S3 LastModified has whole seconds
    url = s3_server.url(f"reupload-{os.getpid()}-{time.time_ns()}")
    fs = s3fs.S3FileSystem(**{k: v for k, v in s3_server.storage_options.items() if k != "endpoint_url"},
                           endpoint_url=s3_server.endpoint_url)
    fs.put(str(tmp_path / "lake") + "/", url.removeprefix("s3://") + "/", recursive=True)
    lake = Lake(url, s3_server.storage_options)
    assert lake.storage.mtime("catalog/_delta_log/00000000000000000000.json") > then.timestamp()
    answers_as_of(lake, first, later, then)


@pytest.mark.parametrize("offset_s", [-3600.0, 3600.0])
def test_as_of_does_not_depend_on_file_times_at_all(tmp_path, offset_s):
    """Commit files' times moved an hour either way (a restore, a clock of the file server)."""
    first, later, then = two_batches(tmp_path / "lake")
    for p in (tmp_path / "lake").rglob("*"):
        st = p.stat()
        os.utime(p, (st.st_atime + offset_s, st.st_mtime + offset_s))
    answers_as_of(Lake(tmp_path / "lake"), first, later, then)
