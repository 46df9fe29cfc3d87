"""Comparing two calibrations of one sensor: where the same ray lands.

For a pixel ``uv`` the calibration B gives a ray in its camera frame
(:func:`fieldcal.model.camera.unproject`); projecting that ray through calibration A gives the
pixel where A would have seen it. The difference ``uv_A(ray_B(uv)) - uv`` [px] over a grid
on the sensor is the correction-field difference of the two calibrations, in pixels,
independent of how the parameters are split between principal point and distortion.

Where the camera frame itself is not observable (a narrow field of view: a principal-
point shift and a small rotation of the camera are nearly indistinguishable), the best
common rotation of B's rays onto A's (Wahba's problem, solved by SVD) is removed first.

Is the change real? (:func:`compare_calibrations`)
--------------------------------------------------
The verdict is a family of tests (:mod:`fieldcal.analysis.change`): one per quantity both
calibrations observe (``f``, the principal point, the radial distortion at the edge of
the field) and the *map test* below over the correction field where both observe,
combined by Holm's procedure at the level ``alpha``.

The map test. Stack the difference map over the tested points as ``d``. To first order
``d = J (theta_A - theta_B)`` with the landing Jacobian ``J`` (2n, p) of
:func:`fieldcal.analysis.uncertainty.landing_jacobian` (a ray fixed in the camera frame:
where it lands moves with the parameters), evaluated once, at A, over the union of the
parameters either calibration estimated. If both measured the same camera with
independent errors, ``d ~ N(0, C)`` with

    C = J (Sigma_A + Sigma_B) J^T = M M^T,    M = J L,   L L^T = Sigma_A + Sigma_B

(the interior covariances, zero-padded to the union). ``C`` has rank ``r`` <= p, far
below 2n: the map is the parameter difference projected onto the sensor. (One Jacobian
for both matters: ``J_A`` and ``J_B`` differ slightly, and stacking both would add
spurious tiny singular values that a pseudo-inverse blows up.) With the SVD
``M = U S V^T`` truncated to the ``r`` directions that move the tested points by more
than ``min_sigma_px`` RMS (``s_k / sqrt(rows) > min_sigma_px``, default 1e-4 px), the
pseudo-inverse gives the statistic

    chi2 = d^T C^+ d = |S_r^-1 U_r^T d|^2    ~  chi-square with r degrees of freedom.

The floor matters: ``d`` is the exact difference, ``C`` its first-order covariance, and
in a direction that moves the points by 1e-5 px the second-order terms of a parameter
difference (1e-4 px between two goniometer sessions) are many "sigmas" -- with a
relative cut-off of 1e-7 such directions turned repeat sessions of one camera into
chi-square values of 60-6000 on 9 degrees of freedom. A change that small is far below
any measurement's accuracy. A part of ``d`` outside the kept directions
(``(I - U_r U_r^T) d``) is a change that neither calibration's uncertainty allows for; it
is reported as ``outside_px`` and makes the change significant when it exceeds
``outside_tol_px``. With ``remove_rotation`` both ``d`` and ``M`` are first projected onto
the fields that no common rotation explains
(:func:`fieldcal.analysis.uncertainty.remove_rotation_part`).

The verdict combines the tests (significant at level ``alpha``) with the size of the
change against a tolerance in the image plane (``tolerance_um``): a camera is *flagged*
when its change is both significant and larger than the tolerance. Sizes are always of
the tested region and in both units, ``px`` and ``um`` of the same numbers (``max_px``,
``max_um``, ``rms_px``, ``rms_um``); the map over the whole sensor (``diff_px``,
``sensor_max_px``) is for display.

A goniometer calibration observes only the two scanned axes of the sensor, and there only
the component along each axis, and not where the optical axis points (the arm's zero is
aligned on the sensor centre): its model off the axes is an extrapolation, and its split
between principal point and decentering is a convention of the method. When either
calibration is a goniometer's (``region="auto"``), the map test and the size of the change
use the points of the centre row (their u component) and of the centre column (their v
component) only, at the spot positions the goniometer measured (its sweeps do not reach
the sensor's edges), with the best common rotation removed; the map over the sensor is
kept for display.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from fieldcal.analysis.change import QuantityTest, holm, observed_quantities, quantity_tests
from fieldcal.analysis.uncertainty import (
    Calibration,
    landing_jacobian,
    rotation_jacobian,
    summarise_2x2,
)
from fieldcal.errors import InputError
from fieldcal.model.camera import PARAM_NAMES, Camera, project, unproject

__all__ = ["ray_difference_px", "best_rotation", "Comparison", "compare_calibrations", "judge", "check_level",
           "check_grid", "MAX_GRID",
           "combined_covariance", "DEFAULT_TOLERANCE_UM", "DEFAULT_ALPHA", "DEFAULT_MIN_SIGMA_PX"]

DEFAULT_TOLERANCE_UM = 2.0
"""Default tolerance of a change in the image plane [um] (about 0.4 px at 5.3 um pixels)."""
DEFAULT_ALPHA = 0.01
"""Default significance level of the change test (the family of tests, Holm)."""
DEFAULT_MIN_SIGMA_PX = 1e-4
"""Directions of the map test that move the tested points by less (RMS) are left out [px]."""


def best_rotation(a, b):
    """The rotation ``R`` (3, 3) minimising ``sum |R b_i - a_i|^2`` for unit vectors (n, 3)."""
    H = np.asarray(b, float).T @ np.asarray(a, float)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    return Vt.T @ np.diag([1.0, 1.0, d]) @ U.T


def ray_difference_px(cam_a: Camera, cam_b: Camera, uv_px=None, *, remove_rotation: bool = False,
                      grid: tuple[int, int] = (41, 31)):
    """Pixel displacement (n, 2) between where A and B map the same rays, over the sensor.

    Parameters
    ----------
    cam_a, cam_b : Camera
        Two calibrations of the same sensor.
    uv_px : (n, 2) array_like, optional
        Pixels to evaluate; default a ``grid`` (columns, rows) spanning the sensor.
    remove_rotation : bool
        Remove the best common rotation of B's camera frame onto A's first.

    Returns
    -------
    uv_px : (n, 2) ndarray
        The pixels evaluated.
    diff_px : (n, 2) ndarray
        ``uv_A(ray_B(uv)) - uv`` [px].
    """
    sa, sb = cam_a.sensor, cam_b.sensor
    if (sa.width_px, sa.height_px) != (sb.width_px, sb.height_px):
        raise InputError(f"the calibrations are of different sensors ({sa.width_px} x {sa.height_px} "
                         f"and {sb.width_px} x {sb.height_px} px)")
    uv = sa.grid_px(*grid) if uv_px is None else np.asarray(uv_px, float)
    ray_b = unproject(uv, cam_b)
    if remove_rotation:
        R = best_rotation(unproject(uv, cam_a), ray_b)
        ray_b = ray_b @ R.T
    uv_a = project(ray_b, np.eye(3), np.zeros(3), cam_a)
    return uv, uv_a - uv


# --------------------------------------------------------------------------------------
# the change test
# --------------------------------------------------------------------------------------
@dataclass
class Comparison:
    """Two calibrations of one sensor compared (see the module docstring).

    Attributes
    ----------
    version_a, version_b : str
        ``a`` is the reference (e.g. the older), ``b`` the other.
    grid : (nx, ny)
    uv_px : (n, 2) ndarray
        The grid pixels, row by row.
    diff_px : (n, 2) ndarray
        ``uv_A(ray_B(uv)) - uv`` [px] over the whole sensor (display; rotation removed with
        ``remove_rotation``).
    sigma_px : (n,) ndarray
        1-sigma (semi-major axis) of the difference at each pixel that the two
        calibrations' uncertainties explain [px].
    chi2, dof, map_p_value : float, int, float
        The map test of the module docstring.
    p_value : float
        The family's: the smallest Holm-adjusted p-value of :attr:`tests`.
    outside_px : float
        Largest norm of the part of the map outside the range of its covariance [px].
    pixel_size_um, tolerance_um, alpha : float
    remove_rotation : bool
    region : {"sensor", "axes"}
        Where the map was tested and the change measured.
    max_px, rms_px : float
        Largest and RMS change where tested [px] (``|d|`` per point over the sensor; the
        along-axis component at the goniometer's spots, rotation removed, for ``axes``).
    tests : tuple of QuantityTest
        One per quantity (:mod:`fieldcal.analysis.change`), the map test last.
    left_out : tuple of str
        What the comparison does not test, and why.
    """

    version_a: str
    version_b: str
    method_a: str
    method_b: str
    grid: tuple[int, int]
    uv_px: np.ndarray
    diff_px: np.ndarray
    sigma_px: np.ndarray
    chi2: float
    dof: int
    map_p_value: float
    p_value: float
    outside_px: float
    pixel_size_um: float
    tolerance_um: float
    alpha: float
    outside_tol_px: float
    remove_rotation: bool
    region: str
    max_px: float
    rms_px: float
    tests: tuple = field(default_factory=tuple)
    left_out: tuple = field(default_factory=tuple)

    @property
    def norm_px(self) -> np.ndarray:
        """``|d|`` (n,) over the whole sensor [px] (display)."""
        return np.hypot(self.diff_px[:, 0], self.diff_px[:, 1])

    @property
    def sensor_max_px(self) -> float:
        """Largest ``|d|`` over the whole sensor [px]; for a goniometer partly an extrapolation."""
        return float(self.norm_px.max())

    @property
    def max_um(self) -> float:
        """:attr:`max_px` in the image plane [um]."""
        return self.max_px * self.pixel_size_um

    @property
    def rms_um(self) -> float:
        """:attr:`rms_px` in the image plane [um]."""
        return self.rms_px * self.pixel_size_um

    @property
    def where(self) -> str:
        return ("along the scanned axes, at the measured spots, pointing removed"
                if self.region == "axes" else "over the sensor"
                + (", common rotation removed" if self.remove_rotation else ""))

    def _judged(self) -> dict:
        return judge(self.record(), self.tolerance_um, self.alpha)

    @property
    def changed(self) -> list[str]:
        """Keys of the quantities that changed significantly (Holm, level ``alpha``)."""
        return self._judged()["changed"]

    @property
    def significant(self) -> bool:
        return self._judged()["significant"]

    @property
    def exceeds_tolerance(self) -> bool:
        return self._judged()["exceeds_tolerance"]

    @property
    def flagged(self) -> bool:
        """Significant and larger than the tolerance."""
        return self._judged()["flagged"]

    @property
    def verdict(self) -> str:
        return self._judged()["verdict"]

    def record(self) -> dict:
        """What the change test found, independent of ``alpha`` and ``tolerance_um``: the
        figures :func:`judge` turns into a verdict at any level and tolerance (the lake's
        ``comparisons`` table stores it)."""
        d = {k: getattr(self, k) for k in (
            "version_a", "version_b", "method_a", "method_b", "region", "where", "chi2", "dof",
            "map_p_value", "p_value", "outside_px", "outside_tol_px", "max_px", "max_um", "rms_px",
            "rms_um", "pixel_size_um", "sensor_max_px")}
        d.update(grid=list(self.grid), tests=[t.to_dict() for t in self.tests], left_out=list(self.left_out))
        return d

    def summary(self) -> dict:
        """Scalars for tables and JSON."""
        d = {k: getattr(self, k) for k in (
            "version_a", "version_b", "method_a", "method_b", "chi2", "dof", "map_p_value",
            "p_value", "outside_px", "pixel_size_um", "tolerance_um", "alpha", "outside_tol_px",
            "remove_rotation", "region", "max_px", "rms_px")}
        d.update(grid=list(self.grid), max_um=self.max_um, rms_um=self.rms_um,
                 sensor_max_px=self.sensor_max_px, max_sigma_px=float(self.sigma_px.max()),
                 significant=self.significant, exceeds_tolerance=self.exceeds_tolerance,
                 flagged=self.flagged, changed=self.changed, verdict=self.verdict,
                 tests=[t.to_dict() for t in self.tests], left_out=list(self.left_out))
        return d


def check_level(tolerance_um: float, alpha: float) -> None:
    """Refuse a tolerance that is not positive or a level outside (0, 1) (:class:`InputError`)."""
    _check(tolerance_um, alpha, "auto", 0.0)


def judge(record: dict, tolerance_um: float, alpha: float) -> dict:
    """The verdict of a change test's :meth:`Comparison.record` at level ``alpha`` and tolerance.

    Returns ``significant`` (the family's Holm-adjusted p-value below ``alpha``, or a change
    outside the explained range), ``exceeds_tolerance`` (largest change where tested above
    ``tolerance_um``), ``flagged`` (both), ``changed`` (keys of the quantities whose own
    adjusted p-value is below ``alpha``) and ``verdict`` (one line).
    """
    check_level(tolerance_um, alpha)
    outside = record["outside_px"] > record["outside_tol_px"]
    significant = bool(record["p_value"] < alpha or outside)
    exceeds = bool(record["max_um"] > tolerance_um)
    changed = [t["key"] for t in record.get("tests", ()) if t["p_adjusted"] < alpha]
    size = (f"largest change {record['max_um']:.3g} µm ({record['max_px']:.3g} px) {record['where']}, "
            f"{'>' if exceeds else '≤'} tolerance {tolerance_um:g} µm")
    if outside:
        why = (f"changed where neither calibration has any uncertainty "
               f"({record['outside_px']:.3g} px outside the explained range)")
    elif significant:
        why = f"significant change in {', '.join(changed)} (p = {record['p_value']:.2g} < {alpha:g}, Holm)"
    else:
        why = f"no significant change (p = {record['p_value']:.2g} ≥ {alpha:g}, Holm)"
    flagged = significant and exceeds
    return {"significant": significant, "exceeds_tolerance": exceeds, "flagged": flagged, "changed": changed,
            "verdict": f"{why}; {size}" + ("; FLAGGED" if flagged else "")}


def _sqrt_psd(cov):
    """``L`` with ``L L^T = cov`` for a symmetric positive semi-definite matrix.

    Factored as ``D sqrt(R)`` with ``D`` the standard deviations and ``R`` the correlation
    matrix: the parameters' variances span 25 orders of magnitude (``f`` in mm^2, ``k3``
    in mm^-12), and an eigendecomposition of ``cov`` itself loses the small eigenvalues
    (a direction of a 6-image field calibration came out as exactly zero).
    """
    cov = 0.5 * (cov + cov.T)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    scale = np.where(sd > 0, sd, 1.0)
    w, V = np.linalg.eigh(cov / np.outer(scale, scale))
    return (V * np.sqrt(np.clip(w, 0.0, None))) * scale[:, None]


def combined_covariance(a: Calibration, b: Calibration):
    """``Sigma_A + Sigma_B`` over the union of their estimated parameters (PARAM_NAMES order)."""
    names = [n for n in PARAM_NAMES if n in a.names or n in b.names]
    pos = {n: i for i, n in enumerate(names)}
    cov = np.zeros((len(names), len(names)))
    for c in (a, b):
        idx = [pos[n] for n in c.names]
        cov[np.ix_(idx, idx)] += c.covariance
    return names, cov


def _swept_points(*cals):
    """The spot positions of a goniometer calibration's frames and the component each tests.

    Returns ``(uv (n, 2), rows)`` with ``rows`` indexing the stacked ``(du, dv)`` vector: the
    u component of the x sweep's points, the v component of the y sweep's; None if no
    calibration lists its frames.
    """
    for cal in cals:
        if cal.method != "goniometer":
            continue
        frames = [im for im in cal.document.get("images", [])
                  if im.get("axis") in ("x", "y") and im.get("u_px") is not None and im.get("v_px") is not None]
        if len(frames) >= 3:
            uv = np.array([(im["u_px"], im["v_px"]) for im in frames], dtype=float)
            uv, first = np.unique(uv, axis=0, return_index=True)
            comp = np.array([0 if frames[i]["axis"] == "x" else 1 for i in first])
            return uv, 2 * np.arange(len(uv)) + comp
    return None


def _axis_points(sensor, grid):
    """Pixels of the centre row (nx) and centre column (ny), and the stacked rows tested."""
    nx, ny = grid
    u = np.linspace(0.0, sensor.width_px - 1.0, nx)
    v = np.linspace(0.0, sensor.height_px - 1.0, ny)
    uv = np.concatenate([np.stack([u, np.full(nx, (sensor.height_px - 1) / 2.0)], axis=1),
                         np.stack([np.full(ny, (sensor.width_px - 1) / 2.0), v], axis=1)])
    rows = np.concatenate([2 * np.arange(nx), 2 * (nx + np.arange(ny)) + 1])
    return uv, rows


def _project_out(basis, X):
    """``X`` without its least-squares part in the span of ``basis`` (columns)."""
    Q, _ = np.linalg.qr(basis)
    return X - Q @ (Q.T @ X)


@dataclass
class _MapTest:
    uv: np.ndarray          # (n, 2) grid
    diff: np.ndarray        # (n, 2) over the grid
    sigma: np.ndarray       # (n,) over the grid
    d_t: np.ndarray         # tested components (rows,)
    M_t: np.ndarray         # (rows, p)
    per_point: int          # components per tested point (1 along axes, 2 over the sensor)


def _midpoint(a: Calibration, b: Calibration, uv):
    """The camera halfway between A and B and where B's rays through ``uv`` land in it."""
    cam_m = Camera(a.sensor, 0.5 * (a.camera.params + b.camera.params))
    return cam_m, project(unproject(uv, b.camera), np.eye(3), np.zeros(3), cam_m)


def _map(a: Calibration, b: Calibration, names, L, grid, region, remove_rotation) -> _MapTest:
    """The difference map over the grid and the tested components with their ``M``.

    ``M`` is linearised halfway between the two calibrations, at the pixels where the
    rays land there: the exact map then differs from ``J (theta_A - theta_B)`` by third-order
    terms only (1.8e-6 px instead of 0.04 px for two 6-image field calibrations whose maps
    differ by 29 px), so that the statistic does not mistake curvature for change.
    """
    uv, d = ray_difference_px(a.camera, b.camera, remove_rotation=remove_rotation, grid=grid)
    n = len(uv)
    cam_m, uv_m = _midpoint(a, b, uv)
    M = landing_jacobian(cam_m, uv_m, names).reshape(2 * n, len(names)) @ L
    dv = d.reshape(2 * n)
    if remove_rotation:
        R = rotation_jacobian(cam_m, uv_m).reshape(-1, 3)
        M, dv = _project_out(R, M), _project_out(R, dv)
    Mp = M.reshape(n, 2, -1)
    sigma = summarise_2x2(np.einsum("nik,njk->nij", Mp, Mp))
    if region != "axes":
        return _MapTest(uv, dv.reshape(n, 2), sigma, dv, M, 2)
    uv_t, rows = _swept_points(a, b) or _axis_points(a.sensor, grid)
    _, d_t = ray_difference_px(a.camera, b.camera, uv_t)
    cam_m, uv_tm = _midpoint(a, b, uv_t)
    R = rotation_jacobian(cam_m, uv_tm).reshape(-1, 3)[rows]
    dv_t = _project_out(R, d_t.reshape(-1)[rows])
    M_t = _project_out(R, (landing_jacobian(cam_m, uv_tm, names).reshape(-1, len(names)) @ L)[rows])
    return _MapTest(uv, dv.reshape(n, 2), sigma, dv_t, M_t, 1)


def _map_test(m: _MapTest, rcond: float, min_sigma_px: float):
    """``(chi2, r, p, outside_px, max_px, rms_px)`` of the map test (module docstring)."""
    rows = m.d_t.size
    U, s, _ = np.linalg.svd(m.M_t, full_matrices=False)
    s_max = s[0] if s.size and s[0] > 0 else 1.0
    keep = (s > rcond * s_max) & (s / np.sqrt(max(rows, 1)) > min_sigma_px)
    r = int(keep.sum())
    z = (U[:, keep].T @ m.d_t) / s[keep]
    chi2 = float(z @ z)
    outside = m.d_t - U[:, keep] @ (U[:, keep].T @ m.d_t)
    size = (np.abs(m.d_t) if m.per_point == 1 else np.hypot(*m.d_t.reshape(-1, 2).T))
    out_size = (np.abs(outside) if m.per_point == 1 else np.hypot(*outside.reshape(-1, 2).T))
    p = float(stats.chi2.sf(chi2, r)) if r > 0 else 1.0
    return (chi2, r, p, float(out_size.max()) if out_size.size else 0.0,
            float(size.max()) if size.size else 0.0,
            float(np.sqrt(np.mean(size**2))) if size.size else 0.0)


MAX_GRID = 1000
"""Points of the comparison grid along each axis, at most (more is no better map, only memory)."""


def check_grid(grid) -> tuple[int, int]:
    """``(nx, ny)`` checked: two integers in 2..:data:`MAX_GRID` (:class:`InputError` otherwise)."""
    try:
        nx, ny = (int(g) for g in grid)
    except (TypeError, ValueError):
        raise InputError(f"grid must be two integers (nx, ny), got {grid!r}", "compare") from None
    if not (2 <= nx <= MAX_GRID and 2 <= ny <= MAX_GRID):
        raise InputError(f"grid must have 2 to {MAX_GRID} points along each axis, got {nx} x {ny}", "compare")
    return nx, ny


def _check(tolerance_um, alpha, region, min_sigma_px) -> None:
    if not (0 < tolerance_um < math.inf):
        raise InputError(f"tolerance_um must be positive and finite, got {tolerance_um}", "compare")
    if not (0 < alpha < 1):
        raise InputError(f"alpha must be in (0, 1), got {alpha}", "compare")
    if region not in ("auto", "sensor", "axes"):
        raise InputError(f"region must be 'auto', 'sensor' or 'axes', got {region!r}", "compare")
    if not (min_sigma_px >= 0):
        raise InputError(f"min_sigma_px must be >= 0, got {min_sigma_px}", "compare")


def compare_calibrations(a: Calibration, b: Calibration, *, grid: tuple[int, int] = (41, 31),
                         tolerance_um: float = DEFAULT_TOLERANCE_UM, alpha: float = DEFAULT_ALPHA,
                         remove_rotation: bool = False, rcond: float = 1e-9,
                         min_sigma_px: float = DEFAULT_MIN_SIGMA_PX, outside_tol_px: float = 0.01,
                         region: str = "auto") -> Comparison:
    """Where the same rays land in two calibrations, and whether the camera changed.

    Parameters
    ----------
    a, b : Calibration
        Two calibrations of the same sensor (``a`` the reference). Either method.
    grid : (nx, ny)
        Grid of pixels spanning the sensor corner to corner.
    tolerance_um : float
        Largest acceptable change in the image plane [um].
    alpha : float
        Significance level of the family of tests (Holm).
    remove_rotation : bool
        Remove the best common rotation first (:func:`ray_difference_px`).
    rcond : float
        Singular values of ``M`` below ``rcond * s_max`` count as zero (numerical rank).
    min_sigma_px : float
        Directions of the map test that move the tested points by less, RMS, are left out
        [px] (module docstring).
    outside_tol_px : float
        A change outside the range of the covariance larger than this [px] is significant.
    region : {"auto", "sensor", "axes"}
        Where the map is tested: the whole grid, or the scanned axes of a goniometer
        (module docstring); ``"auto"`` picks ``"axes"`` when either is a goniometer's.

    Returns
    -------
    Comparison
    """
    _check(tolerance_um, alpha, region, min_sigma_px)
    grid = check_grid(grid)
    if region == "auto":
        region = "axes" if "goniometer" in (a.method, b.method) else "sensor"
    remove_rotation = remove_rotation or region == "axes"
    names, cov = combined_covariance(a, b)
    m = _map(a, b, names, _sqrt_psd(cov), grid, region, remove_rotation)
    chi2, r, p_map, outside_px, max_px, rms_px = _map_test(m, rcond, min_sigma_px)
    keys, left_out = observed_quantities(a, b)
    where = ("along the scanned axes" if region == "axes" else "over the sensor")
    map_test = QuantityTest("map", f"correction field {where}", "px", (max_px,),
                            (float(m.sigma.max()),), chi2, r, p_map)
    tests = quantity_tests(a, b, names, cov, keys) + [map_test]
    adjusted = holm([t.p_value for t in tests])
    tests = tuple(replace(t, p_adjusted=float(q)) for t, q in zip(tests, adjusted, strict=True))
    return Comparison(a.version, b.version, a.method, b.method, tuple(grid), m.uv, m.diff,
                      m.sigma, chi2, r, p_map, float(adjusted.min()), outside_px,
                      float(a.sensor.pixel_size_um), float(tolerance_um), float(alpha),
                      float(outside_tol_px), bool(remove_rotation), region, max_px, rms_px,
                      tests, tuple(left_out))
