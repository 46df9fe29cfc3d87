"""A fleet of session folders: find them under a root, load them, and pick those to calibrate.

A *root* holds session folders (CONTRACT section 3) directly (``ROOT/<session>/``) or one
level deeper (``ROOT/<camera>/<session>/``); it is a local path or an fsspec URL
(``s3://bucket/incoming``). Plain functions, no workflow engine:

- :func:`scan_sessions` lists every folder with a ``session.json`` and loads each with
  the session loader (:func:`fieldcal.session.loader.load_session`): the same validation
  as a run, so ``camera_id`` and ``session_id`` (default: the folder's name) are exactly
  what the run will use. A folder that does not load is returned with its one-line error.
  On an object store only the small files (``*.json``, ``*.csv``) are fetched for this.
- :func:`select_sessions` pairs them with the lake's calibrations: which have one
  already (with the latest version) and which are to be calibrated.
- A rig session (CONTRACT section 3, "Rig sessions") is found like any other, loaded with the
  rig loader (:func:`fieldcal.rig.session.load_rig_session`): its ``camera_id`` is the rig's
  id, ``heads`` its heads' camera ids, and its version the rig's (the ``rigs`` table).

A session on an object store is never copied: a run reads its images on the workers
(:mod:`fieldcal.session.store`).
"""

from __future__ import annotations

import contextlib
import os
import posixpath
import tempfile
from dataclasses import dataclass
from datetime import datetime

from fieldcal.errors import InputError, one_line
from fieldcal.lake import order
from fieldcal.rig.session import is_rig_session, load_rig_session
from fieldcal.session.loader import load_session
from fieldcal.session.store import SMALL_FILES

__all__ = ["FoundSession", "root_filesystem", "check_root", "scan_sessions", "select_sessions",
           "entry", "status_text", "summarize", "head_entries", "SMALL_FILES"]

PATTERNS = ("*/session.json", "*/*/session.json")


@dataclass
class FoundSession:
    """A session folder found under the root.

    ``has_images`` is False for a field session with ``observations.csv`` (nothing to
    measure); ``error`` is the one-line reason it does not load (then the ids are None);
    ``version`` is its latest committed version once :func:`select_sessions` has looked;
    ``note`` why a session with a committed version is calibrated again (that version does
    not read back whole: its folder removed, a partial restore; issue 24).
    A rig session has ``rig`` True, ``camera_id`` the rig's id, ``heads`` its heads' camera
    ids and, once committed, ``head_versions`` their calibrations' versions (of the rig version).
    """

    folder: str                  # local path or URL of the folder
    camera_id: str | None
    session_id: str | None
    has_images: bool = True
    error: str | None = None
    version: str | None = None
    acquired: datetime | None = None      # with session_id, which session it is (fieldcal.lake.order)
    rig: bool = False
    heads: list | None = None
    head_versions: list | None = None
    note: str | None = None


def root_filesystem(root: str, storage_options: dict | None = None):
    """``(fsspec filesystem or None for a local root, the root's path without protocol)``."""
    text = os.fspath(root)
    if "://" in text and not text.startswith("file://"):
        import fsspec

        from fieldcal.lake import secrets

        fs, path = fsspec.core.url_to_fs(text, **(secrets.resolve(storage_options) or {}))
        return fs, path.rstrip("/")
    return None, os.path.abspath(text.removeprefix("file://"))


def check_root(root: str, storage_options: dict | None = None) -> None:
    """Raise :class:`InputError` when the root of sessions does not exist (or is not a folder)."""
    fs, base = root_filesystem(root, storage_options)
    if fs is None:
        if not os.path.isdir(base):
            raise InputError("no folder of sessions there" if not os.path.exists(base) else "not a folder", root)
        return
    try:
        fs.invalidate_cache(base)
        ok = fs.isdir(base)
    except OSError as e:
        raise InputError(f"cannot list it: {one_line(e)}", root) from None
    if not ok:
        raise InputError("no folder of sessions there", root)


def _manifests(fs, base: str) -> list[str]:
    if fs is None:
        import glob

        escaped = glob.escape(base)
        return sorted({p for pat in PATTERNS for p in glob.glob(os.path.join(escaped, pat))})
    fs.invalidate_cache(base)
    return sorted({p for pat in PATTERNS for p in fs.glob(f"{_escape_fs(base)}/{pat}")})


def _escape_fs(path: str) -> str:
    """A path with fsspec's glob metacharacters escaped (``[`` as ``[[]``, ...)."""
    import glob

    return glob.escape(path)


def _fetch_small_files(fs, folder: str, dest: str) -> None:
    """Copy the session folder's ``*.json`` / ``*.csv`` files (no images) into ``dest``."""
    for path in fs.find(folder):
        rel = path[len(folder):].lstrip("/")
        if rel.lower().endswith(SMALL_FILES):
            target = os.path.join(dest, *rel.split("/"))
            os.makedirs(os.path.dirname(target), exist_ok=True)
            fs.get_file(path, target)


def _load(fs, folder: str) -> FoundSession:
    url = fs.unstrip_protocol(folder) if fs is not None else folder
    try:
        with contextlib.ExitStack() as stack:
            local = folder
            if fs is not None:
                tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="fieldcal-scan-"))
                local = os.path.join(tmp, posixpath.basename(folder.rstrip("/")))
                _fetch_small_files(fs, folder, local)
            if is_rig_session(local):
                rig = load_rig_session(local)
                return FoundSession(url, rig.rig_id, rig.session_id, rig.observations_path is None, rig=True,
                                    heads=[h.camera_id for h in rig.heads])
            sess = load_session(local)
        has_images = sess.method == "goniometer" or sess.observations_path is None
        return FoundSession(url, sess.camera_id, sess.session_id, has_images, acquired=sess.acquired)
    except (InputError, OSError) as e:
        text = one_line(e)
        if fs is not None and local != folder:
            text = text.replace(local, url)
        return FoundSession(url, None, None, error=text)


def scan_sessions(root: str, storage_options: dict | None = None) -> list[FoundSession]:
    """Every session folder under ``root`` (module docstring), loaded, sorted by path.

    Raises
    ------
    InputError
        The root does not exist.
    """
    check_root(root, storage_options)
    fs, base = root_filesystem(root, storage_options)
    folders = [posixpath.dirname(m) if fs is not None else os.path.dirname(m) for m in _manifests(fs, base)]
    return [_load(fs, f) for f in folders]


def select_sessions(found: list[FoundSession], lake) -> list[FoundSession]:
    """The sessions without a committed calibration that reads back whole; sets ``version``
    of the others (latest).

    ``lake`` is a :class:`fieldcal.lake.store.Lake`; sessions that did not load are neither
    selected nor given a version. A session is its camera, ``session_id`` and acquisition
    time (:func:`fieldcal.lake.order.session_key`): ``ROOT/2026-01/wall`` and
    ``ROOT/2026-02/wall`` (no ``session_id``) are two. A session whose latest version does
    not read back whole (:meth:`Lake.whole`) is selected, with the reason in its ``note``.
    """
    rows: dict = {}
    for r in lake.catalog().select(["camera_id", *order.ROW_COLUMNS, "document_path", "zarr_path"]).to_pylist():
        rows.setdefault((r["camera_id"], *order.session_key(r)), []).append(r)
    rigs = {(r["rig_id"], r["session_id"]): r for r in lake.rig_catalog().to_pylist()}   # oldest first
    todo, calibrated = [], []
    for s in found:
        if s.error:
            continue
        if s.rig:
            row = rigs.get((s.camera_id, s.session_id))
            if row is None:
                todo.append(s)
            else:
                s.version, s.head_versions = row["version"], list(row["head_versions"])
            continue
        # same-named folders: told apart by acquisition (a version without one: by its name)
        mine = rows.get((s.camera_id, s.session_id, s.acquired)) or rows.get((s.camera_id, s.session_id, None))
        if mine:
            latest = order.latest(mine)
            calibrated.append((s, next(r for r in mine if r["version"] == latest)))
        else:
            todo.append(s)
    for s, row in calibrated:
        why = lake.whole(row["version"], row)
        if why is None:
            s.version = row["version"]
        else:
            s.note = f"version {row['version']} does not read back whole ({why}): calibrated again"
            todo.append(s)
    pos = {id(s): i for i, s in enumerate(found)}
    return sorted(todo, key=lambda s: pos[id(s)])                 # in the order found


def entry(s: FoundSession, status: str | None = None, reason: str | None = None) -> dict:
    """A session's line of the fleet's summary (before or without a run: ``status`` given)."""
    return {"folder": s.folder, "camera_id": s.camera_id, "session_id": s.session_id, "status": status,
            "version": s.version, "new": False, "reason": reason, "seconds": 0.0, "retried": None,
            "n_images": None, "n_left_out": 0, "rig": s.rig, "heads": head_entries(s.heads, s.head_versions)}


def head_entries(heads: list | None, versions: list | None) -> list[dict] | None:
    """A rig's heads in its summary entry: ``[{"camera_id", "version"}]`` (None: not a rig)."""
    if heads is None:
        return None
    versions = versions if versions is not None else [None] * len(heads)
    return [{"camera_id": c, "version": v} for c, v in zip(heads, versions, strict=True)]


def status_text(e: dict) -> str:
    """A summary entry's status for people: "committed" says when images were left out
    ("committed, 2 of 6 images left out")."""
    text = str(e["status"])
    if e.get("n_left_out") and e["status"] in ("committed", "unchanged"):
        text += f", {e['n_left_out']} of {e['n_images']} images left out"
    return text


def summarize(lake: str, root: str, found: list[FoundSession], results: dict | None = None) -> dict:
    """The fleet's summary: every session found, in order, with its version (new or existing).

    ``results`` maps ``id(session)`` to the entry of a session that was run; the others are
    "calibrated already" (with their latest version, once :func:`select_sessions` has
    looked), "failed" (did not load) or "to calibrate".

    Returns
    -------
    dict
        ``lake``, ``root``, ``sessions`` (entries: ``folder``, ``camera_id``, ``session_id``,
        ``status``, ``version``, ``new``, ``reason``, ``seconds``, ``retried``: the first
        run's reason when a session was run again, ``n_images`` and ``n_left_out``: the
        images of a session that was run and those of them left out, ``rig``: whether it is
        a rig session, and then ``camera_id`` the rig's id, ``version`` the rig's and ``heads``
        its heads ``[{"camera_id", "version"}]``), ``n_found``,
        ``n_committed`` (of them ``n_partial`` with images left out), ``n_failed``, ``n_skipped``.
    """
    results = results or {}

    def status(s):
        return "failed" if s.error else "calibrated already" if s.version else "to calibrate"

    entries = [results.get(id(s)) or entry(s, status(s), s.error or s.note) for s in found]
    for s in found:
        if s.note and id(s) in results and not results[id(s)].get("reason"):
            results[id(s)]["reason"] = s.note
    return {
        "lake": str(lake), "root": str(root), "sessions": entries, "n_found": len(entries),
        "n_committed": sum(r["status"] == "committed" for r in entries),
        "n_partial": sum(r["status"] == "committed" and bool(r.get("n_left_out")) for r in entries),
        "n_failed": sum(r["status"] == "failed" for r in entries),
        "n_skipped": sum(r["status"] in ("calibrated already", "unchanged") for r in entries),
    }
