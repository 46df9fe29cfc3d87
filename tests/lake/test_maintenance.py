"""Audit and upkeep: commit metadata in the tables' history, automatic compaction and
checkpoints, ``optimize``, a ``vacuum`` that keeps every committed version, the data
dictionary kept current."""

import datetime as dt
import os
import time

import pytest

from fieldcal.contract.fingerprint import code_version
from fieldcal.errors import LakeError
from fieldcal.lake import history
from fieldcal.lake.dictionary import data_dictionary
from fieldcal.lake.store import Lake
from tests.lake.test_lake import field_document, field_measurements, residual_table


def data_files(root, table):
    return sorted(p for p in (root / table).rglob("*.parquet") if "_delta_log" not in p.parts)


def test_every_commit_records_who_made_it_in_the_table_history(tmp_path):
    lake = Lake(tmp_path)
    v = lake.commit(field_document(), {}, residual_table(), info={"flow_run_id": "run-1234"})
    lake.write_observations("cam-a", "s1", "images/IMG_0.tif", "a" * 64, field_measurements())
    (entry,) = [e for e in lake.tables.log("catalog") if e.get("action") == "commit"]
    assert entry["version"] == v and entry["flow_run_id"] == "run-1234"
    assert entry["code_version"] == code_version() and entry["pid"] == str(os.getpid())
    assert entry["host"] and entry["camera_id"] == "cam-a" and entry["fingerprint"].startswith("sha256:")
    assert isinstance(entry["time"], dt.datetime)
    (res,) = [e for e in lake.tables.log("residuals") if e.get("action") == "residuals"]
    assert res["version"] == v
    (obs,) = [e for e in lake.tables.log("observations_field") if e.get("action") == "observations"]
    assert obs["image"] == "images/IMG_0.tif"


def test_compaction_and_checkpoints_come_every_n_commits(tmp_path):
    lake = Lake(tmp_path, maintain_every=4)
    versions = [lake.commit(field_document("cam-a", f"s{i}"), {}, residual_table(5, seed=i))
                for i in range(9)]
    log = tmp_path / "catalog" / "_delta_log"
    assert any(p.name.endswith(".checkpoint.parquet") for p in log.iterdir())
    ops = [e["operation"] for e in lake.tables.log("catalog")]
    assert ops.count("OPTIMIZE") == 2  # reaching commits 4 and 8
    live = lake.tables.files("catalog")
    assert len(live) < 9 and sum(a["num_records"] for a in live) == 9
    assert lake.catalog()["version"].to_pylist() == versions
    m = lake.tables.optimize("catalog")
    assert len(lake.tables.files("catalog")) == 1 and m["files_added"] == 1
    assert lake.catalog()["version"].to_pylist() == versions


def test_vacuum_never_removes_a_file_a_committed_version_needs(tmp_path):
    lake = Lake(tmp_path, maintain_every=1000)
    versions = [lake.commit(field_document("cam-a", f"s{i}"), {}, residual_table(5, seed=i))
                for i in range(4)]
    before_optimize = dt.datetime.now(dt.UTC)
    time.sleep(0.05)
    for name in ("catalog", "residuals"):
        lake.tables.optimize(name)
    # a file a running commit has written but not committed yet: not the vacuum's to take
    pending = tmp_path / "residuals" / "camera_id=cam-a" / "part-pending.parquet"
    pending.write_bytes(data_files(tmp_path, "residuals")[0].read_bytes())
    old = time.time() - 30 * 86400
    for p in data_files(tmp_path, "catalog") + data_files(tmp_path, "residuals"):
        os.utime(p, (old, old))
    live = {a["path"] for t in ("catalog", "residuals") for a in lake.tables.files(t)}
    removed = lake.tables.vacuum("catalog", 0, dry_run=False) + lake.tables.vacuum("residuals", 0,
                                                                                  dry_run=False)
    assert len(removed) == 8 and not {os.path.basename(r) for r in removed} & {os.path.basename(p)
                                                                                 for p in live}
    assert pending.exists()
    # every committed version whole
    assert lake.catalog()["version"].to_pylist() == versions
    for v in versions:
        assert lake.read_residuals(v).num_rows == 5 and lake.load_document(v)["version"] == v
        lake.open_zarr(v)
    # time travel to before the vacuumed compaction now fails, and says so
    with pytest.raises(LakeError, match="catalog as of .* is no longer readable: .* removed by vacuum"):
        lake.catalog(as_of=before_optimize)


def test_the_data_dictionary_is_written_at_the_first_commit_and_kept_current(tmp_path):
    lake = Lake(tmp_path)
    assert not (tmp_path / "README.md").exists()
    lake.commit(field_document(), {}, residual_table())
    assert (tmp_path / "README.md").read_text() == data_dictionary()
    (tmp_path / "README.md").write_text("stale text of an older fieldcal\n")
    lake.commit(field_document(seed=1), {}, residual_table())
    assert (tmp_path / "README.md").read_text() == data_dictionary()
    for column in history.sql(lake, "SELECT * FROM residuals").column_names:
        assert f"| `{column}` |" in data_dictionary()


def test_a_table_made_by_an_older_fieldcal_gains_new_columns(tmp_path):
    """Schema evolution: an observations table without ``measure_settings`` (an older lake)."""
    from deltalake import DeltaTable

    from fieldcal.lake.tables import table_schema

    old = table_schema("observations_field")
    old = old.remove(old.get_field_index("measure_settings"))
    DeltaTable.create(str(tmp_path / "observations_field"), old, partition_by=["camera_id"])
    lake = Lake(tmp_path)
    lake.write_observations("cam-a", "s1", "images/IMG_0.tif", "a" * 64, field_measurements(n=2))
    assert lake.read_observations("cam-a", "s1", "images/IMG_0.tif", "a" * 64).num_rows == 2
    assert "measure_settings" in DeltaTable(str(tmp_path / "observations_field")).schema().to_arrow().names


def test_fleet_summary_compares_only_where_needed_and_once_per_pair(tmp_path, monkeypatch):
    from fieldcal.products import report, status

    lake = Lake(tmp_path)
    lake.commit(field_document("cam-a", "s1", acquired="2026-01-01"), {}, residual_table())
    lake.commit(field_document("cam-a", "s2", f_mm=50.01, acquired="2026-02-01"), {}, residual_table())
    lake.commit(field_document("cam-b", "s1"), {}, residual_table())  # one calibration: no comparison
    calls = []
    real = status.compare_calibrations
    monkeypatch.setattr(status, "compare_calibrations", lambda *a, **k: calls.append(1) or real(*a, **k))
    first = report.fleet_summary(lake).to_pylist()
    assert len(calls) == 1 and first[0]["p_value"] is not None and first[1]["verdict"] == "only one calibration"
    again = report.fleet_summary(Lake(tmp_path)).to_pylist()
    assert len(calls) == 1 and again == first  # remembered in the lake per pair of versions
    strict = report.fleet_summary(lake, tolerance_um=1e-6, alpha=0.5).to_pylist()
    assert len(calls) == 1                     # another tolerance or level: judged from the stored test
    assert strict[0]["exceeds_tolerance"] and strict[0]["max_change_um"] == first[0]["max_change_um"]
