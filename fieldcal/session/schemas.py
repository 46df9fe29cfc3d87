"""Machine-readable schemas of the contract: JSON Schema for JSON files, Arrow for tables.

The files live in the project's ``schemas/`` folder (installed as ``fieldcal/_schemas``):
``<name>.schema.json`` (JSON Schema, draft 2020-12) and ``<name>.arrow.json`` (an Arrow
schema as a list of ``{"name", "type", "nullable", "doc"}`` fields; types are pyarrow
factory names such as ``float64``, ``int32``, ``string``, ``bool_``, ``timestamp[us, UTC]``).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pyarrow as pa

from fieldcal.errors import InputError

__all__ = ["schema_dir", "json_schema", "validate_json", "arrow_schema"]


def schema_dir() -> Path:
    """The folder holding the schema files (installed copy first, then the source tree)."""
    package = Path(__file__).resolve().parents[1]
    for candidate in (package / "_schemas", package.parent / "schemas"):
        if candidate.is_dir():
            return candidate
    raise FileNotFoundError("fieldcal's schemas/ folder is missing from this installation")


@functools.cache
def json_schema(name: str) -> dict:
    """The JSON Schema ``schemas/<name>.schema.json``."""
    return json.loads((schema_dir() / f"{name}.schema.json").read_text())


def validate_json(document, name: str, where: str) -> None:
    """Validate ``document`` against ``schemas/<name>.schema.json``.

    Raises :class:`InputError` naming ``where`` and the JSON pointer of the first bad field.
    """
    import jsonschema

    validator = jsonschema.Draft202012Validator(json_schema(name))
    errors = sorted(validator.iter_errors(document), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        pointer = "/" + "/".join(str(p) for p in err.absolute_path)
        raise InputError(f"{err.message} (at {pointer})", where)


def _arrow_type(name: str) -> pa.DataType:
    if name.startswith("timestamp["):
        unit, _, tz = name[len("timestamp["):-1].partition(",")
        return pa.timestamp(unit.strip(), tz=tz.strip() or None)
    if name.startswith("list<") and name.endswith(">"):
        return pa.list_(_arrow_type(name[5:-1]))
    return getattr(pa, name)()


@functools.cache
def arrow_schema(name: str) -> pa.Schema:
    """The Arrow schema ``schemas/<name>.arrow.json`` as a :class:`pyarrow.Schema`."""
    spec = json.loads((schema_dir() / f"{name}.arrow.json").read_text())
    fields = [
        pa.field(f["name"], _arrow_type(f["type"]), nullable=f.get("nullable", True),
                 metadata={"doc": f.get("doc", "")})
        for f in spec["fields"]
    ]
    return pa.schema(fields, metadata={"name": spec["name"], "doc": spec.get("doc", "")})
