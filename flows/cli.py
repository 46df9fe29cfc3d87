"""The command line ``fieldcal`` (CONTRACT section 5 and beyond).

Commands
--------
``run SESSION --lake LAKE [--json OUT.json]``
    Calibrate one session with the flow :func:`flows.calibrate.calibrate_session` and
    print the version on standard output (only that when piped; progress and the
    calibration's summary go to standard error on a terminal). With ``--json`` the
    calibration document is also written to ``OUT.json``. A rerun with the same inputs
    and settings prints the existing version (``--force`` makes a new one).
``fleet [ROOT] --lake LAKE``
    Calibrate every session under ROOT (default ``LAKE/sessions``) that has no version yet.
``serve --lake LAKE [--root ROOT] [--cron CRON]``
    Serve the fleet flow on a schedule from this process (Prefect deployment).
``history --lake LAKE [--camera ID | --from DATE --to DATE | --sql QUERY] [--format F]``
    DuckDB SQL over the catalog: one camera's parameters over time, every camera's latest
    calibration in a date range, or any query; as an aligned table, CSV or JSON.
``show VERSION|latest [--camera ID] --lake LAKE [--format text|json]``
    One calibration: its parameters with their sigmas and statistics, or the document.
``synth OUT [--method goniometer|field] ...``
    Write a synthetic session (with ``truth.json``, the camera it was made with).
``demo [--out demo-out]``
    synth -> run -> show -> history on small synthetic sessions, next to their truth.

The report / export commands of :mod:`flows.cli_products` are registered too.

``--lake`` may be given by the environment variable ``FIELDCAL_LAKE``; fsspec options of
an object-store lake by ``--storage-options JSON`` or ``FIELDCAL_STORAGE_OPTIONS``.

Exit status: 0 on success; 2 for bad input or usage (the message names the file and the
problem); 1 for anything else (lake, solver, a failed session in ``fleet``). Errors are
one line on standard error.

Prefect API: ``run``, ``fleet`` and ``demo`` run Prefect flows. When ``PREFECT_API_URL`` is
set (a ``prefect server start`` or Prefect Cloud; also a Prefect profile), they report to
it. Otherwise they start a temporary local Prefect server (SQLite in ``PREFECT_HOME``) for
the duration of the command, which costs 10-20 s on this machine, and put its address in
the settings the Dask workers receive. Prefect's own console logs are silenced (the flow
runs' logs still go to the server) unless ``--verbose``.

Imports are deferred to the commands, so ``fieldcal history`` does not load Prefect and the
Dask worker processes, which re-import this module as their main, start fast.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import time

from fieldcal.errors import one_line

__all__ = ["main", "build_parser"]

LAKE_ENV = "FIELDCAL_LAKE"
OPTIONS_ENV = "FIELDCAL_STORAGE_OPTIONS"
SERVER_TIMEOUT_S = 90


class UsageError(Exception):
    """A command-line argument that is missing or malformed (exit status 2)."""


# --------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------

def _tty(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _lake_args(args) -> tuple[str, dict | None]:
    lake = args.lake or os.environ.get(LAKE_ENV)
    if not lake:
        raise UsageError(f"no lake: give --lake LAKE or set {LAKE_ENV}")
    text = args.storage_options or os.environ.get(OPTIONS_ENV)
    options = None
    if text:
        try:
            options = json.loads(text)
        except json.JSONDecodeError as e:
            raise UsageError(f"--storage-options is not JSON: {e.msg}") from None
        if not isinstance(options, dict):
            raise UsageError("--storage-options must be a JSON object")
    return lake, options


def _open_lake(args):
    from fieldcal.lake.store import Lake

    lake, options = _lake_args(args)
    return Lake(lake, options)


def _settings(args) -> dict | None:
    out = {}
    if getattr(args, "targets_fixed", False):
        out["targets_adjusted"] = False
    if getattr(args, "solver", None):
        out["solver"] = args.solver
    if getattr(args, "rigorous_goniometer", False):
        out["rigorous_goniometer"] = True
    return out or None


def _prefect_env(verbose: bool) -> None:
    """Quiet Prefect's console (not its API logs) before Prefect is imported."""
    if not verbose:
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_FLOW_RUNS_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_TASK_RUNS_LEVEL", "CRITICAL")
        os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "CRITICAL")
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "error")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")


@contextlib.contextmanager
def prefect_api(note=None):
    """Make sure flows have a Prefect API: the configured one, else a temporary local server.

    Parameters
    ----------
    note : callable, optional
        Called with a line of text when a temporary server is started (for a terminal).

    Yields
    ------
    str
        The API URL in use.
    """
    from prefect.settings import PREFECT_API_URL, get_current_settings, temporary_settings

    url = get_current_settings().api.url
    if url:
        yield str(url)
        return
    from prefect.server.api.server import SubprocessASGIServer

    if note:
        note("starting a temporary Prefect server for this command (set PREFECT_API_URL to use a "
             "running one: `prefect server start`)")
    t = time.perf_counter()
    server = SubprocessASGIServer()
    server.start(timeout=SERVER_TIMEOUT_S)
    if note:
        note(f"Prefect server ready at {server.api_url} in {time.perf_counter() - t:.1f} s")
    try:
        with temporary_settings(updates={PREFECT_API_URL: server.api_url}):
            try:
                yield server.api_url
            finally:
                _drain_prefect()
    finally:
        server.stop()


def _drain_prefect() -> None:
    """Send the logs and events still queued to the server before it stops (else exit hangs)."""
    import inspect

    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker
    from prefect.utilities.asyncutils import run_coro_as_sync

    async def drain():
        try:
            result = APILogWorker.instance().drain()
            if inspect.isawaitable(result):
                await result
        except RuntimeError:
            pass
        result = EventsWorker.drain_all()
        if inspect.isawaitable(result):
            await result

    try:
        run_coro_as_sync(drain())
    except Exception:  # noqa: BLE001 - best effort: never turn a finished run into a failure
        pass


def _progress_sink(stream):
    from fieldcal.progress import TerminalProgress

    return TerminalProgress(stream) if _tty(stream) else None


# --------------------------------------------------------------------------------------
# run / fleet / serve
# --------------------------------------------------------------------------------------
def _flow_kwargs(args) -> dict:
    kw = {"dask_address": args.dask, "n_workers": args.workers, "batch_size": args.batch_size,
          "settings": _settings(args),
          "cluster_kwargs": {"processes": True} if getattr(args, "processes", False) else None}
    return {k: v for k, v in kw.items() if v is not None}


def cmd_run(args) -> int:
    from fieldcal import progress

    lake, options = _lake_args(args)
    _prefect_env(args.verbose)
    err = sys.stderr
    human = _tty(err)
    with progress.listening(_progress_sink(err)):
        with prefect_api(note=(lambda s: progress.emit("note", text=s)) if human else None):
            from flows.calibrate import calibrate_session

            result = calibrate_session(str(args.session), str(lake), storage_options=options, force=args.force,
                                       rehash=args.rehash, **_flow_kwargs(args))
    for item in result["left_out"]:
        print(f"fieldcal run: left out {item.get('image')}: {one_line(item.get('reason'))}", file=err)
    if human:
        for line in result["summary"]:
            print(line, file=err)
        state = "new version" if result["new"] else "unchanged (same inputs and settings; --force for a new version)"
        print(f"{result['camera_id']} / {result['session_id']}: {state}", file=err)
    if args.json:
        from fieldcal.lake.store import Lake

        doc = Lake(lake, options).load_document(result["version"])
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(doc, f, indent=2)
            f.write("\n")
    print(result["version"])
    sys.stdout.flush()
    return 0


def _fleet_table(summary: dict) -> str:
    import pyarrow as pa

    from fieldcal.lake.history import to_text

    rows = [{"camera_id": r["camera_id"] or "", "session_id": r["session_id"] or "", "status": r["status"],
             "version": r["version"] or "", "seconds": float(r["seconds"] or 0.0),
             "reason": one_line(r["reason"] or "")} for r in summary["sessions"]]
    schema = pa.schema([("camera_id", pa.string()), ("session_id", pa.string()), ("status", pa.string()),
                        ("version", pa.string()), ("seconds", pa.float64()), ("reason", pa.string())])
    return to_text(pa.Table.from_pylist(rows, schema=schema))


def cmd_fleet(args) -> int:
    lake, options = _lake_args(args)
    _prefect_env(args.verbose)
    from fieldcal import progress

    err = sys.stderr
    with progress.listening(_progress_sink(err)):
        with prefect_api(note=(lambda s: progress.emit("note", text=s)) if _tty(err) else None):
            from flows.fleet import recalibrate_fleet

            kw = _flow_kwargs(args)
            summary = recalibrate_fleet(str(lake), root=args.root, storage_options=options, **kw)
    if args.format == "json":
        print(json.dumps(summary, indent=2))
    else:
        sys.stdout.write(_fleet_table(summary))
        print(f"{summary['n_found']} found, {summary['n_committed']} committed, {summary['n_failed']} failed, "
              f"{summary['n_skipped']} skipped")
    return 1 if summary["n_failed"] else 0


def cmd_serve(args) -> int:
    lake, options = _lake_args(args)
    _prefect_env(args.verbose)
    from flows.fleet import serve_fleet

    params = _flow_kwargs(args)
    if options:
        params["storage_options"] = options
    with prefect_api(note=lambda s: print(s, file=sys.stderr)):
        serve_fleet(str(lake), args.root, name=args.name, cron=args.cron, parameters=params)
    return 0


# --------------------------------------------------------------------------------------
# history / show
# --------------------------------------------------------------------------------------
def _history_extras():
    """The report engineer's optional hook: ``cli_reports.history_extras(parser) -> handler``."""
    from flows import cli_products as cli_reports

    return getattr(cli_reports, "history_extras", None)


def cmd_history(args) -> int:
    handler = getattr(args, "history_extra_handler", None)
    if handler is not None:
        status = handler(args)
        if status is not None:
            return int(status)
    from fieldcal.lake import history

    lake = _open_lake(args)
    if args.sql:
        if args.camera or args.start or args.end:
            raise UsageError("--sql cannot be combined with --camera, --from or --to")
        table = history.sql(lake, args.sql)
    elif args.camera:
        if args.start or args.end:
            raise UsageError("--from / --to select cameras by date; with --camera use --sql for a range")
        table = history.camera_history(lake, args.camera, tuple(args.param or ("f_mm", "xp_mm", "yp_mm")),
                                       all_versions=args.all_versions)
    else:
        table = history.fleet(lake, args.start, args.end)
    sys.stdout.write(history.format_table(table, args.format))
    if args.format == "json":
        sys.stdout.write("\n")
    return 0


def _resolve_version(lake, args) -> str:
    if args.version == "latest":
        if not args.camera:
            raise UsageError("'latest' needs --camera ID")
        v = lake.latest(args.camera, args.session)
        if v is None:
            from fieldcal.errors import LakeError

            raise LakeError(f"no calibration of camera {args.camera!r}"
                            + (f" session {args.session!r}" if args.session else "") + f" in {lake.url}")
        return v
    return args.version


def describe(doc: dict) -> list[str]:
    """Human-readable lines of a calibration document (``fieldcal show``)."""
    from fieldcal.model.camera import PARAM_NAMES

    st = doc.get("stats") or {}
    lines = [f"version   {doc.get('version')}",
             f"camera    {doc.get('camera_id')}   session {doc.get('session_id')}   method {doc.get('method')}",
             f"created   {doc.get('created')}   acquired {doc.get('acquired', '-')}",
             f"sensor    {doc['sensor']['width_px']} x {doc['sensor']['height_px']} px, "
             f"{doc['sensor']['pixel_size_um']} um   model {doc.get('model')}",
             "", f"{'parameter':10s} {'value':>16s} {'sigma':>12s}"]
    fixed = st.get("fixed_parameters") or {}
    for n in PARAM_NAMES:
        s = doc["sigma"].get(n)
        why = f"  fixed ({fixed[n]})" if n in fixed else ("" if s is not None else "  fixed")
        lines.append(f"{n:10s} {doc['parameters'][n]:16.9g} {'' if s is None else format(s, '12.3g'):>12s}{why}")
    lines.append("")
    keys = ("n_images", "n_frames", "n_angles", "n_targets", "n_observations", "n_rejected", "rmse_px",
            "max_px", "sigma0", "sigma_fit_px", "iterations", "solver", "targets_adjusted")
    stats = [f"{k} {st[k]:.4g}" if isinstance(st.get(k), float) else f"{k} {st[k]}" for k in keys if k in st]
    for i in range(0, len(stats), 4):
        lines.append("   ".join(stats[i:i + 4]))
    left = st.get("left_out_images") or []
    if left:
        lines.append(f"left out: {', '.join(str(x) for x in left)}")
    lines.append(f"inputs    {doc.get('inputs', {}).get('fingerprint')}   code {doc.get('code_version', '-')}")
    return lines


def cmd_show(args) -> int:
    lake = _open_lake(args)
    version = _resolve_version(lake, args)
    doc = lake.load_document(version)
    if args.format == "json":
        print(json.dumps(doc, indent=2))
    else:
        print("\n".join(describe(doc)))
    return 0


# --------------------------------------------------------------------------------------
# synth / demo
# --------------------------------------------------------------------------------------
def write_synthetic(out, method: str = "goniometer", *, scenario: str | None = None, seed: int = 0,
                    raster_scale: float = 0.25, images: bool = False, scale: float = 0.25,
                    n_images: int | None = None, marks: bool = False, camera_id: str | None = None,
                    session_id: str | None = None) -> dict:
    """Write a synthetic session into ``out`` and its ``truth.json``; returns the truth.

    Goniometer sessions (``canon5d2`` or ``h3d``) are rendered frames at ``raster_scale``;
    field sessions (``paper`` or ``wide``) are observation-only (``observations.csv``) or,
    with ``images``, rendered images at ``scale`` (``n_images`` of them spread evenly over the
    scenario's images, so that every station is represented; identified from coded targets,
    or from ``marks.csv`` with ``marks``). ``truth.json`` holds the true
    camera (sensor and the 13 parameters) and, for the goniometer, what the method gives
    on the exact spot positions of the same set-up (``noise_free``).
    """
    from pathlib import Path

    import numpy as np

    from fieldcal.errors import InputError
    from fieldcal.model.camera import PARAM_NAMES

    out = Path(out)
    truth: dict = {"method": method, "seed": int(seed)}
    if method == "goniometer":
        from fieldcal.goniometer import method as goniometer
        from fieldcal.synthetic.goniometer import write_session

        scenario = scenario or "canon5d2"
        if scenario not in ("canon5d2", "h3d"):
            raise InputError(f"goniometer scenario must be 'canon5d2' or 'h3d', got {scenario!r}", "synth")
        gt = write_session(out, scenario, seed=seed, raster_scale=raster_scale, camera_id=camera_id,
                           session_id=session_id)
        camera = gt.camera
        frames = goniometer.read_frames_csv(out / "frames.csv")
        ref = goniometer.calibrate(gt.sensor, frames, gt.exact_measurements(),
                                   nominal_focal_mm=gt.scenario.nominal_focal_mm)
        truth["noise_free"] = {n: float(v) for n, v in zip(PARAM_NAMES, ref.parameters, strict=True)}
    elif method == "field":
        from fieldcal.synthetic.field import paper_field, wide_field
        from fieldcal.synthetic.render import scaled_field
        from fieldcal.synthetic.session_writer import write_field_session

        scenario = scenario or "paper"
        makers = {"paper": paper_field, "wide": wide_field}
        if scenario not in makers:
            raise InputError(f"field scenario must be 'paper' or 'wide', got {scenario!r}", "synth")
        sf = makers[scenario](seed=seed)
        if images:
            sf = scaled_field(sf, scale)
            n_all = len(sf.data.images)
            idx = None if n_images is None else sorted({int(round(i)) for i in
                                                        np.linspace(0, n_all - 1, min(int(n_images), n_all))})
            write_field_session(out, sf, images=True, marks_csv=marks, coded=not marks, seed=seed,
                                image_indices=idx, camera_id=camera_id, session_id=session_id)
        else:
            write_field_session(out, sf, images=False, observations_csv=True, seed=seed,
                                camera_id=camera_id, session_id=session_id)
        camera = sf.camera
    else:
        raise InputError(f"method must be 'goniometer' or 'field', got {method!r}", "synth")
    truth.update(scenario=scenario, sensor=camera.sensor.to_dict(),
                 parameters={n: float(v) for n, v in zip(PARAM_NAMES, camera.params, strict=True)})
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth


def cmd_synth(args) -> int:
    write_synthetic(args.out, args.method, scenario=args.scenario, seed=args.seed, raster_scale=args.raster_scale,
                    images=args.images, scale=args.scale, n_images=args.n_images, marks=args.marks,
                    camera_id=args.camera_id, session_id=args.session_id)
    print(os.fspath(args.out))
    return 0


def cmd_demo(args) -> int:
    _prefect_env(args.verbose)
    from flows.demo import run_demo

    return run_demo(args.out, n_workers=args.workers, dask_address=args.dask, with_images=args.images,
                    stream=sys.stdout, note_stream=sys.stderr, api=prefect_api)


# --------------------------------------------------------------------------------------
# the parser
# --------------------------------------------------------------------------------------
def _add_lake(p) -> None:
    p.add_argument("--lake", help=f"the lake: a local path or an fsspec URL (default: ${LAKE_ENV})")
    p.add_argument("--storage-options", metavar="JSON",
                   help=f"fsspec options of the lake as a JSON object (default: ${OPTIONS_ENV})")


def _add_compute(p) -> None:
    p.add_argument("--dask", metavar="ADDRESS", help="scheduler of a running Dask cluster (default: "
                   "$FIELDCAL_DASK_ADDRESS, else a local cluster)")
    p.add_argument("--workers", type=int, default=None, help="workers of the local cluster (default 2)")
    p.add_argument("--processes", action="store_true",
                   help="local cluster: one worker process each instead of threads of this process "
                        "(isolation, at 8-13 s more per run on 2 cores to start and stop them)")
    p.add_argument("--batch-size", type=int, default=None,
                   help="images per measuring task (default: chosen by measurement)")
    p.add_argument("--targets-fixed", action="store_true",
                   help="field method: hold the surveyed targets fixed (default: adjust them)")
    p.add_argument("--solver", choices=("lmqn", "lm"), help="field method: the least-squares method")
    p.add_argument("--rigorous-goniometer", action="store_true",
                   help="goniometer method: the rigorous (non-linearised) principal distance")
    p.add_argument("-v", "--verbose", action="store_true", help="show Prefect's and Dask's logs")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fieldcal", description="Geometric calibration of mapping cameras.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="calibrate one session into the lake; prints the version")
    p.add_argument("session", help="the session folder")
    _add_lake(p)
    p.add_argument("--json", metavar="OUT.json", help="also write the calibration document here")
    p.add_argument("--force", action="store_true", help="a new version even if these inputs are calibrated")
    p.add_argument("--rehash", action="store_true", help="hash every image from its bytes (ignore the "
                   "remembered hashes)")
    _add_compute(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("fleet", help="calibrate every session of a root that has no calibration yet")
    p.add_argument("root", nargs="?", help="root of session folders (default: LAKE/sessions)")
    _add_lake(p)
    p.add_argument("--format", choices=("text", "json"), default="text")
    _add_compute(p)
    p.set_defaults(func=cmd_fleet)

    p = sub.add_parser("serve", help="serve the fleet flow on a cron schedule from this process")
    _add_lake(p)
    p.add_argument("--root", help="root of session folders (default: LAKE/sessions)")
    p.add_argument("--cron", default="0 2 * * *", help="schedule, cron syntax, UTC (default: %(default)s)")
    p.add_argument("--name", default="nightly", help="deployment name (default: %(default)s)")
    _add_compute(p)
    p.set_defaults(func=cmd_serve)

    p = sub.add_parser("history", help="calibration history: SQL over the catalog")
    _add_lake(p)
    p.add_argument("--camera", help="one camera's calibrations over time")
    p.add_argument("--param", action="append", help="catalog column to show with --camera (repeatable; "
                   "default f_mm, xp_mm, yp_mm)")
    p.add_argument("--all-versions", action="store_true", help="with --camera: every version, not the "
                   "latest of each session")
    p.add_argument("--from", dest="start", metavar="DATE", help="every camera's latest calibration acquired "
                   "from this date or time")
    p.add_argument("--to", dest="end", metavar="DATE", help="... up to this date (inclusive) or time")
    p.add_argument("--sql", help="any DuckDB query over the views catalog, residuals, observations")
    p.add_argument("--format", choices=("text", "csv", "json"), default="text")
    extras = _history_extras()
    if extras is not None:
        handler = extras(p)
        if handler is not None:
            p.set_defaults(history_extra_handler=handler)
    p.set_defaults(func=cmd_history)

    p = sub.add_parser("show", help="one calibration: parameters, sigmas, statistics")
    p.add_argument("version", help="a version id, or 'latest' with --camera")
    p.add_argument("--camera", help="with 'latest': the camera")
    p.add_argument("--session", help="with 'latest': the session")
    _add_lake(p)
    p.add_argument("--format", choices=("text", "json"), default="text")
    p.set_defaults(func=cmd_show)

    p = sub.add_parser("synth", help="write a synthetic session (and its truth.json)")
    p.add_argument("out", help="the session folder to write")
    p.add_argument("--method", choices=("goniometer", "field"), default="goniometer")
    p.add_argument("--scenario", help="goniometer: canon5d2 (default) or h3d; field: paper (default) or wide")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--raster-scale", type=float, default=0.25,
                   help="goniometer: pixel grid scale over the same sensor (default %(default)s)")
    p.add_argument("--images", action="store_true", help="field: render images (default: observations.csv only)")
    p.add_argument("--scale", type=float, default=0.25, help="field images: raster scale (default %(default)s)")
    p.add_argument("--n-images", type=int, help="field images: N images spread over the stations (default all)")
    p.add_argument("--marks", action="store_true", help="field images: marks.csv instead of coded targets")
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

    from flows import cli_products as cli_reports

    cli_reports.add_commands(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the ``fieldcal`` console script; returns the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if getattr(args, "func", None) is None:
        parser.print_help(sys.stderr)
        return 2
    name = f"fieldcal {args.command}"
    try:
        return int(args.func(args) or 0)
    except UsageError as e:
        print(f"{name}: {one_line(e)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - one line for people and scripts, the traceback with -v
        from fieldcal.errors import FieldcalError, InputError

        if getattr(args, "verbose", False):
            import traceback

            traceback.print_exc()
        text = one_line(e)
        if not isinstance(e, FieldcalError):
            text = f"{type(e).__name__}: {text}" + ("" if getattr(args, "verbose", False) else
                                                   " (--verbose for details)")
        print(f"{name}: {text}", file=sys.stderr)
        return 2 if isinstance(e, InputError) else 1


if __name__ == "__main__":
    sys.exit(main())
