"""The camera model ``fieldcal-brown/1`` (docs/conventions.md sections 1-2).

Frames
------
- pixel ``(u, v)``: u right (column), v down (row), centre of the top-left pixel at (0, 0).
- image plane ``(x, y)`` [mm]: origin at the sensor centre, x right, y **up**;
  ``x = (u - (W-1)/2) d``, ``y = -(v - (H-1)/2) d`` with ``d = pixel_size_um / 1000``.
- the principal point in pixels: ``u0 = (W-1)/2 + xp/d``, ``v0 = (H-1)/2 - yp/d``
  (:func:`principal_point_px`, :attr:`Camera.principal_point_px`; the inverse
  :func:`principal_point_mm`).
- ideal image point ``q`` [mm]: the measured point corrected for distortion, relative to
  the principal point, ``q = (xb + dx, yb + dy)`` with ``xb = x - xp``, ``yb = y - yp``;
  it obeys the collinearity equations ``q = -f (Xc, Yc) / Zc`` for the point
  ``Xc = R_world_to_camera (X - C)`` in the camera frame (which looks along -z).

The correction (measured -> ideal) is closed form (:func:`correct`); its inverse
(ideal -> measured, :func:`distort`) is solved by Newton's method. Parameters are a
length-13 vector in the order of :data:`PARAM_NAMES`; units: ``f, xp, yp`` [mm],
``k1`` [mm^-2], ``k2`` [mm^-4], ``k3`` [mm^-6], ``p1, p2`` [mm^-1], the rest dimensionless.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fieldcal.errors import ConvergenceError, InputError

MODEL = "fieldcal-brown/1"

PARAM_NAMES: tuple[str, ...] = (
    "f_mm", "xp_mm", "yp_mm", "k0", "k1", "k2", "k3", "p1", "p2", "a1", "a2", "b1", "b2",
)
"""The 13 parameters of ``fieldcal-brown/1``, in the order of every parameter vector."""

FIELD_PARAMS: tuple[str, ...] = (
    "f_mm", "xp_mm", "yp_mm", "k1", "k2", "k3", "p1", "p2", "a1", "a2",
)
"""What the field method estimates; ``k0, b1, b2`` are fixed at 0."""

GONIOMETER_PARAMS: tuple[str, ...] = (
    "f_mm", "xp_mm", "yp_mm", "k0", "k1", "k2", "k3", "p1", "p2", "b1", "b2",
)
"""What the goniometer method estimates; ``a1, a2`` are fixed at 0."""

INDEX = {name: i for i, name in enumerate(PARAM_NAMES)}
NEWTON_TOL_MM = 1e-10
"""Step size [mm] at which :func:`distort`'s Newton iteration (and the compiled kernels' copy of it) has converged."""
NEWTON_MAX_ITER = 30
"""Newton steps :func:`distort` takes at most (beyond them: NaN, not converged)."""
F, XP, YP, K0, K1, K2, K3, P1, P2, A1, A2, B1, B2 = range(13)


@dataclass(frozen=True)
class Sensor:
    """The pixel grid: ``width_px`` columns, ``height_px`` rows, square pixels of ``pixel_size_um``."""

    width_px: int
    height_px: int
    pixel_size_um: float

    def __post_init__(self):
        if not (self.width_px > 0 and self.height_px > 0):
            raise InputError(f"sensor size must be positive, got {self.width_px} x {self.height_px}")
        if not (np.isfinite(self.pixel_size_um) and self.pixel_size_um > 0):
            raise InputError(f"pixel_size_um must be a positive number, got {self.pixel_size_um}")

    @property
    def pixel_mm(self) -> float:
        """Pixel pitch ``d`` [mm]."""
        return self.pixel_size_um / 1000.0

    @property
    def half_diagonal_mm(self) -> float:
        """Distance from the sensor centre to a corner pixel centre [mm]."""
        return 0.5 * np.hypot(self.width_px - 1, self.height_px - 1) * self.pixel_mm

    def pixel_to_mm(self, uv_px):
        """Pixel coordinates (..., 2) [px] -> image-plane coordinates (..., 2) [mm]."""
        uv = np.asarray(uv_px, dtype=float)
        d = self.pixel_mm
        x = (uv[..., 0] - (self.width_px - 1) / 2.0) * d
        y = -(uv[..., 1] - (self.height_px - 1) / 2.0) * d
        return np.stack([x, y], axis=-1)

    def mm_to_pixel(self, xy_mm):
        """Image-plane coordinates (..., 2) [mm] -> pixel coordinates (..., 2) [px]."""
        xy = np.asarray(xy_mm, dtype=float)
        d = self.pixel_mm
        u = xy[..., 0] / d + (self.width_px - 1) / 2.0
        v = -xy[..., 1] / d + (self.height_px - 1) / 2.0
        return np.stack([u, v], axis=-1)

    def grid_px(self, n_u: int = 41, n_v: int = 31):
        """A regular grid of pixel centres spanning the sensor corner to corner, (n_v*n_u, 2)."""
        u = np.linspace(0.0, self.width_px - 1.0, n_u)
        v = np.linspace(0.0, self.height_px - 1.0, n_v)
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu.ravel(), vv.ravel()], axis=-1)

    def to_dict(self) -> dict:
        return {"width_px": int(self.width_px), "height_px": int(self.height_px),
                "pixel_size_um": float(self.pixel_size_um)}


def principal_point_px(sensor: Sensor, xp_mm, yp_mm) -> np.ndarray:
    """The principal point in pixel coordinates: ``(u0, v0) = ((W-1)/2 + xp/d, (H-1)/2 - yp/d)``.

    Parameters
    ----------
    sensor : Sensor
        The pixel grid (``W x H``, pitch ``d`` [mm]).
    xp_mm, yp_mm : float or array_like
        The principal point [mm] in the image plane (docs/conventions.md section 1: from the
        sensor centre, x right, y up).

    Returns
    -------
    (..., 2) ndarray
        ``(u0, v0)`` [px]: column right, row down (:meth:`Sensor.mm_to_pixel` of the point).
    """
    return sensor.mm_to_pixel(np.stack(np.broadcast_arrays(np.asarray(xp_mm, dtype=float),
                                                            np.asarray(yp_mm, dtype=float)), axis=-1))


def principal_point_mm(sensor: Sensor, u0_px, v0_px) -> np.ndarray:
    """The inverse of :func:`principal_point_px`: ``(xp, yp) = ((u0 - (W-1)/2) d, -(v0 - (H-1)/2) d)``.

    Parameters
    ----------
    sensor : Sensor
        The pixel grid (``W x H``, pitch ``d`` [mm]).
    u0_px, v0_px : float or array_like
        The principal point [px] (e.g. ``cx, cy`` of an OpenCV camera matrix).

    Returns
    -------
    (..., 2) ndarray
        ``(xp, yp)`` [mm] (:meth:`Sensor.pixel_to_mm` of the point).
    """
    return sensor.pixel_to_mm(np.stack(np.broadcast_arrays(np.asarray(u0_px, dtype=float),
                                                            np.asarray(v0_px, dtype=float)), axis=-1))


def params_from_dict(values: dict) -> np.ndarray:
    """A length-13 parameter vector from a mapping of names (missing names are 0)."""
    unknown = set(values) - set(PARAM_NAMES)
    if unknown:
        raise InputError(f"unknown camera parameter(s) {sorted(unknown)}; allowed: {list(PARAM_NAMES)}")
    return np.array([float(values.get(n, 0.0)) for n in PARAM_NAMES])


def params_to_dict(params) -> dict:
    """The inverse of :func:`params_from_dict`: ``{name: float}`` in :data:`PARAM_NAMES` order."""
    return {n: float(v) for n, v in zip(PARAM_NAMES, np.asarray(params, dtype=float), strict=True)}


@dataclass(frozen=True)
class Camera:
    """A sensor and the 13 parameters of ``fieldcal-brown/1``."""

    sensor: Sensor
    params: np.ndarray = field(default_factory=lambda: np.zeros(13))

    def __post_init__(self):
        p = np.asarray(self.params, dtype=float)
        if p.shape != (13,):
            raise InputError(f"camera parameters must be a vector of 13, got shape {p.shape}")
        object.__setattr__(self, "params", p)

    @classmethod
    def from_dict(cls, sensor: Sensor, values: dict) -> Camera:
        return cls(sensor, params_from_dict(values))

    @property
    def f_mm(self) -> float:
        return float(self.params[F])

    @property
    def principal_point_px(self) -> np.ndarray:
        """``(u0, v0)`` [px], the principal point in pixel coordinates (:func:`principal_point_px`)."""
        return principal_point_px(self.sensor, self.params[XP], self.params[YP])

    def to_dict(self) -> dict:
        return params_to_dict(self.params)

    # the model, bound to this camera -------------------------------------------------
    def correct(self, xy_mm):
        return correct(xy_mm, self.params)

    def distort(self, q_mm, **kw):
        return distort(q_mm, self.params, **kw)

    def project(self, X_world_m, R_world_to_camera, center_m):
        return project(X_world_m, R_world_to_camera, center_m, self)

    def unproject(self, uv_px):
        return unproject(uv_px, self)


def correction_terms(xb, yb, p):
    """The correction polynomial (docs/conventions.md section 2), written once for the whole package.

    Parameters
    ----------
    xb, yb : ndarray
        Measured points relative to the principal point [mm] (any equal shapes).
    p : (13,) ndarray
        Camera parameters.

    Returns
    -------
    dx, dy : ndarray
        The correction [mm]; the ideal point is ``q = (xb + dx, yb + dy)``.
    g00, g01, g10, g11 : ndarray
        The entries of ``G = dq/dx'``, the Jacobian of the correction with respect to the
        measured point.
    r2, xy_ : ndarray
        ``xb^2 + yb^2`` and ``xb yb`` (shared with :func:`ideal_point_columns`).
    """
    r2 = xb * xb + yb * yb
    radial = p[K0] + r2 * (p[K1] + r2 * (p[K2] + r2 * p[K3]))
    dradial = p[K1] + r2 * (2.0 * p[K2] + 3.0 * r2 * p[K3])
    xy_ = xb * yb
    dx = xb * radial + p[P1] * (r2 + 2 * xb * xb) + 2 * p[P2] * xy_ + p[B1] * xb + p[B2] * yb
    dy = yb * radial + p[P2] * (r2 + 2 * yb * yb) + 2 * p[P1] * xy_ + p[A1] * xb + p[A2] * yb
    g00 = 1 + radial + 2 * xb * xb * dradial + 6 * p[P1] * xb + 2 * p[P2] * yb + p[B1]
    g01 = 2 * xy_ * dradial + 2 * p[P1] * yb + 2 * p[P2] * xb + p[B2]
    g10 = 2 * xy_ * dradial + 2 * p[P2] * xb + 2 * p[P1] * yb + p[A1]
    g11 = 1 + radial + 2 * yb * yb * dradial + 6 * p[P2] * yb + 2 * p[P1] * xb + p[A2]
    return dx, dy, g00, g01, g10, g11, r2, xy_


def correction(xy_mm, params):
    """The correction ``(dx, dy)`` (..., 2) [mm] of measured points ``xy_mm`` (docs/conventions.md section 2)."""
    p = np.asarray(params, dtype=float)
    xy = np.asarray(xy_mm, dtype=float)
    dx, dy = correction_terms(xy[..., 0] - p[XP], xy[..., 1] - p[YP], p)[:2]
    return np.stack([dx, dy], axis=-1)


def correct(xy_mm, params):
    """Measured image points (..., 2) [mm] -> ideal points ``q`` (..., 2) [mm], closed form.

    ``q = (xb + dx, yb + dy)``, relative to the principal point (see the module docstring).
    """
    p = np.asarray(params, dtype=float)
    xy = np.asarray(xy_mm, dtype=float)
    xb, yb = xy[..., 0] - p[XP], xy[..., 1] - p[YP]
    dx, dy = correction_terms(xb, yb, p)[:2]
    return np.stack([xb + dx, yb + dy], axis=-1)


def ideal_point_columns(xb, yb, p, g, r2, xy_, columns):
    """``dq/dp_c`` at fixed measured point for each parameter index ``c``: a list of (x, y) pairs.

    ``g = (g00, g01, g10, g11)``, ``r2`` and ``xy_`` as :func:`correction_terms` returns
    them; constant zero columns are returned as the scalar 0. (``dq/df`` is 0: f enters
    through the collinearity side, ``q = -f Xc/Zc``.)
    """
    g00, g01, g10, g11 = g
    out = []
    for c in columns:
        c = int(c)
        if c == F:
            out.append((0.0, 0.0))
        elif c == XP:
            out.append((-g00, -g10))
        elif c == YP:
            out.append((-g01, -g11))
        elif c in (K0, K1, K2, K3):
            w = r2 ** (c - K0) if c != K0 else 1.0
            out.append((xb * w, yb * w))
        elif c == P1:
            out.append((r2 + 2 * xb * xb, 2 * xy_))
        elif c == P2:
            out.append((2 * xy_, r2 + 2 * yb * yb))
        elif c == A1:
            out.append((0.0, xb))
        elif c == A2:
            out.append((0.0, yb))
        elif c == B1:
            out.append((xb, 0.0))
        else:
            out.append((yb, 0.0))
    return out


def correct_jacobian(xy_mm, params, columns=None):
    """Derivatives of :func:`correct` at measured points ``xy_mm`` (N, 2) [mm].

    Parameters
    ----------
    columns : sequence of int, optional
        Indices (into :data:`PARAM_NAMES`) of the parameter columns of ``Q`` to compute;
        all 13 by default.

    Returns
    -------
    q : (N, 2) ndarray
        The ideal points [mm].
    G : (N, 2, 2) ndarray
        ``dq / d(x, y)``, the Jacobian of the correction with respect to the measured point.
    Q : (N, 2, len(columns)) ndarray
        ``dq / dparams`` at fixed measured point, in the order of ``columns``.
    """
    p = np.asarray(params, dtype=float)
    xy = np.asarray(xy_mm, dtype=float)
    xb, yb = xy[..., 0] - p[XP], xy[..., 1] - p[YP]
    dx, dy, g00, g01, g10, g11, r2, xy_ = correction_terms(xb, yb, p)
    q = np.stack([xb + dx, yb + dy], axis=-1)
    G = np.stack([np.stack([g00, g01], -1), np.stack([g10, g11], -1)], -2)
    cols = range(13) if columns is None else columns
    Q = np.empty(xb.shape + (2, len(cols)))
    for j, (c0, c1) in enumerate(ideal_point_columns(xb, yb, p, (g00, g01, g10, g11), r2, xy_, cols)):
        Q[..., 0, j], Q[..., 1, j] = c0, c1
    return q, G, Q


def distort(q_mm, params, *, tol_mm: float = NEWTON_TOL_MM, max_iter: int = NEWTON_MAX_ITER, check: bool = True,
            start_mm=None):
    """Ideal points ``q`` (..., 2) [mm] -> measured image points (..., 2) [mm].

    Inverts :func:`correct` by Newton's method, started at ``start_mm`` when given (e.g. the
    measured points, a fraction of a pixel away) or else at ``q + (xp, yp)``; each step
    solves the 2x2 system ``G step = correct(x') - q`` in closed form. Converges
    quadratically; the default tolerance (1e-10 mm, about 2e-8 px at 5 um pixels) is far
    below 1e-6 px.

    Raises :class:`ConvergenceError` (when ``check``) if a finite point did not converge;
    with ``check=False`` such points are returned as NaN.
    """
    p = np.asarray(params, dtype=float)
    q = np.asarray(q_mm, dtype=float)
    shape = q.shape
    qf = q.reshape(-1, 2)
    qx_t, qy_t = qf[:, 0], qf[:, 1]
    if start_mm is None:
        xb, yb = qx_t.copy(), qy_t.copy()
    else:
        st = np.asarray(start_mm, dtype=float).reshape(-1, 2)
        xb, yb = st[:, 0] - p[XP], st[:, 1] - p[YP]
        bad = ~np.isfinite(xb + yb)
        xb[bad], yb[bad] = qx_t[bad], qy_t[bad]
    idx = np.flatnonzero(np.isfinite(qx_t + qy_t))
    out_x, out_y = np.full(len(qf), np.nan), np.full(len(qf), np.nan)
    for _ in range(max_iter):
        if idx.size == 0:
            break
        bx, by = xb[idx], yb[idx]
        dx, dy, g00, g01, g10, g11, _, _ = correction_terms(bx, by, p)
        ex, ey = bx + dx - qx_t[idx], by + dy - qy_t[idx]
        det = g00 * g11 - g01 * g10
        sx = (g11 * ex - g01 * ey) / det
        sy = (g00 * ey - g10 * ex) / det
        bx -= sx
        by -= sy
        xb[idx], yb[idx] = bx, by
        done = np.maximum(np.abs(sx), np.abs(sy)) <= tol_mm
        out_x[idx[done]], out_y[idx[done]] = bx[done], by[done]
        idx = idx[~done]
    if idx.size and check:
        raise ConvergenceError(
            f"distort: {idx.size} point(s) did not converge in {max_iter} Newton steps "
            "(far outside the region where the correction is invertible)")
    xy = np.stack([out_x + p[XP], out_y + p[YP]], axis=-1)
    return xy.reshape(shape)


def project(X_world_m, R_world_to_camera, center_m, camera: Camera):
    """World points (..., 3) [m] seen from a pose -> measured pixel coordinates (..., 2) [px].

    ``Xc = R_world_to_camera (X - C)``, ``q = -f (Xc, Yc)/Zc``, then :func:`distort` and
    the sensor's mm -> pixel mapping. Points behind the camera (``Zc >= 0``) give NaN.
    """
    X = np.asarray(X_world_m, dtype=float)
    Xc = np.einsum("...ij,...j->...i", np.asarray(R_world_to_camera, float), X - np.asarray(center_m, float))
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -camera.f_mm * Xc[..., :2] / np.where(z < 0, z, np.nan)[..., None]
    xy = distort(q, camera.params, check=False)
    return camera.sensor.mm_to_pixel(xy)


def unproject(uv_px, camera: Camera):
    """Measured pixels (..., 2) -> unit ray directions (..., 3) in the camera frame.

    The ray of an ideal point ``q`` is ``(qx, qy, -f)`` (the camera looks along -z).
    """
    q = correct(camera.sensor.pixel_to_mm(uv_px), camera.params)
    ray = np.concatenate([q, np.full(q.shape[:-1] + (1,), -camera.f_mm)], axis=-1)
    return ray / np.linalg.norm(ray, axis=-1, keepdims=True)
