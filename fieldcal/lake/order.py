"""The one ordering of a camera's calibrations: acquisition time, ties by commit order.

A camera's calibrations are ordered by when their session was *acquired* (the document's
``acquired``; its ``created`` for a version without one), ties broken by commit time and
then by version id. A *session* is a ``session_id`` with its acquisition time
(:func:`session_key`): ``session_id`` defaults to the folder's name (CONTRACT section 3), so
``ROOT/2026-01/wall`` and ``ROOT/2026-02/wall`` are two sessions named ``wall``, told apart by
when they were acquired; a rerun of a session (``--force``, new settings) stays that session.
A session calibrated more than once counts with its latest version in that order: the
*previous* calibration of a version is the latest version of the session just before its
own session, the *next* one that of the session just after.
A commit out of order (a backfill of an older session) therefore changes which version is
"previous" for the sessions after it; readers pick the pair from this order when they read
(:func:`neighbours`, :data:`ORDER_SQL`), never from the order of commits.

:data:`ORDER_SQL` is the rule for DuckDB queries over the catalog; :func:`order_key` the
same rule for catalog rows in Python.
"""

from __future__ import annotations

__all__ = ["ORDER_SQL", "ORDER_SQL_DESC", "SESSION_SQL", "ROW_COLUMNS", "order_key", "session_key",
           "session_latest", "neighbours", "latest", "previous"]

ORDER_SQL = "coalesce(acquired, created) ASC, committed ASC, version ASC"
"""``ORDER BY`` of the rule (module docstring) over catalog columns."""
ORDER_SQL_DESC = "coalesce(acquired, created) DESC, committed DESC, version DESC"
"""The rule reversed: the first row is the latest."""
SESSION_SQL = "session_id, acquired"
"""``PARTITION BY`` columns of one session of a camera (:func:`session_key`)."""
ROW_COLUMNS = ("version", "session_id", "acquired", "created", "committed")
"""The catalog columns the functions below read."""


def order_key(row: dict) -> tuple:
    """The rule's sort key of a catalog row (a dict with ``acquired``, ``created``, ``committed``, ``version``)."""
    return (row.get("acquired") or row.get("created"), row.get("committed"), row.get("version"))


def session_key(row: dict) -> tuple:
    """Which session a catalog row belongs to: ``(session_id, acquired)`` (module docstring)."""
    return row["session_id"], row.get("acquired")


def session_latest(rows: list[dict]) -> list[dict]:
    """One camera's catalog rows reduced to the latest version of each session, in the rule's order."""
    last: dict = {}
    for row in sorted(rows, key=order_key):
        last[session_key(row)] = row           # a later version of the session replaces it
    return sorted(last.values(), key=order_key)


def latest(rows: list[dict]) -> str | None:
    """The latest version among one camera's catalog rows (of one session, if only its rows are given)."""
    return max(rows, key=order_key)["version"] if rows else None


def previous(rows: list[dict], version: str) -> str | None:
    """The calibration before ``version`` among one camera's catalog rows, None for the first.

    The latest version of the session just before ``version``'s own session in the rule's
    order (the same as :func:`neighbours` for a session's latest version; for an earlier
    version of a session, the session before the one it belongs to)."""
    own = [r for r in rows if r["version"] == version]
    if not own:
        return None
    key, mine = order_key(own[0]), session_key(own[0])
    before = [r for r in session_latest([r for r in rows if session_key(r) != mine]) if order_key(r) < key]
    return before[-1]["version"] if before else None


def neighbours(rows: list[dict], version: str) -> tuple[str | None, str | None]:
    """``(previous, next)`` version of ``version`` among one camera's catalog rows (None: none).

    Both None when ``version`` is not the latest version of its session (a rerun replaced it).
    """
    seq = [r["version"] for r in session_latest(rows)]
    if version not in seq:
        return None, None
    i = seq.index(version)
    return (seq[i - 1] if i > 0 else None), (seq[i + 1] if i + 1 < len(seq) else None)
