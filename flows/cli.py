"""The command line ``fieldcal`` (docs/conventions.md section 5 and beyond).

Commands
--------
``run SESSION --lake LAKE [--json OUT.json]``
    Calibrate one session with the flow :func:`flows.calibrate.calibrate_session` and
    print the version on standard output (only that when piped; progress and the
    calibration's summary go to standard error on a terminal). With ``--json`` the
    calibration document is also written to ``OUT.json``. A rerun with the same inputs
    and settings prints the existing version (``--force`` makes a new one).
``fleet [ROOT] --lake LAKE``
    Calibrate every session under ROOT (default ``LAKE/sessions``) that has no version yet,
    several at once on one Dask cluster.
``serve --lake LAKE [--root ROOT] [--cron CRON]``
    Serve the fleet flow on a schedule from this process (Prefect deployment).
``server start|status|stop``
    The local Prefect server that commands share when ``PREFECT_API_URL`` is not set
    (:mod:`flows.server`).
``history``, ``show``, ``synth``, ``demo``
    The calibration history (DuckDB SQL over the catalog), one calibration, a synthetic
    session, the demonstration.

The report / compare / export / undistort commands of :mod:`flows.cli_products` are
registered too (:func:`register`: a module with ``add_commands(subparsers)``).

Input first, servers later: every command checks its arguments, its output paths and the
session (or lake, camera, version) before it imports Prefect or starts anything, so bad
input is refused with exit status 2 in about a second; a rerun of unchanged inputs is
answered from the lake without any server. Only then does a command that runs flows get a
Prefect API (:func:`flows.server.prefect_api`: ``PREFECT_API_URL``, else the local server
kept in the background) and a Dask cluster.

Exit status: 0 on success; 2 for bad input or usage (the message names the file and the
problem); 1 for anything else (lake, solver, a failed session in ``fleet``). Errors are
one line on standard error, naming the command once. Warnings are not shown unless
``--verbose``; a closed pipe (``| head``) ends the command quietly. BLAS and OpenMP use one
thread each unless ``OPENBLAS_NUM_THREADS`` / ``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS``
say otherwise (:data:`THREAD_DEFAULTS`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import warnings

from fieldcal.errors import FieldcalError, one_line
from flows import cli_common as common
from flows.cli_common import UsageError

__all__ = ["main", "build_parser", "register", "COMMAND_MODULES", "CORE_COMMANDS", "UsageError"]

COMMAND_MODULES = ("flows.cli_products", "flows.cli_lake")
"""Modules whose ``add_commands(subparsers)`` registers more commands."""
THREAD_DEFAULTS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
"""One BLAS / OpenMP thread unless the environment says otherwise: the solver's small dense
blocks run 2.5x slower with a thread per core on a 2-core machine that the Dask workers
already keep busy (bench/README_cli.md)."""


# --------------------------------------------------------------------------------------
# checks shared by the commands that run flows
# --------------------------------------------------------------------------------------
def _settings(args) -> dict:
    out = {}
    if getattr(args, "targets_fixed", False):
        out["targets_adjusted"] = False
    if getattr(args, "solver", None):
        out["solver"] = args.solver
    if getattr(args, "rigorous_goniometer", False):
        out["rigorous_goniometer"] = True
    return out


def _check_compute(args) -> None:
    out = getattr(args, "dashboard", None)
    if out and os.path.exists(out) and not os.path.isdir(out):
        raise UsageError(f"--dashboard {out}: exists and is not a folder")
    for name in ("workers", "batch_size", "max_sessions"):
        value = getattr(args, name, None)
        if value is not None and value < 1:
            raise UsageError(f"--{name.replace('_', '-')} must be at least 1, got {value}")


def _cluster_kwargs(args) -> dict | None:
    return {"processes": True} if getattr(args, "processes", False) else None


def _workers(args) -> int:
    from flows.cluster import DEFAULT_WORKERS

    return args.workers or DEFAULT_WORKERS


def _with_api(args, fn):
    """Run ``fn()`` with progress on a terminal and a Prefect API (Prefect imported only now)."""
    from fieldcal import progress
    from flows import server

    server.quiet_prefect(args.verbose)
    err = sys.stderr
    note = (lambda s: progress.emit("note", text=s)) if common.is_tty(err) else None
    with progress.listening(common.progress_sink(err)), server.prefect_api(note=note):
        return fn()


# --------------------------------------------------------------------------------------
# run
# --------------------------------------------------------------------------------------
def _report_run(result: dict, args, human: bool) -> None:
    err = sys.stderr
    for item in result["left_out"]:
        print(f"fieldcal run: left out {item.get('image')}: {one_line(item.get('reason'))}", file=err)
    for version, why in (result.get("not_whole") or {}).items():
        print(f"fieldcal run: version {version} of these inputs does not read back whole ({one_line(why)}): "
              "calibrated again", file=err)
    if human:
        for line in result["summary"]:
            print(line, file=err)
        state = "new version" if result["new"] else "unchanged (same inputs and settings; --force for a new version)"
        print(f"{result['camera_id']} / {result['session_id']}: {state}", file=err)


def _finish_run(version: str, json_path, document) -> None:
    """A run's last words: with ``--json`` the committed ``document()`` written there, then
    the version on standard output. A failed copy still prints the version (it is committed),
    then says why the copy failed."""
    if json_path:
        try:
            common.write_output(json_path, json.dumps(document(), indent=2) + "\n")
        except OSError as e:
            print(version)
            raise FieldcalError(f"committed {version}, but --json {json_path}: {e.strerror}") from None
    print(version)
    sys.stdout.flush()


def _keep_frame_memory(args) -> bool:
    """With the workers as threads of this process (no ``--dask``, no ``--processes``), have
    glibc keep freed frame memory (:func:`fieldcal.measure.heap.keep_freed_memory`), now,
    before any thread exists: 72 bench frames in 0.81-0.96x the time (``bench/README_flow.md``,
    fifth stop). Returns whether it applied."""
    from flows import cluster

    if not cluster.in_process(args.dask, _cluster_kwargs(args)):
        return False
    from fieldcal.measure.heap import keep_freed_memory

    return keep_freed_memory()


def cmd_run(args) -> int:
    _keep_frame_memory(args)
    from fieldcal import batch, pipeline
    from fieldcal.lake.store import Lake

    lake_url, options = common.lake_arguments(args)
    if args.json:
        common.check_output_file(args.json, "--json", overwrite=args.overwrite)
    _check_compute(args)
    lake = Lake(lake_url, options)
    common.check_lake_target(lake)
    from fieldcal.lake import secrets
    from fieldcal.rig.session import is_rig_session

    if is_rig_session(args.session, options, resolve=secrets.resolve):
        return _run_rig(args, lake_url, options)
    prepared = pipeline.prepare(args.session, pipeline.Settings(**_settings(args)), options)
    human = common.is_tty(sys.stderr)
    version = None
    if not args.force:
        from flows.hashcache import known_hashes

        known = {} if args.rehash else known_hashes(prepared)
        version = batch.plan_session(prepared, lake, known, find_cached=False).unchanged
    if version is not None:
        if human:
            sess = prepared.session
            print(f"{sess.camera_id} / {sess.session_id}: unchanged (version {version} has the same inputs and "
                  "settings; --force for a new version)", file=sys.stderr)
    else:
        result = _with_api(args, lambda: _run_flow(args, lake_url, options))
        _report_run(result, args, human)
        version = result["version"]
    _finish_run(version, args.json, lambda: lake.load_document(version))
    return 0


def _run_rig(args, lake_url: str, options) -> int:
    """``fieldcal run`` of a rig session (CONTRACT section 3, "Rig sessions"): validated before
    anything is written, calibrated in this process (its observations need no image work),
    committed as one version of the rig; prints the rig's version, ``--json`` writes the rig
    document."""
    from fieldcal import pipeline, rig_run
    from fieldcal.lake.store import Lake

    settings = pipeline.Settings(**_settings(args))
    prepared = rig_run.prepare_rig(args.session, settings, options)   # bad input: one line, exit 2, nothing written
    lake = Lake(lake_url, options)
    human = common.is_tty(sys.stderr)
    version, heads, outcome = rig_run.run_rig(args.session, lake, force=args.force, prepared=prepared)
    if human:
        same = ["completed the interrupted commit of the same inputs" if getattr(version, "new", False) else
                "unchanged (same inputs and settings; --force for a new version)"]
        for line in (outcome.summary if outcome is not None else same):
            print(line, file=sys.stderr)
        print(f"head versions: {', '.join(heads)}", file=sys.stderr)
    _finish_run(version, args.json, lambda: lake.load_rig_document(version))
    return 0


def _run_flow(args, lake_url: str, options) -> dict:
    from flows import cluster
    from flows.calibrate import calibrate_session

    runner = cluster.task_runner(args.dask, _workers(args), _cluster_kwargs(args))
    return calibrate_session.with_options(task_runner=runner)(
        str(args.session), str(lake_url), storage_options=common.flow_options(options), force=args.force,
        rehash=args.rehash, settings=_settings(args) or None, batch_size=args.batch_size)


# --------------------------------------------------------------------------------------
# fleet / serve / server
# --------------------------------------------------------------------------------------
def _fleet_table(summary: dict) -> str:
    import pyarrow as pa

    from fieldcal.fleet import status_text
    from fieldcal.lake.history import to_text

    rows = []
    for r in summary["sessions"]:
        rows.append({"camera_id": r["camera_id"] or "", "session_id": r["session_id"] or "",
                     "status": ("rig: " if r.get("rig") else "") + status_text(r), "version": r["version"] or "",
                     "seconds": float(r["seconds"] or 0.0),
                     "reason": one_line(r["reason"] or (f"run again after: {r['retried']}" if r.get("retried")
                                                        else ""))})
        rows += [{"camera_id": "  " + h["camera_id"], "session_id": r["session_id"] or "", "status": "head",
                  "version": h["version"] or "", "seconds": None, "reason": ""} for h in r.get("heads") or ()]
    schema = pa.schema([("camera_id", pa.string()), ("session_id", pa.string()), ("status", pa.string()),
                        ("version", pa.string()), ("seconds", pa.float64()), ("reason", pa.string())])
    return to_text(pa.Table.from_pylist(rows, schema=schema))


def cmd_fleet(args) -> int:
    _keep_frame_memory(args)
    from fieldcal import fleet
    from fieldcal.lake.store import Lake

    lake_url, options = common.lake_arguments(args)
    _check_compute(args)
    common.check_lake_target(Lake(lake_url, options))
    root = args.root or (str(lake_url).rstrip("/") + "/sessions")
    found = fleet.scan_sessions(root, options)
    if not found:
        raise UsageError(f"no session under {root} (folders with a session.json, one or two levels deep)")
    if fleet.select_sessions(found, Lake(lake_url, options)):
        def run():
            from flows.fleet import recalibrate_fleet

            return recalibrate_fleet(str(lake_url), root=root, storage_options=common.flow_options(options),
                                     dask_address=args.dask,
                                     n_workers=_workers(args), settings=_settings(args) or None,
                                     batch_size=args.batch_size, cluster_kwargs=_cluster_kwargs(args),
                                     max_sessions=args.max_sessions, dashboard=args.dashboard)

        summary = _with_api(args, run)
    else:
        summary = fleet.summarize(lake_url, root, found)
    if args.format == "json":
        print(json.dumps(summary, indent=2))
    else:
        sys.stdout.write(_fleet_table(summary))
        partial = f" ({summary['n_partial']} with images left out)" if summary.get("n_partial") else ""
        print(f"{summary['n_found']} found, {summary['n_committed']} committed{partial}, {summary['n_failed']} "
              f"failed, {summary['n_skipped']} skipped")
    return 1 if summary["n_failed"] else 0


def _check_cron(text: str) -> None:
    import datetime as dt

    import cronsim

    try:
        cronsim.CronSim(text, dt.datetime.now(dt.UTC))
    except cronsim.CronSimError as e:
        raise UsageError(f"--cron {text!r} is not a cron schedule: {e}") from None


def cmd_serve(args) -> int:
    from fieldcal import fleet

    lake_url, options = common.lake_arguments(args)
    _check_compute(args)
    _check_cron(args.cron)
    from fieldcal.lake.store import Lake

    common.check_lake_target(Lake(lake_url, options))
    fleet.check_root(args.root or (str(lake_url).rstrip("/") + "/sessions"), options)
    params = {k: v for k, v in {"dask_address": args.dask, "n_workers": args.workers, "batch_size": args.batch_size,
                                "dashboard": os.path.abspath(args.dashboard) if args.dashboard else None,
                                "settings": _settings(args) or None, "cluster_kwargs": _cluster_kwargs(args),
                                "storage_options": common.flow_options(options)}.items() if v is not None}

    def serve():
        from flows.fleet import serve_fleet

        print(f"serving recalibrate-fleet/{args.name} on cron '{args.cron}' (UTC); Ctrl-C stops", file=sys.stderr)
        serve_fleet(str(lake_url), args.root, name=args.name, cron=args.cron, parameters=params,
                    report=lambda line: print(f"fieldcal serve: {line}", file=sys.stderr, flush=True))

    _stop_within(_serve_stop_s())
    try:
        _with_api(args, serve)
    except KeyboardInterrupt:
        print("fieldcal serve: stopped", file=sys.stderr)
    return 0


SERVE_STOP_S = 30.0
"""``fieldcal serve`` exits at most this long after Ctrl-C [s] (:func:`_stop_within`;
``FIELDCAL_SERVE_STOP_S`` sets another)."""


def _serve_stop_s() -> float:
    from flows.server import env_seconds

    return env_seconds("FIELDCAL_SERVE_STOP_S", SERVE_STOP_S, positive=True, error=UsageError)


def _stop_within(grace_s: float) -> None:
    """Make Ctrl-C end this process within ``grace_s`` seconds.

    Prefect's runner pauses the served schedules on the API and cancels its loops when
    stopped; against a server that does not answer (a busy or locked database), that wait
    had no end, and Ctrl-C left ``fieldcal serve`` running. The handler raises
    KeyboardInterrupt as Python's own does, and first starts a timer that ends the process
    (exit status 0, one line on standard error) if the shutdown is still going after
    ``grace_s``.
    """
    import signal
    import threading

    def give_up():
        print(f"fieldcal serve: stopped (Prefect's shutdown did not finish within {grace_s:g} s; "
              "the served schedule may still be active on the server)", file=sys.stderr, flush=True)
        _end_children()
        os._exit(0)

    timer = threading.Timer(grace_s, give_up)
    timer.daemon = True

    def on_sigint(signum, frame):
        if timer.ident is None:                     # not started: the first Ctrl-C starts it
            timer.start()
        signal.default_int_handler(signum, frame)

    signal.signal(signal.SIGINT, on_sigint)


def _end_children(wait_s: float = 2.0) -> None:
    """Kill this process's children (a flow run Prefect's runner started, a helper) before
    ``os._exit``: they would outlive it, orphaned, holding its standard error open. The
    local Prefect server is not among them (it runs detached, :func:`flows.server._launch`)."""
    import psutil

    try:
        children = psutil.Process().children(recursive=True)
    except psutil.Error:
        return
    for child in children:
        with contextlib.suppress(psutil.Error):
            child.kill()
    psutil.wait_procs(children, timeout=wait_s)


def cmd_server(args) -> int:
    from flows import server

    server.quiet_prefect(False)
    if args.linger is not None and not math.isfinite(args.linger):
        raise UsageError(f"--linger must be a number of seconds (0: until stopped), got {args.linger}")
    if args.action == "start":
        state = server.start_server(args.linger, note=lambda s: print(s, file=sys.stderr), ui=args.ui)
        print(state["url"])
        if state.get("ui_url"):
            print(f"Prefect UI: {state['ui_url']}", file=sys.stderr)
    elif args.action == "status":
        state = server.server_status()
        if state is None:
            print(f"no local Prefect server under {server.prefect_home()}")
            return 0
        print(f"{state['url']}  pid {state['pid']}  started {state['started']}  linger {state['linger_s']:g} s"
              + (f"  UI {state['ui_url']}" if state.get("ui_url") else "  (no UI: `server start --ui`)"))
    else:
        state = server.stop_server()
        print(f"stopped the local Prefect server at {state['url']} (pid {state['pid']})" if state
              else f"no local Prefect server under {server.prefect_home()}")
    return 0


# --------------------------------------------------------------------------------------
# history / show
# --------------------------------------------------------------------------------------
def cmd_history(args) -> int:
    if getattr(args, "plot", None):
        common.check_output_file(args.plot, "--plot", overwrite=getattr(args, "overwrite", False))
    lake = common.open_lake(args)
    if args.camera:
        common.require_camera(lake, args.camera)
    if args.rig:
        return _rig_history(lake, args)
    handler = getattr(args, "history_extra_handler", None)
    if handler is not None:
        status = handler(args)
        if status is not None:
            return int(status)
    from fieldcal.lake import history

    if args.sql:
        if args.camera or args.start or args.end:
            raise UsageError("--sql cannot be combined with --camera, --from or --to")
        table = history.sql(lake, args.sql, as_of=args.as_of)
    elif args.camera:
        if args.start or args.end:
            raise UsageError("--from / --to select cameras by date; with --camera use --sql for a range")
        params = tuple(args.param or ("f_mm", "xp_mm", "yp_mm"))
        table = history.camera_history(lake, args.camera, params, all_versions=args.all_versions, as_of=args.as_of)
        table = common.shown_columns(table, "camera", args, params)
        _say_latest_of_sessions(lake, args, table)
    else:
        table = common.shown_columns(history.fleet(lake, args.start, args.end, as_of=args.as_of), "fleet", args)
    from flows.cli_lake import report_problems

    report_problems(lake, "fieldcal history")
    sys.stdout.write(history.format_table(table, args.format))
    if args.format == "json":
        sys.stdout.write("\n")
    return 0


def _rig_history(lake, args) -> int:
    """``fieldcal history --rig RIG_ID``: the rig's relative orientations over time
    (:func:`fieldcal.lake.history.rig_history`)."""
    from fieldcal.lake import history
    from flows.cli_lake import report_problems

    if args.camera or args.sql or args.start or args.end or args.param:
        raise UsageError("--rig cannot be combined with --camera, --sql, --from, --to or --param")
    table = history.rig_history(lake, args.rig, all_versions=args.all_versions, as_of=args.as_of)
    if not table.num_rows:
        rigs = sorted(set(lake.rig_catalog(as_of=args.as_of)["rig_id"].to_pylist()))
        raise UsageError(f"rig {args.rig!r} has no version in {lake.url}; "
                         + (f"its rigs: {', '.join(rigs)}" if rigs else "it holds no rig"))
    report_problems(lake, "fieldcal history")
    sys.stdout.write(history.format_table(common.shown_columns(table, "rig", args), args.format))
    if args.format == "json":
        sys.stdout.write("\n")
    return 0


def _say_latest_of_sessions(lake, args, table) -> None:
    """With ``--camera`` and without ``--all-versions``: say on standard error how many
    versions of re-run sessions the table leaves out."""
    if args.all_versions:
        return
    import pyarrow.dataset as ds

    n_all = lake.catalog(filter=ds.field("camera_id") == args.camera, equal={"camera_id": args.camera},
                         sort=False, as_of=args.as_of).num_rows
    hidden = n_all - table.num_rows
    if hidden > 0:
        print(f"fieldcal history: the latest version of each session ({table.num_rows}); {hidden} earlier "
              "version(s) of re-run sessions not shown (--all-versions shows every version)", file=sys.stderr)


def cmd_show(args) -> int:
    lake = common.open_lake(args)
    version = common.resolve_version(lake, args.version, args.camera, args.session)
    doc = lake.load_document(version)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    else:
        print("\n".join(common.describe(doc)))
    return 0


# --------------------------------------------------------------------------------------
# synth / demo
# --------------------------------------------------------------------------------------
def cmd_synth(args) -> int:
    from fieldcal import progress
    from flows.synth import check_synthetic, write_synthetic

    check_synthetic(args.method, args.scenario)
    if args.seed < 0:
        raise UsageError(f"--seed must be a non-negative integer, got {args.seed}")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise UsageError(f"{args.out}: exists and is not a folder")
    with progress.listening(common.progress_sink(sys.stderr)):
        write_synthetic(args.out, args.method, scenario=args.scenario, seed=args.seed,
                        raster_scale=args.raster_scale, images=args.images, scale=args.scale,
                        n_images=args.n_images, marks=args.marks, camera_id=args.camera_id,
                        session_id=args.session_id, check_points=args.check_points)
    print(os.fspath(args.out))
    return 0


def cmd_demo(args) -> int:
    from flows import server
    from flows.demo import run_demo

    if args.workers < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise UsageError(f"--out {args.out}: exists and is not a folder")
    server.quiet_prefect(args.verbose)
    return run_demo(args.out, n_workers=args.workers, dask_address=args.dask, with_images=args.images,
                    stream=sys.stdout, note_stream=sys.stderr, api=server.prefect_api)


# --------------------------------------------------------------------------------------
# the parser
# --------------------------------------------------------------------------------------
def _add_compute(p) -> None:
    p.add_argument("--dask", metavar="ADDRESS", help="scheduler of a running Dask cluster (default: "
                   "$FIELDCAL_DASK_ADDRESS, else a local cluster)")
    p.add_argument("--workers", type=int, default=None, help="workers of the local cluster (default 2)")
    p.add_argument("--processes", action="store_true",
                   help="local cluster: one worker process each instead of threads of this process "
                        "(isolation, at 3-13 s more per run on 2 cores to start and stop them)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="fixed batches of this many images per measuring task (default: one task per "
                        "worker thread, each pulling the images one by one from a queue)")
    p.add_argument("--targets-fixed", action="store_true",
                   help="field method: hold the surveyed targets fixed (default: adjust them)")
    p.add_argument("--solver", choices=("lmqn", "lm"), help="field method: the least-squares method")
    p.add_argument("--rigorous-goniometer", action="store_true",
                   help="goniometer method: the rigorous (non-linearised) principal distance")
    p.add_argument("-v", "--verbose", action="store_true", help="show Prefect's and Dask's logs and warnings")


def _add_dashboard(p) -> None:
    p.add_argument("--dashboard", metavar="DIR", default=None,
                   help="write the fleet dashboard into DIR after each fleet run (fieldcal dashboard)")


def _add_run_commands(sub) -> None:
    p = sub.add_parser("run", help="calibrate one session into the lake; prints the version")
    p.add_argument("session", help="the session folder: a local path or an fsspec URL (s3://bucket/sessions/x, "
                   "its images read by the workers; --storage-options apply to it too)")
    common.add_lake_arguments(p)
    p.add_argument("--json", metavar="OUT.json", help="also write the calibration document here")
    common.add_overwrite_argument(p)
    p.add_argument("--force", action="store_true", help="a new version even if these inputs are calibrated")
    p.add_argument("--rehash", action="store_true", help="hash every image from its bytes (ignore the "
                   "remembered hashes)")
    _add_compute(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("fleet", help="calibrate every session of a root that has no calibration yet")
    p.add_argument("root", nargs="?", help="root of session folders (default: LAKE/sessions)")
    common.add_lake_arguments(p)
    p.add_argument("--format", choices=("text", "json"), default="text")
    p.add_argument("--max-sessions", type=int, default=None,
                   help="sessions calibrated at once (default: twice the cluster's worker threads)")
    _add_dashboard(p)
    _add_compute(p)
    p.set_defaults(func=cmd_fleet)

    p = sub.add_parser("serve", help="serve the fleet flow on a cron schedule from this process")
    common.add_lake_arguments(p)
    p.add_argument("--root", help="root of session folders (default: LAKE/sessions)")
    p.add_argument("--cron", default="0 2 * * *", help="schedule, cron syntax, UTC (default: %(default)s)")
    p.add_argument("--name", default="nightly", help="deployment name (default: %(default)s)")
    _add_dashboard(p)
    _add_compute(p)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("server", help="the local Prefect server that commands share (start, status, stop)")
    p.add_argument("action", choices=("start", "status", "stop"))
    p.add_argument("--linger", type=float, default=None, metavar="SECONDS",
                   help="start: stop by itself this long after the last command (0: only by `server stop`; "
                        "default $FIELDCAL_SERVER_LINGER_S or 600)")
    p.add_argument("--ui", action="store_true", help="start: also serve Prefect's web UI (its address is printed)")
    p.set_defaults(func=cmd_server)


def _add_query_commands(sub) -> None:
    p = sub.add_parser("history", help="calibration history: SQL over the catalog")
    common.add_lake_arguments(p)
    p.add_argument("--camera", help="one camera's calibrations over time")
    p.add_argument("--rig", metavar="RIG_ID", help="one rig's relative orientations over time (per head but the "
                   "reference: rotation and lever arm, their sigmas [arcsec, mm] and changes since the first)")
    p.add_argument("--param", action="append", help="catalog column to show with --camera (repeatable; "
                   "default f_mm, xp_mm, yp_mm)")
    p.add_argument("--all-versions", action="store_true", help="with --camera or --rig: every version (default: the "
                   "latest version of each session; a line on standard error says how many are not shown)")
    p.add_argument("--from", dest="start", metavar="DATE", help="every camera's latest calibration acquired "
                   "from this date or time")
    p.add_argument("--to", dest="end", metavar="DATE", help="... up to this date (inclusive) or time")
    p.add_argument("--sql", help="a read-only DuckDB SELECT over the views catalog, residuals, "
                   "observations_field, observations_goniometer, rigs (no COPY, ATTACH, INSTALL or file access)")
    p.add_argument("--as-of", metavar="TIME", help="answer as the lake was at this time (ISO 8601, UTC)")
    p.add_argument("--format", choices=("text", "csv", "json"), default="text")
    p.add_argument("--columns", metavar="A,B,...", help="the columns to show, in this order (default, as text: a "
                   "set that fits a terminal; CSV and JSON: every column)")
    p.add_argument("--wide", action="store_true", help="every column (the catalog's 57, or --fleet's 21)")
    from flows import cli_products

    handler = cli_products.history_extras(p)
    if handler is not None:
        p.set_defaults(history_extra_handler=handler)
    p.set_defaults(func=cmd_history)
    _add_show_command(sub)


def _add_show_command(sub) -> None:
    p = sub.add_parser("show", help="one calibration: parameters, sigmas, statistics")
    p.add_argument("version", help="a version id, or 'latest' with --camera")
    p.add_argument("--camera", help="with 'latest': the camera")
    p.add_argument("--session", help="with 'latest': the session")
    common.add_lake_arguments(p)
    p.add_argument("--format", choices=("text", "json"), default="text")
    p.set_defaults(func=cmd_show)


def _add_synthetic_commands(sub) -> None:
    p = sub.add_parser("synth", help="write a synthetic session (and its truth.json)")
    p.add_argument("out", help="the session folder to write")
    p.add_argument("--method", choices=("goniometer", "field", "rig"), default="goniometer")
    p.add_argument("--scenario", help="goniometer: canon5d2 (default) or h3d; field: paper (default) or wide; "
                   "rig: two-head (default) or oblique (observation-only rig sessions)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--raster-scale", type=float, default=0.25,
                   help="goniometer: pixel grid scale over the same sensor (default %(default)s)")
    p.add_argument("--images", action="store_true", help="field: render images (default: observations.csv only)")
    p.add_argument("--scale", type=float, default=0.25, help="field images: raster scale (default %(default)s)")
    p.add_argument("--n-images", type=int, help="field images: N images spread over the stations (default all)")
    p.add_argument("--marks", action="store_true", help="field images: marks.csv instead of coded targets")
    p.add_argument("--check-points", type=int, metavar="N",
                   help="field: withhold N surveyed targets as independent check points (session.json)")
    p.add_argument("--camera-id")
    p.add_argument("--session-id")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("demo", help="synth -> run -> show -> history on small synthetic sessions")
    p.add_argument("--out", default="demo-out", help="folder for the sessions and the lake (default %(default)s)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--dask", metavar="ADDRESS")
    p.add_argument("--images", choices=("auto", "yes", "no"), default="auto",
                   help="also a field session of rendered images (auto: when identification is available)")
    p.add_argument("-v", "--verbose", action="store_true")
    p.set_defaults(func=cmd_demo)


def register(subparsers, module: str) -> None:
    """Let ``module`` add its commands: it has ``add_commands(subparsers)``; each sets ``func``."""
    import importlib

    importlib.import_module(module).add_commands(subparsers)


CORE_COMMANDS = ("run", "fleet", "serve", "server", "show", "synth", "demo")
"""Commands of this module that need neither :data:`COMMAND_MODULES` nor ``history``'s options."""


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command; given one of :data:`CORE_COMMANDS`, of the core commands only.

    The commands of :data:`COMMAND_MODULES` (reports, exports) import SciPy and
    Matplotlib for their option values (~1-2 s); ``fieldcal run`` answers bad input faster
    without them.
    """
    parser = argparse.ArgumentParser(prog="fieldcal", description="Geometric calibration of mapping cameras.")
    parser.add_argument("--version", action=_Version,
                        help="print fieldcal's version (and the git commit it runs from) and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_run_commands(sub)
    _add_synthetic_commands(sub)
    if command in CORE_COMMANDS:
        _add_show_command(sub)
        return parser
    _add_query_commands(sub)
    for module in COMMAND_MODULES:
        register(sub, module)
    return parser


class _Version(argparse.Action):
    """``fieldcal --version``: the version and the git commit it runs from (asked only then)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):  # noqa: A002
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        from fieldcal.contract.fingerprint import code_version

        print(f"fieldcal {code_version()}")
        parser.exit()


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """Parse ``argv``; an unknown option is reported with the usage of the command it was given
    to (and the closest option it has), not with the top-level usage."""
    import difflib

    args, extra = parser.parse_known_args(argv)
    if not extra:
        return args
    sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)   # noqa: SLF001
    target = sub.choices.get(getattr(args, "command", None)) if sub is not None else None
    target = target or parser
    options = list(target._option_string_actions)                                                # noqa: SLF001
    hints = [m for e in extra if e.startswith("-")
             for m in difflib.get_close_matches(e.split("=")[0], options, n=1)]
    target.error(f"unrecognized arguments: {' '.join(extra)}"
                 + (f" (did you mean {', '.join(hints)}?)" if hints else ""))
    return args


def _quiet_broken_pipe() -> None:
    """Standard output was closed by its reader (``| head``): discard what is left, quietly."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def main(argv=None) -> int:
    """Entry point of the ``fieldcal`` console script; returns the exit status."""
    for name, value in THREAD_DEFAULTS.items():     # before NumPy is imported (module docstring)
        os.environ.setdefault(name, value)
    from flows import server

    argv = sys.argv[1:] if argv is None else [str(a) for a in argv]
    parser = build_parser(next((a for a in argv if not a.startswith("-")), None))
    args = _parse(parser, argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    verbose = bool(getattr(args, "verbose", False))
    try:
        with warnings.catch_warnings():
            if not verbose:
                warnings.simplefilter("ignore")
            server.prepare_environment()
            status = int(args.func(args) or 0)
        common.report_skipped(f"fieldcal {args.command}")      # what the readers skipped (issue 24)
        return status
    except KeyboardInterrupt:
        print(f"fieldcal {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        _quiet_broken_pipe()
        return 141
    except Exception as e:  # noqa: BLE001 - one line for people and scripts, the traceback with -v
        if verbose:
            import traceback

            traceback.print_exc()
        line, status = common.error_line(args.command, e, verbose=verbose)
        print(line, file=sys.stderr)
        return status
    finally:
        common.forget_opened()


def console() -> None:
    """The ``fieldcal`` console script: :func:`main`, then leave without the native teardown.

    The Python exit handlers run (Prefect drains its log queue) and the streams are
    flushed; then the process ends with ``os._exit``, skipping the C++ static destructors of
    the native libraries. delta-rs with Arrow's thread pools can abort the process there
    ("terminate called without an active exception", exit status -6, delta-io/delta-rs#2184)
    after a command has done its work and printed its result: seen once in ~1000
    ``fieldcal`` processes of the test suite, a `fieldcal gc` on a loaded machine.
    """
    import atexit

    status = main()
    atexit._run_exitfuncs()  # noqa: SLF001 - the documented exit handlers, run as at a normal exit
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe: nothing more can be said
            pass
    os._exit(status)


if __name__ == "__main__":
    console()
