"""The lake's files: a local directory or an fsspec URL, and the options Delta Lake needs.

:class:`Storage` does the few file operations the lake needs beside its Delta tables
(the Zarr groups, the JSON documents, ``README.md``): atomic writes, exclusive creation,
listing one folder (never a glob pattern: a lake may live at ``x/lake[ab]``), removal.
Local writes go to a temporary file and are renamed into place; an exclusive write
hard-links a complete temporary file (it fails if the name exists). Every file gets the
mode the process's umask gives a new file (``0666 & ~umask``), like the Delta and Zarr
files beside it, so that whoever may read the lake reads all of it (issue 24). fsspec writes are
single PUTs, exclusive ones conditional (``If-None-Match: *`` on S3).

:func:`delta_options` turns fsspec's S3 options into those of delta-rs (object_store):
endpoint, credentials, region, plain HTTP for a loopback endpoint, and
``conditional_put = etag`` so that Delta commits on S3 are conditional writes (no lock
service is needed; AWS S3, MinIO and moto honour them).
"""

from __future__ import annotations

import os
import posixpath
import shutil
import tempfile

__all__ = ["Storage", "delta_options", "check_root", "process_umask", "UNSAFE_PATH_CHARACTERS"]

UNSAFE_PATH_CHARACTERS = "[]^|#?%\\"
"""Characters a lake's path may not contain: delta-rs 1.6 parses a local path as a URL, so
``[``, ``]``, ``^``, ``|`` make it fail, ``#`` and ``?`` cut the path, and ``%41`` is
decoded (a lake at ``x/lake%41`` would be written at ``x/lakeA``)."""


def check_root(text: str) -> None:
    """InputError (one line) for a lake path Delta Lake cannot use as it is."""
    from fieldcal.errors import InputError

    bad = sorted({c for c in text if c in UNSAFE_PATH_CHARACTERS or ord(c) < 32 or ord(c) == 127})
    if bad:
        raise InputError(f"the lake path {text!r} contains {', '.join(repr(c) for c in bad)}: "
                         "Delta Lake cannot keep tables there; choose a path without "
                         f"{' '.join(UNSAFE_PATH_CHARACTERS)} or control characters", "lake")


def delta_options(storage_options: dict | None) -> dict[str, str]:
    """delta-rs storage options from fsspec (s3fs) ones; ``AWS_*`` keys pass through."""
    opts = dict(storage_options or {})
    out: dict[str, str] = {}
    endpoint = opts.pop("endpoint_url", None) or (opts.get("client_kwargs") or {}).get("endpoint_url")
    if endpoint:
        out["AWS_ENDPOINT_URL"] = str(endpoint)
        if str(endpoint).startswith("http://"):
            out["AWS_ALLOW_HTTP"] = "true"
    for src, dst in (("key", "AWS_ACCESS_KEY_ID"), ("secret", "AWS_SECRET_ACCESS_KEY"),
                     ("token", "AWS_SESSION_TOKEN")):
        if opts.get(src):
            out[dst] = str(opts[src])
    region = (opts.get("client_kwargs") or {}).get("region_name") or opts.get("region_name")
    if region:
        out["AWS_REGION"] = str(region)
    for k, v in opts.items():
        if isinstance(k, str) and k.upper().startswith("AWS_") and isinstance(v, (str, int, bool)):
            out[k.upper()] = str(v).lower() if isinstance(v, bool) else str(v)
    out.setdefault("AWS_REGION", os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION")
                   or "us-east-1")
    out.setdefault("conditional_put", "etag")
    return out


def process_umask() -> int:
    """The process's file mode creation mask, read without changing it (Linux
    ``/proc/self/status``; elsewhere set and restored at once)."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _info_time(info: dict) -> float | None:
    """A modification time [s] from an fsspec ``info`` (local ``mtime``, S3 ``LastModified``)."""
    import datetime as dt

    for key in ("LastModified", "last_modified", "mtime", "modified", "updated"):
        v = info.get(key)
        if isinstance(v, dt.datetime):
            return (v if v.tzinfo else v.replace(tzinfo=dt.UTC)).timestamp()
        if isinstance(v, (int, float)):
            return float(v)
        if isinstance(v, str):
            try:
                return dt.datetime.fromisoformat(v.replace("Z", "+00:00")).timestamp()
            except ValueError:
                continue
    return None


class Storage:
    """File operations on a local directory or an fsspec URL (see the module docstring)."""

    def __init__(self, url, storage_options=None):
        from fieldcal.lake import secrets

        text = os.fspath(url)
        self.storage_options = dict(secrets.resolve(storage_options) or {})
        if "://" in text and not text.startswith("file://"):
            import fsspec

            self.fs, root = fsspec.core.url_to_fs(text, **self.storage_options)
            self.root = root.rstrip("/")
            self.local = False
        else:
            if text.startswith("file://"):
                text = text[len("file://"):]
            self.fs = None
            self.root = os.path.abspath(text)
            self.local = True
        check_root(self.root)
        self.delta_options = None if self.local else delta_options(self.storage_options)

    def path(self, rel: str) -> str:
        if self.local:
            return os.path.join(self.root, *rel.split("/")) if rel else self.root
        return f"{self.root}/{rel}" if rel else self.root

    def uri(self, rel: str) -> str:
        """A name other libraries understand: a local path, or a URL with the protocol."""
        return self.path(rel) if self.local else self.fs.unstrip_protocol(self.path(rel))

    def delta_uri(self, rel: str) -> str:
        """The name of a Delta table for delta-rs."""
        return self.uri(rel)

    def write(self, rel: str, data: bytes, *, exclusive: bool = False) -> None:
        """Write ``data`` atomically; with ``exclusive`` raise FileExistsError if ``rel`` exists."""
        if not self.local:
            self.fs.pipe_file(self.path(rel), data, mode="create" if exclusive else "overwrite")
            return
        final = self.path(rel)
        folder = os.path.dirname(final)
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(final)}.", suffix=".tmp", dir=folder)
        try:
            os.fchmod(fd, 0o666 & ~process_umask())   # mkstemp makes 0600: the umask decides (issue 24)
            with os.fdopen(fd, "wb") as f:
                f.write(data)
                f.flush()
                os.fsync(f.fileno())
            if exclusive:
                os.link(tmp, final)
            else:
                os.replace(tmp, final)
        finally:
            if os.path.lexists(tmp):
                os.unlink(tmp)

    def write_many(self, rel: str, objects: dict[str, bytes]) -> None:
        """Write ``{key: bytes}`` under the folder ``rel``: on an object store all at once
        (concurrent PUTs), locally one atomic write each."""
        if not self.local:
            self.fs.pipe({f"{self.path(rel)}/{k}": v for k, v in objects.items()})
            return
        for k, v in objects.items():
            self.write(f"{rel}/{k}", v)

    def read(self, rel: str) -> bytes:
        if self.local:
            with open(self.path(rel), "rb") as f:
                return f.read()
        return self.fs.cat_file(self.path(rel))

    def read_many(self, rels: list[str]) -> dict[str, bytes]:
        """``{rel: bytes}`` of several files (concurrent requests on an object store); files
        that do not exist are left out."""
        if self.local:
            out = {}
            for rel in rels:
                try:
                    out[rel] = self.read(rel)
                except FileNotFoundError:
                    continue
            return out
        if not rels:
            return {}
        got = self.fs.cat([self.path(r) for r in rels], on_error="omit")
        by_path = {self.path(r): r for r in rels}
        return {by_path[p]: data for p, data in got.items() if p in by_path and isinstance(data, bytes)}

    def exists(self, rel: str) -> bool:
        if self.local:
            return os.path.exists(self.path(rel))
        self.fs.invalidate_cache(self.path(rel))
        return self.fs.exists(self.path(rel))

    def listdir(self, rel: str) -> list[str]:
        """Names in one folder (sorted; no pattern matching); [] when it does not exist."""
        p = self.path(rel)
        if self.local:
            try:
                return sorted(os.listdir(p))
            except (FileNotFoundError, NotADirectoryError):
                return []
        self.fs.invalidate_cache(p)
        try:
            return sorted(posixpath.basename(x.rstrip("/")) for x in self.fs.ls(p, detail=False))
        except FileNotFoundError:
            return []

    def mtime(self, rel: str) -> float | None:
        """Last modification time [s since the epoch] of a file as the store records it (the
        file system's, or the object store's ``LastModified``); None when it does not exist."""
        if self.local:
            try:
                return os.path.getmtime(self.path(rel))
            except OSError:
                return None
        try:
            self.fs.invalidate_cache(self.path(rel))
            return _info_time(self.fs.info(self.path(rel)))
        except (OSError, ValueError):
            return None

    def newest_mtime(self, rel: str) -> float | None:
        """The latest modification time [s] of a file, or of a folder and anything in it, by
        the store's clock; None when nothing is there."""
        p = self.path(rel)
        if self.local:
            times = []
            for folder, _, names in os.walk(p):
                times.append(os.path.getmtime(folder))
                times += [os.path.getmtime(os.path.join(folder, n)) for n in names
                          if os.path.lexists(os.path.join(folder, n))]
            return max(times) if times else self.mtime(rel)
        self.fs.invalidate_cache(p)
        try:
            found = self.fs.find(p, detail=True)
        except (OSError, ValueError):
            found = {}
        times = [t for t in (_info_time(i) for i in found.values()) if t is not None]
        return max(times) if times else self.mtime(rel)

    def now(self) -> float:
        """The store's own clock [s since the epoch]: the modification time of a probe file
        written now (so that gc never compares a writer's clock with its own; issue 24). A
        store that cannot be written (a dry run on a read-only lake) gives this host's clock."""
        import secrets
        import time

        rel = f".fieldcal-clock-{secrets.token_hex(4)}.tmp"
        if self.local and not os.path.isdir(self.root):
            return time.time()
        try:
            self.write(rel, b"")
            t = self.mtime(rel)
            self.remove(rel)
        except OSError:
            t = None
        return time.time() if t is None else t

    def move(self, rel: str, dest: str) -> None:
        """Move a file or folder within the lake (``dest``'s folders are made)."""
        if self.local:
            os.makedirs(os.path.dirname(self.path(dest)), exist_ok=True)
            os.replace(self.path(rel), self.path(dest))
            return
        self.fs.invalidate_cache(self.path(rel))
        self.fs.mv(self.path(rel), self.path(dest), recursive=True)

    def remove(self, rel: str) -> None:
        p = self.path(rel)
        if self.local:
            if os.path.isdir(p) and not os.path.islink(p):
                shutil.rmtree(p, ignore_errors=False)
            elif os.path.lexists(p):
                os.unlink(p)
            return
        self.fs.invalidate_cache(p)
        if self.fs.exists(p):
            self.fs.rm(p, recursive=True)

    def zarr_store(self, rel: str, *, read_only: bool):
        import zarr

        if self.local:
            return zarr.storage.LocalStore(self.path(rel), read_only=read_only)
        return zarr.storage.FsspecStore.from_url(self.uri(rel), storage_options=self.storage_options,
                                                 read_only=read_only)
