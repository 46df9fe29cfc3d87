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

from fieldcal.field.eccentricity import correction_px, rim_px
from fieldcal.field.geometry import is_coplanar, plane_frame
from fieldcal.model.camera import Camera
from fieldcal.session.data import TargetField

__all__ = ["SOURCES", "ECC_TOL_FACTOR", "ECC_TOL_MIN_M", "plane_tolerance_m", "TargetNormals", "resolve_normals",
           "estimate_normals", "local_planes", "choose_by_shapes", "shape_vectors", "measured_shape_vectors",
           "eccentricity_bound_px", "normals_summary", "hemisphere"]

SOURCES = ("given", "planar fit", "estimated", "none")
"""How a target's normal was obtained (module docstring)."""
ECC_TOL_FACTOR = 3.0
"""A neighbour belongs to a target's local plane within this many sigmas of the adjusted targets
(:func:`plane_tolerance_m`) ..."""
ECC_TOL_MIN_M = 0.001
"""... and at least this [m] (the targets' flatness on their support)."""


def plane_tolerance_m(sigma_m) -> float:
    """``tol_m`` of :func:`resolve_normals` for adjusted targets of sigmas ``sigma_m`` [m]:
    :data:`ECC_TOL_FACTOR` times their median, at least :data:`ECC_TOL_MIN_M` (NaN sigmas ignored)."""
    s = np.asarray(sigma_m, float).ravel()
    s = s[np.isfinite(s)]
    return max(ECC_TOL_MIN_M, ECC_TOL_FACTOR * float(np.median(s))) if len(s) else ECC_TOL_MIN_M

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
                    tol_m: float = 0.005, towards_m=None, shapes=None) -> TargetNormals:
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
    shapes : tuple (camera, views, radius_m), optional
        The imaged ellipses that choose between local planes (:func:`choose_by_shapes`);
        without them the best-supported plane (:func:`estimate_normals`).
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
    placed = np.isfinite(X).all(axis=1)              # a target the adjustment could not place has no normal
    if placed.sum() < 3:
        return TargetNormals(N, source.astype(str))
    if is_coplanar(X[placed]):
        _, B = plane_frame(X[placed])
        N[~known & placed] = B[:, 2]
        source[~known & placed] = "planar fit"
    elif estimate:
        if shapes is None:
            est = np.full((n, 3), np.nan)
            est[placed] = estimate_normals(X[placed], tol_m=tol_m)
        else:
            camera, views, radius_m = shapes
            cand, sup = local_planes(X, tol_m=tol_m)
            est, _ = choose_by_shapes(camera, views, cand, sup, X, radius_m, towards_m)
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


CANDIDATES = 3
"""Distinct local planes kept per target (:func:`local_planes`) for the ellipses to choose from."""


def local_planes(xyz_m, *, k: int = 20, tol_m: float = 0.005, min_points: int = 5,
                 min_spread: float = 0.25, candidates: int = CANDIDATES):
    """The best-supported distinct local planes of every target (module docstring).

    Returns
    -------
    normals : (n, candidates, 3) ndarray
        Unit normals (either sign), best support first, each tilted by more than
        :data:`AMBIGUOUS_DEG` from the ones before; NaN rows where fewer planes qualify.
    support : (n, candidates) int ndarray
        Inliers of each plane, the target included (0 where none).
    """
    X = np.asarray(xyz_m, float)
    n = len(X)
    out = np.full((n, candidates, 3), np.nan)
    sup = np.zeros((n, candidates), np.int64)
    if n < min_points:
        return out, sup
    k = min(k, n - 1)
    dist, idx = cKDTree(X).query(X, k=k + 1)
    spacing = float(np.median(dist[:, 1]))
    valid = dist[:, 1:] <= 3.0 * spacing                                    # (n, k)
    D = np.where(valid[..., None], X[idx[:, 1:]] - X[:, None, :], 0.0)      # neighbour offsets
    cand, area = _pair_normals(D)
    jj, ll = np.triu_indices(k, k=1)
    # a pair spanning a triangle of too small an area gives no direction
    ok = valid[:, jj] & valid[:, ll] & (area > (0.3 * spacing) ** 2)
    inl = (np.abs(np.einsum("npc,nkc->npk", cand, D)) <= tol_m) & valid[:, None, :]   # (n, P, k)
    support = np.where(ok, inl.sum(axis=2), -1)                             # (n, P)
    order = np.argsort(-support, axis=1, kind="stable")
    cos_max = np.cos(np.radians(AMBIGUOUS_DEG))
    for i in range(n):
        m = 0
        for p in order[i]:
            if support[i, p] + 1 < min_points or m == candidates:
                break
            if m and np.any(np.abs(out[i, :m] @ cand[i, p]) > cos_max):
                continue
            P = np.vstack([X[i], X[idx[i, 1:]][inl[i, p]]])
            c = P - P.mean(axis=0)
            _, sv, Vt = np.linalg.svd(c, full_matrices=False)
            if sv[1] / np.sqrt(len(P)) < min_spread * spacing or np.max(np.abs(c @ Vt[2])) > 2.0 * tol_m:
                continue
            if m and np.any(np.abs(out[i, :m] @ Vt[2]) > cos_max):
                continue
            out[i, m], sup[i, m] = Vt[2], len(P)
            m += 1
    return out, sup


def estimate_normals(xyz_m, *, k: int = 20, tol_m: float = 0.005, min_points: int = 5,
                     min_spread: float = 0.25) -> np.ndarray:
    """Unit normals (n, 3) of the targets' local planes (module docstring): the best-supported
    plane of :func:`local_planes` when no distinct plane has as much support; NaN rows where
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
    N, sup = local_planes(xyz_m, k=k, tol_m=tol_m, min_points=min_points, min_spread=min_spread)
    unique = (sup[:, 0] > 0) & (sup[:, 0] > sup[:, 1])
    return np.where(unique[:, None], N[:, 0], np.nan)


def shape_vectors(uv_rim_px) -> np.ndarray:
    """The shape of figures (..., K, 2) [px] from their points' second moments: ``(s_uu - s_vv,
    2 s_uv) / (s_uu + s_vv)``, ``(a^2 - b^2) / (a^2 + b^2) (cos 2 phi, sin 2 phi)`` for an ellipse
    of semi-axes ``a >= b``, major axis at ``phi`` from +u towards +v. Scale-free: 0 for a circle."""
    c = uv_rim_px - np.nanmean(uv_rim_px, axis=-2, keepdims=True)
    suu, svv, suv = (np.nanmean(c[..., 0] ** 2, axis=-1), np.nanmean(c[..., 1] ** 2, axis=-1),
                     np.nanmean(c[..., 0] * c[..., 1], axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([suu - svv, 2.0 * suv], axis=-1) / (suu + svv)[..., None]


def measured_shape_vectors(major_px, minor_px, angle_deg) -> np.ndarray:
    """:func:`shape_vectors` of the fitted edge ellipses of the measurements table (n, 2)."""
    a2, b2 = np.asarray(major_px, float) ** 2, np.asarray(minor_px, float) ** 2
    t = 2.0 * np.radians(np.asarray(angle_deg, float))
    with np.errstate(invalid="ignore", divide="ignore"):
        e = (a2 - b2) / (a2 + b2)
    return np.stack([e * np.cos(t), e * np.sin(t)], axis=-1)


SHAPE_MIN_GAIN = 9.0
"""The ellipses choose another plane than the best-supported one, or one of two equally supported
planes, when it fits their shapes better by this many times the shape noise's variance
(chi-square 9: three sigmas)."""
SHAPE_MAX_MISFIT = 9.0
"""A normal whose predicted ellipses miss the measured ones by more than this many times the
shape noise's variance per component and view (on average) is not the disc's."""


def _shape_sse(camera, views, X, normals_of, radius_m):
    """Sum over views of |predicted - measured shape vector|^2 (n, m) for the normals
    ``normals_of`` (n, m, 3) of every target (NaN: not evaluated), and the views per target."""
    n, m = normals_of.shape[:2]
    sse = np.zeros((n, m))
    count = np.zeros(n)
    have = np.isfinite(normals_of).all(axis=2)
    for R, C, t, meas in views:
        t = np.asarray(t, np.int64)
        good = np.isfinite(meas).all(axis=1)
        t, meas = t[good], meas[good]
        k, j = np.nonzero(have[t])                   # (view's disc, normal) pairs to evaluate
        if len(k):
            rim = rim_px(camera, R, C, X[t[k]], normals_of[t[k], j], radius_m)
            d = shape_vectors(rim) - meas[k]
            np.add.at(sse, (t[k], j), np.where(np.isfinite(d).all(axis=1), np.sum(d ** 2, axis=1), 0.0))
        np.add.at(count, t, 1.0)
    return np.where(have, sse, np.inf), count


def _fit_shapes(camera, views, X, radius_m, towards, todo):
    """Normals (len(todo), 3) of the targets ``todo`` that fit their ellipses best: a lattice of
    192 directions facing ``towards``, then three rounds of 8 around the best (3, 1, 0.3 deg);
    and their sums of squared shape misfits."""
    k = len(todo)
    if not k:
        return np.zeros((0, 3)), np.zeros(0)
    n_all = len(X)
    ray = _unit(np.asarray(towards, float)[todo] - X[todo])

    def sse_of(M):                                   # M (k, m, 3) -> (k, m)
        full = np.full((n_all, M.shape[1], 3), np.nan)
        full[todo] = M
        return _shape_sse(camera, views, X, full, radius_m)[0][todo]

    best, top = _search_directions(ray, lambda M: -sse_of(M), np.cos(np.radians(80.0)), cone_on_rings=False)
    return best, -top


def _search_directions(ray, score, cos_min: float, *, cone_on_rings: bool):
    """The unit vectors (n, 3) that maximise ``score(M (n, m, 3)) -> (n, m)`` near each ray
    (n, 3), and their scores (n,): a lattice of 192 directions of the half sphere about the ray
    (those within ``arccos(cos_min)`` of it), then three rounds of 8 around the best at 3, 1
    and 0.3 degrees (``cone_on_rings``: a ring's directions outside the cone score 0)."""
    n = len(ray)
    ref = np.where((np.abs(ray[:, 0]) > 0.9)[:, None], [[0.0, 1.0, 0.0]], [[1.0, 0.0, 0.0]])
    a = _unit(ref - np.sum(ref * ray, axis=1, keepdims=True) * ray)
    b = np.cross(ray, a)
    H = hemisphere(192)
    H = H[H[:, 2] >= cos_min]
    M = H[None, :, 0:1] * a[:, None] + H[None, :, 1:2] * b[:, None] + H[None, :, 2:3] * ray[:, None]
    e = score(M)
    best, top = M[np.arange(n), np.argmax(e, axis=1)], e.max(axis=1)
    ring = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    for step_deg in (3.0, 1.0, 0.3):
        u = _unit(np.cross(best, a))
        w = np.cross(best, u)
        d = np.tan(np.radians(step_deg))
        M = _unit(best[:, None] + d * (np.cos(ring)[None, :, None] * u[:, None]
                                       + np.sin(ring)[None, :, None] * w[:, None]))
        e = score(M)
        if cone_on_rings:
            e = np.where(np.einsum("nmc,nc->nm", M, ray) >= cos_min, e, 0.0)
        better = e.max(axis=1) > top
        best = np.where(better[:, None], M[np.arange(n), np.argmax(e, axis=1)], best)
        top = np.maximum(top, e.max(axis=1))
    return best, top


def choose_by_shapes(camera: Camera, views, candidates, support, xyz_m, radius_m, towards_m=None):
    """The normal of every target that its imaged ellipses' shapes confirm.

    The shape vectors (:func:`shape_vectors`) of the disc's rim, predicted for a candidate normal
    in every image that measured the disc, are compared with the measured ones; the shape
    noise is the median RMS misfit of the best candidates. The best-supported local plane is
    kept unless another fits the shapes better by :data:`SHAPE_MIN_GAIN` (a tie of support
    must be broken so); a target whose chosen plane misfits by more than
    :data:`SHAPE_MAX_MISFIT` (no local plane is its own: a face one target wide, a lone target)
    gets the normal its ellipses alone fit best (when ``towards_m`` is given), if that one fits.

    Parameters
    ----------
    camera : Camera
    views : list of (R_world_to_camera, center_m, targets, shapes)
        Per image: its pose, the indices of the targets measured as discs in it and their
        measured :func:`shape_vectors` (k, 2).
    candidates, support : from :func:`local_planes`
    xyz_m : (n, 3) array_like
    radius_m : float
    towards_m : (n, 3) array_like, optional
        A point each target is seen from (NaN rows: not seen).

    Returns
    -------
    normals : (n, 3) ndarray
        NaN where undetermined (no view, or nothing fits).
    noise : float
        The shape vectors' noise per component.
    """
    X = np.asarray(xyz_m, float)
    n = len(X)
    rows = np.arange(n)
    sse, count = _shape_sse(camera, views, X, candidates, radius_m)
    have = np.isfinite(sse)
    seen = count > 0
    best_fit = np.argmin(sse, axis=1)
    top = sse[rows, best_fit]
    ok = seen & np.isfinite(top)
    noise = float(np.sqrt(np.median(top[ok] / (2.0 * count[ok])))) if ok.any() else np.nan
    var = max(noise if np.isfinite(noise) else 0.0, 1e-6) ** 2
    with np.errstate(invalid="ignore"):
        gain = np.where(have[:, 0], sse[:, 0] - top, np.inf) / var          # chi-square units
        other = np.where(best_fit == 0, 1, 0)
        tie_gain = np.where(have[rows, other], sse[rows, other] - top, np.inf) / var
    choice = np.where(seen & (gain > SHAPE_MIN_GAIN), best_fit, 0)
    out = np.where(have[rows, choice][:, None], candidates[rows, choice], np.nan)
    tie = have[:, 1] & (support[:, 1] >= support[:, 0])
    out[tie & ~(seen & (tie_gain > SHAPE_MIN_GAIN))] = np.nan
    misfit = np.where(seen, sse[rows, choice] / (2.0 * np.maximum(count, 1.0) * var), np.inf)
    out[seen & ~(misfit <= SHAPE_MAX_MISFIT)] = np.nan
    if towards_m is not None:
        todo = np.flatnonzero(seen & ~np.isfinite(out).all(axis=1) & np.isfinite(towards_m).all(axis=1))
        fit, e = _fit_shapes(camera, views, X, radius_m, towards_m, todo)
        good = e / (2.0 * count[todo] * var) <= SHAPE_MAX_MISFIT
        out[todo[good]] = fit[good]
    return out, noise


def hemisphere(count: int = 48) -> np.ndarray:
    """``count`` unit vectors spread over the half sphere z > 0 (a Fibonacci lattice)."""
    k = np.arange(count) + 0.5
    z = 1.0 - k / count
    phi = np.pi * (1.0 + 5 ** 0.5) * k
    r = np.sqrt(1.0 - z ** 2)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


RIM = 64
"""Rim points of the bound's eccentricities (the centroid converges as 1 / RIM^2)."""


def _ecc_norm(camera, R, C, X, N, radius_m):
    """|correction_px| (n, m) of discs X (n, 3) for m normals each, N (n, m, 3)."""
    n, m = N.shape[:2]
    e = correction_px(camera, R, C, np.repeat(X, m, axis=0), N.reshape(-1, 3),
                      np.repeat(np.broadcast_to(np.asarray(radius_m, float), (n,)), m), rim_points=RIM)
    mag = np.hypot(e[:, 0], e[:, 1]).reshape(n, m)
    return np.where(np.isfinite(mag), mag, 0.0)


def eccentricity_bound_px(camera: Camera, R_world_to_camera, center_m, centers_m, radius_m, *,
                          max_incidence_deg: float = 75.0) -> np.ndarray:
    """The largest perspective eccentricity (n,) [px] a disc of unknown normal can have in one image.

    The maximum of ``|correction_px|`` (64 rim points) over normals within ``max_incidence_deg``
    of the view ray: 192 directions of a half sphere about the ray, then three rounds of 8 around
    the best (at 3, 1 and 0.3 degrees), which finds it to better than 1 %; to first order
    ``f r^2 / (2 Z^2)``, at 45 degrees (:mod:`.eccentricity`).
    """
    X = np.asarray(centers_m, float).reshape(-1, 3)
    if not len(X):
        return np.zeros(0)
    R, C = np.asarray(R_world_to_camera, float), np.asarray(center_m, float)
    ray = _unit(C[None, :] - X)                                              # towards the camera
    _, top = _search_directions(ray, lambda N: _ecc_norm(camera, R, C, X, N, radius_m),
                                np.cos(np.radians(max_incidence_deg)), cone_on_rings=True)
    return top


def normals_summary(source, observed=None) -> dict:
    """``{"normals": "given" | "estimated" | ... (comma-joined when mixed, most targets first),
    "n_targets": {source: count}}`` over the observed targets (``observed``: a mask or indices)."""
    s = np.asarray(source, str)
    if observed is not None:
        s = s[observed]
    counts = {k: int(np.sum(s == k)) for k in SOURCES if np.sum(s == k)}
    order = sorted(counts, key=lambda k: (-counts[k], SOURCES.index(k)))
    return {"normals": ", ".join(order) if order else "none", "n_targets": counts}
