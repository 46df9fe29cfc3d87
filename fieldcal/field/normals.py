"""The normals of the targets' planes, for the perspective eccentricity (:mod:`.eccentricity`).

A target's normal comes, in this order, from (docs/conventions.md section 3; docs/uncertainty.md
section 2):

``given``
    targets.csv's ``nx,ny,nz`` for that target, else the session's ``field.target_normal``
    (or the ``target_normals`` argument of the library, which replaces both).
``planar fit``
    the best-fit plane of a planar field (every target within :func:`geometry.is_coplanar`).
``estimated``
    the local plane of the target's neighbours in a 3-D field (:func:`estimate_normals`).
``none``
    not determined: the target's eccentricity is not corrected, and what it can do enters its
    image points' sigmas instead (:func:`eccentricity_bound_px`).

Local plane (:func:`estimate_normals`). For each target ``i`` and its ``k`` nearest neighbours
within ``radius_m``, every pair ``(j, l)`` of neighbours proposes the plane through ``X_i`` with
normal ``(X_j - X_i) x (X_l - X_i)``; its support is the neighbours within ``tol_m`` of it. The
plane of largest support is refitted (least squares) to its inliers. The normal is accepted
when the inliers (``i`` included) are at least ``min_points`` and spread in two directions (the
smaller in-plane standard deviation at least ``min_spread`` times the target spacing), and no
plane tilted by more than ``AMBIGUOUS_DEG`` from it has as much support (a target on the edge
where two faces of a structure meet belongs to both and is left ``none``). Steps of parallel
faces (a pillar in front of a wall) are outliers of every face's plane, so targets on either
face get the face's normal. A face one target wide cannot be told from geometry (two parallel
rows of targets are coplanar whatever their depth): there the plane through both rows wins.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fieldcal.field.data import TargetField
from fieldcal.field.eccentricity import correction_px
from fieldcal.field.geometry import is_coplanar, plane_frame
from fieldcal.model.camera import Camera

__all__ = ["SOURCES", "TargetNormals", "resolve_normals", "estimate_normals", "eccentricity_bound_px",
           "normals_summary"]

SOURCES = ("given", "planar fit", "estimated", "none")
"""How a target's normal was obtained (module docstring)."""

AMBIGUOUS_DEG = 15.0
"""A competing local plane tilted by more than this with as much support makes a normal undetermined."""


@dataclass
class TargetNormals:
    """The targets' normals (n, 3), a NaN row where unknown, and how each was obtained
    (``source``: (n,) array of :data:`SOURCES`)."""

    normals: np.ndarray
    source: np.ndarray

    @property
    def known(self) -> np.ndarray:
        return np.isfinite(self.normals).all(axis=1)


def _unit(N):
    return N / np.linalg.norm(N, axis=-1, keepdims=True)


def resolve_normals(targets: TargetField, normals=None, *, xyz_m=None, estimate: bool = True,
                    tol_m: float = 0.005, towards_m=None) -> TargetNormals:
    """The normal of every target and how it was obtained (module docstring).

    Parameters
    ----------
    targets : TargetField
        ``targets.normals`` are the given ones (NaN rows: unknown).
    normals : (n, 3) or (3,) array_like, optional
        Replaces ``targets.normals`` (a synthetic field's truth; NaN rows unknown).
    xyz_m : (n, 3) array_like, optional
        Coordinates for the planar fit and the estimate (the adjusted targets; default the
        surveyed ones) [m].
    estimate : bool
        Estimate the unknown normals of a 3-D field from the local planes.
    tol_m : float
        Distance from a local plane within which a neighbour belongs to it [m] (about three
        times the coordinates' sigma).
    towards_m : (n, 3) array_like, optional
        A point on the side each target is seen from (the mean centre of the cameras that see
        it): estimated normals point towards it.
    """
    n = len(targets)
    N = targets.normals if normals is None else normals
    N = np.full((n, 3), np.nan) if N is None else np.array(np.broadcast_to(np.asarray(N, float), (n, 3)))
    if N.shape != (n, 3):
        raise ValueError(f"target normals must be (n, 3) with n = {n}, got {N.shape}")
    known = np.isfinite(N).all(axis=1)
    N[~known] = np.nan
    N[known] = _unit(N[known])
    source = np.where(known, "given", "none").astype(object)
    X = np.asarray(targets.xyz_m if xyz_m is None else xyz_m, float)
    if known.all() or n < 3:
        return TargetNormals(N, source.astype(str))
    if is_coplanar(X):
        _, B = plane_frame(X)
        N[~known] = B[:, 2]
        source[~known] = "planar fit"
    elif estimate:
        est = estimate_normals(X, tol_m=tol_m)
        take = ~known & np.isfinite(est).all(axis=1)
        N[take] = est[take]
        source[take] = "estimated"
    if towards_m is not None:
        v = np.asarray(towards_m, float) - X
        flip = np.einsum("ij,ij->i", N, v) < 0
        N[flip & ~known] *= -1.0
    return TargetNormals(N, source.astype(str))


def _pair_normals(D):
    """Candidate normals (n, P, 3) from the pairs of neighbour offsets ``D`` (n, k, 3)."""
    j, l = np.triu_indices(D.shape[1], k=1)
    C = np.cross(D[:, j], D[:, l])
    return C / np.maximum(np.linalg.norm(C, axis=2, keepdims=True), 1e-300), np.linalg.norm(C, axis=2)


def estimate_normals(xyz_m, *, k: int = 12, tol_m: float = 0.005, min_points: int = 5,
                     min_spread: float = 0.25) -> np.ndarray:
    """Unit normals (n, 3) of the targets' local planes (module docstring); NaN rows where
    the local plane is not determined. Either sign.

    Parameters
    ----------
    xyz_m : (n, 3) array_like
        Target coordinates [m].
    k : int
        Neighbours considered (within three times the median spacing).
    tol_m : float
        Distance from a plane within which a neighbour supports it [m].
    min_points : int
        Inliers (the target included) a plane needs.
    min_spread : float
        The inliers' smaller in-plane standard deviation, in units of the median spacing.
    """
    X = np.asarray(xyz_m, float)
    n = len(X)
    out = np.full((n, 3), np.nan)
    if n < min_points:
        return out
    k = min(k, n - 1)
    tree = cKDTree(X)
    dist, idx = tree.query(X, k=k + 1)
    spacing = float(np.median(dist[:, 1]))
    near = dist[:, 1:] <= 3.0 * spacing                                     # (n, k)
    D = np.where(near[..., None], X[idx[:, 1:]] - X[:, None, :], np.nan)    # offsets, NaN beyond reach
    cand, area = _pair_normals(np.nan_to_num(D))
    valid = np.isfinite(D[:, :, 0])
    jj, ll = np.triu_indices(k, k=1)
    # a pair spanning a triangle of too small an area gives no direction
    ok = valid[:, jj] & valid[:, ll] & (area > (0.3 * spacing) ** 2)
    dev = np.abs(np.einsum("npc,nkc->npk", cand, np.nan_to_num(D)))           # (n, P, k)
    inl = (dev <= tol_m) & valid[:, None, :]
    support = np.where(ok, inl.sum(axis=2), -1)                             # (n, P)
    best = np.argmax(support, axis=1)
    rows = np.arange(n)
    nb = cand[rows, best]
    # a rival: as much support, tilted by more than AMBIGUOUS_DEG
    cos_t = np.abs(np.einsum("npc,nc->np", cand, nb))
    rival = ((support >= support[rows, best][:, None]) & (cos_t < np.cos(np.radians(AMBIGUOUS_DEG)))).any(axis=1)
    for i in np.flatnonzero(~rival & (support[rows, best] + 1 >= min_points)):
        P = np.vstack([X[i], X[idx[i, 1:]][inl[i, best[i]]]])
        c = P - P.mean(axis=0)
        _, s, Vt = np.linalg.svd(c, full_matrices=False)
        if s[1] / np.sqrt(len(P)) < min_spread * spacing:
            continue
        normal = Vt[2]
        if np.max(np.abs(c @ normal)) > 2.0 * tol_m:
            continue
        out[i] = normal
    return out


def _hemisphere(count: int = 24) -> np.ndarray:
    """``count`` unit vectors spread over the half sphere z > 0 (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def eccentricity_bound_px(camera: Camera, R_world_to_camera, center_m, centers_m, radius_m, *,
                          max_incidence_deg: float = 75.0) -> np.ndarray:
    """The largest perspective eccentricity (n,) [px] a disc of unknown normal can have in one image.

    The maximum of ``|correction_px|`` over normals within ``max_incidence_deg`` of the view ray
    (24 directions of a half sphere about the ray); to first order ``f r^2 / (2 Z^2)``, at
    45 degrees (:mod:`.eccentricity`).
    """
    X = np.asarray(centers_m, float).reshape(-1, 3)
    if not len(X):
        return np.zeros(0)
    ray = _unit(np.asarray(center_m, float)[None, :] - X)                     # towards the camera
    ref = np.where((np.abs(ray[:, 0]) > 0.9)[:, None], [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    a = _unit(ref - np.sum(ref * ray, axis=1, keepdims=True) * ray)
    b = np.cross(ray, a)
    H = _hemisphere()
    H = H[H[:, 2] >= np.cos(np.radians(max_incidence_deg))]
    N = H[None, :, 0:1] * a[:, None] + H[None, :, 1:2] * b[:, None] + H[None, :, 2:3] * ray[:, None]
    m = H.shape[0]
    e = correction_px(camera, R_world_to_camera, center_m, np.repeat(X, m, axis=0), N.reshape(-1, 3),
                      np.repeat(np.broadcast_to(np.asarray(radius_m, float), (len(X),)), m), rim_points=32)
    mag = np.hypot(e[:, 0], e[:, 1]).reshape(len(X), m)
    return np.nanmax(np.where(np.isfinite(mag), mag, 0.0), axis=1)


def normals_summary(source, observed=None) -> dict:
    """``{"normals": "given" | "estimated" | ... (comma-joined when mixed, most targets first),
    "n_targets": {source: count}}`` over the observed targets (``observed``: a mask or indices)."""
    s = np.asarray(source, str)
    if observed is not None:
        s = s[observed]
    counts = {k: int(np.sum(s == k)) for k in SOURCES if np.sum(s == k)}
    order = sorted(counts, key=lambda k: (-counts[k], SOURCES.index(k)))
    return {"normals": ", ".join(order) if order else "none", "n_targets": counts}
