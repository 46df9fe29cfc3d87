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

__all__ = ["schema_dir", "json_schema", "validate_json", "arrow_schema", "shown"]


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
        if err.validator == "oneOf" and err.context:   # the alternative of the value's type
            err = _closest(err.context)
        pointer = "/" + "/".join(str(p) for p in err.absolute_path)
        missing = _missing_here(errors, err)
        message = (f"required properties {', '.join(map(repr, missing))} are missing" if len(missing) > 1
                   else _message(err))
        raise InputError(f"{message} (at {pointer})", where)


def _missing_here(errors, first) -> list[str]:
    """Every required property missing at ``first``'s place (one message names them all)."""
    if first.validator != "required":
        return []
    names: list[str] = []
    for e in errors:
        if e.validator == "required" and list(e.absolute_path) == list(first.absolute_path) \
                and isinstance(e.instance, dict):
            names += [n for n in e.validator_value if n not in e.instance and n not in names]
    return names


def _closest(errors):
    """Among a ``oneOf``'s errors, the deepest of an alternative whose type the value has."""
    branches: dict = {}
    for e in errors:
        branches.setdefault(e.relative_schema_path[0], []).append(e)
    fitting = [b for b in branches.values()
               if not any(e.validator == "type" and not e.relative_path for e in b)]
    pool = min(fitting, key=len) if fitting else list(errors)
    return max(pool, key=lambda e: len(e.absolute_path))


def shown(value, limit: int = 60) -> str:
    """``repr(value)`` for a message: at most ``limit`` characters of a long text (then its
    length), or of a long list or object (then its number of items)."""
    if isinstance(value, str) and len(value) > limit:
        return f"{value[:limit]!r}... ({len(value)} characters)"
    text = repr(value)
    if len(text) > 2 * limit and isinstance(value, (list, dict)):
        return f"{text[:limit]}... ({type(value).__name__} of {len(value)} items)"
    return text


def _message(err) -> str:
    """jsonschema's message; for a definition with a ``description`` that the value breaks
    (pattern, forbidden characters, length), "<value> is not <description>". Long values are
    cut to their first 60 characters, so the message stays one readable line."""
    value = err.instance
    text = shown(value)
    desc = err.schema.get("description") if isinstance(err.schema, dict) else None
    if desc and err.validator in ("pattern", "not", "minLength", "maxLength"):
        return f"{text} is not {desc}"
    return err.message.replace(repr(value), text)


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
