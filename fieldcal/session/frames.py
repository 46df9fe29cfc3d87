"""A goniometer session's ``frames.csv``: its frames, their sweep axis and angle.

docs/conventions.md section 3: ``file, axis, angle_deg``; several frames may share an angle
(the paper's multi-frame statistics, METHODS.md part B, section 1.2.1). The session loader
reads it; the goniometer method (:mod:`fieldcal.goniometer`) is handed the table.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pyarrow as pa

from fieldcal.errors import InputError

__all__ = ["AXES", "read_frames_csv"]

AXES: tuple[str, ...] = ("x", "y")
"""The two sweeps: along the sensor's centre row (``x``) and centre column (``y``)."""


def read_frames_csv(path, *, strict: bool = True) -> pa.Table:
    """Read and check ``frames.csv`` (docs/conventions.md section 3).

    Parameters
    ----------
    path : path-like
    strict : bool
        True: the first bad row raises. False: bad rows are kept with a ``problem`` text
        (and :func:`fieldcal.goniometer.method.calibrate` reports and skips them).

    Returns
    -------
    pyarrow.Table
        ``file`` (string), ``axis`` (string), ``angle_deg`` (float64, NaN if unreadable),
        ``line`` (int32, line number in the file) and ``problem`` (string, null if fine).

    Raises
    ------
    InputError
        Missing or empty file, wrong header, a file listed twice; with ``strict``, a row
        whose axis is not ``x``/``y``, whose angle is not a finite number within +-90 deg,
        or whose file is empty. The message names the file, the line and the value.
    """
    where = str(path)
    p = Path(path)
    if not p.is_file():
        raise InputError("frames file not found", where)
    if p.stat().st_size == 0:
        raise InputError("empty file (0 bytes)", where)
    try:
        with open(p, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = next(reader, [])
            records = [(reader.line_num, row) for row in reader if any(c.strip() for c in row)]
    except (UnicodeDecodeError, csv.Error) as err:
        raise InputError(f"cannot parse as CSV ({err})", where) from None
    if [c.strip() for c in header] != ["file", "axis", "angle_deg"]:
        raise InputError(f"header must be 'file,axis,angle_deg', got {','.join(header)!r}", where)
    if not records:
        raise InputError("no frames listed (header only)", where)
    for line, row in records:
        if len(row) != 3:
            raise InputError(f"line {line}: expected 3 fields (file,axis,angle_deg), got {len(row)}",
                             where)
    lines = [line for line, _ in records]
    files, axes, angle_text = ([row[k].strip() for _, row in records] for k in range(3))
    angles, problems = [], []
    seen: dict[str, int] = {}
    for line, f, a, t in zip(lines, files, axes, angle_text, strict=True):
        if f in seen and f:
            raise InputError(f"line {line}: frame {f!r} is listed twice (first on line {seen[f]})",
                             where)
        seen[f] = line
        try:
            w = float(t)
        except ValueError:
            w = math.nan
        problem = None
        if not f:
            problem = "empty file name"
        elif a not in AXES:
            problem = f"axis {a!r} is not 'x' or 'y'"
        elif not (math.isfinite(w) and abs(w) < 90.0):
            problem = f"angle_deg {t!r} is not a finite angle within +-90 deg"
        if problem and strict:
            shown = f if f.isprintable() else repr(f)[1:-1]      # one line, whatever the name holds
            raise InputError(f"line {line} ({shown or 'no file'}): {problem}", where)
        angles.append(w)
        problems.append(f"frames.csv line {line}: {problem}" if problem else None)
    return pa.table({"file": pa.array(files, pa.string()), "axis": pa.array(axes, pa.string()),
                     "angle_deg": pa.array(angles, pa.float64()),
                     "line": pa.array(lines, pa.int32()),
                     "problem": pa.array(problems, pa.string())})
