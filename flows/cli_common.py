"""What every ``fieldcal`` command shares: the lake and version arguments, checks, the console.

Used by :mod:`flows.cli`, :mod:`flows.cli_products`, :mod:`flows.demo` (and any module that
registers more commands), so that they answer the same way:

- :func:`add_lake_arguments`, :func:`lake_arguments`, :func:`open_lake`: ``--lake`` /
  ``FIELDCAL_LAKE`` and ``--storage-options`` / ``FIELDCAL_STORAGE_OPTIONS``; a lake that a
  command reads must exist ("no lake at PATH").
- :func:`require_camera`, :func:`resolve_version`: a camera id or version that the lake
  does not have is an error that says what exists (the closest ids).
- :func:`check_output_file`: an output path is checked before any work starts; an existing
  file is written over only with ``--overwrite`` (:func:`add_overwrite_argument`), and then
  replaced atomically (:func:`write_output`).
- :func:`is_tty`, :func:`progress_sink`: progress on a terminal, nothing on a pipe.
- :func:`describe`: a calibration document as lines of text (``fieldcal show``).
- :func:`error_line`: the one line (and exit status) of a failed command: the command
  named once, never an internal function.

Imports are deferred, so that a command that fails on its arguments answers at once.
"""

from __future__ import annotations

import difflib
import json
import os
import re

from fieldcal.errors import FieldcalError, InputError, one_line
from fieldcal.lake import secrets

__all__ = ["UsageError", "LAKE_ENV", "OPTIONS_ENV", "EXIT_ERROR", "EXIT_USAGE", "add_lake_arguments",
           "lake_arguments", "flow_options", "open_lake", "report_skipped", "forget_opened", "require_lake",
           "known_cameras", "require_camera",
           "resolve_version", "check_output_file", "add_overwrite_argument", "write_output", "check_input_file",
           "is_tty", "progress_sink", "describe", "error_line", "shown_columns", "check_lake_target"]

LAKE_ENV = "FIELDCAL_LAKE"
OPTIONS_ENV = secrets.OPTIONS_ENV
EXIT_ERROR = 1
EXIT_USAGE = 2
_CONTEXT_WORD = re.compile(r"[a-z_]+")


class UsageError(InputError):
    """A command-line argument that is missing, malformed or names nothing (exit status 2)."""


# --------------------------------------------------------------------------------------
# the lake
# --------------------------------------------------------------------------------------
def add_lake_arguments(p) -> None:
    """``--lake`` and ``--storage-options`` of a sub-command's parser."""
    p.add_argument("--lake", default=None, help=f"the lake: a local path or an fsspec URL (default: ${LAKE_ENV})")
    p.add_argument("--storage-options", metavar="JSON", default=None,
                   help=f"fsspec options of the lake as a JSON object (default: ${OPTIONS_ENV})")


def lake_arguments(args) -> tuple[str, dict | None]:
    """``(lake URL or path, storage options)`` from the arguments or the environment."""
    lake = getattr(args, "lake", None) or os.environ.get(LAKE_ENV)
    if not lake:
        raise UsageError(f"no lake: give --lake LAKE or set {LAKE_ENV}")
    text = getattr(args, "storage_options", None) or os.environ.get(OPTIONS_ENV)
    options = None
    if text:
        try:
            options = json.loads(text)
        except json.JSONDecodeError as e:
            raise UsageError(f"--storage-options is not JSON: {e.msg}") from None
        if not isinstance(options, dict):
            raise UsageError("--storage-options must be a JSON object")
    return lake, options


def flow_options(options: dict | None) -> dict | None:
    """The lake's storage options as a Prefect flow may record them: secrets redacted.

    Their values go into this process's ``FIELDCAL_STORAGE_OPTIONS`` (seen by the flow run in
    this process, its Dask worker threads and the worker processes it starts), where the
    lake, opened there, finds them (:mod:`fieldcal.lake.secrets`); a worker elsewhere needs
    them in its own environment or the storage's own configuration (``AWS_*``)."""
    return secrets.for_flow(options)


LAKE_DATA = ("catalog", "residuals", "observations_field", "observations_goniometer", "comparisons", "assessments",
             "rigs", "calibrations")
"""Entries at a lake's root that only a lake has (its Delta tables, the versions' folders)."""
LAKE_NAMES = LAKE_DATA + ("README.md", "reports", "sessions")
"""Every entry a lake's root may hold (``sessions``: the fleet's default root in it)."""


def _lake_entries(lake) -> list[str] | None:
    """The names at the lake's root; None when there is nothing there (a new lake)."""
    root = lake.uri("")
    if lake.is_local:
        if not os.path.lexists(root):
            return None
        if not os.path.isdir(root):
            raise UsageError(f"no lake at {root}: it is a file (a lake is a folder or an fsspec URL)")
        try:
            return os.listdir(root)
        except OSError as e:
            raise UsageError(f"cannot read the lake at {root}: {e.strerror}") from None
    import posixpath

    try:
        lake.fs.invalidate_cache(root)
        if not lake.fs.exists(root):
            return None
        if lake.fs.isfile(root):
            raise UsageError(f"no lake at {root}: it is a file (a lake is a folder or an fsspec URL)")
        return [posixpath.basename(x.rstrip("/")) for x in lake.fs.ls(root, detail=False)]
    except OSError as e:
        raise UsageError(f"cannot reach the lake at {root}: {one_line(e)}") from None


def _refuse_other_folder(lake, names: list[str]) -> None:
    """A folder with entries, none of them a lake's data, and some no lake has, is not a lake (``/``)."""
    visible = sorted(n for n in names if not n.startswith("."))
    if any(n in LAKE_DATA for n in visible) or all(n in LAKE_NAMES for n in visible):
        return
    shown = ", ".join(n if len(n) <= 32 else n[:29] + "..." for n in visible[:3])
    shown += ", ..." if len(visible) > 3 else ""
    raise UsageError(f"{lake.uri('')} is a folder that is not a lake (it holds {shown}; a lake has "
                     f"{', '.join(LAKE_DATA[:2])}, ...): give a lake, an empty folder or a new path")


def check_lake_target(lake) -> None:
    """Refuse a lake to write into that is a file, or a folder that is not a lake, before any
    work: a new path, an empty folder and a lake are accepted (``run``, ``fleet``, ``serve``)."""
    names = _lake_entries(lake)
    if names is not None:
        _refuse_other_folder(lake, names)


def require_lake(lake) -> None:
    """Raise :class:`UsageError` when there is no lake: nothing at its path ("no lake at PATH"),
    a file, or a folder that is not a lake (:func:`check_lake_target`)."""
    names = _lake_entries(lake)
    if names is None:
        raise UsageError(f"no lake at {lake.uri('')}")
    _refuse_other_folder(lake, names)


_OPENED: list = []
_REPORTED: set = set()


def open_lake(args, *, must_exist: bool = True):
    """The :class:`fieldcal.lake.store.Lake` of the arguments; by default it must exist.

    The lake is remembered: :func:`report_skipped` names what its readers skipped."""
    from fieldcal.lake.store import Lake

    url, options = lake_arguments(args)
    lake = Lake(url, options)
    if must_exist:
        require_lake(lake)
    _OPENED.append(lake)
    return lake


def forget_opened() -> None:
    """Forget the lakes :func:`open_lake` opened and what was reported (a command ended)."""
    _OPENED.clear()
    _REPORTED.clear()


def report_skipped(name: str, lakes=None, stream=None) -> None:
    """One line per damaged object the readers of a command skipped, once each (issue 24,
    goal 3: ``show``, ``history --fleet``, ``export``... say what they left out; the command
    still succeeds). ``lakes``: these (default: every lake :func:`open_lake` opened)."""
    import sys

    stream = stream or sys.stderr
    for lake in (_OPENED if lakes is None else lakes):
        for p in getattr(lake, "problems", []):
            text = str(p)
            if text not in _REPORTED:
                _REPORTED.add(text)
                print(f"{name}: skipped {text} (see `fieldcal lake check`)", file=stream)
    if lakes is None:
        _OPENED.clear()


def _closest(name: str, candidates, what: str) -> str:
    candidates = sorted(set(candidates))
    if not candidates:
        return f"there is no {what} in it"
    near = difflib.get_close_matches(name, candidates, n=3, cutoff=0.5)
    if near:
        return "closest: " + ", ".join(near)
    shown = ", ".join(candidates[:5]) + (", ..." if len(candidates) > 5 else "")
    return f"{len(candidates)} {what}(s): {shown}"


def known_cameras(lake) -> list[str]:
    """Camera ids with at least one committed version, sorted."""
    return sorted(set(lake.catalog()["camera_id"].to_pylist()))


def require_camera(lake, camera: str) -> None:
    """Raise :class:`UsageError` naming the closest known ids when ``camera`` has no version.

    The camera's own rows are looked up first (a filtered read: damaged files that hold
    other cameras' rows are not opened); the whole catalog only when there are none."""
    if lake.catalog(equal={"camera_id": camera}).num_rows:
        return
    cameras = known_cameras(lake)
    if camera not in cameras:
        raise UsageError(f"camera {camera!r} has no calibration in {lake.url}; "
                         + _closest(camera, cameras, "camera"))


def resolve_version(lake, name: str, camera: str | None = None, session: str | None = None) -> str:
    """A committed version id from ``name``: an id, ``latest`` or ``previous`` (with ``camera``).

    ``latest``: the camera's (or the camera's session's) latest version, ``previous``: the
    calibration before it, both by the one rule of :mod:`fieldcal.lake.order` (acquisition
    time, ties by commit order; what ``history --fleet`` and the certificate use). Raises
    :class:`UsageError` saying what exists when there is no such version.
    """
    if name not in ("latest", "previous"):
        versions = lake.catalog()["version"].to_pylist()
        if name not in versions:
            raise UsageError(f"no version {name!r} in {lake.url}; " + _closest(name, versions, "version"))
        return name
    if not camera:
        raise UsageError(f"{name!r} needs --camera ID")
    require_camera(lake, camera)
    from fieldcal.lake import order

    if name == "latest":
        v = lake.latest(camera, session)
        if v is None:
            raise UsageError(f"camera {camera!r} has no calibration of session {session!r} in {lake.url}")
        return v
    rows = lake.camera_rows(camera)
    v = order.previous(rows, order.latest(rows))
    if v is None:
        raise UsageError(f"camera {camera!r} has no calibration before its latest in {lake.url}")
    return v


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def check_output_file(path, what: str = "output", *, overwrite: bool = False) -> None:
    """Refuse an output path that cannot be written, before any work starts.

    Its folder must exist and be writable, and the path must not be a folder. An existing
    file (or link) is written over only with ``overwrite`` (``--overwrite``), and then
    replaced by :func:`write_output`, never written into (its hard links keep their bytes).
    """
    p = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(p)
    if os.path.isdir(p):
        raise UsageError(f"{what} {path}: is a folder")
    if not os.path.isdir(folder):
        raise UsageError(f"{what} {path}: no folder {folder}")
    if os.path.lexists(p) and not overwrite:
        raise UsageError(f"{what} {path}: exists; fieldcal does not write over a file (--overwrite replaces it)")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {path}: not writable")


def add_overwrite_argument(p) -> None:
    """``--overwrite`` of a command that writes files."""
    p.add_argument("--overwrite", action="store_true",
                   help="replace output files that exist (default: refuse, exit 2)")


def write_output(path, data: bytes | str) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in its folder renamed over it.

    An existing ``path`` is replaced, not written into: another hard link to it (a
    photograph's) keeps its bytes, and a failure leaves it as it was."""
    import tempfile

    p = os.path.abspath(os.fspath(path))
    raw = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(p)}.", suffix=".tmp", dir=os.path.dirname(p))
        with os.fdopen(fd, "wb") as f:
            f.write(raw)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, p)
    except OSError as e:                      # a full device, a quota: name the output, not the temporary
        raise OSError(e.errno, e.strerror or str(e), os.fspath(path)) from None
    finally:
        if tmp is not None and os.path.lexists(tmp):
            os.unlink(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def check_input_file(path, what: str = "input") -> None:
    """Refuse an input path that is not a readable file."""
    if not os.path.isfile(path):
        raise UsageError(f"{what} {path}: " + ("not a file" if os.path.exists(path) else "no such file"))


# --------------------------------------------------------------------------------------
# the console
# --------------------------------------------------------------------------------------
def is_tty(stream) -> bool:
    """Whether ``stream`` is a terminal (progress is shown only there)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_sink(stream):
    """A :class:`fieldcal.progress.TerminalProgress` on ``stream`` when it is a terminal, else None."""
    from fieldcal.progress import TerminalProgress

    return TerminalProgress(stream) if is_tty(stream) else None


def describe(doc: dict) -> list[str]:
    """Human-readable lines of a calibration document (``fieldcal show``)."""
    from fieldcal.model.camera import PARAM_NAMES

    st = doc.get("stats") or {}
    lines = [f"version   {doc.get('version')}",
             f"camera    {doc.get('camera_id')}   session {doc.get('session_id')}   method {doc.get('method')}",
             f"created   {doc.get('created')}   acquired {doc.get('acquired', '-')}",
             f"sensor    {doc['sensor']['width_px']} x {doc['sensor']['height_px']} px, "
             f"{doc['sensor']['pixel_size_um']} µm   model {doc.get('model')}",
             "", f"{'parameter':10s} {'value':>16s} {'sigma':>12s}"]
    fixed = st.get("fixed_parameters") or {}
    for n in PARAM_NAMES:
        s = doc["sigma"].get(n)
        why = f"  fixed ({fixed[n]})" if n in fixed else ("" if s is not None else "  fixed")
        lines.append(f"{n:10s} {doc['parameters'][n]:16.9g} {'' if s is None else format(s, '12.3g'):>12s}{why}")
    k0, f = float(doc["parameters"].get("k0") or 0.0), float(doc["parameters"]["f_mm"])
    if k0:
        lines.append(f"effective focal length f / (1 + k0) = {f / (1 + k0):.6g} mm: k0 {k0:+.4g} is a "
                     f"{100 * abs(k0):.2f} % scale, so f alone is right only with this model "
                     "(fieldcal certificate: which focal length to use)")
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


def shown_columns(table, view: str, args, params=("f_mm", "xp_mm", "yp_mm")):
    """The columns ``history`` prints: ``--columns``, every one with ``--wide`` or in CSV and
    JSON (scripts), else the default set of ``view`` (:data:`fieldcal.lake.history.DEFAULT_COLUMNS`)."""
    from fieldcal.lake import history

    columns = [c for c in (getattr(args, "columns", None) or "").replace(",", " ").split() if c]
    wide = getattr(args, "wide", False) or (not columns and getattr(args, "format", "text") != "text")
    return history.pick_columns(table, view, columns, wide=wide, params=params)


def error_line(command: str, error: BaseException, *, verbose: bool = False) -> tuple[str, int]:
    """``(one line, exit status)`` of a command that failed with ``error``.

    The line starts with ``fieldcal COMMAND:`` once; the error's own context is kept when it
    names a file or a place (``targets.csv:4``), and dropped when it is only a word of the
    code (the name of the function that raised it, or ``fieldcal`` again). Exit status 2 for
    bad input or usage, 1 otherwise.
    """
    name = f"fieldcal {command}".strip()
    if isinstance(error, FieldcalError):
        where = getattr(error, "where", None)
        if where is not None and (_CONTEXT_WORD.fullmatch(where) or where.startswith("fieldcal")):
            text = one_line(getattr(error, "reason", error))
        else:
            text = one_line(error)
    elif isinstance(error, OSError) and error.strerror:
        text = f"{error.filename}: {error.strerror}" if error.filename else error.strerror
    else:
        text = f"{type(error).__name__}: {one_line(error)}" + ("" if verbose else " (--verbose for details)")
    for prefix in (f"{name}: ", "fieldcal: "):
        while text.startswith(prefix):
            text = text[len(prefix):]
    return f"{name}: {text}", EXIT_USAGE if isinstance(error, InputError) else EXIT_ERROR
