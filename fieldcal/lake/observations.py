"""The observations cache: what was measured in each image, keyed by the image's content.

Two Delta tables, one schema each (:func:`fieldcal.lake.tables.table_schema`):
``observations_field`` (targets measured in a field image,
``schemas/measurements.arrow.json``) and ``observations_goniometer`` (the spot of a
goniometer frame, :data:`fieldcal.contract.goniometer_schema.MEASUREMENT_SCHEMA`). Each row also
holds ``camera_id``, ``session_id``, ``image`` (the session-relative name), ``key`` (the
cache key: the image's content hash, or a hash of it and the measuring settings), the
image's own ``image_sha256`` and the ``measure_settings`` (JSON) when known (the schema
metadata ``fieldcal.image_sha256`` and ``fieldcal.measure`` of the table written), and
``row`` (the row's position in the image's table). An image's rows are written in one
append, so they are all there or none. An image measured with no result (no target
found) has one row with ``row = -1`` and the measurement columns null, so that it is not
measured again either.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute  # noqa: F401 - pa.compute
import pyarrow.dataset as ds

from fieldcal.errors import InputError
from fieldcal.lake.ids import check_image_name
from fieldcal.lake.tables import table_schema

__all__ = ["kind_of", "rows_for", "strip", "load_session", "has_key", "KINDS"]

KINDS = ("observations_field", "observations_goniometer")
_EXTRA = ("camera_id", "session_id", "image", "key", "image_sha256", "measure_settings", "row")


def _own_schema(kind: str) -> pa.Schema:
    """The measuring step's schema of a kind (with its documentation)."""
    from fieldcal.contract.schemas import arrow_schema
    from fieldcal.lake.tables import goniometer_spot_schema

    return arrow_schema("measurements") if kind == "observations_field" else goniometer_spot_schema()


def _own_columns(kind: str) -> list[pa.Field]:
    """The measurement's own columns of a kind, with their nullability in the kind's schema."""
    return list(_own_schema(kind))


def kind_of(table: pa.Table, where: str) -> str:
    """``observations_field`` or ``observations_goniometer``, told by the table's columns."""
    names = set(table.column_names)
    for kind in KINDS:
        needed = {f.name for f in _own_columns(kind) if not f.nullable}
        if needed <= names:
            return kind
    raise InputError("observations must have the columns of schemas/measurements.arrow.json "
                     "(field) or of fieldcal.contract.goniometer_schema.MEASUREMENT_SCHEMA (goniometer); "
                     f"got {sorted(names)}", where)


def rows_for(camera_id: str, session_id: str, image_name: str, key: str,
             table: pa.Table) -> tuple[str, pa.Table]:
    """``(kind, rows)``: an image's measurements as rows of its observations table."""
    check_image_name(image_name)
    if not isinstance(table, pa.Table):
        raise InputError(f"observations must be a pyarrow.Table, got {type(table).__name__}",
                         image_name)
    kind = kind_of(table, image_name)
    clash = set(table.column_names) & (set(_EXTRA) - {"image"})
    if clash:
        raise InputError(f"observation columns {sorted(clash)} are added by the lake", image_name)
    schema = table_schema(kind)
    unknown = set(table.column_names) - set(schema.names)
    if unknown:
        raise InputError(f"observation columns {sorted(unknown)} are not in the {kind} schema",
                         image_name)
    n = table.num_rows
    for f in _own_columns(kind):
        if not f.nullable and f.name in table.column_names and table[f.name].null_count:
            raise InputError(f"observation column {f.name!r} has null values", image_name)
    meta = table.schema.metadata or {}
    sha, settings = meta.get(b"fieldcal.image_sha256"), meta.get(b"fieldcal.measure")
    m = max(n, 1)  # an empty result is one marker row (row = -1)
    fixed = {"camera_id": [camera_id] * m, "session_id": [session_id] * m,
             "image": [image_name] * m, "key": [key] * m,
             "image_sha256": [sha.decode() if sha else None] * m,
             "measure_settings": [settings.decode() if settings else None] * m,
             "row": list(range(n)) if n else [-1]}
    cols = []
    for f in schema:
        if f.name in fixed:
            cols.append(pa.array(fixed[f.name], f.type))
        elif f.name in table.column_names and n:
            try:
                cols.append(table[f.name].cast(f.type))
            except (pa.ArrowException, ValueError) as e:
                raise InputError(f"observation column {f.name!r} cannot be read as {f.type}: {e}",
                                 image_name) from None
        else:
            cols.append(pa.nulls(m, f.type))
    return kind, pa.Table.from_arrays(cols, schema=schema)


def strip(kind: str, rows: pa.Table) -> pa.Table:
    """One image's rows back as the measuring step's table (in row order)."""
    rows = rows.filter(pa.compute.greater_equal(rows["row"], 0)).sort_by("row")
    schema = _own_schema(kind)
    return pa.Table.from_arrays([rows[f.name].cast(f.type) for f in schema], schema=schema)


def has_key(tables, camera_id: str, session_id: str, image: str, key: str) -> bool:
    """Whether an image's observations under ``key`` are cached: a key-only probe (the
    ``key`` column of the camera's files whose statistics may hold the session and key),
    not a read of the session's observations as :func:`load_session` does."""
    f = (ds.field("session_id") == session_id) & (ds.field("image") == image) & (ds.field("key") == key)
    return any(tables.scan(kind, filter=f, columns=["key"], partition={"camera_id": camera_id},
                           equal={"session_id": session_id, "key": key}).num_rows
               for kind in KINDS if tables.exists(kind))


def load_session(tables, camera_id: str, session_id: str) -> dict:
    """``{(image, key): (kind, table)}`` of every image of a session with observations."""
    out = {}
    f = (ds.field("camera_id") == camera_id) & (ds.field("session_id") == session_id)
    for kind in KINDS:
        if not tables.exists(kind):   # (and no import of the other method's schema)
            continue
        rows = tables.scan(kind, filter=f, partition={"camera_id": camera_id},
                           equal={"session_id": session_id})
        if not rows.num_rows:
            continue
        for k, part in _groups(rows):
            out[k] = (kind, strip(kind, part))
    return out


def _groups(rows: pa.Table):
    """``((image, key), rows)`` per image and key, each part in row order and with one copy of
    each row number (two runs may have cached the same image at once: the first one read is
    kept). One stable sort of the whole table, then zero-copy slices (not a ``take`` per image)."""
    order = pa.compute.sort_indices(rows, sort_keys=[("image", "ascending"), ("key", "ascending"),
                                                      ("row", "ascending")])
    rows = rows.take(order)
    same = _same_as_previous(rows, ("image", "key"))
    duplicate = same & _same_as_previous(rows, ("row",))
    if duplicate.any():
        rows = rows.filter(pa.array(~duplicate))
        same = _same_as_previous(rows, ("image", "key"))
    starts = np.flatnonzero(~same)
    ends = np.append(starts[1:], rows.num_rows)
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        yield (rows["image"][a].as_py(), rows["key"][a].as_py()), rows.slice(a, b - a)


def _same_as_previous(rows: pa.Table, columns) -> np.ndarray:
    """Per row, whether its ``columns`` equal the previous row's (False for the first)."""
    same = np.zeros(rows.num_rows, bool)
    if rows.num_rows > 1:
        same[1:] = True
        for name in columns:
            values = rows[name].to_numpy(zero_copy_only=False)
            same[1:] &= values[1:] == values[:-1]
    return same
