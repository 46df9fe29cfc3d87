"""Recalibrate a fleet: every session under a root that has no committed calibration yet, in parallel.

:func:`recalibrate_fleet` (Prefect flow ``recalibrate-fleet``) is what a schedule runs
(``fieldcal serve``, which serves :func:`fleet_deployment` from one process, or
``deploy/prefect.yaml`` with a work pool):

1. **scan** the root (task): :func:`fieldcal.fleet.scan_sessions` finds every folder with
   a ``session.json`` (``ROOT/<session>/`` or ``ROOT/<camera>/<session>/``; a local path
   or an fsspec URL, by default ``<lake>/sessions``) and loads it with the session
   loader. A folder that does not load is reported with its reason.
2. **select**: :func:`fieldcal.fleet.select_sessions`: the sessions whose ``(camera_id,
   session_id)`` has no version in the lake; the others keep their latest version.
3. **calibrate** the selected sessions concurrently: one task :func:`calibrate_one` per
   session on the flow's thread pool (at most ``max_sessions`` at once), each running
   :func:`flows.calibrate.calibrate_session` as a sub-flow whose task runner is the
   fleet's Dask cluster: the images of every session and the sessions' solves are tasks on
   the same workers. The cluster is the scheduler at ``dask_address`` (or
   ``$FIELDCAL_DASK_ADDRESS``), else a local cluster started for the run. A session on an
   object store is handed over by its URL: its small files travel with the tasks and each
   worker reads its images from the store (docs/deployment.md). A failing session is
   recorded with its reason and never stops the others. A session that failed for a
   reason outside fieldcal (not bad input, geometry, convergence or the lake: e.g. an
   error of the Prefect API or a lost Dask connection) is run once more at once
   (:data:`RETRIES`); the lake makes that safe (observations cached, one version per
   fingerprint) and its summary entry keeps the first failure's reason (``retried``).
   A rig session (CONTRACT section 3, "Rig sessions") is calibrated by the task
   :func:`calibrate_rig` (:func:`fieldcal.rig_run.run_rig`; a session of images has them
   measured on the cluster, each worker reading its image, from the store for a session on
   one; the adjustment runs in the task's thread), committed as one version of the rig;
   its summary entry has the rig's id and version and lists its heads with their versions.
4. **progress and summary**: "session 3 of 5: cam / session: committed VERSION (12.3 s)" in
   the flow run's logs (and on a terminal), and a summary with every session found and
   its version, new or existing.
"""

from __future__ import annotations

import contextlib
import threading
import time

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.futures import as_completed
from prefect.task_runners import ThreadPoolTaskRunner

from fieldcal import fleet as fleet_lib
from fieldcal import progress
from fieldcal.errors import FieldcalError, one_line
from fieldcal.lake import secrets
from fieldcal.lake.store import Lake

from . import cluster
from .calibrate import calibrate_session
from .publish import fleet_run_name

__all__ = ["recalibrate_fleet", "calibrate_one", "calibrate_rig", "scan_sessions", "fleet_deployment", "serve_fleet",
           "publish_dashboard", "watch_runs",
           "DEFAULT_CRON", "DEPLOYMENT_NAME", "MAX_THREADS"]

DEFAULT_CRON = "0 2 * * *"
"""Every night at 02:00 UTC."""
DEPLOYMENT_NAME = "nightly"
MAX_THREADS = 32
"""Threads of the fleet flow's task runner (each session's task mostly waits on the cluster)."""
SUMMARY_KEY = "fleet-summary"
"""Key of the fleet run's table artifact (its description: the counts)."""
RETRIES = 1
"""Further runs of a session whose run failed for a reason outside fieldcal (:func:`_worth_retrying`)."""


@task(name="scan-sessions", cache_policy=NO_CACHE, persist_result=False)
def scan_sessions(root: str, storage_options: dict | None = None) -> list[fleet_lib.FoundSession]:
    """Session folders under ``root`` loaded by the session loader (:func:`fieldcal.fleet.scan_sessions`)."""
    return fleet_lib.scan_sessions(root, storage_options)


def _label(index: int, total: int, s: fleet_lib.FoundSession) -> str:
    return f"session {index} of {total}: {s.camera_id} / {s.session_id}"


@task(name="calibrate-one", cache_policy=NO_CACHE, persist_result=False,
      task_run_name="calibrate-{found.camera_id}-{found.session_id}")
def calibrate_one(found: fleet_lib.FoundSession, index: int, total: int, lake: str, storage_options: dict | None,
                  root_options: dict | None, address: str, n_workers: int, settings: dict | None,
                  batch_size: int | None) -> dict:
    """Calibrate one session of the fleet on the shared cluster; never raises.

    Returns the session's summary entry: ``folder``, ``camera_id``, ``session_id``,
    ``status`` ("committed" | "unchanged" | "failed"), ``version``, ``new``, ``reason``,
    ``seconds``, and ``retried`` (the first run's reason when the session was run again,
    else None).
    """
    logger = get_run_logger()
    label = _label(index, total, found)
    entry = fleet_lib.entry(found)
    logger.info(f"{label}: started")
    progress.emit("note", text=f"{label}: started")
    t = time.perf_counter()
    for attempt in range(1 + RETRIES):
        if found.rig:
            outcome = calibrate_rig(found.folder, lake, storage_options, root_options, settings, address)
        else:
            outcome = _run_session(found.folder, lake, storage_options, root_options, address, n_workers,
                                   settings, batch_size)
        if attempt == RETRIES or not _worth_retrying(outcome):
            break
        entry["retried"] = one_line(outcome)
        logger.warning(f"{label}: {type(outcome).__name__}: {entry['retried']}; running it again")
    entry["seconds"] = round(time.perf_counter() - t, 3)
    if isinstance(outcome, BaseException):
        entry.update(status="failed", reason=one_line(outcome))
        logger.error(f"{label}: failed: {entry['reason']}")
        progress.emit("note", text=f"{label}: failed ({entry['seconds']:.1f} s): {entry['reason']}")
    else:
        entry.update(status=outcome["status"], version=outcome["version"], new=bool(outcome["new"]),
                     n_images=outcome["images"]["total"], n_left_out=len(outcome["left_out"]))
        if found.rig:
            entry["heads"] = fleet_lib.head_entries(found.heads, outcome["head_versions"])
        if entry["retried"] and outcome["status"] == "unchanged":
            # the session had no version when the fleet started: the first run committed this
            # one and failed after its commit (e.g. closing its connection to the cluster)
            entry.update(status="committed", new=True)
        left = (f", {entry['n_left_out']} of {entry['n_images']} images left out" if entry["n_left_out"] else "")
        if entry.get("heads"):
            left += "; heads " + ", ".join(f"{h['camera_id']} {h['version']}" for h in entry["heads"])
        line = f"{label}: {entry['status']} {entry['version']}{left} ({entry['seconds']:.1f} s)"
        (logger.warning if entry["n_left_out"] else logger.info)(line)
        progress.emit("note", text=line)
    return entry


def _run_session(folder: str, lake: str, storage_options: dict | None, root_options: dict | None, address: str,
                 n_workers: int, settings: dict | None, batch_size: int | None):
    """One run of :func:`flows.calibrate.calibrate_session` on the cluster: its result, or
    the exception that ended it (never raised)."""
    try:
        with progress.quiet():
            runner = cluster.task_runner(address, n_workers)
            state = calibrate_session.with_options(task_runner=runner)(
                folder, lake, storage_options=secrets.redact(storage_options), settings=settings,
                batch_size=batch_size, return_state=True,
                session_storage_options=None if root_options == storage_options else secrets.redact(root_options))
            return state.result(raise_on_failure=False)
    except Exception as e:  # noqa: BLE001 - e.g. the store cannot be reached: record it, go on
        return e


@task(name="calibrate-rig", cache_policy=NO_CACHE, persist_result=False)
def calibrate_rig(folder: str, lake: str, storage_options: dict | None, root_options: dict | None,
                  settings: dict | None, address: str | None = None):
    """One rig session's run (:func:`fieldcal.rig_run.run_rig`) in this task's thread: a result
    like :func:`flows.calibrate.calibrate_session`'s (``status``, ``version`` the rig's, ``new``,
    ``images``, ``left_out``) with ``head_versions``, or the exception that ended it (never raised).
    ``folder`` a local path or a URL (``root_options``: its store's); the images of a session to
    measure are measured on the Dask cluster at ``address`` (each worker reads its image, from the
    store for a session on one), the adjustment runs here."""
    from fieldcal import pipeline, rig_run

    try:
        source = folder.removeprefix("file://")
        prepared = rig_run.prepare_rig(source, pipeline.Settings(**(settings or {})), root_options)
        with _rig_mapper(address if prepared.to_measure else None) as mapper:
            version, heads, outcome = rig_run.run_rig(source, Lake(lake, storage_options), prepared=prepared,
                                                      mapper=mapper)
    except Exception as e:  # noqa: BLE001 - recorded in the session's entry, the fleet goes on
        return e
    new = outcome is not None or bool(getattr(version, "new", False))      # solved, or an interrupted commit completed
    return {"status": "committed" if new else "unchanged", "version": str(version),
            "new": new, "images": {"total": len(prepared.session.images)}, "left_out": [],
            "head_versions": list(heads)}


@contextlib.contextmanager
def _rig_mapper(address: str | None):
    """``mapper(function, *iterables)`` of :func:`fieldcal.rig_run.measure_rig` on the Dask
    cluster at ``address`` (None: no cluster, measured in this thread)."""
    if address is None:
        yield None
        return
    import distributed

    with distributed.Client(address, timeout=60) as client:
        yield lambda fn, *its: client.gather(client.map(fn, *its, pure=False))


def _worth_retrying(outcome) -> bool:
    """Whether a session's run ended in a failure from outside fieldcal: an exception that is
    not a :class:`~fieldcal.errors.FieldcalError` (bad input, geometry, convergence and lake
    errors give the same answer again)."""
    return isinstance(outcome, Exception) and not isinstance(outcome, FieldcalError)


@contextlib.contextmanager
def _cluster(address: str | None, n_workers: int, cluster_kwargs: dict | None, logger):
    """The scheduler address to use: the given one, else a local cluster for the block."""
    address = cluster.dask_address(address)
    if address is not None:
        yield address
        return
    import distributed

    t = time.perf_counter()
    with distributed.LocalCluster(**cluster.local_cluster_kwargs(n_workers, cluster_kwargs)) as local:
        logger.info(f"started a local Dask cluster of {n_workers} worker(s) in {time.perf_counter() - t:.1f} s")
        yield local.scheduler_address


@flow(name="recalibrate-fleet", flow_run_name=fleet_run_name, persist_result=False,
      task_runner=ThreadPoolTaskRunner(max_workers=MAX_THREADS))
def recalibrate_fleet(lake: str, root: str | None = None, storage_options: dict | None = None,
                      root_storage_options: dict | None = None, dask_address: str | None = None,
                      n_workers: int = cluster.DEFAULT_WORKERS, settings: dict | None = None,
                      batch_size: int | None = None, cluster_kwargs: dict | None = None,
                      max_sessions: int | None = None, dashboard: str | None = None) -> dict:
    """Calibrate every session under ``root`` that has no committed calibration in ``lake``.

    Parameters
    ----------
    lake : str
        The lake (local path or fsspec URL).
    root : str, optional
        The root of session folders (local path or fsspec URL); default ``<lake>/sessions``.
    storage_options : dict, optional
        fsspec options of the lake. They are stored with the flow run: give secrets as
        :data:`fieldcal.lake.secrets.REDACTED` (the command line does), their values then
        come from ``FIELDCAL_STORAGE_OPTIONS`` or the storage's own configuration where the
        lake is opened (:mod:`fieldcal.lake.secrets`).
    root_storage_options : dict, optional
        fsspec options of the root (default: ``storage_options``), the same way.
    dask_address, n_workers, cluster_kwargs
        The cluster all sessions share: a scheduler address (else
        ``$FIELDCAL_DASK_ADDRESS``), or a local cluster of ``n_workers`` workers.
    settings, batch_size
        As for :func:`flows.calibrate.calibrate_session`.
    max_sessions : int, optional
        Sessions calibrated at once (default: twice the cluster's worker threads, so that
        one session's validation and commit overlap with the others' work on the cluster).
    dashboard : str, optional
        A local folder: the fleet dashboard is written there after the run
        (:func:`publish_dashboard`).

    Returns
    -------
    dict
        ``lake``, ``root``, ``sessions`` (per session found: ``folder``, ``camera_id``,
        ``session_id``, ``status`` ("committed" | "unchanged" | "failed" | "calibrated
        already"), ``version`` (new or existing), ``new``, ``reason``, ``seconds``), and the
        counts ``n_found``, ``n_committed``, ``n_failed``, ``n_skipped``.
    """
    logger = get_run_logger()
    root = root or (str(lake).rstrip("/") + "/sessions")
    root_options = root_storage_options if root_storage_options is not None else storage_options
    found = scan_sessions(root, root_options)
    todo = fleet_lib.select_sessions(found, Lake(lake, storage_options))
    logger.info(f"{len(found)} session(s) under {root}: {len(todo)} to calibrate, "
                f"{sum(1 for s in found if s.error)} that do not load")
    results: dict = {}
    for s in found:
        if s.error:
            logger.error(f"{s.folder}: {s.error}")
    if todo:
        # the sessions' subflows get the options redacted; their lakes find the values here
        with secrets.exported(storage_options), _cluster(dask_address, n_workers, cluster_kwargs, logger) as address:
            threads = n_workers if cluster.dask_address(dask_address) is None else _threads(address)
            at_once = max(1, int(max_sessions or 2 * threads))
            logger.info(f"calibrating {len(todo)} session(s), at most {at_once} at once, on {address}")
            args = (len(todo), lake, storage_options, root_options, address, n_workers, settings, batch_size)
            results = {id(s): r for s, r in zip(todo, _calibrate_all(todo, at_once, args), strict=True)}
    summary = fleet_lib.summarize(lake, root, found, results)
    partial = f" ({summary['n_partial']} with images left out)" if summary["n_partial"] else ""
    counts = (f"{summary['n_found']} found, {summary['n_committed']} committed{partial}, "
              f"{summary['n_failed']} failed, {summary['n_skipped']} skipped")
    logger.info(f"fleet: {counts}")
    _publish_summary(summary, counts)
    if dashboard:
        publish_dashboard(lake, storage_options, dashboard)
    return summary


@task(name="publish-dashboard", cache_policy=NO_CACHE, persist_result=False)
def publish_dashboard(lake: str, storage_options: dict | None, out: str) -> str | None:
    """Write the fleet dashboard (:func:`fieldcal.products.dashboard.write_dashboard`) into
    ``out`` and link it as an artifact; a failure is logged, never raised (the fleet's
    versions are committed). Returns the index's path."""
    from prefect.artifacts import create_link_artifact

    from fieldcal.products.dashboard import write_dashboard

    logger = get_run_logger()
    try:
        got = write_dashboard(Lake(lake, storage_options), out)
    except (FieldcalError, OSError) as e:
        logger.error(f"the dashboard was not written to {out}: {one_line(e)}")
        return None
    logger.info(f"dashboard: {got['index']} ({got['cameras']} cameras: {got['moved']} moved, "
                f"{got['expired']} expired, {got['failed']} failed)")
    create_link_artifact(got["index"].resolve().as_uri(), link_text="fleet dashboard", key="fleet-dashboard",
                         description=f"{got['cameras']} cameras: {got['moved']} moved, {got['expired']} expired, "
                                     f"{got['failed']} failed")
    return str(got["index"])


def _publish_summary(summary: dict, counts: str) -> None:
    """The fleet's summary as a table artifact (:data:`SUMMARY_KEY`), its counts as the description."""
    from prefect.artifacts import create_table_artifact

    rows = []
    for e in summary["sessions"]:
        rows.append({"camera_id": e["camera_id"], "session_id": e["session_id"], "status": fleet_lib.status_text(e),
                     "version": e["version"], "seconds": e["seconds"], "reason": e["reason"]})
        rows += [{"camera_id": h["camera_id"], "session_id": e["session_id"], "status": "head of rig "
                  f"{e['camera_id']}", "version": h["version"], "seconds": None, "reason": None}
                 for h in e.get("heads") or ()]
    create_table_artifact(rows, key=SUMMARY_KEY, description=counts)


def _calibrate_all(todo: list, at_once: int, args: tuple) -> list[dict]:
    """Run :func:`calibrate_one` for every session, at most ``at_once`` at a time; entries in order."""
    results: list = [None] * len(todo)
    pending: dict = {}
    queue = list(enumerate(todo))

    def submit_next():
        k, s = queue.pop(0)
        pending[calibrate_one.submit(s, k + 1, *args)] = k

    while queue and len(pending) < at_once:
        submit_next()
    while pending:
        fut = next(iter(as_completed(list(pending))))
        results[pending.pop(fut)] = fut.result()
        if queue:
            submit_next()
    return results


def _threads(address: str) -> int:
    import distributed

    with distributed.Client(address, timeout=60) as client:
        return cluster.worker_count(client)


def fleet_deployment(lake: str, root: str | None = None, *, name: str = DEPLOYMENT_NAME,
                     cron: str = DEFAULT_CRON, parameters: dict | None = None):
    """The deployment of :func:`recalibrate_fleet` on a cron schedule (UTC), for serving.

    Returns a :class:`prefect.deployments.runner.RunnerDeployment`; the flow is found by
    its module path (``flows.fleet.recalibrate_fleet``), so it runs from any directory.
    """
    from prefect.deployments.runner import EntrypointType

    params = {"lake": str(lake)}
    if root:
        params["root"] = str(root)
    params.update(parameters or {})
    return recalibrate_fleet.to_deployment(name=name, cron=cron, parameters=params,
                                           description="Calibrate every session that has no calibration yet",
                                           tags=["fieldcal"], entrypoint_type=EntrypointType.MODULE_PATH)


def serve_fleet(lake: str, root: str | None = None, *, report=None, **kwargs) -> None:
    """Serve :func:`fleet_deployment` from this process until interrupted (``fieldcal serve``).

    ``report(line)`` (optional) is told each run of the deployment as it starts and how it
    ended (:func:`watch_runs`, in a thread of this process)."""
    from prefect import serve

    deployment = fleet_deployment(lake, root, **kwargs)
    stop = threading.Event()
    if report is not None:
        threading.Thread(target=watch_runs, args=(f"recalibrate-fleet/{deployment.name}", report, stop),
                         daemon=True, name="fieldcal-serve-watch").start()
    try:
        serve(deployment, print_starting_message=False)
    finally:
        stop.set()


def _run_line(run, artifacts) -> str:
    state = run.state
    took = f" in {run.total_run_time.total_seconds():.1f} s" if run.total_run_time else ""
    summary = next((a.description for a in artifacts if a.key == SUMMARY_KEY and a.description), "")
    what = summary or (one_line(state.message) if state and state.message else "")
    return f"run {run.name}: {state.name.lower() if state else 'unknown'}{took}" + (f": {what}" if what else "")


def _news(client, deployment_id, said: dict, since) -> list[str]:
    """Lines about the deployment's runs that started (after ``since``) or ended since ``said``
    (updated). Only runs that started are asked for: a cron deployment keeps up to 100
    scheduled runs ahead, which would crowd a plain listing."""
    from prefect.client.schemas.filters import (
        ArtifactFilter,
        ArtifactFilterFlowRunId,
        DeploymentFilter,
        DeploymentFilterId,
        FlowRunFilter,
        FlowRunFilterStartTime,
    )
    from prefect.client.schemas.sorting import FlowRunSort

    lines = []
    runs = client.read_flow_runs(
        flow_run_filter=FlowRunFilter(start_time=FlowRunFilterStartTime(after_=since)),
        deployment_filter=DeploymentFilter(id=DeploymentFilterId(any_=[deployment_id])),
        sort=FlowRunSort.START_TIME_ASC, limit=50)
    for run in runs:
        final = bool(run.state and run.state.is_final())
        phase = "end" if final else "start" if run.state and run.state.type.value == "RUNNING" else None
        if phase is None or run.start_time is None or said.get(run.id) in (phase, "end"):
            continue                                   # not started yet (or cancelled before it started)
        if phase == "end":
            arts = client.read_artifacts(artifact_filter=ArtifactFilter(
                flow_run_id=ArtifactFilterFlowRunId(any_=[run.id])))
            lines.append(_run_line(run, arts))
        else:
            lines.append(f"run {run.name}: started")
        said[run.id] = phase
    return lines


def watch_runs(deployment: str, report, stop: threading.Event, poll_s: float = 2.0) -> None:
    """Report each flow run of ``deployment`` ("flow/name") as it starts and as it ends
    (its state, time and the fleet's counts), until ``stop`` is set; API errors are retried."""
    import datetime as dt

    from prefect.client.orchestration import get_client

    said: dict = {}
    since = dt.datetime.now(dt.UTC) - dt.timedelta(seconds=5)
    while not stop.wait(poll_s):
        try:
            with get_client(sync_client=True) as client:
                dep = client.read_deployment_by_name(deployment)
                for line in _news(client, dep.id, said, since):
                    report(line)
        except Exception:  # noqa: BLE001, S112 - the server may be starting or busy: try again
            continue
