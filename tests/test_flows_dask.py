"""The calibration flow against a Dask scheduler and two workers running as separate processes.

The test starts ``dask scheduler`` and two ``dask worker`` processes on loopback (one
thread each, the preload and thread settings of ``deploy/dask/``), the way a standing
cluster runs in a deployment, and gives the flow only the scheduler's address.
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fieldcal import goniometer as gon
from fieldcal.camera import INDEX
from fieldcal.lake import Lake
from fieldcal.synth_goniometer import write_session
from flows.calibrate import calibrate_session

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture(autouse=True)
def hash_store(tmp_path, monkeypatch):
    """Image hashes remembered in the test's own store (never in ~/.cache)."""
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))


def _wait_for(predicate, timeout_s, what, procs):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: a process exited with {p.returncode}: {p.stderr.read()[-2000:]}")
        time.sleep(0.2)
    raise TimeoutError(f"{what} within {timeout_s} s")


@pytest.fixture(scope="module")
def standalone_cluster(tmp_path_factory):
    """``(scheduler address, [worker addresses])`` of a scheduler and two worker processes."""
    import distributed

    tmp = tmp_path_factory.mktemp("dask")
    sched_file = tmp / "scheduler.json"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=str(ROOT), DASK_LOGGING__DISTRIBUTED="warning")
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    procs = [subprocess.Popen(dask + ["--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                                      "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(sched_file)],
                              env=env, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)]
    try:
        _wait_for(sched_file.exists, 60, "the scheduler did not write its file", procs)
        for i in range(2):
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file", str(sched_file),
                 "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                 "--name", f"w{i}", "--preload", "flows.worker", "--memory-limit", "2GiB"],
                env=env, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        address = json.loads(sched_file.read_text())["address"]
        with distributed.Client(address, timeout=60) as client:
            client.wait_for_workers(2, timeout=120)
            workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
        yield address, workers
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
            if p.stderr:
                p.stderr.close()


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
    # every task ran on the two worker processes the test started (one probe on each)
    assert used == set(workers)
    assert m["n_workers"] == 2 and m["cluster_s"] < 10.0       # connecting, not starting a cluster
    assert len({t["pid"] for t in m["tasks"]}) == 2 and os.getpid() not in {t["pid"] for t in m["tasks"]}

    frames = gon.read_frames_csv(folder / "frames.csv")
    ref = gon.calibrate(truth.sensor, frames, truth.exact_measurements(),
                        nominal_focal_mm=truth.scenario.nominal_focal_mm)
    doc = Lake(tmp_path / "lake").load_document(out["version"])
    for k in ("f_mm", "xp_mm", "yp_mm"):
        z = (doc["parameters"][k] - ref.parameters[INDEX[k]]) / doc["sigma"][k]
        assert abs(z) < 3.0, f"{k}: {z:.2f} sigma from the noise-free value"
    assert np.isfinite(doc["stats"]["sigma_fit_px"]) and doc["stats"]["sigma_fit_px"] < 0.1
