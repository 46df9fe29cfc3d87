"""Workers that share no disk with the flow (issue 28, goals 1 and 2).

The Dask scheduler and its two worker processes run in a mount namespace of their own
(``unshare --mount``, as root) with an empty tmpfs over the flow's temporary folder and the
tests' folders (:func:`tests.standalone_dask.standalone_cluster` with ``hide``): a task that
is handed a path of the flow's host finds nothing there, as on another machine. Sessions and
lake are on the moto S3 server on loopback (``tests/conftest_s3.py``); the workers take the
store's credentials from their environment, and the storage options the flows are given name
only the endpoint and region. ``fieldcal fleet`` and ``fieldcal run --dask`` go through it;
a local session given to the same cluster fails, loudly, which shows the disk is hidden.
Skipped, with the reason, where a mount namespace cannot be made (not root, no unshare).
"""

import json
import os
import tempfile

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
