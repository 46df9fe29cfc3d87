"""The flows with the lake (and the fleet's sessions) on an S3-compatible object store.

The store is moto in server mode on loopback (``tests/conftest_s3.py``), reached through
fsspec / s3fs exactly as a real bucket would be: the Dask workers write the observations
there, the flow commits the version there, and DuckDB, pyarrow and zarr read it back.
"""

import json

import pytest
import zarr

from fieldcal.lake import history
from fieldcal.lake.store import Lake
from fieldcal.model.camera import PARAM_NAMES
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session
from flows.calibrate import calibrate_session
from flows.fleet import recalibrate_fleet

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture(autouse=True)
def hash_store(tmp_path, monkeypatch):
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))


def test_goniometer_session_into_an_s3_lake_and_read_back_without_fieldcal(s3_lake, dask_cluster, tmp_path):
    url, options = s3_lake
    folder = tmp_path / "lab-s3"
    truth = write_session(folder, "canon5d2", seed=31, raster_scale=0.25, frames_per_angle=1, camera_id="cam-s3")
    n = truth.frames.num_rows
    out = calibrate_session(str(folder), url, storage_options=options, dask_address=dask_cluster)
    assert out["status"] == "committed" and out["images"]["measured"] == n
    assert out["lake"] == url

    lake = Lake(url, options)
    assert len(lake.cached_keys("cam-s3", "lab-s3")) == n      # written by the Dask workers
    (row,) = lake.catalog().to_pylist()
    assert row["version"] == out["version"] and row["n_frames"] == n

    # plain deltalake, zarr's fsspec store, without fieldcal's reader
    from deltalake import DeltaTable

    from fieldcal.lake.storage import delta_options

    cat = DeltaTable(f"{url}/catalog", storage_options=delta_options(options)).to_pyarrow_table()
    assert cat["f_mm"].to_pylist() == [row["f_mm"]]
    store = zarr.storage.FsspecStore.from_url(f"{url}/{row['zarr_path']}", storage_options=options, read_only=True)
    group = zarr.open_group(store=store, mode="r")
    assert group["parameters"][PARAM_NAMES.index("f_mm")] == pytest.approx(row["f_mm"], rel=1e-12)
    q = history.sql(lake, "SELECT count(*) AS n FROM observations_goniometer WHERE camera_id = 'cam-s3'")
    assert q["n"].to_pylist() == [n]
    assert history.camera_history(lake, "cam-s3")["version"].to_pylist() == [out["version"]]

    again = calibrate_session(str(folder), url, storage_options=options, dask_address=dask_cluster)
    assert again["status"] == "unchanged" and again["version"] == out["version"] and again["measure"] is None


def test_fleet_takes_its_sessions_from_the_lakes_bucket(s3_lake, tmp_path):
    url, options = s3_lake
    local = tmp_path / "sessions"
    write_field_session(local / "cam-f1" / "2026-03-01", wide_field(seed=41), images=False, observations_csv=True,
                        camera_id="cam-f1", acquired="2026-03-01")
    (local / "cam-f2" / "2026-03-02").mkdir(parents=True)
    (local / "cam-f2" / "2026-03-02" / "session.json").write_text(json.dumps({"schema": "fieldcal.session/1"}))
    lake = Lake(url, options)
    lake.fs.put(str(local) + "/", f"{url}/sessions/", recursive=True)

    first = recalibrate_fleet(url, storage_options=options)          # root: <lake>/sessions
    assert first["root"] == f"{url}/sessions"
    by_cam = {s["folder"].rsplit("/", 2)[-2]: s for s in first["sessions"]}
    assert by_cam["cam-f1"]["status"] == "committed"
    # loaded by the session loader: the schema's first complaint, naming the manifest by its URL
    reason = by_cam["cam-f2"]["reason"]
    assert by_cam["cam-f2"]["status"] == "failed"
    assert reason.startswith(f"{url}/sessions/cam-f2/2026-03-02/session.json: ")
    assert "required propert" in reason
    assert lake.sessions_with_calibration() == [("cam-f1", "2026-03-01")]
    second = recalibrate_fleet(url, storage_options=options)
    assert (second["n_committed"], second["n_skipped"], second["n_failed"]) == (0, 1, 1)
