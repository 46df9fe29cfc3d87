"""The versioned data lake: immutable versions over Delta tables, Zarr groups and documents.

One root, a local path or an fsspec URL (``s3://bucket/prefix``), laid out so that a
person can browse it and any lakehouse reader (Spark, Trino, Polars, DuckDB, pyarrow) can
query it without fieldcal (``LAKE/README.md``, the data dictionary, says how)::

    LAKE/catalog/                    Delta table: one row per committed version (the commit)
    LAKE/residuals/                  Delta table: residuals of every version (by camera_id)
    LAKE/observations_field/         Delta table: targets measured per field image (cache)
    LAKE/observations_goniometer/    Delta table: the spot of each goniometer frame (cache)
    LAKE/comparisons/                Delta table: the change test of two versions (derived)
    LAKE/assessments/                Delta table: the acceptance of each version (derived)
    LAKE/calibrations/C/S/V.zarr     Zarr v3 group: the arrays, the document in attrs
    LAKE/calibrations/C/S/V.json     the calibration document (docs/conventions.md section 4)
    LAKE/README.md                   the data dictionary, written at the first commit

The tables are described in :mod:`fieldcal.lake.tables`; version ids in
:mod:`fieldcal.lake.ids`.

Commit protocol
---------------
:meth:`Lake.commit` checks and serialises everything in memory first (nothing is written
when the document, the residual table or an array is bad). Then:

1. the document ``calibrations/C/S/V.json`` is created *exclusively* (it reserves the
   version id: two commits can never write into one version; a clash of the random part
   draws another id);
2. the Zarr group, with the SHA-256 of every array in its attributes;
3. the version's residual rows are appended to ``residuals``;
   then every part is read back and verified (:func:`fieldcal.lake.check.read_back`: the
   document byte for byte, each array against its SHA-256, the residual rows counted): a
   part lost meanwhile fails the commit, no row ever points to nothing (issue 24);
4. the catalog row is committed to ``catalog``: **the commit point**. Readers see a
   version only through its catalog row; the residuals view of :mod:`fieldcal.lake.history`
   keeps only rows of versions in the catalog (as of the same time), so rows of a version
   whose catalog row is not committed are never visible.

One version per fingerprint: a commit appends its catalog row with a Delta transaction
identifier naming the fingerprint (:meth:`fieldcal.lake.tables.Tables.append` ``once=``),
unless the catalog's log has that identifier already. When the versions of the fingerprint
do not read back whole (a folder removed), the identifier is the fingerprint *after* the
latest of them, so a rerun makes one new version (:meth:`Lake.committed_whole`). Delta's conflict check fails the
second of two concurrent commits of one fingerprint; it then finds the first's row, removes
its own parts and returns the first's version (``Committed.new`` False). The check reads
the log only, not the catalog's rows: a catalog from before (rows without identifiers)
is also searched for the fingerprint until ``fieldcal lake optimize`` has given it the
identifiers (:meth:`~fieldcal.lake.tables.Tables.adopt_keys`). A commit was a MERGE
"insert unless a row has this fingerprint" before, which costs the catalog's scan twice
(issue 28: 0.4-0.8 s locally, 4.3 s on S3; ``bench/bench_commit.py``). No claim files, no
waiting on another process, nothing to go stale: a crashed commit leaves only unreferenced
parts, which :meth:`Lake.gc` removes once older than its grace period. A forced commit
appends its row whatever the catalog holds (and records its fingerprint's identifier). The
version id needs no check in the catalog: its document was created exclusively. On S3 the
Delta commits are conditional PUTs (``If-None-Match``).

Every commit records who made it in the table's history (``fieldcal lake log``): the code
version, host, process id, user and, when given, the flow run id.

Errors
------
Bad arguments raise :class:`~fieldcal.errors.InputError` before anything is written;
storage failures (read-only destination, full disk, missing bucket) raise
:class:`~fieldcal.errors.LakeError` with a one-line reason, after the failed commit's
parts have been removed as far as possible. Readers skip what they cannot read (a damaged
table file, a version whose folder is gone) and list it in :attr:`Lake.problems`;
:func:`fieldcal.lake.check.check` lists every damaged object and what depends on it.
"""

from __future__ import annotations

import getpass
import json
import os
import socket
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401 - pa.compute
import pyarrow.dataset as ds

from fieldcal.contract.fingerprint import code_version, is_fingerprint
from fieldcal.contract.schemas import validate_json
from fieldcal.errors import InputError, LakeError
from fieldcal.lake import observations as obs
from fieldcal.lake import order
from fieldcal.lake.ids import (
    VERSION_PATTERN,
    check_id,
    check_version,
    iso,
    new_version,
    observations_key,
    parse_time,
    plain_json,
    utcnow,
    version_time,
)
from fieldcal.lake.parts import KNOWN_ARRAYS, array_digest, catalog_row, conform_residuals, prepare_arrays, reason
from fieldcal.lake.storage import Storage
from fieldcal.lake.tables import DEFAULT_MAINTAIN_EVERY, Tables
from fieldcal.session.loader import check_acquired_not_ahead

__all__ = ["Lake", "Committed", "new_version", "version_time", "observations_key",
           "KNOWN_ARRAYS"]


class Committed(str):
    """A version id returned by :meth:`Lake.commit`.

    ``new`` is True when this call created the version, False when the same fingerprint
    was already committed (or was committed concurrently) and that version is returned.
    """

    new: bool

    def __new__(cls, version: str, new: bool):
        obj = super().__new__(cls, version)
        obj.new = bool(new)
        return obj

    def __reduce__(self):
        return (Committed, (str(self), self.new))


def _who() -> dict:
    """Who makes a commit: host, process, user, code version (commit metadata)."""
    try:
        user = getpass.getuser()
    except Exception:  # noqa: BLE001 - no user name in some containers
        user = None
    return {"host": socket.gethostname(), "pid": os.getpid(), "user": user,
            "code_version": code_version()}


def _sql_str(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _refuse_first_layout(store: Storage, url: str) -> None:
    """A lake of the first layout (``catalog/V.parquet``, no Delta log) is not read as an
    empty lake: its history would look lost and a commit would start a second catalog
    beside it. It is moved with ``fieldcal lake migrate`` (:mod:`fieldcal.lake.migrate`)."""
    names = store.listdir("catalog")
    if "_delta_log" in names:
        return
    if any(n.endswith(".parquet") and VERSION_PATTERN.fullmatch(n[:-8]) for n in names):
        raise LakeError(f"{url} is a lake of the first layout (one file per version); move it once "
                        f"with `fieldcal lake migrate {url} --lake NEW` and use NEW")


class Lake:
    """A versioned calibration lake at a local path or an fsspec URL.

    Parameters
    ----------
    url_or_path : str or os.PathLike
        ``/data/lake``, ``file:///data/lake`` or ``s3://bucket/prefix`` (any fsspec URL).
    storage_options : dict, optional
        fsspec options, e.g. ``{"endpoint_url": ..., "key": ..., "secret": ...}`` for s3fs
        (translated for delta-rs by :func:`fieldcal.lake.storage.delta_options`).
    maintain_every : int
        Commits of a table between automatic compactions and checkpoints.
    """

    def __init__(self, url_or_path, storage_options=None, *,
                 maintain_every: int = DEFAULT_MAINTAIN_EVERY):
        self._store = Storage(url_or_path, storage_options)
        self.tables = Tables(self._store, maintain_every)
        self.url = self._store.uri("")
        self._obs_cache: dict[tuple, dict] = {}
        self.not_whole: dict[str, str] = {}
        """``{version: reason}`` of committed versions found not to read back whole."""
        _refuse_first_layout(self._store, self.url)

    def __repr__(self) -> str:
        return f"Lake({self.url!r})"

    @property
    def problems(self) -> list:
        """Damaged objects the readers of this instance skipped (:class:`tables.Problem`)."""
        return self.tables.problems

    @property
    def is_local(self) -> bool:
        """True for a lake on the local filesystem."""
        return self._store.local

    @property
    def fs(self):
        """The fsspec filesystem of a remote lake (None for a local one)."""
        return self._store.fs

    @property
    def storage(self) -> Storage:
        """The lake's file operations (:class:`fieldcal.lake.storage.Storage`)."""
        return self._store

    def uri(self, rel: str) -> str:
        """A path inside the lake as a local path or URL (for DuckDB, pyarrow, zarr)."""
        return self._store.uri(rel)

    @staticmethod
    def paths(camera_id: str, session_id: str, version: str) -> dict[str, str]:
        """Lake-relative names of a version's parts."""
        return {"residuals": "residuals",
                "zarr": f"calibrations/{camera_id}/{session_id}/{version}.zarr",
                "document": f"calibrations/{camera_id}/{session_id}/{version}.json",
                "catalog": "catalog"}

    # -- commit ---------------------------------------------------------------------------
    def commit(self, document: Mapping, arrays: Mapping | None = None, residuals=None, *,
               force: bool = False, acquired=None,
               array_attrs: Mapping[str, Mapping] | None = None,
               info: Mapping | None = None, original: Mapping | None = None) -> Committed:
        """Store one immutable version: document, Zarr arrays, residuals, then the catalog row.

        Parameters
        ----------
        document : mapping
            The calibration document (docs/conventions.md section 4). ``version`` may be absent, null
            or empty (a new id is made) or a version id to write (refused if it exists);
            ``created`` defaults to now; ``code_version`` is added; ``acquired`` (the
            session's acquisition date or time, an extra key) feeds the catalog.
        arrays : mapping of str to array_like, optional
            Named arrays for the Zarr group (:data:`KNOWN_ARRAYS`).
        residuals : pyarrow.Table or mapping of columns
            The residual table (``schemas/residuals.arrow.json``; missing nullable
            columns are filled with nulls).
        force : bool
            Make a new version even when the same fingerprint is already committed.
        acquired : str, date or datetime, optional
            Overrides the document's ``acquired``.
        array_attrs : mapping of str to dict, optional
            Zarr attributes per array name (e.g. ``{"covariance": {"names": [...]}}``).
        info : mapping, optional
            Extra commit metadata for the tables' history (e.g. ``{"flow_run_id": ...}``).
        original : mapping, optional
            Migration only (:mod:`fieldcal.lake.migrate`): ``{"committed": datetime,
            "forced": bool}`` of a version brought over from another lake. The document
            must name its version; the row keeps these values and is inserted unless that
            version exists (fingerprints are not compared).

        Returns
        -------
        Committed
            The version id; ``.new`` False when an existing version of the same
            fingerprint was returned instead of making another.

        Raises
        ------
        InputError
            A bad document, table or array (nothing is written).
        LakeError
            The lake cannot be written, or the version exists already.
        """
        now = utcnow()
        doc, explicit = self._prepare_document(document, now, acquired)
        where = f"calibration {doc['camera_id']}/{doc['session_id']}"
        if original is None and doc.get("acquired") is not None:   # a typo would stay the latest for years
            check_acquired_not_ahead(parse_time(doc["acquired"], where), now, where)
        res = conform_residuals(residuals, where)
        zarr_arrays = prepare_arrays(doc, arrays or {}, array_attrs or {}, where)
        fp = doc["inputs"]["fingerprint"]
        catalog_row(doc, now, force, self.paths(doc["camera_id"], doc["session_id"],
                                                doc["version"]), where)
        meta = dict(_who(), **plain_json(dict(info or {}), "commit info"))
        if original is not None:
            if not explicit:
                raise InputError("a migrated version needs its version id", where)
            force = bool(original.get("forced", False))
        try:
            if original is not None:
                if self._is_committed(doc["version"]):
                    return Committed(doc["version"], new=False)
                return self._write_version(doc, explicit, res, zarr_arrays, force, meta, where,
                                           original)
            broken: dict[str, str] = {}
            if not force:
                existing, broken = self._committed_before(fp)
                if existing is not None:
                    return Committed(existing, new=False)
            return self._write_version(doc, explicit, res, zarr_arrays, force, meta, where,
                                       broken=broken)
        except OSError as e:
            raise LakeError(f"cannot commit to {self.url}: {reason(e)}") from None

    def _write_version(self, doc, explicit, res, zarr_arrays, force, meta, where,
                       original=None, broken: Mapping[str, str] | None = None) -> Committed:
        written: list[str] = []
        residuals_of = None
        done = False
        try:
            version = self._reserve(doc, explicit, written)
            paths = self.paths(doc["camera_id"], doc["session_id"], version)
            meta = dict(meta, version=version, camera_id=doc["camera_id"],
                        session_id=doc["session_id"], fingerprint=doc["inputs"]["fingerprint"])
            written.append(paths["zarr"])
            self._write_zarr(paths["zarr"], zarr_arrays, doc)
            if res.num_rows:
                residuals_of = version
                self.tables.append("residuals", _with_keys(res, doc), dict(meta, action="residuals"))
            self._read_back(doc, paths, res.num_rows)
            row = catalog_row(doc, utcnow() if original is None else original["committed"], force,
                              paths, where)
            meta["action"] = "commit" if original is None else "migrate"
            inserted = self._insert_catalog(row, doc, force, meta, original, broken or {})
            if inserted:
                done = True
                self._write_dictionary()
                return Committed(version, new=True)
            existing = self.find_committed(doc["inputs"]["fingerprint"])
            if existing is None:
                raise LakeError(f"version {version} clashes with a committed version in {self.url}")
            return Committed(existing, new=False)
        except Exception as e:
            if isinstance(e, (OSError, LakeError, InputError)):
                raise
            raise LakeError(f"cannot commit to {self.url}: {reason(e)}") from None
        finally:
            if not done:
                self._discard(written, residuals_of)

    def _read_back(self, doc: dict, paths: dict, n_residuals: int) -> None:
        """Every part of the version read back and verified before its catalog row (issue 24,
        goal 1): a part that a concurrent ``gc``, an operator or the storage lost makes the
        commit fail (its parts removed) instead of committing a row that points to nothing."""
        from fieldcal.lake.check import read_back

        why = read_back(self, doc["version"], paths["document"], paths["zarr"],
                        document=json.dumps(doc, indent=2).encode("utf-8"),
                        residuals=(doc["camera_id"], n_residuals) if n_residuals else None)
        if why is not None:
            raise LakeError(f"version {doc['version']} not committed to {self.url}: {why} when "
                            "read back before the commit")

    CATALOG_BY_MERGE = False
    """The commit path before issue 28 (a MERGE after a scan of the catalog), kept for
    ``bench/bench_commit.py``'s before/after."""

    def _committed_before(self, fp: str) -> tuple[str | None, dict[str, str]]:
        """``(version, broken)``: the version of this fingerprint committed already that reads
        back whole, or None, and the committed ones that do not (:meth:`committed_whole`): the
        catalog's log says whether it has one (:meth:`~fieldcal.lake.tables.Tables.has_key`),
        its rows say which (read only then, and for a catalog from before the identifiers)."""
        keyed = self.tables.has_key("catalog", fp)
        if not self.CATALOG_BY_MERGE and keyed is False:
            return None, {}
        version, broken = self.committed_whole(fp)
        if version is None and not broken and keyed:
            # committed once (the log has its key) but no row: taken out by `lake repair`, or
            # hidden by a damaged file; the log names the versions
            broken = {e["version"]: "its catalog row is missing" for e in self.tables.commits("catalog")
                      if e.get("fingerprint") == fp and e.get("action") in ("commit", "migrate")
                      and isinstance(e.get("version"), str)}
        return version, broken

    def _insert_catalog(self, row, doc: dict, force: bool, meta: dict, original,
                        broken: Mapping[str, str]) -> bool:
        """The commit point: the catalog row, once per fingerprint unless forced (module
        docstring); True when inserted. When the committed versions of the fingerprint do not
        read back whole (``broken``), the key is the fingerprint *after* the latest of them:
        once per fingerprint and generation, so that two reruns replacing one lost version
        still make one (issue 24)."""
        fp, version = doc["inputs"]["fingerprint"], doc["version"]
        if original is not None:
            return self.tables.insert_unless("catalog", row, "t.version = s.version", meta, keys=(fp,),
                                             exists=lambda: self._is_committed(version))
        if self.CATALOG_BY_MERGE and not force:
            return self.tables.insert_unless(
                "catalog", row, "t.fingerprint = s.fingerprint OR t.version = s.version", meta)
        if not force and not self.tables.every_key_once("catalog") and self.find_committed(fp) is not None:
            return False                      # a catalog from before: its rows without identifiers
        key = f"{fp}+after+{max(broken)}" if broken and not force else fp
        return self.tables.append_once("catalog", row, key, meta, exclusive=not force)

    def _reserve(self, doc: dict, explicit: bool, written: list) -> str:
        """Create the version's document exclusively (the version id's reservation)."""
        for _ in range(32):
            version = doc["version"] if explicit else new_version(doc["inputs"]["fingerprint"])
            doc["version"] = version
            rel = self.paths(doc["camera_id"], doc["session_id"], version)["document"]
            try:
                self._store.write(rel, json.dumps(doc, indent=2).encode("utf-8"), exclusive=True)
            except FileExistsError:
                if explicit:
                    state = "committed" if self._is_committed(version) else \
                        "being written, or left by a failed commit (fieldcal gc removes it)"
                    raise LakeError(f"version {version} is already {state} in {self.url}; "
                                    "versions are immutable") from None
                continue
            written.append(rel)
            return version
        raise LakeError(f"could not find a free version id in {self.url}")

    def _discard(self, written: list[str], residuals_of: str | None) -> None:
        """Best-effort removal of a failed or losing commit's parts (gc removes the rest)."""
        for rel in reversed(written):
            try:
                self._store.remove(rel)
            except Exception:  # noqa: BLE001, S110 - best effort; gc() removes what is left
                pass
        if residuals_of is not None:
            try:
                self.tables.delete("residuals", f"version = {_sql_str(residuals_of)}",
                                   {"action": "discard", "version": residuals_of})
            except Exception:  # noqa: BLE001, S110 - invisible anyway; gc() removes them
                pass

    def discard_uncommitted(self, version: str) -> list[str]:
        """Remove the parts of a version that has no catalog row (refused if it has one)."""
        check_version(version)
        if self._is_committed(version):
            raise LakeError(f"version {version} is committed in {self.url}; versions are immutable")
        from fieldcal.lake.gc import version_parts

        parts = version_parts(self, {version})
        self._discard(parts, version)
        return parts

    def _prepare_document(self, document, now, acquired):
        if not isinstance(document, Mapping):
            raise InputError(f"the calibration document must be a mapping, got "
                             f"{type(document).__name__}", "commit")
        doc = plain_json(dict(document), "calibration document")
        check_id(doc.get("camera_id"), "camera_id")
        check_id(doc.get("session_id"), "session_id")
        where = f"calibration document {doc['camera_id']}/{doc['session_id']}"
        fp = (doc.get("inputs") or {}).get("fingerprint") if isinstance(doc.get("inputs"), dict) \
            else None
        if not is_fingerprint(fp):
            raise InputError(f"inputs.fingerprint must be 'sha256:' and 64 hex digits, got {fp!r}",
                             where)
        version = doc.get("version")
        explicit = version not in (None, "")
        if explicit:
            if not isinstance(version, str) or not VERSION_PATTERN.fullmatch(version):
                raise InputError(f"version must look like YYYYMMDDTHHMMSSZ-xxxxxxxx-xxxx, got "
                                 f"{version!r}", where)
        else:
            version = new_version(fp, now)  # provisional; the commit reserves the final one
        doc["version"] = version
        if doc.get("created") in (None, ""):
            doc["created"] = iso(now.replace(microsecond=0))
        doc.setdefault("code_version", code_version())
        if acquired is not None:
            t = parse_time(acquired, where)
            doc["acquired"] = acquired if isinstance(acquired, str) else iso(t)
        validate_json(doc, "calibration", where)
        parse_time(doc["created"], f"{where}: created")
        parse_time(doc.get("acquired"), f"{where}: acquired")
        return doc, explicit

    def _write_zarr(self, rel: str, arrays: dict, doc: dict) -> None:
        """The version's Zarr group. On an object store it is made in memory and its objects
        PUT at once: a Zarr store over fsspec writes them one after the other, ~10 requests
        per array (0.8-1.0 s of a commit on moto S3, ``bench/bench_commit.py``)."""
        import zarr

        if not self._store.local:
            objects: dict = {}
            self._fill_group(zarr.open_group(store=zarr.storage.MemoryStore(objects), mode="w", zarr_format=3),
                             arrays, doc)
            self._store.write_many(rel, {k: buf.to_bytes() for k, buf in objects.items()})
            return
        store = self._store.zarr_store(rel, read_only=False)
        try:
            self._fill_group(zarr.open_group(store=store, mode="w", zarr_format=3), arrays, doc)
        finally:
            store.close()

    @staticmethod
    def _fill_group(group, arrays: dict, doc: dict) -> None:
        group.attrs.update({"document": doc, "arrays": sorted(arrays),
                            "digests": {n: array_digest(a) for n, (a, _, _) in arrays.items()}})
        for name, (data, attrs, dims) in arrays.items():
            group.create_array(name, data=data, attributes=attrs, dimension_names=dims,
                               config={"write_empty_chunks": True})

    def _write_dictionary(self) -> None:
        """Write ``README.md`` (the data dictionary) when it is missing or outdated."""
        from fieldcal.lake.dictionary import data_dictionary

        text = data_dictionary().encode("utf-8")
        try:
            if self._store.exists("README.md") and self._store.read("README.md") == text:
                return
            self._store.write("README.md", text)
        except OSError:
            pass  # the version is committed; the dictionary is written by the next commit

    # -- rigs (CONTRACT section 3, "Rig sessions") ---------------------------------------
    @staticmethod
    def rig_path(rig_id: str, session_id: str, version: str) -> str:
        """Lake-relative name of a rig version's document."""
        return f"rigs/{rig_id}/{session_id}/{version}.json"

    def commit_rig(self, heads, rig_document: Mapping, *, force: bool = False) -> tuple[Committed, list[str]]:
        """Store one version of a rig: a calibration version per head and the rig document,
        atomically (a reader sees every part of the rig version or none).

        ``heads``: one ``{"document", "arrays", "array_attrs", "residuals"}`` per head, as for
        :meth:`commit`; ``rig_document``: the ``fieldcal.rig/1`` document, its heads' versions
        filled in here. Everything is checked in memory first; then every head's document, Zarr
        group and residuals are written and read back, then the rig document and its ``rigs``
        row, and last **one** transaction of ``catalog`` with every head's row: **the commit
        point** of the rig version. Readers see a head version only through its catalog row and
        a rig version only when every head version its row lists is in the catalog
        (:meth:`rig_catalog`, as of the same time), so an interruption anywhere before the
        catalog's transaction leaves only invisible parts (the rig row included), which
        :meth:`gc` removes as any uncommitted part; one after it has committed the whole rig.
        A rerun of the same inputs completes an interrupted rig version whose parts read back
        whole (:meth:`complete_rig`: nothing is solved twice, one version per fingerprint).
        A lake from before, whose heads' rows were committed before the rig row, keeps working:
        when every head's fingerprint is committed, only the rig row is written.

        Returns ``(rig version, head versions)``; ``.new`` False when the rig was committed already.
        """
        now = utcnow()
        prepared = []
        for item in heads:
            doc, explicit = self._prepare_document(item["document"], now, None)
            where = f"calibration {doc['camera_id']}/{doc['session_id']}"
            res = conform_residuals(item.get("residuals"), where)
            arrays = prepare_arrays(doc, item.get("arrays") or {}, item.get("array_attrs") or {}, where)
            prepared.append((doc, explicit, res, arrays))
        rig = plain_json(dict(rig_document), "rig document")
        fp = rig["inputs"]["fingerprint"]
        if not force:
            done = self.complete_rig(fp)
            if done is not None:
                return done
            found = [self.find_committed(p[0]["inputs"]["fingerprint"]) for p in prepared]
            if all(found):      # a lake from before: the heads' rows committed, the rig row not
                return self._write_rig_row(rig, list(found), now, []), list(found)
        try:
            return self._write_rig(prepared, rig, force, now)
        except OSError as e:
            raise LakeError(f"cannot commit to {self.url}: {reason(e)}") from None

    def _write_rig(self, prepared, rig: dict, force: bool, now) -> tuple[Committed, list[str]]:
        written: list[str] = []
        residual_versions: list[str] = []
        done = False
        meta = dict(_who(), rig_id=rig["rig_id"], session_id=rig["session_id"])
        try:
            rows, versions = [], []
            for doc, explicit, res, arrays in prepared:
                version = self._reserve(doc, explicit, written)
                paths = self.paths(doc["camera_id"], doc["session_id"], version)
                written.append(paths["zarr"])
                self._write_zarr(paths["zarr"], arrays, doc)
                if res.num_rows:
                    residual_versions.append(version)
                    self.tables.append("residuals", _with_keys(res, doc), dict(meta, action="residuals",
                                                                               version=version))
                self._read_back(doc, paths, res.num_rows)
                rows.append(catalog_row(doc, utcnow(), force, paths, f"calibration {doc['camera_id']}"))
                versions.append(version)
            version = self._write_rig_row(rig, versions, now, written, pending=True)
            self._commit_heads(pa.concat_tables(rows), [p[0]["inputs"]["fingerprint"] for p in prepared], version,
                               dict(meta, action="commit rig", versions=",".join(versions), rig_version=version))
            done = True
        except Exception as e:
            if isinstance(e, (OSError, LakeError, InputError)):
                raise
            raise LakeError(f"cannot commit to {self.url}: {reason(e)}") from None
        finally:
            if not done:       # the files, then each head's residual rows (invisible without catalog rows)
                self._discard(written, None)
                for v in residual_versions:
                    self._discard([], v)
        self._write_dictionary()
        return version, versions

    def _commit_heads(self, rows: pa.Table, fingerprints: list[str], rig_version: str, meta: dict, *,
                      exclusive: bool = False) -> bool:
        """The rig version's commit point: every head's catalog row in one transaction; True when
        appended. The heads' fingerprints and ``rig:<rig version>`` are recorded as the
        transaction's identifiers (so that a later commit of one of them finds it in the log,
        module docstring); ``exclusive`` (completing an interrupted rig version): nothing is
        appended when one of them is committed already (a concurrent completion won)."""
        return self.tables.append_once("catalog", rows, [*fingerprints, f"rig:{rig_version}"], meta,
                                       exclusive=exclusive)

    def _write_rig_row(self, rig: dict, versions: list[str], now, written: list, *,
                       pending: bool = False) -> Committed:
        """Write the rig document (its heads' versions filled in) and its ``rigs`` row (visible
        once every head version it lists is in the catalog; ``pending``: they are not yet)."""
        from fieldcal.lake.tables import RIGS_SCHEMA
        from fieldcal.rig.document import validate_rig_document

        for head, v in zip(rig["heads"], versions, strict=True):
            head["version"] = v
        for _ in range(32):
            rig["version"] = new_version(rig["inputs"]["fingerprint"], now)
            validate_rig_document(rig, f"rig {rig['rig_id']}/{rig['session_id']}")
            rel = self.rig_path(rig["rig_id"], rig["session_id"], rig["version"])
            try:
                self._store.write(rel, json.dumps(rig, indent=2).encode("utf-8"), exclusive=True)
                written.append(rel)
                break
            except FileExistsError:
                continue
        row = {"rig_id": rig["rig_id"], "session_id": rig["session_id"], "version": rig["version"],
               "reference": rig["reference"], "created": parse_time(rig["created"], "rig document"),
               "committed": utcnow(), "acquired": parse_time(rig.get("acquired"), "rig document"),
               "fingerprint": rig["inputs"]["fingerprint"], "camera_ids": [h["camera_id"] for h in rig["heads"]],
               "head_versions": list(versions), "n_exposures": rig["stats"].get("n_exposures"),
               "sigma0": rig["stats"].get("sigma0"), "document_path": rel}
        self.tables.append("rigs", pa.Table.from_pylist([row], schema=RIGS_SCHEMA),
                           dict(_who(), action="pending" if pending else "commit", version=rig["version"]))
        return Committed(rig["version"], new=True)

    def complete_rig(self, fingerprint: str) -> tuple[Committed, list[str]] | None:
        """``(rig version, head versions)`` of the rig version of these inputs: the committed one
        (``.new`` False), or an interrupted one completed now (its rig row written, its heads' catalog
        rows not: those rows are committed in one transaction when every part reads back whole;
        ``.new`` True); None when there is neither (:meth:`commit_rig`)."""
        hit = self.rig_catalog(fingerprint=fingerprint)
        if hit.num_rows:
            return Committed(hit["version"][-1].as_py(), new=False), hit["head_versions"][-1].as_py()
        raw = self.tables.scan("rigs", filter=ds.field("fingerprint") == fingerprint).to_pylist()
        for row in sorted(raw, key=lambda r: (r["committed"], r["version"]), reverse=True):
            rows = self._pending_heads(row)
            if rows is None:
                continue
            fps = rows["fingerprint"].to_pylist()
            if any(self.find_committed(f) is not None for f in fps):
                continue        # a head of it committed meanwhile by another rig version
            meta = dict(_who(), action="commit rig", rig_id=row["rig_id"], session_id=row["session_id"],
                        rig_version=row["version"], versions=",".join(row["head_versions"]), completed=True)
            if not self._commit_heads(rows, fps, row["version"], meta, exclusive=True):
                hit = self.rig_catalog(fingerprint=fingerprint)
                if hit.num_rows:
                    return Committed(hit["version"][-1].as_py(), new=False), hit["head_versions"][-1].as_py()
                continue
            self._write_dictionary()
            return Committed(row["version"], new=True), list(row["head_versions"])
        return None

    def _pending_heads(self, row: Mapping) -> pa.Table | None:
        """The catalog rows of an interrupted rig version's heads (from their stored documents),
        or None when a part of it (the rig document, a head's document or Zarr group) does not
        read back whole or a head version is in the catalog already."""
        from fieldcal.lake.check import read_back

        if not self._store.exists(row["document_path"]):
            return None
        rows = []
        for cid, v in zip(row["camera_ids"], row["head_versions"], strict=True):
            paths = self.paths(cid, row["session_id"], v)
            if self._is_committed(v) or read_back(self, v, paths["document"], paths["zarr"]) is not None:
                return None
            doc = json.loads(self._store.read(paths["document"]))
            rows.append(catalog_row(doc, utcnow(), False, paths, f"calibration {cid}"))
        return pa.concat_tables(rows)

    def rig_catalog(self, *, rig_id: str | None = None, fingerprint: str | None = None, as_of=None) -> pa.Table:
        """Committed rig versions (the ``rigs`` table), oldest first; of one rig or fingerprint;
        ``as_of``: as the tables were at that time. A row is a committed rig version when every
        head version it lists is in the catalog (as of the same time): the row of an interrupted
        commit (:meth:`commit_rig`) is not."""
        f = None
        if rig_id is not None:
            f = ds.field("rig_id") == rig_id
        if fingerprint is not None:
            g = ds.field("fingerprint") == fingerprint
            f = g if f is None else f & g
        t = self.tables.scan("rigs", filter=f, as_of=_as_of(as_of))
        if t.num_rows:
            t = t.filter(pa.array(self._heads_committed(t, as_of)))
        if t.num_rows < 2:
            return t
        return t.take(pa.compute.sort_indices(t.select(["committed", "version"]),
                                              [("committed", "ascending"), ("version", "ascending")]))

    def _heads_committed(self, rigs: pa.Table, as_of) -> list[bool]:
        """Per ``rigs`` row, whether every head version it lists has its catalog row."""
        wanted = sorted({v for vs in rigs["head_versions"].to_pylist() for v in vs})
        have = set(self.catalog(as_of=as_of, filter=ds.field("version").isin(wanted), sort=False)
                   .column("version").to_pylist())
        return [all(v in have for v in vs) for vs in rigs["head_versions"].to_pylist()]

    def rig_of(self, document: Mapping) -> dict | None:
        """The rig document of the rig version a head's calibration ``document`` belongs to (its
        ``rig`` key names the rig; the latest rig version listing the document's version), or None."""
        rig = document.get("rig")
        if not isinstance(rig, Mapping) or not isinstance(rig.get("rig_id"), str):
            return None
        hits = [r for r in self.rig_catalog(rig_id=rig["rig_id"]).to_pylist()
                if document.get("version") in r["head_versions"]]
        return self.load_rig_document(hits[-1]["version"], row=hits[-1]) if hits else None

    def is_rig_version(self, version: str) -> bool:
        """Whether ``version`` is a committed rig version."""
        if not isinstance(version, str) or not VERSION_PATTERN.fullmatch(version):
            return False
        return version in self.rig_catalog()["version"].to_pylist()

    def load_rig_document(self, version: str, *, row: Mapping | None = None) -> dict:
        """The rig document of a committed rig version (``row``: its ``rigs`` row, when known)."""
        check_version(version)
        if row is None:
            hits = [r for r in self.rig_catalog().to_pylist() if r["version"] == version]
            if not hits:
                raise LakeError(f"rig version {version} is not committed in {self.url}")
            row = hits[-1]
        try:
            return json.loads(self._store.read(row["document_path"]))
        except (OSError, ValueError) as e:
            raise LakeError(f"rig version {version}: cannot read its document: {reason(e)}") from None

    # -- reading --------------------------------------------------------------------------
    def catalog(self, *, as_of=None, filter=None, equal: Mapping | None = None,
                sort: bool = True) -> pa.Table:
        """Committed versions, one row each (``schemas/catalog.arrow.json``), oldest first.

        Parameters
        ----------
        as_of : str or datetime, optional
            The catalog as it was at that time (Delta time travel).
        filter : pyarrow.compute.Expression, optional
            Rows to keep.
        equal : mapping, optional
            ``{column: value}`` the rows kept must have: files whose statistics exclude it
            are not read (give ``filter`` too).
        sort : bool
            Order by commit time (False: file order, faster for a query that orders itself).
        """
        t = self.tables.scan("catalog", filter=filter, as_of=_as_of(as_of), equal=equal)
        if not sort or t.num_rows < 2:
            return t
        return t.take(pa.compute.sort_indices(t.select(["committed", "version"]),
                                              [("committed", "ascending"), ("version", "ascending")]))

    def _is_committed(self, version: str) -> bool:
        return self.catalog(filter=ds.field("version") == version,
                            equal={"version": version}).num_rows > 0

    def find_committed(self, fingerprint: str) -> str | None:
        """The latest committed version made from these inputs and settings, or None."""
        if not is_fingerprint(fingerprint):
            raise InputError(f"fingerprint must be 'sha256:' and 64 hex digits, got "
                             f"{fingerprint!r}", "find_committed")
        return self.committed_whole(fingerprint)[0]

    def committed_whole(self, fingerprint: str) -> tuple[str | None, dict[str, str]]:
        """``(version, broken)``: the latest committed version of these inputs whose parts read
        back whole (:func:`fieldcal.lake.check.read_back`), or None, and ``{version: reason}``
        of the later ones that do not (a folder removed, a partial restore). A rerun answers
        "unchanged" only with a whole version; otherwise it calibrates again and says why
        (the reasons are also kept in :attr:`not_whole`)."""
        from fieldcal.lake.check import read_back

        if not is_fingerprint(fingerprint):
            raise InputError(f"fingerprint must be 'sha256:' and 64 hex digits, got "
                             f"{fingerprint!r}", "find_committed")
        hits = self.catalog(filter=ds.field("fingerprint") == fingerprint,
                            equal={"fingerprint": fingerprint}).to_pylist()
        broken: dict[str, str] = {}
        for row in reversed(hits):
            why = read_back(self, row["version"], row["document_path"], row["zarr_path"])
            if why is None:
                return row["version"], broken
            broken[row["version"]] = why
            self.not_whole[row["version"]] = why
        return None, broken

    def whole(self, version: str, row: Mapping | None = None) -> str | None:
        """Why a committed version does not read back whole, or None when it does (``row``:
        its catalog row, when the caller has read it: ``document_path`` and ``zarr_path``)."""
        from fieldcal.lake.check import read_back

        row = row if row is not None else self.row(version)
        return read_back(self, version, row["document_path"], row["zarr_path"])

    def latest(self, camera_id: str, session_id: str | None = None) -> str | None:
        """A camera's latest version (of its sessions named ``session_id``), or None.

        "Latest" by :mod:`fieldcal.lake.order`: acquisition time, ties by commit order (not
        the last commit: a backfill or a forced rerun of an old session is not the latest)."""
        return order.latest(self.camera_rows(camera_id, session_id))

    def camera_rows(self, camera_id: str, session_id: str | None = None) -> list[dict]:
        """The catalog rows of a camera (of its sessions named ``session_id``) with the
        columns :mod:`fieldcal.lake.order` reads (:data:`fieldcal.lake.order.ROW_COLUMNS`)."""
        check_id(camera_id, "camera_id")
        f = ds.field("camera_id") == camera_id
        if session_id is not None:
            f = f & (ds.field("session_id") == check_id(session_id, "session_id"))
        return self.catalog(filter=f, equal={"camera_id": camera_id}).select(list(order.ROW_COLUMNS)).to_pylist()

    def sessions_with_calibration(self) -> list[tuple[str, str]]:
        """(camera_id, session_id) of every session with at least one committed version."""
        t = self.tables.scan("catalog", columns=["camera_id", "session_id"])
        return sorted(set(zip(t["camera_id"].to_pylist(), t["session_id"].to_pylist(), strict=True)))

    def row(self, version: str) -> dict:
        """The catalog row of a committed version as a dict."""
        check_version(version)
        rows = self.catalog(filter=ds.field("version") == version, equal={"version": version}).to_pylist()
        if not rows:
            raise LakeError(f"version {version} is not committed in {self.url}")
        return rows[-1]

    def load_document(self, version: str) -> dict:
        """The calibration document of a committed version."""
        rel = self.row(version)["document_path"]
        try:
            doc = json.loads(self._store.read(rel))
        except FileNotFoundError:
            raise LakeError(f"version {version}: its document {self.uri(rel)} is missing") from None
        except (OSError, ValueError) as e:
            raise LakeError(f"version {version}: cannot read {self.uri(rel)}: {reason(e)}") from None
        if not isinstance(doc, dict) or doc.get("version") != version:
            raise LakeError(f"version {version}: {self.uri(rel)} is not its document")
        return doc

    def open_zarr(self, version: str, *, verify: bool = True):
        """The Zarr v3 group of a committed version, read-only (:data:`KNOWN_ARRAYS`).

        With ``verify`` every array is read and checked against the SHA-256 recorded at
        the commit: a missing or damaged chunk is a :class:`LakeError` naming it (Zarr
        would read a missing chunk back as the fill value).
        """
        import zarr

        rel = self.row(version)["zarr_path"]
        try:
            group = zarr.open_group(store=self._store.zarr_store(rel, read_only=True), mode="r")
        except (OSError, FileNotFoundError, ValueError, KeyError) as e:
            raise LakeError(f"version {version}: cannot open {self.uri(rel)}: {reason(e)}") from None
        if verify:
            from fieldcal.lake.check import verify_group

            verify_group(self, rel, group, version)
        return group

    def read_residuals(self, version: str) -> pa.Table:
        """The residual table of a committed version (``schemas/residuals.arrow.json``)."""
        row = self.row(version)
        f = (ds.field("camera_id") == row["camera_id"]) & (ds.field("version") == version)
        n_before = len(self.problems)
        t = self.tables.scan("residuals", filter=f, partition={"camera_id": row["camera_id"]},
                             equal={"version": version})
        if len(self.problems) > n_before:
            raise LakeError(f"version {version}: residuals unreadable: {self.problems[-1]}")
        return t.drop_columns(["camera_id", "session_id", "version"])

    # -- observations cache ---------------------------------------------------------------
    def _observations(self, camera_id: str, session_id: str, *, refresh: bool) -> dict:
        """``{(image, key): (kind, table)}`` of a session's cached observations (memoised)."""
        check_id(camera_id, "camera_id")
        check_id(session_id, "session_id")
        k = (camera_id, session_id)
        if refresh or k not in self._obs_cache:
            self._obs_cache[k] = obs.load_session(self.tables, camera_id, session_id)
        return self._obs_cache[k]

    def cached_observations(self, camera_id: str, session_id: str) -> set[str]:
        """:func:`observations_key` of every image of a session with cached observations."""
        return {observations_key(i, k) for i, k in self.cached_keys(camera_id, session_id)}

    def cached_keys(self, camera_id: str, session_id: str) -> set[tuple[str, str]]:
        """``(image, key)`` of every image of a session with cached observations (read now)."""
        return set(self._observations(camera_id, session_id, refresh=True))

    def has_observations(self, camera_id: str, session_id: str, image_name: str,
                         content_sha256: str) -> bool:
        """Whether observations of this image content are cached (:func:`obs.has_key`, a
        key-only probe: re-reading a growing session for every image made the 72-image
        benchmark spend ~18 s in lookups, bench/README_flow.md; the flow now looks its
        images up once, in the plan, :attr:`fieldcal.batch.SessionPlan.present`)."""
        observations_key(image_name, content_sha256)
        if (image_name, content_sha256) in self._obs_cache.get((camera_id, session_id), {}):
            return True
        check_id(camera_id, "camera_id")
        check_id(session_id, "session_id")
        return obs.has_key(self.tables, camera_id, session_id, image_name, content_sha256)

    def write_observations(self, camera_id: str, session_id: str, image_name: str,
                           content_sha256: str, table: pa.Table) -> str:
        """Cache an image's observations (one Delta append); returns the table's name.

        ``table`` is a field image's measurements (``schemas/measurements.arrow.json``) or a
        goniometer frame's (:data:`fieldcal.contract.goniometer_schema.MEASUREMENT_SCHEMA`);
        the kind is told by the columns. Its schema metadata ``fieldcal.image_sha256``
        (the image's own hash) is kept.
        """
        return self.write_observations_many(camera_id, session_id, [(image_name, content_sha256, table)])[0]

    def write_observations_many(self, camera_id: str, session_id: str,
                                items: list[tuple[str, str, pa.Table]]) -> list[str]:
        """Cache several images' observations ``[(image, key, table)]`` of one session.

        One Delta append per observations table for all of them (a measuring task's
        images, not one commit per image); each image's rows are all there or none, as
        with :meth:`write_observations`. Every item is checked before anything is
        written. Returns the table name of each item.
        """
        check_id(camera_id, "camera_id")
        check_id(session_id, "session_id")
        for image_name, key, _ in items:
            observations_key(image_name, key)      # checks the name and the key
        per_item = [obs.rows_for(camera_id, session_id, image_name, key, table)
                    for image_name, key, table in items]
        kinds = [kind for kind, _ in per_item]
        for kind in dict.fromkeys(kinds):
            mine = [i for i, k in enumerate(kinds) if k == kind]
            self._append_observations(kind, pa.concat_tables([per_item[i][1] for i in mine]),
                                      camera_id, session_id, [items[i][0] for i in mine])
        cached = self._obs_cache.get((camera_id, session_id))
        if cached is not None:
            for (image_name, key, _), (kind, rows) in zip(items, per_item, strict=True):
                cached[(image_name, key)] = (kind, obs.strip(kind, rows))
        return kinds

    def _append_observations(self, kind: str, rows: pa.Table, camera_id: str, session_id: str,
                             images: list[str]) -> None:
        """One Delta append of observation rows, its commit naming the images (or their count)."""
        which = images[0] if len(images) == 1 else f"{len(images)} images"
        try:
            self.tables.append(kind, rows, {"action": "observations", "camera_id": camera_id,
                                            "session_id": session_id, "image": which, **_who()})
        except OSError as e:
            raise LakeError(f"cannot write {self.uri(kind)}: {reason(e)}") from None
        except (LakeError, InputError):
            raise
        except Exception as e:  # noqa: BLE001 - delta-rs errors are not OSErrors
            raise LakeError(f"cannot write {self.uri(kind)}: {reason(e)}") from None

    def read_observations(self, camera_id: str, session_id: str, image_name: str,
                          content_sha256: str) -> pa.Table | None:
        """An image's cached observations, or None when this image content has none."""
        observations_key(image_name, content_sha256)
        key = (image_name, content_sha256)
        hit = self._observations(camera_id, session_id, refresh=False).get(key)
        if hit is None:
            hit = self._observations(camera_id, session_id, refresh=True).get(key)
        return None if hit is None else hit[1]

    def sessions_with_observations(self) -> list[tuple[str, str]]:
        """(camera_id, session_id) of every session with cached observations."""
        out = set()
        for name in ("observations_field", "observations_goniometer"):
            t = self.tables.scan(name, columns=["camera_id", "session_id"])
            out |= set(zip(t["camera_id"].to_pylist(), t["session_id"].to_pylist(), strict=True))
        return sorted(out)

    # -- derived tables: comparisons and assessments ---------------------------------------
    def cached_comparisons(self, settings: str, versions_b=None) -> dict[tuple[str, str], dict]:
        """``{(version_a, version_b): result}`` remembered for these comparison settings.

        ``versions_b``: only pairs whose later version is one of these (only their results
        are decoded)."""
        if versions_b is None:
            t = self.tables.scan("comparisons", filter=ds.field("settings") == settings)
        else:                         # only the files and row groups that may hold them are read
            wanted = sorted(set(versions_b))
            t = self.tables.scan("comparisons", filter=(ds.field("settings") == settings)
                                 & ds.field("version_b").isin(wanted), equal={"version_b": wanted})
        return {(a, b): json.loads(r) for a, b, r in zip(t["version_a"].to_pylist(),
                                                         t["version_b"].to_pylist(),
                                                         t["result"].to_pylist(), strict=True)}

    def remember_comparisons(self, settings: str, results: Mapping) -> None:
        """Remember comparisons ``{(version_a, version_b): result}`` (one append); a lake that
        cannot be written is left alone (a cache)."""
        pairs = list(results)
        self._remember("comparisons", {
            "version_a": [a for a, _ in pairs], "version_b": [b for _, b in pairs],
            "settings": [settings] * len(pairs), "computed": [utcnow()] * len(pairs),
            "result": [json.dumps(results[p], default=_jsonable) for p in pairs]})

    def cached_assessments(self, settings: str, versions=None, *, brief: bool = False) -> dict[str, dict]:
        """``{version: result}`` of the ``assessments`` table for these settings (``versions``:
        only these). ``brief``: only ``camera_id``, ``verdict`` and ``radial`` of each (the
        ``result`` column, with every criterion, is not read)."""
        f = ds.field("settings") == settings
        equal = None
        if versions is not None:
            wanted = sorted(set(versions))
            f, equal = f & ds.field("version").isin(wanted), {"version": wanted}
        cols = ["version", "camera_id", "verdict", "radial"] if brief else None
        t = self.tables.scan("assessments", filter=f, equal=equal, columns=cols)
        if brief:
            return {v: {"camera_id": c, "verdict": d, "radial": json.loads(r) if r else None}
                    for v, c, d, r in zip(*(t[k].to_pylist() for k in cols), strict=True)}
        return {v: json.loads(r) for v, r in zip(t["version"].to_pylist(), t["result"].to_pylist(), strict=True)}

    def remember_assessments(self, settings: str, results: Mapping) -> None:
        """Remember assessments ``{version: result}`` (each result has ``camera_id`` and
        ``verdict``); one append, a lake that cannot be written is left alone."""
        versions = list(results)
        self._remember("assessments", {
            "version": versions, "camera_id": [results[v]["camera_id"] for v in versions],
            "settings": [settings] * len(versions), "computed": [utcnow()] * len(versions),
            "verdict": [results[v]["verdict"] for v in versions],
            "radial": [json.dumps(results[v].get("radial"), default=_jsonable) for v in versions],
            "result": [json.dumps(results[v], default=_jsonable) for v in versions]})

    def _remember(self, table: str, columns: dict) -> None:
        if not next(iter(columns.values())):
            return
        try:
            self.tables.append(table, pa.table(columns), {"action": table, **_who()})
        except Exception:  # noqa: BLE001, S110 - a cache: a read-only lake just computes again
            pass

    # -- maintenance ------------------------------------------------------------------------
    def gc(self, grace_s: float = 86400.0, *, dry_run: bool = False) -> list[str]:
        """Remove parts of versions that were never committed, older than ``grace_s`` [s].

        See :func:`fieldcal.lake.gc.gc`.
        """
        from fieldcal.lake.gc import gc

        return gc(self, grace_s, dry_run=dry_run)


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if hasattr(value, "isoformat"):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _as_of(value):
    """An ``as_of`` argument as an aware datetime (strings are ISO 8601; naive is UTC)."""
    if value is None or isinstance(value, int):
        return value
    return parse_time(value, "as of")


def _with_keys(res: pa.Table, doc: dict) -> pa.Table:
    n = res.num_rows
    keys = {"camera_id": pa.array([doc["camera_id"]] * n, pa.string()),
            "session_id": pa.array([doc["session_id"]] * n, pa.string()),
            "version": pa.array([doc["version"]] * n, pa.string())}
    return pa.table({**keys, **{c: res[c] for c in res.column_names}})


