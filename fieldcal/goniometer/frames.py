"""Goniometer frames: ``frames.csv``, the spot of each frame, and the mean per angle.

A goniometer session lists its frames in ``frames.csv`` (docs/conventions.md section 3: ``file,
axis, angle_deg``; read and checked by :func:`fieldcal.session.frames.read_frames_csv`);
several frames share an angle (the paper's multi-frame statistics, METHODS.md part B,
section 1.2.1). :func:`measure_frame` measures the spot of one frame with
:func:`fieldcal.measure.spots.measure_spot` (iterative threshold, region growing,
bilinear interpolation, squared-weight centroid) and never raises for a bad frame: the
row says ``flag`` and ``reason``; :func:`average_frames` joins the two tables and averages
the usable frames of each angle, with the standard error of the mean, rejecting a frame
far from the others at its angle.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow as pa

from fieldcal.contract.goniometer_schema import MEASUREMENT_SCHEMA
from fieldcal.errors import ImageError, InputError
from fieldcal.measure.imageio import read_image
from fieldcal.measure.spots import FLAGS, measure_spot
from fieldcal.model.camera import Sensor
from fieldcal.session.frames import AXES

__all__ = ["AXES", "FRAME_FLAGS", "MEASUREMENT_SCHEMA", "measure_frame",
           "measurements_table", "measure_session", "average_frames"]

FRAME_FLAGS: tuple[str, ...] = FLAGS + ("unreadable",)
"""Flags of a measured frame: those of :data:`fieldcal.measure.spots.FLAGS`, and ``unreadable``
(the file is missing, corrupt, not the sensor's size, ...)."""

# --------------------------------------------------------------------------- measuring
def measure_frame(path, sensor: Sensor | None = None, *, name: str | None = None,
                  **spot_options) -> dict:
    """Measure the spot of one frame: one row of :data:`MEASUREMENT_SCHEMA`.

    Parameters
    ----------
    path : path-like
        The TIFF file.
    sensor : Sensor, optional
        The session's sensor; a frame of another size is ``unreadable``.
    name : str, optional
        The frame's name in frames.csv (default ``str(path)``).
    **spot_options
        Passed to :func:`fieldcal.measure.spots.measure_spot`.

    Returns
    -------
    dict
        Never raises for a bad frame: a missing, corrupt or wrong-size file gives
        ``flag="unreadable"`` with the reason; a bad spot its flag (:data:`FRAME_FLAGS`).
    """
    row = {"file": name if name is not None else str(path)}
    try:
        img = read_image(path, expect_size=(sensor.width_px, sensor.height_px) if sensor else None)
    except ImageError as err:
        return {**row, "u_px": math.nan, "v_px": math.nan, "peak_dn": math.nan,
                "background_dn": math.nan, "noise_dn": math.nan, "threshold_dn": math.nan,
                "n_pixels": 0, "snr": math.nan, "flag": "unreadable", "reason": err.reason}
    spot = measure_spot(img, **spot_options)
    d = spot.to_dict()
    return {**row, **{k: d[k] for k in ("u_px", "v_px", "peak_dn", "background_dn", "noise_dn",
                                         "threshold_dn", "n_pixels", "snr", "flag", "reason")}}


def measurements_table(rows) -> pa.Table:
    """Rows of :func:`measure_frame` (any iterable of dicts) as a :data:`MEASUREMENT_SCHEMA` table.

    Missing optional columns are filled with NaN / 0.
    """
    rows = list(rows)
    cols = {}
    for f in MEASUREMENT_SCHEMA:
        default = "" if f.name == "reason" else 0 if f.name == "n_pixels" else math.nan
        cols[f.name] = pa.array([r.get(f.name, default) for r in rows], f.type)
    return pa.table(cols, schema=MEASUREMENT_SCHEMA)


def measure_session(folder, frames: pa.Table, sensor: Sensor, **spot_options) -> pa.Table:
    """Measure every frame of ``frames`` (serially) in the session ``folder``.

    The flow fans :func:`measure_frame` out instead; this is for notebooks and tests.
    """
    folder = Path(folder)
    return measurements_table(measure_frame(folder / f, sensor, name=f, **spot_options)
                              for f in frames.column("file").to_pylist())


# --------------------------------------------------------------------------- per angle
def _table_column(t: pa.Table, name: str, default=None):
    return t.column(name).to_pylist() if name in t.column_names else [default] * t.num_rows


def _check_columns(frames: pa.Table, measurements: pa.Table) -> None:
    for col in ("file", "axis", "angle_deg"):
        if col not in frames.column_names:
            raise InputError(f"frames table lacks the column {col!r}")
    for col in ("file", "u_px", "v_px", "flag"):
        if col not in measurements.column_names:
            raise InputError(f"measurements table lacks the column {col!r}")


def _join(frames: pa.Table, measurements: pa.Table):
    """The usable frames grouped by ``(axis, angle)`` and the rows left out, with why."""
    meas = {r["file"]: r for r in measurements.to_pylist()}
    rejected, groups = [], {}
    problems = _table_column(frames, "problem")
    for f, a, w, prob in zip(frames.column("file").to_pylist(), frames.column("axis").to_pylist(),
                             frames.column("angle_deg").to_pylist(), problems, strict=True):
        w = math.nan if w is None else float(w)
        base = {"file": f, "axis": a, "angle_deg": w}
        if prob or a not in AXES or not math.isfinite(w):
            rejected.append({**base, "flag": "bad_row",
                             "reason": prob or f"axis {a!r} / angle {w} not usable"})
            continue
        m = meas.get(f)
        if m is None:
            rejected.append({**base, "flag": "unmeasured", "reason": "no measurement for this frame"})
            continue
        u, v = m["u_px"], m["v_px"]
        if m["flag"] != "ok" or u is None or v is None or not (math.isfinite(u) and math.isfinite(v)):
            flag = m["flag"] if m["flag"] != "ok" else "missing"
            rejected.append({**base, "flag": flag, "reason": m.get("reason") or "no position"})
            continue
        groups.setdefault((a, w), []).append((f, u, v))
    return groups, rejected


def average_frames(frames: pa.Table, measurements: pa.Table, max_spread_px: float = 2.0):
    """Join frames and measurements and average the good frames of each (axis, angle).

    Parameters
    ----------
    frames : pyarrow.Table
        ``file, axis, angle_deg`` (:func:`read_frames_csv`; a ``problem`` column, if present,
        marks rows to report and skip).
    measurements : pyarrow.Table
        :data:`MEASUREMENT_SCHEMA` rows (at least ``file, u_px, v_px, flag, reason``).
    max_spread_px : float
        With 3 or more frames at an angle, a frame this far from their median [px] is
        rejected as ``inconsistent``.

    Returns
    -------
    means : list of dict
        Per (axis, angle), sorted: ``axis, angle_deg, files`` (the frames averaged),
        ``uv`` (2,) the mean position [px], ``se`` (2,) its standard error [px] (NaN with a
        single frame) and ``frames_uv`` (k, 2).
    rejected : list of dict
        Frames left out: ``file, axis, angle_deg, flag, reason``.

    Raises
    ------
    InputError
        A table lacks a required column.
    """
    _check_columns(frames, measurements)
    groups, rejected = _join(frames, measurements)
    means = []
    for (a, w), items in sorted(groups.items()):
        uv = np.array([(u, v) for _, u, v in items])
        if len(items) >= 3:
            med = np.median(uv, axis=0)
            dist = np.hypot(*(uv - med).T)
            keep = dist <= max_spread_px
            for (f, _, _), d, k in zip(items, dist, keep, strict=True):
                if not k:
                    rejected.append({"file": f, "axis": a, "angle_deg": w, "flag": "inconsistent",
                                     "reason": f"{d:.2f} px from the median of the frames at this "
                                               f"angle (limit {max_spread_px:g} px)"})
            items = [it for it, k in zip(items, keep, strict=True) if k]
            uv = uv[keep]
        n = len(items)
        se = uv.std(axis=0, ddof=1) / np.sqrt(n) if n >= 2 else np.full(2, np.nan)
        means.append({"axis": a, "angle_deg": w, "files": [it[0] for it in items],
                      "uv": uv.mean(axis=0), "se": se, "frames_uv": uv})
    return means, rejected
