"""The fleet flow: sessions at once on one Dask cluster, a failing one never stops the others.

The sessions are small observation-only field sessions (a wide-angle camera, 24 images)
and one goniometer session of rendered frames, so that sessions and images share the
cluster's workers. Concurrency is shown, not timed: the solver is wrapped so that the first
two solves must meet (the first waits for the second to start), which they can only do when
two sessions are solved at the same time on the cluster. The waiting solve leaves its
worker's thread (``distributed.secede``) so that it never holds up the other sessions'
tasks; after the wait, met or not, it solves as usual, so that a missed meeting fails one
assertion instead of the sessions.
"""

import io
import json
import sys
import threading
import time

import pytest

from fieldcal import pipeline
from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session
from flows import cli, server
from flows.fleet import recalibrate_fleet

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


class Terminal(io.StringIO):
    def isatty(self):
        return True


class Rendezvous:
    """The first ``n`` callers wait for each other (up to ``timeout_s``); later ones pass.

    ``arrived`` lists the callers' labels in order; ``met`` whether the first ``n`` met.
    """

    def __init__(self, n: int, timeout_s: float):
        self.n, self.timeout_s = n, timeout_s
        self.cond = threading.Condition()
        self.arrived: list[str] = []
        self.met = False

    def __call__(self, where: str) -> None:
        with self.cond:
            self.arrived.append(where)
            if len(self.arrived) > self.n:
                return
            self.cond.notify_all()
            if self.cond.wait_for(lambda: len(self.arrived) >= self.n, self.timeout_s):
                self.met = True


@pytest.fixture
def root(tmp_path):
    """4 observation-only sessions of two cameras, a goniometer session, one that cannot calibrate, one broken."""
    root = tmp_path / "sessions"
    for k in range(4):
        write_field_session(root / f"cam-w{k % 2}" / f"2026-05-0{k + 1}", wide_field(seed=20 + k), images=False,
                            observations_csv=True, camera_id=f"cam-w{k % 2}", acquired=f"2026-05-0{k + 1}")
    write_session(root / "cam-lab" / "2026-05-09", "canon5d2", seed=29, raster_scale=0.25, frames_per_angle=1,
                  camera_id="cam-lab")
    few = root / "cam-few" / "2026-05-10"              # two images: the field method needs three
    write_field_session(few, wide_field(seed=30), images=False, observations_csv=True, camera_id="cam-few")
    lines = (few / "observations.csv").read_text().splitlines()
    two = sorted({ln.split(",")[0] for ln in lines[1:]})[:2]
    (few / "observations.csv").write_text("\n".join([lines[0]] + [ln for ln in lines[1:]
                                                                   if ln.split(",")[0] in two]) + "\n")
    (root / "broken").mkdir()
    (root / "broken" / "session.json").write_text("{not json")
    return root


def fleet_logs(root) -> str | None:
    """The log lines of the latest fleet flow run over ``root`` on the test's Prefect server."""
    from prefect import get_client
    from prefect.client.schemas.filters import LogFilter, LogFilterFlowRunId
    from prefect.client.schemas.sorting import FlowRunSort

    with get_client(sync_client=True) as client:
        runs = client.read_flow_runs(sort=FlowRunSort.EXPECTED_START_TIME_DESC, limit=50)
        runs = [r for r in runs if r.parameters.get("root") == str(root)]
        if not runs:
            return None
        logs = client.read_logs(LogFilter(flow_run_id=LogFilterFlowRunId(any_=[runs[0].id])), limit=200)
    return "\n".join(log.message for log in logs)


def test_fleet_calibrates_sessions_at_once_and_a_failing_one_does_not_stop_the_others(root, tmp_path, monkeypatch,
                                                                                       capsys):
    meet = Rendezvous(2, timeout_s=600.0)
    solve = pipeline.solve

    def solve_together(*args, **kwargs):
        from distributed import get_worker, rejoin, secede

        where = get_worker().address
        secede()                      # the worker's thread is free for other tasks while this one waits
        try:
            meet(where)
        finally:
            rejoin()
        return solve(*args, **kwargs)

    monkeypatch.setattr(pipeline, "solve", solve_together)
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    monkeypatch.setattr(server, "quiet_prefect", lambda verbose: None)
    term = Terminal()
    monkeypatch.setattr(sys, "stderr", term)
    lake = str(tmp_path / "lake")
    assert cli.main(["fleet", str(root), "--lake", lake, "--format", "json"]) == 1          # 2 failed
    first = json.loads(capsys.readouterr().out)
    status = {(s["camera_id"], s["session_id"]): s["status"] for s in first["sessions"]}
    reasons = {(s["camera_id"], s["session_id"]): s["reason"] or f"run again after: {s['retried']}"
               for s in first["sessions"] if s["reason"] or s["retried"]}
    assert status == {("cam-w0", "2026-05-01"): "committed", ("cam-w1", "2026-05-02"): "committed",
                      ("cam-w0", "2026-05-03"): "committed", ("cam-w1", "2026-05-04"): "committed",
                      ("cam-lab", "2026-05-09"): "committed", ("cam-few", "2026-05-10"): "failed",
                      (None, None): "failed"}, reasons
    assert (first["n_found"], first["n_committed"], first["n_failed"]) == (7, 5, 2)
    # the first two solves met: two sessions solved at once on the cluster; six sessions
    # reach the solve, a session run again (a failure outside fieldcal, e.g. the Prefect
    # server's "database is locked" under load) a second time if its first run had got there
    retried = sum(1 for s in first["sessions"] if s["retried"])
    assert meet.met and 6 <= len(meet.arrived) <= 6 + retried, (meet.arrived, reasons)
    few = next(s for s in first["sessions"] if s["camera_id"] == "cam-few")
    assert "at least 3" in few["reason"] and few["version"] is None
    # every session's version, and the lake agrees
    committed = {s["version"] for s in first["sessions"] if s["status"] == "committed"}
    assert committed == set(Lake(lake).catalog()["version"].to_pylist()) and len(committed) == 5

    # progress per session on the terminal (not the sessions' own image counts) and in the logs
    text = term.getvalue()
    for k in range(1, 7):
        assert f"session {k} of 6: " in text
    assert ": committed " in text and ": failed " in text and "measuring images [" not in text
    deadline = time.monotonic() + 60
    while (logs := fleet_logs(root) or "").count(" of 6: ") < 12 and time.monotonic() < deadline:
        time.sleep(0.5)                                         # logs reach the server in batches
    assert logs.count(" of 6: ") >= 12 and "session 6 of 6: " in logs   # started and finished, each

    # the next night: the calibrated sessions keep their versions, the failing one is tried again
    second = recalibrate_fleet(lake, str(root), n_workers=2)
    again = {(s["camera_id"], s["session_id"]): (s["status"], s["version"]) for s in second["sessions"]}
    for s in first["sessions"]:
        if s["status"] == "committed":
            assert again[(s["camera_id"], s["session_id"])] == ("calibrated already", s["version"])
    assert again[("cam-few", "2026-05-10")] == ("failed", None)
    assert (second["n_committed"], second["n_skipped"], second["n_failed"]) == (0, 5, 2)


def test_a_session_failing_outside_fieldcal_is_run_again_and_a_geometry_failure_is_not(tmp_path, monkeypatch):
    """A run that ends in an error from outside fieldcal (here a lost connection, raised by the
    first solve of one session, and after the first commit of another) is run once more and
    commits, or finds its first run's version; its entry keeps the first reason. A session
    that cannot calibrate (GeometryError) runs once."""
    root = tmp_path / "sessions"
    write_field_session(root / "cam-ok" / "2026-06-01", wide_field(seed=40), images=False, observations_csv=True,
                        camera_id="cam-ok")
    write_field_session(root / "cam-late" / "2026-06-03", wide_field(seed=42), images=False, observations_csv=True,
                        camera_id="cam-late")
    commit = Lake.commit
    commits: list[str] = []

    def commit_then_lose_the_connection(self, document, *args, **kwargs):
        version = commit(self, document, *args, **kwargs)
        commits.append(document["camera_id"])
        if document["camera_id"] == "cam-late" and commits.count("cam-late") == 1:
            raise ConnectionResetError("lost the connection after the commit")
        return version

    monkeypatch.setattr(Lake, "commit", commit_then_lose_the_connection)
    few = root / "cam-few" / "2026-06-02"
    write_field_session(few, wide_field(seed=41), images=False, observations_csv=True, camera_id="cam-few")
    lines = (few / "observations.csv").read_text().splitlines()
    two = sorted({ln.split(",")[0] for ln in lines[1:]})[:2]
    (few / "observations.csv").write_text("\n".join([lines[0]] + [ln for ln in lines[1:]
                                                                   if ln.split(",")[0] in two]) + "\n")
    calls: dict[str, int] = {}
    lock = threading.Lock()
    solve = pipeline.solve

    def flaky_solve(prepared, *args, **kwargs):
        camera = prepared.session.camera_id
        with lock:
            calls[camera] = calls.get(camera, 0) + 1
            first = calls[camera] == 1
        if camera == "cam-ok" and first:
            raise ConnectionResetError("lost the connection to the scheduler")
        return solve(prepared, *args, **kwargs)

    monkeypatch.setattr(pipeline, "solve", flaky_solve)
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    summary = recalibrate_fleet(str(tmp_path / "lake"), str(root), n_workers=2)
    entries = {s["camera_id"]: s for s in summary["sessions"]}
    assert calls == {"cam-ok": 2, "cam-few": 1, "cam-late": 1}       # cam-late's second run: no solve
    assert entries["cam-ok"]["status"] == "committed" and entries["cam-ok"]["version"]
    assert "lost the connection to the scheduler" in entries["cam-ok"]["retried"]
    assert entries["cam-few"]["status"] == "failed" and entries["cam-few"]["retried"] is None
    assert "at least 3" in entries["cam-few"]["reason"]
    # the second run found the version the first committed: one version, reported as this run's
    late = entries["cam-late"]
    assert (late["status"], late["new"]) == ("committed", True) and "after the commit" in late["retried"]
    catalog = Lake(str(tmp_path / "lake")).catalog()
    assert catalog["camera_id"].to_pylist().count("cam-late") == 1 and commits.count("cam-late") == 1
    assert late["version"] in catalog["version"].to_pylist()
    assert (summary["n_committed"], summary["n_failed"]) == (2, 1)
