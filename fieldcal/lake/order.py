"""The one ordering of a camera's calibrations: acquisition time, ties by commit order.

A camera's calibrations are ordered by when their session was *acquired* (the document's
``acquired``; its ``created`` for a version without one), ties broken by commit time and
then by version id. A session calibrated more than once (a forced rerun) counts with its
latest version in that order: the *previous* calibration of a version is the latest version
of the session just before its own session, the *next* one that of the session just after.
A commit out of order (a backfill of an older session) therefore changes which version is
"previous" for the sessions after it; readers pick the pair from this order when they read
(:func:`neighbours`, :data:`ORDER_SQL`), never from the order of commits.

:data:`ORDER_SQL` is the rule for DuckDB queries over the catalog; :func:`order_key` the
same rule for catalog rows in Python.
"""

from __future__ import annotations

__all__ = ["ORDER_SQL", "ORDER_SQL_DESC", "order_key", "session_latest", "neighbours"]

ORDER_SQL = "coalesce(acquired, created) ASC, committed ASC, version ASC"
"""``ORDER BY`` of the rule (module docstring) over catalog columns."""
ORDER_SQL_DESC = "coalesce(acquired, created) DESC, committed DESC, version DESC"
"""The rule reversed: the first row is the latest."""


def order_key(row: dict) -> tuple:
    """The rule's sort key of a catalog row (a dict with ``acquired``, ``created``, ``committed``, ``version``)."""
    return (row.get("acquired") or row.get("created"), row.get("committed"), row.get("version"))


def session_latest(rows: list[dict]) -> list[dict]:
    """One camera's catalog rows reduced to the latest version of each session, in the rule's order."""
    latest: dict = {}
    for row in sorted(rows, key=order_key):
        latest[row["session_id"]] = row        # a later version of the session replaces it
    return sorted(latest.values(), key=order_key)


def neighbours(rows: list[dict], version: str) -> tuple[str | None, str | None]:
    """``(previous, next)`` version of ``version`` among one camera's catalog rows (None: none).

    Both None when ``version`` is not the latest version of its session (a rerun replaced it).
    """
    seq = [r["version"] for r in session_latest(rows)]
    if version not in seq:
        return None, None
    i = seq.index(version)
    return (seq[i - 1] if i > 0 else None), (seq[i + 1] if i + 1 < len(seq) else None)
