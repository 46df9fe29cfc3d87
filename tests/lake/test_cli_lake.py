"""``fieldcal lake log|optimize|vacuum|check`` and ``history --as-of`` / read-only ``--sql``
through the CLI's entry point (in this process: fast)."""

import datetime as dt
import json
import time

import pytest

from fieldcal.lake.store import Lake
from flows import cli
from tests.lake.test_lake import field_document, residual_table


@pytest.fixture
def lake_dir(tmp_path):
    lake = Lake(tmp_path)
    lake.commit(field_document("cam-a", "s1"), {}, residual_table(), info={"flow_run_id": "run-1"})
    time.sleep(0.05)
    lake.commit(field_document("cam-a", "s2", f_mm=50.2), {}, residual_table())
    return tmp_path


def test_lake_log_lists_who_committed_what(lake_dir, capsys):
    assert cli.main(["lake", "log", "--lake", str(lake_dir), "--table", "catalog", "--format", "json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    commits = [r for r in rows if r["action"] == "commit"]
    assert [r["session_id"] for r in commits] == ["s2", "s1"]  # newest first
    assert commits[1]["flow_run_id"] == "run-1" and commits[0]["code_version"] and commits[0]["host"]
    assert rows[-1]["operation"] == "CREATE TABLE"


def test_history_as_of_and_read_only_sql_through_the_cli(lake_dir, capsys):
    first = Lake(lake_dir).tables.log("catalog")[-2]["time"] + dt.timedelta(milliseconds=1)
    assert cli.main(["history", "--lake", str(lake_dir), "--camera", "cam-a", "--format", "json",
                     "--as-of", first.isoformat()]) == 0
    assert [r["session_id"] for r in json.loads(capsys.readouterr().out)] == ["s1"]
    status = cli.main(["history", "--lake", str(lake_dir), "--sql",
                       f"COPY (SELECT * FROM catalog) TO '{lake_dir}/catalog/x.parquet'"])
    err = capsys.readouterr().err
    assert status == 2 and "read-only" in err and len(err.splitlines()) == 1
    assert not (lake_dir / "catalog" / "x.parquet").exists()


def test_optimize_vacuum_and_check_commands(lake_dir, capsys):
    assert cli.main(["lake", "optimize", "--lake", str(lake_dir), "--table", "catalog"]) == 0
    assert "catalog: 2 file(s) compacted into 1" in capsys.readouterr().out
    assert cli.main(["lake", "vacuum", "--lake", str(lake_dir), "--retention-hours", "0"]) == 2
    assert "at least 1" in capsys.readouterr().err
    assert cli.main(["lake", "vacuum", "--lake", str(lake_dir)]) == 0
    out = capsys.readouterr().out
    assert "catalog: would delete 0 file(s)" in out  # the replaced files are younger than a week
    # ... and it says so, with the retention (issue 30)
    assert ("catalog: 2 replaced file(s) younger than the retention of 168 h are kept (readers of older "
            "snapshots and --as-of need them; --retention-hours sets it, at least 1)") in out
    assert cli.main(["lake", "check", "--lake", str(lake_dir)]) == 0
    assert "no damage found" in capsys.readouterr().out
    assert cli.main(["lake", "log", "--lake", str(lake_dir), "--table", "nope"]) == 2
