"""Calibration history: DuckDB SQL over the lake's catalog, residuals and observations.

:func:`connect` opens an in-memory DuckDB connection with three views:

- ``catalog``: one row per committed version (``schemas/catalog.arrow.json``), read with
  :meth:`fieldcal.lake.store.Lake.catalog` and registered as an Arrow table (the same code path
  for a local and an object-store lake; DuckDB's httpfs extension is not needed);
- ``residuals``: the residual tables (``schemas/residuals.arrow.json``) of the committed
  versions only, with the hive partition columns ``camera_id``, ``session_id``, ``version``;
- ``observations``: the cached per-image observations with ``camera_id``, ``session_id``.

Residuals and observations are read by DuckDB's ``read_parquet`` straight from the files
(lazily); for an fsspec lake the lake's filesystem is registered with DuckDB
(``register_filesystem``). Empty views have the right columns, so every query works on an
empty lake. Timestamps are ``TIMESTAMP WITH TIME ZONE`` in UTC.

:func:`camera_history` (one camera over time), :func:`fleet` (every camera's latest
calibration in a date range) and :func:`sql` (anything) return :class:`pyarrow.Table`;
:func:`to_text`, :func:`to_csv` and :func:`to_json` format a table for people and scripts.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import math

import duckdb
import pyarrow as pa

from fieldcal.errors import InputError, LakeError
from fieldcal.session.schemas import arrow_schema

__all__ = ["connect", "sql", "camera_history", "fleet", "to_text", "to_csv", "to_json",
           "format_table", "FORMATS"]

UTC = dt.UTC
HIVE_TYPES = "{'camera_id': 'VARCHAR', 'session_id': 'VARCHAR', 'version': 'VARCHAR'}"
HIVE_TYPES_OBS = "{'camera_id': 'VARCHAR', 'session_id': 'VARCHAR'}"
FORMATS = ("text", "csv", "json")


def _quote(text: str) -> str:
    return "'" + text.replace("'", "''") + "'"


def _empty_view(con, name: str, schema: pa.Schema, keys: tuple[str, ...]) -> None:
    fields = [pa.field(k, pa.string()) for k in keys] + [f for f in schema if f.name not in keys]
    con.register(name, pa.schema(fields).empty_table())


def connect(lake) -> duckdb.DuckDBPyConnection:
    """An in-memory DuckDB connection with the views ``catalog``, ``residuals``, ``observations``.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake

    Returns
    -------
    duckdb.DuckDBPyConnection
        Close it when done (or use it as a context manager).
    """
    con = duckdb.connect(":memory:")
    try:
        con.sql("SET TimeZone = 'UTC'")
        if not lake.is_local:
            con.register_filesystem(lake.fs)
        catalog = lake.catalog()
        con.register("catalog", catalog)

        paths = catalog["residuals_path"].to_pylist()
        if paths:
            files = ", ".join(_quote(lake.uri(p)) for p in paths)
            con.sql(f"CREATE VIEW residuals AS SELECT * FROM read_parquet([{files}], "
                    f"hive_partitioning = true, hive_types = {HIVE_TYPES}, union_by_name = true)")
        else:
            _empty_view(con, "residuals", arrow_schema("residuals"),
                        ("camera_id", "session_id", "version"))

        pattern = "observations/camera_id=*/session_id=*/*.parquet"
        if lake.glob(pattern):
            con.sql(f"CREATE VIEW observations AS SELECT * FROM read_parquet("
                    f"{_quote(lake.uri(pattern))}, hive_partitioning = true, "
                    f"hive_types = {HIVE_TYPES_OBS}, union_by_name = true)")
        else:
            _empty_view(con, "observations", arrow_schema("observations"),
                        ("camera_id", "session_id"))
    except duckdb.Error as e:
        con.close()
        raise LakeError(f"cannot open the lake {lake.url} in DuckDB: {' '.join(str(e).split())}") \
            from None
    except BaseException:
        con.close()
        raise
    return con


def sql(lake, query: str, params=None) -> pa.Table:
    """Run a SQL query over the lake's views (:func:`connect`) and return its result.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    query : str
        DuckDB SQL over ``catalog``, ``residuals`` and ``observations``.
    params : sequence, optional
        Values for ``?`` placeholders.

    Raises
    ------
    InputError
        The query is not valid SQL or refers to unknown columns / tables.
    """
    con = connect(lake)
    try:
        try:
            rel = con.sql(query, params=params)
        except duckdb.Error as e:
            raise InputError(" ".join(str(e).split()), "sql") from None
        return rel.to_arrow_table() if rel is not None else pa.table({})
    finally:
        con.close()


def _param_columns(parameters) -> list[str]:
    """The catalog columns for ``parameters``: each value, its sigma when there is one."""
    schema = arrow_schema("catalog")
    if isinstance(parameters, str):
        parameters = (parameters,)
    out = []
    for name in parameters:
        if name not in schema.names or not (pa.types.is_floating(schema.field(name).type)
                                            or pa.types.is_integer(schema.field(name).type)):
            numeric = [f.name for f in schema if pa.types.is_floating(f.type)
                       or pa.types.is_integer(f.type)]
            raise InputError(f"unknown numeric catalog column {name!r}; choose from "
                             f"{', '.join(numeric)}", "camera_history")
        out.append(name)
    return out


def camera_history(lake, camera_id: str, parameters=("f_mm", "xp_mm", "yp_mm"), *,
                   all_versions: bool = False) -> pa.Table:
    """One camera over time: its calibrations ordered by acquisition time.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    camera_id : str
    parameters : sequence of str
        Numeric catalog columns to show (default the principal distance and point [mm]).
        Each comes with ``sigma_<name>`` when the catalog has it and ``delta_<name>``, the
        change since the first row of the history (same unit).
    all_versions : bool
        Every committed version instead of the latest version of each session.

    Returns
    -------
    pyarrow.Table
        ``camera_id, session_id, version, method, acquired, created, forced``, then per
        parameter ``name, sigma_name, delta_name``, then ``rmse_px, sigma0, sigma_fit_px,
        n_images, n_observations, n_rejected, code_version``; ordered by ``acquired``
        (versions without it last), then commit time.
    """
    names = list(dict.fromkeys(_param_columns(parameters)))
    schema = arrow_schema("catalog")
    cols = []
    for name in names:
        cols.append(name)
        if "sigma_" + name in schema.names:
            cols.append("sigma_" + name)
        cols.append(f"{name} - first_value({name}) OVER w AS delta_{name}")
    tail = [c for c in ("rmse_px", "sigma0", "sigma_fit_px", "n_images", "n_observations",
                        "n_rejected", "code_version") if c not in names]
    latest = "" if all_versions else (
        "QUALIFY row_number() OVER (PARTITION BY session_id "
        "ORDER BY committed DESC, version DESC) = 1")
    query = f"""
        WITH c AS (SELECT * FROM catalog WHERE camera_id = ? {latest})
        SELECT camera_id, session_id, version, method, acquired, created, forced,
               {", ".join(cols + tail)}
        FROM c
        WINDOW w AS (ORDER BY acquired ASC NULLS LAST, committed, version
                     ROWS BETWEEN UNBOUNDED PRECEDING AND CURRENT ROW)
        ORDER BY acquired ASC NULLS LAST, committed, version
    """
    return sql(lake, query, [camera_id])


def _bound(value, *, end: bool):
    """A range bound as an aware UTC datetime; a date as an end bound means the day's end."""
    if value is None:
        return None
    if isinstance(value, str):
        try:
            parsed = dt.datetime.fromisoformat(value.strip())
        except ValueError:
            raise InputError(f"not an ISO 8601 date or time: {value!r}", "fleet") from None
        is_date = len(value.strip()) <= 10
        value = parsed.date() if is_date else parsed
    if isinstance(value, dt.datetime):
        t = value if value.tzinfo else value.replace(tzinfo=UTC)
        return t.astimezone(UTC)
    if isinstance(value, dt.date):
        t = dt.datetime(value.year, value.month, value.day, tzinfo=UTC)
        return t + dt.timedelta(days=1) - dt.timedelta(microseconds=1) if end else t
    raise InputError(f"expected a date or time, got {type(value).__name__}", "fleet")


def fleet(lake, start=None, end=None) -> pa.Table:
    """Every camera's latest calibration acquired in ``[start, end]``.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    start, end : str, date or datetime, optional
        Inclusive bounds on the acquisition time (the creation time for versions without
        one); a date as ``end`` includes that whole day. Naive times are UTC.

    Returns
    -------
    pyarrow.Table
        One catalog row per camera (all catalog columns), ordered by ``camera_id``: the
        version with the latest acquisition time in the range, the latest commit of it.
    """
    lo, hi = _bound(start, end=False), _bound(end, end=True)
    if lo is not None and hi is not None and hi < lo:
        raise InputError(f"end {end!r} is before start {start!r}", "fleet")
    query = """
        WITH c AS (
            SELECT *, coalesce(acquired, created) AS _t FROM catalog
            WHERE (?::TIMESTAMPTZ IS NULL OR coalesce(acquired, created) >= ?::TIMESTAMPTZ)
              AND (?::TIMESTAMPTZ IS NULL OR coalesce(acquired, created) <= ?::TIMESTAMPTZ))
        SELECT * EXCLUDE (_t) FROM c
        QUALIFY row_number() OVER (PARTITION BY camera_id
                                   ORDER BY _t DESC, committed DESC, version DESC) = 1
        ORDER BY camera_id
    """
    return sql(lake, query, [lo, lo, hi, hi])


# --------------------------------------------------------------------------------------
# formatting
# --------------------------------------------------------------------------------------
def _cell(value, float_format: str | None):
    """A JSON-ready value (``float_format`` None) or display text of one cell."""
    if isinstance(value, dt.datetime):
        if value.tzinfo is not None:
            value = value.astimezone(UTC)
        return value.isoformat().replace("+00:00", "Z")
    if isinstance(value, dt.date):
        return value.isoformat()
    if isinstance(value, float):
        if not math.isfinite(value):
            return None if float_format is None else ("nan" if math.isnan(value) else str(value))
        if float_format is None:
            return value
        return repr(value) if float_format == "r" else format(value, float_format)
    if isinstance(value, bool):
        return value if float_format is None else str(value).lower()
    if isinstance(value, list):
        return value if float_format is None else ";".join(str(_cell(v, float_format) or "")
                                                          for v in value)
    if value is None:
        return None if float_format is None else ""
    return value if float_format is None else str(value)


def to_text(table: pa.Table, *, float_format: str = ".7g") -> str:
    """An aligned plain-text table (numbers right-aligned), one line per row."""
    names = table.column_names
    rows = [[_cell(v, float_format) for v in r.values()] for r in table.to_pylist()]
    numeric = [pa.types.is_integer(f.type) or pa.types.is_floating(f.type) for f in table.schema]
    widths = [max([len(n)] + [len(r[i]) for r in rows]) for i, n in enumerate(names)]

    def line(cells):
        return "  ".join(c.rjust(w) if num else c.ljust(w)
                         for c, w, num in zip(cells, widths, numeric, strict=True)).rstrip()

    out = [line(names), line(["-" * w for w in widths])] + [line(r) for r in rows]
    return "\n".join(out) + "\n"


def to_csv(table: pa.Table) -> str:
    """CSV with a header; floats at full precision (``repr``), timestamps ISO 8601 UTC."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(table.column_names)
    for r in table.to_pylist():
        writer.writerow([_cell(v, "r") for v in r.values()])
    return buf.getvalue()


def to_json(table: pa.Table, *, indent: int | None = None) -> str:
    """A JSON array of row objects; timestamps ISO 8601 UTC, NaN as null."""
    rows = [{k: _cell(v, None) for k, v in r.items()} for r in table.to_pylist()]
    return json.dumps(rows, indent=indent, allow_nan=False)


def format_table(table: pa.Table, fmt: str = "text") -> str:
    """Format ``table`` as ``"text"``, ``"csv"`` or ``"json"``."""
    if fmt == "text":
        return to_text(table)
    if fmt == "csv":
        return to_csv(table)
    if fmt == "json":
        return to_json(table)
    raise InputError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}", "format_table")
