"""Calibration history: read-only DuckDB SQL over the lake's Delta tables, as of any time.

:func:`connect` opens an in-memory DuckDB connection with one view per table of the lake
(:mod:`fieldcal.lake.tables`), each read through ``deltalake`` as a pyarrow dataset (the
same code path for a local and an object-store lake; DuckDB's delta extension is not
needed):

- ``catalog``: one row per committed version (``schemas/catalog.arrow.json``);
- ``residuals``: the residual rows of catalogued versions only (a semi-join on
  ``version``), with ``camera_id``, ``session_id``, ``version``;
- ``observations_field`` and ``observations_goniometer``: the cached measurements;
- ``rigs``: one row per committed rig version (its heads' versions, CONTRACT section 3).

``as_of`` (an ISO 8601 time or a datetime) reads every table as it was then (Delta time
travel): the catalog of that time and the residuals of its versions. Empty tables have
their columns, so every query works on an empty lake. Timestamps are ``TIMESTAMP WITH TIME
ZONE`` in UTC. A damaged data file is left out of its view and listed in
``lake.problems``.

The connection is read-only for the query: only ``SELECT`` statements run, and DuckDB's
external access is switched off and locked before the query (no ``COPY``, ``ATTACH``,
``INSTALL``, ``read_csv('/etc/passwd')``: the query sees the views and nothing else).

:func:`camera_history` (one camera over time), :func:`rig_history` (a rig's relative
orientations over time, from its rig documents), :func:`fleet` (every camera's latest
calibration in a date range), :func:`fleet_pairs` (that and the version before it) and
:func:`sql` (anything) return :class:`pyarrow.Table`; :func:`to_text`, :func:`to_csv` and
:func:`to_json` format a table for people and scripts.
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import math
import re

import duckdb
import pyarrow as pa
import pyarrow.compute as pc

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError, LakeError
from fieldcal.lake.order import ORDER_SQL, ORDER_SQL_DESC, SESSION_SQL

__all__ = ["connect", "sql", "camera_history", "rig_history", "fleet", "fleet_pairs", "pick_columns",
           "DEFAULT_COLUMNS",
           "to_text", "to_csv",
           "to_json", "format_table", "FORMATS", "VIEWS", "READ_ONLY_NOTE"]

UTC = dt.UTC
FORMATS = ("text", "csv", "json")
VIEWS = ("catalog", "residuals", "observations_field", "observations_goniometer", "rigs")
READ_ONLY_NOTE = ("history --sql is read-only: one or more SELECT statements over the views "
                  f"{', '.join(VIEWS)}; no COPY, ATTACH, INSTALL or file access")


def _as_of(value):
    if value is None:
        return None
    from fieldcal.lake.ids import parse_time

    return parse_time(value, "--as-of")


def _register(con, lake, name: str, as_of, only: dict | None = None) -> None:
    if name == "catalog":
        f = None
        for col, value in (only or {}).items():
            e = pc.field(col) == value
            f = e if f is None else f & e
        if only:
            con.register("catalog", lake.catalog(as_of=as_of, filter=f, equal=only, sort=False))
            return
    if name == "rigs":          # committed rig versions only (Lake.rig_catalog: their heads in the catalog)
        con.register("rigs", lake.rig_catalog(as_of=as_of))
        return
    dataset, rest = lake.tables.lazy(name, as_of=as_of)
    con.register(f"_{name}_recent", rest)
    if dataset is not None:
        con.register(f"_{name}_compacted", dataset)
        source = f"SELECT * FROM _{name}_compacted UNION ALL BY NAME SELECT * FROM _{name}_recent"
    else:
        source = f"SELECT * FROM _{name}_recent"
    if name == "residuals":
        con.sql(f"CREATE VIEW residuals AS SELECT r.* FROM ({source}) r "
                "SEMI JOIN catalog c ON r.version = c.version")
    else:
        con.sql(f"CREATE VIEW {name} AS {source}")


def views_of(query: str) -> tuple[str, ...]:
    """The views a query names (each is read only when named; ``catalog`` always)."""
    words = set(re.findall(r"[A-Za-z_]+", query.lower()))
    return tuple(v for v in VIEWS if v in words or v == "catalog")


def connect(lake, *, as_of=None, views=VIEWS, only: dict | None = None) -> duckdb.DuckDBPyConnection:
    """An in-memory, read-only DuckDB connection with the lake's views (module docstring).

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    as_of : str or datetime, optional
        Read the tables as they were at that time.
    views : sequence of str
        The views to make (``catalog`` is always made).
    only : dict, optional
        ``{column: value}``: the catalog view holds only those rows (read from the row
        groups that may hold them).

    Returns
    -------
    duckdb.DuckDBPyConnection
        Close it when done (or use it as a context manager).
    """
    con = duckdb.connect(":memory:")
    when = _as_of(as_of)
    try:
        con.sql("SET TimeZone = 'UTC'")
        for name in dict.fromkeys(("catalog",) + tuple(views)):
            if name not in VIEWS:
                raise InputError(f"unknown view {name!r}; the views are {', '.join(VIEWS)}", "history")
            _register(con, lake, name, when, only)
        con.sql("SET enable_external_access = false")
        con.sql("SET lock_configuration = true")
    except duckdb.Error as e:
        con.close()
        raise LakeError(f"cannot open the lake {lake.url} in DuckDB: {' '.join(str(e).split())}") \
            from None
    except BaseException:
        con.close()
        raise
    return con


def _check_read_only(con, query: str) -> None:
    try:
        statements = con.extract_statements(query)
    except duckdb.Error as e:
        raise InputError(" ".join(str(e).split()), "sql") from None
    if not statements:
        raise InputError("the query is empty", "sql")
    for st in statements:
        if st.type != duckdb.StatementType.SELECT:
            raise InputError(f"{READ_ONLY_NOTE} (got a {st.type.name} statement)", "sql")


def sql(lake, query: str, params=None, *, as_of=None, views=None, only: dict | None = None) -> pa.Table:
    """Run a read-only SQL query over the lake's views (:func:`connect`) and return its result.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    query : str
        DuckDB ``SELECT`` over ``catalog``, ``residuals``, ``observations_field`` and
        ``observations_goniometer``.
    params : sequence, optional
        Values for ``?`` placeholders.
    as_of : str or datetime, optional
        Query the lake as it was at that time.
    views : sequence of str, optional
        The views to read (default: those the query names).

    Raises
    ------
    InputError
        The query is not valid SQL, refers to unknown columns / tables, is not a
        ``SELECT`` or touches anything outside the views.
    """
    con = connect(lake, as_of=as_of, views=views_of(query) if views is None else views, only=only)
    try:
        _check_read_only(con, query)
        try:
            rel = con.sql(query, params=params)
        except duckdb.Error as e:
            text = " ".join(str(e).split())
            if isinstance(e, duckdb.PermissionException):
                text = f"{READ_ONLY_NOTE}: {text}"
            raise InputError(text, "sql") from None
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
                   all_versions: bool = False, as_of=None) -> pa.Table:
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
    as_of : str or datetime, optional
        The history as the lake knew it at that time.

    Returns
    -------
    pyarrow.Table
        ``camera_id, session_id, version, method, acquired, created, forced``, then per
        parameter ``name, sigma_name, delta_name``, then ``rmse_px, sigma0, sigma_fit_px,
        n_images, n_observations, n_rejected, code_version``; in the order of
        :mod:`fieldcal.lake.order` (acquisition time, the creation time of a version without
        one, ties by commit order); a session is a ``session_id`` with its acquisition time.
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
        f"QUALIFY row_number() OVER (PARTITION BY {SESSION_SQL} ORDER BY {ORDER_SQL_DESC}) = 1")
    query = f"""
        WITH c AS (SELECT * FROM catalog WHERE camera_id = ? {latest})
        SELECT camera_id, session_id, version, method, acquired, created, forced,
               {", ".join(cols + tail)}
        FROM c
        WINDOW w AS (ORDER BY {ORDER_SQL} ROWS BETWEEN UNBOUNDED PRECEDING AND CURRENT ROW)
        ORDER BY {ORDER_SQL}
    """
    return sql(lake, query, [camera_id], as_of=as_of, views=("catalog",), only={"camera_id": camera_id})


RIG_COMPONENTS = ("x", "y", "z")


def _rig_rows(lake, row: dict, doc: dict) -> list[dict]:
    """One history row per head but the reference of one rig version (:func:`rig_history`)."""
    import numpy as np

    from fieldcal.model.rotations import opk_from_R_world_to_camera

    out = []
    for head in doc["heads"]:
        if head["camera_id"] == doc["reference"]:
            continue
        R = np.asarray(head["R_camera_to_rig"], float)
        angles = np.degrees(opk_from_R_world_to_camera(R.T))      # R_camera_to_rig = Rz(k) Ry(p) Rx(o)
        r = {"rig_id": row["rig_id"], "session_id": row["session_id"], "version": row["version"],
             "acquired": row["acquired"], "committed": row["committed"], "camera_id": head["camera_id"],
             "head_version": head["version"], "R_camera_to_rig": R}
        r.update(zip(("omega_deg", "phi_deg", "kappa_deg"), map(float, angles), strict=True))
        for i, c in enumerate(RIG_COMPONENTS):
            r[f"sigma_rot_{c}_arcsec"] = float(head["sigma_rotation_arcsec"][i])
        for i, c in enumerate(RIG_COMPONENTS):
            r[f"t_{c}_mm"] = 1000.0 * float(head["t_camera_in_rig_m"][i])
            r[f"sigma_t_{c}_mm"] = float(head["sigma_t_mm"][i])
        r.update({"rmse_px": head.get("rmse_px"), "sigma0": row["sigma0"], "n_exposures": row["n_exposures"]})
        out.append(r)
    return out


def _with_changes(rows: list[dict]) -> list[dict]:
    """Per head, the change since its first row: ``delta_rot_*_arcsec``, the small rotation about
    the rig frame's axes ``log(R R_first^T)`` (the convention of ``sigma_rotation_arcsec`` and of
    ``fieldcal compare RIG_V1 RIG_V2``), and ``delta_t_*_mm``."""
    import numpy as np

    from fieldcal.model.rotations import rotvec_from_R

    first: dict[str, dict] = {}
    for r in rows:
        f = first.setdefault(r["camera_id"], r)
        d_rot = rotvec_from_R(r["R_camera_to_rig"] @ f["R_camera_to_rig"].T) * (180.0 * 3600.0 / np.pi)
        for i, c in enumerate(RIG_COMPONENTS):
            r[f"delta_rot_{c}_arcsec"] = float(d_rot[i])
            r[f"delta_t_{c}_mm"] = r[f"t_{c}_mm"] - f[f"t_{c}_mm"]
    return rows


RIG_HISTORY_COLUMNS = (
    ["rig_id", "session_id", "version", "acquired", "committed", "camera_id", "head_version",
     "omega_deg", "phi_deg", "kappa_deg"]
    + [f"{k}_rot_{c}_arcsec" for k in ("delta", "sigma") for c in RIG_COMPONENTS]
    + [f"{k}_{c}_mm" for k in ("t", "sigma_t", "delta_t") for c in RIG_COMPONENTS]
    + ["rmse_px", "sigma0", "n_exposures"])
"""The columns of :func:`rig_history`, in order."""


def rig_history(lake, rig_id: str, *, all_versions: bool = False, as_of=None) -> pa.Table:
    """A rig's relative orientations over time: one row per rig version and head (the reference
    head, the identity by definition, left out), from the ``rigs`` table and its rig documents.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    rig_id : str
    all_versions : bool
        Every committed rig version instead of the latest version of each session.
    as_of : str or datetime, optional
        The history as the lake knew it at that time.

    Returns
    -------
    pyarrow.Table
        :data:`RIG_HISTORY_COLUMNS`: the head's ``R_camera_to_rig`` as ``omega, phi, kappa``
        [deg] (``R = Rz(kappa) Ry(phi) Rx(omega)``, CONTRACT section 1), the change of its rotation
        since the head's first row as a small rotation about the rig frame's axes [arcsec] and
        the rotation's sigmas [arcsec], its lever arm ``t_camera_in_rig`` [mm] with sigmas and
        change; ordered by ``acquired`` (versions without it last), then commit time.
    """
    t = lake.rig_catalog(rig_id=rig_id, as_of=_as_of(as_of)).to_pylist()
    if not all_versions:
        latest = {}
        for row in t:                                   # oldest first: the last of a session wins
            latest[row["session_id"]] = row
        t = list(latest.values())
    far = dt.datetime.max.replace(tzinfo=UTC)
    t.sort(key=lambda r: (r["acquired"] or far, r["committed"], r["version"]))
    rows = []
    for row in t:
        rows += _rig_rows(lake, row, lake.load_rig_document(row["version"], row=row))
    rows = _with_changes(rows)
    schema = pa.schema([(c, pa.string() if c in ("rig_id", "session_id", "version", "camera_id", "head_version")
                         else pa.timestamp("us", "UTC") if c in ("acquired", "committed")
                         else pa.int32() if c == "n_exposures" else pa.float64()) for c in RIG_HISTORY_COLUMNS])
    return pa.Table.from_pylist([{c: r.get(c) for c in RIG_HISTORY_COLUMNS} for r in rows], schema=schema)


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
        try:
            return t.astimezone(UTC)
        except OverflowError:         # 9999-12-31T23:59-23:00 is after the year 9999 in UTC
            raise InputError(f"out of range in UTC (years 1 to 9999): {value.isoformat()}", "fleet") from None
    if isinstance(value, dt.date):
        t = dt.datetime(value.year, value.month, value.day, tzinfo=UTC)
        if not end:
            return t
        try:
            return t + dt.timedelta(days=1) - dt.timedelta(microseconds=1)
        except OverflowError:         # the end of 9999-12-31: the last representable time
            return dt.datetime.max.replace(tzinfo=UTC)
    raise InputError(f"expected a date or time, got {type(value).__name__}", "fleet")


def fleet(lake, start=None, end=None, *, as_of=None) -> pa.Table:
    """Every camera's latest calibration acquired in ``[start, end]``.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    start, end : str, date or datetime, optional
        Inclusive bounds on the acquisition time (the creation time for versions without
        one); a date as ``end`` includes that whole day. Naive times are UTC.
    as_of : str or datetime, optional
        The fleet as the lake knew it at that time.

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
    return sql(lake, query, [lo, lo, hi, hi], as_of=as_of, views=("catalog",))


def fleet_pairs(lake, start=None, end=None, *, as_of=None) -> pa.Table:
    """Every camera's latest calibration in ``[start, end]`` and the one before it: one query.

    The *previous* calibration follows :mod:`fieldcal.lake.order` (the latest version of each
    session, ordered by acquisition time, ties by commit order), found with window functions
    over one read of the catalog.

    Returns
    -------
    pyarrow.Table
        ``camera_id, version, method, acquired, previous_version, previous_method,
        previous_acquired`` (previous columns null for a camera with one calibration),
        ordered by ``camera_id``.
    """
    lo, hi = _bound(start, end=False), _bound(end, end=True)
    if lo is not None and hi is not None and hi < lo:
        raise InputError(f"end {end!r} is before start {start!r}", "fleet")
    query = f"""
        WITH sessions AS (
            SELECT * FROM catalog
            QUALIFY row_number() OVER (PARTITION BY camera_id, {SESSION_SQL} ORDER BY {ORDER_SQL_DESC}) = 1),
        ordered AS (
            SELECT camera_id, version, method, acquired,
                   lag(version) OVER w AS previous_version, lag(method) OVER w AS previous_method,
                   lag(acquired) OVER w AS previous_acquired
            FROM sessions
            WINDOW w AS (PARTITION BY camera_id ORDER BY {ORDER_SQL})),
        latest AS (
            SELECT camera_id, version FROM catalog
            WHERE (?::TIMESTAMPTZ IS NULL OR coalesce(acquired, created) >= ?::TIMESTAMPTZ)
              AND (?::TIMESTAMPTZ IS NULL OR coalesce(acquired, created) <= ?::TIMESTAMPTZ)
            QUALIFY row_number() OVER (PARTITION BY camera_id ORDER BY {ORDER_SQL_DESC}) = 1)
        SELECT l.camera_id, l.version, c.method, c.acquired,
               o.previous_version, o.previous_method, o.previous_acquired
        FROM latest l JOIN catalog c USING (version)
        LEFT JOIN ordered o ON o.version = l.version
        ORDER BY l.camera_id
    """
    return sql(lake, query, [lo, lo, hi, hi], as_of=as_of, views=("catalog",))


# --------------------------------------------------------------------------------------
# columns for people
# --------------------------------------------------------------------------------------
DEFAULT_COLUMNS = {
    "fleet": ("camera_id", "session_id", "acquired", "method", "f_mm", "rmse_px", "n_images"),
    "camera": ("session_id", "acquired", "{params}"),
    "changes": ("camera_id", "acquired", "max_change_um", "p_value", "changed", "flagged"),
    "rig": ("session_id", "acquired", "camera_id", "delta_rot_x_arcsec", "delta_rot_y_arcsec",
            "delta_rot_z_arcsec", "delta_t_x_mm", "delta_t_y_mm", "delta_t_z_mm"),
}
"""The columns ``fieldcal history`` shows by default (about 100 characters wide): every
camera's latest (``fleet``), one camera (``camera``; ``{params}`` stands for each parameter
asked for and its sigma), ``--fleet`` (``changes``), one rig (``rig``: the changes of its
heads' relative orientations); ``--wide`` shows every column,
``--columns`` the ones named."""


def pick_columns(table: pa.Table, view: str, columns=None, *, wide: bool = False,
                 params=("f_mm", "xp_mm", "yp_mm")) -> pa.Table:
    """The columns of ``table`` to show: ``columns`` (names, in that order), every one with
    ``wide``, else :data:`DEFAULT_COLUMNS` of ``view``.

    Raises
    ------
    InputError
        A name in ``columns`` that the table does not have (the message lists them).
    """
    if wide:
        return table
    if columns:
        names = [c for c in dict.fromkeys(columns)]
        unknown = [c for c in names if c not in table.column_names]
        if unknown:
            raise InputError(f"no column {', '.join(map(repr, unknown))} in this table; its columns: "
                             f"{', '.join(table.column_names)}", "history --columns")
        return table.select(names)
    names = []
    for c in DEFAULT_COLUMNS[view]:
        if c == "{params}":
            for p in params:
                names += [p] + ([f"sigma_{p}"] if f"sigma_{p}" in table.column_names else [])
        else:
            names.append(c)
    return table.select([c for c in dict.fromkeys(names) if c in table.column_names])


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
