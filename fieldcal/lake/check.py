"""Checking a lake: every damaged object, and what depends on it.

:func:`check` reads everything a reader may need and returns one :class:`Damage` per
damaged object: a table's commit or data file that cannot be read (with the versions or
cameras whose rows it held, from the file's statistics), a catalogued version whose
document or Zarr group is missing or does not match, an array whose chunk is missing or
whose bytes differ from the SHA-256 recorded at the commit, a rig version (a row of the
``rigs`` table) whose rig document is missing or does not match, or whose heads' versions are
not in the catalog. ``fieldcal lake check`` prints them and exits 1 when there is any.

:func:`verify_group` is the check :meth:`fieldcal.lake.store.Lake.open_zarr` runs on every
read: Zarr reads a missing chunk back as the fill value (zeros), which must never pass
for data (variances of exactly 0).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math

import numpy as np
import pyarrow as pa

from fieldcal.errors import LakeError
from fieldcal.lake.parts import array_digest, reason
from fieldcal.lake.tables import TABLES

__all__ = ["check", "verify_group", "read_back", "open_group", "unreadable_files", "Damage"]


@dataclasses.dataclass(frozen=True)
class Damage:
    """A damaged object of the lake and what depends on it."""

    path: str
    problem: str
    affects: str

    def __str__(self) -> str:
        return f"{self.path}: {self.problem} -> {self.affects}"


def _chunk_keys(arr) -> list[str]:
    grid = [range(math.ceil(s / c)) if s else range(0) for s, c in zip(arr.shape, arr.chunks,
                                                                       strict=True)]
    if not arr.shape:
        return ["c"]
    return ["c/" + "/".join(map(str, idx)) for idx in itertools.product(*grid)]


def verify_group(lake, rel: str, group, version: str) -> None:
    """Every array of a version's group against its recorded SHA-256; LakeError naming a bad one."""
    digests = group.attrs.get("digests")
    if not isinstance(digests, dict):
        return  # made before digests were recorded: nothing to compare with
    for name, want in sorted(digests.items()):
        try:
            arr = group[name]
            data = arr[...]
        except Exception as e:  # noqa: BLE001 - zarr raises many types for damaged metadata
            raise LakeError(f"version {version}: array {rel}/{name} cannot be read: {reason(e)}") \
                from None
        if array_digest(np.asarray(data)) == want:
            continue
        missing = [k for k in _chunk_keys(arr) if not lake.storage.exists(f"{rel}/{name}/{k}")]
        if missing:
            raise LakeError(f"version {version}: chunk {rel}/{name}/{missing[0]} is missing"
                            + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        raise LakeError(f"version {version}: array {rel}/{name} does not match the SHA-256 "
                        "recorded at its commit (damaged chunk)")


def open_group(lake, rel: str, version: str):
    """A version's Zarr group, read-only (LakeError in one line when it cannot be opened)."""
    import zarr

    try:
        return zarr.open_group(store=lake.storage.zarr_store(rel, read_only=True), mode="r")
    except (OSError, FileNotFoundError, ValueError, KeyError) as e:
        raise LakeError(f"version {version}: cannot open {lake.uri(rel)}: {reason(e)}") from None


def read_back(lake, version: str, document_path: str, zarr_path: str, *, document: bytes | None = None,
              residuals: tuple[str, int] | None = None) -> str | None:
    """Why a version's parts do not read back whole, or None when they do (issue 24, goal 1).

    The document must exist, parse and name ``version`` (with ``document``: be exactly those
    bytes); the Zarr group must open, record a SHA-256 for each of its arrays and every array
    must match it (:func:`verify_group`); with ``residuals`` (``(camera_id, n_rows)``, at the
    commit) the residuals table must hold exactly ``n_rows`` readable rows of the version.
    A commit runs this before its catalog row (the commit point), a rerun before it answers
    "unchanged" with an existing version.
    """
    try:
        data = lake.storage.read(document_path)
    except FileNotFoundError:
        return f"its document {document_path} is missing"
    except OSError as e:
        return f"its document {document_path} cannot be read: {reason(e)}"
    if document is not None and data != document:
        return f"its document {document_path} does not read back as written"
    try:
        doc = json.loads(data)
    except ValueError as e:
        return f"its document {document_path} is not JSON: {reason(e)}"
    if not isinstance(doc, dict) or doc.get("version") != version:
        return f"{document_path} is not its document"
    try:
        group = open_group(lake, zarr_path, version)
        digests = group.attrs.get("digests")
        if document is not None and (not isinstance(digests, dict)
                                     or set(digests) != set(group.attrs.get("arrays") or [])):
            return f"its Zarr group {zarr_path} does not record the SHA-256 of each array"
        verify_group(lake, zarr_path, group, version)
    except LakeError as e:
        return str(e).removeprefix(f"version {version}: ")
    if residuals is not None:
        return _residuals_back(lake, version, *residuals)
    return None


def _residuals_back(lake, version: str, camera_id: str, n_rows: int) -> str | None:
    import pyarrow.dataset as ds

    before = len(lake.problems)
    t = lake.tables.scan("residuals", filter=ds.field("version") == version, columns=["version"],
                         partition={"camera_id": camera_id}, equal={"version": version})
    if len(lake.problems) > before:
        return f"its residual rows cannot be read back: {lake.problems[-1]}"
    if t.num_rows != n_rows:
        return f"{t.num_rows} of its {n_rows} residual row(s) read back"
    return None


def unreadable_files(lake, name: str) -> list[tuple[str, str]]:
    """``(lake-relative path, reason)`` of the table's live data files that cannot be read."""
    if lake.tables.open(name) is None:
        return []
    fs = lake.tables.open(name).to_pyarrow_dataset().filesystem
    out = []
    for add in lake.tables.files(name):
        try:
            lake.tables.read_file(name, add, fs)
        except (OSError, pa.ArrowException) as e:
            out.append((f"{name}/{add['path']}", reason(e)))
    return out


def _table_damage(lake, name: str) -> list[Damage]:
    out = []
    before = len(lake.problems)
    try:
        table = lake.tables.open(name)
    except LakeError as e:
        return [Damage(f"{name}/_delta_log", str(e), f"every reader of {name}")]
    for p in lake.problems[before:]:
        out.append(Damage(p.path, p.reason, f"the latest commits of {name}"))
    if table is None:
        return out
    fs = table.to_pyarrow_dataset().filesystem
    for add in lake.tables.files(name):
        try:
            lake.tables.read_file(name, add, fs)
        except (OSError, pa.ArrowException) as e:
            out.append(Damage(f"{name}/{add['path']}", reason(e), _dependents(name, add)))
    return out


def _dependents(name: str, add: dict) -> str:
    """What the rows of a damaged file were, from its statistics in the commit log."""
    n = add.get("num_records")
    lo, hi = add.get("min.version"), add.get("max.version")
    if name == "catalog":
        return f"{n} catalog row(s), versions {lo} .. {hi}, are hidden from every reader"
    if name == "rigs":
        return f"{n} rig version(s), {lo} .. {hi}, are hidden from history and compare"
    cam = add.get("partition.camera_id")
    what = f"versions {lo} .. {hi}" if lo else f"sessions {add.get('min.session_id')} .. " \
                                                f"{add.get('max.session_id')}"
    return f"{n} row(s) of {name} of camera {cam} ({what}) cannot be read"


def _version_damage(lake, row: dict) -> list[Damage]:
    v = row["version"]
    out = []
    doc_rel, zarr_rel = row["document_path"], row["zarr_path"]
    try:
        doc = json.loads(lake.storage.read(doc_rel))
        if not isinstance(doc, dict) or doc.get("version") != v:
            raise ValueError("not this version's document")
    except FileNotFoundError:
        out.append(Damage(doc_rel, "missing", f"version {v}: show, export, report"))
    except (OSError, ValueError) as e:
        out.append(Damage(doc_rel, reason(e), f"version {v}: show, export, report"))
    try:
        lake.open_zarr(v)
    except LakeError as e:
        out.append(Damage(zarr_rel, str(e), f"version {v}: compare, uncertainty, fleet comparison"))
    return out


def _hidden_versions(lake, catalogued: set[str]) -> list[Damage]:
    """Versions the catalog's log names as committed whose document is there but whose row
    is not (a damaged file or a quarantined commit took it): ``lake repair`` restores them."""
    from fieldcal.lake.gc import logged_versions, walk_calibrations

    named = logged_versions(lake) - catalogued
    if not named:
        return []
    return [Damage(rel, "committed (the catalog's log names it) but the catalog has no row for it",
                   f"version {stem} is hidden from every reader (`fieldcal lake repair --apply` restores it)")
            for rel, _, stem in walk_calibrations(lake) if stem in named and rel.endswith(".json")]


def _rig_damage(lake, row: dict, catalogued: set) -> list[Damage]:
    """A rig version's document (readable, this version's, listing the row's heads) and its
    heads' calibration versions (catalogued)."""
    v, rel = row["version"], row["document_path"]
    affects = f"rig version {v}: history --rig, compare, the rig in reports and certificates"
    try:
        doc = json.loads(lake.storage.read(rel))
        if not isinstance(doc, dict) or doc.get("version") != v:
            raise ValueError("not this rig version's document")
        if [h.get("version") for h in doc.get("heads", [])] != list(row["head_versions"]):
            raise ValueError("its heads' versions differ from the rigs table's")
    except FileNotFoundError:
        return [Damage(rel, "missing", affects)]
    except (OSError, ValueError, AttributeError) as e:
        return [Damage(rel, reason(e), affects)]
    missing = [h for h in row["head_versions"] if h not in catalogued]
    if missing:
        return [Damage(f"rigs: version={v}", f"head version(s) {', '.join(missing)} not in the catalog", affects)]
    return []


def _rig_heads_logged(lake) -> set[str]:
    """Head versions the catalog's log names as committed by a rig commit (``versions`` of its
    ``commit rig`` commits): a rig row listing one of them is a committed rig version even when
    damage hides its heads' rows."""
    try:
        entries = lake.tables.commits("catalog")
    except Exception:  # noqa: BLE001 - a log that cannot be read: the catalog rows decide
        return set()
    return {v for e in entries if e.get("action") == "commit rig" and isinstance(e.get("versions"), str)
            for v in e["versions"].split(",")}


def check(lake) -> list[Damage]:
    """Every damaged object of the lake (empty when the lake is sound)."""
    out = []
    for name in TABLES:
        out += _table_damage(lake, name)
    catalog = lake.catalog().to_pylist()
    for row in catalog:
        out += _version_damage(lake, row)
    catalogued = {row["version"] for row in catalog}
    out += _hidden_versions(lake, catalogued)
    logged = _rig_heads_logged(lake)
    for row in lake.tables.scan("rigs").to_pylist():
        if logged.isdisjoint(row["head_versions"]) and catalogued.isdisjoint(row["head_versions"]):
            continue        # an interrupted rig commit (its heads never committed): not a version, gc's
        out += _rig_damage(lake, row, catalogued)
    seen, unique = set(), []
    for d in out:
        if (d.path, d.problem) not in seen:
            seen.add((d.path, d.problem))
            unique.append(d)
    return unique
