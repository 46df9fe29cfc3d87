"""Content hashes of session images, remembered by file identity so unchanged files are not re-read.

The observations cache and the inputs' fingerprint are keyed by the SHA-256 of each image's
bytes. Hashing a 72-image session of full-size TIFFs means reading ~5 GB, which would make
a rerun of an unchanged session cost seconds of I/O for nothing. So, like git's index, the
flow remembers ``sha256`` per file together with the file's identity and stamp
``(size, mtime_ns, ctime_ns, inode, device)``: when ``os.stat`` still gives the same stamp,
the file has not been rewritten and its hash is taken from here without reading it.

The store is one SQLite database (safe for concurrent processes), by default
``$XDG_CACHE_HOME/fieldcal/hashes.sqlite`` (``~/.cache/fieldcal/hashes.sqlite``). The
environment variable ``FIELDCAL_HASH_CACHE`` names another file, or ``off`` disables it
(every image is then hashed from its bytes). An entry is only written when the stamp the
hashing worker saw before reading equals the stamp the flow sees afterwards, so a file
rewritten during the run is never remembered with a stale hash.

Limits: a file rewritten in place with the same size within the filesystem's timestamp
resolution (and the same ctime) would be missed; on filesystems with nanosecond stamps
(ext4, xfs, btrfs, tmpfs) that does not happen in practice. ``fieldcal run --rehash``
ignores the store.
"""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Iterable
from pathlib import Path

from fieldcal.measure.imageio import stat_stamp

__all__ = ["HashCache", "file_stamp", "default_path", "known_hashes"]

ENV = "FIELDCAL_HASH_CACHE"


def default_path() -> Path | None:
    """The store's file from ``FIELDCAL_HASH_CACHE`` or the XDG cache folder; None when off."""
    value = os.environ.get(ENV, "").strip()
    if value.lower() in ("off", "0", "none", "false"):
        return None
    if value:
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "fieldcal" / "hashes.sqlite"


def file_stamp(path) -> tuple[int, int, int, int, int] | None:
    """``(size, mtime_ns, ctime_ns, inode, device)`` of a file, or None when it is not a file."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    if not os.path.isfile(path):
        return None
    return stat_stamp(st)


class HashCache:
    """SHA-256 of files by ``(real path, stamp)`` in a SQLite file (see the module docstring).

    Parameters
    ----------
    path : path-like or None
        The database file (created with its folder); None disables the cache (every
        lookup misses, nothing is stored). Default: :func:`default_path`.
    """

    def __init__(self, path="default"):
        self.path = default_path() if path == "default" else (None if path is None else Path(path))
        self._con = None
        if self.path is not None:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._con = sqlite3.connect(self.path, timeout=30.0)
                self._con.execute("PRAGMA journal_mode=WAL")
                self._con.execute(
                    "CREATE TABLE IF NOT EXISTS hashes (path TEXT PRIMARY KEY, size INTEGER, "
                    "mtime_ns INTEGER, ctime_ns INTEGER, inode INTEGER, device INTEGER, "
                    "sha256 TEXT)")
                self._con.commit()
            except (OSError, sqlite3.Error):
                # an unusable cache folder must not stop a calibration: hash from the bytes
                self.path, self._con = None, None

    @property
    def enabled(self) -> bool:
        return self._con is not None

    def close(self) -> None:
        if self._con is not None:
            self._con.close()
            self._con = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    @staticmethod
    def _key(path) -> str:
        return os.path.realpath(os.fspath(path))

    def lookup(self, paths: Iterable) -> dict[str, str]:
        """``{path: sha256}`` for the files whose current stamp matches a remembered one.

        ``path`` keys are returned exactly as given.
        """
        out: dict[str, str] = {}
        if self._con is None:
            return out
        for p in paths:
            stamp = file_stamp(p)
            if stamp is None:
                continue
            try:
                row = self._con.execute(
                    "SELECT size, mtime_ns, ctime_ns, inode, device, sha256 FROM hashes WHERE path = ?",
                    (self._key(p),)).fetchone()
            except sqlite3.Error:
                return out
            if row is not None and tuple(row[:5]) == stamp:
                out[p] = row[5]
        return out

    def remember(self, entries: Iterable[tuple[object, str, tuple | list | None]]) -> int:
        """Store ``(path, sha256, stamp_seen_when_hashing)`` entries; returns how many were kept.

        An entry is kept only when the file's stamp now equals the one seen when it was
        hashed (the file was not rewritten in between).
        """
        if self._con is None:
            return 0
        rows = []
        for p, sha, seen in entries:
            stamp = file_stamp(p)
            if stamp is None or seen is None or tuple(seen) != stamp or not sha:
                continue
            rows.append((self._key(p), *stamp, sha))
        if not rows:
            return 0
        try:
            with self._con:
                self._con.executemany("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?, ?, ?, ?)", rows)
        except sqlite3.Error:
            return 0
        return len(rows)


def known_hashes(prepared, path="default") -> dict[str, str]:
    """``{image: sha256}`` of a prepared session's images whose stamp matches a remembered one.

    ``prepared`` is a :class:`fieldcal.pipeline.Prepared`; no image is read. A session on
    an object store has no file stamps here: ``{}`` (its images are hashed as they are read).
    """
    if prepared.session.store is not None:
        return {}                  # on an object store: hashed from the bytes the workers read
    paths = {n: os.fspath(prepared.session.image_path(n)) for n in prepared.to_measure}
    if not paths:
        return {}
    with HashCache(path) as store:
        remembered = store.lookup(paths.values())
    return {n: remembered[p] for n, p in paths.items() if p in remembered}
