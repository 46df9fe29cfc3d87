"""The lake of the first layout (fieldcal before the Delta lake), kept verbatim so that the
migration test can make a lake with the old code path. Not used by fieldcal itself.

Original docstring follows.


One root, a local path or an fsspec URL (``s3://bucket/prefix``), laid out so that a
person can browse it and DuckDB / pyarrow / zarr can read it without fieldcal::

    LAKE/observations/camera_id=C/session_id=S/<image-key>-<sha256>.parquet   one per image
    LAKE/residuals/camera_id=C/session_id=S/version=V/residuals.parquet       one per version
    LAKE/calibrations/C/S/V.zarr          Zarr v3 group: the arrays, the document in attrs
    LAKE/calibrations/C/S/V.json          the calibration document (CONTRACT section 4)
    LAKE/catalog/V.parquet                one row per version (schemas/catalog.arrow.json)
    LAKE/_claims/...                      commit claims (internal; see "Concurrency")

Version ids
-----------
``YYYYMMDDTHHMMSSZ-ffffffff-rrrr``: the commit time (UTC, to the second), the first 8 hex
digits of the inputs' fingerprint and 4 random hex digits. They sort by time to the
second; the catalog's ``committed`` column (microseconds) orders versions made within the
same second. A collision of the random part is detected by the version claim and retried.

Commit protocol
---------------
:meth:`Lake.commit` validates and serialises everything in memory first (nothing is
written when the document, the residual table or an array is bad), then writes the
residual table, the Zarr group and the JSON document, and last the catalog row
``catalog/V.parquet``. The catalog row *is* the commit: it is written under a temporary
name and hard-linked into place on a local filesystem (atomic and exclusive), and with a
single conditional PUT (``If-None-Match: *``) on an object store. Readers
(:meth:`Lake.catalog`, :mod:`fieldcal.lake.history`, :meth:`Lake.find_committed`) only see
versions with a catalog row; a crash before it leaves invisible garbage that a later
commit of the same version overwrites or :meth:`Lake.gc` removes. Committed versions are
immutable: committing into one is refused with :class:`LakeError`.

Concurrency
-----------
Several processes may commit to one lake at once. The catalog is one file per version, so
no row is ever lost. Two commits of the same fingerprint (same inputs and settings) must
not make two versions, so a non-forced commit first takes an exclusive *claim* on its
fingerprint: ``_claims/fingerprint/<hex>/<n>.json`` created exclusively (hard link of a
complete temporary file locally, conditional PUT on S3; moto and AWS S3 both honour
``If-None-Match: *``). The first committer holds claim 0; a concurrent committer of the
same fingerprint finds it taken, waits until the holder's version has its catalog row and
returns that version (``Committed.new`` is False). A holder that fails releases its claim
(rewrites it with ``"released": true``); a holder that crashed is recognised as gone when
it ran on this host and its process no longer exists, otherwise when its claim is older
than ``claim_timeout_s``; the next committer then creates claim ``n + 1`` (exclusively
again, so only one takes over). Each version is claimed the same way
(``_claims/version/V/<n>.json``) so that two commits can never write into one version.
Claims are a few hundred bytes and are kept (a fingerprint claim also protects later
commits against a race with a committed version); :meth:`Lake.gc` prunes version claims.

Limits: a local lake needs a filesystem with hard links (ext4, xfs, btrfs, tmpfs, NFS);
an object store must honour conditional PUTs (AWS S3, MinIO, moto do). A claim is judged
by process id only when it was made on the same host in the same process-id namespace;
a commit that runs longer than ``claim_timeout_s`` may be taken over, which it notices
before writing its catalog row (it then fails with :class:`LakeError`).

Errors
------
Bad arguments (document, arrays, tables, ids) raise :class:`~fieldcal.errors.InputError`
before anything is written. Storage failures (read-only destination, missing bucket,
network) raise :class:`~fieldcal.errors.LakeError` with a one-line reason; the failed
commit's claims are released and its partial files removed as far as possible, and it
never has a catalog row.
"""

from __future__ import annotations

import datetime as dt
import glob
import json
import math
import os
import posixpath
import re
import secrets
import shutil
import socket
import tempfile
import time
from collections.abc import Mapping

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from fieldcal.contract.fingerprint import code_version, is_fingerprint
from fieldcal.contract.schemas import arrow_schema, validate_json
from fieldcal.errors import InputError, LakeError
from fieldcal.model.camera import PARAM_NAMES, Sensor, correction

__all__ = [
    "Lake", "Committed", "new_version", "version_time", "observations_key",
    "KNOWN_ARRAYS", "CORRECTION_GRID",
]

UTC = dt.UTC
ID_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")
"""camera_id / session_id: the pattern of schemas/session.schema.json (safe in paths)."""
VERSION_PATTERN = re.compile(r"^(\d{8}T\d{6}Z)-([0-9a-f]{8})-([0-9a-f]{4})$")
SHA256_PATTERN = re.compile(r"^[0-9a-f]{64}$")
ARRAY_NAME_PATTERN = re.compile(r"^[A-Za-z0-9_]+(/[A-Za-z0-9_]+)*$")
PARTITION_KEYS = ("camera_id", "session_id", "version")

CORRECTION_GRID = (41, 31)
"""(n_u, n_v): grid of ``correction_field`` when the lake derives it (sensor corner to corner)."""

KNOWN_ARRAYS = {
    "parameters": "(13,) the parameters in fieldcal.model.camera.PARAM_NAMES order; attrs names. "
                  "Derived from the document when not given.",
    "sigma": "(13,) their a-posteriori sigmas, NaN where null; attrs names. Derived from the "
             "document when not given.",
    "covariance": "(n, n) a-posteriori covariance of the estimated parameters (units of "
                  "PARAM_NAMES); attrs names (n,) required unless n == 13.",
    "correlation": "(n, n) the correlation matrix; attrs names as for covariance.",
    "exterior/center_m": "(n_images, 3) [m] camera centres, rows in document images order. "
                         "Derived from a field document when not given.",
    "exterior/rotation_world_to_camera": "(n_images, 3, 3) rotation matrices. Derived from a "
                                         "field document when not given.",
    "exterior/sigma_center_m": "(n_images, 3) [m] sigmas of the centres, NaN where null. "
                               "Derived from a field document when not given.",
    "correction_field": "(ny, nx, 2) [px] the model's correction (dx, dy) of CONTRACT section 2 "
                        "at grid pixels, in pixels along u and v: (dx / d, -dy / d). Derived "
                        "from the parameters on a 41 x 31 grid when not given.",
    "grid_u_px": "(nx,) [px] column coordinates of the correction_field grid.",
    "grid_v_px": "(ny,) [px] row coordinates of the correction_field grid.",
}
"""The arrays a version's Zarr group holds, by name. Callers (the solvers) should give
``covariance`` and ``correlation`` with ``attrs={"names": [...]}``; the others are derived
from the document when absent. Any other named numeric array is stored as given."""


# --------------------------------------------------------------------------------------
# ids, keys and times
# --------------------------------------------------------------------------------------
def _utcnow() -> dt.datetime:
    return dt.datetime.now(UTC)


def _iso(t: dt.datetime) -> str:
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


def new_version(fingerprint: str, when: dt.datetime | None = None) -> str:
    """A fresh version id ``YYYYMMDDTHHMMSSZ-<fingerprint[:8]>-<4 random hex>``.

    Parameters
    ----------
    fingerprint : str
        ``"sha256:<64 hex>"`` of the inputs (:func:`fieldcal.contract.fingerprint.fingerprint`).
    when : datetime, optional
        The commit time (default: now); naive times are taken as UTC.
    """
    if not is_fingerprint(fingerprint):
        raise InputError(f"fingerprint must be 'sha256:' and 64 hex digits, got {fingerprint!r}",
                         "new_version")
    t = when or _utcnow()
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    stamp = t.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    return f"{stamp}-{fingerprint[7:15]}-{secrets.token_hex(2)}"


def version_time(version: str) -> dt.datetime:
    """The commit time (UTC, whole seconds) encoded in a version id."""
    m = VERSION_PATTERN.match(version or "")
    if not m:
        raise InputError(f"not a version id (YYYYMMDDTHHMMSSZ-xxxxxxxx-xxxx): {version!r}")
    return dt.datetime.strptime(m.group(1), "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC)


def observations_key(image_name: str, content_sha256: str) -> str:
    """The file stem of an image's cached observations: ``<image-key>-<sha256>``.

    ``image-key`` is the image name (session-relative path) with every character outside
    ``[A-Za-z0-9._-]`` replaced by ``_`` (so ``images/IMG_1.tif`` -> ``images_IMG_1.tif``);
    the full content hash follows, so the key changes whenever the image's bytes do.
    """
    if not isinstance(image_name, str) or not image_name:
        raise InputError(f"image name must be a non-empty string, got {image_name!r}",
                         "observations_key")
    if not isinstance(content_sha256, str) or not SHA256_PATTERN.match(content_sha256):
        raise InputError(f"content_sha256 must be 64 lower-case hex digits, got {content_sha256!r}",
                         "observations_key")
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", image_name).lstrip(".") or "_"
    return f"{stem}-{content_sha256}"


def _check_id(value, what: str) -> str:
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise InputError(f"{what} must match {ID_PATTERN.pattern} (letters, digits, '.', '_', "
                         f"'-'), got {value!r}", "lake")
    return value


def _parse_time(value, where: str) -> dt.datetime | None:
    """An ISO 8601 date or time (or date / datetime) as an aware UTC datetime; None stays None.

    A date alone is midnight UTC; a time without a zone is taken as UTC.
    """
    if value is None:
        return None
    if isinstance(value, dt.datetime):
        t = value
    elif isinstance(value, dt.date):
        t = dt.datetime(value.year, value.month, value.day)
    elif isinstance(value, str):
        try:
            t = dt.datetime.fromisoformat(value.strip())
        except ValueError:
            raise InputError(f"not an ISO 8601 date or time: {value!r}", where) from None
    else:
        raise InputError(f"expected an ISO 8601 date or time, got {type(value).__name__}", where)
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    return t.astimezone(UTC)


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (dt.datetime, dt.date)):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _plain_json(obj, where: str):
    """A deep copy of ``obj`` as plain JSON values (numpy -> Python); NaN / inf refused."""
    try:
        return json.loads(json.dumps(obj, default=_json_default, allow_nan=False))
    except ValueError as e:
        raise InputError(f"{e} (NaN and infinity have no JSON form; use null)", where) from None
    except TypeError as e:
        raise InputError(str(e), where) from None


def _parquet_bytes(table: pa.Table) -> bytes:
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, compression="zstd")
    return sink.getvalue().to_pybytes()


# --------------------------------------------------------------------------------------
# storage: a local directory or an fsspec filesystem
# --------------------------------------------------------------------------------------
class _Storage:
    """The few operations the lake needs, on a local directory or an fsspec URL.

    Local writes are atomic (temporary file + rename) and exclusive writes use a hard link
    of a complete temporary file (fails if the name exists). fsspec writes are single
    PUTs; exclusive ones are conditional (``mode="create"``, ``If-None-Match: *`` on S3).
    Listings on fsspec invalidate its directory cache first (other processes write too).
    """

    def __init__(self, url, storage_options=None):
        text = os.fspath(url)
        self.storage_options = dict(storage_options or {})
        if "://" in text and not text.startswith("file://"):
            import fsspec

            self.fs, root = fsspec.core.url_to_fs(text, **self.storage_options)
            self.root = root.rstrip("/")
            self.local = False
        else:
            if text.startswith("file://"):
                text = text[len("file://"):]
            self.fs = None
            self.root = os.path.abspath(text)
            self.local = True

    def path(self, rel: str) -> str:
        if self.local:
            return os.path.join(self.root, *rel.split("/")) if rel else self.root
        return f"{self.root}/{rel}" if rel else self.root

    def uri(self, rel: str) -> str:
        """A name other libraries understand: a local path, or a URL with the protocol."""
        return self.path(rel) if self.local else self.fs.unstrip_protocol(self.path(rel))

    def write(self, rel: str, data: bytes, *, exclusive: bool = False) -> None:
        """Write ``data`` atomically; with ``exclusive`` raise FileExistsError if ``rel`` exists."""
        if not self.local:
            self.fs.pipe_file(self.path(rel), data, mode="create" if exclusive else "overwrite")
            return
        final = self.path(rel)
        folder = os.path.dirname(final)
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(final)}.", suffix=".tmp",
                                   dir=folder)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            if exclusive:
                os.link(tmp, final)
            else:
                os.replace(tmp, final)
        finally:
            if os.path.lexists(tmp):
                os.unlink(tmp)

    def read(self, rel: str) -> bytes:
        if self.local:
            with open(self.path(rel), "rb") as f:
                return f.read()
        return self.fs.cat_file(self.path(rel))

    def exists(self, rel: str) -> bool:
        if self.local:
            return os.path.exists(self.path(rel))
        self.fs.invalidate_cache(self.path(rel))
        return self.fs.exists(self.path(rel))

    def listdir(self, rel: str) -> list[str]:
        """Names in a folder (sorted); [] when it does not exist."""
        p = self.path(rel)
        if self.local:
            try:
                return sorted(os.listdir(p))
            except (FileNotFoundError, NotADirectoryError):
                return []
        self.fs.invalidate_cache(p)
        try:
            return sorted(posixpath.basename(x.rstrip("/")) for x in self.fs.ls(p, detail=False))
        except FileNotFoundError:
            return []

    def glob(self, pattern: str) -> list[str]:
        """Relative names matching a glob pattern (``*`` within one level), sorted."""
        if self.local:
            return sorted(os.path.relpath(h, self.root).replace(os.sep, "/")
                          for h in glob.glob(self.path(pattern)))
        self.fs.invalidate_cache(self.root)
        hits = self.fs.glob(self.path(pattern))
        n = len(self.root) + 1
        return sorted(h.rstrip("/")[n:] for h in hits)

    def remove(self, rel: str) -> None:
        p = self.path(rel)
        if self.local:
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=False)
            elif os.path.lexists(p):
                os.unlink(p)
            return
        self.fs.invalidate_cache(p)
        if self.fs.exists(p):
            self.fs.rm(p, recursive=True)

    def zarr_store(self, rel: str, *, read_only: bool):
        import zarr

        if self.local:
            return zarr.storage.LocalStore(self.path(rel), read_only=read_only)
        return zarr.storage.FsspecStore.from_url(self.uri(rel),
                                                 storage_options=self.storage_options,
                                                 read_only=read_only)

    def read_tables(self, rels: list[str], schema: pa.Schema | None = None) -> pa.Table:
        import pyarrow.dataset as ds

        paths = [self.path(r) for r in rels]
        dataset = ds.dataset(paths, schema=schema, format="parquet",
                             filesystem=None if self.local else self.fs)
        return dataset.to_table()


def _host_id() -> str:
    """This host and process-id namespace: where a claim's pid can be checked."""
    try:
        ns = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        ns = 0
    return f"{socket.gethostname()}/{ns}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Committed(str):
    """A version id returned by :meth:`Lake.commit`.

    ``new`` is True when this call created the version, False when the same fingerprint
    was already committed (or was being committed concurrently) and that version is returned.
    """

    new: bool

    def __new__(cls, version: str, new: bool):
        obj = super().__new__(cls, version)
        obj.new = bool(new)
        return obj

    def __reduce__(self):
        return (Committed, (str(self), self.new))


# --------------------------------------------------------------------------------------
# the lake
# --------------------------------------------------------------------------------------
class Lake:
    """A versioned calibration lake at a local path or an fsspec URL.

    Parameters
    ----------
    url_or_path : str or os.PathLike
        ``/data/lake``, ``file:///data/lake`` or ``s3://bucket/prefix`` (any fsspec URL).
    storage_options : dict, optional
        fsspec options, e.g. ``{"endpoint_url": ..., "key": ..., "secret": ...}`` for s3fs.
    claim_timeout_s : float
        Age after which another host's unfinished commit claim counts as abandoned [s].
    poll_s : float
        Polling interval while waiting for a concurrent commit of the same inputs [s].
    """

    def __init__(self, url_or_path, storage_options=None, *, claim_timeout_s: float = 600.0,
                 poll_s: float = 0.2):
        self._store = _Storage(url_or_path, storage_options)
        self.url = self._store.uri("")
        self.claim_timeout_s = float(claim_timeout_s)
        self.poll_s = float(poll_s)

    def __repr__(self) -> str:
        return f"Lake({self.url!r})"

    # -- properties other modules use (history) -------------------------------------------
    @property
    def is_local(self) -> bool:
        """True for a lake on the local filesystem."""
        return self._store.local

    @property
    def fs(self):
        """The fsspec filesystem of a remote lake (None for a local one)."""
        return self._store.fs

    def uri(self, rel: str) -> str:
        """A path inside the lake as a local path or URL (for DuckDB, pyarrow, zarr)."""
        return self._store.uri(rel)

    def glob(self, pattern: str) -> list[str]:
        """Lake-relative paths matching a glob pattern."""
        try:
            return self._store.glob(pattern)
        except OSError as e:
            raise LakeError(f"cannot list {self.uri(pattern)}: {_reason(e)}") from None

    # -- layout ---------------------------------------------------------------------------
    @staticmethod
    def _paths(camera_id: str, session_id: str, version: str) -> dict[str, str]:
        return {
            "residuals": f"residuals/camera_id={camera_id}/session_id={session_id}/"
                         f"version={version}/residuals.parquet",
            "zarr": f"calibrations/{camera_id}/{session_id}/{version}.zarr",
            "document": f"calibrations/{camera_id}/{session_id}/{version}.json",
            "catalog": f"catalog/{version}.parquet",
        }

    # -- commit ---------------------------------------------------------------------------
    def commit(self, document: Mapping, arrays: Mapping | None = None, residuals=None, *,
               force: bool = False, acquired=None,
               array_attrs: Mapping[str, Mapping] | None = None) -> Committed:
        """Store one immutable version: residuals, Zarr arrays, document, then the catalog row.

        Parameters
        ----------
        document : mapping
            The calibration document (CONTRACT section 4). ``version`` may be absent, null
            or empty (a new id is made) or a version id to write (refused if committed);
            ``created`` defaults to now; ``code_version`` is added; ``acquired`` (the
            session's acquisition date or time, an extra key) feeds the catalog. Validated
            against ``schemas/calibration.schema.json``.
        arrays : mapping of str to array_like, optional
            Named arrays for the Zarr group (:data:`KNOWN_ARRAYS`); names may contain ``/``
            for subgroups. Missing derivable arrays are made from the document.
        residuals : pyarrow.Table or mapping of columns
            The residual table (``schemas/residuals.arrow.json``): missing nullable columns
            are filled with nulls, extra columns are kept after the schema's.
        force : bool
            Make a new version even when the same fingerprint is already committed.
        acquired : str, date or datetime, optional
            Overrides the document's ``acquired``.
        array_attrs : mapping of str to dict, optional
            Zarr attributes per array name (e.g. ``{"covariance": {"names": [...]}}``).

        Returns
        -------
        Committed
            The version id (a ``str``); ``.new`` is False when an existing version of the
            same fingerprint was returned instead of making another.

        Raises
        ------
        InputError
            A bad document, table or array (nothing is written).
        LakeError
            The lake cannot be written, or the version is already committed.
        """
        now = _utcnow()
        doc, explicit = self._prepare_document(document, now, acquired)
        where = f"calibration {doc['camera_id']}/{doc['session_id']}"
        res_bytes = _parquet_bytes(_conform_residuals(residuals, where))
        zarr_arrays = _prepare_arrays(doc, arrays or {}, array_attrs or {}, where)
        fp = doc["inputs"]["fingerprint"]
        # the catalog row is checked now, with the provisional version, so that a bad
        # value fails before anything is written
        _catalog_row(doc, now, force, self._paths(doc["camera_id"], doc["session_id"],
                                                  doc["version"]), where)

        claims: list[str] = []
        written: list[str] = []
        done = False
        try:
            if not force:
                existing = self.find_committed(fp)
                if existing is not None:
                    return Committed(existing, new=False)
            version = self._claim_version(doc["version"] if explicit else None, fp, now, claims)
            if not force:
                fp_claim, holder = self._claim("fingerprint", fp[7:], version, wait=True)
                if fp_claim is None:
                    if self._is_committed(holder["version"]):
                        return Committed(holder["version"], new=False)
                    raise LakeError(f"timed out waiting for a concurrent commit of {fp[:15]}... "
                                    f"(version {holder['version']}, pid {holder.get('pid')} on "
                                    f"{holder.get('host')}) in {self.url}")
                claims.append(fp_claim)
            doc["version"] = version
            paths = self._paths(doc["camera_id"], doc["session_id"], version)
            doc_bytes = json.dumps(doc, indent=2).encode("utf-8")

            written.append(paths["residuals"])
            self._store.write(paths["residuals"], res_bytes)
            written.append(paths["zarr"])
            self._write_zarr(paths["zarr"], zarr_arrays, doc)
            written.append(paths["document"])
            self._store.write(paths["document"], doc_bytes)
            if not force and not self._holds(claims[-1]):
                raise LakeError(f"the claim on fingerprint {fp[:15]}... was taken over by another "
                                f"commit (this one took longer than claim_timeout_s="
                                f"{self.claim_timeout_s:g} s); version {version} not committed")
            row = _catalog_row(doc, _utcnow(), force, paths, where)
            self._write_catalog_row(paths["catalog"], _parquet_bytes(row))
            done = True
            return Committed(version, new=True)
        except OSError as e:
            raise LakeError(f"cannot commit to {self.url}: {_reason(e)}") from None
        finally:
            if not done:
                for rel in written:
                    try:
                        self._store.remove(rel)
                    except Exception:  # noqa: BLE001 - best effort; gc() removes what is left
                        pass
                for rel in claims:
                    self._release(rel)

    def _claim_version(self, version: str | None, fp: str, now, claims: list) -> str:
        """Claim an explicit version, or a fresh one (retrying on a random-part collision)."""
        for _ in range(32):
            candidate = version or new_version(fp, now)
            rel, holder = self._claim("version", candidate, candidate, wait=False)
            if rel is not None:
                claims.append(rel)
                return candidate
            if version is None:
                continue
            if self._is_committed(version):
                raise LakeError(f"version {version} is already committed in {self.url}; "
                                "versions are immutable")
            raise LakeError(f"version {version} is being written by another commit "
                            f"(pid {holder.get('pid')} on {holder.get('host')}) in {self.url}")
        raise LakeError(f"could not find a free version id for {fp[:15]}... in {self.url}")

    def _write_catalog_row(self, rel: str, data: bytes) -> None:
        """The commit point: create ``catalog/V.parquet`` exclusively and atomically."""
        try:
            self._store.write(rel, data, exclusive=True)
        except FileExistsError:
            raise LakeError(f"{rel} already exists in {self.url}; versions are immutable") from None

    def _prepare_document(self, document, now, acquired):
        if not isinstance(document, Mapping):
            raise InputError(f"the calibration document must be a mapping, got "
                             f"{type(document).__name__}", "commit")
        doc = _plain_json(dict(document), "calibration document")
        where = f"calibration document {doc.get('camera_id')}/{doc.get('session_id')}"
        fp = (doc.get("inputs") or {}).get("fingerprint") if isinstance(doc.get("inputs"), dict) \
            else None
        if not is_fingerprint(fp):
            raise InputError(f"inputs.fingerprint must be 'sha256:' and 64 hex digits, got {fp!r}",
                             where)
        version = doc.get("version")
        explicit = version not in (None, "")
        if explicit:
            if not isinstance(version, str) or not VERSION_PATTERN.match(version):
                raise InputError(f"version must look like YYYYMMDDTHHMMSSZ-xxxxxxxx-xxxx, got "
                                 f"{version!r}", where)
        else:
            version = new_version(fp, now)  # provisional; the commit claims the final one
        doc["version"] = version
        if doc.get("created") in (None, ""):
            doc["created"] = _iso(now.replace(microsecond=0))
        doc.setdefault("code_version", code_version())
        if acquired is not None:
            t = _parse_time(acquired, where)
            doc["acquired"] = acquired if isinstance(acquired, str) else _iso(t)
        validate_json(doc, "calibration", where)
        _parse_time(doc["created"], f"{where}: created")
        _parse_time(doc.get("acquired"), f"{where}: acquired")
        return doc, explicit

    def _write_zarr(self, rel: str, arrays: dict, doc: dict) -> None:
        import zarr

        store = self._store.zarr_store(rel, read_only=False)
        try:
            group = zarr.open_group(store=store, mode="w", zarr_format=3)
            group.attrs.update({"document": doc, "arrays": sorted(arrays)})
            for name, (data, attrs, dims) in arrays.items():
                group.create_array(name, data=data, attributes=attrs, dimension_names=dims)
        finally:
            store.close()

    # -- claims ---------------------------------------------------------------------------
    def _claim(self, kind: str, key: str, version: str, *, wait: bool):
        """Take the exclusive claim ``_claims/kind/key``; see the module docstring.

        Returns ``(rel, None)`` when taken, or ``(None, holder)`` when the current holder's
        version is committed, or is alive and ``wait`` is False (or waiting timed out).
        """
        folder = f"_claims/{kind}/{key}"
        deadline = time.monotonic() + 2.0 * self.claim_timeout_s + 10.0 * self.poll_s
        while True:
            seqs = sorted(int(n[:-5]) for n in self._store.listdir(folder)
                          if re.fullmatch(r"\d{6}\.json", n))
            n = 0
            if seqs:
                holder = self._read_claim(f"{folder}/{seqs[-1]:06d}.json")
                if holder is not None and self._is_committed(holder["version"]):
                    return None, holder
                if holder is not None and not self._claim_abandoned(holder):
                    if not wait or time.monotonic() > deadline:
                        return None, holder
                    time.sleep(self.poll_s)
                    continue
                n = seqs[-1] + 1
            rel = f"{folder}/{n:06d}.json"
            payload = {"version": version, "host": _host_id(), "pid": os.getpid(),
                       "time": time.time(), "released": False}
            try:
                self._store.write(rel, json.dumps(payload).encode(), exclusive=True)
            except FileExistsError:
                continue
            return rel, None

    def _read_claim(self, rel: str) -> dict | None:
        try:
            payload = json.loads(self._store.read(rel))
        except (FileNotFoundError, ValueError):
            return None
        if not isinstance(payload, dict) or not isinstance(payload.get("version"), str):
            return None
        return payload

    def _claim_abandoned(self, holder: dict) -> bool:
        if holder.get("released"):
            return True
        if holder.get("host") == _host_id() and isinstance(holder.get("pid"), int) \
                and not _pid_alive(holder["pid"]):
            return True
        return time.time() - float(holder.get("time", 0.0)) > self.claim_timeout_s

    def _holds(self, rel: str) -> bool:
        folder, name = rel.rsplit("/", 1)
        seqs = [n for n in self._store.listdir(folder) if re.fullmatch(r"\d{6}\.json", n)]
        return bool(seqs) and max(seqs) == name

    def _release(self, rel: str) -> None:
        try:
            payload = self._read_claim(rel) or {}
            payload["released"] = True
            self._store.write(rel, json.dumps(payload).encode())
        except Exception:  # noqa: BLE001 - best effort; an unreleased claim times out
            pass

    # -- reading --------------------------------------------------------------------------
    def _is_committed(self, version: str) -> bool:
        return self._store.exists(f"catalog/{version}.parquet")

    def _catalog_files(self, fp8: str | None = None) -> list[str]:
        try:
            names = self._store.listdir("catalog")
        except OSError as e:
            raise LakeError(f"cannot list {self.uri('catalog')}: {_reason(e)}") from None
        out = []
        for name in names:
            if not name.endswith(".parquet"):
                continue
            m = VERSION_PATTERN.match(name[:-len(".parquet")])
            if m and (fp8 is None or m.group(2) == fp8):
                out.append(f"catalog/{name}")
        return out

    def _read_catalog(self, rels: list[str]) -> pa.Table:
        schema = arrow_schema("catalog")
        if not rels:
            return schema.empty_table()
        try:
            table = self._store.read_tables(rels, schema)
        except (OSError, pa.ArrowException) as e:
            raise LakeError(f"cannot read the catalog of {self.url}: {_reason(e)}") from None
        return table.sort_by([("committed", "ascending"), ("version", "ascending")])

    def catalog(self) -> pa.Table:
        """All committed versions, one row each (``schemas/catalog.arrow.json``), oldest first.

        An empty lake (or a root that does not exist yet) gives an empty table with the
        catalog's columns.
        """
        return self._read_catalog(self._catalog_files())

    def find_committed(self, fingerprint: str) -> str | None:
        """The latest committed version made from these inputs and settings, or None."""
        if not is_fingerprint(fingerprint):
            raise InputError(f"fingerprint must be 'sha256:' and 64 hex digits, got "
                             f"{fingerprint!r}", "find_committed")
        table = self._read_catalog(self._catalog_files(fp8=fingerprint[7:15]))
        hits = [v for v, f in zip(table["version"].to_pylist(), table["fingerprint"].to_pylist(),
                                  strict=True) if f == fingerprint]
        return hits[-1] if hits else None

    def latest(self, camera_id: str, session_id: str | None = None) -> str | None:
        """The most recently committed version of a camera (of one session), or None."""
        _check_id(camera_id, "camera_id")
        if session_id is not None:
            _check_id(session_id, "session_id")
        rows = self.catalog().select(["camera_id", "session_id", "version"]).to_pylist()
        hits = [r["version"] for r in rows if r["camera_id"] == camera_id
                and (session_id is None or r["session_id"] == session_id)]
        return hits[-1] if hits else None

    def sessions_with_calibration(self) -> list[tuple[str, str]]:
        """(camera_id, session_id) of every session with at least one committed version."""
        t = self.catalog()
        return sorted(set(zip(t["camera_id"].to_pylist(), t["session_id"].to_pylist(),
                              strict=True)))

    def sessions_with_observations(self) -> list[tuple[str, str]]:
        """(camera_id, session_id) of every session with cached observations."""
        out = set()
        for rel in self.glob("observations/camera_id=*/session_id=*"):
            _, cam, ses = rel.split("/")
            out.add((cam[len("camera_id="):], ses[len("session_id="):]))
        return sorted(out)

    def row(self, version: str) -> dict:
        """The catalog row of a committed version as a dict."""
        version_time(version)  # checks the form
        rel = f"catalog/{version}.parquet"
        try:
            data = self._store.read(rel)
        except FileNotFoundError:
            raise LakeError(f"version {version} is not committed in {self.url}") from None
        except OSError as e:
            raise LakeError(f"cannot read {self.uri(rel)}: {_reason(e)}") from None
        return pq.read_table(pa.BufferReader(data)).to_pylist()[0]

    def load_document(self, version: str) -> dict:
        """The calibration document of a committed version."""
        rel = self.row(version)["document_path"]
        try:
            return json.loads(self._store.read(rel))
        except (OSError, ValueError) as e:
            raise LakeError(f"cannot read {self.uri(rel)}: {_reason(e)}") from None

    def open_zarr(self, version: str):
        """The Zarr v3 group of a committed version, read-only (:data:`KNOWN_ARRAYS`)."""
        import zarr

        rel = self.row(version)["zarr_path"]
        try:
            return zarr.open_group(store=self._store.zarr_store(rel, read_only=True), mode="r")
        except (OSError, FileNotFoundError) as e:
            raise LakeError(f"cannot open {self.uri(rel)}: {_reason(e)}") from None

    def read_residuals(self, version: str) -> pa.Table:
        """The residual table of a committed version."""
        rel = self.row(version)["residuals_path"]
        try:
            return pq.read_table(pa.BufferReader(self._store.read(rel)))
        except (OSError, pa.ArrowException) as e:
            raise LakeError(f"cannot read {self.uri(rel)}: {_reason(e)}") from None

    # -- observations cache ---------------------------------------------------------------
    def observations_path(self, camera_id: str, session_id: str, image_name: str,
                          content_sha256: str) -> str:
        """Lake-relative path of an image's cached observations."""
        _check_id(camera_id, "camera_id")
        _check_id(session_id, "session_id")
        key = observations_key(image_name, content_sha256)
        return f"observations/camera_id={camera_id}/session_id={session_id}/{key}.parquet"

    def has_observations(self, camera_id: str, session_id: str, image_name: str,
                         content_sha256: str) -> bool:
        """Whether observations of this image content are cached."""
        rel = self.observations_path(camera_id, session_id, image_name, content_sha256)
        try:
            return self._store.exists(rel)
        except OSError as e:
            raise LakeError(f"cannot read {self.uri(rel)}: {_reason(e)}") from None

    def write_observations(self, camera_id: str, session_id: str, image_name: str,
                           content_sha256: str, table: pa.Table) -> str:
        """Cache an image's observations (atomic); returns the lake-relative path.

        ``table`` is whatever the measuring step produced (any columns except the
        partition keys ``camera_id``, ``session_id``, ``version``); the image name and
        content hash are stored in the file's schema metadata.
        """
        rel = self.observations_path(camera_id, session_id, image_name, content_sha256)
        if not isinstance(table, pa.Table):
            raise InputError(f"observations must be a pyarrow.Table, got {type(table).__name__}",
                             image_name)
        clash = set(table.column_names) & set(PARTITION_KEYS)
        if clash:
            raise InputError(f"observation columns {sorted(clash)} clash with the lake's "
                             "partition keys", image_name)
        meta = dict(table.schema.metadata or {})
        meta.update({b"fieldcal.image": image_name.encode(),
                     b"fieldcal.content_sha256": content_sha256.encode()})
        try:
            self._store.write(rel, _parquet_bytes(table.replace_schema_metadata(meta)))
        except OSError as e:
            raise LakeError(f"cannot write {self.uri(rel)}: {_reason(e)}") from None
        return rel

    def read_observations(self, camera_id: str, session_id: str, image_name: str,
                          content_sha256: str) -> pa.Table | None:
        """An image's cached observations, or None when this image content has none."""
        rel = self.observations_path(camera_id, session_id, image_name, content_sha256)
        try:
            data = self._store.read(rel)
        except FileNotFoundError:
            return None
        except OSError as e:
            raise LakeError(f"cannot read {self.uri(rel)}: {_reason(e)}") from None
        table = pq.read_table(pa.BufferReader(data))
        meta = table.schema.metadata or {}
        if meta.get(b"fieldcal.image", image_name.encode()) != image_name.encode():
            return None  # another image name with the same key and content
        return table

    # -- garbage collection ---------------------------------------------------------------
    def gc(self, grace_s: float = 86400.0, *, dry_run: bool = False) -> list[str]:
        """Remove uncommitted leftovers of failed commits older than ``grace_s`` [s].

        Leftovers are version parts (residuals, Zarr group, document) without a catalog
        row, whose version id is older than ``grace_s``, local temporary files older than
        ``grace_s``, and version claims of committed or old versions. ``grace_s`` must
        exceed the longest commit in progress (default one day). Returns the removed
        lake-relative paths (with ``dry_run`` only lists them).
        """
        if not (grace_s >= 0):
            raise InputError(f"grace_s must be >= 0, got {grace_s}", "gc")
        now = _utcnow()
        committed = {r[len("catalog/"):-len(".parquet")] for r in self._catalog_files()}

        def old_uncommitted(version: str) -> bool:
            if version in committed or not VERSION_PATTERN.match(version):
                return False
            return (now - version_time(version)).total_seconds() > grace_s

        doomed = []
        for rel in self.glob("calibrations/*/*/*"):
            name = rel.rsplit("/", 1)[1]
            stem = name.rsplit(".", 1)[0]
            if name.endswith((".zarr", ".json")) and old_uncommitted(stem):
                doomed.append(rel)
        for rel in self.glob("residuals/camera_id=*/session_id=*/version=*"):
            if old_uncommitted(rel.rsplit("=", 1)[1]):
                doomed.append(rel)
        for rel in self.glob("_claims/version/*"):
            version = rel.rsplit("/", 1)[1]
            if version in committed or old_uncommitted(version):
                doomed.append(rel)
        if self.is_local:
            cutoff = time.time() - grace_s
            for top in ("catalog", "calibrations", "residuals", "observations", "_claims"):
                for folder, _, files in os.walk(self._store.path(top)):
                    for name in files:
                        p = os.path.join(folder, name)
                        if name.startswith(".") and name.endswith(".tmp") \
                                and os.path.getmtime(p) < cutoff:
                            doomed.append(os.path.relpath(p, self._store.root).replace(os.sep, "/"))
        if not dry_run:
            for rel in doomed:
                try:
                    self._store.remove(rel)
                except FileNotFoundError:
                    pass
                except OSError as e:
                    raise LakeError(f"cannot remove {self.uri(rel)}: {_reason(e)}") from None
        return doomed


# --------------------------------------------------------------------------------------
# preparing the parts of a version
# --------------------------------------------------------------------------------------
def _reason(e: BaseException) -> str:
    """One line describing an exception."""
    if isinstance(e, OSError) and e.strerror:
        text = e.strerror
    else:
        text = str(e) or type(e).__name__
    return " ".join(text.split())


def _conform_residuals(residuals, where: str) -> pa.Table:
    """Check the residual table against ``schemas/residuals.arrow.json`` and cast it."""
    schema = arrow_schema("residuals")
    where = f"{where}: residuals"
    if residuals is None:
        raise InputError("a residual table is required (it may have no rows)", where)
    if isinstance(residuals, Mapping):
        try:
            residuals = pa.table(dict(residuals))
        except (pa.ArrowException, TypeError, ValueError) as e:
            raise InputError(f"cannot make a table of the columns: {e}", where) from None
    if not isinstance(residuals, pa.Table):
        raise InputError(f"expected a pyarrow.Table, got {type(residuals).__name__}", where)
    clash = set(residuals.column_names) & set(PARTITION_KEYS)
    if clash:
        raise InputError(f"columns {sorted(clash)} are partition keys of the lake", where)
    n = residuals.num_rows
    columns, fields = [], []
    for f in schema:
        if f.name in residuals.column_names:
            col = residuals[f.name]
            try:
                col = col.cast(f.type)
            except (pa.ArrowException, ValueError) as e:
                raise InputError(f"column {f.name!r} ({col.type}) cannot be read as {f.type}: "
                                 f"{_reason(e)}", where) from None
        elif f.nullable:
            col = pa.nulls(n, f.type)
        else:
            raise InputError(f"column {f.name!r} is missing", where)
        if not f.nullable and col.null_count:
            raise InputError(f"column {f.name!r} has {col.null_count} null value(s)", where)
        columns.append(col)
        fields.append(f)
    for name in residuals.column_names:
        if name not in schema.names:
            columns.append(residuals[name])
            fields.append(residuals.schema.field(name))
    table = pa.Table.from_arrays(columns, schema=pa.schema(fields, metadata=schema.metadata))
    used = np.asarray(table["used"].to_numpy(zero_copy_only=False), dtype=bool)
    has_reason = np.asarray(table["reason"].is_valid().to_numpy(zero_copy_only=False), dtype=bool)
    bad = np.flatnonzero(used == has_reason)
    if bad.size:
        i = int(bad[0])
        raise InputError(f"row {i}: reason must be null exactly when used is true "
                         f"(used={bool(used[i])}, reason={table['reason'][i].as_py()!r}); "
                         f"{bad.size} such row(s)", where)
    axis = table["axis"].drop_null().to_pylist()
    if any(a not in ("x", "y") for a in axis):
        raise InputError(f"axis must be 'x', 'y' or null, got {sorted(set(axis) - {'x', 'y'})}",
                         where)
    return table


def _as_array(name: str, value, where: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise InputError(f"array {name!r} must be numeric or boolean, got dtype {arr.dtype}", where)
    return arr


def _prepare_arrays(doc: dict, arrays: Mapping, array_attrs: Mapping, where: str) -> dict:
    """``{name: (ndarray, attrs, dimension_names)}`` for the Zarr group of a version."""
    where = f"{where}: arrays"
    for name in list(arrays) + list(array_attrs):
        if not isinstance(name, str) or not ARRAY_NAME_PATTERN.match(name):
            raise InputError(f"array name {name!r} must be words of [A-Za-z0-9_] joined by '/'",
                             where)
    unknown_attrs = set(array_attrs) - set(arrays) - set(KNOWN_ARRAYS)
    if unknown_attrs:
        raise InputError(f"attributes given for arrays that are not given: {sorted(unknown_attrs)}",
                         where)
    out: dict[str, tuple] = {}
    given = {name: _as_array(name, value, where) for name, value in arrays.items()}
    names13 = list(PARAM_NAMES)

    def put(name, arr, attrs=None, dims=None):
        a = dict(attrs or {})
        a.update(_plain_json(dict(array_attrs.get(name, {})), f"{where}: attrs of {name}"))
        out[name] = (np.ascontiguousarray(arr), a, dims)

    # parameters and sigma
    params = given.pop("parameters", None)
    if params is None:
        params = np.array([doc["parameters"][n] for n in names13], dtype=float)
    sigma = given.pop("sigma", None)
    if sigma is None:
        sigma = np.array([np.nan if doc["sigma"][n] is None else doc["sigma"][n] for n in names13],
                         dtype=float)
    for name, arr in (("parameters", params), ("sigma", sigma)):
        if arr.shape != (13,):
            raise InputError(f"array {name!r} must have shape (13,), got {arr.shape}", where)
        put(name, arr, {"names": names13}, ("parameter",))

    # covariance and correlation
    for name in ("covariance", "correlation"):
        arr = given.pop(name, None)
        if arr is None:
            continue
        if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
            raise InputError(f"array {name!r} must be square (n, n), got {arr.shape}", where)
        labels = array_attrs.get(name, {}).get("names")
        if labels is None and arr.shape[0] == 13:
            labels = names13
        if labels is None or len(labels) != arr.shape[0]:
            raise InputError(f"array {name!r} of shape {arr.shape} needs attrs 'names' with "
                             f"{arr.shape[0]} entries (array_attrs={{{name!r}: {{'names': "
                             "[...]}}})", where)
        put(name, arr, {"names": list(labels)}, ("row", "col"))

    # exterior orientations
    images = doc.get("images") or []
    files = [im.get("file") for im in images if isinstance(im, dict)]
    ext = {k: given.pop(k, None) for k in ("exterior/center_m", "exterior/rotation_world_to_camera",
                                            "exterior/sigma_center_m")}
    if doc["method"] == "field" and images:
        if ext["exterior/center_m"] is None:
            ext["exterior/center_m"] = np.array([im["center_m"] for im in images], dtype=float)
        if ext["exterior/rotation_world_to_camera"] is None:
            ext["exterior/rotation_world_to_camera"] = np.array(
                [im["rotation_world_to_camera"] for im in images], dtype=float)
        if ext["exterior/sigma_center_m"] is None:
            ext["exterior/sigma_center_m"] = np.array(
                [[np.nan] * 3 if im["sigma_center_m"] is None else
                 [np.nan if s is None else s for s in im["sigma_center_m"]] for im in images],
                dtype=float)
    shapes = {"exterior/center_m": (3,), "exterior/rotation_world_to_camera": (3, 3),
              "exterior/sigma_center_m": (3,)}
    for name, arr in ext.items():
        if arr is None:
            continue
        if arr.shape[1:] != shapes[name] or arr.shape[0] != len(files):
            raise InputError(f"array {name!r} must have shape ({len(files)}, "
                             f"{', '.join(map(str, shapes[name]))}) for the document's "
                             f"{len(files)} images, got {arr.shape}", where)
        dims = ("image", "xyz") if arr.ndim == 2 else ("image", "row", "col")
        put(name, arr, {"images": files}, dims)

    # the correction field over the sensor
    field = given.pop("correction_field", None)
    grid_u = given.pop("grid_u_px", None)
    grid_v = given.pop("grid_v_px", None)
    if field is None:
        if grid_u is not None or grid_v is not None:
            raise InputError("grid_u_px / grid_v_px given without correction_field", where)
        s = doc["sensor"]
        sensor = Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"]))
        grid_u = np.linspace(0.0, sensor.width_px - 1.0, CORRECTION_GRID[0])
        grid_v = np.linspace(0.0, sensor.height_px - 1.0, CORRECTION_GRID[1])
        uv = np.stack(np.meshgrid(grid_u, grid_v), axis=-1)
        d_mm = correction(sensor.pixel_to_mm(uv), np.asarray(out["parameters"][0], dtype=float))
        field = np.stack([d_mm[..., 0], -d_mm[..., 1]], axis=-1) / sensor.pixel_mm
    if grid_u is None or grid_v is None:
        raise InputError("correction_field needs grid_u_px (nx,) and grid_v_px (ny,)", where)
    if grid_u.ndim != 1 or grid_v.ndim != 1 or field.shape != (grid_v.size, grid_u.size, 2):
        raise InputError(f"correction_field must have shape (ny, nx, 2) = ({grid_v.size}, "
                         f"{grid_u.size}, 2) for the grids given, got {field.shape}", where)
    put("correction_field", field,
        {"units": "px", "components": ["du_px", "dv_px"],
         "doc": "model correction (dx, dy) at grid pixels in pixels along u and v: "
                "(dx / d, -dy / d)"}, ("v", "u", "component"))
    put("grid_u_px", grid_u, {"units": "px"}, ("u",))
    put("grid_v_px", grid_v, {"units": "px"}, ("v",))

    for name, arr in given.items():  # anything else, as given
        put(name, arr)
    return out


def _num(value):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if math.isfinite(value) else None


def _count(value):
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, (list, dict)):
        return len(value)
    return None


def _catalog_row(doc: dict, committed: dt.datetime, forced: bool, paths: dict,
                 where: str) -> pa.Table:
    """The one-row catalog table of a version (``schemas/catalog.arrow.json``)."""
    stats = doc.get("stats") or {}
    fixed = stats.get("fixed_parameters")
    row = {
        "camera_id": doc["camera_id"], "session_id": doc["session_id"],
        "version": doc["version"], "method": doc["method"],
        "created": _parse_time(doc["created"], where),
        "committed": committed,
        "acquired": _parse_time(doc.get("acquired"), where),
        "fingerprint": doc["inputs"]["fingerprint"], "code_version": doc["code_version"],
        "forced": bool(forced), "model": doc["model"],
        "width_px": doc["sensor"]["width_px"], "height_px": doc["sensor"]["height_px"],
        "pixel_size_um": float(doc["sensor"]["pixel_size_um"]),
        "fixed_parameters": sorted(fixed) if isinstance(fixed, dict) else [],
        "rmse_px": _num(stats.get("rmse_px")), "max_px": _num(stats.get("max_px")),
        "sigma0": _num(stats.get("sigma0")), "sigma_fit_px": _num(stats.get("sigma_fit_px")),
        "n_images": _count(stats.get("n_images")) if _count(stats.get("n_images")) is not None
        else len(doc.get("images") or []),
        "n_targets": _count(stats.get("n_targets")),
        "n_observations": _count(stats.get("n_observations")),
        "n_rejected": _count(stats.get("n_rejected")),
        "n_frames": _count(stats.get("n_frames")), "n_angles": _count(stats.get("n_angles")),
        "iterations": _count(stats.get("iterations")),
        "solver": stats.get("solver") if isinstance(stats.get("solver"), str) else None,
        "targets_adjusted": stats.get("targets_adjusted")
        if isinstance(stats.get("targets_adjusted"), bool) else None,
        "document_path": paths["document"], "zarr_path": paths["zarr"],
        "residuals_path": paths["residuals"],
    }
    for name in PARAM_NAMES:
        row[name] = float(doc["parameters"][name])
        s = doc["sigma"][name]
        row["sigma_" + name] = None if s is None else float(s)
    try:
        return pa.Table.from_pylist([row], schema=arrow_schema("catalog"))
    except (pa.ArrowException, TypeError, ValueError) as e:
        raise InputError(f"cannot make the catalog row: {_reason(e)}", where) from None
