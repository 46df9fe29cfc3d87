"""Automatic referencing: plain discs no survey names, matched across oriented images.

PhotoModeler calls it automatic referencing (issue 26 goal 1): after the identification and an
adjustment, every image has discs the survey does not name. With the camera and the poses
known, a disc of image ``i`` is a ray ``C_i + s d`` (``d = R_i^T unproject(uv)``,
:func:`fieldcal.model.camera.unproject`); its match in image ``j`` lies on the ray's image
there, the epipolar line. The procedure (all images' discs at once, vectorised per image pair):

Steps 1-2 work in the ideal image plane (``correct`` of each disc once, pinhole projections,
the gate ``gate_px`` times the pixel size), step 3 in pixels through the full camera.

1. **Pairs** (epipolar geometry). For images ``i < j`` whose centres are at least
   ``min_base_m`` apart, every disc ``a`` of ``i`` and ``b`` of ``j``: the two rays' nearest
   points, their midpoint ``X_ab`` (in front of both cameras, rays at least ``min_angle_deg``
   apart), projected into ``i`` and ``j``: a
   candidate when both reprojections lie within ``gate_px`` (the epipolar distance of the
   pair, measured where it matters, in pixels).
2. **Verification** (as the identification verifies a pose: by what else it predicts).
   ``X_ab`` is projected into every other oriented image; there the nearest unreferenced disc
   within ``gate_px`` supports it. A candidate seen (with support) in at least ``min_views``
   images is a track.
3. **Acceptance**, greedy: of a pair's tracks, the ones with the most views first; a track is
   taken when none of its discs belongs to a track taken before; it is intersected again
   from all its rays (least squares, as :mod:`fieldcal.field.intersection`)
   and kept when every ray reprojects within ``gate_px`` and it is seen in at least
   ``min_seen_fraction`` of the images whose frame it falls in. Pairs are taken in turn, and
   a pair only looks at the discs no track has taken yet (the cost falls as tracks are
   found). Ambiguity along an epipolar line (several discs on it) is resolved by the third
   and further views: a wrong pair predicts nothing elsewhere.

Each track becomes an unsurveyed target with an id of its own (``prefix`` and a number) and
enters the adjustment as any unsurveyed target (:mod:`fieldcal.field.adjustment`), which
rejects what still does not fit (data snooping).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from fieldcal.model.camera import Camera, correct, project, unproject

__all__ = ["REFERENCED_PREFIX", "ReferencingOptions", "Tracks", "reference_discs", "track_ids"]

REFERENCED_PREFIX = "AR"
"""Ids of the targets automatic referencing finds: the prefix and a number (``AR0001``).

A track is never given an id targets.csv lists: a listed unsurveyed plain target has no
coordinates to predict where it is, and plain discs carry no identity, so nothing in the images
ties a disc to a listed id (docs/conventions.md section 3, referenced targets)."""


def track_ids(n: int, taken) -> list[str]:
    """``n`` ids ``AR0001, AR0002, ...`` skipping those in ``taken``."""
    taken, ids, k = set(taken), [], 0
    while len(ids) < n:
        k += 1
        name = f"{REFERENCED_PREFIX}{k:04d}"
        if name not in taken:
            ids.append(name)
    return ids


@dataclass(frozen=True)
class ReferencingOptions:
    """Settings of :func:`reference_discs`.

    Attributes
    ----------
    gate_px : float
        Reprojection gate of a candidate and of its support [px]: a few times the
        adjustment's residuals (the poses and camera are adjusted ones).
    min_views : int
        Images a track must be seen in (3: two to intersect, one to verify).
    min_angle_deg : float
        Least angle between the two rays of a pair.
    min_base_m : float
        Least distance between the centres of a pair's images.
    min_seen_fraction : float
        A track must be seen in at least this fraction of the images it lies in the frame of
        (a wrong pair's point, far along nearly parallel rays, falls in many frames and is
        seen in few).
    """

    gate_px: float = 1.5
    min_views: int = 3
    min_angle_deg: float = 3.0
    min_base_m: float = 0.0
    min_seen_fraction: float = 0.5


@dataclass
class Tracks:
    """The referenced discs.

    Attributes
    ----------
    X_m : (n, 3) ndarray
        Each track's intersection [m].
    image, point, track : (k,) int ndarray
        Observation ``k``: point ``point[k]`` of image ``image[k]`` (indices into the lists
        given to :func:`reference_discs`) belongs to track ``track[k]``.
    """

    X_m: np.ndarray
    image: np.ndarray
    point: np.ndarray
    track: np.ndarray

    def __len__(self) -> int:
        return len(self.X_m)


def _midpoints(Ci, di, Cj, dj):
    """Nearest-point midpoints of ray pairs (k, 3) and the ray parameters (k,), (k,)."""
    w = Ci - Cj
    b = np.einsum("ka,ka->k", di, dj)
    d, e = np.einsum("ka,ka->k", di, w), np.einsum("ka,ka->k", dj, w)
    den = 1.0 - b**2
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (b * e - d) / den
        t = (e - b * d) / den
    return 0.5 * (Ci + s[:, None] * di + Cj + t[:, None] * dj), s, t


def _nearest(pred, tree, gate):
    """Per predicted point (m, 2): index of the nearest point of ``tree`` within ``gate``, else -1."""
    if tree is None or not len(pred):
        return np.full(len(pred), -1)
    p = np.where(np.isfinite(pred), pred, 1e30)
    dist, k = tree.query(p, k=1, distance_upper_bound=gate)
    return np.where(np.isfinite(dist), k, -1)


def _ideal(X, R, C, f_mm):
    """Pinhole image (k, 2) [mm] of points X (k, 3) in the ideal plane (NaN behind the camera)."""
    Xc = (X - C) @ R.T
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        return -f_mm * Xc[:, :2] / np.where(z < 0, z, np.nan)[:, None]


def _pair_candidates(f_mm, R, C, rays, q, i, j, opt, gate_mm, centres, rotations):
    """Step 1 for two images (``rays``, ``q``: their discs, indexed 0 and 1; ``centres``,
    ``rotations``: their poses): (a, b, X) of every candidate pair (gates in the ideal plane)."""
    C, R = centres, rotations
    na, nb = len(q[i]), len(q[j])
    if not na or not nb:
        return np.zeros(0, int), np.zeros(0, int), np.zeros((0, 3))
    a, b = np.repeat(np.arange(na), nb), np.tile(np.arange(nb), na)
    di, dj = rays[i][a], rays[j][b]
    cos_min = np.cos(np.radians(opt.min_angle_deg))
    ok = np.einsum("ka,ka->k", di, dj) < cos_min
    a, b, di, dj = a[ok], b[ok], di[ok], dj[ok]
    X, s, t = _midpoints(C[i][None], di, C[j][None], dj)
    ok = (s > 0) & (t > 0)
    a, b, X = a[ok], b[ok], X[ok]
    ui, uj = _ideal(X, R[i], C[i], f_mm), _ideal(X, R[j], C[j], f_mm)
    with np.errstate(invalid="ignore"):
        ok = (np.sum((ui - q[i][a]) ** 2, axis=1) <= gate_mm**2) & (np.sum((uj - q[j][b]) ** 2, axis=1) <= gate_mm**2)
    return a[ok], b[ok], X[ok]


def _accept(m, used, rays, C, R, uv, camera, opt, X_out) -> bool:
    """Step 3 for one track ``m`` (n_images,) (point per image, -1): none of its discs taken, every
    ray within the gate of the track's intersection (pixels); then taken (``used``, ``X_out``)."""
    imgs = np.flatnonzero(m >= 0)
    if any(used[k][m[k]] for k in imgs):
        return False
    d = np.stack([rays[k][m[k]] for k in imgs])
    X = _intersect(d, C[imgs])
    pred = project(np.broadcast_to(X, (len(C), 3)), R, C, camera)        # in every image
    obs = np.stack([uv[k][m[k]] for k in imgs])
    with np.errstate(invalid="ignore"):
        if not np.all(np.sum((pred[imgs] - obs) ** 2, axis=1) <= opt.gate_px**2):
            return False
        s = camera.sensor
        framed = np.isfinite(pred).all(axis=1) & (pred[:, 0] >= 0) & (pred[:, 0] <= s.width_px - 1) \
            & (pred[:, 1] >= 0) & (pred[:, 1] <= s.height_px - 1)
    if len(imgs) < opt.min_seen_fraction * framed.sum():
        return False
    for k in imgs:
        used[k][m[k]] = True
    X_out.append(X)
    return True


def _intersect(rays, centers):
    """Least-squares point nearest a track's rays (k, 3), (k, 3) -> (3,)."""
    P = np.eye(3)[None] - rays[:, :, None] * rays[:, None, :]
    return np.linalg.solve(P.sum(0), np.einsum("kab,kb->a", P, centers))


def reference_discs(camera: Camera, R_world_to_camera, center_m, uv_px, options: ReferencingOptions | None = None
                    ) -> Tracks:
    """Match the unreferenced discs ``uv_px`` (a list, one (k_i, 2) array [px] per oriented image,
    poses ``R_world_to_camera`` (n, 3, 3), ``center_m`` (n, 3) [m]) across the images (module
    docstring). Returns the :class:`Tracks`."""
    opt = options or ReferencingOptions()
    R, C = np.asarray(R_world_to_camera, float), np.asarray(center_m, float)
    uv = [np.asarray(u, float).reshape(-1, 2) for u in uv_px]
    n = len(uv)
    rays = [unproject(u, camera) @ R[i] if len(u) else np.zeros((0, 3)) for i, u in enumerate(uv)]   # R^T d
    # steps 1-2 in the ideal image plane (no Newton per candidate): q = correct(x'), the gate
    # in mm (the distortion's change of scale is a few per cent at most); step 3 in pixels
    q = [correct(camera.sensor.pixel_to_mm(u), camera.params) if len(u) else np.zeros((0, 2)) for u in uv]
    f, gate_mm = camera.f_mm, opt.gate_px * camera.sensor.pixel_mm
    trees = [cKDTree(p) if len(p) else None for p in q]
    used = [np.zeros(len(u), bool) for u in uv]
    X_out, img_out, pt_out, trk_out = [], [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(C[j] - C[i]) < opt.min_base_m:
                continue
            fi, fj = np.flatnonzero(~used[i]), np.flatnonzero(~used[j])     # discs not referenced yet
            a, b, X = _pair_candidates(f, R, C, [rays[i][fi], rays[j][fj]], [q[i][fi], q[j][fj]], 0, 1, opt,
                                       gate_mm, (C[i], C[j]), (R[i], R[j]))
            if not len(a):
                continue
            members = np.full((len(a), n), -1)
            members[:, i], members[:, j] = fi[a], fj[b]
            for k in range(n):
                if k not in (i, j):
                    members[:, k] = _nearest(_ideal(X, R[k], C[k], f), trees[k], gate_mm)
            views = (members >= 0).sum(axis=1)
            keep = np.flatnonzero(views >= opt.min_views)
            for c in keep[np.argsort(-views[keep], kind="stable")]:      # 3: most views first
                if _accept(members[c], used, rays, C, R, uv, camera, opt, X_out):
                    imgs = np.flatnonzero(members[c] >= 0)
                    img_out.extend(imgs.tolist())
                    pt_out.extend(members[c][imgs].tolist())
                    trk_out.extend([len(X_out) - 1] * len(imgs))
    return Tracks(np.array(X_out).reshape(-1, 3), np.array(img_out, np.int64), np.array(pt_out, np.int64),
                  np.array(trk_out, np.int64))
