"""The calibration and fleet flows on Prefect's local server with real local Dask clusters.

Sessions are small but real: a goniometer session of 180 rendered frames (Canon 5D Mark
II-like, pixel grid at 1/4 scale over the same sensor, 3 frames per angle) and
observation-only field sessions (the field paper's geometry and a wide-angle camera).
The Prefect server and one two-worker Dask cluster are shared by all flow tests
(``tests/conftest_prefect.py``); the first test lets the flow start its own local
cluster, the default path of ``fieldcal run``.
"""

import json
import shutil
from pathlib import Path

import duckdb
import numpy as np
import pytest
import tifffile
import yaml
import zarr

from fieldcal import batch, progress
from fieldcal.contract.fingerprint import sha256_file
from fieldcal.errors import InputError
from fieldcal.goniometer import method as gon
from fieldcal.lake import history
from fieldcal.lake.store import Lake
from fieldcal.model.camera import INDEX, PARAM_NAMES
from fieldcal.session.frames import read_frames_csv
from fieldcal.session.loader import Session
from fieldcal.synthetic.field import paper_field, wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session
from flows.calibrate import calibrate_session
from flows.fleet import fleet_deployment, recalibrate_fleet
from flows.hashcache import HashCache, file_stamp

ROOT = Path(__file__).resolve().parents[2]
CORE = ("f_mm", "xp_mm", "yp_mm")
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture(autouse=True)
def hash_store(tmp_path, monkeypatch):
    """Each test remembers image hashes in its own store (never in ~/.cache)."""
    path = tmp_path / "hashes.sqlite"
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(path))
    return path


@pytest.fixture(scope="module")
def gonio(tmp_path_factory):
    """A rendered goniometer session and the method's values on its noise-free spot positions."""
    folder = tmp_path_factory.mktemp("sessions") / "lab-2026-11-20"
    truth = write_session(folder, "canon5d2", seed=5, raster_scale=0.25, camera_id="cam-gonio")
    frames = read_frames_csv(folder / "frames.csv")
    ref = gon.calibrate(truth.sensor, frames, truth.exact_measurements(),
                        nominal_focal_mm=truth.scenario.nominal_focal_mm)
    return truth, ref


@pytest.fixture(scope="module")
def first_run(prefect_server, gonio, tmp_path_factory):
    """The goniometer session through the flow's default path: it starts its own local cluster."""
    lake = tmp_path_factory.mktemp("lake")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FIELDCAL_HASH_CACHE", str(lake.parent / "first-run-hashes.sqlite"))
        result = calibrate_session(str(gonio[0].folder), str(lake), n_workers=2)
    return lake, result


def copy_session(src: Path, dest_parent: Path) -> Path:
    dest = dest_parent / src.name          # same folder name: same session_id
    shutil.copytree(src, dest)
    return dest


# --------------------------------------------------------------------------------------
# the goniometer session end to end
# --------------------------------------------------------------------------------------
def test_goniometer_flow_on_a_local_cluster_passes_the_accuracy_checks(first_run, gonio):
    lake_dir, r = first_run
    truth, ref = gonio
    assert r["status"] == "committed" and r["new"] is True
    assert r["images"] == {"total": 180, "measured": 180, "cached": 0, "bad": 0, "hashed": 180}
    # the fan-out ran one Prefect task on each worker of the cluster the flow started, both
    # pulling the images from the run's queue, many small frames at a time
    m = r["measure"]
    assert sum(t["n"] for t in m["tasks"]) == 180 and m["n_workers"] == 2 and m["pulled"]
    assert len(m["tasks"]) == 2 and len({t["worker"] for t in m["tasks"]}) == 2
    assert 1 < m["estimate"]["per_pull"] < 180
    assert all(t["n"] % m["estimate"]["per_pull"] in (0, 180 % m["estimate"]["per_pull"]) for t in m["tasks"])

    doc = Lake(lake_dir).load_document(r["version"])
    p = np.array([doc["parameters"][n] for n in PARAM_NAMES])
    for k in CORE:
        # the goniometer issue's check: within 3 sigma of the method's noise-free values
        z = (p[INDEX[k]] - ref.parameters[INDEX[k]]) / doc["sigma"][k]
        assert abs(z) < 3.0, f"{k}: {z:.2f} sigma from the noise-free value"
    res = Lake(lake_dir).read_residuals(r["version"])
    used = np.asarray(res["used"].to_pylist())
    uv = np.column_stack([res["u_px"].to_numpy(zero_copy_only=False), res["v_px"].to_numpy(zero_copy_only=False)])
    axis = np.asarray(res["axis"].to_pylist())
    d = gon.along_axis_difference_px(p, truth.camera.params, truth.sensor, uv[used], axis[used])
    # the goniometer issue's check: the fitted correction along both axes within 0.05 px RMS
    assert np.sqrt(np.mean(d**2)) < 0.05
    assert doc["stats"]["sigma_fit_px"] < 0.1      # the centroid noise level (0.03-0.05 px here)


def test_observations_are_cached_per_image_and_the_version_has_one_catalog_row(first_run, gonio):
    lake_dir, r = first_run
    lake = Lake(lake_dir)
    assert len(lake.cached_keys("cam-gonio", "lab-2026-11-20")) == 180
    rows = history.sql(lake, "SELECT image, key, image_sha256, measure_settings FROM observations_goniometer "
                             "ORDER BY image LIMIT 1").to_pylist()[0]
    # keyed by the image's content hash (with the measuring settings); the hash is in the row
    assert rows["image_sha256"] == sha256_file(gonio[0].folder / rows["image"])
    assert json.loads(rows["measure_settings"])["method"] == "goniometer"
    assert rows["key"] == batch.measurement_key(rows["image_sha256"], json.loads(rows["measure_settings"]))
    assert lake.catalog()["version"].to_pylist() == [r["version"]]


def test_rerun_of_the_same_session_is_a_no_op_that_reads_no_image(first_run, gonio, monkeypatch):
    lake_dir, r = first_run
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(lake_dir.parent / "first-run-hashes.sqlite"))

    def must_not_run(*a, **k):
        raise AssertionError("an image was read")

    monkeypatch.setattr(Session, "read_image", must_not_run)  # reads (and hashes) an image
    monkeypatch.setattr(batch.pipeline, "measure", must_not_run)
    again = calibrate_session(str(gonio[0].folder), str(lake_dir))
    assert again["status"] == "unchanged" and again["new"] is False
    assert again["version"] == r["version"] and again["fingerprint"] == r["fingerprint"]
    assert again["measure"] is None          # no fan-out, no cluster
    assert again["images"]["hashed"] == 0 and again["images"]["measured"] == 0
    assert len(Lake(lake_dir).catalog()) == 1


def test_force_makes_a_new_version_from_the_cached_observations(first_run, gonio, monkeypatch):
    lake_dir, r = first_run
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(lake_dir.parent / "first-run-hashes.sqlite"))
    forced = calibrate_session(str(gonio[0].folder), str(lake_dir), force=True)
    assert forced["status"] == "committed" and forced["version"] != r["version"]
    assert forced["images"]["cached"] == 180 and forced["measure"] is None
    assert forced["fingerprint"] == r["fingerprint"]
    assert Lake(lake_dir).row(forced["version"])["forced"] is True


def test_a_changed_image_is_measured_again_and_gives_a_new_version(first_run, gonio, dask_cluster, tmp_path):
    lake_dir, r = first_run
    folder = copy_session(gonio[0].folder, tmp_path)
    name = "images/x_+00.00_1.tif"
    img = tifffile.imread(folder / name)
    img[0, 0] += 1                                      # one DN in a corner: new content
    tifffile.imwrite(folder / name, img, tile=(256, 256), compression="zstd")
    out = calibrate_session(str(folder), str(lake_dir), dask_address=dask_cluster)
    # a copy at new paths: every image is hashed, only the changed one is measured
    assert out["images"] == {"total": 180, "measured": 1, "cached": 179, "bad": 0, "hashed": 180}
    assert out["status"] == "committed" and out["fingerprint"] != r["fingerprint"]


def test_bad_frames_are_reported_and_left_out_and_the_run_goes_on(gonio, dask_cluster, tmp_path):
    folder = copy_session(gonio[0].folder, tmp_path)
    corrupt, missing = "images/x_+10.00_0.tif", "images/y_-04.00_2.tif"
    data = (folder / corrupt).read_bytes()
    (folder / corrupt).write_bytes(data[: len(data) // 3])           # truncated TIFF
    (folder / missing).unlink()                                        # listed in frames.csv, gone
    out = calibrate_session(str(folder), str(tmp_path / "lake"), dask_address=dask_cluster)
    assert out["status"] == "committed"
    left = {d["image"]: d["reason"] for d in out["left_out"]}
    assert corrupt in left and missing in left
    assert "not found" in left[missing].lower() or "missing" in left[missing].lower()
    doc = Lake(tmp_path / "lake").load_document(out["version"])
    assert doc["stats"]["n_frames"] == 178


# --------------------------------------------------------------------------------------
# a field session of rendered images (identification from coded targets)
# --------------------------------------------------------------------------------------
# two attitudes per station of the paper's six (as tests/test_field_images.py)
FIELD_IMAGES = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]


def test_rendered_field_session_with_a_corrupt_image_passes_the_solver_checks(dask_cluster, tmp_path):
    from fieldcal.synthetic.render import scaled_field

    sf = scaled_field(paper_field(seed=5), 0.25)
    folder = tmp_path / "wall-images"
    info = write_field_session(folder, sf, image_indices=FIELD_IMAGES, coded=True, seed=5, camera_id="cam-img")
    good = folder / info["images"][0]
    (folder / "images" / "corrupt.tif").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    manifest = json.loads((folder / "session.json").read_text())
    manifest["images"].append({"file": "images/corrupt.tif"})
    (folder / "session.json").write_text(json.dumps(manifest))

    seen = []
    with progress.listening(lambda event, **f: seen.append(f) if event == "images" else None):
        out = calibrate_session(str(folder), str(tmp_path / "lake"), dask_address=dask_cluster)
    assert out["status"] == "committed"
    assert out["images"] == {"total": 13, "measured": 12, "cached": 0, "bad": 1, "hashed": 13}
    # progress image by image, from the workers' reports or the tasks' results, each image once
    done = [f["done"] for f in seen]
    assert done == sorted(set(done)) and done[0] == 0 and seen[-1] == {"total": 13, "done": 13, "cached": 0, "bad": 1}
    (left,) = out["left_out"]
    assert left["image"] == "images/corrupt.tif" and "corrupt.tif" not in left["reason"] and left["reason"]
    doc = Lake(tmp_path / "lake").load_document(out["version"])
    assert doc["stats"]["n_images"] == 12 and doc["stats"]["left_out_images"] == ["images/corrupt.tif"]
    for k in CORE:
        # the solver issue's check: f and the principal point within 3 sigma of the truth
        z = (doc["parameters"][k] - sf.camera.params[INDEX[k]]) / doc["sigma"][k]
        assert abs(z) < 3.0, f"{k}: {z:.2f} sigma"
    assert doc["stats"]["rmse_px"] < 0.02            # the detector's accuracy on rendered discs (~0.005 px)


# --------------------------------------------------------------------------------------
# field sessions without images
# --------------------------------------------------------------------------------------
def test_observation_only_field_session_needs_no_cluster_and_recovers_the_camera(prefect_server, tmp_path):
    sf = paper_field(seed=3)
    folder = tmp_path / "wall-a"
    write_field_session(folder, sf, images=False, observations_csv=True, camera_id="cam-field")
    out = calibrate_session(str(folder), str(tmp_path / "lake"), dask_address="tcp://127.0.0.1:9")
    assert out["measure"] is None and out["images"]["total"] == 0   # the bogus address was never used
    doc = Lake(tmp_path / "lake").load_document(out["version"])
    for k in CORE:
        # the solver issue's check: f and the principal point within 3 sigma of the truth
        z = (doc["parameters"][k] - sf.camera.params[INDEX[k]]) / doc["sigma"][k]
        assert abs(z) < 3.0, f"{k}: {z:.2f} sigma"
    assert 0.09 < doc["stats"]["rmse_px"] < 0.15      # image noise 0.1 px per coordinate
    assert doc["stats"]["sigma0"] == pytest.approx(1.0, abs=0.1)


def test_bad_input_fails_with_the_file_named_and_writes_nothing(prefect_server, tmp_path, hash_store):
    folder = tmp_path / "broken"
    write_field_session(folder, wide_field(seed=1), images=False, observations_csv=True)
    manifest = json.loads((folder / "session.json").read_text())
    del manifest["camera_id"]
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match=r"session\.json.*camera_id"):
        calibrate_session(str(folder), str(tmp_path / "lake"))
    assert not (tmp_path / "lake").exists()
    assert not hash_store.exists()


# --------------------------------------------------------------------------------------
# outputs readable without fieldcal; DuckDB history
# --------------------------------------------------------------------------------------
def test_outputs_open_with_plain_deltalake_zarr_and_duckdb(first_run, gonio):
    from deltalake import DeltaTable

    lake_dir, r = first_run
    version = r["version"]
    (row,) = [r for r in DeltaTable(str(lake_dir / "catalog")).to_pyarrow_table().to_pylist()
              if r["version"] == version]
    assert row["camera_id"] == "cam-gonio" and row["method"] == "goniometer"
    group = zarr.open_group(str(lake_dir / row["zarr_path"]), mode="r")
    assert group["parameters"][:].shape == (13,)
    assert group["parameters"][PARAM_NAMES.index("f_mm")] == pytest.approx(row["f_mm"], rel=1e-12)
    assert group.attrs["document"]["version"] == version
    with duckdb.connect() as con:
        con.register("spots", DeltaTable(str(lake_dir / "observations_goniometer")).to_pyarrow_table())
        con.register("res", DeltaTable(str(lake_dir / row["residuals_path"])).to_pyarrow_table())
        n_obs = con.execute("SELECT count(DISTINCT file) FROM spots WHERE camera_id = 'cam-gonio'").fetchone()[0]
        n_res = con.execute(f"SELECT count(*) FROM res WHERE used AND version = '{version}'").fetchone()[0]
    assert n_obs == 180                          # one row of spot measurements per frame
    assert n_res == 60                           # one residual per angle (35 x + 25 y)


def test_duckdb_history_over_the_catalog_returns_the_expected_rows(first_run):
    lake_dir, r = first_run
    lake = Lake(lake_dir)
    cat = lake.catalog()
    hist = history.camera_history(lake, "cam-gonio", ("f_mm",), all_versions=True)
    assert hist.num_rows == cat.num_rows >= 1
    assert r["version"] in hist["version"].to_pylist()
    fleet = history.fleet(lake, "2026-11-20", "2026-11-20")
    assert fleet["camera_id"].to_pylist() == ["cam-gonio"]
    assert fleet["version"].to_pylist() == [lake.latest("cam-gonio")]
    assert history.fleet(lake, "2026-11-21").num_rows == 0          # acquired the day before
    q = history.sql(lake, "SELECT method, count(*) AS n FROM catalog GROUP BY method")
    assert q.to_pylist() == [{"method": "goniometer", "n": cat.num_rows}]


# --------------------------------------------------------------------------------------
# the fleet
# --------------------------------------------------------------------------------------
def test_fleet_calibrates_the_sessions_without_a_version_and_survives_a_bad_one(prefect_server, tmp_path):
    root = tmp_path / "sessions"
    write_field_session(root / "cam-w1" / "2026-05-01", wide_field(seed=11), images=False, observations_csv=True,
                        camera_id="cam-w1", acquired="2026-05-01")
    write_field_session(root / "cam-w2" / "2026-06-01", wide_field(seed=12), images=False, observations_csv=True,
                        camera_id="cam-w2", acquired="2026-06-01")
    (root / "broken").mkdir()
    (root / "broken" / "session.json").write_text("{not json")
    lake = str(tmp_path / "lake")
    first = recalibrate_fleet(lake, str(root))
    status = {(s["camera_id"], s["session_id"]): s["status"] for s in first["sessions"]}
    assert status == {("cam-w1", "2026-05-01"): "committed", ("cam-w2", "2026-06-01"): "committed",
                      (None, None): "failed"}
    assert (first["n_found"], first["n_committed"], first["n_failed"]) == (3, 2, 1)
    assert "session.json" in next(s["reason"] for s in first["sessions"] if s["status"] == "failed")
    second = recalibrate_fleet(lake, str(root))
    assert (second["n_committed"], second["n_failed"], second["n_skipped"]) == (0, 1, 2)
    assert sorted(Lake(lake).sessions_with_calibration()) == [("cam-w1", "2026-05-01"), ("cam-w2", "2026-06-01")]


# --------------------------------------------------------------------------------------
# deployment
# --------------------------------------------------------------------------------------
def test_prefect_yaml_deploys_the_fleet_flow_on_a_cron_schedule():
    # the models `prefect deploy` reads prefect.yaml with (Prefect 3.8, pinned)
    from prefect.cli.deploy._models import PrefectYamlModel, RawScheduleConfig
    from prefect.flows import load_flow_from_entrypoint
    from prefect.schedules import Cron

    spec = yaml.safe_load((ROOT / "deploy" / "prefect.yaml").read_text())
    (dep,) = PrefectYamlModel.model_validate(spec).deployments
    flow_obj = load_flow_from_entrypoint(str(ROOT / dep.entrypoint))
    assert flow_obj.name == "recalibrate-fleet"
    (sched,) = spec["deployments"][0]["schedules"]
    RawScheduleConfig.model_validate(sched)                     # no unknown keys
    Cron(sched["cron"], timezone=sched["timezone"])            # a valid cron expression
    assert set(dep.parameters) <= set(flow_obj.parameters.properties)
    assert dep.work_pool.job_variables["env"]["OPENBLAS_NUM_THREADS"] == "1"


def test_served_deployment_is_registered_with_its_schedule(prefect_server):
    from prefect import get_client

    dep = fleet_deployment("s3://bucket/lake", cron="15 3 * * *", parameters={"n_workers": 4})
    deployment_id = dep.apply()
    with get_client(sync_client=True) as client:
        stored = client.read_deployment(deployment_id)
    assert stored.name == "nightly" and stored.entrypoint.endswith("recalibrate_fleet")
    assert [s.schedule.cron for s in stored.schedules] == ["15 3 * * *"]
    assert stored.parameters == {"lake": "s3://bucket/lake", "n_workers": 4}


# --------------------------------------------------------------------------------------
# plain parts: batch sizes and the hash store
# --------------------------------------------------------------------------------------
def test_hash_store_recognises_unchanged_files_and_forgets_rewritten_ones(tmp_path):
    f = tmp_path / "a.tif"
    f.write_bytes(b"abc")
    with HashCache(tmp_path / "h.sqlite") as store:
        stamp = file_stamp(f)
        assert store.remember([(str(f), "h1", stamp)]) == 1
        assert store.lookup([str(f)]) == {str(f): "h1"}
        f.write_bytes(b"abcd")                                   # rewritten: new size and stamp
        assert store.lookup([str(f)]) == {}
        assert store.remember([(str(f), "h2", stamp)]) == 0      # stale stamp: not remembered
    assert HashCache(None).lookup([str(f)]) == {}                # disabled


def test_a_task_placed_on_a_worker_runs_there(prefect_server):
    # the fan-out places each batch on a worker thread (fieldcal.batch.assign_batches);
    # one task at a time on an idle cluster: nothing to steal, each runs where it was put
    from prefect import flow, task

    from flows import calibrate, cluster

    @task(persist_result=False)
    def where() -> str:
        from distributed import get_worker

        return get_worker().address

    @flow(persist_result=False)
    def placing() -> tuple[list[str], list[str]]:
        with cluster.task_runner(None, 2, None) as runner:
            slots = sorted(set(cluster.worker_slots(runner.client)))
            wanted = [slots[1], slots[0], slots[1], slots[1], slots[0]]
            return wanted, [calibrate.submit_placed(runner, where, {}, w, priority=1).result() for w in wanted]

    wanted, ran = placing()
    assert len(set(wanted)) == 2 and ran == wanted


def test_images_are_counted_as_their_worker_reports_them_while_the_task_still_runs(dask_cluster):
    # image-by-image progress (flows.image_events): the task reports a.tif, then waits until
    # the flow has counted it; a.tif can only be counted from the worker's event
    import threading

    import distributed
    from prefect import flow, task

    from flows import cluster, image_events

    @task(persist_result=False)
    def two_images(run: str) -> bool:
        image_events.report_image(run, "a.tif", "measured")
        counted = distributed.Event("fieldcal-test-a-counted").wait(timeout=60)
        image_events.report_image(run, "b.tif", "bad")
        return counted

    @flow(persist_result=False)
    def counting():
        with cluster.task_runner(dask_cluster) as runner:
            changes, changed = [], threading.Condition()

            def on_change(**counts):         # in the client's event loop: no blocking calls here
                with changed:
                    changes.append(counts)
                    changed.notify_all()

            counts = image_events.ImageCounts(2, on_change, runner.client)
            fut = runner.submit(two_images, {"run": counts.run})
            with changed:
                assert changed.wait_for(lambda: changes, timeout=60), "a.tif was not reported"
            distributed.Event("fieldcal-test-a-counted", client=runner.client).set()
            assert fut.result() is True
            with changed:                    # b.tif's event may come after the task's result
                changed.wait_for(lambda: len(changes) == 2, timeout=60)
            counts.add([("a.tif", "measured"), ("b.tif", "bad")])   # the task's rows: counted already
            counts.close()
            counts.add([("c.tif", "measured")])                        # after close: ignored
            return changes, counts.counts()

    changes, final = counting()
    assert changes == [{"done": 1, "cached": 0, "bad": 0}, {"done": 2, "cached": 0, "bad": 1}]
    assert final == {"done": 2, "cached": 0, "bad": 1}
