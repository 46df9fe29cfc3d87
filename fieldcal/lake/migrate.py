"""Moving a lake of the first layout (one Parquet file per version) onto Delta tables.

The first layout (fieldcal before the Delta lake) kept, under one root::

    catalog/V.parquet                                                   one row per version
    residuals/camera_id=C/session_id=S/version=V/residuals.parquet      one per version
    observations/camera_id=C/session_id=S/<image-key>-<key>.parquet     one per image
    calibrations/C/S/V.json, calibrations/C/S/V.zarr                    as now
    _claims/...                                                         commit claims

:class:`OldLake` is a small reader of it; :func:`migrate` brings every version (catalog
row with its version id, fingerprint, ``created``/``committed``/``acquired`` times and
``forced`` flag; document; Zarr arrays and attributes; residual rows) and every cached
observation into a lake of the current layout through the lake's own commit path, then
:func:`verify` compares the two row for row and value for value. A migration that stopped
half-way is resumed by running it again: versions already present are skipped.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from fieldcal.errors import LakeError
from fieldcal.lake import observations as obs
from fieldcal.lake.ids import ID_PATTERN, SHA256_PATTERN, VERSION_PATTERN
from fieldcal.lake.parts import reason
from fieldcal.lake.storage import Storage

__all__ = ["OldLake", "migrate", "verify", "Report"]

_PATH_COLUMNS = ("residuals_path",)
"""Catalog columns whose value changes in the move (the residuals are a table now)."""


@dataclasses.dataclass
class Report:
    """What a migration brought over (counts) and what it could not read."""

    versions: int = 0
    residual_rows: int = 0
    observation_images: int = 0
    observation_rows: int = 0
    skipped: list = dataclasses.field(default_factory=list)

    def lines(self) -> list[str]:
        out = [f"versions {self.versions}, residual rows {self.residual_rows}, observation images "
               f"{self.observation_images} ({self.observation_rows} rows)"]
        return out + [f"skipped {s}" for s in self.skipped]


class OldLake:
    """A read-only view of a lake of the first layout (see the module docstring)."""

    def __init__(self, url, storage_options=None):
        self.store = Storage(url, storage_options)
        self.url = self.store.uri("")

    def catalog(self) -> list[dict]:
        """Every catalog row (one file each), oldest commit first."""
        rows = []
        for name in self.store.listdir("catalog"):
            if not (name.endswith(".parquet") and VERSION_PATTERN.fullmatch(name[:-8])):
                continue
            try:
                rows += pq.read_table(pa.BufferReader(self.store.read(f"catalog/{name}"))).to_pylist()
            except (OSError, pa.ArrowException) as e:
                raise LakeError(f"cannot read {self.store.uri('catalog/' + name)}: {reason(e)}") \
                    from None
        return sorted(rows, key=lambda r: (r["committed"], r["version"]))

    def read(self, rel: str) -> bytes:
        return self.store.read(rel)

    def document(self, row: dict) -> dict:
        return json.loads(self.store.read(row["document_path"]))

    def residuals(self, row: dict) -> pa.Table:
        return pq.read_table(pa.BufferReader(self.store.read(row["residuals_path"])))

    def arrays(self, row: dict) -> tuple[dict, dict]:
        """``({name: ndarray}, {name: attrs})`` of a version's Zarr group."""
        import zarr

        group = zarr.open_group(store=self.store.zarr_store(row["zarr_path"], read_only=True), mode="r")
        arrays, attrs = {}, {}
        for name in group.attrs.get("arrays", []):
            arr = group[name]
            arrays[name] = np.asarray(arr[...])
            attrs[name] = dict(arr.attrs)
        return arrays, attrs

    def observations(self):
        """``(camera_id, session_id, image, key, table)`` of every cached image."""
        for cam in self.store.listdir("observations"):
            if not (cam.startswith("camera_id=") and ID_PATTERN.fullmatch(cam[10:])):
                continue
            for ses in self.store.listdir(f"observations/{cam}"):
                if not (ses.startswith("session_id=") and ID_PATTERN.fullmatch(ses[11:])):
                    continue
                for name in self.store.listdir(f"observations/{cam}/{ses}"):
                    if not name.endswith(".parquet"):
                        continue
                    table = pq.read_table(pa.BufferReader(
                        self.store.read(f"observations/{cam}/{ses}/{name}")))
                    meta = table.schema.metadata or {}
                    image = meta.get(b"fieldcal.image", b"").decode()
                    key = meta.get(b"fieldcal.content_sha256", b"").decode()
                    if not image or not SHA256_PATTERN.fullmatch(key):
                        continue
                    yield cam[10:], ses[11:], image, key, table


def _migrate_version(old: OldLake, lake, row: dict) -> int:
    doc = old.document(row)
    arrays, attrs = old.arrays(row)
    residuals = old.residuals(row)
    lake.commit(doc, arrays, residuals, array_attrs=attrs,
                original={"committed": row["committed"], "forced": row["forced"]},
                info={"migrated_from": old.url})
    return residuals.num_rows


def _migrate_observations(old: OldLake, lake, report: Report, batch: int = 500) -> None:
    done = {}
    pending: dict[str, list] = {k: [] for k in obs.KINDS}

    def flush(kind):
        if pending[kind]:
            lake.tables.append(kind, pa.concat_tables(pending[kind]),
                               {"action": "migrate", "migrated_from": old.url})
            pending[kind] = []

    for cam, ses, image, key, table in old.observations():
        if (cam, ses) not in done:
            done[(cam, ses)] = lake.cached_keys(cam, ses)
        if (image, key) in done[(cam, ses)]:
            continue
        kind, rows = obs.rows_for(cam, ses, image, key, table)
        pending[kind].append(rows)
        report.observation_images += 1
        report.observation_rows += table.num_rows
        if len(pending[kind]) >= batch:
            flush(kind)
    for kind in obs.KINDS:
        flush(kind)


def migrate(old: OldLake, lake) -> Report:
    """Bring every version and observation of ``old`` into ``lake``, then :func:`verify`.

    Parameters
    ----------
    old : OldLake
    lake : fieldcal.lake.store.Lake
        The destination (a new folder or prefix: the first layout's ``catalog/`` and
        ``residuals/`` folders have the names of the new tables).

    Raises
    ------
    LakeError
        Something of ``old`` cannot be read, or the verification finds a difference.
    """
    if lake.url.rstrip("/") == old.url.rstrip("/"):
        raise LakeError(f"migrate into a new lake, not into {old.url} itself")
    report = Report()
    rows = old.catalog()
    present = set(lake.tables.scan("catalog", columns=["version"])["version"].to_pylist())
    for row in rows:
        if row["version"] in present:
            continue
        try:
            report.residual_rows += _migrate_version(old, lake, row)
        except (OSError, ValueError, KeyError) as e:
            raise LakeError(f"cannot migrate version {row['version']}: {reason(e)}") from None
        report.versions += 1
    _migrate_observations(old, lake, report)
    verify(old, lake)
    return report


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (np.isnan(a) and np.isnan(b))
    return a == b


def _same_rows(a: pa.Table, b: pa.Table) -> bool:
    """The columns of ``b`` hold the same values in ``a`` and ``b`` (NaN equal to NaN)."""
    cols = [c for c in b.column_names if c in a.column_names]
    if a.num_rows != b.num_rows or len(cols) != len(b.column_names):
        return False
    for c in cols:
        x, y = a[c].to_pylist(), b[c].to_pylist()
        if not all(_same(u, v) for u, v in zip(x, y, strict=True)):
            return False
    return True


def _verify_version(old: OldLake, lake, row: dict) -> None:
    v = row["version"]
    new = lake.row(v)
    diff = [k for k in row if k not in _PATH_COLUMNS and not _same(row[k], new.get(k))]
    if diff:
        raise LakeError(f"migration check: version {v}: catalog columns differ: {diff}")
    if lake.load_document(v) != old.document(row):
        raise LakeError(f"migration check: version {v}: the documents differ")
    arrays, _ = old.arrays(row)
    group = lake.open_zarr(v)
    for name, want in arrays.items():
        if not np.array_equal(np.asarray(group[name][...]), want, equal_nan=True):
            raise LakeError(f"migration check: version {v}: array {name} differs")
    a, b = old.residuals(row), lake.read_residuals(v)
    if not _same_rows(a, b.select([c for c in b.column_names if c in a.column_names])):
        raise LakeError(f"migration check: version {v}: residual rows differ")


def verify(old: OldLake, lake) -> None:
    """Every version and observation of ``old`` is in ``lake`` with equal values (LakeError if not)."""
    rows = old.catalog()
    versions = set(lake.tables.scan("catalog", columns=["version"])["version"].to_pylist())
    missing = [r["version"] for r in rows if r["version"] not in versions]
    if missing:
        raise LakeError(f"migration check: {len(missing)} version(s) missing, first {missing[0]}")
    for row in rows:
        _verify_version(old, lake, row)
    for cam, ses, image, key, table in old.observations():
        got = lake.read_observations(cam, ses, image, key)
        if got is None or not _same_rows(table, got):
            raise LakeError(f"migration check: observations of {cam}/{ses}/{image} differ")
