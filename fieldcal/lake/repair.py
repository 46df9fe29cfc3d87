"""Repairing a lake: back to "every catalog row points to a whole version" (issue 24).

:func:`repair` finds what :func:`fieldcal.lake.check.check` reports and, with ``apply``,
restores consistency. Nothing is deleted: a damaged file, or what is left of a version
that cannot be restored, is moved to ``LAKE/quarantine/<time>/`` under its own path (the
user decides what to keep); a catalog row that is taken out of the catalog is kept there
as JSON, with the version's residual rows as Parquet. Kinds of damage, and what is done:

=======================================  ===========================================================
damage                                   repair
=======================================  ===========================================================
``_last_checkpoint`` naming a missing    the hint is quarantined (the log is read from its commits)
checkpoint
a commit file that is not JSON           it (and any later commit) is quarantined; the table goes
(truncated), after the last loadable     on from the last loadable commit; catalog rows it held are
one                                      restored below
a data file that cannot be read (zero    quarantined, and taken out of the table (a Delta FSCK
bytes, garbage) or is missing            commit); catalog rows it held are restored below
a catalogued version whose document is   the document is written again from the copy in its Zarr
missing or damaged, Zarr group whole     group's attributes (``document``), byte for byte
a catalogued version whose Zarr group    what is left of it is quarantined with its catalog row
or a chunk is missing or damaged         and residual rows, and the row leaves the catalog (a rerun
                                         of its session calibrates again)
a whole version with no catalog row      its row is restored: from a data file the catalog no longer
that the catalog's log, a quarantined    references (the row as it was), else made again from the
commit or an unreferenced catalog file   document with the commit's time from the log
names as committed
=======================================  ===========================================================

Damaged files of the other tables lose their rows: residual rows of those versions
(``lake check`` then names them), cached observations (measured again by the next run),
comparisons and assessments (computed again, ``fieldcal lake fill``).
"""

from __future__ import annotations

import dataclasses
import json

import pyarrow as pa
import pyarrow.parquet as pq

from fieldcal.errors import LakeError
from fieldcal.lake.check import read_back
from fieldcal.lake.gc import logged_versions
from fieldcal.lake.ids import VERSION_PATTERN, parse_time, utcnow
from fieldcal.lake.parts import catalog_row, reason
from fieldcal.lake.tables import QUARANTINE, TABLES, table_schema

__all__ = ["repair", "Repair"]

@dataclasses.dataclass(frozen=True)
class Repair:
    """One thing repaired (or, in a dry run, to repair): the object and what was done."""

    path: str
    action: str

    def __str__(self) -> str:
        return f"{self.path}: {self.action}"


def repair(lake, *, apply: bool = False) -> list[Repair]:
    """Restore the lake's consistency (module docstring); with ``apply`` False only list.

    Returns
    -------
    list of Repair
        What was done (or would be), in order: logs, data files, versions, restored rows.
    """
    out: list[Repair] = []
    for name in TABLES:
        out += _repair_log(lake, name, apply)
    for name in TABLES:
        out += _repair_files(lake, name, apply)
    removed: set[str] = set()
    for row in lake.catalog().to_pylist():
        out += _repair_version(lake, row, apply, removed)
    out += _restore_rows(lake, apply, removed)
    return out


# --------------------------------------------------------------------------------------
# the tables
# --------------------------------------------------------------------------------------
def _repair_log(lake, name: str, apply: bool) -> list[Repair]:
    tables = lake.tables
    if not tables.exists(name):
        return []
    try:
        tables.load_latest(name)
        return []
    except Exception as e:  # noqa: BLE001 - delta-rs raises several types for a bad log
        error = e
    if not apply:
        return [Repair(f"{name}/_delta_log", f"cannot be loaded ({reason(error)}): the damaged "
                       "commit or checkpoint hint would be quarantined")]
    before = len(tables.problems)
    if not tables.heal_log(name, error):
        raise LakeError(f"{name}/_delta_log cannot be loaded and repair does not know how to "
                        f"heal it: {reason(error)}")
    tables.load_for_write(name)
    return [Repair(p.path, p.reason) for p in tables.problems[before:]]


def _repair_files(lake, name: str, apply: bool) -> list[Repair]:
    """Unreadable or missing data files: quarantined and taken out of the table (FSCK)."""
    from fieldcal.lake.check import unreadable_files

    bad = unreadable_files(lake, name)
    if not bad:
        return []
    out = []
    for rel, why in bad:
        present = lake.storage.exists(rel)
        if not apply:
            out.append(Repair(rel, f"{why}: would be " + ("quarantined and " if present else "")
                              + "taken out of the table"))
            continue
        if present:
            dest = lake.tables.quarantine(rel, why)
            out.append(Repair(rel, f"{why}: moved to {dest} and taken out of the table"))
        else:
            out.append(Repair(rel, f"{why}: taken out of the table"))
    if apply:
        lake.tables.fsck(name, [r.split("/", 1)[1] for r, _ in bad],
                         {"action": "repair", "files": ", ".join(r for r, _ in bad)})
    return out


# --------------------------------------------------------------------------------------
# versions
# --------------------------------------------------------------------------------------
def _document_from_zarr(lake, row: dict) -> bytes | None:
    """The version's document as written at its commit, from its whole Zarr group, or None."""
    from fieldcal.lake.check import open_group, verify_group

    try:
        group = open_group(lake, row["zarr_path"], row["version"])
        verify_group(lake, row["zarr_path"], group, row["version"])
        doc = dict(group.attrs["document"])
    except (LakeError, KeyError, TypeError):
        return None
    if doc.get("version") != row["version"]:
        return None
    return json.dumps(doc, indent=2).encode("utf-8")


def _repair_version(lake, row: dict, apply: bool, removed: set[str]) -> list[Repair]:
    v = row["version"]
    why = read_back(lake, v, row["document_path"], row["zarr_path"])
    if why is None:
        return []
    if "document" in why:
        text = _document_from_zarr(lake, row)
        if text is not None:
            if not apply:
                return [Repair(row["document_path"], f"version {v}: {why}: would be written again "
                               "from its Zarr group")]
            if lake.storage.exists(row["document_path"]):
                lake.tables.quarantine(row["document_path"], why)
            lake.storage.write(row["document_path"], text)
            if read_back(lake, v, row["document_path"], row["zarr_path"], document=text) is None:
                return [Repair(row["document_path"], f"version {v}: {why}: written again from its Zarr group")]
            why = read_back(lake, v, row["document_path"], row["zarr_path"]) or why
    if not apply:
        return [Repair(f"catalog: version {v}", f"{why}: its row and what is left of it would be "
                       "quarantined (a rerun calibrates its session again)")]
    removed.add(v)
    return [Repair(f"catalog: version {v}", f"{why}: {_quarantine_version(lake, row, why)}")]


def _quarantine_version(lake, row: dict, why: str) -> str:
    import pyarrow.dataset as ds

    v = row["version"]
    store = lake.storage
    stamp = utcnow().strftime("%Y%m%dT%H%M%SZ")
    base = f"{QUARANTINE}/{stamp}-{v}"
    store.write(f"{base}/catalog-row.json", json.dumps(
        {"reason": why, "row": row}, indent=2, default=str).encode("utf-8"))
    res = lake.tables.scan("residuals", filter=ds.field("version") == v,
                           partition={"camera_id": row["camera_id"]}, equal={"version": v})
    if res.num_rows:
        sink = pa.BufferOutputStream()
        pq.write_table(res, sink)
        store.write(f"{base}/residuals.parquet", sink.getvalue().to_pybytes())
    for rel in (row["document_path"], row["zarr_path"]):
        if store.exists(rel):
            store.move(rel, f"{base}/{rel}")
    lake.tables.delete("catalog", f"version = '{v}'", {"action": "repair", "version": v})
    if res.num_rows:
        lake.tables.delete("residuals", f"version = '{v}'", {"action": "repair", "version": v})
    return f"its row, {res.num_rows} residual row(s) and what was left of it moved to {base}"


# --------------------------------------------------------------------------------------
# catalog rows to restore
# --------------------------------------------------------------------------------------
def _unreferenced_rows(lake) -> dict[str, dict]:
    """``{version: row}`` of readable catalog data files the table no longer references."""
    live = {a["path"] for a in lake.tables.files("catalog")}
    out = {}
    for name in lake.storage.listdir("catalog"):
        if not name.endswith(".parquet") or name in live:
            continue
        try:
            t = pq.read_table(pa.BufferReader(lake.storage.read(f"catalog/{name}")))
        except (OSError, pa.ArrowException):
            continue
        schema = table_schema("catalog")
        for r in t.to_pylist():
            if isinstance(r.get("version"), str):
                out.setdefault(r["version"], {k: r.get(k) for k in schema.names})
    return out


def _restore_rows(lake, apply: bool, removed: set[str]) -> list[Repair]:
    from fieldcal.lake.gc import walk_calibrations

    present = set(lake.catalog()["version"].to_pylist())
    named = logged_versions(lake) - present - removed
    old_rows = {v: r for v, r in _unreferenced_rows(lake).items() if v not in present and v not in removed}
    wanted = named | set(old_rows)
    if not wanted:
        return []
    where = {stem: rel.rsplit("/", 1)[0] for rel, _, stem in walk_calibrations(lake)
             if stem in wanted and rel.endswith(".json")}
    log = {e["version"]: e for e in lake.tables.commits("catalog") if e.get("version") in wanted
           and e.get("action") in ("commit", "migrate")}
    rows, out = [], []
    for v in sorted(wanted):
        if v not in where or not VERSION_PATTERN.fullmatch(v):
            continue
        folder = where[v]
        doc_rel, zarr_rel = f"{folder}/{v}.json", f"{folder}/{v}.zarr"
        if read_back(lake, v, doc_rel, zarr_rel) is not None:
            continue
        row = old_rows.get(v) or _row_from_document(lake, doc_rel, zarr_rel, log.get(v))
        rows.append(row)
        source = "as it was in an unreferenced catalog file" if v in old_rows else "made again from its document"
        out.append(Repair(f"catalog: version {v}", "whole but not in the catalog: its row "
                          + ("restored " if apply else "would be restored ") + source))
    if apply and rows:
        lake.tables.append("catalog", pa.Table.from_pylist(rows, schema=table_schema("catalog")),
                           {"action": "repair", "versions": ", ".join(r["version"] for r in rows)})
    return out


def _row_from_document(lake, doc_rel: str, zarr_rel: str, logged: dict | None) -> dict:
    """A catalog row made again from a whole version's document: the commit's time and
    whether it was forced (an append, not a MERGE) from its log entry when there is one."""
    doc = json.loads(lake.storage.read(doc_rel))
    when = (logged or {}).get("time") or parse_time(doc.get("created"), doc_rel)
    forced = (logged or {}).get("operation") == "WRITE"
    paths = {"document": doc_rel, "zarr": zarr_rel, "residuals": "residuals"}
    return catalog_row(doc, when, forced, paths, doc_rel).to_pylist()[0]
