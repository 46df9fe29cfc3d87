"""The same lake through an object store: s3://bucket/prefix on a moto server on loopback."""

import multiprocessing
import threading

import duckdb
import numpy as np
import pytest
import s3fs
import zarr

from fieldcal.errors import LakeError
from fieldcal.lake import history
from fieldcal.lake.store import Lake
from fieldcal.model.camera import FIELD_PARAMS, PARAM_NAMES
from tests import conftest_s3
from tests.lake.test_lake import (
    _crashing_commit,
    field_document,
    field_measurements,
    goniometer_document,
    residual_table,
)

s3_server = conftest_s3.s3_server  # the fixtures (the shared conftest may import them too)
s3_lake = conftest_s3.s3_lake


def test_s3_commit_catalog_zarr_history_round_trip(s3_lake):
    url, options = s3_lake
    lake = Lake(url, options)
    assert lake.catalog().num_rows == 0 and history.fleet(lake).num_rows == 0

    doc = field_document("cam-a", "s1")
    cov = np.diag(np.linspace(1e-6, 1e-5, 10))
    v1 = lake.commit(doc, {"covariance": cov}, residual_table(20),
                     array_attrs={"covariance": {"names": list(FIELD_PARAMS)}})
    assert v1.new and lake.commit(doc, {}, residual_table(20)) == v1
    assert lake.find_committed(doc["inputs"]["fingerprint"]) == v1
    v2 = lake.commit(field_document("cam-a", "s2", f_mm=50.01, acquired="2026-12-01"), {},
                     residual_table(10))
    v3 = lake.commit(goniometer_document("cam-g"), {},
                     {"image": ["images/F000.tif"], "u_px": [1.0], "v_px": [2.0],
                      "du_px": [0.1], "dv_px": [0.0], "sigma_px": [0.05], "used": [True],
                      "reason": [None], "axis": ["y"], "angle_deg": [3.0]})

    cat = lake.catalog()
    assert cat["version"].to_pylist() == [v1, v2, v3]
    assert lake.load_document(v2)["parameters"]["f_mm"] == 50.01
    g = lake.open_zarr(v1)
    np.testing.assert_array_equal(g["covariance"][:], cov)
    np.testing.assert_array_equal(g["parameters"][:], [doc["parameters"][n] for n in PARAM_NAMES])
    assert g["exterior/rotation_world_to_camera"].shape == (3, 3, 3)
    assert lake.read_residuals(v3)["axis"].to_pylist() == ["y"]
    assert lake.latest("cam-a") == v2 and lake.sessions_with_calibration() == [
        ("cam-a", "s1"), ("cam-a", "s2"), ("cam-g", "lab-1")]

    hist = history.camera_history(lake, "cam-a")
    assert hist["f_mm"].to_pylist() == [50.0, 50.01]
    rows = history.sql(lake, "SELECT camera_id, count(*) AS n FROM residuals GROUP BY ALL "
                             "ORDER BY camera_id")
    assert rows.to_pylist() == [{"camera_id": "cam-a", "n": 30}, {"camera_id": "cam-g", "n": 1}]
    assert history.fleet(lake, "2026-11-01", "2026-11-30")["version"].to_pylist() == [v1]

    # observations cache
    sha = "ab" * 32
    assert lake.read_observations("cam-a", "s1", "images/IMG_0000.tif", sha) is None
    lake.write_observations("cam-a", "s1", "images/IMG_0000.tif", sha,
                            field_measurements("images/IMG_0000.tif", n=4))
    assert lake.has_observations("cam-a", "s1", "images/IMG_0000.tif", sha)
    assert lake.read_observations("cam-a", "s1", "images/IMG_0000.tif", sha).num_rows == 4
    assert history.sql(lake, "SELECT count(*) AS n FROM observations_field").to_pylist() == [{"n": 4}]
    assert lake.gc(grace_s=0.0) == []

    # the same objects with plain deltalake / s3fs / zarr / duckdb, without fieldcal
    from deltalake import DeltaTable

    from fieldcal.lake.storage import delta_options

    plain = DeltaTable(f"{url}/catalog", storage_options=delta_options(options)).to_pyarrow_table()
    assert sorted(plain["version"].to_pylist()) == sorted([v1, v2, v3])
    group = zarr.open_group(store=zarr.storage.FsspecStore.from_url(
        f"{url}/calibrations/cam-a/s1/{v1}.zarr", storage_options=options, read_only=True),
        mode="r")
    assert group.attrs["document"]["version"] == v1
    res = DeltaTable(f"{url}/residuals", storage_options=delta_options(options)).to_pyarrow_table()
    con = duckdb.connect()
    con.register("res", res)
    n = con.sql("SELECT count(*) FROM res WHERE camera_id = 'cam-a'").fetchall()
    con.close()
    assert n == [(30,)]
    fs = s3fs.S3FileSystem(**options)
    assert fs.cat_file(f"{url[5:]}/README.md").decode().startswith("# fieldcal lake")


def test_s3_delta_commits_are_conditional_puts(s3_lake):
    """moto honours If-None-Match: * (what delta-rs's commits on S3 rely on, conditional_put=etag)."""
    url, options = s3_lake
    fs = s3fs.S3FileSystem(**options)
    path = url[len("s3://"):] + "/probe.json"
    fs.pipe_file(path, b"first", mode="create")
    with pytest.raises(FileExistsError):
        fs.pipe_file(path, b"second", mode="create")
    assert fs.cat_file(path) == b"first"


def test_s3_concurrent_commits_of_the_same_inputs_make_one_version(s3_lake):
    url, options = s3_lake
    doc = field_document("cam-a", "s1", seed=5)
    results, errors = [], []
    barrier = threading.Barrier(5)

    def commit():
        try:
            lake = Lake(url, options)
            barrier.wait(30)
            results.append(lake.commit(doc, {}, residual_table()))
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    threads = [threading.Thread(target=commit) for _ in range(5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    assert not errors
    assert len(set(results)) == 1 and sum(v.new for v in results) == 1
    lake = Lake(url, options)
    assert lake.catalog().num_rows == 1
    assert lake.tables.scan("residuals", columns=["version"])["version"].unique().to_pylist() == \
        [results[0]]  # the losers removed their rows


def test_s3_crash_before_the_catalog_row_is_invisible_and_recoverable(s3_lake):
    url, options = s3_lake
    child = multiprocessing.get_context("spawn").Process(target=_crashing_commit,
                                                         args=(url, options))
    child.start()
    child.join(120)
    assert child.exitcode == 17
    lake = Lake(url, options)
    leftovers = lake.storage.listdir("calibrations/cam-a/s1")
    assert len(leftovers) == 2 and lake.catalog().num_rows == 0
    version = lake.commit(field_document(), {}, residual_table())  # waits for nothing
    assert version.new and lake.catalog()["version"].to_pylist() == [version]
    removed = lake.gc(grace_s=0.0)
    assert {f"calibrations/cam-a/s1/{n}" for n in leftovers} <= set(removed)
    assert lake.storage.listdir("calibrations/cam-a/s1") == [f"{version}.json", f"{version}.zarr"]
    assert lake.read_residuals(version).num_rows == 20


def test_s3_missing_bucket_fails_cleanly(s3_server):
    lake = Lake("s3://no-such-bucket-here/lake", s3_server.storage_options)
    with pytest.raises(LakeError, match="cannot commit to s3://no-such-bucket-here/lake") as info:
        lake.commit(field_document(), {}, residual_table())
    assert "\n" not in str(info.value)
    assert lake.catalog().num_rows == 0
