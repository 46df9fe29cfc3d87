"""Faults: a Dask worker killed, the flow killed at every step, writes that fail, runs at once.

Every test checks the two promises of the lake (``fieldcal/lake/store.py``): a version is visible
only once its catalog row exists, which is written last; and nothing already done is lost
(the observations written before a fault are reused by the rerun). "Same result" means the
rerun's parameters, sigmas and statistics equal those of an undisturbed run of the same
session, compared to 1e-12 relative.

The faults are real where they can be on this machine: processes die by SIGKILL (flows,
Dask workers), a write fails in the kernel (a path under a regular file; a file size limit
set with ``RLIMIT_FSIZE``, the way a full disk or quota fails a write), and concurrent runs
are separate ``fieldcal run`` processes on one lake. The tests run as root here, so a
read-only directory would not stop a write; the file size limit stands in for it.
"""

import json
import os
import resource
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest

from fieldcal.lake import history
from fieldcal.lake.store import Lake
from fieldcal.model.camera import PARAM_NAMES
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session
from flows.calibrate import calibrate_session
from tests import standalone_dask as standalone

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]
N_FRAMES = 60            # the small goniometer session: 30 angles per axis, one frame each


@pytest.fixture(autouse=True)
def hash_store(tmp_path, monkeypatch):
    """Image hashes remembered in the test's own store (subprocesses inherit it)."""
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))


@pytest.fixture(scope="module")
def small_gonio(tmp_path_factory):
    """A goniometer session of 60 rendered frames and an undisturbed run of it: ``(folder, document)``."""
    folder = tmp_path_factory.mktemp("sessions") / "lab-faults"
    write_session(folder, "canon5d2", seed=11, raster_scale=0.25, frames_per_angle=1, camera_id="cam-faults")
    lake = tmp_path_factory.mktemp("reference-lake")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("FIELDCAL_HASH_CACHE", str(lake / "hashes.sqlite"))
        out = calibrate_session(str(folder), str(lake))
    assert out["images"]["measured"] == N_FRAMES
    return folder, Lake(lake).load_document(out["version"])


def child_env(prefect_server, **extra) -> dict:
    return dict(os.environ, PREFECT_API_URL=prefect_server, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
                PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL="CRITICAL", PYTHONPATH=str(ROOT), **extra)


def assert_same_result(doc: dict, ref: dict) -> None:
    """The rerun's calibration equals the undisturbed run's (parameters, sigmas, statistics)."""
    for part in ("parameters", "sigma"):
        got = np.array([doc[part][n] for n in PARAM_NAMES], float)
        want = np.array([ref[part][n] for n in PARAM_NAMES], float)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=0.0, err_msg=part)
    assert_close(doc["stats"], ref["stats"], "stats")
    assert doc["inputs"]["fingerprint"] == ref["inputs"]["fingerprint"]


def assert_close(got, want, where: str) -> None:
    """Nested dicts and lists equal, floats to 1e-12 relative."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and sorted(got) == sorted(want), where
        for k in want:
            assert_close(got[k], want[k], f"{where}.{k}")
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (g, w) in enumerate(zip(got, want, strict=True)):
            assert_close(g, w, f"{where}[{i}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, rel=1e-12, abs=1e-300), where
    else:
        assert got == want, where


def assert_nothing_visible(lake_dir: Path, camera_id: str) -> None:
    lake = Lake(lake_dir)
    assert lake.catalog().num_rows == 0
    assert lake.latest(camera_id) is None
    assert history.sql(lake, "SELECT count(*) AS n FROM catalog")["n"].to_pylist() == [0]


def assert_only_the_version(lake_dir: Path, version: str) -> None:
    """After ``gc``: the lake holds the one committed version's parts and no temporary file."""
    parts = sorted(p.name for p in (lake_dir / "calibrations").glob("*/*/*"))
    assert parts == [f"{version}.json", f"{version}.zarr"], parts
    assert residual_versions(lake_dir) == [version]
    assert not [p for p in lake_dir.rglob("*.tmp")]


def residual_versions(lake_dir: Path) -> list[str]:
    """Versions with rows in the residuals table, visible or not."""
    rows = Lake(lake_dir).tables.scan("residuals", columns=["version"])
    return sorted(set(rows["version"].to_pylist()))


def cached_images(lake_dir: Path) -> int:
    """Images with cached observations in the lake (one Delta append each)."""
    lake = Lake(lake_dir)
    return sum(len(lake.cached_keys(c, s)) for c, s in lake.sessions_with_observations())


# --------------------------------------------------------------------------------------
# the flow killed at every step
# --------------------------------------------------------------------------------------
KILLER = textwrap.dedent("""
    import os, signal, sys

    def die():
        os.kill(os.getpid(), signal.SIGKILL)

    def after(owner, name, when=lambda *args, **kwargs: True):
        original = getattr(owner, name)

        def wrapper(*args, **kwargs):
            out = original(*args, **kwargs)
            if when(*args, **kwargs):
                die()
            return out

        setattr(owner, name, wrapper)

    def before(owner, name):
        def wrapper(*args, **kwargs):
            die()

        setattr(owner, name, wrapper)

    if __name__ == "__main__":
        session, lake, point = sys.argv[1:4]
        import fieldcal.lake.store, fieldcal.lake.tables, fieldcal.pipeline

        writes = []
        if point == "validated":             # the session is validated, nothing is measured
            after(fieldcal.pipeline, "prepare")
        elif point == "measuring":           # 20 or more of the 60 frames' observations are written
            after(fieldcal.lake.store.Lake, "write_observations_many",
                  lambda lake, camera, session, items: writes.extend(items) or len(writes) >= 20)
        elif point == "observed":            # every observation is written, the solve starts
            before(fieldcal.pipeline, "solve")
        elif point == "solved":              # solved, the commit starts
            before(fieldcal.lake.store.Lake, "commit")
        elif point == "zarr-written":        # document and Zarr group written, no residuals, no row
            after(fieldcal.lake.store.Lake, "_write_zarr")
        elif point == "residuals-appended":  # residual rows committed, the catalog row not
            before(fieldcal.lake.tables.Tables, "append_once")
        else:
            raise SystemExit(f"unknown point {point}")
        from flows.calibrate import calibrate_session

        calibrate_session(session, lake, batch_size=10)   # several appends: a kill between them
""")


@pytest.mark.parametrize("point, written", [("validated", (0, 0)), ("measuring", (20, N_FRAMES - 1)),
                                            ("observed", (N_FRAMES, N_FRAMES)), ("solved", (N_FRAMES, N_FRAMES)),
                                            ("zarr-written", (N_FRAMES, N_FRAMES)),
                                            ("residuals-appended", (N_FRAMES, N_FRAMES))])
def test_flow_killed_at_any_step_leaves_no_version_and_the_rerun_gives_the_same_result(
        prefect_server, small_gonio, tmp_path, point, written):
    folder, ref = small_gonio
    lake_dir = tmp_path / "lake"
    script = tmp_path / "killed_run.py"
    script.write_text(KILLER)
    proc = subprocess.run([sys.executable, str(script), str(folder), str(lake_dir), point],
                          env=child_env(prefect_server), cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr[-3000:]
    assert_nothing_visible(lake_dir, "cam-faults")
    n_obs = cached_images(lake_dir)
    assert written[0] <= n_obs <= written[1]  # what was done before the kill is kept ...

    out = calibrate_session(str(folder), str(lake_dir))
    assert out["status"] == "committed"
    assert out["images"]["cached"] == n_obs  # ... and reused, not measured again
    assert out["images"]["cached"] + out["images"]["measured"] == N_FRAMES
    lake = Lake(lake_dir)
    assert lake.catalog()["version"].to_pylist() == [out["version"]]
    assert lake.latest("cam-faults") == out["version"]
    assert_same_result(lake.load_document(out["version"]), ref)
    lake.gc(grace_s=0.0)                         # the killed run's leftovers go; the version stays
    assert_only_the_version(lake_dir, out["version"])
    assert lake.catalog()["version"].to_pylist() == [out["version"]]


# --------------------------------------------------------------------------------------
# a Dask worker killed in the middle of extraction
# --------------------------------------------------------------------------------------
def test_a_dask_worker_killed_during_extraction_does_not_stop_the_run(small_gonio, tmp_path):
    folder, ref = small_gonio
    lake_dir = tmp_path / "lake"
    killed = {}

    def kill_when_measuring(procs):
        standalone.wait_for(lambda: cached_images(lake_dir) >= 12, 120, "no observation was written")
        killed["n_obs"] = cached_images(lake_dir)
        procs[0].send_signal(signal.SIGKILL)
        killed["pid"] = procs[0].pid

    with standalone.standalone_cluster(tmp_path, 2, nanny=False) as (address, workers, procs):
        watcher = threading.Thread(target=kill_when_measuring, args=(procs,), daemon=True)
        watcher.start()
        # 4 frames per task: 15 tasks, several still to run on the killed worker when it dies
        out = calibrate_session(str(folder), str(lake_dir), dask_address=address, batch_size=4)
        watcher.join(5)
        assert procs[0].poll() == -signal.SIGKILL and procs[1].poll() is None
    assert 12 <= killed["n_obs"] <= 32
    tasks = out["measure"]["tasks"]
    assert sum(t["n"] for t in tasks) == N_FRAMES
    # the killed worker delivered only tasks it finished before it died (an undisturbed
    # run splits the 15 tasks about evenly: 7 or 8 each)
    n_dead = sum(t["worker"] == workers[0] for t in tasks)
    assert 4 * n_dead <= killed["n_obs"] + 4
    assert out["images"]["bad"] == 0 and out["images"]["measured"] + out["images"]["cached"] == N_FRAMES
    # the survivor did the rest: Dask moved the dead worker's tasks to it
    assert {t["worker"] for t in tasks} <= set(workers)
    assert sum(t["worker"] == workers[1] for t in tasks) > len(tasks) / 2
    lake = Lake(lake_dir)
    assert lake.catalog()["version"].to_pylist() == [out["version"]]
    assert_same_result(lake.load_document(out["version"]), ref)


def test_a_worker_lost_while_it_holds_pulled_images_loses_none_of_them(small_gonio, tmp_path, monkeypatch):
    # the default fan-out: one task per worker, both pulling images (here one per pull) from
    # the run's queue. The order is forced, nothing left to timing: worker 1 is stopped
    # (SIGSTOP) before the run, so worker 0 takes the first image; the flow puts the second
    # only once worker 0 has reported the first and is stopped in turn (it holds that
    # image's observations, appended only when its task ends); worker 1 then resumes and
    # empties the queue, and worker 0 is killed: what it held must be measured again.
    import distributed

    from fieldcal import batch
    from flows import image_events

    monkeypatch.setattr(batch, "MIN_PULL_S", 0.0)        # one image per pull
    folder, ref = small_gonio
    lake_dir = tmp_path / "lake"
    reported, first = {}, threading.Event()
    put = distributed.Queue.put

    def put_after_the_first_is_held(queue, value, *args, **kwargs):   # the flow's puts (this process)
        if getattr(queue, "_puts", 0) == 1:
            assert first.wait(120), "worker 0 reported no image"
        queue._puts = getattr(queue, "_puts", 0) + 1
        return put(queue, value, *args, **kwargs)

    monkeypatch.setattr(distributed.Queue, "put", put_after_the_first_is_held)

    with standalone.standalone_cluster(tmp_path, 2, nanny=False) as (address, workers, procs), \
            distributed.Client(address) as watch:

        def on_event(event):                             # in the client's event loop
            msg = event[1]
            reported.setdefault(msg["worker"], set()).add(msg["image"])
            if msg["worker"] == workers[0] and not first.is_set():
                procs[0].send_signal(signal.SIGSTOP)
                first.set()

        watch.subscribe_topic(image_events.TOPIC, on_event)

        def resume_the_other_then_kill():
            try:
                assert first.wait(120), "worker 0 reported no image"
            finally:
                procs[1].send_signal(signal.SIGCONT)
            # worker 1's task ends only at its end marker: every image pulled
            standalone.wait_for(lambda: sum(map(len, watch.processing(workers=[workers[1]]).values())) == 0
                                and len(reported.get(workers[1], ())) > 0, 120, "worker 1 did not finish")
            procs[0].send_signal(signal.SIGKILL)

        procs[1].send_signal(signal.SIGSTOP)
        watcher = threading.Thread(target=resume_the_other_then_kill, daemon=True)
        watcher.start()
        try:
            out = calibrate_session(str(folder), str(lake_dir), dask_address=address)
        finally:
            procs[1].send_signal(signal.SIGCONT)
            watcher.join(5)
        assert procs[0].poll() == -signal.SIGKILL and procs[1].poll() is None
    m = out["measure"]
    held = reported[workers[0]]
    # worker 0 measured exactly the first image (nothing else was in the queue until it was
    # stopped); it may also have asked for the next one before the stop, and holds it then
    assert m["pulled"] and len(held) == 1
    # three tasks: the survivor's; the lost one's, run again by Dask, finding the queue
    # empty; and the images no task returned (what the lost worker held), measured again
    n_held = N_FRAMES - max(t["n"] for t in m["tasks"])
    assert sorted(t["n"] for t in m["tasks"]) == [0, n_held, N_FRAMES - n_held] and n_held in (1, 2)
    # nothing came back from the lost worker; its images were measured by the survivor
    assert all(t["worker"] == workers[1] for t in m["tasks"])
    assert sorted(r["image"] for r in m["rows"]) == sorted(set(r["image"] for r in m["rows"]))
    assert len(m["rows"]) == N_FRAMES and held <= {r["image"] for r in m["rows"] if r["status"] == "measured"}
    assert out["images"]["bad"] == 0 and out["images"]["measured"] == N_FRAMES
    lake = Lake(lake_dir)
    assert lake.catalog()["version"].to_pylist() == [out["version"]]
    assert_same_result(lake.load_document(out["version"]), ref)


# --------------------------------------------------------------------------------------
# writes that fail
# --------------------------------------------------------------------------------------
def fieldcal_run(prefect_server, *args, limit_bytes=None, timeout=300):
    """``fieldcal run ...`` in a process of its own (with a file size limit when given)."""
    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)      # a write past the limit fails with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, limit_bytes))

    return subprocess.run([sys.executable, "-m", "flows.cli", "run", *map(str, args)],
                          env=child_env(prefect_server), cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, preexec_fn=limit if limit_bytes else None)


@pytest.fixture(scope="module")
def field_sessions(tmp_path_factory):
    """Two observation-only field sessions of one camera: ``{session_id: folder}``."""
    root = tmp_path_factory.mktemp("field-sessions")
    out = {}
    for sid, sf in (("wall-a", wide_field(seed=3)), ("wall-b", wide_field(seed=4))):
        write_field_session(root / sid, sf, images=False, observations_csv=True, camera_id="cam-wall")
        out[sid] = root / sid
    return out


def test_a_full_destination_fails_the_commit_cleanly_and_the_next_run_commits(
        prefect_server, field_sessions, tmp_path):
    lake_dir = tmp_path / "lake"
    session = field_sessions["wall-a"]
    # 64 KiB per file: the document fits, the version's residual rows (~100 KiB) do not
    proc = fieldcal_run(prefect_server, session, "--lake", lake_dir, limit_bytes=64 * 1024)
    assert proc.returncode == 1, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("fieldcal run: cannot commit to "), proc.stderr[-3000:]
    assert str(lake_dir) in lines[0] and "File too large" in lines[0]
    assert proc.stdout == ""
    assert_nothing_visible(lake_dir, "cam-wall")
    # the failed commit removed what it had written (a data file delta-rs could not finish
    # is in no commit: no reader sees it)
    assert not [p for p in (lake_dir / "calibrations").rglob("*") if p.is_file()]
    assert residual_versions(lake_dir) == []

    proc = fieldcal_run(prefect_server, session, "--lake", lake_dir, "--json", tmp_path / "out.json")
    assert proc.returncode == 0, proc.stderr[-3000:]
    version = proc.stdout.strip()
    assert Lake(lake_dir).catalog()["version"].to_pylist() == [version]
    assert json.loads((tmp_path / "out.json").read_text())["version"] == version


def test_a_lake_that_cannot_be_written_fails_the_run_with_one_line(prefect_server, small_gonio, tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a regular file where the lake's parent folder should be\n")
    folder, _ = small_gonio
    proc = fieldcal_run(prefect_server, folder, "--lake", blocker / "lake", "--json", tmp_path / "out.json")
    assert proc.returncode == 1, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(blocker) in lines[0] and "Not a directory" in lines[0], proc.stderr[-3000:]
    assert blocker.read_text().startswith("a regular file")
    assert not (tmp_path / "out.json").exists() and proc.stdout == ""


# --------------------------------------------------------------------------------------
# several runs at once on one lake
# --------------------------------------------------------------------------------------
def test_concurrent_runs_of_the_same_and_different_sessions_lose_nothing(
        prefect_server, field_sessions, small_gonio, tmp_path):
    lake_dir = tmp_path / "lake"
    gonio, ref = small_gonio
    sessions = [field_sessions["wall-a"], field_sessions["wall-a"], field_sessions["wall-b"], gonio, gonio]
    env = child_env(prefect_server)
    procs = []
    for i, session in enumerate(sessions):
        procs.append(subprocess.Popen(
            [sys.executable, "-m", "flows.cli", "run", str(session), "--lake", str(lake_dir),
             "--json", str(tmp_path / f"run{i}.json")],
            env=env, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outputs = [p.communicate(timeout=600) for p in procs]
    for p, (_, err) in zip(procs, outputs, strict=True):
        assert p.returncode == 0, err[-3000:]
    versions = [out.strip() for out, _ in outputs]
    # one version per session: the runs of the same inputs agree on it
    assert versions[0] == versions[1] and versions[3] == versions[4]
    assert len({versions[0], versions[2], versions[3]}) == 3
    lake = Lake(lake_dir)
    cat = lake.catalog()
    assert sorted(cat["version"].to_pylist()) == sorted({versions[0], versions[2], versions[3]})
    assert lake.latest("cam-wall", "wall-a") == versions[0]
    assert lake.latest("cam-wall", "wall-b") == versions[2]
    assert lake.latest("cam-faults") == versions[3]
    rows = history.sql(lake, "SELECT camera_id, session_id, count(*) AS n FROM catalog "
                             "GROUP BY camera_id, session_id ORDER BY camera_id, session_id")
    assert rows.to_pylist() == [{"camera_id": "cam-faults", "session_id": "lab-faults", "n": 1},
                                {"camera_id": "cam-wall", "session_id": "wall-a", "n": 1},
                                {"camera_id": "cam-wall", "session_id": "wall-b", "n": 1}]
    for i in range(len(sessions)):
        assert json.loads((tmp_path / f"run{i}.json").read_text())["version"] == versions[i]
    # the two runs of the image session measured the same frames at once: the cache holds
    # each frame once (a frame cached twice reads back once), and the calibration is the
    # undisturbed one; the losers of the same inputs removed their residual rows
    assert cached_images(lake_dir) == N_FRAMES
    assert residual_versions(lake_dir) == sorted({versions[0], versions[2], versions[3]})
    assert_same_result(lake.load_document(versions[3]), ref)
