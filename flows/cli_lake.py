"""Lake commands of the ``fieldcal`` CLI: ``lake log|optimize|vacuum|check|repair|migrate`` and ``gc``.

``fieldcal lake log [--table T] [--limit N]``
    The commits of the lake's Delta tables, newest first: time, table, operation, and
    who made each (code version, host, process, user, flow run id, the version committed).
``fieldcal lake optimize [--table T]``
    Compact the tables' small files and write checkpoints (also done automatically every
    ``maintain_every`` commits of a table).
``fieldcal lake vacuum [--retention-hours H] [--apply]``
    Delete the table files that no current row needs and that were replaced more than H
    hours ago (default 168, at least 1): only files a commit removed (compaction,
    deletes), never a file of the current state or one a running commit is writing. Time
    travel (``--as-of``) to before the retention then fails. A dry run unless ``--apply``.
``fieldcal lake check``
    Every damaged object and what depends on it; exit status 1 when there is any.
``fieldcal lake repair [--apply]``
    Restore consistency (:mod:`fieldcal.lake.repair`): damaged or missing table files and
    log entries are quarantined (moved to ``LAKE/quarantine/``, never deleted) and taken out
    of their table, a lost document is written again from its Zarr group, a version that
    cannot be restored leaves the catalog (kept in the quarantine), and the rows of whole
    versions that damage hid are restored. A dry run unless ``--apply``; exit status 1 when
    ``lake check`` still finds damage afterwards.
``fieldcal lake migrate OLD --lake NEW``
    Bring a lake of the first layout (one Parquet file per version) into NEW and verify it
    row for row.
``fieldcal lake fill [--all]``
    Compute the change tests and acceptances that a lake made before they were kept at the
    commit lacks (each camera's latest version and its pair with the previous one; ``--all``
    every version and consecutive pair), with progress on a terminal. Once is enough: the
    commits keep them from then on.
``fieldcal gc [--grace-s S] [--apply]``
    The parts of versions that were never committed (failed or killed commits) older than
    S seconds (default one day). A dry run unless ``--apply``.

Errors are one line on standard error: exit status 2 for bad input, 1 otherwise.
"""

from __future__ import annotations

import sys

from fieldcal.errors import FieldcalError, InputError, one_line

__all__ = ["add_commands", "report_problems"]

MIN_RETENTION_HOURS = 1.0
"""Shortest vacuum retention: longer than any commit writing files."""


def _open(args):
    from flows.cli_products import open_lake

    return open_lake(args)


def report_problems(lake, name: str, stream=None) -> None:
    """One line per damaged object a reader skipped (the command still succeeds)."""
    from flows.cli_common import report_skipped

    report_skipped(name, [lake], stream)


def _run(fn):
    def run(args) -> int:
        name = f"fieldcal {args.command}" + (f" {args.lake_command}" if getattr(args, "lake_command", None)
                                            else "")
        try:
            return int(fn(args) or 0)
        except FieldcalError as e:
            print(f"{name}: {one_line(e)}", file=sys.stderr)
            return 2 if isinstance(e, InputError) else 1
        except OSError as e:
            print(f"{name}: {one_line(e)}", file=sys.stderr)
            return 1
    run.__doc__ = fn.__doc__
    return run


def _tables(args) -> tuple[str, ...]:
    from fieldcal.lake.tables import TABLES

    if args.table is None:
        return TABLES
    if args.table not in TABLES:
        raise InputError(f"--table must be one of {', '.join(TABLES)}, got {args.table!r}", "fieldcal lake")
    return (args.table,)


@_run
def _log(args) -> int:
    import pyarrow as pa

    from fieldcal.lake import history

    lake = _open(args)
    rows = [r for name in _tables(args) for r in lake.tables.log(name, args.limit)]
    rows.sort(key=lambda r: (r["time"] is None, r["time"]), reverse=True)
    keys = ["time", "table", "commit", "operation", "action", "version", "camera_id", "session_id",
            "code_version", "host", "pid", "user", "flow_run_id"]
    table = pa.Table.from_pylist([{k: (None if r.get(k) is None else r[k] if k == "time" else str(r[k]))
                                   for k in keys} for r in rows[:args.limit]])
    if not rows:
        table = pa.table({k: pa.array([], pa.string()) for k in keys})
    sys.stdout.write(history.format_table(table, args.format))
    return 0


@_run
def _optimize(args) -> int:
    lake = _open(args)
    for name in _tables(args):
        m = lake.tables.optimize(name, {"action": "optimize"})
        print(f"{name}: {m['files_removed']} file(s) compacted into {m['files_added']}")
    return 0


@_run
def _vacuum(args) -> int:
    if not (args.retention_hours >= MIN_RETENTION_HOURS):
        raise InputError(f"--retention-hours must be at least {MIN_RETENTION_HOURS:g} (files of "
                         f"running commits must stay), got {args.retention_hours:g}", "fieldcal lake vacuum")
    lake = _open(args)
    for name in _tables(args):
        files = lake.tables.vacuum(name, args.retention_hours, dry_run=not args.apply,
                                   info={"action": "vacuum"})
        verb = "deleted" if args.apply else "would delete"
        print(f"{name}: {verb} {len(files)} file(s)")
        for f in files:
            print(f"  {f}")
        younger = set(lake.tables.vacuum(name, 0, dry_run=True)) - set(files)
        if younger:
            print(f"{name}: {len(younger)} replaced file(s) younger than the retention of "
                  f"{args.retention_hours:g} h are kept (readers of older snapshots and --as-of need them; "
                  f"--retention-hours sets it, at least {MIN_RETENTION_HOURS:g})")
    return 0


@_run
def _check(args) -> int:
    from fieldcal.lake.check import check

    lake = _open(args)
    damage = check(lake)
    lake.problems.clear()                       # listed as damage, not as skipped
    for d in damage:
        print(str(d))
    if damage:
        print(f"fieldcal lake check: {len(damage)} damaged object(s) in {lake.url}", file=sys.stderr)
        return 1
    print(f"{lake.url}: no damage found")
    return 0


@_run
def _repair(args) -> int:
    from fieldcal.lake.check import check
    from fieldcal.lake.repair import repair

    lake = _open(args)
    done = repair(lake, apply=args.apply)
    lake.problems.clear()                       # listed as repairs, not as skipped
    for r in done:
        print(str(r))
    if not args.apply:
        print(f"{len(done)} repair(s) to make in {lake.url}" + (" (dry run: --apply to make them)" if done else ""))
        return 0
    left = check(type(lake)(lake.url, lake.storage.storage_options))
    for d in left:
        print(f"fieldcal lake repair: still damaged: {d}", file=sys.stderr)
    rest = "no damage left" if not left else f"{len(left)} damaged object(s) left"
    print(f"{len(done)} repair(s) made in {lake.url}; {rest}")
    return 1 if left else 0


@_run
def _migrate(args) -> int:
    from fieldcal.errors import LakeError
    from fieldcal.lake.migrate import OldLake, migrate
    from fieldcal.lake.store import Lake
    from flows.cli_common import check_lake_target, lake_arguments

    url, options = lake_arguments(args)
    old = OldLake(args.old, options)
    if OldLake(url, options).url.rstrip("/") == old.url.rstrip("/"):
        raise LakeError(f"migrate into a new lake, not into {old.url} itself")
    lake = Lake(url, options)
    check_lake_target(lake)                  # a file, or a folder that is not a lake: before any work
    report = migrate(old, lake)
    for line in report.lines():
        print(line)
    print(f"verified: every version, residual row and observation of {args.old} is in {lake.url}")
    return 0


@_run
def _fill(args) -> int:
    from fieldcal.products.status import fill
    from flows.cli_common import is_tty

    lake = _open(args)
    tty = is_tty(sys.stderr)

    def progress(done: int, total: int) -> None:
        if tty:
            print(f"\rfieldcal lake fill: {done} of {total} computed", end="" if done < total else "\n",
                  file=sys.stderr, flush=True)

    counts = fill(lake, everything=args.all, progress=progress)
    for line in counts["errors"]:
        print(f"fieldcal lake fill: cannot compute {line}", file=sys.stderr)
    print(f"{lake.url}: {counts['pairs']} pair(s) and {counts['versions']} version(s) wanted, "
          f"{counts['computed']} computed now, {counts['failed']} could not be")
    return 1 if counts["failed"] else 0


@_run
def _gc(args) -> int:
    lake = _open(args)
    removed = lake.gc(args.grace_s, dry_run=not args.apply)
    verb = "removed" if args.apply else "would remove"
    for rel in removed:
        print(f"{verb} {rel}")
    print(f"{len(removed)} part(s) of uncommitted versions {verb}" + ("" if args.apply else
                                                                       " (dry run: --apply to remove)"))
    return 0


def _add_lake(p) -> None:
    p.add_argument("--lake", default=None, help="the lake: a path or fsspec URL (default: $FIELDCAL_LAKE)")
    p.add_argument("--storage-options", metavar="JSON", default=None,
                   help="fsspec options of the lake as JSON (default: $FIELDCAL_STORAGE_OPTIONS)")


def add_commands(subparsers) -> None:
    """Register ``lake`` (log, optimize, vacuum, check, migrate) and ``gc``."""
    from fieldcal.lake.history import FORMATS

    lake_p = subparsers.add_parser("lake", help="the lake's tables: log, optimize, vacuum, check, repair, migrate, "
                                   "fill")
    sub = lake_p.add_subparsers(dest="lake_command", metavar="ACTION", required=True)

    p = sub.add_parser("log", help="the commits of the lake's tables, newest first (who, what, when)")
    _add_lake(p)
    p.add_argument("--table", help="one table (default: all)")
    p.add_argument("--limit", type=int, default=50, help="commits to list (default %(default)s)")
    p.add_argument("--format", choices=FORMATS, default="text")
    p.set_defaults(func=_log)

    p = sub.add_parser("optimize", help="compact small files and write checkpoints")
    _add_lake(p)
    p.add_argument("--table", help="one table (default: all)")
    p.set_defaults(func=_optimize)

    p = sub.add_parser("vacuum", help="delete replaced table files older than the retention (dry run)")
    _add_lake(p)
    p.add_argument("--table", help="one table (default: all)")
    p.add_argument("--retention-hours", type=float, default=168.0,
                   help=f"keep replaced files this long (default %(default)s, at least {MIN_RETENTION_HOURS:g})")
    p.add_argument("--apply", action="store_true", help="delete (default: only list)")
    p.set_defaults(func=_vacuum)

    p = sub.add_parser("check", help="list every damaged object and what depends on it")
    _add_lake(p)
    p.set_defaults(func=_check)

    p = sub.add_parser("repair", help="quarantine damaged files, restore what can be restored (dry run)")
    _add_lake(p)
    p.add_argument("--apply", action="store_true", help="repair (default: only list)")
    p.set_defaults(func=_repair)

    p = sub.add_parser("migrate", help="bring a lake of the first layout into --lake and verify it")
    p.add_argument("old", help="the lake of the first layout (path or URL)")
    _add_lake(p)
    p.set_defaults(func=_migrate)

    p = sub.add_parser("fill", help="compute the change tests and acceptances an older lake lacks (once)")
    _add_lake(p)
    p.add_argument("--all", action="store_true", help="every version and consecutive pair (default: each "
                   "camera's latest and its previous, what history --fleet and the dashboard read)")
    p.set_defaults(func=_fill)

    p = subparsers.add_parser("gc", help="remove parts of versions never committed (dry run by default)")
    _add_lake(p)
    p.add_argument("--grace-s", type=float, default=86400.0,
                   help="only parts older than this [s] (default one day; must exceed the longest commit)")
    p.add_argument("--apply", action="store_true", help="remove (default: only list)")
    p.set_defaults(func=_gc)

