"""The calibration flow of one session: validate -> measure the images on Dask -> solve -> commit.

:func:`calibrate_session` (Prefect flow ``calibrate-session``) wraps the plain steps of
:mod:`fieldcal.pipeline`; every piece of real work is there, the flow only decides what
runs where and what can be skipped:

1. **validate** (task, in the flow's process): :func:`fieldcal.pipeline.prepare`. Bad input
   raises :class:`~fieldcal.errors.InputError` naming the file and nothing is written
   anywhere (the lake, the hash store).
2. **what is known already**: each image's SHA-256 from the hash store
   (:mod:`flows.hashcache`, no image is read for it) and the lake's cached observations
   (one listing). When every image's hash is known and a version with the same
   fingerprint (inputs and settings) is committed, the run ends there: it is a no-op
   that returns that version (``force=True`` makes a new one).
3. **measure** (sub-flow ``measure-images`` on a :class:`prefect_dask.DaskTaskRunner`: a
   temporary local cluster, or the scheduler at ``dask_address``): one task
   (:func:`measure_batch`) per image or per small batch of images. Each task hashes its
   images (unless known), skips those whose observations are cached under that hash,
   measures the others (:func:`fieldcal.pipeline.measure`) and writes one Parquet file
   per image into the lake. A bad image (:class:`~fieldcal.errors.ImageError`, a missing
   file) is reported and left out; the run goes on. The Dask cluster is only started
   when some image has to be read.
4. **solve** (one task): reads the observations back from the lake and runs
   :func:`fieldcal.pipeline.solve`, which dispatches on the session's method (field or
   goniometer; a field session with ``observations.csv`` has no images to measure).
5. **commit** (one task): :meth:`fieldcal.lake.store.Lake.commit`: everything of the version
   first, its catalog row last. A run killed before this point leaves no visible version;
   the rerun finds the observations cached and completes the work.

Batch sizes "chosen by measurement": the first wave is one single-image task per worker
(probes). From the first probe back, the flow knows the work per image ``t_img`` (timed
inside the task) and the per-task overhead ``t_ovh`` (time from submitting the task to
having its result, minus its work: Prefect's context serialisation and state reports,
Dask scheduling, the result's trip back). The remaining images are split by guided
self-scheduling (:func:`plan_batches`): each batch takes a quarter (with two workers) of
the images left, so batches start large (overhead negligible) and shrink towards the end
(the workers finish together), but never below ``ceil(t_ovh / t_img)`` images (no task
shorter than its own overhead). Full-size images (``t_img`` ~1 s, ``t_ovh`` ~0.3 s) go in
batches of 18, 13, 10, ... down to 1; the 5 ms frames of a goniometer session in a few
batches of 50 or more.

Cached observations are keyed by the image's content hash combined with the session's
measuring settings (method, sensor, target polarity, coded-target dictionary): an image
is measured again when its bytes change or when the session changes how it is measured,
never otherwise. The key and the image's own SHA-256 are in each Parquet file's metadata.

Progress goes to :mod:`fieldcal.progress` (the CLI shows it on a terminal) and to the
Prefect logger (the flow run's logs in the Prefect UI).
"""

from __future__ import annotations

import math
import os
import resource
import statistics
import time
from pathlib import Path

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.context import FlowRunContext
from prefect.futures import as_completed

from fieldcal import pipeline, progress
from fieldcal.errors import ImageError, InputError, LakeError, one_line
from fieldcal.lake.store import Lake, observations_key
from fieldcal.measure.imageio import read_file
from fieldcal.session.fingerprint import canonical_json, sha256_bytes

from . import cluster
from .hashcache import HashCache, file_stamp

__all__ = ["calibrate_session", "measure_images", "measure_batch", "validate_session", "solve_session",
           "commit_version", "plan_batches", "measure_settings", "measurement_key"]

TASKS_PER_WORKER = 2
"""Guided batch sizing: each batch takes 1 / (TASKS_PER_WORKER x workers) of the images left."""
MAX_TASK_S = 60.0
"""Largest measured work per task [s] (beyond the overhead floor): progress, retries."""
_META_KEYS = (b"fieldcal.image", b"fieldcal.content_sha256", b"fieldcal.image_sha256",
              b"fieldcal.measure")


# --------------------------------------------------------------------------------------
# plain helpers (no Prefect): keys and batch sizes
# --------------------------------------------------------------------------------------
def measure_settings(prepared: pipeline.Prepared) -> dict:
    """What in a session decides how its images are measured (part of the observations' key)."""
    sess = prepared.session
    out = {"method": sess.method, "sensor": sess.sensor.to_dict()}
    if sess.method == "field":
        out["target_polarity"] = sess.target_polarity
        out["coded"] = sess.coded
    return out


def measurement_key(image_sha256: str, settings: dict) -> str:
    """The observations' cache key: SHA-256 of the image's hash and the measuring settings."""
    return sha256_bytes(canonical_json({"image_sha256": image_sha256, "measure": settings}))


def plan_batches(n: int, n_workers: int, image_s: float, overhead_s: float, *,
                 tasks_per_worker: int = TASKS_PER_WORKER, max_task_s: float = MAX_TASK_S) -> list[int]:
    """Batch sizes (images per task) for ``n`` images, from the measured costs.

    Guided self-scheduling: each batch takes ``ceil(left / (tasks_per_worker * n_workers))``
    of the images still left, so batches are large first and shrink towards the end and
    the workers finish together; but no batch is smaller than ``ceil(overhead_s /
    image_s)`` (a task at least as long as its own overhead) or, beyond that, larger than
    ``max_task_s`` of work (progress and retries stay fine-grained).

    Parameters
    ----------
    n : int
        Images to distribute.
    n_workers : int
        Worker threads of the cluster.
    image_s : float
        Measured work per image [s] (hashing, reading, extraction, writing).
    overhead_s : float
        Measured overhead per task [s] (from submission to result, minus the work).

    Returns
    -------
    list of int
        Sizes summing to ``n``, in submission order (non-increasing).
    """
    if n <= 0:
        return []
    w = max(1, int(n_workers))
    if image_s > 0:
        floor_ = max(1, math.ceil(max(overhead_s, 0.0) / image_s))
        cap = max(floor_, int(max_task_s // image_s))
    else:                       # no work to speak of (cached images): one task
        floor_ = cap = n
    sizes, left = [], n
    while left > 0:
        b = min(left, cap, max(floor_, math.ceil(left / (tasks_per_worker * w))))
        sizes.append(b)
        left -= b
    return sizes


def _settings(settings: dict | None) -> pipeline.Settings:
    try:
        return pipeline.Settings(**(settings or {}))
    except TypeError:
        known = sorted(pipeline.Settings().to_dict())
        raise InputError(f"unknown setting(s) {sorted(set(settings or {}) - set(known))}; known: "
                         f"{known}", "settings") from None



def _strip_meta(table):
    meta = {k: v for k, v in (table.schema.metadata or {}).items() if k not in _META_KEYS}
    return table.replace_schema_metadata(meta or None)


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


def _warm(method: str, nthreads: int | None) -> None:
    """Import the measuring code (and load the compiled disc kernel) before the work is timed;
    one OpenCV thread and one codec thread per Dask thread."""
    if method == "goniometer":
        import fieldcal.goniometer.method  # noqa: F401
    else:
        from fieldcal.measure import disc_kernel

        disc_kernel.warm_up()
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
def validate_session(session: str, settings: dict | None = None) -> pipeline.Prepared:
    """Validate the session folder (:func:`fieldcal.pipeline.prepare`); nothing is written."""
    return pipeline.prepare(session, _settings(settings))


@task(name="measure-batch", cache_policy=NO_CACHE, persist_result=False, retries=1,
      retry_delay_seconds=2, retry_condition_fn=_transient)
def measure_batch(prepared: pipeline.Prepared, names: list[str], known: dict[str, str], lake: str,
                  storage_options: dict | None = None) -> dict:
    """Hash, look up and (when not cached) measure a batch of images; observations to the lake.

    Parameters
    ----------
    prepared : fieldcal.pipeline.Prepared
    names : list of str
        Image names (session-relative paths).
    known : dict
        ``{name: sha256}`` of images whose hash is known already (not read for hashing).
    lake, storage_options
        Where the observations go (one Parquet file per image).

    Returns
    -------
    dict
        ``rows``: per image ``image, sha256, key, status ("measured" | "cached" | "bad"),
        reason, n_rows, stamp, hash_s, measure_s, write_s`` (times [s]; ``hash_s`` reads and
        hashes the file once, ``measure_s`` decodes those bytes and measures); ``task_s`` the
        time of the whole batch [s]; ``worker`` the Dask worker's address (None outside
        Dask); ``rss_peak_mb`` the peak resident memory of the process the task ran in
        so far [MiB] (a worker process, or the flow's own process for in-process workers).
    """
    worker, nthreads = _worker_info()
    _warm(prepared.method, nthreads)
    t_task = time.perf_counter()
    lk = Lake(lake, storage_options)
    sess = prepared.session
    msettings = measure_settings(prepared)
    rows = []
    for name in names:
        row = {"image": name, "sha256": None, "key": None, "status": None, "reason": None, "n_rows": 0,
               "stamp": None, "hash_s": 0.0, "measure_s": 0.0, "write_s": 0.0}
        rows.append(row)
        source = sess.image_path(name)
        t = time.perf_counter()
        sha = known.get(name)
        if sha is None:
            try:     # one read: the bytes hashed here are the ones decoded below
                source = read_file(source)
            except (InputError, OSError) as e:
                row.update(status="bad", reason=getattr(e, "reason", None) or one_line(e))
                continue
            sha, row["stamp"] = source.sha256, source.stamp
            row["hash_s"] = time.perf_counter() - t
        key = measurement_key(sha, msettings)
        row.update(sha256=sha, key=key)
        if lk.has_observations(sess.camera_id, sess.session_id, name, key):
            row["status"] = "cached"
            continue
        t = time.perf_counter()
        try:
            table = pipeline.measure(prepared, name, source)
        except ImageError as e:
            row.update(status="bad", reason=e.reason, measure_s=time.perf_counter() - t)
            continue
        row["measure_s"] = time.perf_counter() - t
        t = time.perf_counter()
        meta = dict(table.schema.metadata or {})
        meta.update({b"fieldcal.image_sha256": sha.encode(),
                     b"fieldcal.measure": canonical_json(msettings)})
        lk.write_observations(sess.camera_id, sess.session_id, name, key,
                              table.replace_schema_metadata(meta))
        row.update(status="measured", n_rows=int(table.num_rows), write_s=time.perf_counter() - t)
    return {"rows": rows, "task_s": time.perf_counter() - t_task, "worker": worker, "pid": os.getpid(),
            "rss_peak_mb": _peak_rss_mb()}


@task(name="solve", cache_policy=NO_CACHE, persist_result=False)
def solve_session(prepared: pipeline.Prepared, lake: str, storage_options: dict | None,
                  keys: dict[str, str], left_out: list[dict], fingerprint: str
                  ) -> tuple[pipeline.Outcome, dict[str, float]]:
    """Read the observations back from the lake and calibrate (:func:`fieldcal.pipeline.solve`).

    ``keys`` maps every measured image to its observations' cache key; ``left_out`` lists
    the images that could not be measured (``{image, status, reason}``). Returns the
    outcome and the times [s] of reading the observations (``read_s``) and of the
    solver itself (``solver_s``).
    """
    t = time.perf_counter()
    lk = Lake(lake, storage_options)
    sess = prepared.session
    measurements = {}
    for name, key in keys.items():
        table = lk.read_observations(sess.camera_id, sess.session_id, name, key)
        if table is None:
            raise LakeError(f"the observations of {name} are missing from {lk.url} (removed during the run?)")
        measurements[name] = _strip_meta(table)
    read_s = time.perf_counter() - t
    t = time.perf_counter()
    outcome = pipeline.solve(prepared, measurements, fingerprint_=fingerprint,
                             progress=lambda text: progress.emit("note", text=text), left_out=left_out)
    return outcome, {"read_s": read_s, "solver_s": time.perf_counter() - t}


@task(name="commit", cache_policy=NO_CACHE, persist_result=False)
def commit_version(lake: str, storage_options: dict | None, outcome: pipeline.Outcome,
                   force: bool = False) -> tuple[str, bool]:
    """Commit the outcome as one immutable version; returns ``(version, new)``."""
    from prefect.runtime import flow_run

    v = Lake(lake, storage_options).commit(outcome.document, outcome.arrays, outcome.residuals,
                                           force=force, array_attrs=outcome.array_attrs,
                                           info={"flow_run_id": flow_run.id, "flow": flow_run.flow_name})
    return str(v), bool(v.new)


# --------------------------------------------------------------------------------------
# the fan-out
# --------------------------------------------------------------------------------------
def _runner_threads(runner) -> tuple[int, float]:
    """(worker threads, seconds it took to reach / start the cluster) of the flow's task runner."""
    t = time.perf_counter()
    client = getattr(runner, "client", None)  # a DaskTaskRunner starts its cluster here
    if client is not None:
        return cluster.worker_count(client), time.perf_counter() - t
    return int(getattr(runner, "_max_workers", None) or os.cpu_count() or 1), 0.0


@flow(name="measure-images", persist_result=False, validate_parameters=False)
def measure_images(session: str, settings: dict | None, names: list[str], known: dict[str, str],
                   lake: str, storage_options: dict | None = None, batch_size: int | None = None) -> dict:
    """Fan the images out as :func:`measure_batch` tasks (batch size chosen by measurement).

    Returns
    -------
    dict
        ``rows`` (per image, see :func:`measure_batch`), ``tasks`` (per task: ``n``,
        ``wall_s``, ``task_s``, ``submit_s``, ``worker``, ``rss_peak_mb``), ``batches``
        (the sizes planned after the probes), ``batch_size`` (the largest), ``n_workers``,
        ``cluster_s`` (time to start or reach the cluster [s]), ``estimate`` (``image_s``,
        ``overhead_s`` from the probe) and ``body_s`` (this flow's own time [s]; the rest
        of its run is Prefect's start and end of a flow run and the shutdown of a cluster
        it started).
    """
    t_body = time.perf_counter()
    logger = get_run_logger()
    prepared = pipeline.prepare(session, _settings(settings))
    progress.emit("stage", text="starting the Dask cluster" if getattr(FlowRunContext.get().task_runner,
                                                                        "address", None) is None
                  else "connecting to the Dask cluster")
    n_workers, cluster_s = _runner_threads(FlowRunContext.get().task_runner)
    logger.info(f"{len(names)} image(s) to measure on {n_workers} worker thread(s) "
                f"(cluster ready in {cluster_s:.1f} s)")
    queue = list(names)
    submitted: dict = {}
    total = len(queue)
    counts = {"done": 0, "cached": 0, "bad": 0}

    def submit(batch):
        t0 = time.perf_counter()
        fut = measure_batch.submit(prepared, batch, {n: known[n] for n in batch if n in known}, lake,
                                   storage_options)
        submitted[fut] = (batch, t0, time.perf_counter() - t0)
        return fut

    def collect(fut, tasks, rows):
        batch, t0, submit_s = submitted[fut]
        res = fut.result()
        wall = time.perf_counter() - t0
        rows.extend(res["rows"])
        tasks.append({"n": len(batch), "wall_s": wall, "task_s": res["task_s"], "submit_s": submit_s,
                      "worker": res["worker"], "pid": res["pid"], "rss_peak_mb": res["rss_peak_mb"]})
        counts["done"] += len(batch)
        counts["cached"] += sum(r["status"] == "cached" for r in res["rows"])
        counts["bad"] += sum(r["status"] == "bad" for r in res["rows"])
        for r in res["rows"]:
            if r["status"] == "bad":
                logger.warning(f"{r['image']}: {r['reason']} (left out)")
        progress.emit("images", total=total, **counts)
        return res

    rows: list[dict] = []
    tasks: list[dict] = []
    estimate = None
    progress.emit("images", total=total, **counts)
    if batch_size:
        b = max(1, int(batch_size))
        sizes = [min(b, len(queue) - i) for i in range(0, len(queue), b)]
        first = []
    else:
        first = [submit([n]) for n in queue[:n_workers]]
        queue = queue[n_workers:]
        sizes = []
        if queue:
            probe = next(iter(as_completed(first)))
            res = collect(probe, tasks, rows)
            first.remove(probe)
            work = [r["hash_s"] + r["measure_s"] + r["write_s"] for r in res["rows"]]
            image_s = statistics.median(work) if work else 0.0
            overhead_s = max(0.0, tasks[-1]["wall_s"] - res["task_s"])
            sizes = plan_batches(len(queue), n_workers, image_s, overhead_s)
            estimate = {"image_s": image_s, "overhead_s": overhead_s}
            logger.info(f"probe: {image_s:.3f} s per image, {overhead_s:.3f} s overhead per task "
                        f"-> {len(sizes)} batches of {sizes[0]} down to {sizes[-1]} images")
    rest, i = [], 0
    for size in sizes:
        rest.append(submit(queue[i:i + size]))
        i += size
    for fut in as_completed(first + rest):
        collect(fut, tasks, rows)
    order = {n: i for i, n in enumerate(names)}
    rows.sort(key=lambda r: order[r["image"]])
    return {"rows": rows, "tasks": tasks, "batches": sizes, "batch_size": max(sizes, default=1),
            "n_workers": n_workers, "cluster_s": cluster_s, "estimate": estimate,
            "body_s": time.perf_counter() - t_body}


# --------------------------------------------------------------------------------------
# the flow
# --------------------------------------------------------------------------------------
def _run_name() -> str:
    from prefect.runtime import flow_run

    return f"calibrate-{Path(str(flow_run.parameters.get('session', 'session'))).name}"


def _observation_listing(lk: Lake, camera_id: str, session_id: str) -> set[str]:
    return lk.cached_observations(camera_id, session_id)


@flow(name="calibrate-session", flow_run_name=_run_name, persist_result=False)
def calibrate_session(session: str, lake: str, storage_options: dict | None = None, force: bool = False,
                      settings: dict | None = None, dask_address: str | None = None,
                      n_workers: int = cluster.DEFAULT_WORKERS, batch_size: int | None = None,
                      cluster_kwargs: dict | None = None, rehash: bool = False) -> dict:
    """Calibrate one session folder into the lake (see the module docstring).

    Parameters
    ----------
    session : str
        The session folder (docs/conventions.md section 3), on a filesystem the Dask workers see
        under the same path.
    lake : str
        The lake: a local path or an fsspec URL (``s3://bucket/prefix``).
    storage_options : dict, optional
        fsspec options of the lake (e.g. ``{"endpoint_url": ...}``). They are flow
        parameters, stored by the Prefect server: give credentials through the
        environment (``AWS_ACCESS_KEY_ID`` ...) rather than here.
    force : bool
        Make a new version even when these inputs and settings are committed already.
    settings : dict, optional
        :class:`fieldcal.pipeline.Settings` fields (``targets_adjusted``, ``solver``,
        ``rigorous_goniometer``); part of the inputs' fingerprint.
    dask_address : str, optional
        Scheduler of an existing Dask cluster (else ``$FIELDCAL_DASK_ADDRESS``, else a
        temporary local cluster of ``n_workers`` single-threaded worker processes).
    n_workers : int
        Workers of the temporary local cluster.
    batch_size : int, optional
        Images per measuring task; default: chosen by measurement (module docstring).
    cluster_kwargs : dict, optional
        Extra :class:`distributed.LocalCluster` arguments.
    rehash : bool
        Hash every image from its bytes (ignore the remembered hashes; the new ones are
        remembered).

    Returns
    -------
    dict
        ``version`` (str), ``new`` (False when the inputs were committed already),
        ``status`` (``"committed"`` or ``"unchanged"``), ``camera_id``, ``session_id``,
        ``method``, ``lake``, ``fingerprint``, ``images`` (counts: ``total``, ``measured``,
        ``cached``, ``bad``, ``hashed``), ``left_out`` (``{image, status, reason}``),
        ``summary`` (the solver's lines), ``measure`` (the fan-out's figures, or None),
        ``timings`` (seconds per step: ``validate_s``, ``lookup_s``, ``measure_s`` (the
        sub-flow, cluster start included), ``solve_s`` (the task; of it
        ``read_observations_s`` and ``solver_s``), ``commit_s``, ``total_s``).
    """
    logger = get_run_logger()
    t_start = time.perf_counter()
    timings: dict[str, float] = {}

    def lap(name, t0):
        timings[name] = time.perf_counter() - t0

    t = time.perf_counter()
    progress.emit("stage", text=f"validating {session}")
    prepared = validate_session(session, settings)
    lap("validate_s", t)
    sess = prepared.session
    lk = Lake(lake, storage_options)
    logger.info(f"{sess.camera_id} / {sess.session_id}: {sess.method} method, "
                f"{len(prepared.to_measure)} image(s) to measure, lake {lk.url}")

    # what is known without reading an image
    t = time.perf_counter()
    paths = {n: os.fspath(sess.image_path(n)) for n in prepared.to_measure}
    remembered = {}
    if not rehash:
        with HashCache() as store:
            remembered = store.lookup(paths.values())
    hashes = {n: remembered[p] for n, p in paths.items() if p in remembered}
    bad: dict[str, str] = {}
    for n, p in paths.items():
        if n not in hashes and file_stamp(p) is None:
            bad[n] = "file not found" if not os.path.exists(p) else "not a regular file"
            hashes[n] = "missing"
    msettings = measure_settings(prepared)
    base = dict(session=str(session), camera_id=sess.camera_id, session_id=sess.session_id,
                method=sess.method, lake=lk.url)
    counts = {"total": len(paths), "measured": 0, "cached": 0, "bad": len(bad), "hashed": 0}

    def unchanged(version, fp):
        lap("total_s", t_start)
        logger.info(f"unchanged: version {version} has the same inputs and settings (use force for a new one)")
        progress.emit("note", text=f"unchanged: version {version} was made from the same inputs and settings")
        return dict(base, version=version, new=False, status="unchanged", fingerprint=fp,
                    images=counts, left_out=[{"image": n, "status": "left out", "reason": r}
                                             for n, r in bad.items()],
                    summary=[], measure=None, timings=timings)

    if not force and len(hashes) == len(paths):
        fp = pipeline.input_fingerprint(prepared, hashes)
        existing = lk.find_committed(fp)
        if existing is not None:
            counts["cached"] = len(paths) - len(bad)
            lap("lookup_s", t)
            return unchanged(existing, fp)
    listing = _observation_listing(lk, sess.camera_id, sess.session_id) if paths else set()
    keys: dict[str, str] = {}
    todo = []
    for n in prepared.to_measure:
        if n in bad:
            continue
        if n in hashes:
            key = measurement_key(hashes[n], msettings)
            if observations_key(n, key) in listing:
                keys[n] = key
                counts["cached"] += 1
                continue
        todo.append(n)
    lap("lookup_s", t)

    # measure on Dask
    measured = None
    if todo:
        t = time.perf_counter()
        progress.emit("stage", text=f"measuring {len(todo)} image(s)"
                      + (f" ({counts['cached']} cached)" if counts["cached"] else ""))
        runner = cluster.task_runner(dask_address, n_workers, cluster_kwargs)
        measured = measure_images.with_options(task_runner=runner)(
            str(session), settings, todo, {n: hashes[n] for n in todo if n in hashes}, lake,
            storage_options, batch_size)
        lap("measure_s", t)
        stamps = []
        for r in measured["rows"]:
            if r["sha256"]:
                hashes[r["image"]] = r["sha256"]
                if r["stamp"] is not None:
                    stamps.append((paths[r["image"]], r["sha256"], r["stamp"]))
                    counts["hashed"] += 1
            if r["status"] == "bad":
                bad[r["image"]] = r["reason"]
                hashes.setdefault(r["image"], "unreadable")
            else:
                keys[r["image"]] = r["key"]
                counts[r["status"]] += 1
        counts["bad"] = len(bad)
        with HashCache() as store:
            store.remember(stamps)

    fp = pipeline.input_fingerprint(prepared, hashes)
    if not force:
        existing = lk.find_committed(fp)
        if existing is not None:
            result = unchanged(existing, fp)
            result["measure"] = measured
            return result

    left_out = [{"image": n, "status": "left out", "reason": r} for n, r in bad.items()]
    t = time.perf_counter()
    progress.emit("stage", text=f"solving ({sess.method} method)")
    outcome, solve_times = solve_session(prepared, lake, storage_options, keys, left_out, fp)
    lap("solve_s", t)
    timings["read_observations_s"] = solve_times["read_s"]
    timings["solver_s"] = solve_times["solver_s"]
    t = time.perf_counter()
    progress.emit("stage", text="committing")
    version, new = commit_version(lake, storage_options, outcome, force)
    lap("commit_s", t)
    lap("total_s", t_start)
    for line in outcome.summary:
        logger.info(line)
    for item in _left_out(outcome.left_out):
        logger.warning(f"left out {item.get('image')}: {item.get('reason')}")
    logger.info(f"{'committed' if new else 'unchanged'}: version {version}")
    return dict(base, version=version, new=new, status="committed" if new else "unchanged", fingerprint=fp,
                images=counts, left_out=_left_out(outcome.left_out), summary=list(outcome.summary),
                measure=measured, timings=timings)


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

