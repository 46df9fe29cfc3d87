"""Command-line commands for reports, comparisons and exports (issue 6).

:func:`add_commands` is called by :mod:`flows.cli` with its ``argparse`` sub-parsers;
each command registered here sets ``func`` (called with the parsed arguments, returns
the exit status). Every command takes ``--lake LAKE`` (default: the ``FIELDCAL_LAKE``
environment variable) and names a calibration by its version, or ``latest --camera ID``
(``compare`` also takes ``previous``: the version before the latest of that camera's
sessions).

- ``fieldcal report VERSION [--out DIR]``: ``DIR/report.html`` (self-contained) and the
  plots as PNG (:mod:`fieldcal.products.report`); prints the HTML's path.
- ``fieldcal certificate VERSION [--out DIR] [--config FILE] [--pdf] [--strict]``:
  ``DIR/certificate.html`` (and ``certificate.pdf``), the calibration certificate with its
  acceptance verdict (:mod:`fieldcal.products.certificate`); prints the paths; one warning
  line names what the configuration does not state (``--strict`` refuses then).
- ``fieldcal compare V1 V2 [--plot PNG] [--format text|json] [--out FILE]``: where the same
  ray lands in both, what their uncertainties explain, and the change test
  (:mod:`fieldcal.analysis.compare`).
- ``fieldcal dashboard --out DIR``: the fleet dashboard, a static site
  (:mod:`fieldcal.products.dashboard`); prints the path of its ``index.html``.
- ``fieldcal export VERSION --format opencv|colmap|metashape|json [--out FILE]``: to standard
  output unless ``--out``; the fit's residual and round trip on standard error
  (:mod:`fieldcal.products.export`). ``--strict`` refuses (exit 3) an export that cannot be exact.
- ``fieldcal undistort VERSION IMAGE.tif OUT.tif``: the corrected image by ``cv2.remap``
  (:mod:`fieldcal.products.undistort`).

``fieldcal history`` belongs to :mod:`flows.cli`; :func:`history_extras` adds its
``--plot FILE.png`` and ``--fleet`` options and :func:`history_handler` runs them (it
returns None when neither was asked for, so the plain history runs as usual).

Exit status (as :func:`flows.cli.main`): 0 on success; 2 with a one-line reason on
standard error for bad input (an argument, a version id, a file); 1 for other fieldcal
errors (an unreadable lake, a version that is not committed); 3 for ``export --strict``
when the export cannot be exact.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from fieldcal import progress
from flows.cli_common import (
    EXIT_ERROR,
    EXIT_USAGE,
    LAKE_ENV,
    OPTIONS_ENV,
    UsageError,
    add_lake_arguments,
    add_overwrite_argument,
    check_input_file,
    check_output_file,
    open_lake,
    progress_sink,
    resolve_version,
    write_output,
)

__all__ = ["add_commands", "history_extras", "history_handler", "resolve_version",
           "open_lake", "EXIT_ERROR", "EXIT_USAGE", "EXIT_NOT_EXACT", "LAKE_ENV", "OPTIONS_ENV"]

EXIT_NOT_EXACT = 3


# --------------------------------------------------------------------------------------
# shared arguments
# --------------------------------------------------------------------------------------
def _add_lake(p: argparse.ArgumentParser) -> None:
    add_lake_arguments(p)


def _add_camera(p: argparse.ArgumentParser) -> None:
    p.add_argument("--camera", default=None, metavar="ID",
                   help="camera id, to name a version as 'latest' (or 'previous')")


def _lake_and_version(args):
    """``(lake, version)`` named by ``--lake``, ``--version`` and ``--camera``."""
    lake = open_lake(args)
    return lake, resolve_version(lake, args.version, args.camera)


def _run(fn):
    """Mark a command function (kept for the commands registered here): errors propagate to
    :func:`flows.cli.main`, which prints them as one line naming the command and sets the
    exit status (2 for bad input, 1 otherwise)."""
    return fn


def _check_outputs(args, *pairs) -> None:
    """Check every ``(path, option)`` output before any work (None paths are skipped); an
    existing file only with ``--overwrite``."""
    for path, what in pairs:
        if path:
            check_output_file(path, what, overwrite=getattr(args, "overwrite", False))


def _write_text(text: str, out: str | None) -> None:
    if out:
        write_output(out, text)
    else:
        sys.stdout.write(text)


# --------------------------------------------------------------------------------------
# commands
# --------------------------------------------------------------------------------------
@_run
def _report(args) -> int:
    from fieldcal.products.report import write_report

    if args.out and os.path.exists(args.out) and not os.path.isdir(args.out):
        raise UsageError(f"--out {args.out}: exists and is not a folder")
    lake = open_lake(args)
    version = resolve_version(lake, args.version, args.camera)
    out = args.out or f"fieldcal-report-{version}"
    if os.path.exists(os.path.join(out, "report.html")) and not args.overwrite:
        raise UsageError(f"--out {out}: has a report.html; fieldcal does not write over it (--overwrite replaces it)")
    with progress.listening(progress_sink(sys.stderr)):
        progress.emit("stage", text=f"report of {version}: reading the version and drawing the plots")
        files = write_report(lake, version, out)
    print(files.html)
    return 0


@_run
def _certificate(args) -> int:
    from fieldcal.products.certificate import check_outputs, load_config, missing_line, write_certificate

    config = load_config(args.config)             # a bad configuration: before the lake is read
    lake = open_lake(args)
    version = resolve_version(lake, args.version, args.camera)
    out = args.out or f"fieldcal-certificate-{version}"
    check_outputs(out, pdf=args.pdf)
    strict = args.strict or config["certificate"]["strict"]
    warning = None if strict else missing_line(config, args.config)
    written = write_certificate(lake, version, out, args.config, pdf=args.pdf, strict=strict)
    if warning:
        print(f"fieldcal certificate: warning: {warning}", file=sys.stderr)
    if args.pdf:
        print(Path(out) / "certificate.html")
    print(written)
    return 0


def _comparison_text(c, a, b) -> str:
    lines = [f"A: {a.label()}", f"B: {b.label()}",
             f"tested {c.where}"
             + (f" (grid {c.grid[0]} x {c.grid[1]})" if c.region == "sensor" else ""),
             f"change where tested: max {c.max_px:.4g} px = {c.max_um:.4g} µm, "
             f"RMS {c.rms_px:.4g} px = {c.rms_um:.4g} µm",
             f"over the whole sensor (display{', extrapolated off the axes' if c.region == 'axes' else ''}): "
             f"max {c.sensor_max_px:.4g} px = {c.sensor_max_px * c.pixel_size_um:.4g} µm; "
             f"explained by the two uncertainties (1 sigma): up to {float(c.sigma_px.max()):.4g} px",
             f"tests (Holm at alpha = {c.alpha:g}):"]
    lines += [f"  {t.line()}" for t in c.tests]
    lines.append(f"  outside the explained range: {c.outside_px:.2g} px (limit {c.outside_tol_px:g} px)")
    lines += [f"not tested: {x}" for x in c.left_out]
    lines.append(f"verdict: {c.verdict}")
    return "\n".join(lines) + "\n"


@_run
def _compare(args) -> int:
    from fieldcal.analysis.compare import check_grid, check_level, compare_calibrations
    from fieldcal.analysis.uncertainty import Calibration

    check_level(args.tolerance_um, args.alpha)       # bad settings: refused before the lake is read
    check_grid(args.grid)
    _check_outputs(args, (args.plot, "--plot"), (args.out, "--out"))
    lake = open_lake(args)
    if lake.is_rig_version(args.v1) or lake.is_rig_version(args.v2):
        return _compare_rigs(lake, args)
    va = resolve_version(lake, args.v1, args.camera)
    vb = resolve_version(lake, args.v2, args.camera)
    a, b = Calibration.from_lake(lake, va), Calibration.from_lake(lake, vb)
    c = compare_calibrations(a, b, grid=tuple(args.grid), tolerance_um=args.tolerance_um,
                             alpha=args.alpha, remove_rotation=args.remove_rotation)
    if args.plot:
        from fieldcal.products.plots import compare_figure, to_png

        write_output(args.plot, to_png(compare_figure(c, a.sensor)))
    if args.format == "json":
        text = json.dumps(c.summary(), indent=2) + "\n"
    else:
        text = _comparison_text(c, a, b)
    _write_text(text, args.out)
    return 0


def _compare_rigs(lake, args) -> int:
    """``fieldcal compare RIG_V1 RIG_V2``: the change test of the relative orientations
    (:mod:`fieldcal.products.rig_compare`)."""
    from fieldcal.errors import InputError
    from fieldcal.products.rig_compare import compare_rigs, rig_comparison_text

    for v in (args.v1, args.v2):
        if not lake.is_rig_version(v):
            raise InputError(f"{v} is not a rig version of {lake.url}: compare two rig versions, or two "
                             "calibration versions of one camera", "compare")
    c = compare_rigs(lake.load_rig_document(args.v1), lake.load_rig_document(args.v2), alpha=args.alpha,
                     tolerance_arcsec=args.tolerance_arcsec, tolerance_mm=args.tolerance_mm)
    text = json.dumps(c, indent=2) + "\n" if args.format == "json" else rig_comparison_text(c)
    _write_text(text, args.out)
    return 0


@_run
def _dashboard(args) -> int:
    from fieldcal.analysis.compare import check_level
    from fieldcal.products.certificate import load_config
    from fieldcal.products.dashboard import write_dashboard

    load_config(args.config)
    check_level(args.tolerance_um, args.alpha)
    if os.path.exists(args.out) and not os.path.isdir(args.out):
        raise UsageError(f"--out {args.out}: exists and is not a folder")
    lake = open_lake(args)
    with progress.listening(progress_sink(sys.stderr)):
        progress.emit("stage", text=f"dashboard of {lake.url}")
        got = write_dashboard(lake, args.out, config_path=args.config, tolerance_um=args.tolerance_um,
                              alpha=args.alpha, reports_url=args.reports_url)
    print(got["index"])
    print(f"{got['cameras']} camera(s): {got['moved']} moved, {got['expired']} expired, {got['failed']} failed",
          file=sys.stderr)
    return 0


@_run
def _export(args) -> int:
    from fieldcal.analysis.uncertainty import Calibration
    from fieldcal.products.export import export_text

    _check_outputs(args, (args.out, "--out"))
    cal = Calibration.from_lake(*_lake_and_version(args))
    exp = export_text(cal, args.format, model=args.model)
    for line in exp.report_lines():
        print(line, file=sys.stderr)
    if args.strict and not exp.exact:
        print(f"fieldcal export: refused (--strict): the {args.format} export cannot round-trip "
              "within 0.01 px", file=sys.stderr)
        return EXIT_NOT_EXACT
    _write_text(exp.text, args.out)
    return 0


@_run
def _undistort(args) -> int:
    from fieldcal.analysis.uncertainty import Calibration
    from fieldcal.products.undistort import undistort_file

    check_input_file(args.image, "IMAGE")
    if os.path.exists(args.output) and os.path.samefile(args.image, args.output):
        raise UsageError(f"OUT {args.output} is the input image {args.image} (the same file): "
                         "refusing to overwrite the photograph")
    check_output_file(args.output, "OUT", overwrite=args.overwrite)
    cal = Calibration.from_lake(*_lake_and_version(args))
    doc = cal.document
    out = Path(os.path.abspath(args.output))
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp.tif")     # renamed over OUT: its links keep their bytes
    try:
        info = undistort_file(cal.camera, args.image, tmp, f_px=args.f_px, interpolation=args.interpolation,
                              provenance={"camera_id": doc.get("camera_id"),
                                          "session_id": doc.get("session_id"), "version": doc.get("version")})
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    k = info["K"]
    print(f"{args.output}: corrected image {info['width_px']} x {info['height_px']} px, pinhole "
          f"fx = fy = {k[0][0]:.6g} px, cx = {k[0][2]:.6g}, cy = {k[1][2]:.6g} (OpenCV convention), "
          "no distortion")
    return 0


def _add_certificate(subparsers) -> None:
    """Register ``certificate`` (module docstring)."""
    p = subparsers.add_parser("certificate", help="write the printable calibration certificate",
                              description="Write DIR/certificate.html (and with --pdf DIR/certificate.pdf): "
                                          "identity, interior orientation with expanded uncertainties, the "
                                          "focal lengths to use, distortion per semi-diagonal and its plot, "
                                          "correlations, adjustment, coverage, check points, traceability "
                                          "and conditions, the change since the previous calibration and "
                                          "the acceptance verdict (A4). An existing certificate is not "
                                          "overwritten.")
    p.add_argument("version", metavar="VERSION", help="a version id, or 'latest' with --camera")
    _add_camera(p)
    _add_lake(p)
    p.add_argument("--out", metavar="DIR", default=None,
                   help="output folder (default ./fieldcal-certificate-VERSION)")
    p.add_argument("--config", metavar="FILE", default=None,
                   help="TOML or JSON: issuer, facility, identity, traceability, conditions, validity "
                        "and acceptance thresholds (defaults: fieldcal.products.certificate.DEFAULT_CONFIG)")
    p.add_argument("--pdf", action="store_true",
                   help="also DIR/certificate.pdf, printed by headless Chromium (apt-get install chromium)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 2) when the configuration leaves out what an agency's certificate "
                        "states (camera, lens, facility, issuer, traceability, focus, aperture)")
    p.set_defaults(func=_certificate, command="certificate")


def add_commands(subparsers) -> None:
    """Register ``report``, ``certificate``, ``compare``, ``export`` and ``undistort`` (module
    docstring)."""
    from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM
    from fieldcal.products.export import FORMATS, OPENCV_MODELS
    from fieldcal.products.undistort import INTERPOLATION

    p = subparsers.add_parser("report", help="write the HTML report of a calibration",
                              description="Write DIR/report.html (self-contained, plots embedded) "
                                          "and the plots as PNG.")
    p.add_argument("version", metavar="VERSION", help="a version id, or 'latest' with --camera")
    _add_camera(p)
    _add_lake(p)
    p.add_argument("--out", metavar="DIR", default=None,
                   help="output folder (default ./fieldcal-report-VERSION)")
    add_overwrite_argument(p)
    p.set_defaults(func=_report, command="report")

    _add_certificate(subparsers)

    p = subparsers.add_parser("compare", help="compare two calibrations of one camera",
                              description="Where the same ray lands in V1 and V2 over the sensor, "
                                          "what their uncertainties explain, and a chi-square test "
                                          "of the change.")
    p.add_argument("v1", metavar="V1", help="reference version (or 'latest' / 'previous')")
    p.add_argument("v2", metavar="V2", help="other version (or 'latest' / 'previous')")
    _add_camera(p)
    _add_lake(p)
    p.add_argument("--tolerance-um", type=float, default=DEFAULT_TOLERANCE_UM,
                   help=f"tolerance of a change in the image plane [µm] (default {DEFAULT_TOLERANCE_UM:g})")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                   help=f"significance level (default {DEFAULT_ALPHA:g})")
    p.add_argument("--remove-rotation", action="store_true",
                   help="remove the best common rotation of the camera frames first")
    p.add_argument("--tolerance-arcsec", type=float, default=10.0,
                   help="rig versions: tolerance of a relative rotation change [arcsec] (default 10)")
    p.add_argument("--tolerance-mm", type=float, default=1.0,
                   help="rig versions: tolerance of a lever-arm change [mm] (default 1)")
    p.add_argument("--grid", type=int, nargs=2, default=(41, 31), metavar=("NX", "NY"),
                   help="grid over the sensor (default 41 31)")
    p.add_argument("--plot", metavar="PNG", default=None, help="also draw the maps into PNG")
    p.add_argument("--format", choices=("text", "json"), default="text")
    p.add_argument("--out", metavar="FILE", default=None, help="write here instead of stdout")
    add_overwrite_argument(p)
    p.set_defaults(func=_compare, command="compare")

    p = subparsers.add_parser("dashboard", help="write the fleet dashboard: a static site (open DIR/index.html)",
                              description="One row per camera (latest calibration, verdict, certificate "
                                          "validity, last change test) with filters, and a page per camera "
                                          "with history plots and its versions; no server needed.")
    _add_lake(p)
    p.add_argument("--out", metavar="DIR", required=True, help="folder of the site (index.html, cameras/)")
    p.add_argument("--config", metavar="FILE", default=None, help="certificate configuration (validity, "
                   "acceptance thresholds), as for `fieldcal certificate`")
    p.add_argument("--tolerance-um", type=float, default=DEFAULT_TOLERANCE_UM,
                   help=f"tolerance of a change in the image plane [um] (default {DEFAULT_TOLERANCE_UM:g})")
    p.add_argument("--alpha", type=float, default=DEFAULT_ALPHA, help=f"significance level (default {DEFAULT_ALPHA:g})")
    p.add_argument("--reports-url", metavar="URL", default=None,
                   help="the URL the lake is served at: links become URL/reports/... (default: relative to DIR "
                        "for a local lake, else the lake's URL)")
    p.set_defaults(func=_dashboard, command="dashboard")

    p = subparsers.add_parser("export", help="export a calibration to OpenCV, COLMAP, Metashape "
                                             "or JSON",
                              description="Fit the target model to the calibration and write it; "
                                          "the fit residual and round trip go to stderr.")
    p.add_argument("version", metavar="VERSION", help="a version id, or 'latest' with --camera")
    _add_camera(p)
    _add_lake(p)
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("--model", default="auto", choices=("auto",) + tuple(OPENCV_MODELS),
                   help="OpenCV / COLMAP distortion model (default: the simplest exact one)")
    p.add_argument("--strict", action="store_true",
                   help="refuse (exit 3) when the export cannot round-trip within 0.01 px")
    p.add_argument("--out", metavar="FILE", default=None, help="write here instead of stdout")
    add_overwrite_argument(p)
    p.set_defaults(func=_export, command="export")

    p = subparsers.add_parser("undistort", help="write the distortion-free image of a photograph",
                              description="Resample IMAGE.tif with cv2.remap into the image of a "
                                          "distortion-free pinhole camera (same size, principal "
                                          "point at the centre).")
    p.add_argument("version", metavar="VERSION", help="a version id, or 'latest' with --camera")
    p.add_argument("image", metavar="IMAGE.tif")
    p.add_argument("output", metavar="OUT.tif")
    _add_camera(p)
    _add_lake(p)
    p.add_argument("--interpolation", choices=tuple(INTERPOLATION), default="linear")
    p.add_argument("--f-px", type=float, default=None,
                   help="principal distance of the output [px] (default f / pixel pitch)")
    add_overwrite_argument(p)
    p.set_defaults(func=_undistort, command="undistort")


# --------------------------------------------------------------------------------------
# history --plot / --fleet
# --------------------------------------------------------------------------------------
def history_extras(parser: argparse.ArgumentParser):
    """Add ``--plot FILE.png``, ``--fleet``, ``--tolerance-um``, ``--alpha`` and ``--param``
    to ``fieldcal history``'s parser (options it does not already have); returns
    :func:`history_handler`, which :func:`flows.cli.cmd_history` calls first."""
    from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM

    have = set(parser._option_string_actions)            # noqa: SLF001 - argparse has no API
    if "--plot" not in have:
        parser.add_argument("--plot", metavar="PNG", default=None,
                            help="draw the parameters over time (or, with --fleet, the fleet) "
                                 "into PNG")
    if "--fleet" not in have:
        parser.add_argument("--fleet", action="store_true",
                            help="every camera's latest calibration against its previous one, "
                                 "flagged when it moved significantly and by more than the "
                                 "tolerance")
    if "--tolerance-um" not in have:
        parser.add_argument("--tolerance-um", type=float, default=DEFAULT_TOLERANCE_UM,
                            help=f"tolerance in the image plane [µm] (default {DEFAULT_TOLERANCE_UM:g})")
    if "--alpha" not in have:
        parser.add_argument("--alpha", type=float, default=DEFAULT_ALPHA,
                            help=f"significance level of the change test (default {DEFAULT_ALPHA:g})")
    if "--overwrite" not in have:
        add_overwrite_argument(parser)
    if "--param" not in have:
        parser.add_argument("--param", action="append", default=None, metavar="NAME",
                            help="another parameter to plot (repeatable)")
    return history_handler


def _history_parameters(args) -> list[str]:
    names = ["f_mm", "xp_mm", "yp_mm"]
    for attr in ("parameters", "param"):
        extra = getattr(args, attr, None)
        if isinstance(extra, str):
            extra = [x for x in extra.replace(",", " ").split() if x]
        for n in extra or []:
            if n not in names:
                names.append(n)
    return names


def history_handler(args) -> int | None:
    """Run ``history --plot`` / ``--fleet``; None when neither was asked for."""
    if not (getattr(args, "plot", None) or getattr(args, "fleet", False)):
        return None
    return _history(args)


@_run
def _history(args) -> int:
    from fieldcal.lake import history
    from fieldcal.products import plots
    from fieldcal.products.report import fleet_summary, parameter_tolerance

    _check_outputs(args, (args.plot, "--plot"), (getattr(args, "out", None), "--out"))
    lake = open_lake(args)
    if args.fleet:
        table = fleet_summary(lake, tolerance_um=args.tolerance_um, alpha=args.alpha,
                              start=getattr(args, "start", None), end=getattr(args, "end", None),
                              as_of=getattr(args, "as_of", None))
        fmt = getattr(args, "format", None) or "text"
        from flows.cli_common import shown_columns

        shown = shown_columns(table, "changes", args)
        text = history.format_table(shown, fmt if fmt in history.FORMATS else "text")
        _write_text(text, getattr(args, "out", None))
        if args.plot:
            write_output(args.plot, plots.to_png(plots.fleet_plot(table, tolerance_um=args.tolerance_um)))
        return 0
    camera = getattr(args, "camera", None)
    if not camera:
        raise UsageError("--plot needs --camera ID (or --fleet)")
    names = _history_parameters(args)
    table = history.camera_history(lake, camera, names)
    if table.num_rows == 0:
        raise UsageError(f"camera {camera!r} has no calibration in {lake.url}")
    from fieldcal.model.camera import Sensor

    row = lake.row(table["version"][0].as_py())
    sensor = Sensor(int(row["width_px"]), int(row["height_px"]), float(row["pixel_size_um"]))
    tol = {n: parameter_tolerance(n, args.tolerance_um, sensor) for n in names
           if n in ("f_mm", "xp_mm", "yp_mm", "k0", "k1", "k2", "k3", "p1", "p2", "a1", "a2",
                    "b1", "b2")}
    fig = plots.history_plot(table, names, tolerance=tol,
                             title=f"{camera}: {table.num_rows} calibration(s); band: "
                                   f"±{args.tolerance_um:g} µm around the first")
    write_output(args.plot, plots.to_png(fig))
    print(args.plot)
    return 0
