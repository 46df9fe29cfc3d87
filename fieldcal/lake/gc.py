"""Garbage collection: the parts of versions that were never committed.

A commit that failed or was killed before its catalog row leaves parts nobody sees: its
document and Zarr group under ``calibrations/`` and its rows in ``residuals`` (hidden by the
residuals view, which keeps only rows of catalogued versions), and on a local lake temporary
files of interrupted writes. A rig commit interrupted before its heads' catalog rows (its
commit point, :meth:`fieldcal.lake.store.Lake.commit_rig`) leaves the heads' parts and the rig
document (``rigs/R/S/V.json``), maybe with its row in ``rigs``, which no reader sees: they are
removed as a calibration's are (a rerun of the rig's inputs completes the version when its parts
are whole, else writes a new one). :func:`gc`
removes those older than a grace period (which must exceed the longest commit in progress).
It lists folders one level at a time and never uses a path as a glob pattern, so a lake at
``x/lake[ab]`` cannot touch ``x/lakea``. Delta's own unreferenced files are
:func:`fieldcal.lake.maintenance.vacuum`'s.

Age by the store's clock (issue 24, goal 1): a part's age is the store's time now (the
modification time of a probe file gc writes, :meth:`Storage.now`) minus the newest
modification time of anything of that version (its document, every file of its Zarr
group), both as the store records them. The time in a version id is the *writer's* clock
and is never used: a writer whose clock is a day behind makes ids that look a day old.
A version named committed by the catalog's own log (its commits record the version) is
never collected, even when a damaged catalog file hides its row (``fieldcal lake repair``
restores the row).
"""

from __future__ import annotations

import re

from fieldcal.errors import InputError, LakeError
from fieldcal.lake.ids import ID_PATTERN, VERSION_PATTERN
from fieldcal.lake.parts import reason

__all__ = ["gc", "version_parts", "walk_calibrations", "walk_rigs", "logged_versions"]


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


def _doomed(lake, walk, committed: set, cutoff: float) -> list[str]:
    """The entries of ``walk`` of versions not in ``committed`` none of whose files was
    modified after ``cutoff`` (the store's clock), and temporary files older than it."""
    parts: dict[str, list[str]] = {}
    out = []
    for rel, name, stem in walk:
        if stem is not None and VERSION_PATTERN.fullmatch(stem):
            if stem not in committed:
                parts.setdefault(stem, []).append(rel)
        elif name.startswith(".") and name.endswith(".tmp"):
            mtime = lake.storage.mtime(rel)
            if mtime is not None and mtime <= cutoff:
                out.append(rel)
    for rels in parts.values():
        newest = _newest(lake, rels)
        if newest is not None and newest <= cutoff:
            out += rels
    return out


def version_parts(lake, versions: set[str]) -> list[str]:
    """Lake-relative documents and Zarr groups of the given versions."""
    return [rel for rel, _, stem in walk_calibrations(lake) if stem in versions]


def logged_versions(lake) -> set[str]:
    """Versions the catalog's commit log names as committed (``fieldcal.version`` of its
    commit and migrate commits), and those named by catalog commit files moved to the
    quarantine (even truncated ones): their rows may be hidden by damage, never gone."""
    try:
        entries = lake.tables.commits("catalog")
    except Exception:  # noqa: BLE001 - a log that cannot be read: the catalog rows decide
        entries = []
    return {e["version"] for e in entries if e.get("action") in ("commit", "migrate")
            and isinstance(e.get("version"), str)} | _quarantined_versions(lake)


_LOGGED_VERSION = re.compile(r'"fieldcal\.version":"(\d{8}T\d{6}Z-[0-9a-f]{8}-[0-9a-f]{4})"')


def _quarantined_versions(lake) -> set[str]:
    """Versions named by quarantined catalog commit files (a regular expression over the
    text: a truncated file still names them)."""
    from fieldcal.lake.tables import QUARANTINE

    out = set()
    store = lake.storage
    for stamp in store.listdir(QUARANTINE):
        log = f"{QUARANTINE}/{stamp}/catalog/_delta_log"
        for name in store.listdir(log):
            if name.endswith(".json"):
                try:
                    out |= set(_LOGGED_VERSION.findall(store.read(f"{log}/{name}").decode("utf-8", "replace")))
                except OSError:
                    continue
    return out


def _newest(lake, rels: list[str]) -> float | None:
    times = [t for t in (lake.storage.newest_mtime(r) for r in rels) if t is not None]
    return max(times) if times else None


def gc(lake, grace_s: float = 86400.0, *, dry_run: bool = False) -> list[str]:
    """Remove parts of versions that were never committed, older than ``grace_s`` [s].

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    grace_s : float
        Only parts of versions none of whose files was modified in the last ``grace_s``
        seconds (by the store's clock, module docstring) are removed, and temporary files
        older than this [s]; must exceed the longest commit in progress.
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
    committed = set(lake.tables.scan("catalog", columns=["version"])["version"].to_pylist())
    # committed rig versions only: the row of an interrupted rig commit (its heads not in the
    # catalog) does not keep its document (Lake.commit_rig)
    rigs = set(lake.rig_catalog()["version"].to_pylist())
    if lake.problems:
        raise LakeError(f"gc stops: the catalog or the rigs table of {lake.url} is damaged "
                        f"({lake.problems[0]}); run `fieldcal lake check`")
    committed |= logged_versions(lake)
    cutoff = lake.storage.now() - grace_s
    doomed = (_doomed(lake, walk_calibrations(lake), committed, cutoff)
              + _doomed(lake, walk_rigs(lake), rigs, cutoff))
    stray = _stray_residuals(lake, committed, cutoff)
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


def _stray_residuals(lake, committed: set[str], cutoff: float) -> list[str]:
    """Uncommitted versions with residual rows whose parts are gone or older than the cutoff.

    A commit creates its document before its residual rows, so a version in progress has
    a document; it is looked for now (after the residuals were read), not in the earlier
    listing, and its age comes from the store."""
    res = lake.tables.scan("residuals", columns=["camera_id", "session_id", "version"])
    keys = {}
    for c, s, v in zip(*(res[k].to_pylist() for k in ("camera_id", "session_id", "version")), strict=True):
        if v not in committed and VERSION_PATTERN.fullmatch(v):
            keys.setdefault(v, (c, s))
    out = []
    for v, (c, s) in sorted(keys.items()):
        newest = _newest(lake, [f"calibrations/{c}/{s}/{v}.json", f"calibrations/{c}/{s}/{v}.zarr"])
        if newest is None or newest <= cutoff:
            out.append(v)
    return out
