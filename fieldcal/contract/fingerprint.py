"""Fingerprints of a calibration's inputs, and the version of the code that made it.

A version in the lake records the fingerprint of everything that determined its result
(the session's identity ``camera_id`` / ``session_id``, image content hashes, the
control-point / frames / observations tables, the session manifest and the solver
settings; :func:`fieldcal.pipeline.input_fingerprint`) so that the same inputs of the same
session are recognised and not solved twice, and the code version so that any number can be
traced back. The identity is part of it because two folders may hold the same files (two
copies without a ``session_id`` are two sessions, named after their folders); the path of a
folder is not, so a session moved elsewhere is still the same session.

The fingerprint is ``"sha256:" + hex`` of the *canonical JSON* of a dict of parts:
keys sorted, no insignificant whitespace, UTF-8, floats in Python's shortest round-trip
``repr``; NaN and infinity are refused (they have no JSON form). Binary parts are
replaced by their SHA-256 before serialising:

- ``bytes`` / ``bytearray`` / ``memoryview`` -> ``"sha256:<hex>"`` of the bytes, so a
  table may be given either as its file bytes or as the hash of that file
  (:func:`sha256_file`) with the same result;
- a numpy array -> ``{"dtype", "shape", "sha256"}`` of its C-ordered bytes;
- a :class:`pyarrow.Table` -> ``"sha256:<hex>"`` of its Arrow IPC stream (chunks combined
  first, so the chunking does not matter; the schema, including its metadata, does).

Paths are refused on purpose: hash the file's content (:func:`sha256_file`), not its name.
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import subprocess
from collections.abc import Mapping
from pathlib import Path, PurePath

import numpy as np
import pyarrow as pa

from fieldcal import __version__
from fieldcal.errors import InputError

__all__ = [
    "sha256_file", "sha256_bytes", "canonical_json", "fingerprint", "is_fingerprint",
    "git_commit", "code_version",
]

PREFIX = "sha256:"


def sha256_file(path) -> str:
    """SHA-256 of a file's content, read in streamed chunks (never the whole file at once).

    Parameters
    ----------
    path : str or os.PathLike
        A local file.

    Returns
    -------
    str
        64 lower-case hex digits (no prefix).
    """
    try:
        with open(path, "rb") as f:
            return hashlib.file_digest(f, "sha256").hexdigest()
    except FileNotFoundError:
        raise InputError("file not found", os.fspath(path)) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a file", os.fspath(path)) from None


def sha256_bytes(data) -> str:
    """SHA-256 of bytes, 64 lower-case hex digits (no prefix)."""
    return hashlib.sha256(data).hexdigest()


def _arrow_table_digest(table: pa.Table) -> str:
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table.combine_chunks())
    return sha256_bytes(sink.getvalue())


def _canonical(value, where: str):
    """Plain JSON values from ``value`` (binary parts replaced by their hashes)."""
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (bytes, bytearray, memoryview)):
        return PREFIX + sha256_bytes(value)
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        if arr.dtype.hasobject:
            raise InputError("object arrays cannot be fingerprinted", where)
        return {"dtype": arr.dtype.str, "shape": list(arr.shape),
                "sha256": sha256_bytes(arr.tobytes())}
    if isinstance(value, np.generic):
        value = value.item()
        if isinstance(value, (bytes, str, bool)):
            return _canonical(value, where)
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise InputError(f"non-finite number {value!r} cannot be fingerprinted", where)
        return float(value)
    if isinstance(value, Mapping):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise InputError(f"keys must be strings, got {k!r}", where)
            out[k] = _canonical(v, f"{where}/{k}")
        return out
    if isinstance(value, (list, tuple)):
        return [_canonical(v, f"{where}/{i}") for i, v in enumerate(value)]
    if isinstance(value, (PurePath, Path)):
        raise InputError("a path cannot be fingerprinted; pass sha256_file(path) instead", where)
    if isinstance(value, pa.Table):
        return PREFIX + _arrow_table_digest(value)
    raise InputError(f"cannot fingerprint a value of type {type(value).__name__}", where)


def canonical_json(obj) -> bytes:
    """The canonical JSON bytes of ``obj`` (see the module docstring)."""
    plain = _canonical(obj, "")
    return json.dumps(plain, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode("utf-8")


def fingerprint(parts: Mapping) -> str:
    """The fingerprint ``"sha256:<64 hex>"`` of a calibration's inputs.

    Parameters
    ----------
    parts : mapping of str to JSON-like values
        What determined the result, for example ``{"images": {name: sha256_file(path)},
        "targets": sha256_file(targets.csv), "session": manifest_dict,
        "settings": {...}}``. Binary values are hashed (module docstring).

    Returns
    -------
    str
        ``"sha256:"`` followed by 64 lower-case hex digits.
    """
    if not isinstance(parts, Mapping):
        raise InputError(f"fingerprint parts must be a mapping, got {type(parts).__name__}",
                         "fingerprint")
    return PREFIX + sha256_bytes(canonical_json(parts))


def is_fingerprint(value) -> bool:
    """Whether ``value`` has the form ``"sha256:<64 lower-case hex>"``."""
    if not isinstance(value, str) or not value.startswith(PREFIX) or len(value) != 71:
        return False
    return all(c in "0123456789abcdef" for c in value[len(PREFIX):])


@functools.cache
def git_commit() -> str | None:
    """The git commit (40 hex) of the source tree fieldcal is imported from, if any.

    Only when the package directory lies in a git work tree whose top level is the
    package's parent (an editable install of this project); ``None`` for an installed
    wheel, without git, or when git refuses the repository.
    """
    pkg = Path(__file__).resolve().parents[1]
    try:
        top = subprocess.run(["git", "-C", str(pkg), "rev-parse", "--show-toplevel"],
                             capture_output=True, text=True, timeout=10)
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != pkg.parent:
            return None
        head = subprocess.run(["git", "-C", str(pkg), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    sha = head.stdout.strip()
    if head.returncode != 0 or len(sha) != 40:
        return None
    return sha


def code_version() -> str:
    """``fieldcal.__version__``, with ``+g<12 hex>`` of the git commit when known.

    For example ``"0.1.0+g2c3ef37a1b2c"`` (a PEP 440 local version) or ``"0.1.0"``.
    Uncommitted edits in the work tree are not detectable cheaply and are not marked.
    """
    sha = git_commit()
    return f"{__version__}+g{sha[:12]}" if sha else __version__
