"""The names a session gives things, and what each may be (``schemas/session.schema.json``).

One definition per kind of name, in the schema's ``$defs``, used both by the schema (for
session.json) and by the readers of the CSV tables (for the same names there):

- ``id``: ``camera_id`` and ``session_id``; 1 to 128 characters from ``A-Z a-z 0-9 . _ -``,
  the first a letter or a digit. They become folder names and partition values in the lake.
- ``label``: a target id (targets.csv, observations.csv, marks.csv) or a station name; 1 to
  128 printable characters, none of ``/ \\ * ? [ ]``.
- ``file``: an image, a frame or a table of the session, as a path relative to the session
  folder with forward slashes; 1 to 1024 printable characters, none of ``* ? [ ]``, no
  ``..`` part, not absolute. Names are compared after :func:`normal_file_name`
  (``images/./a.tif`` and ``images//a.tif`` are ``images/a.tif``).
- ``glob``: the manifest's ``images`` pattern; printable, 1 to 1024 characters.

"Printable" leaves out control characters (C0, DEL, C1), line and paragraph separators,
invisible format characters (soft hyphen, zero-width characters, bidirectional controls,
the byte-order mark) and lone surrogates: the characters that can break a message line,
hide a difference between two names, or not be written as UTF-8. Every pattern that ends the
text writes ``$(?!\\n)``: in Python's ``re`` (which the jsonschema package uses) ``$`` alone
also matches before a final newline, so ``"cam-1\\n"`` would pass.
"""

from __future__ import annotations

import functools
import posixpath
import re

from fieldcal.contract.schemas import json_schema, shown
from fieldcal.errors import InputError

__all__ = ["KINDS", "is_valid", "first_invalid", "check_name", "normal_file_name"]

KINDS = ("id", "label", "file", "glob")


@functools.cache
def _rule(kind: str):
    """(definition, required pattern or None, forbidden pattern or None) of a kind of name."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind of name {kind!r}; one of {KINDS}")
    d = json_schema("session")["$defs"][kind]
    need = re.compile(d["pattern"]) if "pattern" in d else None
    forbid = re.compile(d["not"]["pattern"]) if "not" in d else None
    return d, need, forbid


def is_valid(value, kind: str) -> bool:
    """Whether ``value`` is a valid name of ``kind`` (``"id"``, ``"label"``, ``"file"``, ``"glob"``)."""
    d, need, forbid = _rule(kind)
    if not isinstance(value, str):
        return False
    if not d.get("minLength", 0) <= len(value) <= d.get("maxLength", len(value)):
        return False
    if need is not None and not need.search(value):
        return False
    return forbid is None or not forbid.search(value)


def first_invalid(values: list[str], kind: str) -> int | None:
    """Index of the first value that is not a valid name of ``kind``, or None (all valid).

    The same test as :func:`is_valid`, run as one regular-expression scan over all values
    joined by a character every kind allows (a comma), then per value only if it fails.
    """
    d, need, forbid = _rule(kind)
    lo, hi = d.get("minLength", 0), d.get("maxLength", None)
    short = any(len(v) < lo or (hi is not None and len(v) > hi) for v in values)
    if short or need is not None or (forbid is not None and forbid.search(",".join(values))):
        return next((k for k, v in enumerate(values) if not is_valid(v, kind)), None)
    return None


def check_name(value, kind: str, what: str, where: str | None) -> str:
    """``value`` when it is a valid name of ``kind``; else :class:`InputError` of one line.

    Parameters
    ----------
    value : str
    kind : {"id", "label", "file", "glob"}
        The definition in ``schemas/session.schema.json`` (module docstring).
    what : str
        What the value is, for the message (``"target id"``, ``"image"``).
    where : str
        The file (and row) it comes from.
    """
    if not is_valid(value, kind):
        raise InputError(f"{what} {shown(value)} is not {_rule(kind)[0]['description']}", where)
    return value


def normal_file_name(name: str, what: str = "file", where: str | None = None) -> str:
    """A session-relative file name in its one spelling: ``/`` separators, no ``.`` parts.

    ``images\\a.tif``, ``./images/a.tif``, ``images/./a.tif`` and ``images//a.tif`` are all
    ``images/a.tif``. The name must be a valid ``file`` (module docstring); absolute names,
    drive letters and ``..`` parts are refused (:class:`InputError` naming ``where``).
    """
    check_name(name, "file", what, where)
    rel = name.replace("\\", "/")
    if rel.startswith("/") or (len(rel) > 1 and rel[1] == ":"):
        raise InputError(f"{what} {shown(name)} must be relative to the session folder", where)
    if ".." in rel.split("/"):
        raise InputError(f"{what} {shown(name)} leaves the session folder", where)
    normal = posixpath.normpath(rel)
    if normal == ".":
        raise InputError(f"{what} {shown(name)} names the session folder, not a file", where)
    return normal
