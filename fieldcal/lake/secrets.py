"""Storage credentials kept out of what a workflow engine records.

A lake's fsspec options (``--storage-options``, ``FIELDCAL_STORAGE_OPTIONS``) may hold
credentials (``key``, ``secret``, ``token``, ``AWS_SECRET_ACCESS_KEY``, a password, ...).
Whatever a Prefect flow is called with is stored as its flow-run parameters (in the
server's database, readable by any client of its API), so the command line passes only
:func:`redact`'s copy through Prefect: every secret value replaced by :data:`REDACTED`.

The values come back where the lake is opened (:class:`fieldcal.lake.storage.Storage`
calls :func:`resolve`, in the command's process or on a Dask worker): from the same key
of ``FIELDCAL_STORAGE_OPTIONS`` in that process's environment (the command line puts its
``--storage-options`` there for its own process and the worker processes it starts), else
the option is left out and the storage's own configuration answers (``AWS_*`` variables,
``~/.aws``, an instance role: what s3fs and delta-rs read by themselves). A worker on
another host needs one of those.

A *secret* is a string value under a name (at any depth, case ignored) that contains
``secret``, ``token``, ``passw``, ``credential``, ``private``, ``signature`` or
``connection_string``, or that is or ends in ``key`` / ``key_id`` (``key``,
``access_key``, ``account_key``, ``aws_access_key_id``).
"""

from __future__ import annotations

import contextlib
import json
import os
import re

__all__ = ["REDACTED", "OPTIONS_ENV", "is_secret_name", "redact", "resolve", "secret_values", "for_flow", "exported"]

REDACTED = "<redacted: from FIELDCAL_STORAGE_OPTIONS on the worker>"
"""What a secret option's value is replaced with in anything a workflow engine records."""
OPTIONS_ENV = "FIELDCAL_STORAGE_OPTIONS"
"""The environment variable with the lake's fsspec options as a JSON object."""

_SECRET_NAME = re.compile(r"secret|token|passw|credential|private|signature|connection_string|"
                          r"(^|_)key(_id)?$", re.IGNORECASE)


def is_secret_name(name) -> bool:
    """Whether an option of this name holds a secret (module docstring)."""
    return isinstance(name, str) and bool(_SECRET_NAME.search(name))


def redact(options: dict | None) -> dict | None:
    """A copy of ``options`` with every secret string value replaced by :data:`REDACTED`."""
    if options is None:
        return None
    out = {}
    for k, v in options.items():
        if isinstance(v, dict):
            out[k] = redact(v)
        elif isinstance(v, str) and v and is_secret_name(k):
            out[k] = REDACTED
        else:
            out[k] = v
    return out


def secret_values(options: dict | None) -> list[str]:
    """The secret string values of ``options`` (what must never be recorded)."""
    found = []
    for k, v in (options or {}).items():
        if isinstance(v, dict):
            found += secret_values(v)
        elif isinstance(v, str) and v and v != REDACTED and is_secret_name(k):
            found.append(v)
    return found


def _has_redacted(options) -> bool:
    return any(v == REDACTED or (isinstance(v, dict) and _has_redacted(v)) for v in options.values())


def _environment_options(environ) -> dict:
    from fieldcal.errors import InputError

    text = environ.get(OPTIONS_ENV)
    if not text:
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        raise InputError(f"${OPTIONS_ENV} is not JSON: {e.msg}", "storage options") from None
    if not isinstance(value, dict):
        raise InputError(f"${OPTIONS_ENV} must be a JSON object", "storage options")
    return value


def _fill(options: dict, source: dict) -> dict:
    out = {}
    for k, v in options.items():
        if isinstance(v, dict):
            inner = source.get(k)
            out[k] = _fill(v, inner if isinstance(inner, dict) else {})
        elif v == REDACTED:
            given = source.get(k)
            if isinstance(given, str) and given and given != REDACTED:
                out[k] = given
            # else left out: the storage's own configuration (AWS_*, ~/.aws, a role) answers
        else:
            out[k] = v
    return out


def resolve(options: dict | None, environ=None) -> dict | None:
    """``options`` with each :data:`REDACTED` value taken from ``FIELDCAL_STORAGE_OPTIONS``.

    A redacted option the environment does not give is left out (module docstring).
    ``options`` without a redacted value is returned as it is.

    Raises
    ------
    fieldcal.errors.InputError
        ``FIELDCAL_STORAGE_OPTIONS`` is set but is not a JSON object.
    """
    if not options or not _has_redacted(options):
        return options
    return _fill(options, _environment_options(os.environ if environ is None else environ))


def for_flow(options: dict | None) -> dict | None:
    """The options to give a Prefect flow (or a subflow): :func:`redact`'s copy.

    Their secret values go into this process's ``FIELDCAL_STORAGE_OPTIONS`` first (seen by
    the flow runs of this process, its Dask worker threads and the worker processes it
    starts), where :func:`resolve` finds them; options already redacted change nothing. A
    worker on another host needs them in its own environment or the storage's configuration."""
    if options and secret_values(options):
        os.environ[OPTIONS_ENV] = json.dumps(options)
    return redact(options)


@contextlib.contextmanager
def exported(options: dict | None):
    """:func:`for_flow` for the block only: ``FIELDCAL_STORAGE_OPTIONS`` is what it was after it.

    For a flow called from Python with its credentials, which runs subflows with the
    redacted copy (``flows.fleet``); yields that copy."""
    before = os.environ.get(OPTIONS_ENV)
    try:
        yield for_flow(options)
    finally:
        if before is None:
            os.environ.pop(OPTIONS_ENV, None)
        else:
            os.environ[OPTIONS_ENV] = before
