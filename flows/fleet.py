"""Recalibrate a fleet: every session under a root that has no committed calibration yet.

:func:`recalibrate_fleet` (Prefect flow ``recalibrate-fleet``) is what a schedule runs
(``deploy/prefect.yaml``, or ``fieldcal serve``, which serves :func:`fleet_deployment`
from one process):

1. **scan** the root of sessions: every folder with a ``session.json``, directly under the
   root or one level deeper (``ROOT/<session>/`` or ``ROOT/<camera>/<session>/``). The
   root is a local path or an fsspec URL; by default ``<lake>/sessions`` (raw sessions
   kept in the lake's bucket). Each manifest is read for its ``camera_id`` and
   ``session_id`` (default: the folder's name).
2. **select** the sessions whose ``(camera_id, session_id)`` has no version in the lake's
   catalog.
3. **calibrate** each with :func:`flows.calibrate.calibrate_session` (a sub-flow run per
   session). Sessions on an object store are copied to a temporary local folder first
   (the measuring code reads local files). One Dask cluster serves all of them: the
   scheduler at ``dask_address``, or a local cluster started when the first session with
   images needs it. A failing session is recorded with its reason and the others go on.
4. **summary**: returned (a dict) and logged, one line per session.
"""

from __future__ import annotations

import contextlib
import json
import os
import posixpath
import tempfile
import time
from dataclasses import dataclass

from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from fieldcal.errors import one_line
from fieldcal.lake.store import Lake
from fieldcal.session.loader import default_session_id

from . import cluster
from .calibrate import calibrate_session

__all__ = ["recalibrate_fleet", "scan_sessions", "FoundSession", "fleet_deployment", "serve_fleet",
           "DEFAULT_CRON", "DEPLOYMENT_NAME"]

DEFAULT_CRON = "0 2 * * *"
"""Every night at 02:00 UTC."""
DEPLOYMENT_NAME = "nightly"


@dataclass
class FoundSession:
    """A session folder found under the root."""

    folder: str                  # local path or URL of the folder
    camera_id: str | None
    session_id: str | None
    has_images: bool = True      # False: a field session with observations.csv (nothing to measure)
    error: str | None = None     # why its manifest could not be read


def _filesystem(root: str, storage_options: dict | None):
    """(fsspec filesystem or None for local, root path without protocol)."""
    text = os.fspath(root)
    if "://" in text and not text.startswith("file://"):
        import fsspec

        fs, path = fsspec.core.url_to_fs(text, **(storage_options or {}))
        return fs, path.rstrip("/")
    if text.startswith("file://"):
        text = text[len("file://"):]
    return None, os.path.abspath(text)



@task(name="scan-sessions", cache_policy=NO_CACHE, persist_result=False)
def scan_sessions(root: str, storage_options: dict | None = None) -> list[FoundSession]:
    """Session folders under ``root`` (see the module docstring), sorted by path."""
    fs, base = _filesystem(root, storage_options)
    patterns = ("*/session.json", "*/*/session.json")
    if fs is None:
        import glob

        manifests = sorted({p for pat in patterns for p in glob.glob(os.path.join(base, pat))})
    else:
        fs.invalidate_cache(base)
        manifests = sorted({p for pat in patterns for p in fs.glob(f"{base}/{pat}")})
    found = []
    for m in manifests:
        folder = posixpath.dirname(m) if fs is not None else os.path.dirname(m)
        url = fs.unstrip_protocol(folder) if fs is not None else folder
        try:
            if fs is None:
                with open(m, "rb") as f:
                    raw = f.read()
                has_obs = os.path.isfile(os.path.join(folder, "observations.csv"))
            else:
                raw = fs.cat_file(m)
                has_obs = fs.exists(f"{folder}/observations.csv")
            manifest = json.loads(raw)
            if not isinstance(manifest, dict):
                raise ValueError("session.json must be a JSON object")
            camera_id = manifest.get("camera_id")
            if not isinstance(camera_id, str) or not camera_id:
                raise ValueError("session.json has no camera_id")
            session_id = default_session_id(manifest, folder)
            has_images = manifest.get("method") == "goniometer" or not has_obs
            found.append(FoundSession(url, camera_id, str(session_id), has_images))
        except (OSError, ValueError) as e:
            found.append(FoundSession(url, None, None, error=f"{m}: {one_line(e)}"))
    return found


@contextlib.contextmanager
def _local_copy(folder: str, storage_options: dict | None):
    """The session folder itself when local, else a temporary local copy (removed afterwards)."""
    fs, path = _filesystem(folder, storage_options)
    if fs is None:
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="fieldcal-session-") as tmp:
        local = os.path.join(tmp, path.rstrip("/").rsplit("/", 1)[-1])
        fs.get(path.rstrip("/") + "/", local + "/", recursive=True)
        yield local


@flow(name="recalibrate-fleet", persist_result=False)
def recalibrate_fleet(lake: str, root: str | None = None, storage_options: dict | None = None,
                      root_storage_options: dict | None = None, dask_address: str | None = None,
                      n_workers: int = cluster.DEFAULT_WORKERS, settings: dict | None = None,
                      batch_size: int | None = None, cluster_kwargs: dict | None = None) -> dict:
    """Calibrate every session under ``root`` that has no committed calibration in ``lake``.

    Parameters
    ----------
    lake : str
        The lake (local path or fsspec URL).
    root : str, optional
        The root of session folders (local path or fsspec URL); default ``<lake>/sessions``.
    storage_options : dict, optional
        fsspec options of the lake (non-secret: they are stored with the flow run).
    root_storage_options : dict, optional
        fsspec options of the root (default: ``storage_options``).
    dask_address, n_workers, settings, batch_size, cluster_kwargs
        As for :func:`flows.calibrate.calibrate_session`; one cluster serves all sessions.

    Returns
    -------
    dict
        ``lake``, ``root``, ``sessions`` (per session found: ``folder``, ``camera_id``,
        ``session_id``, ``status`` ("committed" | "unchanged" | "failed" | "calibrated
        already"), ``version``, ``reason``, ``seconds``), and the counts ``n_found``,
        ``n_committed``, ``n_failed``, ``n_skipped``.
    """
    logger = get_run_logger()
    root = root or (str(lake).rstrip("/") + "/sessions")
    root_options = root_storage_options if root_storage_options is not None else storage_options
    found = scan_sessions(root, root_options)
    calibrated = set(Lake(lake, storage_options).sessions_with_calibration())
    logger.info(f"{len(found)} session(s) under {root}, {len(calibrated)} calibrated in the lake")

    results = []
    address = cluster.dask_address(dask_address)
    with contextlib.ExitStack() as stack:
        for s in found:
            entry = {"folder": s.folder, "camera_id": s.camera_id, "session_id": s.session_id,
                     "status": None, "version": None, "reason": None, "seconds": 0.0}
            results.append(entry)
            if s.error:
                entry.update(status="failed", reason=s.error)
                logger.error(f"{s.folder}: {s.error}")
                continue
            if (s.camera_id, s.session_id) in calibrated:
                entry["status"] = "calibrated already"
                continue
            if address is None and s.has_images:
                import distributed

                local = stack.enter_context(distributed.LocalCluster(
                    **cluster.local_cluster_kwargs(n_workers, cluster_kwargs)))
                address = local.scheduler_address
                logger.info(f"started a local Dask cluster of {n_workers} worker(s) at {address}")
            t = time.perf_counter()
            try:
                with _local_copy(s.folder, root_options) as folder:
                    state = calibrate_session(folder, lake, storage_options=storage_options,
                                              settings=settings, dask_address=address, n_workers=n_workers,
                                              batch_size=batch_size, cluster_kwargs=cluster_kwargs,
                                              return_state=True)
                    outcome = state.result(raise_on_failure=False)
            except Exception as e:  # noqa: BLE001 - e.g. the copy failed: record it, go on
                outcome = e
            entry["seconds"] = round(time.perf_counter() - t, 3)
            if isinstance(outcome, BaseException):
                entry.update(status="failed", reason=one_line(outcome))
                logger.error(f"{s.camera_id} / {s.session_id}: failed: {entry['reason']}")
            else:
                entry.update(status=outcome["status"], version=outcome["version"])
                logger.info(f"{s.camera_id} / {s.session_id}: {outcome['status']} {outcome['version']}")
    summary = {
        "lake": str(lake), "root": str(root), "sessions": results, "n_found": len(found),
        "n_committed": sum(r["status"] == "committed" for r in results),
        "n_failed": sum(r["status"] == "failed" for r in results),
        "n_skipped": sum(r["status"] in ("calibrated already", "unchanged") for r in results),
    }
    logger.info(f"fleet: {summary['n_found']} found, {summary['n_committed']} committed, "
                f"{summary['n_failed']} failed, {summary['n_skipped']} skipped")
    return summary


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


def serve_fleet(lake: str, root: str | None = None, **kwargs) -> None:
    """Serve :func:`fleet_deployment` from this process until interrupted (``fieldcal serve``)."""
    from prefect import serve

    serve(fleet_deployment(lake, root, **kwargs), print_starting_message=True)
