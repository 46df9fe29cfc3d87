"""The calibration flow against a Dask scheduler and two workers running as separate processes.

The test starts ``dask scheduler`` and two ``dask worker`` processes on loopback (one
thread each, the preload and thread settings of ``deploy/dask/``), the way a standing
cluster runs in a deployment, and gives the flow only the scheduler's address.
"""

import os

import numpy as np
import pytest

from fieldcal.goniometer import method as gon
from fieldcal.lake.store import Lake
from fieldcal.model.camera import INDEX
from fieldcal.session.frames import read_frames_csv
from fieldcal.synthetic.goniometer import write_session
from flows.calibrate import calibrate_session
from tests import standalone_dask as standalone

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture(autouse=True)
def hash_store(tmp_path, monkeypatch):
    """Image hashes remembered in the test's own store (never in ~/.cache)."""
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))


@pytest.fixture(scope="module")
def standalone_cluster(tmp_path_factory):
    """``(scheduler address, [worker addresses])`` of a scheduler and two worker processes."""
    with standalone.standalone_cluster(tmp_path_factory.mktemp("dask"), 2) as (address, workers, _):
        yield address, workers


def test_flow_runs_its_tasks_on_an_existing_scheduler_and_its_two_worker_processes(standalone_cluster, tmp_path):
    address, workers = standalone_cluster
    assert address.startswith("tcp://127.0.0.1:") and len(workers) == 2
    folder = tmp_path / "lab-h3d"
    truth = write_session(folder, "h3d", seed=21, raster_scale=0.25, camera_id="cam-h3d")
    out = calibrate_session(str(folder), str(tmp_path / "lake"), dask_address=address)
    m = out["measure"]
    n_frames = truth.frames.num_rows
    assert out["status"] == "committed" and out["images"]["measured"] == n_frames
    used = {t["worker"] for t in m["tasks"]}
    # every task ran on the two worker processes the test started (batches placed on both)
    assert used == set(workers)
    # connected, not a cluster of its own: the tasks ran in the two processes the test started
    assert m["n_workers"] == 2
    assert len({t["pid"] for t in m["tasks"]}) == 2 and os.getpid() not in {t["pid"] for t in m["tasks"]}

    frames = read_frames_csv(folder / "frames.csv")
    ref = gon.calibrate(truth.sensor, frames, truth.exact_measurements(),
                        nominal_focal_mm=truth.scenario.nominal_focal_mm)
    doc = Lake(tmp_path / "lake").load_document(out["version"])
    for k in ("f_mm", "xp_mm", "yp_mm"):
        z = (doc["parameters"][k] - ref.parameters[INDEX[k]]) / doc["sigma"][k]
        assert abs(z) < 3.0, f"{k}: {z:.2f} sigma from the noise-free value"
    assert np.isfinite(doc["stats"]["sigma_fit_px"]) and doc["stats"]["sigma_fit_px"] < 0.1
