"""The parts of a version, checked and prepared in memory before anything is written.

- :func:`conform_residuals`: the residual table against ``schemas/residuals.arrow.json``.
- :func:`prepare_arrays`: the arrays of the version's Zarr group (:data:`KNOWN_ARRAYS`),
  derived from the document where not given.
- :func:`catalog_row`: the version's catalog row (``schemas/catalog.arrow.json``).
- :func:`array_digest`: the SHA-256 of an array's bytes, kept in the group's attributes so
  that a missing or damaged chunk is found on reading instead of reading back as the
  fill value (zeros).
"""

from __future__ import annotations

import datetime as dt
import hashlib
import math
import re
from collections.abc import Mapping

import numpy as np
import pyarrow as pa

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError, one_line
from fieldcal.lake.ids import parse_time, plain_json
from fieldcal.model.camera import PARAM_NAMES

__all__ = ["conform_residuals", "prepare_arrays", "catalog_row", "array_digest", "reason",
           "KNOWN_ARRAYS", "KEY_COLUMNS"]

ARRAY_NAME_PATTERN = re.compile(r"[A-Za-z0-9_]+(/[A-Za-z0-9_]+)*")
KEY_COLUMNS = ("camera_id", "session_id", "version")
"""Columns the lake adds to the residual table (they may not be given)."""

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
    "correction_field": "(ny, nx, 2) [px] the model's correction (dx, dy) of docs/conventions.md section 2 "
                        "at grid pixels, in pixels along u and v: (dx / d, -dy / d). Stored as given "
                        "(fieldcal.analysis.correction.correction_arrays); none when not given.",
    "grid_u_px": "(nx,) [px] column coordinates of the correction_field grid.",
    "grid_v_px": "(ny,) [px] row coordinates of the correction_field grid.",
}
"""The arrays a version's Zarr group holds, by name. Callers (the solvers) should give
``covariance`` and ``correlation`` with ``attrs={"names": [...]}``; the others are derived
from the document when absent. Any other named numeric array is stored as given."""

_EXTERIOR_SHAPES = {"exterior/center_m": (3,), "exterior/rotation_world_to_camera": (3, 3),
                    "exterior/sigma_center_m": (3,)}


def reason(e: BaseException) -> str:
    """One line describing an exception."""
    if isinstance(e, OSError) and e.strerror:
        text = e.strerror
    else:
        text = str(e) or type(e).__name__
    return one_line(text)


def array_digest(arr: np.ndarray) -> str:
    """``sha256:<hex>`` of an array's dtype, shape and C-order bytes."""
    a = np.ascontiguousarray(arr)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return "sha256:" + h.hexdigest()


# --------------------------------------------------------------------------------------
# residuals
# --------------------------------------------------------------------------------------
def _as_table(residuals, where: str) -> pa.Table:
    if residuals is None:
        raise InputError("a residual table is required (it may have no rows)", where)
    if isinstance(residuals, Mapping):
        try:
            residuals = pa.table(dict(residuals))
        except (pa.ArrowException, TypeError, ValueError) as e:
            raise InputError(f"cannot make a table of the columns: {e}", where) from None
    if not isinstance(residuals, pa.Table):
        raise InputError(f"expected a pyarrow.Table, got {type(residuals).__name__}", where)
    clash = set(residuals.column_names) & set(KEY_COLUMNS)
    if clash:
        raise InputError(f"columns {sorted(clash)} are added by the lake", where)
    return residuals


def _check_residual_rows(table: pa.Table, where: str) -> None:
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


def conform_residuals(residuals, where: str) -> pa.Table:
    """The residual table cast to ``schemas/residuals.arrow.json`` (and only its columns).

    Missing nullable columns are filled with nulls. Columns the schema does not know are
    refused: the lake's residuals are one Delta table with one schema.
    """
    schema = arrow_schema("residuals")
    where = f"{where}: residuals"
    residuals = _as_table(residuals, where)
    extra = [n for n in residuals.column_names if n not in schema.names]
    if extra:
        raise InputError(f"columns {extra} are not in schemas/residuals.arrow.json", where)
    n = residuals.num_rows
    columns = []
    for f in schema:
        if f.name in residuals.column_names:
            col = residuals[f.name]
            try:
                col = col.cast(f.type)
            except (pa.ArrowException, ValueError) as e:
                raise InputError(f"column {f.name!r} ({col.type}) cannot be read as {f.type}: "
                                 f"{reason(e)}", where) from None
        elif f.nullable:
            col = pa.nulls(n, f.type)
        else:
            raise InputError(f"column {f.name!r} is missing", where)
        if not f.nullable and col.null_count:
            raise InputError(f"column {f.name!r} has {col.null_count} null value(s)", where)
        columns.append(col)
    table = pa.Table.from_arrays(columns, schema=schema)
    _check_residual_rows(table, where)
    return table


# --------------------------------------------------------------------------------------
# arrays
# --------------------------------------------------------------------------------------
def _as_array(name: str, value, where: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "biuf":
        raise InputError(f"array {name!r} must be numeric or boolean, got dtype {arr.dtype}", where)
    return arr


def _check_names(arrays: Mapping, array_attrs: Mapping, where: str) -> None:
    for name in list(arrays) + list(array_attrs):
        if not isinstance(name, str) or not ARRAY_NAME_PATTERN.fullmatch(name):
            raise InputError(f"array name {name!r} must be words of [A-Za-z0-9_] joined by '/'",
                             where)
    unknown_attrs = set(array_attrs) - set(arrays) - set(KNOWN_ARRAYS)
    if unknown_attrs:
        raise InputError(f"attributes given for arrays that are not given: {sorted(unknown_attrs)}",
                         where)


class _Group:
    """The arrays of a group being prepared: ``{name: (ndarray, attrs, dimension_names)}``."""

    def __init__(self, array_attrs: Mapping, where: str):
        self.out: dict[str, tuple] = {}
        self.array_attrs = array_attrs
        self.where = where

    def put(self, name, arr, attrs=None, dims=None):
        a = dict(attrs or {})
        a.update(plain_json(dict(self.array_attrs.get(name, {})), f"{self.where}: attrs of {name}"))
        self.out[name] = (np.ascontiguousarray(arr), a, dims)


def _put_parameters(group: _Group, given: dict, doc: dict) -> None:
    names13 = list(PARAM_NAMES)
    params = given.pop("parameters", None)
    if params is None:
        params = np.array([doc["parameters"][n] for n in names13], dtype=float)
    sigma = given.pop("sigma", None)
    if sigma is None:
        sigma = np.array([np.nan if doc["sigma"][n] is None else doc["sigma"][n] for n in names13],
                         dtype=float)
    for name, arr in (("parameters", params), ("sigma", sigma)):
        if arr.shape != (13,):
            raise InputError(f"array {name!r} must have shape (13,), got {arr.shape}", group.where)
        group.put(name, arr, {"names": names13}, ("parameter",))


def _put_covariances(group: _Group, given: dict) -> None:
    for name in ("covariance", "correlation"):
        arr = given.pop(name, None)
        if arr is None:
            continue
        if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
            raise InputError(f"array {name!r} must be square (n, n), got {arr.shape}", group.where)
        labels = group.array_attrs.get(name, {}).get("names")
        if labels is None and arr.shape[0] == 13:
            labels = list(PARAM_NAMES)
        if labels is None or len(labels) != arr.shape[0]:
            raise InputError(f"array {name!r} of shape {arr.shape} needs attrs 'names' with "
                             f"{arr.shape[0]} entries (array_attrs={{{name!r}: {{'names': "
                             "[...]}}})", group.where)
        group.put(name, arr, {"names": list(labels)}, ("row", "col"))


def _exterior_from_document(images: list) -> dict:
    sigmas = [[np.nan] * 3 if im["sigma_center_m"] is None else
              [np.nan if s is None else s for s in im["sigma_center_m"]] for im in images]
    return {"exterior/center_m": np.array([im["center_m"] for im in images], dtype=float),
            "exterior/rotation_world_to_camera":
                np.array([im["rotation_world_to_camera"] for im in images], dtype=float),
            "exterior/sigma_center_m": np.array(sigmas, dtype=float)}


def _put_exterior(group: _Group, given: dict, doc: dict) -> None:
    images = doc.get("images") or []
    files = [im.get("file") for im in images if isinstance(im, dict)]
    ext = {k: given.pop(k, None) for k in _EXTERIOR_SHAPES}
    if doc["method"] == "field" and images:
        derived = _exterior_from_document(images)
        ext = {k: derived[k] if v is None else v for k, v in ext.items()}
    for name, arr in ext.items():
        if arr is None:
            continue
        shape = _EXTERIOR_SHAPES[name]
        if arr.shape[1:] != shape or arr.shape[0] != len(files):
            raise InputError(f"array {name!r} must have shape ({len(files)}, "
                             f"{', '.join(map(str, shape))}) for the document's "
                             f"{len(files)} images, got {arr.shape}", group.where)
        dims = ("image", "xyz") if arr.ndim == 2 else ("image", "row", "col")
        group.put(name, arr, {"images": files}, dims)


def _put_correction_field(group: _Group, given: dict, doc: dict) -> None:
    field = given.pop("correction_field", None)
    grid_u = given.pop("grid_u_px", None)
    grid_v = given.pop("grid_v_px", None)
    if field is None:           # the lake stores what it is given (analysis.correction makes it)
        if grid_u is not None or grid_v is not None:
            raise InputError("grid_u_px / grid_v_px given without correction_field", group.where)
        return
    if grid_u is None or grid_v is None:
        raise InputError("correction_field needs grid_u_px (nx,) and grid_v_px (ny,)", group.where)
    if grid_u.ndim != 1 or grid_v.ndim != 1 or field.shape != (grid_v.size, grid_u.size, 2):
        raise InputError(f"correction_field must have shape (ny, nx, 2) = ({grid_v.size}, "
                         f"{grid_u.size}, 2) for the grids given, got {field.shape}", group.where)
    group.put("correction_field", field,
              {"units": "px", "components": ["du_px", "dv_px"],
               "doc": "model correction (dx, dy) at grid pixels in pixels along u and v: "
                      "(dx / d, -dy / d)"}, ("v", "u", "component"))
    group.put("grid_u_px", grid_u, {"units": "px"}, ("u",))
    group.put("grid_v_px", grid_v, {"units": "px"}, ("v",))


def prepare_arrays(doc: dict, arrays: Mapping, array_attrs: Mapping, where: str) -> dict:
    """``{name: (ndarray, attrs, dimension_names)}`` for the Zarr group of a version.

    Parameters
    ----------
    doc : dict
        The (validated) calibration document.
    arrays : mapping of str to array_like
        Named arrays (:data:`KNOWN_ARRAYS`; others are stored as given).
    array_attrs : mapping of str to dict
        Zarr attributes per array name.
    where : str
        What the error messages name.
    """
    where = f"{where}: arrays"
    _check_names(arrays, array_attrs, where)
    given = {name: _as_array(name, value, where) for name, value in arrays.items()}
    group = _Group(array_attrs, where)
    _put_parameters(group, given, doc)
    _put_covariances(group, given)
    _put_exterior(group, given, doc)
    _put_correction_field(group, given, doc)
    for name, arr in given.items():  # anything else, as given
        group.put(name, arr)
    return group.out


# --------------------------------------------------------------------------------------
# the catalog row
# --------------------------------------------------------------------------------------
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


def _stats_columns(doc: dict) -> dict:
    stats = doc.get("stats") or {}
    fixed = stats.get("fixed_parameters")
    n_images = _count(stats.get("n_images"))
    return {
        "fixed_parameters": sorted(fixed) if isinstance(fixed, dict) else [],
        "rmse_px": _num(stats.get("rmse_px")), "max_px": _num(stats.get("max_px")),
        "sigma0": _num(stats.get("sigma0")), "sigma_fit_px": _num(stats.get("sigma_fit_px")),
        "n_images": n_images if n_images is not None else len(doc.get("images") or []),
        "n_targets": _count(stats.get("n_targets")),
        "n_observations": _count(stats.get("n_observations")),
        "n_rejected": _count(stats.get("n_rejected")),
        "n_frames": _count(stats.get("n_frames")), "n_angles": _count(stats.get("n_angles")),
        "iterations": _count(stats.get("iterations")),
        "solver": stats.get("solver") if isinstance(stats.get("solver"), str) else None,
        "targets_adjusted": stats.get("targets_adjusted")
        if isinstance(stats.get("targets_adjusted"), bool) else None,
    }


def catalog_row(doc: dict, committed: dt.datetime, forced: bool, paths: dict,
                where: str) -> pa.Table:
    """The one-row catalog table of a version (``schemas/catalog.arrow.json``)."""
    row = {
        "camera_id": doc["camera_id"], "session_id": doc["session_id"],
        "version": doc["version"], "method": doc["method"],
        "created": parse_time(doc["created"], where),
        "committed": committed,
        "acquired": parse_time(doc.get("acquired"), where),
        "fingerprint": doc["inputs"]["fingerprint"], "code_version": doc["code_version"],
        "forced": bool(forced), "model": doc["model"],
        "width_px": doc["sensor"]["width_px"], "height_px": doc["sensor"]["height_px"],
        "pixel_size_um": float(doc["sensor"]["pixel_size_um"]),
        "document_path": paths["document"], "zarr_path": paths["zarr"],
        "residuals_path": paths["residuals"],
    }
    row.update(_stats_columns(doc))
    for name in PARAM_NAMES:
        row[name] = float(doc["parameters"][name])
        s = doc["sigma"][name]
        row["sigma_" + name] = None if s is None else float(s)
    try:
        return pa.Table.from_pylist([row], schema=arrow_schema("catalog"))
    except (pa.ArrowException, TypeError, ValueError) as e:
        raise InputError(f"cannot make the catalog row: {reason(e)}", where) from None
