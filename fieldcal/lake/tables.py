"""The lake's Delta tables: their schemas, and every read and write of them.

Four tables, each a Delta Lake table (delta-rs through the ``deltalake`` package) in its
own folder of the lake, one schema each:

===========================  ===============  =====================================================
table                        partitioned by   rows
===========================  ===============  =====================================================
``catalog``                  (none)           one per committed version (the commit point)
``residuals``                ``camera_id``    per-observation residuals of every version
``observations_field``       ``camera_id``    targets measured in each field image (cache)
``observations_goniometer``  ``camera_id``    the spot of each goniometer frame (cache)
``comparisons``              (none)           the change test of two versions (derived)
``assessments``              (none)           the acceptance of each version (derived)
===========================  ===============  =====================================================

Writes are Delta commits: appends, an append *once* per key (the commit carries a Delta
transaction identifier, ``txn``, naming the key: a table that has it already is not
appended to, and of two concurrent commits carrying it Delta's conflict check fails the
second; :meth:`Tables.append`), an insert-unless-present (``MERGE ... WHEN NOT MATCHED
INSERT``, whose conflict check makes "one row per key" hold under concurrency), deletes.
A table created by this code carries the identifier :data:`EVERY_KEY_ONCE` from its
first commit: every key-once append it holds carries its key; a table from before gets it
from :meth:`Tables.adopt_keys` (with the keys of the rows it has).
Each carries the caller's commit metadata (code version, host, process, flow run) into the
table's history. Every ``maintain_every`` commits of a table, the commit that reaches the
multiple compacts the table's small files (``optimize.compact``), and every
:data:`CHECKPOINT_EVERY` delta-rs writes a checkpoint (``delta.checkpointInterval``), so
that reading stays fast as versions pile up.

Reads never let one bad file take a table down: a data file that cannot be read (zero
bytes, garbage, truncated) is skipped and reported as a :class:`Problem`; a damaged commit
file makes the table read as of its last readable version, also reported.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import os
import random
import time

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError, LakeError
from fieldcal.lake.parts import reason

__all__ = ["Tables", "Problem", "TABLES", "table_schema", "PARTITIONS", "DEFAULT_MAINTAIN_EVERY"]

TABLES = ("catalog", "residuals", "observations_field", "observations_goniometer", "comparisons", "assessments",
          "rigs")
PARTITIONS = {"catalog": [], "residuals": ["camera_id"], "observations_field": ["camera_id"],
              "observations_goniometer": ["camera_id"], "comparisons": [], "assessments": [], "rigs": []}
QUARANTINE = "quarantine"
"""The lake's folder of damaged files moved out of the way (by a writer or ``lake repair``)."""
DEFAULT_MAINTAIN_EVERY = 100
"""Commits of a table between compactions."""
CHECKPOINT_EVERY = 10
"""Commits of a table between checkpoints (at most ``maintain_every``): opening a table reads
its last checkpoint and every commit since, one request each on an object store (with 100,
a commit on moto S3 read up to ~200 commit files of the catalog and the residuals:
``bench/bench_commit.py``)."""
ROW_GROUP_ROWS = 4096
"""Rows per row group of the compacted catalog (pruned by their camera_id statistics)."""
SORTED_BY = {"catalog": "camera_id", "comparisons": "version_b", "assessments": "version"}
"""The column a compaction sorts a table by (row groups of :data:`ROW_GROUP_ROWS`): reads of
a camera, or of the latest versions (ids begin with their time), touch few row groups."""
COMMIT_RETRIES = 200
"""Attempts of an insert-unless-present that keeps meeting concurrent commits."""
EVERY_KEY_ONCE = "fieldcal.every-key-once"
"""Transaction identifier of a table whose rows all have their key's identifier (:meth:`Tables.append`)."""
KEYED = {"catalog": "fingerprint"}
"""The column whose values the key-once appends of a table name (:meth:`Tables.adopt_keys`)."""

_KEYS = [pa.field("camera_id", pa.string(), nullable=False),
         pa.field("session_id", pa.string(), nullable=False)]
_OBS_KEYS = _KEYS + [
    pa.field("image", pa.string(), nullable=False),
    pa.field("key", pa.string(), nullable=False),
    pa.field("image_sha256", pa.string()),
    pa.field("measure_settings", pa.string()),
    pa.field("row", pa.int32(), nullable=False)]


@dataclasses.dataclass(frozen=True)
class Problem:
    """A damaged object found while reading: which table or file, and why."""

    table: str
    path: str
    reason: str

    def __str__(self) -> str:
        return f"{self.table}: {self.path}: {self.reason}"


def _plain(schema: pa.Schema) -> list[pa.Field]:
    return [pa.field(f.name, f.type, nullable=f.nullable) for f in schema]


def goniometer_spot_schema() -> pa.Schema:
    """The columns of a goniometer frame's measurement (``fieldcal.goniometer``)."""
    from fieldcal.contract.goniometer_schema import MEASUREMENT_SCHEMA

    return MEASUREMENT_SCHEMA


def table_schema(name: str) -> pa.Schema:
    """The Arrow schema of one of the lake's Delta tables (partition columns included)."""
    if name == "catalog":
        return pa.schema(_plain(arrow_schema("catalog")))
    if name == "residuals":
        return pa.schema(_KEYS + [pa.field("version", pa.string(), nullable=False)]
                         + _plain(arrow_schema("residuals")))
    if name == "observations_field":  # measurement columns nullable: see observations.py
        return pa.schema(_OBS_KEYS + [f.with_nullable(True) for f in _plain(arrow_schema("measurements"))
                                      if f.name != "image"])
    if name == "observations_goniometer":
        return pa.schema(_OBS_KEYS + [f.with_nullable(True) for f in _plain(goniometer_spot_schema())])
    if name == "comparisons":
        return pa.schema([pa.field("version_a", pa.string(), nullable=False),
                          pa.field("version_b", pa.string(), nullable=False),
                          pa.field("settings", pa.string(), nullable=False),
                          pa.field("computed", pa.timestamp("us", "UTC"), nullable=False),
                          pa.field("result", pa.string(), nullable=False)])
    if name == "assessments":
        return pa.schema([pa.field("version", pa.string(), nullable=False),
                          pa.field("camera_id", pa.string(), nullable=False),
                          pa.field("settings", pa.string(), nullable=False),
                          pa.field("computed", pa.timestamp("us", "UTC"), nullable=False),
                          pa.field("verdict", pa.string(), nullable=False),
                          pa.field("radial", pa.string()),
                          pa.field("result", pa.string(), nullable=False)])
    if name == "rigs":
        return RIGS_SCHEMA
    raise InputError(f"unknown table {name!r}; the lake's tables are {', '.join(TABLES)}", "lake")


RIGS_SCHEMA = pa.schema([
    pa.field("rig_id", pa.string(), nullable=False), pa.field("session_id", pa.string(), nullable=False),
    pa.field("version", pa.string(), nullable=False), pa.field("reference", pa.string(), nullable=False),
    pa.field("created", pa.timestamp("us", "UTC"), nullable=False),
    pa.field("committed", pa.timestamp("us", "UTC"), nullable=False),
    pa.field("acquired", pa.timestamp("us", "UTC")),
    pa.field("fingerprint", pa.string(), nullable=False),
    pa.field("camera_ids", pa.list_(pa.string()), nullable=False),
    pa.field("head_versions", pa.list_(pa.string()), nullable=False),
    pa.field("n_exposures", pa.int32()), pa.field("sigma0", pa.float64()),
    pa.field("document_path", pa.string(), nullable=False)])
"""The ``rigs`` table: one row per committed rig version (CONTRACT section 3, "Rig sessions")."""


def _quote(text: str) -> str:
    return "'" + str(text).replace("'", "''") + "'"


class Tables:
    """The Delta tables of one lake (see the module docstring).

    Parameters
    ----------
    storage : fieldcal.lake.storage.Storage
    maintain_every : int
        Commits of a table between compactions and checkpoints.
    """

    def __init__(self, storage, maintain_every: int = DEFAULT_MAINTAIN_EVERY):
        if int(maintain_every) < 2:
            raise InputError(f"maintain_every must be >= 2, got {maintain_every}", "lake")
        self.storage = storage
        self.maintain_every = int(maintain_every)
        self.checkpoint_every = min(self.maintain_every, CHECKPOINT_EVERY)
        self.problems: list[Problem] = []
        self._current: dict = {}  # name -> DeltaTable kept current with update_incremental
        self._commit_times: dict = {}  # (name, commit) -> commitInfo.timestamp [ms]
        self._every_key_once: set[str] = set()   # tables known to carry EVERY_KEY_ONCE

    # -- opening ------------------------------------------------------------------------
    def uri(self, name: str) -> str:
        table_schema(name)  # checks the name
        return self.storage.uri(name)

    def _load(self, name: str, version=None):
        from deltalake import DeltaTable

        return DeltaTable(self.storage.delta_uri(name), version=version,
                          storage_options=self.storage.delta_options)

    def exists(self, name: str) -> bool:
        return bool(self.storage.listdir(f"{name}/_delta_log"))

    def quarantine(self, rel: str, why: str) -> str:
        """Move a damaged file of the lake to ``quarantine/<time>/<rel>`` (never deleted: the
        user decides); returns where it went, and records it in :attr:`problems`."""
        import secrets

        stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ") + "-" + secrets.token_hex(2)
        dest = f"{QUARANTINE}/{stamp}/{rel}"
        self.storage.move(rel, dest)
        self._commit_times.clear()
        self.problems.append(Problem(rel.split("/", 1)[0], rel, f"{why}; moved to {dest}"))
        return dest

    def heal_log(self, name: str, error: Exception) -> bool:
        """Make a table whose log cannot be loaded writable again (issue 24, goal 3): a
        ``_last_checkpoint`` hint naming a missing checkpoint, or commit files after the last
        loadable commit that are not JSON (truncated), are moved to the quarantine. The rows
        of a quarantined commit are out of the table; ``fieldcal lake repair`` brings back the
        catalog rows of whole versions. True when something was moved."""
        log = f"{name}/_delta_log"
        names = self.storage.listdir(log)
        if "_last_checkpoint" in names and "checkpoint" in reason(error).lower():
            self.quarantine(f"{log}/_last_checkpoint", f"names a checkpoint that cannot be read ({reason(error)})")
            return True
        commits = sorted(int(n[:20]) for n in names if n.endswith(".json") and n[:20].isdigit())
        good = next((v for v in reversed(commits[:-1]) if self._loads(name, v)), None)
        if good is None:
            return False                         # nothing loads: no commit is moved
        later = [v for v in commits if v > good]
        bad = next((v for v in later if _parses(self.storage, f"{log}/{v:020d}.json") is False), None)
        if bad is None:
            return False                         # every later commit is JSON: not this damage
        for v in (v for v in later if v >= bad):
            self.quarantine(f"{log}/{v:020d}.json", f"commit {v} of {name} cannot be read"
                            f" ({reason(error)}); the table continues from commit {bad - 1}")
        return True

    def _loads(self, name: str, version: int) -> bool:
        try:
            self._load(name, version=version)
            return True
        except Exception:  # noqa: BLE001 - any failure: not loadable
            return False

    def fsck(self, name: str, paths: list[str], info: dict | None = None) -> int:
        """Take data files (``add`` paths, relative to the table) out of the table: one Delta
        commit of ``remove`` actions (operation ``FSCK``, as delta-rs's ``repair`` writes),
        created exclusively as the next commit (a conditional PUT on S3; a concurrent commit
        makes it try the next number). Written here because ``DeltaTable.repair`` lists the
        whole table first, which never answered on moto S3 (180 s timeouts). Returns the
        commit number."""
        import json

        for _ in range(COMMIT_RETRIES):
            target = self.load_for_write(name)
            live = {a["path"] for a in pa.table(target.get_add_actions(flatten=True)).to_pylist()}
            gone = [p for p in paths if p in live]
            if not gone:
                return target.version()
            now_ms = int(time.time() * 1000)
            lines = [{"commitInfo": {"timestamp": now_ms, "operation": "FSCK", "operationParameters": {},
                                     "readVersion": target.version(), "clientVersion": "fieldcal",
                                     **{f"fieldcal.{k}": str(v) for k, v in (info or {}).items()}}}]
            lines += [{"remove": {"path": p, "deletionTimestamp": now_ms, "dataChange": True}} for p in gone]
            number = target.version() + 1
            try:
                self.storage.write(f"{name}/_delta_log/{number:020d}.json",
                                   "\n".join(json.dumps(line) for line in lines).encode("utf-8") + b"\n",
                                   exclusive=True)
            except FileExistsError:
                continue
            self._current.pop(name, None)
            return number
        raise LakeError(f"could not commit to {self.uri(name)}: {COMMIT_RETRIES} concurrent commits in a row")

    def load_latest(self, name: str):
        """The table at its latest commit (delta-rs's error when the log cannot be loaded)."""
        return self._load(name)

    def load_for_write(self, name: str):
        """The table at its latest commit for a write; a damaged log is healed first
        (:meth:`heal_log`), else a :class:`LakeError` in one line."""
        try:
            return self._load(name)
        except Exception as e:  # noqa: BLE001 - delta-rs raises several types for a bad log
            if self.heal_log(name, e):
                self._current.pop(name, None)
                return self._load(name)
            raise LakeError(f"cannot write {self.uri(name)}: {reason(e)} (see `fieldcal lake check`)") from None

    def open(self, name: str, *, as_of=None):
        """The table (a ``deltalake.DeltaTable``), as of a time if given; None if it has none.

        A damaged commit file makes the table load at its last readable version (reported
        in :attr:`problems`).
        """
        from deltalake.exceptions import TableNotFoundError

        cached = self._current.get(name)
        if cached is not None and as_of is None:
            try:
                cached.update_incremental()  # reads only the commits made since
                return cached
            except Exception:  # noqa: BLE001 - reload below (and report if the log is damaged)
                self._current.pop(name, None)
        if not self.exists(name):
            return None
        try:
            table = self._load(name)
        except TableNotFoundError:
            return None
        except Exception as e:  # noqa: BLE001 - delta-rs raises several types for a bad log
            table = self._load_last_good(name, e)
        if as_of is None:
            self._current[name] = table
            return table
        version = as_of if isinstance(as_of, int) else self.version_at(name, as_of)
        if version is None:
            return None                          # before the table's first commit
        if version > table.version():
            return table                         # a commit the log holds but could not be loaded
        try:
            table.load_as_version(version)
        except Exception as e:  # noqa: BLE001 - vacuumed, or a damaged log
            raise LakeError(f"cannot read {self.uri(name)} as of {as_of}: {reason(e)}") from None
        return table

    def version_at(self, name: str, when) -> int | None:
        """The table's last commit made at or before ``when`` by the commit timestamps its log
        records (``commitInfo.timestamp``), or None before its first commit (issue 24, goal 5).

        Not the commit files' modification times, which delta-rs's own time travel uses: a
        copy (``cp -r``), a sync or a restore gives every file the time of the copy. The
        timestamps are taken to grow with the version (each writer's clock; the Delta spec
        assumes as much); a binary search reads about log2(n) commit files.
        """
        t = when if isinstance(when, dt.datetime) else dt.datetime.fromisoformat(str(when))
        if t.tzinfo is None:
            t = t.replace(tzinfo=dt.UTC)
        t_ms = t.timestamp() * 1000.0
        log = f"{name}/_delta_log"
        commits = sorted(int(n[:20]) for n in self.storage.listdir(log) if n.endswith(".json") and n[:20].isdigit())
        lo, hi = 0, len(commits)
        while lo < hi:                           # the first commit later than ``when``
            mid = (lo + hi) // 2
            ts = self._commit_ms(name, commits[mid])
            if ts is not None and ts <= t_ms:
                lo = mid + 1
            else:
                hi = mid
        return commits[lo - 1] if lo else None

    def _commit_ms(self, name: str, version: int) -> float | None:
        """A commit's ``commitInfo.timestamp`` [ms] (commits are immutable: remembered)."""
        import json

        key = (name, version)
        if key not in self._commit_times:
            ts = None
            try:
                for line in self.storage.read(f"{name}/_delta_log/{version:020d}.json").decode("utf-8").splitlines():
                    if '"commitInfo"' in line:
                        ts = json.loads(line)["commitInfo"].get("timestamp")
                        break
            except (OSError, ValueError, KeyError):
                ts = None                        # unreadable: treated as later than any time
            self._commit_times[key] = float(ts) if isinstance(ts, (int, float)) else None
        return self._commit_times[key]

    def _load_last_good(self, name: str, error: Exception):
        versions = sorted((int(n[:20]) for n in self.storage.listdir(f"{name}/_delta_log")
                           if n.endswith(".json") and n[:20].isdigit()), reverse=True)
        for v in versions[1:self.maintain_every + 2]:
            try:
                table = self._load(name, version=v)
            except Exception:  # noqa: BLE001, S112 - keep looking for a readable version
                continue
            self.problems.append(Problem(name, f"{name}/_delta_log", f"cannot load the latest "
                                         f"commit ({reason(error)}); read as of commit {v}"))
            return table
        raise LakeError(f"cannot read the table {self.uri(name)}: {reason(error)}") from None

    def create(self, name: str):
        """Open the table, creating it empty first when the lake has none (race-safe)."""
        from deltalake import DeltaTable

        table = self.open(name)
        if table is not None:
            return table
        if self.storage.local:
            os.makedirs(self.storage.root, exist_ok=True)
        config = {"delta.checkpointInterval": str(self.checkpoint_every),
                  "delta.logRetentionDuration": "interval 3650 days",
                  "delta.deletedFileRetentionDuration": "interval 7 days"}
        failure = None
        try:
            DeltaTable.create(self.storage.delta_uri(name), table_schema(name), mode="ignore",
                              partition_by=PARTITIONS[name] or None, configuration=config,
                              storage_options=self.storage.delta_options,
                              commit_properties=self._commit_properties(None, EVERY_KEY_ONCE))
        except Exception as e:  # noqa: BLE001 - another process created it first: loaded below
            failure = e
        # loaded afresh: the object create() returns may hold a losing creator's metadata
        self._current.pop(name, None)
        table = self.open(name)
        if table is None:
            if isinstance(failure, OSError):
                raise failure
            raise LakeError(f"cannot create the table {self.uri(name)}: "
                            f"{reason(failure) if failure else 'no table after creating it'}")
        return table

    # -- writing ------------------------------------------------------------------------
    def _commit_properties(self, info: dict | None, *keys: str):
        from deltalake import CommitProperties, Transaction

        meta = {f"fieldcal.{k}": str(v) for k, v in (info or {}).items() if v is not None}
        return CommitProperties(custom_metadata=meta, max_commit_retries=COMMIT_RETRIES,
                                app_transactions=[Transaction(app_id=k, version=1) for k in keys] or None)

    def has_key(self, name: str, key: str) -> bool | None:
        """Whether a key-once append of ``key`` is committed to the table (:meth:`append`):
        True or False when the table holds every key it has rows of (:data:`EVERY_KEY_ONCE`),
        None when it cannot tell (a table from before, not adopted: look in its rows)."""
        target = self.open(name)
        if target is None:
            return False
        if target.transaction_version(key) is not None:
            return True
        return False if self.every_key_once(name, target) else None

    def every_key_once(self, name: str, target=None) -> bool:
        """Whether the table carries :data:`EVERY_KEY_ONCE` (remembered: it never goes away).
        Each look at a transaction identifier reads the table's log since its last checkpoint."""
        if name not in self._every_key_once:
            target = target if target is not None else self.open(name)
            if target is not None and target.transaction_version(EVERY_KEY_ONCE) is not None:
                self._every_key_once.add(name)
        return name in self._every_key_once

    def append(self, name: str, table: pa.Table, info: dict | None = None, *, once=None,
               exclusive: bool = True) -> bool:
        """Append rows (a blind append: concurrent appends never conflict); True when appended.

        ``once``: a key (e.g. a fingerprint), or a list of keys, the commit names in Delta
        transaction identifiers. With ``exclusive``, nothing is appended (False) when the table
        has a commit of such a key already, or when a concurrent commit of one wins: Delta's conflict
        check fails the second of two commits that carry one identifier, whose retry then
        finds the first. Without ``exclusive`` the key is recorded and the rows appended
        whatever the table holds (a forced version of a fingerprint).

        A table made by an older fieldcal with fewer columns gains the new ones (Delta
        schema evolution); its old rows read them as null.
        """
        from deltalake import write_deltalake
        from deltalake.exceptions import CommitFailedError

        target = self.create(name)
        if any(p.table == name and p.path == f"{name}/_delta_log" for p in self.problems):
            target = self.load_for_write(name)  # opened at an older commit: heal the log first
        schema = table_schema(name)
        keys = () if once is None else (once,) if isinstance(once, str) else tuple(once)
        for attempt in range(COMMIT_RETRIES):
            if exclusive and any(target.transaction_version(k) is not None for k in keys):
                return False
            # schema evolution only when needed: a metadata change conflicts with concurrent appends
            have = set(pa.schema(target.schema().to_arrow()).names)
            evolve = "merge" if set(schema.names) - have else None
            try:
                write_deltalake(target, table.cast(schema), mode="append", schema_mode=evolve,
                                commit_properties=self._commit_properties(info, *keys))
            except CommitFailedError:
                # a concurrent metadata commit (a racing create or schema evolution on an
                # object store) or one of the same key: the data files are in no commit;
                # look again on the new state
                time.sleep(0.02 * (1 + random.random()) * min(attempt + 1, 10))
                target = self.load_for_write(name)
                self._current[name] = target
                continue
            self._maintain(name, target)
            return True
        raise LakeError(f"could not commit to {self.uri(name)}: {COMMIT_RETRIES} concurrent "
                        "commits in a row")

    def append_once(self, name: str, table: pa.Table, key, info: dict | None = None, *,
                    exclusive: bool = True) -> bool:
        """:meth:`append` of rows once per ``key`` (``once=key``; a key or a list of keys): the
        catalog's commit point."""
        return self.append(name, table, info, once=key, exclusive=exclusive)

    def adopt_keys(self, name: str, info: dict | None = None) -> int:
        """Give a table from before the key-once appends the identifiers of the keys its rows
        have (:data:`KEYED`) and :data:`EVERY_KEY_ONCE`, in one commit, so that :meth:`has_key`
        answers from the table's log; returns the keys adopted (0: nothing to do).

        Run while no older fieldcal writes to the table (its commits carry no identifier)."""
        from deltalake import write_deltalake

        target = self.open(name)
        if target is None or self.every_key_once(name, target):
            return 0
        keys = sorted(set(self.scan(name, columns=[KEYED[name]])[KEYED[name]].to_pylist()) - {None})
        write_deltalake(target, table_schema(name).empty_table(), mode="append",
                        commit_properties=self._commit_properties(info, EVERY_KEY_ONCE, *keys))
        self._current.pop(name, None)
        return len(keys)

    def insert_unless(self, name: str, row: pa.Table, match: str, info: dict | None = None,
                      *, poll_s: float = 0.02, keys: tuple[str, ...] = (), exists=None) -> bool:
        """Insert ``row`` unless a row matching ``match`` exists; True when inserted.
        ``keys``: transaction identifiers the commit carries (:meth:`append`).

        ``match`` is a predicate over ``t`` (the table) and ``s`` (the row), e.g.
        ``t.fingerprint = s.fingerprint``. Two processes inserting rows that match each
        other: the MERGE's conflict check fails the second commit, which then sees the
        first's row and inserts nothing.

        ``exists`` (a callable, True when a matching row is readable): when the MERGE cannot
        read one of the table's data files (zero bytes, garbage, deleted), the row is
        appended unless ``exists()``, which reads the table skipping that file, and the file
        is named in :attr:`problems` (issue 24, goal 3: one damaged file never stops the
        commits; ``fieldcal lake repair`` quarantines it). Without ``exists`` the error is a
        :class:`LakeError` in one line.
        """
        from deltalake.exceptions import CommitFailedError

        self.create(name)
        for attempt in range(COMMIT_RETRIES):
            target = self.load_for_write(name)
            try:
                metrics = (target.merge(row.cast(table_schema(name)), match, source_alias="s",
                                        target_alias="t",
                                        commit_properties=self._commit_properties(info, *keys))
                           .when_not_matched_insert_all().execute())
            except CommitFailedError:
                time.sleep(poll_s * (1 + random.random()) * min(attempt + 1, 10))
                continue
            except Exception as e:  # noqa: BLE001 - delta-rs: a data file it cannot read
                damaged = _damaged_file(name, e)
                if damaged is None or exists is None:
                    raise LakeError(f"cannot commit to {self.uri(name)}: {reason(e)}") from None
                self.problems.append(Problem(name, damaged, f"cannot be read ({reason(e)}); the "
                                             "row was appended after a read that skips it"))
                if exists():
                    return False
                self.append(name, row, info, once=keys or None, exclusive=False)
                return True
            inserted = int(metrics.get("num_target_rows_inserted", 0)) > 0
            if inserted:
                self._maintain(name, target)
            return inserted
        raise LakeError(f"could not commit to {self.uri(name)}: {COMMIT_RETRIES} concurrent "
                        "commits in a row")

    def delete(self, name: str, predicate: str, info: dict | None = None) -> int:
        """Delete the rows matching a SQL predicate; returns how many were deleted."""
        target = self.open(name)
        if target is None:
            return 0
        metrics = target.delete(predicate, commit_properties=self._commit_properties(info))
        return int(metrics.get("num_deleted_rows", 0))

    def _maintain(self, name: str, target) -> None:
        """Compact the table when this commit's number is a multiple of ``maintain_every``."""
        try:
            target.update_incremental()
            if target.version() % self.maintain_every == 0:
                self._compact(name, target, {"action": "automatic compaction"})
        except Exception:  # noqa: BLE001, S110 - maintenance is best effort; `lake optimize` redoes it
            pass

    def _compact(self, name: str, target, info: dict | None) -> dict:
        """Compact small files; the catalog is rewritten sorted by camera (Z-order), in row
        groups of :data:`ROW_GROUP_ROWS`, so that one camera's rows are a few row groups (the
        derived tables by version: :data:`SORTED_BY`)."""
        from deltalake import WriterProperties

        props = self._commit_properties(info)
        if name in SORTED_BY:
            return target.optimize.z_order([SORTED_BY[name]], commit_properties=props,
                                           writer_properties=WriterProperties(
                                               max_row_group_size=ROW_GROUP_ROWS))
        return target.optimize.compact(commit_properties=props)

    # -- reading ------------------------------------------------------------------------
    def files(self, name: str, *, as_of=None, partition: dict | None = None) -> list[dict]:
        """The table's live files (add actions: ``path``, ``num_records``, ``partition.*``, stats).

        ``partition`` keeps only the files of those partition values (``{"camera_id": c}``).
        """
        table = self.open(name, as_of=as_of)
        if table is None:
            return []
        adds = pa.table(table.get_add_actions(flatten=True)).to_pylist()
        parts = set(table.metadata().partition_columns)
        for col, value in (partition or {}).items():
            if col in parts:
                adds = [a for a in adds if a.get(f"partition.{col}") == value]
        return adds

    def read_file(self, name: str, add: dict, fs, columns=None, equal: dict | None = None) -> pa.Table:
        """One data file as rows of the table's schema (partition values filled in).

        ``columns`` reads only those; ``equal`` (``{column: value}``) reads only the row
        groups whose statistics may hold the value (the catalog is written sorted by
        ``camera_id`` in row groups of :data:`ROW_GROUP_ROWS`).
        """
        schema = table_schema(name)
        with fs.open_input_file(add["path"]) as handle:
            pf = pq.ParquetFile(handle)
            groups = _row_groups(pf, equal or {})
            names = set(pf.schema_arrow.names)
            want = [c for c in (columns or schema.names) if c in names]
            t = pf.read_row_groups(groups, columns=want) if groups else \
                pf.schema_arrow.empty_table().select(want)
        n = t.num_rows
        cols = []
        for f in schema:
            if columns and f.name not in columns:
                cols.append(pa.nulls(n, f.type))
            elif f"partition.{f.name}" in add:
                cols.append(pa.array([add[f"partition.{f.name}"]] * n, f.type))
            elif f.name in t.column_names:
                cols.append(t[f.name].cast(f.type))
            else:
                cols.append(pa.nulls(n, f.type))
        out = pa.Table.from_arrays(cols, schema=schema)
        return out.select(columns) if columns else out

    def scan(self, name: str, *, filter=None, columns=None, as_of=None,
             partition: dict | None = None, equal: dict | None = None) -> pa.Table:
        """The table's rows (those matching ``filter``, a pyarrow expression), bad files skipped.

        Each file is read with its own types (delta-rs's DataFusion writes strings as
        ``string_view``, which pyarrow cannot filter), cast to :func:`table_schema` and
        filtered in memory; ``partition`` (``{"camera_id": c}``) selects files first, and
        ``equal`` (``{"version": v}``) skips files whose min/max statistics exclude the
        value, or every value of a sorted list (it does not filter rows: give ``filter`` too).
        An unreadable file is left out and reported in :attr:`problems`.
        """
        table = self.open(name, as_of=as_of)
        schema = table_schema(name)
        if table is None:
            empty = schema.empty_table()
            return empty.select(columns) if columns else empty
        fs = table.to_pyarrow_dataset().filesystem
        need = None
        if columns:
            need = list(dict.fromkeys(list(columns) + _filter_columns(filter, schema)))
        parts = []
        for add in self.files(name, as_of=as_of, partition=partition):
            if any(_outside(add, col, value) for col, value in (equal or {}).items()):
                continue
            try:
                parts.append(self.read_file(name, add, fs, need, equal))
            except FileNotFoundError as e:
                if as_of is not None:  # not damage: vacuum removed the files of that time
                    raise LakeError(f"{name} as of {as_of} is no longer readable: its file "
                                    f"{add['path']} was removed by vacuum") from None
                self.problems.append(Problem(name, f"{name}/{add['path']}", reason(e)))
            except (OSError, pa.ArrowException) as e:
                self.problems.append(Problem(name, f"{name}/{add['path']}", reason(e)))
        out = pa.concat_tables(parts) if parts else (schema.empty_table().select(need) if need
                                                     else schema.empty_table())
        if filter is not None:
            out = out.filter(filter)
        return out.select(columns) if columns else out

    def lazy(self, name: str, *, as_of=None) -> tuple:
        """``(dataset, rest)``: the table as a lazy pyarrow dataset of its files written with
        plain types (compacted files: projection and filters are pushed down) and a table
        of the rows of the other files (``string_view``, written by MERGE or DELETE since the
        last compaction), read and cast. Unreadable files are left out and reported."""
        schema = table_schema(name)
        table = self.open(name, as_of=as_of)
        if table is None:
            return None, schema.empty_table()
        fs = table.to_pyarrow_dataset().filesystem
        fmt = ds.ParquetFileFormat()
        frags, rest = [], []
        for add in self.files(name, as_of=as_of):
            try:
                frag = fmt.make_fragment(add["path"], fs, partition_expression=_partition_expr(add, schema))
                physical = frag.physical_schema
                if any(pa.types.is_string_view(f.type) or "view" in str(f.type) for f in physical):
                    rest.append(self.read_file(name, add, fs))
                else:
                    frags.append(frag)
            except FileNotFoundError as e:
                if as_of is not None:
                    raise LakeError(f"{name} as of {as_of} is no longer readable: its file "
                                    f"{add['path']} was removed by vacuum") from None
                self.problems.append(Problem(name, f"{name}/{add['path']}", reason(e)))
            except (OSError, pa.ArrowException) as e:
                self.problems.append(Problem(name, f"{name}/{add['path']}", reason(e)))
        dataset = ds.FileSystemDataset(frags, schema, fmt, fs) if frags else None
        return dataset, (pa.concat_tables(rest) if rest else schema.empty_table())

    # -- maintenance and audit ------------------------------------------------------------
    def optimize(self, name: str, info: dict | None = None) -> dict:
        """Compact the table's small files and write a checkpoint (a keyed table from before
        the key-once appends adopts its keys first: :meth:`adopt_keys`)."""
        target = self.open(name)
        if target is None:
            return {"table": name, "files_removed": 0, "files_added": 0}
        if name in KEYED and self.adopt_keys(name, info):
            target = self.open(name)
        interval = target.metadata().configuration.get("delta.checkpointInterval")
        if interval is None or int(interval) > self.checkpoint_every:     # a table from before
            target.alter.set_table_properties({"delta.checkpointInterval": str(self.checkpoint_every)},
                                              commit_properties=self._commit_properties(info))
        metrics = self._compact(name, target, info)
        target.update_incremental()
        target.create_checkpoint()
        return {"table": name, "files_removed": int(metrics.get("numFilesRemoved", 0)),
                "files_added": int(metrics.get("numFilesAdded", 0)), "version": target.version()}

    def vacuum(self, name: str, retention_hours: float, *, dry_run: bool,
               info: dict | None = None) -> list[str]:
        """Files no longer referenced by the table's current state and older than the retention.

        Only files that a commit removed (compaction, deletes) and that the current state
        does not reference are candidates (delta-rs "lite" vacuum: a file not yet committed
        by a running writer is never touched); the catalog rows and residual rows of every
        committed version are in the current state, so their files stay.
        """
        target = self.open(name)
        if target is None:
            return []
        return list(target.vacuum(retention_hours=int(retention_hours), dry_run=dry_run,
                                  enforce_retention_duration=False,
                                  commit_properties=self._commit_properties(info)))

    def commits(self, name: str) -> list[dict]:
        """Every readable commit of the table, oldest first, read from its commit files:
        ``commit``, ``time`` (the ``commitInfo`` timestamp), ``operation`` and the fieldcal
        metadata (``version``, ``action``, ...). Unlike ``DeltaTable.history`` it reads each
        file once, concurrently on an object store (delta-rs's history took 180 s for two
        commits on moto S3)."""
        import json

        log = f"{name}/_delta_log"
        rels = [f"{log}/{n}" for n in self.storage.listdir(log) if n.endswith(".json") and n[:20].isdigit()]
        out = []
        for rel, data in sorted(self.storage.read_many(rels).items()):
            info = None
            for line in data.decode("utf-8", "replace").splitlines():
                if '"commitInfo"' in line:
                    try:
                        info = json.loads(line)["commitInfo"]
                    except (ValueError, KeyError, TypeError):
                        info = None
                    break
            if not isinstance(info, dict):
                continue
            ts = info.get("timestamp")
            when = dt.datetime.fromtimestamp(ts / 1000.0, dt.UTC) if isinstance(ts, (int, float)) else None
            out.append({"table": name, "commit": int(rel[-25:-5]), "time": when,
                        "operation": info.get("operation"),
                        **{k[len("fieldcal."):]: v for k, v in info.items()
                           if isinstance(k, str) and k.startswith("fieldcal.")}})
        return out

    def log(self, name: str, limit: int | None = None) -> list[dict]:
        """The table's commits, newest first: version, time, operation, fieldcal metadata."""
        target = self.open(name)
        if target is None:
            return []
        out = []
        for h in target.history(limit):
            ts = h.get("timestamp")
            when = dt.datetime.fromtimestamp(ts / 1000.0, dt.UTC) if isinstance(ts, (int, float)) else None
            out.append({"table": name, "commit": h.get("version"), "time": when,
                        "operation": h.get("operation"),
                        **{k[len("fieldcal."):]: v for k, v in h.items()
                           if isinstance(k, str) and k.startswith("fieldcal.")}})
        return out


def _parses(storage, rel: str) -> bool | None:
    """Whether a commit file is whole JSON lines; None when it cannot be read now (a file
    that could not be read is never taken for a damaged one)."""
    import json

    try:
        data = storage.read(rel)
    except OSError:
        return None
    try:
        for line in data.decode("utf-8").splitlines():
            if line.strip():
                json.loads(line)
        return True
    except ValueError:
        return False


def _damaged_file(name: str, error: Exception) -> str | None:
    """The table's data file a delta-rs error names (``NAME/part-....parquet``), or None
    when the error is not about reading one of its data files."""
    import re

    text = str(error)
    if "parquet" not in text.lower() and "not found" not in text.lower():
        return None
    m = re.search(rf"{re.escape(name)}/([^\s:]+\.parquet)", text)
    return f"{name}/{m.group(1)}" if m else None


def _filter_columns(expr, schema: pa.Schema) -> list[str]:
    """Column names a filter expression refers to (from its text; all when unsure)."""
    if expr is None:
        return []
    text = str(expr)
    return [n for n in schema.names if n in text]


def _excludes(value, lo, hi) -> bool:
    """Whether ``[lo, hi]`` holds no ``value`` (a value, or a sorted list of values: any of them)."""
    try:
        if isinstance(value, list):
            import bisect

            i = bisect.bisect_left(value, lo)
            return i == len(value) or value[i] > hi
        return value < lo or value > hi
    except TypeError:
        return False


def _outside(add: dict, column: str, value) -> bool:
    """True when a file's statistics show it holds no row with ``column == value`` (for a
    sorted list: with any of its values)."""
    lo, hi = add.get(f"min.{column}"), add.get(f"max.{column}")
    if lo is None or hi is None:
        return False
    return _excludes(value, lo, hi)


def _row_groups(pf, equal: dict) -> list[int]:
    """Row groups of a Parquet file whose statistics do not exclude ``column == value`` (a
    sorted list: any of its values)."""
    keep = []
    meta = pf.metadata
    leaf = {meta.schema.column(j).path: j for j in range(meta.num_columns)}
    for i in range(meta.num_row_groups):
        rg = meta.row_group(i)
        ok = True
        for col, value in equal.items():
            if col not in leaf:
                continue
            st = rg.column(leaf[col]).statistics
            if st is not None and st.has_min_max:
                lo, hi = st.min, st.max
                lo = lo.decode() if isinstance(lo, bytes) else lo
                hi = hi.decode() if isinstance(hi, bytes) else hi
                ok = ok and not _excludes(value, lo, hi)
        if ok:
            keep.append(i)
    return keep


def _partition_expr(add: dict, schema: pa.Schema):
    expr = ds.scalar(True)
    for key, value in add.items():
        if key.startswith("partition.") and key[10:] in schema.names:
            col = key[10:]
            expr = expr & (ds.field(col) == pa.scalar(value, schema.field(col).type))
    return expr
