"""Names at the lake's boundary: camera and session ids, version ids, image names, times.

Everything that becomes part of a path or a table key in the lake passes through here and
is checked exactly (``re.fullmatch``: a pattern's ``$`` would let a trailing newline
through). A bad name is refused with one line (:class:`~fieldcal.errors.InputError`)
before anything is read or written.

Version ids are ``YYYYMMDDTHHMMSSZ-ffffffff-rrrr``: the commit time (UTC, to the second),
the first 8 hex digits of the inputs' fingerprint and 4 random hex digits. They sort by
time to the second; the catalog's ``committed`` column (microseconds) orders versions
made within one second.
"""

from __future__ import annotations

import datetime as dt
import json
import re
import secrets

import numpy as np

from fieldcal.contract.fingerprint import is_fingerprint
from fieldcal.errors import InputError

__all__ = ["check_id", "check_image_name", "check_version", "new_version", "version_time",
           "observations_key", "parse_time", "iso", "utcnow", "plain_json", "ID_PATTERN",
           "VERSION_PATTERN", "SHA256_PATTERN", "MAX_IMAGE_NAME"]

UTC = dt.UTC
ID_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
"""camera_id / session_id: the pattern of schemas/session.schema.json, matched in full."""
VERSION_PATTERN = re.compile(r"(\d{8}T\d{6}Z)-([0-9a-f]{8})-([0-9a-f]{4})")
SHA256_PATTERN = re.compile(r"[0-9a-f]{64}")
MAX_IMAGE_NAME = 1024
"""Longest image name (session-relative path) the lake accepts [characters]."""


def _shown(value) -> str:
    """A short, printable rendering of a (possibly hostile) value for a one-line message."""
    text = repr(value)
    return text if len(text) <= 80 else text[:60] + "..." + f" ({len(text)} characters)"


def check_id(value, what: str) -> str:
    """``value`` if it is a valid camera or session id, else :class:`InputError` (one line)."""
    if not isinstance(value, str) or not ID_PATTERN.fullmatch(value):
        raise InputError(f"{what} must be 1-128 of letters, digits, '.', '_', '-' starting with "
                         f"a letter or digit, got {_shown(value)}", "lake")
    return value


def check_version(value) -> str:
    """``value`` if it has the form of a version id, else :class:`InputError`."""
    if not isinstance(value, str) or not VERSION_PATTERN.fullmatch(value):
        raise InputError(f"not a version id (YYYYMMDDTHHMMSSZ-xxxxxxxx-xxxx): {_shown(value)}",
                         "lake")
    return value


def check_image_name(value) -> str:
    """An image name (session-relative path, forward slashes) without control characters."""
    if not isinstance(value, str) or not value or len(value) > MAX_IMAGE_NAME \
            or any(ord(c) < 32 or ord(c) == 127 for c in value) or "\\" in value \
            or value.startswith("/") or ".." in value.split("/"):
        raise InputError(f"image name must be a relative path of at most {MAX_IMAGE_NAME} "
                         f"printable characters without '..' or '\\', got {_shown(value)}", "lake")
    return value


def utcnow() -> dt.datetime:
    return dt.datetime.now(UTC)


def iso(t: dt.datetime) -> str:
    """ISO 8601 in UTC with a ``Z``."""
    return t.astimezone(UTC).isoformat().replace("+00:00", "Z")


def new_version(fingerprint: str, when: dt.datetime | None = None) -> str:
    """A fresh version id ``YYYYMMDDTHHMMSSZ-<fingerprint[:8]>-<4 random hex>``.

    Parameters
    ----------
    fingerprint : str
        ``"sha256:<64 hex>"`` of the inputs (:func:`fieldcal.contract.fingerprint.fingerprint`).
    when : datetime, optional
        The commit time (default: now); naive times are taken as UTC.
    """
    if not is_fingerprint(fingerprint):
        raise InputError(f"fingerprint must be 'sha256:' and 64 hex digits, got {_shown(fingerprint)}",
                         "new_version")
    t = when or utcnow()
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    stamp = t.astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    return f"{stamp}-{fingerprint[7:15]}-{secrets.token_hex(2)}"


def version_time(version: str) -> dt.datetime:
    """The commit time (UTC, whole seconds) encoded in a version id."""
    m = VERSION_PATTERN.fullmatch(version) if isinstance(version, str) else None
    if not m:
        raise InputError(f"not a version id (YYYYMMDDTHHMMSSZ-xxxxxxxx-xxxx): {_shown(version)}")
    return dt.datetime.strptime(m.group(1), "%Y%m%dT%H%M%SZ").replace(tzinfo=UTC)


def observations_key(image_name: str, content_sha256: str) -> str:
    """The name of an image's cached observations: ``<image-key>-<sha256>``.

    ``image-key`` is the image name (session-relative path) with every character outside
    ``[A-Za-z0-9._-]`` replaced by ``_`` (so ``images/IMG_1.tif`` -> ``images_IMG_1.tif``);
    the full content hash follows, so the key changes whenever the image's bytes do.
    """
    if not isinstance(image_name, str) or not image_name:
        raise InputError(f"image name must be a non-empty string, got {_shown(image_name)}",
                         "observations_key")
    if not isinstance(content_sha256, str) or not SHA256_PATTERN.fullmatch(content_sha256):
        raise InputError(f"content_sha256 must be 64 lower-case hex digits, got "
                         f"{_shown(content_sha256)}", "observations_key")
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", image_name).lstrip(".") or "_"
    return f"{stem}-{content_sha256}"


def parse_time(value, where: str) -> dt.datetime | None:
    """An ISO 8601 date or time (or date / datetime) as an aware UTC datetime; None stays None.

    A date alone is midnight UTC; a time without a zone is taken as UTC.
    """
    if value is None:
        return None
    if isinstance(value, dt.datetime):
        t = value
    elif isinstance(value, dt.date):
        t = dt.datetime(value.year, value.month, value.day)
    elif isinstance(value, str):
        try:
            t = dt.datetime.fromisoformat(value.strip())
        except ValueError:
            raise InputError(f"not an ISO 8601 date or time: {_shown(value)}", where) from None
    else:
        raise InputError(f"expected an ISO 8601 date or time, got {type(value).__name__}", where)
    if t.tzinfo is None:
        t = t.replace(tzinfo=UTC)
    try:
        return t.astimezone(UTC)
    except OverflowError:            # 9999-12-31T23:59-23:00 is after the year 9999 in UTC
        raise InputError(f"out of range in UTC (years 1 to 9999): {_shown(value)}", where) from None


def _json_default(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (dt.datetime, dt.date)):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def plain_json(obj, where: str):
    """A deep copy of ``obj`` as plain JSON values (numpy -> Python); NaN / inf refused."""
    try:
        return json.loads(json.dumps(obj, default=_json_default, allow_nan=False))
    except ValueError as e:
        raise InputError(f"{e} (NaN and infinity have no JSON form; use null)", where) from None
    except TypeError as e:
        raise InputError(str(e), where) from None
