r"""Exports of a calibration to the tools photogrammetrists use: OpenCV, COLMAP, Metashape, JSON.

fieldcal's model (docs/conventions.md section 2) corrects a *measured* point to the *ideal* one; OpenCV,
COLMAP and Metashape distort an *ideal* normalised point into a pixel, with other
polynomials. No exact conversion exists, so each export is a least-squares fit, and every
export says how good it is.

Frames
------
A pixel ``uv`` (docs/conventions.md section 1: centre of the top-left pixel at (0, 0), v down) has the
ideal point ``q = correct(x'(uv))`` [mm] relative to the principal point (y up) and the
camera-frame ray ``(qx, qy, -f)`` (the camera looks along -z). OpenCV, COLMAP and Metashape
use a camera frame with y down and z forward, so the ray's *normalised* coordinates are

    xn = qx / f,        yn = -qy / f.

Pixel origins: OpenCV puts the centre of the top-left pixel at (0, 0), like fieldcal;
COLMAP at (0.5, 0.5) (``cx_colmap = cx + 0.5``); Metashape measures ``cx, cy`` from the
image centre ``(w/2, h/2)`` in a frame whose top-left *corner* is (0, 0), so
``cx_metashape = cx - (w - 1)/2`` (and ``cy`` likewise).

OpenCV's model (``distCoeffs`` order ``k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4``)::

    r2 = xn^2 + yn^2,  radial = (1 + k1 r2 + k2 r2^2 + k3 r2^3) / (1 + k4 r2 + k5 r2^2 + k6 r2^3)
    xd = xn radial + 2 p1 xn yn + p2 (r2 + 2 xn^2) + s1 r2 + s2 r2^2
    yd = yn radial + p1 (r2 + 2 yn^2) + 2 p2 xn yn + s3 r2 + s4 r2^2
    u = fx xd + cx,   v = fy yd + cy

Metashape's frame-camera model (Agisoft Metashape manual, appendix "Camera models"); note
that its ``P1, P2`` are OpenCV's ``p2, p1``::

    xd = xn (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P1 (r2 + 2 xn^2) + 2 P2 xn yn
    yd = yn (1 + K1 r2 + K2 r2^2 + K3 r2^3 + K4 r2^4) + P2 (r2 + 2 yn^2) + 2 P1 xn yn
    u = w/2 + cx + xd (f + B1) + yd B2,     v = h/2 + cy + yd f        (corner origin)

The fit
-------
Over a dense grid of pixels spanning the sensor corner to corner (81 x 61), fieldcal gives
each pixel's normalised ray; the target model's parameters make the target model project
those rays onto the pixels. The requirement is on the largest error, so the fit is a
minimax fit: least squares (SciPy's Levenberg-Marquardt), then Lawson's iteratively
reweighted least squares (weights multiplied by the errors), keeping the parameters with
the smallest largest error. On the field paper's camera this takes OpenCV's five
coefficients from 0.026 px to 0.009 px. ``fit_rms_px`` and ``fit_max_px`` are that forward
residual.

The round trip (the figure that matters to a user): at 20 000 other pixels (seeded,
uniform over the whole sensor, plus its corners and edge midpoints), the exported model's
own inverse -- ``cv2.undistortPoints`` for OpenCV and COLMAP, a Newton inversion of the
forward model for Metashape -- must give fieldcal's normalised ray within
:data:`EXACT_PX` (0.01 px, measured in pixels as ``|dn| * f``). ``auto`` takes the simplest
model of the format that meets it; when none does, the best one is exported and the export
says that it cannot be that exact.
"""

from __future__ import annotations

import datetime as dt
import json
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.errors import ConvergenceError, InputError
from fieldcal.model.camera import Camera

__all__ = ["EXACT_PX", "OPENCV_MODELS", "FORMATS", "ModelFit", "normalised_rays",
           "opencv_project", "opencv_jacobian", "metashape_project", "fit_opencv", "fit_metashape",
           "opencv_yaml", "colmap_cameras_txt", "metashape_xml", "export_text", "Export"]

EXACT_PX = 0.01
"""Round-trip accuracy an export must reach to count as exact [px]."""

OPENCV_MODELS = {
    "brown4": ("k1", "k2", "p1", "p2"),
    "brown5": ("k1", "k2", "p1", "p2", "k3"),
    "rational8": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
    "prism12": ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4"),
}
"""OpenCV distortion models by the coefficients they use (``distCoeffs`` of 4, 5, 8, 12)."""

FORMATS = ("opencv", "colmap", "metashape", "json")
AUTO = {"opencv": ("brown5", "rational8", "prism12"), "colmap": ("brown4", "rational8")}
COLMAP_MODEL = {"brown4": "OPENCV", "rational8": "FULL_OPENCV"}
METASHAPE_PARAMS = ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2")
FIT_GRID = (81, 61)
CHECK_POINTS = 20000
MAX_NFEV = 100
"""Evaluations per least-squares round of the minimax fit (each with the analytic Jacobian,
:func:`opencv_jacobian`). A round of brown5 converges in 4-10, of the rational models in
30-100; some rounds of a rational model (its numerator and denominator nearly cancel) walked
to the old limit of 5000 for nothing (the fit keeps the best round anyway): a goniometer
camera's OpenCV export took 41 s, now 3-5 s (bench/README_reports.md)."""


# --------------------------------------------------------------------------------------
# the rays of fieldcal's model
# --------------------------------------------------------------------------------------
def normalised_rays(camera: Camera, uv_px):
    """Normalised ray coordinates (n, 2) ``(qx/f, -qy/f)`` of pixels (module docstring)."""
    q = camera.correct(camera.sensor.pixel_to_mm(np.asarray(uv_px, float)))
    return np.stack([q[..., 0], -q[..., 1]], axis=-1) / camera.f_mm


def _check_points(camera: Camera, n: int = CHECK_POINTS, seed: int = 20261122):
    s = camera.sensor
    rng = np.random.default_rng(seed)
    lo, hi = -0.5, np.array([s.width_px - 0.5, s.height_px - 0.5])
    uv = rng.uniform(lo, hi, (n, 2))
    u = np.array([lo, (hi[0] + lo) / 2, hi[0]])
    v = np.array([lo, (hi[1] + lo) / 2, hi[1]])
    edges = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    return np.concatenate([edges, uv])


def _fit_grid(camera: Camera, grid=FIT_GRID):
    s = camera.sensor
    u = np.linspace(-0.5, s.width_px - 0.5, grid[0])
    v = np.linspace(-0.5, s.height_px - 0.5, grid[1])
    return np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)


# --------------------------------------------------------------------------------------
# target models (forward: normalised ray -> pixel in fieldcal's pixel convention)
# --------------------------------------------------------------------------------------
def _opencv_full(dist):
    full = np.zeros(12)
    full[: len(dist)] = dist
    return full


def opencv_project(n, K, dist):
    """OpenCV's projection (module docstring) of normalised rays (n, 2) -> pixels (n, 2).

    The same as ``cv2.projectPoints`` of ``(xn, yn, 1)`` with no rotation and translation
    (checked in the tests); vectorised for the fit.
    """
    x, y = np.asarray(n, float)[..., 0], np.asarray(n, float)[..., 1]
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _opencv_full(dist)
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + s4 * r2)
    return np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], axis=-1)


def opencv_jacobian(n, K, dist):
    """Derivatives (n, 2, 4 + m) of :func:`opencv_project` by ``fx, fy, cx, cy`` and the ``m``
    coefficients of ``dist`` (``distCoeffs`` order): the fit's Jacobian, analytic (finite
    differences cost 4 + m projections per step, and the rational models' near-cancelling
    numerator and denominator need hundreds of steps)."""
    x, y = np.asarray(n, float)[..., 0], np.asarray(n, float)[..., 1]
    m = len(dist)
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _opencv_full(dist)
    fx, fy = K[0, 0], K[1, 1]
    r2 = x * x + y * y
    r4, r6 = r2 * r2, r2 * r2 * r2
    num = 1 + k1 * r2 + k2 * r4 + k3 * r6
    den = 1 + k4 * r2 + k5 * r4 + k6 * r6
    radial = num / den
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + s2 * r2)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + s4 * r2)
    zero, one = np.zeros_like(x), np.ones_like(x)
    d_num = [r2 / den, r4 / den, r6 / den]                    # d radial / d k1, k2, k3
    d_den = [-radial * r2 / den, -radial * r4 / den, -radial * r6 / den]   # / d k4, k5, k6
    cols_u = [xd, zero, one, zero, fx * x * d_num[0], fx * x * d_num[1], fx * 2 * x * y,
              fx * (r2 + 2 * x * x), fx * x * d_num[2], *(fx * x * d for d in d_den),
              fx * r2, fx * r4, zero, zero]
    cols_v = [zero, yd, zero, one, fy * y * d_num[0], fy * y * d_num[1], fy * (r2 + 2 * y * y),
              fy * 2 * x * y, fy * y * d_num[2], *(fy * y * d for d in d_den),
              zero, zero, fy * r2, fy * r4]
    return np.stack([np.stack(cols_u[: 4 + m], axis=-1), np.stack(cols_v[: 4 + m], axis=-1)], axis=-2)


def metashape_project(n, params: dict, width: int, height: int):
    """Metashape's frame-camera projection (module docstring) -> pixels in fieldcal's convention."""
    x, y = np.asarray(n, float)[..., 0], np.asarray(n, float)[..., 1]
    p = {k: float(params.get(k, 0.0)) for k in METASHAPE_PARAMS}
    r2 = x * x + y * y
    radial = 1 + r2 * (p["k1"] + r2 * (p["k2"] + r2 * (p["k3"] + r2 * p["k4"])))
    xd = x * radial + p["p1"] * (r2 + 2 * x * x) + 2 * p["p2"] * x * y
    yd = y * radial + p["p2"] * (r2 + 2 * y * y) + 2 * p["p1"] * x * y
    u = width / 2 + p["cx"] + xd * (p["f"] + p["b1"]) + yd * p["b2"] - 0.5
    v = height / 2 + p["cy"] + yd * p["f"] - 0.5
    return np.stack([u, v], axis=-1)


def _invert(forward, uv_px, n0, *, tol=1e-13, max_iter=50):
    """Normalised rays (n, 2) with ``forward(n) = uv`` by Newton's method (2x2 central differences)."""
    n = np.array(n0, dtype=float)
    uv = np.asarray(uv_px, float)
    h = 1e-7
    for _ in range(max_iter):
        r = forward(n) - uv
        ex, ey = np.array([h, 0.0]), np.array([0.0, h])
        Jx = (forward(n + ex) - forward(n - ex)) / (2 * h)
        Jy = (forward(n + ey) - forward(n - ey)) / (2 * h)
        det = Jx[:, 0] * Jy[:, 1] - Jy[:, 0] * Jx[:, 1]
        sx = (Jy[:, 1] * r[:, 0] - Jy[:, 0] * r[:, 1]) / det
        sy = (Jx[:, 0] * r[:, 1] - Jx[:, 1] * r[:, 0]) / det
        n[:, 0] -= sx
        n[:, 1] -= sy
        if np.nanmax(np.abs(np.concatenate([sx, sy]))) < tol:
            return n
    raise ConvergenceError("the exported model could not be inverted over the sensor "
                           f"(Newton did not converge in {max_iter} steps)")


# --------------------------------------------------------------------------------------
# fits
# --------------------------------------------------------------------------------------
@dataclass
class ModelFit:
    """A target model fitted to a calibration, with how good it is.

    Attributes
    ----------
    format : str
        ``"opencv"`` (also COLMAP) or ``"metashape"``.
    model : str
        ``brown4``, ``brown5``, ``rational8``, ``prism12`` (OpenCV) or ``frame`` (Metashape).
    width_px, height_px : int
    K : (3, 3) ndarray
        OpenCV camera matrix (fieldcal's pixel origin); for Metashape the equivalent
        ``fx = f + b1, fy = f``, skew ``b2`` in ``K[0, 1]``.
    dist : (m,) ndarray
        OpenCV ``distCoeffs`` (empty for Metashape).
    params : dict
        The model's own parameters by name (Metashape: ``f, cx, cy, b1, b2, k1..k4, p1, p2``
        in its conventions; OpenCV: ``fx, fy, cx, cy`` and the coefficients).
    fit_rms_px, fit_max_px : float
        Forward residual over the fit grid [px].
    roundtrip_rms_px, roundtrip_max_px : float
        Round-trip error over the check points [px] (module docstring).
    roundtrip_with : str
        What inverted the exported model.
    tried : list of dict
        Every model tried: ``model, fit_rms_px, fit_max_px, roundtrip_max_px``.
    """

    format: str
    model: str
    width_px: int
    height_px: int
    K: np.ndarray
    dist: np.ndarray
    params: dict
    fit_rms_px: float
    fit_max_px: float
    roundtrip_rms_px: float
    roundtrip_max_px: float
    roundtrip_with: str
    tried: list = field(default_factory=list)

    @property
    def exact(self) -> bool:
        """Whether the round trip is within :data:`EXACT_PX`."""
        return bool(self.roundtrip_max_px <= EXACT_PX)

    def choice_line(self) -> str:
        """Which model was exported and why (the models tried, each with its round trip)."""
        n = len(self.dist) if self.format != "metashape" else len(METASHAPE_PARAMS) - 3
        what = f"{self.format}: exported the {self.model} model ({n} distortion coefficients)"
        others = [t for t in self.tried if t["model"] != self.model]
        if not others:
            return what
        tried = ", ".join(f"{t['model']} {t['roundtrip_max_px']:.3g} px" for t in self.tried)
        why = (f"the simplest whose round trip is within {EXACT_PX} px" if self.exact
               else "the best round trip; none is within " + f"{EXACT_PX} px")
        return f"{what}: {why} (tried, largest round-trip error: {tried})"

    def report_lines(self) -> list[str]:
        lines = [self.choice_line(),
                 f"{self.format} {self.model}: fit residual {self.fit_rms_px:.3g} px RMS, "
                 f"{self.fit_max_px:.3g} px max over the sensor; round trip through "
                 f"{self.roundtrip_with}: {self.roundtrip_rms_px:.3g} px RMS, "
                 f"{self.roundtrip_max_px:.3g} px max"]
        if not self.exact:
            lines.append(f"warning: the {self.format} export cannot be that exact: the round trip "
                         f"is off by up to {self.roundtrip_max_px:.3g} px (> {EXACT_PX} px); "
                         f"the best of {', '.join(t['model'] for t in self.tried)} is exported")
        return lines

    def summary(self) -> dict:
        return {"format": self.format, "model": self.model, "fit_rms_px": self.fit_rms_px,
                "fit_max_px": self.fit_max_px, "roundtrip_rms_px": self.roundtrip_rms_px,
                "roundtrip_max_px": self.roundtrip_max_px, "roundtrip_with": self.roundtrip_with,
                "exact": self.exact, "exact_px": EXACT_PX, "tried": self.tried}


def _minimax_fit(project, x0, n, uv, *, rounds: int = 25, jacobian=None):
    """Parameters ``x`` making ``project(n, x)`` match ``uv`` (n, 2) [px] in the max norm.

    Least squares first (Levenberg-Marquardt), then Lawson's iteratively reweighted least
    squares towards the minimax fit (weights ``w <- w |e|``, normalised): the requirement
    is on the *largest* error over the sensor, which plain least squares leaves in the
    corners. Returns the parameters with the smallest largest error seen, ``x0`` included
    (so a model started from a nested smaller model's fit is never worse). (Lawson's
    iteration converges slowly near the optimum; a sequential-LP polish was tried and
    gained under 1 % on the paper's camera for several times the cost.)
    """
    w = np.ones(len(uv))
    x = np.asarray(x0, dtype=float)
    best, best_max = x, float(np.hypot(*(project(n, x) - uv).T).max())
    for _ in range(rounds + 1):
        sw = np.sqrt(w)[:, None]

        def residual(p, sw=sw):
            return ((project(n, p) - uv) * sw).ravel()

        jac = "2-point" if jacobian is None else (
            lambda p, sw=sw: (jacobian(n, p) * sw[:, :, None]).reshape(2 * len(uv), -1))
        x = least_squares(residual, x, jac=jac, method="lm", x_scale="jac", xtol=1e-15, ftol=1e-15,
                          gtol=1e-15, max_nfev=MAX_NFEV).x
        e = np.hypot(*(project(n, x) - uv).T)
        if e.max() < best_max:
            best, best_max = x, float(e.max())
        w = w * e
        w = w / w.mean()
        if not np.all(np.isfinite(w)) or w.max() == 0:
            break
    return best


def _fit_opencv_model(camera: Camera, model: str, start: ModelFit | None = None) -> ModelFit:
    """One OpenCV model; ``start``: a fit of a model whose coefficients are a prefix of these."""
    names = OPENCV_MODELS[model]
    s = camera.sensor
    uv = _fit_grid(camera)
    n = normalised_rays(camera, uv)
    f_px = camera.f_mm / s.pixel_mm
    c0 = camera.principal_point_px

    def unpack(x):
        K = np.array([[x[0], 0.0, x[2]], [0.0, x[1], x[3]], [0.0, 0.0, 1.0]])
        return K, x[4:]

    def project(nn, x):
        return opencv_project(nn, *unpack(x))

    def jacobian(nn, x):
        return opencv_jacobian(nn, *unpack(x))

    x0 = np.concatenate([[f_px, f_px, c0[0], c0[1]], np.zeros(len(names))])
    if start is not None and len(start.dist) <= len(names):
        x0[:4] = start.K[0, 0], start.K[1, 1], start.K[0, 2], start.K[1, 2]
        x0[4:4 + len(start.dist)] = start.dist
    x = _minimax_fit(project, x0, n, uv, jacobian=jacobian)
    K, dist = unpack(x)
    fit = np.hypot(*(opencv_project(n, K, dist) - uv).T)
    check = _check_points(camera)
    n_true = normalised_rays(camera, check)
    n_cv = cv2.undistortPoints(check.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    err = np.hypot(*((n_cv - n_true) * [K[0, 0], K[1, 1]]).T)
    params = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    params.update({k: float(v) for k, v in zip(names, dist, strict=True)})
    return ModelFit("opencv", model, s.width_px, s.height_px, K, dist.copy(), params,
                    float(np.sqrt(np.mean(fit**2))), float(fit.max()),
                    float(np.sqrt(np.mean(err**2))), float(np.nanmax(err)),
                    "cv2.undistortPoints")


def fit_opencv(camera: Camera, model: str = "auto", *, candidates=None) -> ModelFit:
    """Fit OpenCV's camera matrix and distortion coefficients to ``camera`` (module docstring).

    Parameters
    ----------
    camera : Camera
    model : str
        A key of :data:`OPENCV_MODELS`, or ``"auto"``: the first of ``candidates`` (default
        ``brown5, rational8, prism12``) whose round trip is within :data:`EXACT_PX`, else the
        one with the smallest round-trip error. Each model starts from the previous one's fit
        (their coefficients are nested), so a larger model never fits worse.

    Returns
    -------
    ModelFit
    """
    if model != "auto" and model not in OPENCV_MODELS:
        raise InputError(f"model must be 'auto' or one of {', '.join(OPENCV_MODELS)}, got {model!r}",
                         "export")
    order = [model] if model != "auto" else list(candidates or AUTO["opencv"])
    nested = ("brown5", "rational8", "prism12")
    start = None
    if model in nested[1:]:           # start from the nested smaller models' fits
        for m in nested[:nested.index(model)]:
            start = _fit_opencv_model(camera, m, start)
    tried, best = [], None
    for m in order:
        fit = _fit_opencv_model(camera, m, start if start is not None
                                and len(OPENCV_MODELS[m]) >= len(start.dist) else None)
        start = fit
        tried.append({"model": m, "fit_rms_px": fit.fit_rms_px, "fit_max_px": fit.fit_max_px,
                      "roundtrip_max_px": fit.roundtrip_max_px})
        if best is None or fit.roundtrip_max_px < best.roundtrip_max_px:
            best = fit
        if fit.exact:
            best = fit
            break
    best.tried = tried
    return best


def fit_metashape(camera: Camera) -> ModelFit:
    """Fit Metashape's frame-camera model (module docstring) to ``camera``."""
    s = camera.sensor
    W, H = s.width_px, s.height_px
    uv = _fit_grid(camera)
    n = normalised_rays(camera, uv)
    f_px = camera.f_mm / s.pixel_mm
    c0 = camera.principal_point_px
    names = METASHAPE_PARAMS

    def project(nn, x):
        return metashape_project(nn, dict(zip(names, x, strict=True)), W, H)

    x0 = np.zeros(len(names))
    x0[:3] = f_px, c0[0] - (W - 1) / 2, c0[1] - (H - 1) / 2
    p = dict(zip(names, map(float, _minimax_fit(project, x0, n, uv)), strict=True))
    fit = np.hypot(*(metashape_project(n, p, W, H) - uv).T)
    check = _check_points(camera)
    n_true = normalised_rays(camera, check)

    def forward(nn):
        return metashape_project(nn, p, W, H)

    n_ms = _invert(forward, check, n_true + 1e-4)
    err = np.hypot(*((n_ms - n_true) * p["f"]).T)
    K = np.array([[p["f"] + p["b1"], p["b2"], (W - 1) / 2 + p["cx"]],
                  [0.0, p["f"], (H - 1) / 2 + p["cy"]], [0.0, 0.0, 1.0]])
    fit_ = ModelFit("metashape", "frame", W, H, K, np.zeros(0), p, float(np.sqrt(np.mean(fit**2))),
                    float(fit.max()), float(np.sqrt(np.mean(err**2))), float(err.max()),
                    "Newton inversion of Metashape's model")
    fit_.tried = [{"model": "frame", "fit_rms_px": fit_.fit_rms_px, "fit_max_px": fit_.fit_max_px,
                   "roundtrip_max_px": fit_.roundtrip_max_px}]
    return fit_


# --------------------------------------------------------------------------------------
# file formats
# --------------------------------------------------------------------------------------
def _provenance(doc: dict) -> dict:
    return {"camera_id": doc.get("camera_id"), "session_id": doc.get("session_id"),
            "version": doc.get("version"), "method": doc.get("method"),
            "created": doc.get("created"), "model": doc.get("model")}


def opencv_yaml(fit: ModelFit, doc: dict) -> str:
    """OpenCV ``FileStorage`` YAML: ``camera_matrix``, ``distortion_coefficients``, sizes, fit figures.

    Read it back with ``cv2.FileStorage(path, cv2.FILE_STORAGE_READ)``.
    """
    fs = cv2.FileStorage("export.yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.writeComment("fieldcal export: OpenCV pinhole + distortion fitted to the calibration "
                    "(fieldcal-brown/1); pixel (0,0) is the centre of the top-left pixel")
    fs.writeComment(fit.choice_line())
    for k, v in _provenance(doc).items():
        fs.write(f"fieldcal_{k}", str(v))
    fs.write("image_width", int(fit.width_px))
    fs.write("image_height", int(fit.height_px))
    fs.write("camera_matrix", fit.K)
    fs.write("distortion_coefficients", fit.dist.reshape(1, -1))
    fs.write("distortion_model", fit.model)
    fs.write("fit_rms_px", fit.fit_rms_px)
    fs.write("fit_max_px", fit.fit_max_px)
    fs.write("roundtrip_rms_px", fit.roundtrip_rms_px)
    fs.write("roundtrip_max_px", fit.roundtrip_max_px)
    fs.write("exact", int(fit.exact))
    return fs.releaseAndGetString()


def colmap_cameras_txt(fit: ModelFit, doc: dict, camera_id: int = 1) -> str:
    """COLMAP's ``cameras.txt`` with one camera (OPENCV or FULL_OPENCV; pixel centres at +0.5)."""
    if fit.model not in COLMAP_MODEL:
        raise InputError(f"COLMAP takes OPENCV (brown4) or FULL_OPENCV (rational8), not {fit.model}",
                         "export")
    k = fit.K
    params = [k[0, 0], k[1, 1], k[0, 2] + 0.5, k[1, 2] + 0.5] + list(fit.dist)
    prov = _provenance(doc)
    lines = ["# Camera list with one line of data per camera:",
             "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
             "# Number of cameras: 1",
             f"# fieldcal export of {prov['camera_id']}/{prov['session_id']} version {prov['version']}"
             f" ({prov['method']})",
             f"# fit residual {fit.fit_rms_px:.2g} px RMS, {fit.fit_max_px:.2g} px max; round trip "
             f"{fit.roundtrip_max_px:.2g} px max" + ("" if fit.exact else f" (> {EXACT_PX} px: not exact)"),
             f"{camera_id} {COLMAP_MODEL[fit.model]} {fit.width_px} {fit.height_px} "
             + " ".join(repr(float(p)) for p in params)]
    return "\n".join(lines) + "\n"


def metashape_xml(fit: ModelFit, doc: dict) -> str:
    """Agisoft Metashape's camera calibration XML (``<calibration>``, frame projection)."""
    root = ET.Element("calibration")
    ET.SubElement(root, "projection").text = "frame"
    ET.SubElement(root, "width").text = str(fit.width_px)
    ET.SubElement(root, "height").text = str(fit.height_px)
    for name in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4", "p1", "p2"):
        ET.SubElement(root, name).text = repr(float(fit.params[name]))
    created = doc.get("created") or dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    ET.SubElement(root, "date").text = str(created)
    prov = _provenance(doc)
    root.insert(0, ET.Comment(
        f" fieldcal export of {prov['camera_id']}/{prov['session_id']} version {prov['version']} "
        f"({prov['method']}); fit residual {fit.fit_rms_px:.2g} px RMS, {fit.fit_max_px:.2g} px "
        f"max; round trip {fit.roundtrip_max_px:.2g} px max"
        + ("" if fit.exact else f" (> {EXACT_PX} px: not exact)") + " "))
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


@dataclass
class Export:
    """An export: the text to write and the fit behind it (None for JSON)."""

    format: str
    text: str
    fit: ModelFit | None

    @property
    def exact(self) -> bool:
        return self.fit is None or self.fit.exact

    def report_lines(self) -> list[str]:
        return [] if self.fit is None else self.fit.report_lines()


def export_text(calibration: Calibration | dict, fmt: str, *, model: str = "auto") -> Export:
    """The export of a calibration in ``fmt`` (one of :data:`FORMATS`).

    Parameters
    ----------
    calibration : Calibration or dict
        The calibration (or its document).
    fmt : str
        ``opencv`` (FileStorage YAML), ``colmap`` (cameras.txt), ``metashape`` (XML) or
        ``json`` (the calibration document itself).
    model : str
        OpenCV / COLMAP: ``auto`` or a key of :data:`OPENCV_MODELS` (COLMAP: ``brown4`` or
        ``rational8``).
    """
    cal = calibration if isinstance(calibration, Calibration) else Calibration.from_document(calibration)
    doc = cal.document
    if fmt not in FORMATS:
        raise InputError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}", "export")
    if fmt == "json":
        return Export(fmt, json.dumps(doc, indent=2) + "\n", None)
    if fmt == "metashape":
        fit = fit_metashape(cal.camera)
        return Export(fmt, metashape_xml(fit, doc), fit)
    if fmt == "colmap":
        if model not in ("auto",) + tuple(COLMAP_MODEL):
            raise InputError(f"COLMAP model must be auto, brown4 (OPENCV) or rational8 (FULL_OPENCV), "
                             f"got {model!r}", "export")
        fit = fit_opencv(cal.camera, model, candidates=AUTO["colmap"])
        fit.format = "colmap"
        return Export(fmt, colmap_cameras_txt(fit, doc), fit)
    fit = fit_opencv(cal.camera, model)
    return Export(fmt, opencv_yaml(fit, doc), fit)
