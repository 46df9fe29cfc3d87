r"""The laboratory goniometer method (METHODS.md part B; Yuan et al. 2016, eq. 1-10).

A collimated point target on a turning arm is photographed at known arm angles ``W_i``
while its image sweeps the sensor's centre row (``x`` sweep) and, with the camera turned,
its centre column (``y`` sweep); several frames per angle (docs/conventions.md section 3, frames.csv).

Measurement (per frame, fan-out friendly)
-----------------------------------------
:func:`measure_frame` reads one frame and measures its spot with
:func:`fieldcal.measure.spots.measure_spot` (iterative threshold, region growing, bilinear
interpolation, squared-weight centroid). It never raises for a bad frame: the row says
``flag`` and ``reason``. :func:`calibrate` then averages the usable frames of each angle
(the paper's multi-frame statistics), with the standard error of the mean.

Principal distance and point per axis: minimum sum of squared distortion (eq. 1-7)
-----------------------------------------------------------------------------------
Along one sweep let ``L_i`` be the spot's measured coordinate [mm] along the axis (x for
the ``x`` sweep, y -- up -- for the ``y`` sweep; docs/conventions.md section 1) and ``t_i = tan W_i``.
With principal distance ``f`` and principal-point offset ``p`` along the axis, the ideal
image of the target is ``p + f tan(W_i - dW)`` (eq. 1) and its distortion

    D_i = f tan(W_i - dW) - L_i + p                                        (eq. 2)

is the contract's correction along the axis (ideal minus measured; ``D = dx`` of
:func:`fieldcal.model.camera.correction` with ``xp = p``). The paper aligns the arm's zero on
the sensor centre, so the zero ray makes the angle ``dW = atan(p/f)`` with the optical
axis, and linearises ``tan(W - dW) ~ tan W - sec^2 W dW`` (eq. 3-4):

    D_i = f t_i - p t_i^2 - L_i                                            (eq. 5)

``f, p`` minimise ``sum D_i^2``: a linear least-squares problem (eq. 6-7).

*Zero offset.* The alignment is never perfect: the zero lands at ``c`` (a fraction of a
pixel) instead of the centre, i.e. its ray is turned by ``w = -c/f`` more. Linearising
``L - p = f tan(W - dW - w)`` gives ``L_i ~ c + f t_i - p' t_i^2`` with ``p' = p - c``.
Fitted without ``c``, the constant is partly taken up by the ``t`` and ``t^2`` columns,
so ``f`` and ``p`` carry the alignment error; by default (``zero_offset=True``) eq. 6-7
therefore have the third unknown ``c``:

    D_i = f t_i - p' t_i^2 + c - L_i,      p = c + p'                      (eq. 5')

which is eq. 5 when the alignment is perfect. ``zero_offset=False`` is eq. 5 verbatim.

*Rigorous variant* (``rigorous=True``): the exact eq. 1-2 with the set-up's small
misalignments instead of the linearisation: a tilt ``tau`` of the spot's track (a line
fitted through the measured points; ``L`` is then the coordinate along that line) and an
angle offset ``W0`` of the arm (its zero need not point at the sensor centre):

    D_i = p + f tan(W_i + W0 - atan(p/f)) - L_i                            (eq. 2')

minimised over ``f, p, W0`` by non-linear least squares (SciPy, from the linear
solution). Both variants are always solved; ``stats["linearisation"]`` reports what the
linearisation changes.

The final ``f`` is that of the sweep spanning the wider angle; the other sweep's
distortions use it too, so its scale difference is carried by ``k0`` (and ``b1``), as
docs/conventions.md section 4 says.

Distortion fit (eq. 8-10)
-------------------------
With ``f`` and the principal point ``(px, py)`` fixed, each angle gives one distortion
value: ``D_i`` is ``dx`` at the measured point of the ``x`` sweep, ``dy`` of the ``y``
sweep. The contract's correction model is linear in ``k0, k1, k2, k3, p1, p2, b1, b2``
(the columns are :func:`fieldcal.model.camera.correct_jacobian`'s) and is fitted by least
squares together with one nuisance unknown per sweep, its *pointing* ``kappa``: a rotation
of the sweep by ``kappa`` moves its image points by ``f sec^2(phi_i) kappa`` (``phi_i``
the angle from the optical axis: ``W_i``, or ``W_i + W0 - atan(p/f)`` in the rigorous
variant). The min-sum step makes every sweep's ``D`` free of constant, ``tan`` and
``tan^2`` components, but the model's terms are not (``p1 (r^2 + 2 xb^2)`` has a mean; a
shifted centre of the radial terms has even parts); without the pointing, the model cannot
follow and leaves systematic residuals (``fit_pointing=False``; on the full-size Canon
scenario, noise-free, 0.11 px RMS instead of 0.005 px: bench/bench_goniometer.py). The
pointing is not a camera parameter -- where the optical axis points is not observed --
and is reported as ``stats["pointing_arcsec"]``.

``sigma_fit = sqrt(sum v_i^2 / (n - t))`` (eq. 10) over the ``n`` distortion values and
``t`` unknowns of the fit (the coefficients and the two pointings). A coefficient that the
two sweeps cannot exercise is held at 0 and named in ``stats["fixed_parameters"]``: this
is ``b2`` in practice (the shear moves ``dx`` in proportion to ``yb``, and the ``x`` sweep
stays on the principal point's row, where ``b2 yb`` is a constant that the pointing has).

Precision
---------
The whole chain (per-axis fits, choice of ``f``, distortion values, distortion fit) is a
smooth function of the ``n`` measured along-axis coordinates; its Jacobian ``J`` is taken
by central differences. With ``v`` the fit residuals and ``R = dv/dL``, the a-posteriori
accuracy of one averaged spot coordinate is ``sigma0 = sqrt(v'v / trace(R'R))`` (unbiased
for independent errors), and the covariance of everything is ``sigma0^2 J J'``.
Correlations between the sweeps (the final ``f``) and the effect of the principal point on
the distortion columns are thereby included.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
from scipy.optimize import least_squares

from fieldcal.errors import GeometryError, ImageError, InputError
from fieldcal.measure.imageio import read_image
from fieldcal.measure.spots import FLAGS, measure_spot
from fieldcal.model import camera as cam
from fieldcal.model.camera import PARAM_NAMES, Sensor

__all__ = [
    "FRAME_FLAGS", "MEASUREMENT_SCHEMA", "FIT_PARAMS", "GoniometerResult",
    "read_frames_csv", "measure_frame", "measurements_table", "measure_session",
    "min_sum_linear", "min_sum_rigorous", "calibrate", "along_axis_difference_px",
]

FRAME_FLAGS: tuple[str, ...] = FLAGS + ("unreadable",)
"""Flags of a measured frame: those of :data:`fieldcal.measure.spots.FLAGS`, and ``unreadable``
(the file is missing, corrupt, not the sensor's size, ...)."""

MEASUREMENT_SCHEMA = pa.schema([
    pa.field("file", pa.string(), nullable=False,
             metadata={"doc": "frame path relative to the session folder, as frames.csv names it"}),
    pa.field("u_px", pa.float64(), metadata={"doc": "spot centroid, column [px]; NaN if none"}),
    pa.field("v_px", pa.float64(), metadata={"doc": "spot centroid, row [px]; NaN if none"}),
    pa.field("peak_dn", pa.float64(), metadata={"doc": "brightest pixel of the spot [DN]"}),
    pa.field("background_dn", pa.float64(), metadata={"doc": "median background [DN]"}),
    pa.field("noise_dn", pa.float64(), metadata={"doc": "robust background sigma [DN]"}),
    pa.field("threshold_dn", pa.float64(), metadata={"doc": "iterative threshold [DN]"}),
    pa.field("n_pixels", pa.int32(), metadata={"doc": "pixels in the spot's region"}),
    pa.field("snr", pa.float64(), metadata={"doc": "(peak - background) / noise"}),
    pa.field("flag", pa.string(), nullable=False, metadata={"doc": "one of FRAME_FLAGS"}),
    pa.field("reason", pa.string(), nullable=False, metadata={"doc": "empty when ok"}),
], metadata={"name": "fieldcal.goniometer_measurements/1",
             "doc": "One row per goniometer frame: the spot centroid and its quality flag."})

FIT_PARAMS: tuple[str, ...] = ("k0", "k1", "k2", "k3", "p1", "p2", "b1", "b2")
"""The coefficients of the distortion fit (eq. 9), in :data:`fieldcal.model.camera.PARAM_NAMES` order."""
_FIT_IDX = np.array([cam.INDEX[n] for n in FIT_PARAMS])
_AXES = ("x", "y")


# --------------------------------------------------------------------------- frames.csv
def read_frames_csv(path, *, strict: bool = True) -> pa.Table:
    """Read and check ``frames.csv`` (docs/conventions.md section 3).

    Parameters
    ----------
    path : path-like
    strict : bool
        True: the first bad row raises. False: bad rows are kept with a ``problem`` text
        (and :func:`calibrate` reports and skips them).

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
        elif a not in _AXES:
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


# --------------------------------------------------------------------------- per axis
def min_sum_linear(angle_deg, along_mm, *, zero_offset: bool = True) -> dict:
    """Principal distance and point of one sweep by eq. 5-7 (module docstring).

    Parameters
    ----------
    angle_deg : (n,) array_like
        Encoder angles W [deg].
    along_mm : (n,) array_like
        Measured coordinates L along the swept axis [mm].
    zero_offset : bool
        Add the unknown ``c`` (where the arm's zero lands) to eq. 5.

    Returns
    -------
    dict
        ``f_mm``, ``p_mm`` (principal-point offset along the axis), ``pprime_mm``
        (coefficient of ``-tan^2 W``), ``c_mm`` (0 without ``zero_offset``) and
        ``distortion_mm`` (n,), the ``D_i`` of eq. 5 / 5'.
    """
    t = np.tan(np.radians(np.asarray(angle_deg, float)))
    L = np.asarray(along_mm, float)
    cols = [t, -t * t] + ([np.ones_like(t)] if zero_offset else [])
    A = np.column_stack(cols)
    theta = np.linalg.lstsq(A, L, rcond=None)[0]
    f, pp = theta[0], theta[1]
    c = theta[2] if zero_offset else 0.0
    return {"f_mm": float(f), "p_mm": float(c + pp), "pprime_mm": float(pp), "c_mm": float(c),
            "distortion_mm": A @ theta - L}


def _track_coordinate(along, cross):
    """Tilt [rad] of the line through the points and their coordinate along it [mm]."""
    slope = np.polyfit(along, cross, 1)[0] if along.size >= 2 else 0.0
    tau = math.atan(slope)
    return tau, along * math.cos(tau) + cross * math.sin(tau)


def _rigorous_residual(theta, W, L, zero_offset):
    f, p = theta[0], theta[1]
    w0 = theta[2] if zero_offset else 0.0
    return p + f * np.tan(W + w0 - np.arctan(p / f)) - L


def min_sum_rigorous(angle_deg, along_mm, cross_mm=None, *, zero_offset: bool = True,
                     start: dict | None = None) -> dict:
    """Principal distance and point of one sweep from the exact eq. 2' (module docstring).

    Parameters
    ----------
    angle_deg, along_mm : (n,) array_like
        As :func:`min_sum_linear`.
    cross_mm : (n,) array_like, optional
        The perpendicular coordinates [mm]; with them the track's tilt is fitted and ``L``
        is the coordinate along the tilted track.
    zero_offset : bool
        Estimate the arm's angle offset ``W0`` (else 0: eq. 1-2 verbatim).
    start : dict, optional
        A :func:`min_sum_linear` or :func:`min_sum_rigorous` result to start from.

    Returns
    -------
    dict
        ``f_mm``, ``p_mm``, ``w0_rad``, ``tilt_rad``, ``distortion_mm`` (n,) and the
        track coordinate ``track_mm`` (n,).
    """
    W = np.radians(np.asarray(angle_deg, float))
    along = np.asarray(along_mm, float)
    if cross_mm is None:
        tau, L = 0.0, along
    else:
        tau, L = _track_coordinate(along, np.asarray(cross_mm, float))
    if start is None:
        start = min_sum_linear(angle_deg, along, zero_offset=zero_offset)
    f0, p0 = start["f_mm"], start["p_mm"]
    w00 = start.get("w0_rad", start.get("c_mm", 0.0) / f0)
    x0 = np.array([f0, p0, w00] if zero_offset else [f0, p0])
    scale = np.array([abs(f0), 0.01, 1e-3] if zero_offset else [abs(f0), 0.01])
    sol = least_squares(_rigorous_residual, x0, args=(W, L, zero_offset), method="lm",
                        x_scale=scale, xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=200)
    f, p = sol.x[0], sol.x[1]
    w0 = sol.x[2] if zero_offset else 0.0
    return {"f_mm": float(f), "p_mm": float(p), "w0_rad": float(w0), "tilt_rad": float(tau),
            "distortion_mm": sol.fun.copy(),
            "track_mm": L}


# --------------------------------------------------------------------------- the chain
@dataclass
class _Sweep:
    axis: str
    angle_deg: np.ndarray      # (n,)
    along_mm: np.ndarray       # (n,) measured coordinate along the axis
    cross_mm: np.ndarray       # (n,) the perpendicular one

    @property
    def span_deg(self) -> float:
        return float(self.angle_deg.max() - self.angle_deg.min())

    def points_mm(self, along=None):
        a = self.along_mm if along is None else along
        return np.column_stack([a, self.cross_mm] if self.axis == "x" else [self.cross_mm, a])


@dataclass
class _Chain:
    """The calibration as a function of the along-axis coordinates (for its Jacobian)."""

    sweeps: dict
    rigorous: bool
    zero_offset: bool
    f_axis: str
    fit_pointing: bool = True
    fit_mask: np.ndarray = field(default_factory=lambda: np.ones(len(FIT_PARAMS), bool))

    def solve(self, along: dict, start: dict | None = None) -> dict:
        axes = {}
        for a, sw in self.sweeps.items():
            if self.rigorous:
                st = start["axes"][a] if start else None
                axes[a] = min_sum_rigorous(sw.angle_deg, along[a], sw.cross_mm,
                                           zero_offset=self.zero_offset, start=st)
            else:
                axes[a] = min_sum_linear(sw.angle_deg, along[a], zero_offset=self.zero_offset)
        f = axes[self.f_axis]["f_mm"]
        px, py = axes["x"]["p_mm"], axes["y"]["p_mm"]
        D, comp, pts, sec2 = [], [], [], []
        for a, sw in self.sweeps.items():
            W = np.radians(sw.angle_deg)
            s = axes[a]
            if self.rigorous:
                w0 = s["w0_rad"] if self.zero_offset else 0.0
                phi = W + w0 - np.arctan(s["p_mm"] / f)
                D.append(s["p_mm"] + f * np.tan(phi) - s["track_mm"])
            else:
                phi = W
                t = np.tan(W)
                D.append(f * t - s["pprime_mm"] * t * t + s["c_mm"] - along[a])
            sec2.append(1.0 / np.cos(phi) ** 2)
            comp.append(np.full(W.size, 0 if a == "x" else 1))
            pts.append(sw.points_mm(along[a]))
        D, comp, pts, sec2 = (np.concatenate(x) for x in (D, comp, pts, sec2))
        params = np.zeros(13)
        params[[cam.F, cam.XP, cam.YP]] = f, px, py
        B = _design(pts, comp, params)
        # the sweeps' pointing (nuisance): a rotation by kappa moves the image by f sec^2(phi) kappa
        K = f * sec2[:, None] * np.column_stack([comp == 0, comp == 1]) * float(self.fit_pointing)
        Bm = np.column_stack([B[:, self.fit_mask], K])
        scale = np.abs(Bm).max(axis=0)
        scale[scale == 0] = 1.0
        x = np.linalg.lstsq(Bm / scale, D, rcond=None)[0] / scale
        beta = np.zeros(len(FIT_PARAMS))
        beta[self.fit_mask] = x[:-2]
        params[_FIT_IDX] = beta
        fit = Bm @ x
        return {"axes": axes, "params": params, "D": D, "fit": fit, "v": D - fit,
                "pointing_rad": {"x": float(x[-2]), "y": float(x[-1])},
                "comp": comp, "points": pts}

    def outputs(self, sol: dict) -> np.ndarray:
        """The vector whose Jacobian is taken: f, px, py, fx, fy, fitted coefficients, v."""
        p = sol["params"]
        return np.concatenate([[p[cam.F], p[cam.XP], p[cam.YP], sol["axes"]["x"]["f_mm"],
                                sol["axes"]["y"]["f_mm"]], p[_FIT_IDX][self.fit_mask], sol["v"]])


def _design(points_mm, comp, params):
    """Columns of the distortion fit (n, 8): d(correction along comp)/d(coefficient)."""
    _, _, Q = cam.correct_jacobian(points_mm, params)
    return Q[np.arange(len(comp)), comp][:, _FIT_IDX]


def along_axis_difference_px(params_a, params_b, sensor: Sensor, uv_px, axis) -> np.ndarray:
    """How two camera models differ along the scanned axes, without the common pointing.

    For each measured point, the angle that each model assigns to it along its axis,
    ``atan(q_axis / f)`` with ``q`` the model's ideal point (:func:`fieldcal.model.camera.correct`),
    is compared; the mean difference per axis (where the optical axis points, which the
    goniometer does not observe) is removed, and the rest is expressed as an image
    displacement ``f sec^2(angle) dangle`` of model ``b`` [px].

    Parameters
    ----------
    params_a, params_b : (13,) array_like
        Two camera parameter vectors.
    sensor : Sensor
    uv_px : (n, 2) array_like
        Measured points [px].
    axis : (n,) array_like of {"x", "y"}
        The axis each point was swept along (its component is compared).

    Returns
    -------
    (n,) ndarray [px]
    """
    pa_, pb = np.asarray(params_a, float), np.asarray(params_b, float)
    xy = sensor.pixel_to_mm(np.asarray(uv_px, float))
    comp = np.where(np.asarray(axis) == "x", 0, 1)
    idx = np.arange(len(comp))
    qa, qb = cam.correct(xy, pa_)[idx, comp], cam.correct(xy, pb)[idx, comp]
    ang_a, ang_b = np.arctan(qa / pa_[cam.F]), np.arctan(qb / pb[cam.F])
    diff = ang_a - ang_b
    for c in (0, 1):
        m = comp == c
        if m.any():
            diff[m] -= diff[m].mean()
    return diff * pb[cam.F] / np.cos(ang_b) ** 2 / sensor.pixel_mm


# --------------------------------------------------------------------------- result
@dataclass
class GoniometerResult:
    """A goniometer calibration (docs/conventions.md sections 2 and 4).

    Attributes
    ----------
    sensor : Sensor
    parameters : (13,) ndarray
        In :data:`fieldcal.model.camera.PARAM_NAMES` order; ``a1 = a2 = 0``.
    sigma : dict
        Name -> a-posteriori sigma, or None for a parameter not estimated.
    covariance : (13, 13) ndarray
        Of the parameters; NaN rows and columns for those not estimated.
    stats : dict
        The contract's keys (``n_frames, n_angles, fx_mm, fy_mm, px_mm, py_mm,
        sigma_axes, sigma_fit_px``) and more; see :func:`calibrate`.
    images : list of dict
        The frames used: ``file, axis, angle_deg, u_px, v_px``.
    rejected : list of dict
        Frames left out: ``file, axis, angle_deg, flag, reason``.
    residuals : pyarrow.Table
        Per angle and axis (see :func:`calibrate`).
    """

    sensor: Sensor
    parameters: np.ndarray
    sigma: dict
    covariance: np.ndarray
    stats: dict
    images: list
    rejected: list
    residuals: pa.Table
    method: str = "goniometer"

    def camera(self) -> cam.Camera:
        return cam.Camera(self.sensor, self.parameters)

    def document_fields(self) -> dict:
        """The method's part of the calibration document (docs/conventions.md section 4): ``method,
        sensor, model, parameters, sigma, stats, images``; the caller adds ``schema,
        camera_id, session_id, version, created, inputs``."""
        return {"method": self.method, "sensor": self.sensor.to_dict(), "model": cam.MODEL,
                "parameters": cam.params_to_dict(self.parameters), "sigma": dict(self.sigma),
                "stats": self.stats, "images": list(self.images)}

    def arrays(self, grid: tuple[int, int] = (41, 31)) -> dict:
        """Named arrays for the lake: ``parameters`` (13,), ``sigma`` (13,) NaN where null,
        ``covariance`` and ``correlation`` (13, 13), ``correction_field`` (ny, nx, 2) [px]
        of the correction on a grid of ``grid = (nx, ny)`` pixel centres with ``grid_u_px``
        (nx,) and ``grid_v_px`` (ny,). Off the two scanned axes the field is the fitted
        model's extrapolation: the goniometer observes only the axes."""
        nx, ny = grid
        uv = self.sensor.grid_px(nx, ny)
        field_px = cam.correction(self.sensor.pixel_to_mm(uv), self.parameters) / self.sensor.pixel_mm
        field_px[:, 1] *= -1.0      # image-plane y up -> pixel v down
        sd = np.sqrt(np.diag(self.covariance))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = self.covariance / np.outer(sd, sd)
        return {"parameters": self.parameters.copy(),
                "sigma": np.array([np.nan if self.sigma[n] is None else self.sigma[n]
                                   for n in PARAM_NAMES]),
                "covariance": self.covariance.copy(), "correlation": corr,
                "correction_field": field_px.reshape(ny, nx, 2),
                "grid_u_px": uv[:nx, 0].copy(), "grid_v_px": uv[::nx, 1].copy()}

    def lake_residuals(self) -> pa.Table:
        """The residuals as rows of ``schemas/residuals.arrow.json`` (fieldcal.residuals/1).

        One row per angle (``image`` null: the mean of its frames) with the fit residual
        as measured minus model along the swept axis (``du_px`` for the ``x`` sweep,
        ``dv_px`` for the ``y`` sweep; the other component is NaN: the method models only
        the along-axis coordinate), ``sigma_px`` the standard error of the mean along the
        axis; then one row per rejected frame (``used`` false, ``reason`` its flag and
        reason, NaN positions).
        """
        from fieldcal.session.schemas import arrow_schema

        rows = []
        for r in self.residuals.to_pylist():
            along_px = -r["residual_px"]          # measured minus model, image-plane axis
            x_sweep = r["axis"] == "x"
            se = r["se_u_px"] if x_sweep else r["se_v_px"]
            rows.append({"image": None, "target_id": None, "u_px": r["u_px"], "v_px": r["v_px"],
                         "du_px": along_px if x_sweep else math.nan,
                         "dv_px": math.nan if x_sweep else -along_px,    # y up -> v down
                         "sigma_px": se, "used": True, "reason": None,
                         "normalized_residual": (abs(along_px) / se if se and math.isfinite(se)
                                                 and se > 0 else None),
                         "axis": r["axis"], "angle_deg": r["angle_deg"]})
        for r in self.rejected:
            rows.append({"image": r["file"], "target_id": None, "u_px": math.nan,
                         "v_px": math.nan, "du_px": math.nan, "dv_px": math.nan,
                         "sigma_px": math.nan, "used": False,
                         "reason": f"{r['flag']}: {r['reason']}", "normalized_residual": None,
                         "axis": r["axis"] if r["axis"] in _AXES else None,
                         "angle_deg": r["angle_deg"] if math.isfinite(r["angle_deg"]) else None})
        return pa.Table.from_pylist(rows, schema=arrow_schema("residuals"))

    def report_lines(self) -> list[str]:
        """A human summary, one line per item."""
        s, p, sg = self.stats, cam.params_to_dict(self.parameters), self.sigma
        um = 1000.0

        def pm(name):
            return f"{p[name]:.5f} +- {sg[name]:.5f}" if sg.get(name) is not None else f"{p[name]:.5f}"
        lines = [
            f"goniometer calibration ({s['solver']}): {s['n_angles']} angles from {s['n_frames']} "
            f"frames, {s['n_rejected']} frame(s) rejected",
            f"  f  = {pm('f_mm')} mm from the {s['f_axis']} sweep (+-{s['half_span_deg'][s['f_axis']]:.1f} deg); "
            f"fx = {s['fx_mm']:.5f}, fy = {s['fy_mm']:.5f} mm",
            f"  xp = {pm('xp_mm')} mm, yp = {pm('yp_mm')} mm",
            f"  arm zero landed {s['zero_offset_px']['x']:+.2f} px (x sweep) and "
            f"{s['zero_offset_px']['y']:+.2f} px (y sweep) from the sensor centre",
            f"  distortion before the fit: max {s['max_distortion_px']:.2f} px; after: "
            f"sigma_fit {s['sigma_fit_px']:.3f} px (n = {s['n_angles']}, t = {s['n_fitted']}), "
            f"max {s['max_px']:.3f} px",
        ]
        if s.get("sigma0") is not None:
            lines.append(f"  a-posteriori spot accuracy {s['sigma0_px']:.3f} px = {s['sigma0']:.2f} x "
                         f"the frame-to-frame standard error")
        for name, why in s["fixed_parameters"].items():
            lines.append(f"  held at 0: {name} ({why})")
        lin = s["linearisation"]
        lines.append(f"  rigorous minus linearised: df {lin['df_mm'] * um:+.2f} um, dxp "
                     f"{lin['dxp_mm'] * um:+.2f} um, dyp {lin['dyp_mm'] * um:+.2f} um; along the axes "
                     f"{lin['rms_px']:.3f} px RMS, {lin['max_px']:.3f} px max")
        lines.extend(f"  note: {n}" for n in s["notes"])
        lines.extend(f"  rejected {r['file']}: {r['flag']}: {r['reason']}" for r in self.rejected)
        return lines


# --------------------------------------------------------------------------- calibrate
RESIDUAL_SCHEMA = pa.schema([
    ("axis", pa.string()), ("angle_deg", pa.float64()), ("n_frames", pa.int32()),
    ("u_px", pa.float64()), ("v_px", pa.float64()),
    ("se_u_px", pa.float64()), ("se_v_px", pa.float64()),
    ("along_mm", pa.float64()), ("cross_mm", pa.float64()),
    ("distortion_px", pa.float64()), ("fit_px", pa.float64()), ("residual_px", pa.float64()),
])


def _table_column(t: pa.Table, name: str, default=None):
    return t.column(name).to_pylist() if name in t.column_names else [default] * t.num_rows


def _usable_frames(frames: pa.Table, measurements: pa.Table, max_spread_px: float):
    """Join frames and measurements; group the good frames by (axis, angle)."""
    for col in ("file", "axis", "angle_deg"):
        if col not in frames.column_names:
            raise InputError(f"frames table lacks the column {col!r}")
    for col in ("file", "u_px", "v_px", "flag"):
        if col not in measurements.column_names:
            raise InputError(f"measurements table lacks the column {col!r}")
    meas = {}
    for r in measurements.to_pylist():
        meas[r["file"]] = r
    rejected, groups = [], {}
    problems = _table_column(frames, "problem")
    for f, a, w, prob in zip(frames.column("file").to_pylist(), frames.column("axis").to_pylist(),
                             frames.column("angle_deg").to_pylist(), problems, strict=True):
        w = math.nan if w is None else float(w)
        base = {"file": f, "axis": a, "angle_deg": w}
        if prob or a not in _AXES or not math.isfinite(w):
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


def _observability(points_mm, comp, params, fraction):
    """Coefficients that the sweeps do not exercise: max |column| over the observations
    below ``fraction`` of its max over the box the sweeps span (both components).

    Comparing with the spanned box, not the whole sensor, keeps short sweeps from losing
    their higher-order terms (they are exercised, over a shorter range), while ``b2``,
    which moves ``dx`` in proportion to ``yb`` and is observed only on the ``x`` sweep,
    where ``yb`` stays near 0, is caught.
    """
    B = _design(points_mm, comp, params)
    lo, hi = points_mm.min(axis=0), points_mm.max(axis=0)
    gx, gy = np.meshgrid(np.linspace(lo[0], hi[0], 21), np.linspace(lo[1], hi[1], 15))
    _, _, Q = cam.correct_jacobian(np.column_stack([gx.ravel(), gy.ravel()]), params)
    reach = np.abs(Q[:, :, _FIT_IDX]).max(axis=(0, 1))
    seen = np.abs(B).max(axis=0)
    fixed = {}
    for j, name in enumerate(FIT_PARAMS):
        if seen[j] < fraction * reach[j]:
            why = ("the x sweep stays on the principal point's row, where dx = b2 yb is a constant"
                   if name == "b2" else "the sweeps hardly exercise it")
            fixed[name] = (f"not observed: its column reaches {seen[j]:.3g} on the sweeps, "
                           f"{reach[j]:.3g} over the area they span ({why})")
    return fixed


def calibrate(sensor: Sensor, frames: pa.Table, measurements: pa.Table, *,
              nominal_focal_mm: float | None = None, rigorous: bool = False,
              zero_offset: bool = True, min_angles_per_axis: int = 5,
              max_frame_spread_px: float = 2.0, observable_fraction: float = 0.05,
              fit_pointing: bool = True, jacobian_step_mm: float = 1e-6) -> GoniometerResult:
    """Calibrate a camera from a goniometer session (the module docstring's method).

    Parameters
    ----------
    sensor : Sensor
    frames : pyarrow.Table
        ``file, axis, angle_deg`` (as :func:`read_frames_csv` returns; a ``problem`` column,
        if present, marks rows to report and skip).
    measurements : pyarrow.Table
        :data:`MEASUREMENT_SCHEMA` rows (at least ``file, u_px, v_px, flag, reason``).
    nominal_focal_mm : float, optional
        For a plausibility note in ``stats["notes"]`` (more than 10% off).
    rigorous : bool
        Take f and the principal point from the exact eq. 2' rather than eq. 5'.
    zero_offset : bool
        Estimate where the arm's zero landed (eq. 5' / ``W0`` in eq. 2'); False: the
        paper's equations verbatim.
    min_angles_per_axis : int
        Fewer usable angles on a sweep is a :class:`GeometryError`.
    max_frame_spread_px : float
        With 3 or more frames at an angle, a frame this far from their median is rejected.
    observable_fraction : float
        See the module docstring (coefficients held at 0).
    fit_pointing : bool
        Fit the sweeps' pointing with the distortion (module docstring); False only to
        show what it is for.
    jacobian_step_mm : float
        Central-difference step of the precision estimate [mm].

    Returns
    -------
    GoniometerResult
        ``stats`` holds: ``n_frames, n_angles, n_rejected, rejected_by_flag, fx_mm, fy_mm,
        px_mm, py_mm, sigma_axes, sigma_fit_px`` (eq. 10), ``n_fitted``, ``sigma0_px`` (the
        a-posteriori accuracy of one averaged spot coordinate) and ``sigma0`` (its ratio to
        the RMS frame-to-frame standard error; None with single frames), ``rmse_px`` and
        ``max_px`` of the fit residuals, ``max_distortion_px`` before the fit, ``f_axis``,
        ``half_span_deg``, ``zero_offset_px`` (where the arm's zero landed, eq. 5'),
        ``pointing_arcsec`` (the sweeps' fitted pointing), ``misalignment`` (rigorous: ``w0_arcsec``,
        ``tilt_mrad`` per axis), ``linearisation`` (rigorous minus linearised: ``df_mm,
        dxp_mm, dyp_mm``, per axis ``dfx_mm`` ..., and along the axes ``rms_px, max_px``),
        ``fixed_parameters``, ``solver``, ``notes``; for the lake catalog also
        ``n_images`` (= n_frames), ``n_observations`` (= n_angles), ``sigma0``.
        ``residuals`` columns: ``axis, angle_deg, n_frames, u_px, v_px, se_u_px, se_v_px,
        along_mm, cross_mm, distortion_px`` (before the fit), ``fit_px``, ``residual_px``.

    Raises
    ------
    GeometryError
        A sweep has fewer than ``min_angles_per_axis`` usable angles, or no angle on one
        side of zero, or gives a non-positive f (angle sign or axis label wrong).
    InputError
        A table lacks a required column.
    """
    means, rejected = _usable_frames(frames, measurements, max_frame_spread_px)
    by_flag: dict[str, int] = {}
    for r in rejected:
        by_flag[r["flag"]] = by_flag.get(r["flag"], 0) + 1
    why = ", ".join(f"{n} {k}" for k, n in sorted(by_flag.items())) or "none rejected"

    sweeps = {}
    for a in _AXES:
        ms = [m for m in means if m["axis"] == a]
        W = np.array([m["angle_deg"] for m in ms])
        if len(ms) < min_angles_per_axis or not ((W > 0).any() and (W < 0).any()):
            raise GeometryError(
                f"the {a} sweep has {len(ms)} usable angle(s) "
                f"({int((W > 0).sum()) if len(ms) else 0} positive, "
                f"{int((W < 0).sum()) if len(ms) else 0} negative); need at least "
                f"{min_angles_per_axis} on both sides of zero (frames rejected: {why})")
        xy = sensor.pixel_to_mm(np.array([m["uv"] for m in ms]))
        c = 0 if a == "x" else 1
        sweeps[a] = _Sweep(a, W, xy[:, c].copy(), xy[:, 1 - c].copy())
    f_axis = max(_AXES, key=lambda a: (sweeps[a].span_deg, a == "x"))

    for a, sw in sweeps.items():
        f_a = min_sum_linear(sw.angle_deg, sw.along_mm, zero_offset=zero_offset)["f_mm"]
        if not f_a > 0:
            raise GeometryError(f"the {a} sweep gives f = {f_a:.3f} mm: the sign of angle_deg or "
                                f"the axis label in frames.csv is wrong")
    along0 = {a: sw.along_mm for a, sw in sweeps.items()}
    chains = {r: _Chain(sweeps, r, zero_offset, f_axis, fit_pointing) for r in (False, True)}
    sols = {r: chains[r].solve(along0) for r in (False, True)}
    # coefficients that the sweeps cannot determine are held at 0, the same for both variants
    sol = sols[rigorous]
    fixed = _observability(sol["points"], sol["comp"], sol["params"], observable_fraction)
    mask = np.array([n not in fixed for n in FIT_PARAMS])
    for r in (False, True):
        chains[r].fit_mask = mask
        sols[r] = chains[r].solve(along0)
    chain, sol = chains[rigorous], sols[rigorous]

    n = sum(sw.along_mm.size for sw in sweeps.values())
    n_fit = int(mask.sum()) + 2 * fit_pointing     # the coefficients and the sweeps' pointing
    n_unknown = n_fit + 2 * (3 if zero_offset else 2)
    if n < n_unknown + 2:
        raise GeometryError(f"{n} usable angles for {n_unknown} unknowns (interior orientation "
                            f"per sweep and the distortion fit); need at least {n_unknown + 2} "
                            f"(frames rejected: {why})")

    # precision: central differences of the whole chain w.r.t. the along-axis coordinates
    out0 = chain.outputs(sol)
    J = np.empty((out0.size, n))
    col = 0
    h = jacobian_step_mm
    for a in _AXES:
        for i in range(sweeps[a].along_mm.size):
            plus = {b: v.copy() for b, v in along0.items()}
            minus = {b: v.copy() for b, v in along0.items()}
            plus[a][i] += h
            minus[a][i] -= h
            J[:, col] = (chain.outputs(chain.solve(plus, sol)) - chain.outputs(chain.solve(minus, sol))) / (2 * h)
            col += 1
    v = sol["v"]
    R = J[-n:, :]
    dof_eff = float(np.sum(R * R))
    sigma0_mm = float(np.sqrt(v @ v / dof_eff)) if dof_eff > 0 else math.nan
    cov_out = sigma0_mm ** 2 * (J[:-n] @ J[:-n].T)
    # map outputs -> 13 parameters
    idx13 = [cam.F, cam.XP, cam.YP] + [cam.INDEX[nm] for nm, k in zip(FIT_PARAMS, mask, strict=True) if k]
    rows = [0, 1, 2] + list(range(5, 5 + int(mask.sum())))
    cov13 = np.full((13, 13), np.nan)
    cov13[np.ix_(idx13, idx13)] = cov_out[np.ix_(rows, rows)]
    sd = np.sqrt(np.clip(np.diag(cov_out), 0, None))
    sigma = {nm: None for nm in PARAM_NAMES}
    for k, j in zip(rows, idx13, strict=True):
        sigma[PARAM_NAMES[j]] = float(sd[k])

    d = sensor.pixel_mm
    params = sol["params"]
    dof = n - n_fit
    sigma_fit_px = float(np.sqrt(v @ v / dof) / d) if dof > 0 else math.nan
    se_along = []
    for a in _AXES:
        c = 0 if a == "x" else 1
        se_along += [m["se"][c] for m in means if m["axis"] == a]
    se_along = np.array(se_along)
    se_ok = se_along[np.isfinite(se_along)]
    se_rms = float(np.sqrt(np.mean(se_ok ** 2))) if se_ok.size else math.nan
    sigma0_px = sigma0_mm / d

    # the other variant, for what the linearisation costs
    lin, rig = sols[False], sols[True]
    uv_all = np.array([m["uv"] for a in _AXES for m in means if m["axis"] == a])
    axis_all = np.array([a for a in _AXES for m in means if m["axis"] == a])
    dl = along_axis_difference_px(rig["params"], lin["params"], sensor, uv_all, axis_all)
    linearisation = {
        "df_mm": float(rig["params"][cam.F] - lin["params"][cam.F]),
        "dxp_mm": float(rig["params"][cam.XP] - lin["params"][cam.XP]),
        "dyp_mm": float(rig["params"][cam.YP] - lin["params"][cam.YP]),
        "dfx_mm": rig["axes"]["x"]["f_mm"] - lin["axes"]["x"]["f_mm"],
        "dfy_mm": rig["axes"]["y"]["f_mm"] - lin["axes"]["y"]["f_mm"],
        "rms_px": float(np.sqrt(np.mean(dl ** 2))), "max_px": float(np.abs(dl).max()),
    }
    notes = []
    fx, fy = sol["axes"]["x"]["f_mm"], sol["axes"]["y"]["f_mm"]
    if nominal_focal_mm is not None and abs(params[cam.F] / nominal_focal_mm - 1) > 0.1:
        notes.append(f"f = {params[cam.F]:.3f} mm is more than 10% from the nominal "
                     f"{nominal_focal_mm:g} mm")

    stats = {
        "n_frames": int(sum(len(m["files"]) for m in means)),
        "n_angles": len(means),
        "n_rejected": len(rejected),
        "rejected_by_flag": by_flag,
        "fx_mm": float(fx), "fy_mm": float(fy),
        "px_mm": float(params[cam.XP]), "py_mm": float(params[cam.YP]),
        "sigma_axes": {"fx_mm": float(sd[3]), "fy_mm": float(sd[4]),
                       "px_mm": float(sd[1]), "py_mm": float(sd[2])},
        "sigma_fit_px": sigma_fit_px,
        "n_fitted": n_fit,
        "sigma0_px": float(sigma0_px),
        "sigma0": float(sigma0_px / se_rms) if np.isfinite(se_rms) and se_rms > 0 else None,
        "rmse_px": float(np.sqrt(np.mean(v ** 2)) / d),
        "max_px": float(np.abs(v).max() / d),
        "max_distortion_px": float(np.abs(sol["D"]).max() / d),
        "f_axis": f_axis,
        "half_span_deg": {a: float(np.abs(sweeps[a].angle_deg).max()) for a in _AXES},
        "zero_offset_px": {a: float(lin["axes"][a]["c_mm"] / d) for a in _AXES},
        "pointing_arcsec": {a: float(np.degrees(sol["pointing_rad"][a]) * 3600) for a in _AXES},
        "misalignment": {a: {"w0_arcsec": float(np.degrees(rig["axes"][a]["w0_rad"]) * 3600),
                             "tilt_mrad": float(1e3 * rig["axes"][a]["tilt_rad"])} for a in _AXES},
        "linearisation": linearisation,
        "fixed_parameters": fixed,
        "solver": "min-sum rigorous (eq. 2')" if rigorous else
                  ("min-sum linear (eq. 5')" if zero_offset else "min-sum linear (eq. 5)"),
        "notes": notes,
        "n_images": int(sum(len(m["files"]) for m in means)),
        "n_observations": len(means),
    }
    images, res_rows = [], []
    off = 0
    for a in _AXES:
        ms = [m for m in means if m["axis"] == a]
        sw = sweeps[a]
        for i, m in enumerate(ms):
            for f, (u, vv) in zip(m["files"], m["frames_uv"], strict=True):
                images.append({"file": f, "axis": a, "angle_deg": m["angle_deg"],
                               "u_px": float(u), "v_px": float(vv)})
            res_rows.append({"axis": a, "angle_deg": m["angle_deg"], "n_frames": len(m["files"]),
                             "u_px": float(m["uv"][0]), "v_px": float(m["uv"][1]),
                             "se_u_px": float(m["se"][0]), "se_v_px": float(m["se"][1]),
                             "along_mm": float(sw.along_mm[i]), "cross_mm": float(sw.cross_mm[i]),
                             "distortion_px": float(sol["D"][off + i] / d),
                             "fit_px": float(sol["fit"][off + i] / d),
                             "residual_px": float(v[off + i] / d)})
        off += len(ms)
    residuals = pa.Table.from_pylist(res_rows, schema=RESIDUAL_SCHEMA)
    return GoniometerResult(sensor, params.copy(), sigma, cov13, stats, images, rejected, residuals)
