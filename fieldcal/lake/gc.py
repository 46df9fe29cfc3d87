"""Garbage collection: the parts of versions that were never committed.

A commit that failed or was killed before its catalog row leaves parts nobody sees: its
document and Zarr group under ``calibrations/`` and its rows in ``residuals`` (hidden by the
residuals view, which keeps only rows of catalogued versions), and on a local lake temporary
files of interrupted writes. A rig commit interrupted after its rig document
(``rigs/R/S/V.json``) and before its row in the ``rigs`` table leaves that document: it is
removed as a calibration's is (a rerun of the rig's inputs writes a new one). :func:`gc`
removes those older than a grace period (which must exceed the longest commit in progress).
It lists folders one level at a time and never uses a path as a glob pattern, so a lake at
``x/lake[ab]`` cannot touch ``x/lakea``. Delta's own unreferenced files are
:func:`fieldcal.lake.maintenance.vacuum`'s.
"""

from __future__ import annotations

import time

import pyarrow.compute as pc

from fieldcal.errors import InputError, LakeError
from fieldcal.lake.ids import ID_PATTERN, VERSION_PATTERN, utcnow, version_time
from fieldcal.lake.parts import reason

__all__ = ["gc", "version_parts", "walk_calibrations", "walk_rigs"]


def _walk(lake, top: str):
    """``(rel, name, stem)`` of every entry of ``top/A/S/`` (valid A and S only)."""
    store = lake.storage
    for cam in store.listdir(top):
        if not ID_PATTERN.fullmatch(cam):
            continue
        for ses in store.listdir(f"{top}/{cam}"):
            if not ID_PATTERN.fullmatch(ses):
                continue
            for name in store.listdir(f"{top}/{cam}/{ses}"):
                stem = name.rsplit(".", 1)[0] if name.endswith((".json", ".zarr")) else None
                yield f"{top}/{cam}/{ses}/{name}", name, stem


def walk_calibrations(lake):
    """``(rel, name, stem)`` of every entry of ``calibrations/C/S/`` (valid C and S only)."""
    yield from _walk(lake, "calibrations")


def walk_rigs(lake):
    """``(rel, name, stem)`` of every entry of ``rigs/R/S/`` (valid R and S only): rig documents."""
    yield from _walk(lake, "rigs")


def _doomed(lake, walk, committed: set, grace_s: float, now, cutoff: float) -> list[str]:
    """The entries of ``walk`` of versions not in ``committed`` and old temporary files."""
    out = []
    for rel, name, stem in walk:
        if stem is not None and VERSION_PATTERN.fullmatch(stem):
            if stem not in committed and _old(stem, grace_s, now):
                out.append(rel)
        elif name.startswith(".") and name.endswith(".tmp"):
            mtime = lake.storage.mtime(rel)
            if mtime is not None and mtime < cutoff:
                out.append(rel)
    return out


def version_parts(lake, versions: set[str]) -> list[str]:
    """Lake-relative documents and Zarr groups of the given versions."""
    return [rel for rel, _, stem in walk_calibrations(lake) if stem in versions]


def _old(version: str, grace_s: float, now) -> bool:
    return (now - version_time(version)).total_seconds() > grace_s


def gc(lake, grace_s: float = 86400.0, *, dry_run: bool = False) -> list[str]:
    """Remove parts of versions that were never committed, older than ``grace_s`` [s].

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    grace_s : float
        Only parts of versions whose id (commit time) is older than this are removed, and
        temporary files older than this [s]; must exceed the longest commit in progress.
    dry_run : bool
        Only list what would be removed.

    Returns
    -------
    list of str
        Lake-relative paths removed (or that would be: documents and Zarr groups under
        ``calibrations/``, rig documents under ``rigs/``), and ``residuals: version=V`` for the
        residual rows of each uncommitted version.
    """
    if not (grace_s >= 0):
        raise InputError(f"grace_s must be >= 0, got {grace_s}", "gc")
    now = utcnow()
    committed = set(lake.tables.scan("catalog", columns=["version"])["version"].to_pylist())
    rigs = set(lake.tables.scan("rigs", columns=["version"])["version"].to_pylist())
    if lake.problems:
        raise LakeError(f"gc stops: the catalog or the rigs table of {lake.url} is damaged "
                        f"({lake.problems[0]}); run `fieldcal lake check`")
    cutoff = time.time() - grace_s
    doomed = (_doomed(lake, walk_calibrations(lake), committed, grace_s, now, cutoff)
              + _doomed(lake, walk_rigs(lake), rigs, grace_s, now, cutoff))
    res = lake.tables.scan("residuals", columns=["version"])
    stray = sorted(v for v in pc.unique(res["version"]).to_pylist()
                   if v not in committed and VERSION_PATTERN.fullmatch(v) and _old(v, grace_s, now))
    if dry_run:
        return doomed + [f"residuals: version={v}" for v in stray]
    for rel in doomed:
        try:
            lake.storage.remove(rel)
        except FileNotFoundError:
            pass
        except OSError as e:
            raise LakeError(f"cannot remove {lake.uri(rel)}: {reason(e)}") from None
    if stray:
        values = ", ".join("'" + v + "'" for v in stray)
        lake.tables.delete("residuals", f"version IN ({values})", {"action": "gc"})
    return doomed + [f"residuals: version={v}" for v in stray]
