"""Workers that share no disk with the flow (issue 28, goals 1 and 2).

The Dask scheduler and its two worker processes run in a mount namespace of their own
(``unshare --mount``, as root) with an empty tmpfs over the flow's temporary folder and the
tests' folders (:func:`tests.standalone_dask.standalone_cluster` with ``hide``): a task that
is handed a path of the flow's host finds nothing there, as on another machine. Sessions and
lake are on the moto S3 server on loopback (``tests/conftest_s3.py``); the workers take the
store's credentials from their environment, and the storage options the flows are given name
only the endpoint and region. ``fieldcal fleet``, ``fieldcal run --dask`` and ``fieldcal serve``
(its deployment's run, started on the API and run by the serving process) go through it; a
local session given to the same cluster fails, loudly, which shows the disk is hidden.
Skipped, with the reason, where a mount namespace cannot be made (not root, no unshare).
"""

import json
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from fieldcal.errors import GeometryError
from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session
from flows import cli
from flows.calibrate import calibrate_session
from tests import standalone_dask as standalone
from tests.conftest_s3 import REGION

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]

FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
ROOT = Path(__file__).resolve().parents[2]
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing"}


def hidden(tmp_path_factory) -> list[str]:
    return standalone.hidden_folders([tempfile.gettempdir(), str(tmp_path_factory.getbasetemp())])


@pytest.fixture(scope="module")
def isolated_cluster(tmp_path_factory, prefect_server):
    """``(scheduler address, worker pids, hidden folders)``: two workers that cannot see the flow's disk."""
    hide = hidden(tmp_path_factory)
    problem = standalone.isolation_problem(hide)
    if problem:
        print(f"skipping the no-shared-disk test: {problem}")
        pytest.skip(f"workers in their own mount namespace: {problem}")
    env = dict(CREDENTIALS, PREFECT_API_URL=prefect_server)
    folder = tmp_path_factory.mktemp("dask-hidden")
    # no nanny: two processes fewer to start and stop (28 s of setup and 6 s of teardown at load 8)
    with standalone.standalone_cluster(folder, 2, hide=hide, env=env, nanny=False) as (address, _, procs):
        yield address, {p.pid for p in procs}, hide


@pytest.fixture
def store(s3_server, monkeypatch, tmp_path):
    """Storage options without credentials (they are in this process's environment, as in the
    workers'), a fresh lake prefix, and the test's own hash store."""
    for k, v in CREDENTIALS.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    options = {"endpoint_url": s3_server.endpoint_url, "client_kwargs": {"region_name": REGION}}
    return s3_server, options, s3_server.url(f"hidden-{tmp_path.name}")


def put(s3_server, local, url) -> None:
    import fsspec

    fs, path = fsspec.core.url_to_fs(url, **s3_server.storage_options)
    fs.put(str(local) + "/", path + "/", recursive=True)


def test_the_workers_see_neither_the_flows_temporary_folder_nor_the_tests(isolated_cluster, tmp_path):
    import distributed

    address, _, hide = isolated_cluster
    mine = tempfile.NamedTemporaryFile(prefix="fieldcal-flow-", delete=False)   # noqa: SIM115
    mine.close()
    try:
        with distributed.Client(address, timeout=30) as client:
            seen = client.run(lambda paths: [os.path.exists(p) for p in paths], [mine.name, str(tmp_path)])
        assert os.path.exists(mine.name) and tmp_path.is_dir()
        assert list(seen.values()) == [[False, False], [False, False]], hide
    finally:
        os.unlink(mine.name)


def test_fleet_and_run_with_sessions_and_lake_on_s3_and_workers_that_share_no_disk(
        isolated_cluster, store, tmp_path, capsys):
    address, _, _ = isolated_cluster
    s3, options, lake_url = store
    local = tmp_path / "sessions"
    truth = write_session(local / "cam-lab" / "2026-05-09", "canon5d2", seed=29, raster_scale=0.25,
                          frames_per_angle=1, camera_id="cam-lab")
    for k in range(2):
        write_field_session(local / f"cam-w{k}" / f"2026-05-0{k + 1}", wide_field(seed=20 + k), images=False,
                            observations_csv=True, camera_id=f"cam-w{k}", acquired=f"2026-05-0{k + 1}")
    put(s3, local, f"{lake_url}/sessions")
    opts = json.dumps(options)

    assert cli.main(["fleet", "--lake", lake_url, "--storage-options", opts, "--dask", address,
                     "--format", "json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["n_found"] == 3 and summary["n_committed"] == 3, summary
    lake = Lake(lake_url, options)
    n_frames = truth.frames.num_rows
    assert len(lake.cached_keys("cam-lab", "2026-05-09")) == n_frames     # measured on the workers

    lab2 = tmp_path / "lab2"
    truth2 = write_session(lab2, "h3d", seed=21, raster_scale=0.25, frames_per_angle=1, camera_id="cam-h3d")
    put(s3, lab2, f"{lake_url}/incoming/lab2")
    assert cli.main(["run", f"{lake_url}/incoming/lab2", "--lake", lake_url, "--storage-options", opts,
                     "--dask", address]) == 0
    version = capsys.readouterr().out.strip().splitlines()[-1]
    doc = lake.load_document(version)
    assert doc["camera_id"] == "cam-h3d" and doc["stats"]["n_frames"] == truth2.frames.num_rows
    (row,) = [r for r in lake.catalog().to_pylist() if r["version"] == version]
    assert row["session_id"] == "lab2" and len(lake.cached_keys("cam-h3d", "lab2")) == truth2.frames.num_rows

    # the same cluster given a session on the flow's disk: every frame is "file not found" there
    with pytest.raises(GeometryError, match="no goniometer frame could be measured"):
        calibrate_session(str(lab2), lake_url, storage_options=options, dask_address=address, force=True)


def _deployment_id(name: str, serving: subprocess.Popen, log: Path, timeout_s: float = 120.0):
    """The id of deployment ``name`` once the serving process has made it."""
    from prefect.client.orchestration import get_client
    from prefect.exceptions import ObjectNotFound

    deadline = time.monotonic() + timeout_s
    with get_client(sync_client=True) as client:
        while True:
            try:
                return client.read_deployment_by_name(name).id
            except ObjectNotFound:
                assert serving.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
                time.sleep(0.5)


def test_serve_runs_its_deployment_with_sessions_and_lake_on_s3_on_workers_that_share_no_disk(
        isolated_cluster, store, prefect_server, tmp_path):
    """``fieldcal serve --dask ADDRESS``: a run of its deployment (created on the API, as the
    scheduler would at the cron's time) runs in the serving process's runner with the
    deployment's parameters (the S3 root and lake, the storage options without secrets, the
    isolated cluster), and its image tasks read the frames from S3 on the hidden workers."""
    from prefect.client.orchestration import get_client

    address, _, _ = isolated_cluster
    s3, options, lake_url = store
    local = tmp_path / "sessions"
    truth = write_session(local / "cam-srv" / "2026-06-01", "h3d", seed=31, raster_scale=0.25,
                          frames_per_angle=1, camera_id="cam-srv")
    write_field_session(local / "cam-ws" / "2026-06-02", wide_field(seed=32), images=False,
                        observations_csv=True, camera_id="cam-ws", acquired="2026-06-02")
    put(s3, local, f"{lake_url}/sessions")
    env = dict(os.environ, PREFECT_API_URL=prefect_server, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1",
               PREFECT_RUNNER_POLL_FREQUENCY="1", **CREDENTIALS)
    log = tmp_path / "serve.log"
    name = f"hidden-{tmp_path.name}"[:60]
    with open(log, "w") as out:
        serving = subprocess.Popen(
            [FIELDCAL, "serve", "--lake", lake_url, "--storage-options", json.dumps(options), "--dask", address,
             "--cron", "0 2 * * *", "--name", name], env=env, cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True)
    try:
        deployment = _deployment_id(f"recalibrate-fleet/{name}", serving, log)
        with get_client(sync_client=True) as client:
            params = client.read_deployment(deployment).parameters
            assert params["dask_address"] == address and params["lake"] == lake_url, params
            assert "testing" not in json.dumps(params)                  # no secret in the deployment
            run = client.create_flow_run_from_deployment(deployment)
            deadline = time.monotonic() + 300
            while not (state := client.read_flow_run(run.id).state).is_final():
                assert serving.poll() is None and time.monotonic() < deadline, log.read_text()[-3000:]
                time.sleep(1)
        assert state.is_completed(), (state, log.read_text()[-3000:])
        lake = Lake(lake_url, options)
        assert {(r["camera_id"], r["session_id"]) for r in lake.catalog().to_pylist()} == {
            ("cam-srv", "2026-06-01"), ("cam-ws", "2026-06-02")}
        assert len(lake.cached_keys("cam-srv", "2026-06-01")) == truth.frames.num_rows   # measured on the workers
        deadline = time.monotonic() + 30                                # the serving process says so
        while not re.search(r"fieldcal serve: run \S+: completed in [0-9.]+ s: 2 found, 2 committed, 0 failed",
                            log.read_text()):
            assert time.monotonic() < deadline, log.read_text()[-3000:]
            time.sleep(0.5)
    finally:
        if serving.poll() is None:
            os.killpg(serving.pid, signal.SIGINT)
        try:
            serving.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(serving.pid, signal.SIGKILL)
            serving.wait()
    assert serving.returncode == 0, log.read_text()[-3000:]             # Ctrl-C stops it cleanly
