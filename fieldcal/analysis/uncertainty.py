r"""How precisely a calibration places a ray on the sensor: covariance propagation.

A calibration (docs/conventions.md section 4) maps a ray, fixed in the camera frame, to the pixel
where the camera sees it. Its interior parameters ``theta`` (the estimated subset of
:data:`fieldcal.model.camera.PARAM_NAMES`) carry an a-posteriori covariance ``Sigma``; this
module propagates it to that pixel.

Landing Jacobian
----------------
Let a ray have the ideal image point ``q = f (a, b)`` (its direction ``(a, b, -1)`` in the
camera frame is fixed, so ``q`` scales with ``f``). The measured point ``x'`` where the
ray lands solves ``correct(x'; theta) = q(theta)`` (:func:`fieldcal.model.camera.correct`).
Differentiating both sides,

    G dx' + Q dtheta = (q / f) df          =>     dx'/dtheta = G^-1 (e_f q / f - Q)

with ``G = dq/dx'`` and ``Q = dq/dtheta`` at fixed ``x'`` (both from
:func:`fieldcal.model.camera.correct_jacobian`) and ``e_f`` selecting the ``f`` column. In
pixels ``du = dx / d``, ``dv = -dy / d`` (docs/conventions.md section 1). :func:`landing_jacobian`
returns this ``J`` (n, 2, p) [px per parameter unit]; it is checked against central
differences of :func:`fieldcal.model.camera.project` in the tests.

Projection uncertainty
----------------------
The 2 x 2 covariance of the landing pixel is ``C = J Sigma J^T``. Its 1-sigma size is
reported as the semi-major axis of the 1-sigma ellipse, ``sqrt(lambda_max(C))``
("worst direction", the default) or as ``sqrt(trace C)`` (the RMS radial error).
``Sigma`` is the marginal covariance of the interior parameters: the field method's
exterior orientations and targets are integrated out (their correlation with the
principal point is part of the principal point's sigma), the goniometer method gives its
13 x 13 covariance directly.

Without the camera rotation
---------------------------
Part of that uncertainty moves every ray the way a small rotation of the camera would
(a principal-point shift on a long lens is nearly that); in any use of the calibration
the exterior orientation absorbs it. :func:`rotation_jacobian` gives the landing shift
per small rotation ``omega`` of the camera frame, ``R(uv)`` (n, 2, 3) [px/rad], and
:func:`remove_rotation_part` the projection of a displacement field over a grid onto the
fields no common rotation explains (least squares over the grid). With
``remove_rotation=True`` :func:`uncertainty_map` propagates the covariance of that
projected field: what is left is the calibration's *shape* uncertainty, which shows where
the data were thin.

Does the region cover the truth?
--------------------------------
:func:`within_region` says whether landing errors lie inside the ``n_sigma`` region of
their 2 x 2 covariances: the ellipse ``e^T C^-1 e <= k^2`` that holds the probability of
``+-n_sigma`` in one dimension (95.45 % for 2 sigma: ``k = 2.486``, the 0.9545 quantile of
chi-square with 2 degrees of freedom). (The circle of radius ``n_sigma`` times the
semi-major axis, which the maps draw, holds between 86.5 % (a round ellipse) and 95.45 % (a
flat one); ``what="circle"`` tests that.) :func:`coverage_fraction` is the fraction of a
grid where the true error of a calibration lies inside its region: the issue's measure of
honest uncertainty (docs/uncertainty.md).

Distortion curves
-----------------
:func:`radial_curve` and :func:`decentering_curve` give Brown's radial correction
``dr(r) = r (k0 + k1 r^2 + k2 r^4 + k3 r^6)`` and the decentering profile
``P(r) = sqrt(p1^2 + p2^2) r^2`` with their 1-sigma from the covariance (first order).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2, norm

from fieldcal.errors import InputError, LakeError
from fieldcal.model.camera import (
    INDEX,
    K0,
    K1,
    K2,
    K3,
    P1,
    P2,
    PARAM_NAMES,
    Camera,
    F,
    Sensor,
    correct_jacobian,
    project,
    unproject,
)

__all__ = ["Calibration", "interior_covariance", "landing_jacobian", "rotation_jacobian",
           "remove_rotation_part", "landing_covariance", "summarise_2x2", "projection_uncertainty_px",
           "uncertainty_map", "radial_curve", "decentering_curve", "UNCERTAINTY_WHAT", "within_region",
           "coverage_fraction"]

UNCERTAINTY_WHAT = ("worst", "rms")
"""How a 2 x 2 landing covariance is summarised: semi-major axis, or sqrt of the trace."""


# --------------------------------------------------------------------------------------
# a calibration with its interior covariance
# --------------------------------------------------------------------------------------
def interior_covariance(names, covariance, *, where: str = "covariance"):
    """The interior block of a stored covariance: (estimated names, (p, p) matrix).

    Parameters
    ----------
    names : sequence of str
        Labels of the rows of ``covariance`` (the Zarr attribute ``names``): the field
        method's reduced block starts with the estimated interior parameters and continues
        with exterior unknowns (``"<image>:w_x"`` ...); the goniometer's is the 13
        parameters with NaN rows for those not estimated.
    covariance : (n, n) array_like
        A-posteriori covariance, parameter units of :data:`fieldcal.model.camera.PARAM_NAMES`.

    Returns
    -------
    names : tuple of str
        The camera parameters with a finite variance, in :data:`PARAM_NAMES` order.
    cov : (p, p) ndarray
    """
    cov = np.asarray(covariance, dtype=float)
    labels = [str(n) for n in names]
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1] or cov.shape[0] != len(labels):
        raise InputError(f"covariance of shape {cov.shape} does not match its {len(labels)} names",
                         where)
    pos = {n: i for i, n in enumerate(labels)}
    keep = [n for n in PARAM_NAMES if n in pos and np.isfinite(cov[pos[n], pos[n]])]
    idx = [pos[n] for n in keep]
    block = cov[np.ix_(idx, idx)]
    if not np.all(np.isfinite(block)):
        raise InputError("the interior covariance has non-finite entries", where)
    return tuple(keep), 0.5 * (block + block.T)


@dataclass(frozen=True)
class Calibration:
    """A calibration document with its camera and the interior covariance.

    Attributes
    ----------
    document : dict
        The calibration document (docs/conventions.md section 4).
    camera : Camera
    names : tuple of str
        The estimated parameters (rows of ``covariance``), in :data:`PARAM_NAMES` order.
    covariance : (p, p) ndarray
        Their a-posteriori covariance [parameter units].
    covariance_source : str
        ``"covariance"`` (the stored matrix) or ``"sigmas"`` (the document's sigmas only,
        correlations unknown: a version stored without its covariance).
    """

    document: dict
    camera: Camera
    names: tuple[str, ...]
    covariance: np.ndarray
    covariance_source: str = "covariance"
    arrays: dict = field(default_factory=dict, repr=False)
    array_attrs: dict = field(default_factory=dict, repr=False)

    @property
    def version(self) -> str:
        return str(self.document.get("version") or "")

    @property
    def method(self) -> str:
        return str(self.document.get("method"))

    @property
    def sensor(self) -> Sensor:
        return self.camera.sensor

    def label(self) -> str:
        d = self.document
        return f"{d.get('camera_id')}/{d.get('session_id')} {self.version} ({self.method})"

    @classmethod
    def from_document(cls, document: dict, names=None, covariance=None, arrays=None,
                      array_attrs=None) -> Calibration:
        """From a document and optionally a stored covariance (``names`` labels its rows)."""
        where = f"calibration {document.get('camera_id')}/{document.get('version')}"
        try:
            s = document["sensor"]
            sensor = Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"]))
            camera = Camera(sensor, np.array([float(document["parameters"][n]) for n in PARAM_NAMES]))
            sigma = document["sigma"]
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"not a calibration document ({e})", where) from None
        if covariance is not None and names is not None:
            keep, cov = interior_covariance(names, covariance, where=where)
            source = "covariance"
        else:
            keep = tuple(n for n in PARAM_NAMES if sigma.get(n) is not None)
            cov = np.diag([float(sigma[n]) ** 2 for n in keep])
            source = "sigmas"
        return cls(document, camera, keep, cov, source, dict(arrays or {}), dict(array_attrs or {}))

    @classmethod
    def from_lake(cls, lake, version: str) -> Calibration:
        """A committed version of a lake (:class:`fieldcal.lake.store.Lake`): document and arrays."""
        doc = lake.load_document(version)
        group = lake.open_zarr(version)
        arrays, attrs = {}, {}
        try:
            for name in group.attrs.get("arrays", []):
                arrays[name] = np.asarray(group[name][...])
                attrs[name] = dict(group[name].attrs)
        except (KeyError, OSError) as e:
            raise LakeError(f"cannot read the arrays of version {version}: {e}") from None
        cov = arrays.get("covariance")
        names = attrs.get("covariance", {}).get("names")
        return cls.from_document(doc, names, cov, arrays, attrs)

    def sigma_of(self, name: str) -> float | None:
        if name not in self.names:
            return None
        i = self.names.index(name)
        return float(np.sqrt(max(self.covariance[i, i], 0.0)))

    def correlation(self) -> np.ndarray:
        """The correlation matrix of ``names`` (p, p)."""
        sd = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = self.covariance / np.outer(sd, sd)
        corr[~np.isfinite(corr)] = 0.0
        np.fill_diagonal(corr, 1.0)
        return corr


# --------------------------------------------------------------------------------------
# the landing Jacobian and covariance
# --------------------------------------------------------------------------------------
def _columns(names) -> list[int]:
    cols = []
    for n in names:
        if n not in INDEX:
            raise InputError(f"unknown camera parameter {n!r}; allowed: {list(PARAM_NAMES)}",
                             "landing_jacobian")
        cols.append(INDEX[n])
    return cols


def landing_jacobian(camera: Camera, uv_px, names=PARAM_NAMES):
    """How the pixel where a fixed ray lands moves with the parameters (module docstring).

    Parameters
    ----------
    camera : Camera
    uv_px : (n, 2) array_like
        Where the rays land now [px].
    names : sequence of str
        The parameters (columns), default all 13.

    Returns
    -------
    (n, 2, p) ndarray
        ``d(u, v) / d(theta)`` [px per parameter unit].
    """
    cols = _columns(names)
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    s = camera.sensor
    d = s.pixel_mm
    q, G, Q = correct_jacobian(s.pixel_to_mm(uv), camera.params, columns=cols)
    rhs = -Q
    for j, c in enumerate(cols):
        if c == F:
            rhs[:, :, j] += q / camera.f_mm
    dxy = np.linalg.solve(G, rhs)                      # (n, 2, p) [mm per unit]
    dxy[:, 0, :] /= d
    dxy[:, 1, :] /= -d
    return dxy


def rotation_jacobian(camera: Camera, uv_px):
    """Landing shift (n, 2, 3) [px/rad] of the rays through ``uv_px`` per small camera rotation.

    A rotation ``omega`` (a rotation vector in the camera frame) turns a ray ``r`` into
    ``r + omega x r``; ``q = -f (X/Z, Y/Z)`` then moves by ``dq/dr (-[r]_x) omega`` and the
    measured point by ``G^-1 dq``.
    """
    uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
    s = camera.sensor
    q, G, _ = correct_jacobian(s.pixel_to_mm(uv), camera.params, columns=[])
    f = camera.f_mm
    r = np.concatenate([q, np.full((len(q), 1), -f)], axis=1)        # (X, Y, Z), Z = -f
    X, Y, Z = r[:, 0], r[:, 1], r[:, 2]
    zero = np.zeros_like(X)
    dq_dr = -f * np.stack([np.stack([1 / Z, zero, -X / Z**2], -1),
                           np.stack([zero, 1 / Z, -Y / Z**2], -1)], -2)  # (n, 2, 3)
    skew = np.stack([np.stack([zero, -Z, Y], -1), np.stack([Z, zero, -X], -1),
                     np.stack([-Y, X, zero], -1)], -2)                  # [r]_x
    dxy = np.linalg.solve(G, dq_dr @ (-skew))
    dxy[:, 0, :] /= s.pixel_mm
    dxy[:, 1, :] /= -s.pixel_mm
    return dxy


def remove_rotation_part(camera: Camera, uv_px, fields):
    """Displacement fields without their best common-rotation part (least squares).

    Parameters
    ----------
    camera : Camera
    uv_px : (n, 2) array_like
        The grid the fields are sampled on.
    fields : (2n,) or (2n, k) array_like
        Stacked displacement fields [px] (``(du_0, dv_0, du_1, ...)``).

    Returns
    -------
    ndarray like ``fields``
        ``P fields`` with ``P = I - R (R^T R)^-1 R^T``, ``R`` (2n, 3) the stacked
        :func:`rotation_jacobian` (applied through a QR factor, never formed).
    """
    R = rotation_jacobian(camera, uv_px).reshape(-1, 3)
    Q, _ = np.linalg.qr(R)
    X = np.asarray(fields, dtype=float)
    return X - Q @ (Q.T @ X)


def landing_covariance(camera: Camera, uv_px, names, covariance):
    """The 2 x 2 covariance (n, 2, 2) [px^2] of where the rays through ``uv_px`` land."""
    cov = np.asarray(covariance, dtype=float)
    if cov.shape != (len(names), len(names)):
        raise InputError(f"covariance of shape {cov.shape} for {len(names)} parameters",
                         "landing_covariance")
    J = landing_jacobian(camera, uv_px, names)
    return np.einsum("nip,pq,njq->nij", J, cov, J)


def summarise_2x2(C, what: str = "worst"):
    """1-sigma size (n,) [px] of 2 x 2 covariances: semi-major axis or sqrt(trace)."""
    C = np.asarray(C, dtype=float)
    if what == "rms":
        return np.sqrt(np.clip(C[..., 0, 0] + C[..., 1, 1], 0.0, None))
    if what != "worst":
        raise InputError(f"what must be one of {', '.join(UNCERTAINTY_WHAT)}, got {what!r}",
                         "projection_uncertainty")
    a, b, c = C[..., 0, 0], C[..., 0, 1], C[..., 1, 1]
    lam = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
    return np.sqrt(np.clip(lam, 0.0, None))


def projection_uncertainty_px(calibration: Calibration, uv_px, *, what: str = "worst"):
    """1-sigma uncertainty (n,) [px] of where the rays through ``uv_px`` land."""
    C = landing_covariance(calibration.camera, uv_px, calibration.names, calibration.covariance)
    return summarise_2x2(C, what)


def uncertainty_map(calibration: Calibration, grid: tuple[int, int] = (41, 31), *,
                    what: str = "worst", remove_rotation: bool = False):
    """The projection uncertainty over a grid spanning the sensor corner to corner.

    With ``remove_rotation`` the part of the uncertainty that a common rotation of the
    camera frame explains is removed first (module docstring).

    Returns
    -------
    grid_u_px : (nx,) ndarray
    grid_v_px : (ny,) ndarray
    sigma_px : (ny, nx) ndarray
        1-sigma [px] (``what``: see :func:`summarise_2x2`).
    """
    nx, ny = grid
    s = calibration.sensor
    uv = s.grid_px(nx, ny)
    if not remove_rotation:
        sig = projection_uncertainty_px(calibration, uv, what=what)
    else:
        J = landing_jacobian(calibration.camera, uv, calibration.names)     # (n, 2, p)
        n, _, p = J.shape
        Jp = remove_rotation_part(calibration.camera, uv, J.reshape(2 * n, p)).reshape(n, 2, p)
        C = np.einsum("nip,pq,njq->nij", Jp, calibration.covariance, Jp)
        sig = summarise_2x2(C, what)
    return uv[:nx, 0].copy(), uv[::nx, 1].copy(), sig.reshape(ny, nx)


# --------------------------------------------------------------------------------------
# does the region cover the truth?
# --------------------------------------------------------------------------------------
def within_region(error_px, C, n_sigma: float = 2.0, *, what: str = "ellipse"):
    """Whether each 2-D error lies in the ``n_sigma`` region of its covariance (module docstring).

    Parameters
    ----------
    error_px : (n, 2) array_like
        Errors [px].
    C : (n, 2, 2) array_like
        Their covariances [px^2].
    n_sigma : float
    what : {"ellipse", "circle"}
        The ellipse holding the one-dimensional ``+-n_sigma`` probability, or the circle of
        radius ``n_sigma`` semi-major axes.

    Returns
    -------
    (n,) bool ndarray
    """
    e = np.asarray(error_px, float).reshape(-1, 2)
    C = np.asarray(C, float).reshape(-1, 2, 2)
    if what == "circle":
        return np.hypot(e[:, 0], e[:, 1]) <= n_sigma * summarise_2x2(C, "worst")
    if what != "ellipse":
        raise InputError(f"what must be 'ellipse' or 'circle', got {what!r}", "within_region")
    k2 = chi2.ppf(1.0 - 2.0 * norm.sf(n_sigma), 2)
    a, b, c = C[:, 0, 0], 0.5 * (C[:, 0, 1] + C[:, 1, 0]), C[:, 1, 1]
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        m2 = (c * e[:, 0] ** 2 - 2 * b * e[:, 0] * e[:, 1] + a * e[:, 1] ** 2) / det
    return np.where(det > 0, m2 <= k2, np.hypot(e[:, 0], e[:, 1]) == 0)


def coverage_fraction(calibration: Calibration, truth: Camera, grid: tuple[int, int] = (21, 15), *,
                      n_sigma: float = 2.0, what: str = "ellipse") -> float:
    """Fraction of a sensor grid where the true landing error lies in its ``n_sigma`` region.

    The error at pixel ``uv`` is where the calibration lands the ray that the ``truth``
    camera sees at ``uv``, minus ``uv`` (a ray fixed in the camera frame; both cameras of
    one sensor); the region is that of :func:`landing_covariance` at ``uv``
    (:func:`within_region`).
    """
    s = calibration.sensor
    uv = s.grid_px(*grid)
    rays = unproject(uv, truth)
    e = project(rays, np.eye(3), np.zeros(3), calibration.camera) - uv
    C = landing_covariance(calibration.camera, uv, calibration.names, calibration.covariance)
    return float(np.mean(within_region(e, C, n_sigma, what=what)))


# --------------------------------------------------------------------------------------
# distortion curves
# --------------------------------------------------------------------------------------
def _block(calibration: Calibration, which):
    """Indices into ``names`` of the estimated parameters among ``which`` and their columns."""
    pos = [i for i, n in enumerate(calibration.names) if INDEX[n] in which]
    cols = [which.index(INDEX[calibration.names[i]]) for i in pos]
    return pos, cols


def radial_curve(calibration: Calibration, r_mm):
    """Radial correction ``dr(r)`` (n,) [mm] and its 1-sigma (n,) [mm] (module docstring)."""
    r = np.asarray(r_mm, dtype=float)
    p = calibration.camera.params
    which = [K0, K1, K2, K3]
    basis = np.stack([r, r**3, r**5, r**7], axis=-1)
    value = basis @ p[which]
    pos, cols = _block(calibration, which)
    g = basis[..., cols]
    cov = calibration.covariance[np.ix_(pos, pos)]
    sigma = np.sqrt(np.clip(np.einsum("...i,ij,...j->...", g, cov, g), 0.0, None))
    return value, sigma


def decentering_curve(calibration: Calibration, r_mm):
    """Decentering profile ``P(r)`` (n,) [mm] and its first-order 1-sigma (n,) [mm]."""
    r = np.asarray(r_mm, dtype=float)
    p = calibration.camera.params
    which = [P1, P2]
    pp = p[which]
    norm = float(np.hypot(*pp))
    value = norm * r**2
    pos, cols = _block(calibration, which)
    cov = calibration.covariance[np.ix_(pos, pos)]
    if norm > 0:
        u = (pp / norm)[cols]
        var_norm = float(u @ cov @ u)
    else:   # at zero the profile's spread is that of |p|: the larger eigenvalue
        var_norm = float(np.linalg.eigvalsh(cov).max()) if len(cols) else 0.0
    return value, np.sqrt(max(var_norm, 0.0)) * r**2
