"""The calibration flow of one session: validate -> measure the images on Dask -> solve -> commit.

:func:`calibrate_session` (Prefect flow ``calibrate-session``) decides what runs where; every
piece of real work and every decision a notebook would also make is a plain function of
:mod:`fieldcal.pipeline` (validate, measure, solve) and :mod:`fieldcal.batch` (cache keys,
what is cached, the no-op check, batch sizes):

1. **validate** (task, in the flow's process): :func:`fieldcal.pipeline.prepare`. Bad input
   raises :class:`~fieldcal.errors.InputError` naming the file; nothing is written anywhere.
2. **plan**: each image's SHA-256 from the hash store (:mod:`flows.hashcache`, no image is
   read for it), then :func:`fieldcal.batch.plan_session`: missing files, cached
   observations, the images left to measure, and the no-op (every hash known and a version
   with the same fingerprint committed: that version is returned; ``force=True`` makes a
   new one).
3. **measure** (tasks :func:`measure_batch` on Dask, one per worker thread pulling the
   images from a queue, :func:`fan_out`): each task hashes its images (unless
   known), skips those cached under that hash and measures the others
   (:func:`fieldcal.batch.measure_into_lake`), their observations into the lake. A
   bad image is reported and left out; the run goes on. Where the tasks run:

   - the flow's own task runner when it is a :class:`prefect_dask.DaskTaskRunner` (the
     command line and the fleet call ``calibrate_session.with_options(task_runner=...)``);
     it connects to the cluster, or starts a local one, at the first task only;
   - otherwise a Dask task runner for ``dask_address`` (or ``$FIELDCAL_DASK_ADDRESS``, or
     a temporary local cluster), entered by the flow itself only when some image has to
     be read and left (the local cluster stopped) when the images are measured. Its task
     runs belong to this flow run: no sub-flow run, whose start and end cost Prefect
     ~0.5-1 s per run (``bench/README_flow.md``).
4. **solve** (task): reads the observations back from the lake and runs
   :func:`fieldcal.pipeline.solve`, on the Dask cluster when the flow runs on one that is
   reached by address or was started for the images (so that the fleet's sessions share
   the workers), else in the flow's process.
5. **commit** (task): :meth:`fieldcal.lake.store.Lake.commit`: everything of the version
   first, its catalog row last. A run killed before this point leaves no visible version;
   the rerun finds the observations cached and completes the work.

Where the images go (:func:`fan_out`): one measuring task per worker thread, placed on it,
and every task pulls the images from a Dask queue of the run, a full-size frame (or ~0.25 s
of a goniometer's small frames) at a time (:func:`fieldcal.batch.pull_chunks`), until the
queue's end marker: the threads stay busy to the last image and finish within one image of
each other, with one Prefect task run each (~0.25 s of a worker's CPU per task run; the
guided batches 36, 18, 9, 5, 2, 1, 1 of 72 frames before made seven). Each task appends its
observations to the lake every 30 s of measuring and at its end; an image no task returned
(a worker lost) is measured again by a task of its own. ``batch_size`` (``--batch-size``)
gives fixed batches instead, placed so that each thread gets an equal share.

Progress goes to :mod:`fieldcal.progress` (the command line shows it on a terminal) and to
the Prefect logger (the flow run's logs on the Prefect server).
"""

from __future__ import annotations

import functools
import os
import resource
import threading
import time
import uuid
from dataclasses import dataclass, field

import dask
from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.context import FlowRunContext
from prefect.futures import as_completed
from prefect.runtime import task_run
from prefect_dask import DaskTaskRunner

from fieldcal import batch, pipeline, progress
from fieldcal.errors import InputError, LakeError
from fieldcal.lake.store import Lake

from . import cluster, image_events, publish
from .hashcache import HashCache, file_stamp, known_hashes

__all__ = ["calibrate_session", "measure_batch", "validate_session", "solve_session",
           "commit_version", "fan_out", "submit_placed", "warm_process"]


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------
def _settings(settings: dict | None) -> pipeline.Settings:
    try:
        return pipeline.Settings(**(settings or {}))
    except TypeError:
        known = sorted(pipeline.Settings().to_dict())
        raise InputError(f"unknown setting(s) {sorted(set(settings or {}) - set(known))}; known: "
                         f"{known}", "settings") from None


def _worker_info() -> tuple[str | None, int | None]:
    try:
        from distributed import get_worker

        w = get_worker()
        return w.address, int(w.state.nthreads)
    except (ImportError, ValueError, AttributeError):
        return None, None


def _peak_rss_mb() -> float:
    """Peak resident memory of this process so far [MiB].

    ``VmHWM`` from ``/proc/self/status`` (Linux): unlike ``getrusage``'s ``ru_maxrss`` it
    does not include the parent's peak in a process started by fork + exec (Dask's
    worker processes).
    """
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0          # kB
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0   # Linux: KiB


PULL_TIMEOUT_S = 60.0
"""A measuring task that finds its queue empty this long stops (:func:`_pulled`)."""
_WARM_LOCK = threading.Lock()
_WARMED: set[str] = set()


def warm_process(method: str, nthreads: int | None) -> None:
    """Import and run the measuring code (:func:`fieldcal.measure.warm.warm_up_measuring`)
    before the work is timed, once per process (threads wait for a warm-up in progress
    instead of repeating it); one OpenCV thread and one codec thread per Dask thread.
    Called by the flow before an in-process cluster starts, by every measuring task, and by
    a worker process's preload (:mod:`flows.worker`)."""
    with _WARM_LOCK:
        if method not in _WARMED:
            if method == "goniometer":
                import fieldcal.goniometer.method  # noqa: F401
            else:
                from fieldcal.measure.warm import warm_up_measuring

                warm_up_measuring()
            _WARMED.add(method)
    if nthreads:
        import cv2

        from fieldcal.measure.imageio import set_decode_threads

        set_decode_threads(nthreads)
        if cv2.getNumThreads() != nthreads:
            cv2.setNumThreads(nthreads)


def _transient(task_, task_run, state) -> bool:
    """Retry a measuring task only for storage trouble (network, object store), never for bugs."""
    try:
        exc = state.result(raise_on_failure=False)
    except Exception:  # noqa: BLE001 - no exception to look at: do not retry
        return False
    return isinstance(exc, (LakeError, OSError)) and not isinstance(exc, InputError)


# --------------------------------------------------------------------------------------
# tasks
# --------------------------------------------------------------------------------------
@task(name="validate", cache_policy=NO_CACHE, persist_result=False)
def validate_session(session: str, settings: dict | None = None,
                     storage_options: dict | None = None) -> pipeline.Prepared:
    """Validate the session folder, a local path or an fsspec URL with its ``storage_options``
    (:func:`fieldcal.pipeline.prepare`); nothing is written."""
    return pipeline.prepare(session, _settings(settings), storage_options)


@task(name="measure-batch", cache_policy=NO_CACHE, persist_result=False, retries=1,
      retry_delay_seconds=2, retry_condition_fn=_transient)
def measure_batch(prepared: pipeline.Prepared, names: list[str] | None, known: dict[str, str], lake: str,
                  storage_options: dict | None = None, present: list | None = None,
                  progress_run: str | None = None, queue: str | None = None) -> dict:
    """Hash and measure images, their observations into the lake
    (:func:`fieldcal.batch.measure_many_into_lake`; the images were looked up by the plan).

    Parameters
    ----------
    prepared : fieldcal.pipeline.Prepared
    names : list of str, or None
        Image names (session-relative paths): a fixed batch. None: pull them from ``queue``.
    known : dict
        ``{name: sha256}`` of images whose hash is known already (not read for hashing).
    lake, storage_options
        Where the observations go (the lake's observation tables): one append at the end,
        and one after every :data:`fieldcal.batch.APPEND_EVERY_S` of measuring.
    present : list, optional
        ``(image, key)`` of these images cached in the lake when the run was planned
        (:attr:`fieldcal.batch.SessionPlan.present`).
    progress_run : str, optional
        The flow's token for image-by-image progress (:mod:`flows.image_events`): each
        image is reported as soon as it is done. None: no reports.
    queue : str, optional
        Name of the run's Dask queue (with ``names`` None): pieces of the image list
        (:func:`fieldcal.batch.pull_chunks`), taken one at a time until the end marker,
        None (:func:`fan_out`).

    Returns
    -------
    dict
        ``rows``: per image the row of :func:`fieldcal.batch.measure_into_lake` plus
        ``stamp`` (the file's stamp before hashing, for the hash store; None when the hash
        was known); ``task_s`` the time of the whole task [s]; ``worker`` the Dask
        worker's address (None outside Dask); ``pid``; ``rss_peak_mb`` the peak resident
        memory of the process the task ran in so far [MiB].
    """
    worker, nthreads = _worker_info()
    warm_process(prepared.method, nthreads)
    t_task, start_unix = time.perf_counter(), time.time()
    stamps = {}

    def stamped(images):
        local = prepared.session.store is None
        for name in images:
            if name not in known and local:
                stamps[name] = file_stamp(prepared.session.image_path(name))
            yield name

    source = names if queue is None else _pulled(queue)
    try:
        # the plan's view of the lake, unless this is a retry that may find its first try's rows
        rows = batch.measure_many_into_lake(
            prepared, stamped(source), Lake(lake, storage_options), known,
            present=None if task_run.run_count > 1 else {tuple(p) for p in present or ()},
            on_image=lambda row: image_events.report_image(progress_run, row["image"], row["status"]),
            append_every_s=batch.APPEND_EVERY_S)
    finally:
        if queue is not None:
            source.close()                   # gives the queue back (_pulled's finally)
    for row in rows:
        row["stamp"] = stamps.get(row["image"])
    return {"rows": rows, "task_s": time.perf_counter() - t_task, "worker": worker, "pid": os.getpid(),
            "rss_peak_mb": _peak_rss_mb(), "start_unix": start_unix, "end_unix": time.time()}


def _pulled(queue: str, timeout_s: float = PULL_TIMEOUT_S):
    """Image names from the Dask queue ``queue``, a piece at a time, until the end marker
    (None) or ``timeout_s`` without one (the flow gives the images no task returned to
    another task)."""
    from distributed import Queue

    q = Queue(queue)
    try:
        while True:
            try:
                piece = q.get(timeout=timeout_s)
            except TimeoutError:
                return
            if piece is None:
                return
            yield from piece
    finally:
        q.close()


@task(name="solve", cache_policy=NO_CACHE, persist_result=False)
def solve_session(prepared: pipeline.Prepared, lake: str, storage_options: dict | None,
                  keys: dict[str, str], left_out: list[dict], fingerprint: str, show_progress: bool = True
                  ) -> tuple[pipeline.Outcome, dict[str, float]]:
    """Read the observations back from the lake and calibrate (:func:`fieldcal.pipeline.solve`).

    ``keys`` maps every measured image to its observations' cache key; ``left_out`` lists
    the images that could not be measured (``{image, status, reason}``). Returns the
    outcome and the times [s] of reading the observations (``read_s``) and of the
    solver itself (``solver_s``). The outcome leaves the solver's own result object
    behind (``result`` None): its matrices are ~70 MB for a 24-image session, and the
    flow needs only the document, the arrays and the residuals, which on a Dask cluster
    travel back from the worker.
    """
    t = time.perf_counter()
    measurements = batch.read_observations(prepared, Lake(lake, storage_options), keys)
    read_s = time.perf_counter() - t
    t = time.perf_counter()
    note = (lambda text: progress.emit("note", text=text)) if show_progress else None
    outcome = pipeline.solve(prepared, measurements, fingerprint_=fingerprint, progress=note, left_out=left_out)
    outcome.result = None
    return outcome, {"read_s": read_s, "solver_s": time.perf_counter() - t}


@task(name="commit", cache_policy=NO_CACHE, persist_result=False)
def commit_version(lake: str, storage_options: dict | None, outcome: pipeline.Outcome,
                   force: bool = False) -> tuple[str, bool]:
    """Commit the outcome as one immutable version; returns ``(version, new)``."""
    from prefect.runtime import flow_run

    store = Lake(lake, storage_options)
    v = store.commit(outcome.document, outcome.arrays, outcome.residuals,
                     force=force, array_attrs=outcome.array_attrs,
                     info={"flow_run_id": flow_run.id, "flow": flow_run.flow_name})
    for p in dict.fromkeys(str(p) for p in store.problems):      # damage met and stepped over (issue 24)
        get_run_logger().warning(f"lake: {p} (see `fieldcal lake check` and `fieldcal lake repair`)")
    return str(v), bool(v.new)


# --------------------------------------------------------------------------------------
# the fan-out
# --------------------------------------------------------------------------------------
def _dask_runner() -> DaskTaskRunner | None:
    runner = FlowRunContext.get().task_runner
    return runner if isinstance(runner, DaskTaskRunner) else None


def _cluster_threads(runner: DaskTaskRunner) -> tuple[int, float]:
    """(worker threads, seconds it took to reach or start the cluster) of a Dask task runner."""
    t = time.perf_counter()
    client = runner.client                 # connects, or starts the local cluster, on first use
    return cluster.worker_count(client), time.perf_counter() - t


def submit_placed(runner: DaskTaskRunner, task_, params: dict, worker: str | None = None, priority: int = 0):
    """Submit a Prefect task to an entered Dask task runner, placed on ``worker`` (an address)
    when given, with Dask ``priority`` (a worker runs its higher ones first). Another worker
    may still take it (one that left, work stealing): ``allow_other_workers``."""
    if worker is None:
        return runner.submit(task_, params)
    # dask.annotate holds its annotations in a context variable: this thread's submission
    # only (the fleet's sessions submit from threads of one process)
    with dask.annotate(workers=[worker], allow_other_workers=True, priority=priority):
        return runner.submit(task_, params)


class _Collector:
    """Results of the measuring tasks as they come back: rows, per-task figures, progress.

    Progress counts each image when its worker reports it (:mod:`flows.image_events`), or
    at the latest when its task's result comes back."""

    def __init__(self, total: int, logger, client=None):
        self.rows: list[dict] = []
        self.tasks: list[dict] = []
        self.logger = logger
        self.submitted: dict = {}
        progress.emit("images", total=total, done=0, cached=0, bad=0)
        self.images = image_events.ImageCounts(
            total, lambda **counts: progress.emit("images", total=total, **counts),
            None if progress.is_quiet() else client)

    def submit(self, runner, params: dict, worker=None, priority=0):
        """Submit one measuring task (:func:`submit_placed`; without a priority a worker
        runs its tasks in the order of their random keys)."""
        t0 = time.perf_counter()
        fut = submit_placed(runner, measure_batch, dict(params, progress_run=self.images.run), worker, priority)
        self.submitted[fut] = (t0, time.perf_counter() - t0)
        return fut

    def collect(self, fut) -> dict:
        t0, submit_s = self.submitted[fut]
        res = fut.result()
        self.rows.extend(res["rows"])
        self.tasks.append({"n": len(res["rows"]), "wall_s": time.perf_counter() - t0, "task_s": res["task_s"],
                           "submit_s": submit_s, "worker": res["worker"], "pid": res["pid"],
                           "rss_peak_mb": res["rss_peak_mb"], "start_unix": res["start_unix"],
                           "end_unix": res["end_unix"]})
        self.images.add([(r["image"], r["status"]) for r in res["rows"]])
        for r in res["rows"]:
            if r["status"] == "bad":
                self.logger.warning(f"{r['image']}: {r['reason']} (left out)")
        return res

    def collect_all(self, futures) -> None:
        for fut in as_completed(futures):
            self.collect(fut)


def _batch_params(prepared, names, known, lake, storage_options, present) -> dict:
    """:func:`measure_batch`'s parameters for a fixed batch ``names``."""
    mine = set(names)
    return {"prepared": prepared, "names": names, "known": {n: known[n] for n in names if n in known},
            "lake": lake, "storage_options": storage_options, "present": [p for p in present if p[0] in mine]}


def _fixed_batches(c: _Collector, runner, slots, names, batch_size, params) -> None:
    """``batch_size`` images per task, placed by images (:func:`fieldcal.batch.assign_batches`);
    ``params(names)`` gives a task's parameters."""
    b = max(1, int(batch_size))
    sizes = [min(b, len(names) - i) for i in range(0, len(names), b)]
    futures = [c.submit(runner, params(names[k * b:(k + 1) * b]), slots[slot], priority=len(sizes) - k)
               for k, slot in enumerate(batch.assign_batches(sizes, len(slots)))]
    c.collect_all(futures)


def _pulled_from_queue(c: _Collector, runner, slots, names, params, image_s: float) -> int:
    """One task per worker thread, each pulling pieces of ``names`` from a Dask queue of this
    run until its end marker (:func:`fieldcal.batch.pull_chunks`); returns images per piece."""
    from distributed import Queue

    pieces = batch.pull_chunks(names, image_s, n_tasks=len(slots))
    slots = slots[:len(pieces)]                       # no more tasks than pieces
    queue = Queue(f"fieldcal-images-{uuid.uuid4().hex}", client=runner.client)
    try:
        everything = dict(params(names), names=None, queue=queue.name)
        futures = [c.submit(runner, everything, slot, priority=1) for slot in slots]
        for piece in pieces:                          # while the tasks start (a round trip each)
            queue.put(piece)
        for _ in slots:
            queue.put(None)                           # one end marker per task
        c.collect_all(futures)
    finally:
        queue.close()
    return len(pieces[0]) if pieces else 0


def fan_out(runner: DaskTaskRunner, prepared: pipeline.Prepared, names: list[str], known: dict[str, str],
            lake: str, storage_options: dict | None, batch_size: int | None,
            present: list | None = None) -> dict:
    """Run :func:`measure_batch` tasks on ``runner`` (entered) for the images ``names``.

    By default one task per worker thread, placed on it, all pulling the images from a Dask
    queue of this run, one full-size frame (or ~0.25 s of small ones) at a time
    (:func:`fieldcal.batch.pull_chunks`): the threads stay busy until the last image, with
    one Prefect task run each. With ``batch_size``: fixed batches of that many images,
    placed so that each thread gets an equal share (:func:`fieldcal.batch.assign_batches`).
    An image that no task returned (its worker lost while it held it) is measured by a
    task of its own afterwards. Call it inside a flow.

    Returns ``rows`` (per image, in ``names`` order), ``tasks`` (per task: ``n``,
    ``wall_s``, ``task_s``, ``submit_s``, ``worker``, ``pid``, ``rss_peak_mb``,
    ``start_unix``, ``end_unix``), ``batches`` (images per task, largest first), ``pulled``
    (whether the tasks pulled from a queue), ``estimate`` (``image_s`` the expected work per
    image and ``per_pull`` the images per piece; None with ``batch_size``) and
    ``start_unix`` / ``end_unix`` of the fan-out.
    """
    logger = get_run_logger()
    start_unix = time.time()
    c = _Collector(len(names), logger, runner.client)
    slots = cluster.worker_slots(runner.client) or [None]
    params = functools.partial(_batch_params, prepared, known=known, lake=lake, storage_options=storage_options,
                               present=present or [])
    estimate = None
    try:
        if batch_size:
            _fixed_batches(c, runner, slots, names, batch_size, params)
        elif names:
            image_s = batch.image_seconds([_file_bytes(prepared, n) for n in names])
            per_pull = _pulled_from_queue(c, runner, slots, names, params, image_s)
            estimate = {"image_s": image_s, "per_pull": per_pull}
            logger.info(f"{len(names)} image(s), ~{image_s:.2f} s each, pulled {per_pull} at a time by "
                        f"{min(len(slots), len(names))} task(s), one per worker thread")
        returned = {r["image"] for r in c.rows}
        lost = [n for n in names if n not in returned]
        if lost:
            logger.warning(f"{len(lost)} image(s) came back from no task (a worker lost?): measuring them again")
            c.collect_all([c.submit(runner, params(lost))])
    finally:
        c.images.close()
    order = {n: k for k, n in enumerate(names)}
    c.rows.sort(key=lambda r: order[r["image"]])
    return {"rows": c.rows, "tasks": c.tasks, "batches": sorted((t["n"] for t in c.tasks), reverse=True),
            "pulled": not batch_size, "estimate": estimate, "start_unix": start_unix, "end_unix": time.time()}


def _file_bytes(prepared: pipeline.Prepared, name: str) -> int:
    """Size of an image file [bytes] (a store's listing, or the local file's); 0 when it
    cannot be told (its task reports why)."""
    return prepared.session.image_size(name)


def _measure_on(runner: DaskTaskRunner, prepared, names, known, lake, storage_options, batch_size,
                present) -> dict:
    t_body = time.perf_counter()
    progress.emit("stage", text="connecting to the Dask cluster" if runner.address else "starting the Dask cluster")
    n_workers, cluster_s = _cluster_threads(runner)
    get_run_logger().info(f"{len(names)} image(s) to measure on {n_workers} worker thread(s) "
                          f"(cluster ready in {cluster_s:.1f} s)")
    out = fan_out(runner, prepared, names, known, lake, storage_options, batch_size, present)
    out.update(n_workers=n_workers, cluster_s=cluster_s, body_s=time.perf_counter() - t_body)
    return out


# --------------------------------------------------------------------------------------
# the flow's steps
# --------------------------------------------------------------------------------------
@dataclass
class _Run:
    """What one run of :func:`calibrate_session` has learnt so far."""

    session: str
    lake: str
    storage_options: dict | None
    settings: dict | None
    logger: object
    t_start: float = field(default_factory=time.perf_counter)
    timings: dict = field(default_factory=dict)
    prepared: pipeline.Prepared | None = None
    plan: batch.SessionPlan | None = None
    counts: dict = field(default_factory=dict)
    keys: dict = field(default_factory=dict)
    measured: dict | None = None
    on_cluster: bool = False

    def lap(self, name: str, t0: float) -> None:
        self.timings[name] = time.perf_counter() - t0

    def base(self) -> dict:
        sess = self.prepared.session
        return {"session": str(self.session), "camera_id": sess.camera_id, "session_id": sess.session_id,
                "method": sess.method, "lake": Lake(self.lake, self.storage_options).url}


def _plan(run: _Run, rehash: bool, force: bool) -> None:
    """Step 2: hashes known by file stamp, then :func:`fieldcal.batch.plan_session`."""
    t = time.perf_counter()
    prepared = run.prepared
    known = {} if rehash else known_hashes(prepared)
    run.plan = batch.plan_session(prepared, Lake(run.lake, run.storage_options), known, force=force)
    run.keys = dict(run.plan.cached)
    run.counts = {"total": len(prepared.to_measure), "measured": 0, "cached": len(run.plan.cached),
                  "bad": len(run.plan.missing), "hashed": 0}
    run.lap("lookup_s", t)


def _measure(run: _Run, dask_address, n_workers, cluster_kwargs, batch_size) -> None:
    """Step 3: measure the images left on Dask; remember the new hashes."""
    plan, todo = run.plan, run.plan.todo
    t = time.perf_counter()
    progress.emit("stage", text=f"measuring {len(todo)} image(s)"
                  + (f" ({run.counts['cached']} cached)" if run.counts["cached"] else ""))
    known = {n: plan.hashes[n] for n in todo if n in plan.hashes}
    mine = set(todo)
    present = sorted(p for p in plan.present if p[0] in mine)   # cached under another content, maybe this one
    runner = _dask_runner()
    in_process = (cluster.in_process(dask_address, cluster_kwargs) if runner is None
                  else cluster.runner_in_process(runner))
    if todo and in_process:
        # the workers will be threads of this process: warm it up now, before the cluster
        # starts (a warm-up thread beside the cluster's start and the submissions made the
        # 72-frame run 1.02-1.12x as long: the imports fight for the GIL; bench/README_flow.md)
        t_warm = time.perf_counter()
        warm_process(run.prepared.method, None)
        run.lap("warm_s", t_warm)
    args = (run.prepared, todo, known, run.lake, run.storage_options, batch_size, present)
    if runner is not None:
        run.on_cluster = True
        run.measured = _measure_on(runner, *args)
    else:
        with cluster.task_runner(dask_address, n_workers, cluster_kwargs) as own:
            run.measured = _measure_on(own, *args)
    run.lap("measure_s", t)
    stamps = []
    for r in run.measured["rows"]:
        if r["sha256"]:
            plan.hashes[r["image"]] = r["sha256"]
            if r["stamp"] is not None:
                stamps.append((os.fspath(run.prepared.session.image_path(r["image"])), r["sha256"], r["stamp"]))
                run.counts["hashed"] += 1
        if r["status"] == "bad":
            plan.missing[r["image"]] = r["reason"]
            plan.hashes.setdefault(r["image"], batch.UNREADABLE)
        else:
            run.keys[r["image"]] = r["key"]
            run.counts[r["status"]] += 1
    run.counts["bad"] = len(plan.missing)
    with HashCache() as store:
        store.remember(stamps)


def _unchanged(run: _Run, version: str, fp: str) -> dict:
    run.lap("total_s", run.t_start)
    run.logger.info(f"unchanged: version {version} has the same inputs and settings (use force for a new one)")
    progress.emit("note", text=f"unchanged: version {version} was made from the same inputs and settings")
    if not run.measured:
        run.counts["cached"] = run.counts["total"] - run.counts["bad"]
    return dict(run.base(), version=version, new=False, status="unchanged", fingerprint=fp, images=run.counts,
                left_out=[{"image": n, "status": "left out", "reason": r} for n, r in run.plan.missing.items()],
                summary=[], measure=run.measured, timings=run.timings)


def _solve_and_commit(run: _Run, fp: str, force: bool) -> dict:
    """Steps 4-5: solve (on the cluster when the flow runs on one), then commit."""
    sess = run.prepared.session
    left_out = [{"image": n, "status": "left out", "reason": r} for n, r in run.plan.missing.items()]
    t = time.perf_counter()
    progress.emit("stage", text=f"solving ({sess.method} method)")
    args = (run.prepared, run.lake, run.storage_options, run.keys, left_out, fp, not progress.is_quiet())
    runner = _dask_runner()
    if runner is not None and (runner.address or run.on_cluster):
        outcome, solve_times = solve_session.submit(*args).result()
    else:
        outcome, solve_times = solve_session(*args)
    run.lap("solve_s", t)
    run.timings["read_observations_s"] = solve_times["read_s"]
    run.timings["solver_s"] = solve_times["solver_s"]
    t = time.perf_counter()
    progress.emit("stage", text="committing")
    version, new = commit_version(run.lake, run.storage_options, outcome, force)
    run.lap("commit_s", t)
    for line in outcome.summary:
        run.logger.info(line)
    left = _left_out(outcome.left_out)
    for item in left:
        run.logger.warning(f"left out {item.get('image')}: {item.get('reason')}")
    run.logger.info(f"{'committed' if new else 'unchanged'}: version {version}")
    out = dict(run.base(), version=version, new=new, status="committed" if new else "unchanged", fingerprint=fp,
               images=run.counts, left_out=left, summary=list(outcome.summary), measure=run.measured,
               timings=run.timings, published=None, not_whole=dict(run.plan.not_whole))
    if new:
        t = time.perf_counter()
        try:
            out["published"] = publish.publish_version(run.lake, run.storage_options, out, outcome)
        except Exception as e:  # noqa: BLE001 - the version is committed: what is shown of it must not undo that
            run.logger.warning(f"version {version} is committed; publishing it failed: {type(e).__name__}: {e}")
        run.lap("publish_s", t)
    run.lap("total_s", run.t_start)
    return out


def _left_out(items: list[dict]) -> list[dict]:
    """Left-out images as plain dicts, one per image (the first reason given: the flow's own)."""
    out, seen = [], set()
    for item in items:
        name = item.get("image")
        if name in seen:
            continue
        seen.add(name)
        out.append({str(k): (v if isinstance(v, (str, int, float, bool, type(None))) else str(v))
                    for k, v in item.items()})
    return out


# --------------------------------------------------------------------------------------
# the flow
# --------------------------------------------------------------------------------------
@flow(name="calibrate-session", flow_run_name=publish.calibrate_run_name, persist_result=False)
def calibrate_session(session: str, lake: str, storage_options: dict | None = None, force: bool = False,
                      settings: dict | None = None, dask_address: str | None = None,
                      n_workers: int = cluster.DEFAULT_WORKERS, batch_size: int | None = None,
                      cluster_kwargs: dict | None = None, rehash: bool = False,
                      session_storage_options: dict | None = None) -> dict:
    """Calibrate one session folder into the lake (see the module docstring).

    Parameters
    ----------
    session : str
        The session folder (CONTRACT section 3): a local path, which the Dask workers must
        see under the same path, or an fsspec URL (``s3://bucket/sessions/cam/2026-05-01``),
        whose images each worker reads from the store itself (docs/deployment.md).
    lake : str
        The lake: a local path or an fsspec URL (``s3://bucket/prefix``).
    storage_options : dict, optional
        fsspec options of the lake (e.g. ``{"endpoint_url": ...}``). They are flow
        parameters, stored by the Prefect server: give each credential as
        :data:`fieldcal.lake.secrets.REDACTED` (the command line does); its value comes
        from ``FIELDCAL_STORAGE_OPTIONS`` or the storage's own configuration (``AWS_*``)
        wherever the lake is opened (:mod:`fieldcal.lake.secrets`).
    force : bool
        Make a new version even when these inputs and settings are committed already.
    settings : dict, optional
        :class:`fieldcal.pipeline.Settings` fields (``targets_adjusted``, ``solver``,
        ``rigorous_goniometer``); part of the inputs' fingerprint.
    dask_address : str, optional
        When the flow's own task runner is not a Dask one: the scheduler of an existing
        cluster for the measuring tasks (else ``$FIELDCAL_DASK_ADDRESS``, else a
        temporary local cluster of ``n_workers`` single-threaded workers).
    n_workers : int
        Workers of that temporary local cluster.
    batch_size : int, optional
        Images per measuring task; default: chosen by measurement (module docstring).
    cluster_kwargs : dict, optional
        Extra :class:`distributed.LocalCluster` arguments.
    rehash : bool
        Hash every image from its bytes (ignore the remembered hashes; the new ones are
        remembered).
    session_storage_options : dict, optional
        fsspec options of the session's store when ``session`` is a URL (default:
        ``storage_options``); as those, without credentials.

    Returns
    -------
    dict
        ``version`` (str), ``new`` (False when the inputs were committed already),
        ``status`` (``"committed"`` or ``"unchanged"``), ``session``, ``camera_id``,
        ``session_id``, ``method``, ``lake``, ``fingerprint``, ``images`` (counts:
        ``total``, ``measured``, ``cached``, ``bad``, ``hashed``), ``left_out`` (``{image,
        status, reason}``), ``summary`` (the solver's lines), ``measure`` (the fan-out's
        figures, or None), ``timings`` (seconds per step: ``validate_s``, ``lookup_s``,
        ``measure_s`` (cluster start included; of it ``warm_s``, the warm-up of this
        process when its threads measure), ``solve_s`` (of it ``read_observations_s``
        and ``solver_s``), ``commit_s``, ``publish_s``, ``total_s``), ``published`` (a new
        version's verdict, whether the camera moved, the links of its report and certificate:
        :func:`flows.publish.publish_version`; None otherwise).
    """
    run = _Run(session, lake, storage_options, settings, get_run_logger())
    t = time.perf_counter()
    progress.emit("stage", text=f"validating {session}")
    options = storage_options if session_storage_options is None else session_storage_options
    run.prepared = validate_session(session, settings, options)
    run.lap("validate_s", t)
    sess = run.prepared.session
    try:
        publish.label_run(sess)
    except Exception as e:  # noqa: BLE001 - a name and tags are not worth failing a calibration
        run.logger.warning(f"could not tag the flow run: {e}")
    run.logger.info(f"{sess.camera_id} / {sess.session_id}: {sess.method} method, "
                    f"{len(run.prepared.to_measure)} image(s) to measure, lake {run.base()['lake']}")
    _plan(run, rehash, force)
    if run.plan.unchanged is not None:
        return _unchanged(run, run.plan.unchanged, run.plan.fingerprint)
    if run.plan.todo:
        _measure(run, dask_address, n_workers, cluster_kwargs, batch_size)
    probe = Lake(lake, storage_options)
    fp, existing = batch.unchanged_version(run.prepared, probe, run.plan.hashes)
    if existing is not None and not force:
        return _unchanged(run, existing, fp)
    run.plan.not_whole.update(probe.not_whole)
    for version, why in run.plan.not_whole.items():
        run.logger.warning(f"version {version} of these inputs does not read back whole ({why}): "
                           "calibrating again")
        progress.emit("note", text=f"version {version} of these inputs does not read back whole: calibrating again")
    return _solve_and_commit(run, fp, force)
