"""The field bundle adjustment against its peers, on the paper-sized problem.

One run builds the paper-sized problem once (:func:`fieldcal.synthetic.field.paper_field`: 72
images, ~1900 targets, ~14 000 image points, 0.1 px image noise, 5 mm survey noise), makes
one perturbed start (f +0.5 %, principal point +0.05 mm in x and y, every distortion
coefficient 0, rotations perturbed by N(0, 0.5 mrad) per axis and centres by N(0, 5 cm)
per axis) and solves it to convergence with each of (timed interleaved, round robin, best
and median of N rounds):

- fieldcal: :func:`fieldcal.solver.lsq.solve` (LMQN and LM, with :class:`AdjustmentOptions`'s
  default ``tau``, ``eps2``, ``ftol`` and ``sigma_tol``) on :class:`FieldProblem`, targets fixed and targets
  adjusted (weighted by their survey sigma); the time includes building the
  :class:`BundleModel` and the problem from the arrays;
- ``cv2.calibrateCamera`` with ``CALIB_USE_INTRINSIC_GUESS`` (per-view object points are
  the surveyed targets that view sees; OpenCV's own k1, k2, p1, p2, k3 model; it computes
  its own initial poses from the intrinsic guess, see below);
- pycolmap's Ceres bundle adjustment with every 3-D point constant (camera model
  ``OPENCV``: fx, fy, cx, cy, k1, k2, p1, p2; ``FULL_OPENCV`` is run once for the record),
  principal point refined, one thread; the time is building the adjuster plus the solve,
  not filling the ``Reconstruction`` from Python;
- ``scipy.optimize.least_squares`` ('trf', ``tr_solver='lsmr'``, tolerances 1e-12, lsmr
  ``atol = btol = 1e-12``) with finite differences on the sparsity pattern
  (``jac_sparsity``), and with fieldcal's analytic Jacobian (``BlockSparseJacobian.to_csr``).
  Both run in fieldcal's scaled variables ``z = D x`` (D: column norms of J(x0), computed
  once outside the timer) with ``x_scale='jac'``: finite differences in the raw variables
  take steps of ``sqrt(eps) max(1, |x|)``, i.e. 1.5e-8 mm^-6 for k3 = 0 (several mm of
  image motion), and stop early; one such run is recorded too.

and, separately, :func:`fieldcal.field.adjustment.adjust_field`: the whole procedure from the
observations alone (initial values, blunder rounds, parameter selection), which is not
what the peers do.

A second, cheaper section repeats the fixed-target case on the same geometry with a
precise survey (0.01 mm), where the final RMS shows how well each solver's camera model
fits data made with fieldcal's model (with 5 mm survey noise every solver's RMS is ~3.1 px,
dominated by the survey). The "model floor" is the RMS misfit of the peer's model fitted
directly to the true camera on a 41 x 31 grid over the whole sensor.

Run (single-threaded BLAS and OpenMP; set before NumPy is imported below as well)::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python bench/bench_solver.py
    .venv/bin/python bench/bench_solver.py --repeat 3 --quick      # ~20 s, no slow SciPy rows
    .venv/bin/python bench/bench_solver.py --profile                # where fieldcal's time goes

It prints markdown tables; ``bench/README_solver.md`` holds a recorded run.

Notes on the peers
------------------
- OpenCV 5's Python ``calibrateCamera`` ignores initial ``rvecs``/``tvecs`` even with
  ``CALIB_USE_EXTRINSIC_GUESS`` (rotations perturbed by 0.05 rad give the same result to
  15 digits), so it starts from its own per-view pose estimate with the intrinsic guess;
  that is inside its time (the ``maxCount=1`` row shows how much).
  It does not report iterations: they are found once, outside the timing, as the smallest
  ``maxCount`` that reproduces the converged result. Criteria: ``COUNT + EPS``, 100,
  ``eps = 1e-10`` (OpenCV's test is a relative step, like fieldcal's ``eps2``).
- Ceres stops on ``function_tolerance = 1e-12``, ``gradient_tolerance = 1e-12``,
  ``parameter_tolerance = 1e-10`` (COLMAP's own defaults stop a few iterations early here,
  ~0.4 px from the optimum in the principal point).
- COLMAP's pixel convention puts the centre of the top-left pixel at (0.5, 0.5); fieldcal's
  and OpenCV's at (0, 0) (CONTRACT section 1): the observations given to pycolmap are
  shifted by +0.5 px and its principal point shifted back.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import datetime  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import pycolmap  # noqa: E402
import scipy  # noqa: E402
import scipy.optimize  # noqa: E402
import scipy.sparse  # noqa: E402

from fieldcal.field.adjustment import AdjustmentOptions, FieldProblem, adjust_field  # noqa: E402
from fieldcal.field.bundle import BundleModel  # noqa: E402
from fieldcal.model.camera import FIELD_PARAMS, INDEX, Camera  # noqa: E402
from fieldcal.model.rotations import R_from_rotvec  # noqa: E402
from fieldcal.solver import (
    blocksparse,  # noqa: E402
    lsq,
)
from fieldcal.synthetic.field import SyntheticField, paper_field  # noqa: E402

# OpenCV's camera frame is x right, y down, z forward; fieldcal's x right, y up, z backwards
# (CONTRACT section 1): R_cv = FLIP @ R_world_to_camera.
FLIP = np.diag([1.0, -1.0, -1.0])
SCIPY_TOL = 1e-12
LSMR_TOL = 1e-12
CV_EPS = 1e-10
CERES_TOL = {"function_tolerance": 1e-12, "gradient_tolerance": 1e-12, "parameter_tolerance": 1e-10}


# ------------------------------------------------------------------------------------------
# the problem and the start
# ------------------------------------------------------------------------------------------
@dataclass
class Start:
    """The perturbed start shared by every solver.

    Attributes
    ----------
    params : (13,) ndarray
        Camera parameters (fieldcal-brown/1): f +0.5 %, principal point +0.05 mm, the
        distortion coefficients 0.
    R_world_to_camera : (n_images, 3, 3) ndarray
    center_m : (n_images, 3) ndarray [m]
    """

    params: np.ndarray
    R_world_to_camera: np.ndarray
    center_m: np.ndarray


def perturbed_start(sf: SyntheticField, seed: int = 1, rot_mrad: float = 0.5,
                    center_m: float = 0.05) -> Start:
    """The common start: f +0.5 %, xp and yp +0.05 mm, distortion 0, poses perturbed.

    Parameters
    ----------
    sf : SyntheticField
    seed : int
        Seeds the pose perturbation.
    rot_mrad : float
        Standard deviation of each rotation-vector component of the perturbation [mrad].
    center_m : float
        Standard deviation of each centre coordinate's perturbation [m].
    """
    rng = np.random.default_rng(seed)
    p = sf.camera.params.copy()
    p[INDEX["f_mm"]] *= 1.005
    p[INDEX["xp_mm"]] += 0.05
    p[INDEX["yp_mm"]] += 0.05
    p[[INDEX[n] for n in FIELD_PARAMS[3:]]] = 0.0
    n = len(sf.center_m)
    R = R_from_rotvec(rng.normal(0.0, rot_mrad * 1e-3, (n, 3))) @ sf.R_world_to_camera
    C = sf.center_m + rng.normal(0.0, center_m, (n, 3))
    return Start(p, R, C)


@dataclass
class Row:
    """One solver's result: what the tables print."""

    solver: str
    case: str
    model: str
    times_s: list[float]
    iterations: str
    evaluations: str
    rmse_px: float
    f_mm: float
    xp_mm: float
    yp_mm: float
    status: str
    extra: dict = field(default_factory=dict)

    @property
    def time_s(self) -> float:
        return min(self.times_s)


@dataclass
class Case:
    """One solver on one problem: ``solve(prepare())`` is timed, ``report`` makes the Row.

    ``prepare`` (untimed, optional) makes a fresh input for solvers that work in place.
    """

    solve: Callable[[object], object]
    report: Callable[[object, list[float]], Row]
    prepare: Callable[[], object] | None = None
    times: list[float] = field(default_factory=list)
    result: object = None


def measure(cases: list[Case], repeat: int) -> list[Row]:
    """Time every case ``repeat`` times, interleaved (round robin), and report each.

    Interleaving makes the load of a shared machine fall on every solver alike; the tables
    give the best (and median) of the repetitions.
    """
    for _ in range(max(1, repeat)):
        for c in cases:
            arg = c.prepare() if c.prepare is not None else None
            t0 = time.perf_counter()
            c.result = c.solve(arg)
            c.times.append(time.perf_counter() - t0)
    return [c.report(c.result, c.times) for c in cases]


def rmse_2d(du_dv) -> float:
    """``sqrt(mean(du^2 + dv^2))`` [px] of residuals (k, 2) (CONTRACT section 4)."""
    d = np.asarray(du_dv, float)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


# ------------------------------------------------------------------------------------------
# fieldcal
# ------------------------------------------------------------------------------------------
def fieldcal_problem(sf: SyntheticField, start: Start, adjusted: bool):
    """``(FieldProblem, x0)`` for the start (all of FIELD_PARAMS estimated)."""
    model = BundleModel(sf.data, start.params, FIELD_PARAMS, start.R_world_to_camera,
                        targets_adjusted=adjusted)
    x0 = model.pack(start.params, start.center_m, sf.data.targets.xyz_m)
    return FieldProblem(model), x0


def image_rmse(model: BundleModel, r) -> float:
    """Image-space RMS [px] from weighted residuals ``r`` of the model."""
    ri = np.asarray(r)[: model.n_rows_image].reshape(-1, 2) * model.sigma_px[:, None]
    return rmse_2d(ri)


def case_fieldcal(sf, start, adjusted, method) -> Case:
    """fieldcal's engine on FieldProblem (model set-up included in the time)."""
    o = AdjustmentOptions()

    def go(_):
        problem, x0 = fieldcal_problem(sf, start, adjusted)
        return problem, lsq.solve(problem, x0, method=method, tau=o.tau, eps2=o.eps2,
                                  ftol=o.ftol, sigma_tol=o.sigma_tol, max_iter=o.max_iter)

    return Case(go, lambda out, times: _report_fieldcal(out, times, adjusted, method))


def _report_fieldcal(out, times, adjusted, method) -> Row:
    problem, res = out
    p = problem.model.unpack(res.x)[0]
    it = f"{res.iterations}" + (f" ({res.qn_iterations} QN)" if method == "lmqn" else "")
    return Row(f"fieldcal {method.upper()}", _case(adjusted), "fieldcal-brown/1 (10)", times, it,
               str(res.evaluations), image_rmse(problem.model, res.r), p[0], p[1], p[2],
               "converged" if res.success else res.message)


def case_adjust_field(sf, adjusted) -> Case:
    """The whole field procedure from the observations alone (not what the peers do)."""
    opts = AdjustmentOptions(targets_adjusted=adjusted)
    return Case(lambda _: adjust_field(sf.data, opts),
                lambda res, times: _report_adjust_field(res, times, adjusted))


def _report_adjust_field(res, times, adjusted) -> Row:
    st = res.stats()
    fixed = ", ".join(sorted(res.fixed_parameters))
    return Row("fieldcal adjust_field (whole procedure)", _case(adjusted),
               f"fieldcal-brown/1 ({len(res.estimate)})", times,
               f"{st['iterations']} last / {res.iterations_total} total",
               f"{len(res.rounds)} solves", st["rmse_px"], res.params[0], res.params[1],
               res.params[2], f"{st['n_rejected']} rejected; fixed {fixed or 'none'}")


def _case(adjusted: bool) -> str:
    return "adjusted" if adjusted else "fixed"


# ------------------------------------------------------------------------------------------
# OpenCV
# ------------------------------------------------------------------------------------------
@dataclass
class PeerInput:
    """Per-view object points / image points and the start in OpenCV's conventions."""

    views: list[np.ndarray]                  # observation indices of each view
    obj32: list[np.ndarray]                  # (k, 3) float32 [m]
    img32: list[np.ndarray]                  # (k, 2) float32 [px]
    K0: np.ndarray                           # (3, 3) [px]
    rvec0: list[np.ndarray]
    tvec0: list[np.ndarray]
    size: tuple[int, int]


def peer_input(sf: SyntheticField, start: Start) -> PeerInput:
    """OpenCV's inputs: the surveyed targets each view sees, and the start (pixels, y down)."""
    d = sf.data
    s = d.sensor
    views = [np.flatnonzero(d.obs.image == i) for i in range(len(d.images))]
    obj = [d.targets.xyz_m[d.obs.target[k]].astype(np.float32) for k in views]
    img = [d.obs.uv_px[k].astype(np.float32) for k in views]
    K0 = camera_matrix(start.params, s)
    Rc = FLIP @ start.R_world_to_camera
    rvec0 = [cv2.Rodrigues(R)[0] for R in Rc]
    tvec0 = [-(R @ C)[:, None] for R, C in zip(Rc, start.center_m, strict=True)]
    return PeerInput(views, obj, img, K0, rvec0, tvec0, (s.width_px, s.height_px))


def camera_matrix(params, sensor) -> np.ndarray:
    """OpenCV's K [px] of f, xp, yp (pixel centres at integers, v down)."""
    px = sensor.pixel_mm
    return np.array([[params[0] / px, 0.0, (sensor.width_px - 1) / 2.0 + params[1] / px],
                     [0.0, params[0] / px, (sensor.height_px - 1) / 2.0 - params[2] / px],
                     [0.0, 0.0, 1.0]])


def fxy_from_K(K, sensor):
    """``(f_mm (from fx), xp_mm, yp_mm)`` of an OpenCV camera matrix."""
    px = sensor.pixel_mm
    return (K[0, 0] * px, (K[0, 2] - (sensor.width_px - 1) / 2.0) * px,
            -(K[1, 2] - (sensor.height_px - 1) / 2.0) * px)


def _calibrate(pi: PeerInput, max_count: int):
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, max_count, CV_EPS)
    return cv2.calibrateCamera(pi.obj32, pi.img32, pi.size, pi.K0.copy(), np.zeros(5),
                               [r.copy() for r in pi.rvec0], [t.copy() for t in pi.tvec0],
                               flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)


def case_opencv(sf, pi: PeerInput, max_count: int = 100, count_iterations=True) -> Case:
    """cv2.calibrateCamera with the intrinsic guess (``max_count`` iterations at most)."""
    return Case(lambda _: _calibrate(pi, max_count),
                lambda out, times: _report_opencv(sf, pi, out, times, max_count, count_iterations))


def _report_opencv(sf, pi, out, times, max_count, count_iterations) -> Row:
    rms, K, dist, rvecs, tvecs = out
    # residuals in float64 with the final parameters (the RMS OpenCV returns agrees)
    d = sf.data
    res = np.empty((len(d.obs), 2))
    for k, rv, tv in zip(pi.views, rvecs, tvecs, strict=True):
        uv, _ = cv2.projectPoints(d.targets.xyz_m[d.obs.target[k]], rv, tv, K, dist)
        res[k] = d.obs.uv_px[k] - uv.reshape(-1, 2)
    its = str(max_count) if max_count < 100 else "?"
    if count_iterations and max_count >= 100:
        its = "100 (limit)"
        for n in range(1, 101):                 # the smallest maxCount giving the same result
            again = _calibrate(pi, n)
            if np.array_equal(again[1], K) and np.array_equal(again[2], dist):
                its = str(n)
                break
    f, xp, yp = fxy_from_K(K, d.sensor)
    name = "OpenCV calibrateCamera" + (f", maxCount={max_count} (initial poses + 1 iteration)"
                                       if max_count == 1 else "")
    return Row(name, "fixed", "k1,k2,p1,p2,k3; fx,fy (9)", times, its, "-",
               rmse_2d(res), f, xp, yp, f"returned RMS {rms:.6f}",
               extra={"fy/fx - 1": K[1, 1] / K[0, 0] - 1.0, "dist": dist.ravel().tolist()})


# ------------------------------------------------------------------------------------------
# pycolmap (Ceres)
# ------------------------------------------------------------------------------------------
def colmap_reconstruction(sf: SyntheticField, start: Start, pi: PeerInput, model_name: str):
    """A pycolmap Reconstruction of the start: one camera, trivial rigs and frames, points."""
    d = sf.data
    s = d.sensor
    rec = pycolmap.Reconstruction()
    K = pi.K0
    cam = pycolmap.Camera.create_from_model_name(1, model_name, float(K[0, 0]), s.width_px,
                                                 s.height_px)
    prm = np.array(cam.params)
    fi, ci = list(cam.focal_length_idxs()), list(cam.principal_point_idxs())
    prm[fi] = K[0, 0]
    prm[ci] = [K[0, 2] + 0.5, K[1, 2] + 0.5]          # COLMAP: pixel centres at +0.5
    prm[list(cam.extra_params_idxs())] = 0.0
    cam.params = prm
    rec.add_camera_with_trivial_rig(cam)
    point_idx = np.empty(len(d.obs), np.int64)
    for i, k in enumerate(pi.views):
        point_idx[k] = np.arange(len(k))
        image = pycolmap.Image(name=d.images[i].file, keypoints=d.obs.uv_px[k] + 0.5,
                               camera_id=1, image_id=i + 1)
        Rc = FLIP @ start.R_world_to_camera[i]
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(Rc), -Rc @ start.center_m[i]))
    order = np.argsort(d.obs.target, kind="stable")
    bounds = np.searchsorted(d.obs.target[order], np.arange(len(d.targets) + 1))
    for t in range(len(d.targets)):
        k = order[bounds[t]:bounds[t + 1]]
        if len(k) == 0:
            continue
        track = pycolmap.Track([pycolmap.TrackElement(int(d.obs.image[j]) + 1, int(point_idx[j]))
                                for j in k])
        rec.add_point3D(d.targets.xyz_m[t], track)
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(len(d.images)):
        config.add_image(i + 1)
    for pid in rec.point3D_ids():
        config.add_constant_point(pid)
    return rec, config


def colmap_options(max_iter: int = 100):
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = True
    opts.refine_principal_point = True
    opts.refine_extra_params = True
    opts.refine_points3D = False
    opts.print_summary = False
    so = opts.ceres.solver_options
    so.num_threads = 1
    so.max_num_iterations = max_iter
    for k, v in CERES_TOL.items():
        setattr(so, k, v)
    return opts


def case_pycolmap(sf, start, pi, model_name) -> Case:
    """pycolmap's Ceres BA, points constant; a fresh copy of the reconstruction per run."""
    rec0, config = colmap_reconstruction(sf, start, pi, model_name)
    opts = colmap_options()

    def go(rec):
        summary = pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
        return rec, summary

    return Case(go, lambda out, times: _report_pycolmap(sf, pi, model_name, out, times),
                prepare=lambda: pycolmap.Reconstruction(rec0))


def _report_pycolmap(sf, pi, model_name, out, times) -> Row:
    rec, summary = out
    cs = summary.ceres_summary
    d = sf.data
    cam = rec.camera(1)
    res = np.empty((len(d.obs), 2))
    for i, k in enumerate(pi.views):
        T = rec.image(i + 1).cam_from_world().matrix()
        Xc = d.targets.xyz_m[d.obs.target[k]] @ T[:, :3].T + T[:, 3]
        res[k] = d.obs.uv_px[k] - (np.asarray(cam.img_from_cam(Xc)) - 0.5)
    prm = np.array(cam.params)
    fi, ci = list(cam.focal_length_idxs()), list(cam.principal_point_idxs())
    K = np.array([[prm[fi[0]], 0, prm[ci[0]] - 0.5], [0, prm[fi[-1]], prm[ci[1]] - 0.5], [0, 0, 1]])
    f, xp, yp = fxy_from_K(K, d.sensor)
    n_extra = len(cam.extra_params_idxs())
    return Row(f"pycolmap BA, points constant ({model_name})", "fixed",
               f"{model_name} ({len(fi) + 2 + n_extra})", times,
               f"{cs.num_successful_steps + cs.num_unsuccessful_steps} "
               f"({cs.num_unsuccessful_steps} rejected)",
               f"{cs.num_residual_evaluations} r, {cs.num_jacobian_evaluations} J",
               rmse_2d(res), f, xp, yp,
               f"{summary.termination_type.name.lower()}; {str(cs.linear_solver_type_used).split('.')[-1]}",
               extra={"ceres_ms": {k: 1e3 * getattr(cs, k) for k in (
                   "preprocessor_time_in_seconds", "residual_evaluation_time_in_seconds",
                   "jacobian_evaluation_time_in_seconds", "linear_solver_time_in_seconds",
                   "minimizer_time_in_seconds", "total_time_in_seconds")}})


# ------------------------------------------------------------------------------------------
# SciPy
# ------------------------------------------------------------------------------------------
def case_scipy(sf, start, adjusted, jac: str, scaled: bool = True) -> Case:
    """least_squares 'trf' + lsmr with finite differences (``jac='fd'``) or fieldcal's Jacobian."""
    problem, x0 = fieldcal_problem(sf, start, adjusted)
    _, J0 = problem.evaluate(x0, True)
    D = J0.column_norms() if scaled else np.ones(len(x0))
    D[~(D > 0)] = 1.0
    pattern = J0.to_csr()
    pattern.data[:] = 1.0
    Dinv = scipy.sparse.diags(1.0 / D)
    calls = {"r": 0, "J": 0}

    def go(_):
        calls.update(r=0, J=0)
        cache: dict = {}

        def fun(z):
            calls["r"] += 1
            if jac == "fd":
                return problem.evaluate(z / D, False)[0]
            r, J = problem.evaluate(z / D, True)
            cache.update(z=z.copy(), J=J)
            return r

        def jacobian(z):
            if "z" not in cache or not np.array_equal(cache["z"], z):
                cache.update(z=z.copy(), J=problem.evaluate(z / D, True)[1])
            calls["J"] += 1
            return cache["J"].to_csr() @ Dinv

        kw = dict(jac_sparsity=pattern) if jac == "fd" else dict(jac=jacobian)
        return scipy.optimize.least_squares(
            fun, x0 * D, method="trf", tr_solver="lsmr", x_scale="jac",
            ftol=SCIPY_TOL, xtol=SCIPY_TOL, gtol=SCIPY_TOL,
            tr_options=dict(atol=LSMR_TOL, btol=LSMR_TOL), **kw)

    name = ("SciPy trf+lsmr, finite differences" if jac == "fd"
            else "SciPy trf+lsmr, fieldcal's analytic J")
    if not scaled:
        name += ", raw variables"
    def go_safe(arg):
        try:
            return go(arg)
        except ValueError as err:                    # NaN residuals (a point behind a camera)
            return err

    def report(res, times) -> Row:
        if isinstance(res, Exception):
            nan = float("nan")
            return Row(name, _case(adjusted), "fieldcal-brown/1 (10)", times, "-", f"{calls['r']} r",
                       nan, nan, nan, nan, f"failed: {res}")
        p = problem.model.unpack(res.x / D)[0]
        evals = f"{calls['r']} r" + (f", {calls['J']} J" if jac != "fd" else " (incl. FD)")
        why = res.message.replace("`", "").replace(" termination condition is satisfied", " reached")
        return Row(name, _case(adjusted), "fieldcal-brown/1 (10)", times, str(res.nfev), evals,
                   image_rmse(problem.model, res.fun), p[0], p[1], p[2],
                   f"{why.rstrip('.')}; cost {res.cost:.10g}")

    return Case(go_safe, report)


# ------------------------------------------------------------------------------------------
# model floors: how well a peer's model can represent the true camera
# ------------------------------------------------------------------------------------------
def opencv_model_floor(camera: Camera, n_coeffs: int) -> float:
    """RMS [px] of the best fit of OpenCV's model (k1, k2, p1, p2[, k3]; fx, fy, cx, cy).

    The true camera's mapping on a 41 x 31 grid of pixels over the whole sensor: each pixel's
    ideal ray (``correct``) is pushed through OpenCV's model, whose parameters are fitted in
    least squares to land on the pixel.
    """
    s = camera.sensor
    uv = s.grid_px(41, 31)
    q = camera.correct(s.pixel_to_mm(uv))
    xn, yn = q[:, 0] / camera.f_mm, -q[:, 1] / camera.f_mm
    K = camera_matrix(camera.params, s)

    def resid(p):
        fx, fy, cx, cy, k1, k2, p1, p2, k3 = np.r_[p, np.zeros(9 - len(p))]
        r2 = xn * xn + yn * yn
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        return np.r_[fx * xd + cx - uv[:, 0], fy * yd + cy - uv[:, 1]]

    p0 = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(n_coeffs)]
    fit = scipy.optimize.least_squares(resid, p0, method="lm", x_scale="jac", xtol=1e-14, ftol=1e-14)
    return rmse_2d(fit.fun.reshape(2, -1).T)


# ------------------------------------------------------------------------------------------
# profile
# ------------------------------------------------------------------------------------------
def profile_fieldcal(sf, start, adjusted=False, method="lmqn", runs=7):
    """Where a fieldcal solve spends its time: inclusive wall time of its parts.

    The parts are wrapped with timers for the duration of ``runs`` solves (cheaper and less
    distorting than cProfile, which also hooks every NumPy call); the best run is printed.
    Indented parts are inside the part above them.
    """
    from fieldcal.field import adjustment, bundle

    o = AdjustmentOptions()
    parts = [  # (label, owner, attribute)
        ("model set-up (BundleModel + FieldProblem)", None, None),
        ("problem.evaluate: residuals + Jacobian", adjustment.FieldProblem, "evaluate"),
        ("  BundleModel._predict", BundleModel, "_predict"),
        ("    distort (Newton, from the measured points)", bundle, "distort"),
        ("    correct_jacobian", bundle, "correct_jacobian"),
        ("    _correct_terms (G at the solution)", bundle, "_correct_terms"),
        ("  BlockSparseJacobian(...) (index analysis on the 1st call)", blocksparse.BlockSparseJacobian,
         "__init__"),
        ("finite check of J (all_finite; concatenates the parts)", blocksparse.BlockSparseJacobian,
         "all_finite"),
        ("J^T r (gradient), all calls", blocksparse.BlockSparseJacobian, "gradient"),
        ("J h (matvec), all calls", blocksparse.BlockSparseJacobian, "matvec"),
        ("BFGS update (2 J^T r + 1 J h, every trial step)", lsq._State, "update_bfgs"),
        ("normal equations N = J^T J", blocksparse.NormalEquations, "__init__"),
        ("damped solve (Schur + equilibrated Cholesky)", blocksparse.NormalEquations, "solve"),
    ]
    # the model's helpers differ between versions of bundle.py: time those it has
    parts = [p for p in parts if p[1] is None or hasattr(p[1], p[2])]
    acc: dict[str, list[float]] = {}
    saved = []

    def timed(label, fn):
        def wrapper(*args, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                acc[label][0] += time.perf_counter() - t0
                acc[label][1] += 1
        return wrapper

    for label, owner, attr in parts:
        if owner is not None:
            saved.append((owner, attr, getattr(owner, attr)))
            setattr(owner, attr, timed(label, getattr(owner, attr)))
    best = None
    try:
        for _ in range(runs + 1):                       # the first run warms up
            for label, _o, _a in parts:
                acc[label] = [0.0, 0]
            t0 = time.perf_counter()
            problem, x0 = fieldcal_problem(sf, start, adjusted)
            acc[parts[0][0]] = [time.perf_counter() - t0, 1]
            res = lsq.solve(problem, x0, method=method, tau=o.tau, eps2=o.eps2, ftol=o.ftol,
                            sigma_tol=o.sigma_tol, max_iter=o.max_iter)
            total = time.perf_counter() - t0
            if best is None or total < best[0]:
                best = (total, {k: list(v) for k, v in acc.items()}, res)
    finally:
        for owner, attr, fn in saved:
            setattr(owner, attr, fn)
    total, times, res = best
    n_it = res.iterations
    print(f"\nProfile: fieldcal {method.upper()}, {_case(adjusted)} targets: best of {runs} solves, "
          f"{total * 1e3:.0f} ms, {n_it} iterations, {res.evaluations} evaluations (timers on)")
    print("| part | calls | ms per solve | ms per iteration | share |\n|---|---|---|---|---|")
    for label, _o, _a in parts:
        t, n = times[label]
        print(f"| {label} | {n} | {1e3 * t:.1f} | {1e3 * t / n_it:.2f} | {100 * t / total:.0f} % |")
    print(f"| whole solve | 1 | {1e3 * total:.1f} | {1e3 * total / n_it:.2f} | 100 % |")


# ------------------------------------------------------------------------------------------
# output
# ------------------------------------------------------------------------------------------
def print_table(rows: list[Row], ref: Row, truth, title: str):
    """A markdown table of rows; times are best (median) of the repetitions, ratios to ``ref``."""
    print(f"\n### {title}\n")
    print("| solver | targets | model (parameters) | time [s], best (median, n) | ratio to OpenCV, best "
          "(median) | iterations | evaluations | RMS [px] | f [mm] | xp [mm] | yp [mm] | status |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    ref_best, ref_med = ref.time_s, float(np.median(ref.times_s))
    for r in rows:
        med = float(np.median(r.times_s))
        print(f"| {r.solver} | {r.case} | {r.model} | {r.time_s:.3f} ({med:.3f}, {len(r.times_s)}) | "
              f"{r.time_s / ref_best:.2f} ({med / ref_med:.2f}) | {r.iterations} | {r.evaluations} | "
              f"{r.rmse_px:.4f} | {r.f_mm:.4f} | {r.xp_mm:.4f} | {r.yp_mm:.4f} | {r.status} |")
    print(f"| truth | | | | | | | | {truth[0]:.4f} | {truth[1]:.4f} | {truth[2]:.4f} | |")


def machine_line() -> str:
    cpu = "?"
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (f"{cpu}, {os.cpu_count()} logical CPUs, load average {os.getloadavg()[0]:.2f}; "
            f"Python {platform.python_version()}, NumPy {np.__version__}, SciPy {scipy.__version__}, "
            f"OpenCV {cv2.__version__} ({cv2.getNumThreads()} thread(s)), pycolmap {pycolmap.__version__}; "
            f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")


def code_line() -> str:
    """The fieldcal code measured: git commit and the fieldcal modules changed since (read only)."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", root, "status", "--porcelain", "--", "fieldcal"],
                               capture_output=True, text=True, check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return "fieldcal code: unknown (no git)"
    changed = sorted(line[3:] for line in dirty if line.strip())
    return f"fieldcal code: commit {head}" + (f" + uncommitted changes in {', '.join(changed)}"
                                              if changed else "")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=9,
                    help="repetitions of the fast solvers (interleaved; best of)")
    ap.add_argument("--repeat-slow", type=int, default=1,
                    help="repetitions of the SciPy and adjust_field rows (best of)")
    ap.add_argument("--seed", type=int, default=0, help="paper_field seed")
    ap.add_argument("--quick", action="store_true", help="skip the slow SciPy rows")
    ap.add_argument("--profile", action="store_true", help="only profile fieldcal's solves")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)

    t_start = time.perf_counter()
    sf = paper_field(seed=args.seed)
    start = perturbed_start(sf, seed=args.seed + 1)
    d = sf.data
    truth = sf.camera.params[:3]
    print(f"# fieldcal solver benchmark, {datetime.datetime.now().isoformat(timespec='minutes')}")
    print(f"machine: {machine_line()}")
    print(code_line())
    print(f"problem: paper_field(seed={args.seed}): {len(d.images)} images, {len(d.targets)} targets, "
          f"{len(d.obs)} image points ({np.bincount(d.obs.image).min()}-{np.bincount(d.obs.image).max()} "
          f"per image), noise 0.1 px / 5 mm survey")
    if args.profile:
        for adjusted in (False, True):
            for method in ("lmqn", "lm"):
                profile_fieldcal(sf, start, adjusted=adjusted, method=method)
        return

    pi = peer_input(sf, start)
    fast = measure([case_opencv(sf, pi), case_opencv(sf, pi, max_count=1),
                    case_pycolmap(sf, start, pi, "OPENCV"),
                    case_fieldcal(sf, start, False, "lmqn"), case_fieldcal(sf, start, False, "lm"),
                    case_fieldcal(sf, start, True, "lmqn"), case_fieldcal(sf, start, True, "lm")],
                   args.repeat)
    slow_fixed = [case_pycolmap(sf, start, pi, "FULL_OPENCV")]
    slow_adj = []
    if not args.quick:
        slow_fixed += [case_scipy(sf, start, False, "analytic"), case_scipy(sf, start, False, "fd"),
                       case_scipy(sf, start, False, "fd", scaled=False)]
        slow_adj += [case_scipy(sf, start, True, "analytic"), case_scipy(sf, start, True, "fd")]
    slow_fixed.append(case_adjust_field(sf, False))
    slow_adj.append(case_adjust_field(sf, True))
    slow = measure(slow_fixed + slow_adj, args.repeat_slow)
    ref = fast[0]
    print_table(fast[:5] + slow[:len(slow_fixed)], ref, truth,
                "Targets fixed (paper_field, 5 mm survey noise)")
    print_table(fast[5:] + slow[len(slow_fixed):], ref, truth,
                "Targets adjusted (no peer adjusts weighted targets; ratio to OpenCV's fixed-target time)")

    # the same geometry with a precise survey: the RMS shows each camera model's fit
    sfp = paper_field(seed=args.seed, survey_noise_mm=0.01)
    pip = peer_input(sfp, start)
    precise = measure([case_opencv(sfp, pip), case_pycolmap(sfp, start, pip, "OPENCV"),
                       case_fieldcal(sfp, start, False, "lmqn"), case_fieldcal(sfp, start, False, "lm")],
                      args.repeat)
    print_table(precise, precise[0], truth,
                "Targets fixed, precise survey (0.01 mm): the RMS is the camera model's fit")
    print("\nModel floors (best fit of the peer's model to the true camera, 41 x 31 grid, "
          f"whole sensor): OpenCV k1,k2,p1,p2,k3 {opencv_model_floor(sf.camera, 5):.4f} px; "
          f"COLMAP OPENCV (k1,k2,p1,p2) {opencv_model_floor(sf.camera, 4):.4f} px; "
          "fieldcal-brown/1 0 (the data's own model).")
    cm = fast[2]
    print(f"Ceres' own timing of the last pycolmap OPENCV run, ms ({cm.iterations} iterations): "
          + ", ".join(f"{k.replace('_time_in_seconds', '')} {v:.1f}" for k, v in cm.extra["ceres_ms"].items()))
    cvrow = fast[0]
    print(f"OpenCV fy/fx - 1 = {cvrow.extra['fy/fx - 1']:.3e}; dist = "
          f"{np.array2string(np.array(cvrow.extra['dist']), precision=4)}")
    print(f"\nload average at the end {os.getloadavg()[0]:.2f}; total run time "
          f"{time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
