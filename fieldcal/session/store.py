"""Where a session's files live: a local folder, or a folder on an object store (an fsspec URL).

A session on an object store (``s3://bucket/sessions/cam/2026-05-01``) is never copied to
the machine that runs the flow (docs/deployment.md):

- its small files (:data:`SMALL_FILES`: ``session.json`` and the CSV tables) are fetched
  into a temporary folder only while the session loader validates them; they are read into
  memory there (:class:`fieldcal.pipeline.Prepared` carries them to the tasks);
- every other file is listed once, name and size (:meth:`SessionStore.list`): the loader
  matches the ``images`` glob against that listing (:func:`glob_names`, Python's
  :mod:`glob` rules) and the plan finds missing images in it;
- each image is read where it is measured, on the Dask worker, straight from the store, in
  one pass whose bytes are hashed as they arrive (:meth:`SessionStore.read_image`): the hash
  is of the bytes decoded, as for a local file.

A :class:`SessionStore` is a URL, its fsspec ``storage_options`` and that listing: small,
picklable, and it opens its filesystem where it is used. Credentials are best left out of
``storage_options`` and given to every process (the flow's and each worker's) by its
environment (``AWS_ACCESS_KEY_ID``, ...): the tasks' arguments then hold none.
"""

from __future__ import annotations

import fnmatch
import hashlib
import os
import posixpath
import re
from collections.abc import Callable
from dataclasses import dataclass, field

from fieldcal.errors import ImageError, InputError, one_line
from fieldcal.measure.imageio import ImageFile, read_stream

__all__ = ["SessionStore", "is_url", "open_store", "glob_names", "sample_digest", "distinct_by_md5",
           "SMALL_FILES", "REMOTE_CHUNK_BYTES"]

SMALL_FILES = (".json", ".csv")
"""Files fetched from an object store to validate a session (everything else is listed only)."""
_MD5 = re.compile(r"[0-9a-f]{32}")
REMOTE_CHUNK_BYTES = 16 << 20
"""Bytes per ranged read of an image on an object store (5-7 requests per full-size frame)."""


def is_url(location) -> bool:
    """Whether a session or root is an fsspec URL (``s3://...``) rather than a local path
    (``file://`` counts as local)."""
    text = os.fspath(location) if not isinstance(location, str) else location
    return "://" in text and not text.startswith("file://")


def glob_names(pattern: str, names) -> list[str]:
    """The names (relative, ``/``-separated) that :func:`glob.glob` would match with
    ``root_dir`` at their folder, sorted: ``*``, ``?`` and ``[...]`` within one path segment,
    case-sensitive, and a segment starting with ``.`` matched only by a pattern segment
    starting with ``.`` (no ``**`` recursion: the loader does not ask for it)."""
    parts = pattern.replace("\\", "/").split("/")
    out = []
    for name in names:
        segs = name.split("/")
        if len(segs) != len(parts):
            continue
        if all(fnmatch.fnmatchcase(s, p) and (not s.startswith(".") or p.startswith("."))
               for s, p in zip(segs, parts, strict=True)):
            out.append(name)
    return sorted(out)


@dataclass
class SessionStore:
    """A session folder on an object store (module docstring).

    Attributes
    ----------
    url : str
        The folder's URL, without a trailing ``/``.
    storage_options : dict or None
        fsspec options of the store (endpoint, region; credentials best from the environment).
    files : dict
        ``{name: size [bytes]}`` of every file under the folder (names relative, ``/``).
    md5 : dict
        ``{name: MD5 hex}`` of the files whose listed ETag is their content's MD5 (an S3
        object written in one part; :func:`distinct_by_md5`).
    resolve : callable or None
        ``resolve(storage_options) -> options`` applied where the store is opened (the flow's
        process, a worker): the application gives :func:`fieldcal.lake.secrets.resolve`, which
        fills redacted credentials from that process's environment. A module-level function,
        so that it travels with the store by reference.
    """

    url: str
    storage_options: dict | None = None
    files: dict[str, int] = field(default_factory=dict)
    md5: dict[str, str] = field(default_factory=dict)
    resolve: Callable[[dict | None], dict | None] | None = None

    def filesystem(self):
        """``(fsspec filesystem, the folder's path in it)`` (fsspec reuses instances)."""
        import fsspec

        options = self.resolve(self.storage_options) if self.resolve is not None else self.storage_options
        fs, path = fsspec.core.url_to_fs(self.url, **(options or {}))
        return fs, path.rstrip("/")

    @property
    def name(self) -> str:
        """The folder's own name (the default ``session_id``)."""
        return posixpath.basename(self.url.rstrip("/"))

    def url_of(self, name: str) -> str:
        """The URL of a file of the session, for messages."""
        return f"{self.url}/{name}"

    def list(self) -> dict[str, int]:
        """List the folder (one listing, sizes included) into :attr:`files` and return it."""
        fs, base = self.filesystem()
        fs.invalidate_cache(base)
        found = fs.find(base, detail=True)
        files = {p[len(base):].lstrip("/"): info for p, info in found.items()
                 if info.get("type", "file") == "file" and p.startswith(base + "/")}
        self.files = {n: int(info.get("size") or 0) for n, info in files.items()}
        self.md5 = {n: tag for n, tag in ((n, str(info.get("ETag") or "").strip('"').lower())
                                          for n, info in files.items()) if _MD5.fullmatch(tag)}
        return self.files

    def fetch_small_files(self, dest: str) -> None:
        """Copy the :data:`SMALL_FILES` of the folder into the local folder ``dest``."""
        fs, base = self.filesystem()
        os.makedirs(dest, exist_ok=True)
        for rel in self.files:
            if rel.lower().endswith(SMALL_FILES):
                target = os.path.join(dest, *rel.split("/"))
                os.makedirs(os.path.dirname(target), exist_ok=True)
                fs.get_file(f"{base}/{rel}", target)

    def has_folder(self, rel: str) -> bool:
        """Whether some file of the session lies under the folder ``rel`` (an object store has
        no folders of its own; ``""`` is the session folder)."""
        prefix = rel.strip("/") + "/" if rel.strip("/") else ""
        return any(n.startswith(prefix) for n in self.files)

    def read_image(self, name: str) -> ImageFile:
        """An image's bytes, read once from the store and hashed as they arrive
        (:func:`fieldcal.measure.imageio.read_stream`, :data:`REMOTE_CHUNK_BYTES` per request).

        Raises
        ------
        ImageError
            The object is missing, unreadable or too large (named by its URL).
        """
        where = self.url_of(name)
        fs, base = self.filesystem()
        try:
            with fs.open(f"{base}/{name}", "rb", cache_type="none", block_size=REMOTE_CHUNK_BYTES) as f:
                return read_stream(f, int(f.size), where, chunk_bytes=REMOTE_CHUNK_BYTES)
        except FileNotFoundError:
            raise ImageError("file not found", where) from None
        except IsADirectoryError:
            raise ImageError("is a directory, not a file", where) from None
        except OSError as err:
            raise ImageError(f"cannot read the file ({one_line(err)[:160]})", where) from None

    def read_range(self, name: str, start: int, n_bytes: int) -> bytes:
        """``n_bytes`` of a file from byte ``start`` (one ranged request)."""
        fs, base = self.filesystem()
        return fs.cat_file(f"{base}/{name}", start=start, end=start + n_bytes)

    def sha256(self, name: str) -> str:
        """SHA-256 of a file's bytes, streamed from the store."""
        return self.read_image(name).sha256


def open_store(url: str, storage_options: dict | None = None, resolve=None) -> SessionStore:
    """The :class:`SessionStore` of a session folder's URL, listed (``resolve``: :class:`SessionStore`).

    Raises
    ------
    InputError
        Nothing is there, or it cannot be listed (named by its URL).
    """
    store = SessionStore(url.rstrip("/"), storage_options, resolve=resolve)
    try:
        files = store.list()
    except OSError as e:
        raise InputError(f"cannot list the session folder: {one_line(e)}", store.url) from None
    if not files:
        raise InputError("session folder not found", store.url)
    return store


def distinct_by_md5(store: SessionStore, names) -> set[str]:
    """The names whose bytes differ from every other name's of the same size, by the MD5s of
    the listing alone: a size shared only by files with known MD5s, and an MD5 no other of
    them has (the loader reads nothing more of those to tell copies apart)."""
    by_size: dict[int, list[str]] = {}
    for n in names:
        by_size.setdefault(store.files.get(n, 0), []).append(n)
    out = set()
    for group in by_size.values():
        if all(n in store.md5 for n in group):
            tags = [store.md5[n] for n in group]
            out.update(n for n, t in zip(group, tags, strict=True) if tags.count(t) == 1)
    return out


def sample_digest(store: SessionStore, name: str, size: int) -> str:
    """SHA-256 of at most 64 KiB from the middle of a file on the store (as the loader's
    local ``_sample_digest``)."""
    n = min(size, 1 << 16)
    return hashlib.sha256(store.read_range(name, (size - n) // 2, n)).hexdigest()
