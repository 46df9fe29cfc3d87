"""Pose hypotheses for an image with fewer than three seeds: priors and a pose-free search.

Method
------
:func:`fieldcal.field.identify.identify_image` needs a starting pose: three or more seeds
(coded targets, hand marks) or an approximate pose. This module makes approximate poses for
the other images from what the session knows once some images are oriented (a calibrated
camera, their poses); every hypothesis is only a start, verified afterwards by
:func:`fieldcal.field.identify.identify_image` and by the session's uniqueness test
(:mod:`fieldcal.field.identify_session`).

Anchored correspondences. A *pivot* is a measured point with a known or hypothesised target
(a seed, or a disc near the image centre tried against every target); its measured
neighbours, in order of distance, get targets among the pivot target's nearest neighbours in
the field. Each anchored set gives poses:

- **centre known** (:func:`poses_from_centre`; the station's position, or the centre of an
  oriented image): the rotation alone is unknown. The world directions ``w = (X - C) / |X - C|``
  and the rays of the measured points (:meth:`Camera.unproject`) are related by one
  rotation, which keeps the angle between any two of them. Two seeds give it directly
  (Kabsch's rotation of the direction pairs, :func:`rotations_from_directions`); with one
  seed or none, the pivot and its nearest measured neighbour (angle ``theta``) are paired
  with every target pair seen at ``theta`` (the star tracker's pair catalogue: a KD-tree
  of the unit directions), each pair giving one rotation;
- **a marker's corners** (:func:`poses_from_marker`): OpenCV's IPPE on the four corners of a
  square of known size gives the camera's pose relative to the marker (:func:`marker_poses`,
  two solutions); the marker lies in the field's surface, so its frame is the world's up to a
  turn ``phi`` about the surface normal at its target, which is searched in steps;
- **nothing known** (:func:`poses_pose_free`): the pivot and two measured neighbours paired
  with the pivot target and two of its field neighbours give up to four poses each by
  Grunert's P3P (:func:`p3p_batch`, every real part of the quartic's roots, vectorised
  over all triples; the rotation from the two triangles' frames).

Local support. Every pose projects the pivot target's nearest field neighbours
(:func:`local_support`); it scores the number of the pivot's nearest measured neighbours
that have a projected target within a quarter of the pivot's neighbour spacing, in three
stages (6 against 12, 8 against 25, 40 against 100), each keeping the poses tied best. Only
the best-supported poses go on to the full matching; on a field whose pattern repeats, many
poses have full local support and the session's uniqueness test decides.

Twins. :func:`field_symmetries` finds the rigid motions in the field's plane under which the
targets repeat (a regular grid's shifts, a square sheet's quarter turns); the identification
of an image has a *twin* under each (:meth:`Symmetry.pose`), which the session refines and
judges by its fit.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

from fieldcal.field.geometry import plane_frame, singular_values_centred
from fieldcal.model.camera import Camera
from fieldcal.model.opencv_frames import FLIP_YZ, ideal_pixels, opencv_camera_matrix

__all__ = ["rotations_from_directions", "p3p_batch", "local_support", "poses_from_centre",
           "poses_pose_free", "Anchor", "field_neighbours", "Symmetry", "field_symmetries",
           "marker_poses", "poses_from_marker"]

_CHUNK = 4000


def field_neighbours(X, m: int):
    """Each target's ``m`` nearest targets (itself first), (n, m) int.

    Measured in the field's best-fit plane: the depth of a facade's relief (a pilaster 0.5 m
    in front of a 0.35 m grid) would otherwise make the targets on it each other's nearest
    neighbours, while the image shows the neighbours beside them."""
    X = np.asarray(X, float)
    if len(X) >= 3:
        _, B = plane_frame(X)
        P = (X - X.mean(axis=0)) @ B[:, :2]
    else:
        P = X
    return cKDTree(P).query(P, k=m)[1].reshape(len(X), m)


def rotations_from_directions(a_cam, b_world, weights=None):
    """Rotations ``R`` (H, 3, 3) with ``a ~ R b`` in the least-squares sense (Kabsch).

    Parameters
    ----------
    a_cam, b_world : (H, k, 3) ndarrays
        Unit vectors in the camera frame and the world (k >= 2, not all parallel).
    weights : (k,) ndarray, optional

    Returns
    -------
    (H, 3, 3) ndarray
        Proper rotations (det +1), world to camera.
    """
    a = np.asarray(a_cam, float)
    b = np.asarray(b_world, float)
    if weights is not None:
        a = a * np.asarray(weights, float)[None, :, None]
    M = np.einsum("hki,hkj->hij", a, b)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U[:, :, 2] *= d[:, None]
    return U @ Vt


def grunert_distances(X, rays):
    """Distances along unit ``rays`` (H, 3, 3) to the world points ``X`` (H, 3, 3) of many triples.

    Grunert's P3P solution (as reviewed by Haralick et al., IJCV 13(3), 1994): with
    ``s2 = u s1``, ``s3 = v s1`` the law of cosines in the three triangles through the
    centre gives a quartic in ``v``. Near the "danger cylinder" two of its real roots merge
    and a little noise turns them into a complex pair; OpenCV's P3P then drops both and with
    them the right pose. Here every root contributes its real part (the pose is refined
    afterwards), so the candidate survives.

    Returns
    -------
    s : (H, 4, 3) ndarray
        ``(s1, s2, s3)`` of each of the quartic's four roots.
    good : (H, 4) bool ndarray
        Finite, positive distances.
    """
    X = np.asarray(X, float)
    rays = np.asarray(rays, float)
    H = len(X)
    a2 = np.sum((X[:, 1] - X[:, 2]) ** 2, axis=1)
    b2 = np.sum((X[:, 0] - X[:, 2]) ** 2, axis=1)
    c2 = np.sum((X[:, 0] - X[:, 1]) ** 2, axis=1)
    ca = np.sum(rays[:, 1] * rays[:, 2], axis=1)
    cb = np.sum(rays[:, 0] * rays[:, 2], axis=1)
    cg = np.sum(rays[:, 0] * rays[:, 1], axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        p, q = (a2 - c2) / b2, (a2 + c2) / b2
        A4 = (p - 1) ** 2 - 4 * c2 / b2 * ca**2
        A3 = 4 * (p * (1 - p) * cb - (1 - q) * ca * cg + 2 * c2 / b2 * ca**2 * cb)
        A2 = 2 * (p**2 - 1 + 2 * p**2 * cb**2 + 2 * (b2 - c2) / b2 * ca**2 - 4 * q * ca * cb * cg
                  + 2 * (b2 - a2) / b2 * cg**2)
        A1 = 4 * (-p * (1 + p) * cb + 2 * a2 / b2 * cg**2 * cb - (1 - q) * ca * cg)
        A0 = (1 + p) ** 2 - 4 * a2 / b2 * cg**2
        coef = np.stack([A3, A2, A1, A0], axis=1) / A4[:, None]
    ok = np.isfinite(coef).all(axis=1) & (np.abs(A4) > 1e-12)
    comp = np.zeros((H, 4, 4))
    comp[:, 0, :] = -np.where(ok[:, None], coef, 0.0)
    comp[:, 1, 0] = comp[:, 2, 1] = comp[:, 3, 2] = 1.0
    v = np.linalg.eigvals(comp).real                                   # (H, 4)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = ((p - 1)[:, None] * v**2 - 2 * (p * cb)[:, None] * v + (1 + p)[:, None]) / \
            (2 * (cg[:, None] - v * ca[:, None]))
        s1 = np.sqrt(b2[:, None] / (1 + v**2 - 2 * v * cb[:, None]))
    s = np.stack([s1, u * s1, v * s1], axis=2)                         # (H, 4, 3)
    good = ok[:, None] & np.isfinite(s).all(axis=2) & (s > 0).all(axis=2)
    return s, good


def p3p_batch(X, rays):
    """Poses of many point triples by Grunert's P3P (every real part of the quartic's roots).

    Parameters
    ----------
    X : (H, 3, 3) ndarray
        World points [m] of each triple.
    rays : (H, 3, 3) ndarray
        Unit rays of their images in the camera frame (:meth:`Camera.unproject`).

    Returns
    -------
    R : (N, 3, 3) ndarray
        World-to-camera rotations.
    C : (N, 3) ndarray
        Camera centres [m].
    source : (N,) int ndarray
        The triple each pose comes from (up to four per triple).
    """
    X = np.asarray(X, float)
    rays = np.asarray(rays, float)
    H = len(X)
    if H == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    s, good = grunert_distances(X, rays)
    h, r = np.nonzero(good)
    Pc = rays[h] * s[h, r][:, :, None]                                 # (N, 3, 3) camera frame
    Xw = X[h]
    # the rotation that takes the triangle's frame in the world to its frame in the camera (the
    # distances agree exactly, so the two triads are congruent): R = F_c F_w^T
    with np.errstate(divide="ignore", invalid="ignore"):        # a collinear triple has no frame
        R = _triad(Pc) @ np.swapaxes(_triad(Xw), 1, 2)
    C = Xw.mean(axis=1) - np.einsum("nji,nj->ni", np.nan_to_num(R), Pc.mean(axis=1))
    fin = np.isfinite(R).all(axis=(1, 2)) & np.isfinite(C).all(axis=1)
    R, C, h = R[fin], C[fin], h[fin]
    return R, C, h


def _triad(P):
    """Orthonormal frames (N, 3, 3) (columns) of point triangles (N, 3, 3): the first side, the
    normal, and their cross product."""
    e1 = P[:, 1] - P[:, 0]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e3 = np.cross(e1, P[:, 2] - P[:, 0])
    e3 /= np.linalg.norm(e3, axis=1, keepdims=True)
    return np.stack([e1, np.cross(e3, e1), e3], axis=2)


def local_support(camera: Camera, R, C, anchor, X, world_nbrs, nbr_uv, gate_px):
    """How many of a pivot's measured neighbours each pose explains.

    Compared in the ideal image plane (the measured neighbours corrected once, the targets
    projected by the pinhole alone), so no distortion is inverted per pose.

    Parameters
    ----------
    R, C : (H, 3, 3), (H, 3) ndarrays
        The poses.
    anchor : (H,) int ndarray
        The target each pose gives the pivot.
    X : (n, 3) ndarray
        Targets [m].
    world_nbrs : (n, m) int ndarray
        Each target's nearest targets (itself first).
    nbr_uv : (k, 2) ndarray
        The pivot's nearest measured neighbours [px].
    gate_px : float

    Returns
    -------
    (H,) int ndarray
        Neighbours with a projected target within ``gate_px``.
    """
    q_meas = camera.correct(camera.sensor.pixel_to_mm(np.asarray(nbr_uv, float)))       # (k, 2) [mm]
    gate_mm = gate_px * camera.sensor.pixel_mm
    tree = cKDTree(q_meas)
    f = camera.f_mm
    k = len(q_meas)
    out = np.zeros(len(R), np.int64)
    for a in range(0, len(R), _CHUNK):
        sl = slice(a, a + _CHUNK)
        P = X[world_nbrs[anchor[sl]]] - C[sl][:, None]                  # (h, m, 3)
        Pc = np.einsum("hij,hmj->hmi", R[sl], P)
        z = Pc[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            q = -f * Pc[..., :2] / np.where(z < 0, z, np.nan)[..., None]  # (h, m, 2)
        if k <= 10:       # a few measured neighbours: every distance (no tree)
            d2 = ((q[:, :, None, :] - q_meas[None, None]) ** 2).sum(axis=3)          # (h, m, k)
            out[sl] = np.sum((np.where(np.isfinite(d2), d2, np.inf) <= gate_mm**2).any(axis=1), axis=1)
            continue
        flat = q.reshape(-1, 2)
        fin = np.isfinite(flat).all(axis=1)
        j = np.full(len(flat), k)
        j[fin] = tree.query(flat[fin], distance_upper_bound=gate_mm)[1]
        hit = np.zeros((q.shape[0], k + 1), bool)                      # measured neighbours explained
        hit[np.repeat(np.arange(q.shape[0]), q.shape[1]), j] = True
        out[sl] = hit[:, :k].sum(axis=1)
    return out


class Anchor:
    """A pivot measured point, its nearest measured neighbours and the targets it may be."""

    def __init__(self, uv, nbr_uv, targets):
        self.uv = np.asarray(uv, float)               # (2,)
        self.nbr_uv = np.asarray(nbr_uv, float)       # (k, 2), nearest first
        self.targets = np.asarray(targets, np.int64)  # (t,) candidates for the pivot

    @property
    def spacing_px(self) -> float:
        return float(np.linalg.norm(self.nbr_uv[0] - self.uv))


def _two_stage(camera, R, C, anchor_t, X, world_nbrs, anchor: Anchor, keep):
    """Local support of the nearest 6 measured neighbours against 12 field neighbours, of the
    nearest 8 against 25 for the poses tied best, then of all the anchor's neighbours against
    all the field neighbours for the poses tied best again (on a grid many poses explain a small
    neighbourhood; the pattern's gaps tell them apart farther out)."""
    gate = 0.25 * anchor.spacing_px
    if len(R) == 0:
        return []
    # a cheap first cut: the 6 nearest measured neighbours against 12 field neighbours
    zero = local_support(camera, R, C, anchor_t, X, world_nbrs[:, :12], anchor.nbr_uv[:6], gate)
    k = np.flatnonzero(zero >= zero.max() - 1)
    R, C, anchor_t = R[k], C[k], anchor_t[k]
    first = local_support(camera, R, C, anchor_t, X, world_nbrs[:, :25], anchor.nbr_uv[:8], gate)
    best = first >= first.max() - 1
    k = np.flatnonzero(best)
    second = local_support(camera, R[k], C[k], anchor_t[k], X, world_nbrs, anchor.nbr_uv, gate)
    return _top(second, R[k], C[k], anchor_t[k], keep)


def _top(scores, R, C, anchor, keep):
    """The ``keep`` best-supported poses, and every pose tied with the last of them."""
    order = np.argsort(-scores, kind="stable")
    if len(order) > keep:
        order = order[scores[order] >= scores[order[keep - 1]]][:20 * keep]
    return [(R[k], C[k], int(scores[k]), int(anchor[k])) for k in order]


def poses_from_centre(camera: Camera, center_m, X, world_nbrs, anchor: Anchor, *, seeds=None,
                      angle_tol: float = 0.08, keep: int = 20):
    """Rotations for a known camera centre (module docstring), best local support first.

    Parameters
    ----------
    camera : Camera
        The calibrated camera.
    center_m : (3,) array_like
        The prior centre [m].
    X : (n, 3) ndarray
        Targets [m] (the pivot's candidates and their neighbours index it).
    world_nbrs : (n, m) int ndarray
        Each target's nearest targets, itself first.
    anchor : Anchor
    seeds : (targets (k,), uv (k, 2)), optional
        With two or more seeds the rotation comes from them alone.
    angle_tol : float
        Relative tolerance of the pivot-neighbour angle (relief, the centre's error).
    keep : int
        Hypotheses returned.

    Returns
    -------
    list of (R (3, 3), C (3,), support, pivot target)
    """
    C = np.asarray(center_m, float)
    w = X - C
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    direct = []
    if seeds is not None and len(seeds[0]) >= 2:
        rays = camera.unproject(np.asarray(seeds[1], float))
        R = rotations_from_directions(rays[None], w[np.asarray(seeds[0])][None])
        direct = [(R[0], C, len(seeds[0]), int(seeds[0][0]))]
    r_p, r_q = camera.unproject(np.stack([anchor.uv, anchor.nbr_uv[0]]))
    theta = float(np.arccos(np.clip(r_p @ r_q, -1, 1)))
    lo, hi = 2 * np.sin(theta * (1 - angle_tol) / 2), 2 * np.sin(theta * (1 + angle_tol) / 2)
    tree = cKDTree(w)
    k_list, k2_list = [], []
    for k, ball in zip(anchor.targets, tree.query_ball_point(w[anchor.targets], hi), strict=True):
        ball = np.asarray(ball, np.int64)
        ball = ball[np.linalg.norm(w[ball] - w[k], axis=1) >= lo]
        k_list.append(np.full(len(ball), k))
        k2_list.append(ball)
    k1 = np.concatenate(k_list) if k_list else np.zeros(0, np.int64)
    k2 = np.concatenate(k2_list) if k2_list else np.zeros(0, np.int64)
    if len(k1) == 0:
        return direct
    a = np.broadcast_to(np.stack([r_p, r_q]), (len(k1), 2, 3))
    R = rotations_from_directions(a, np.stack([w[k1], w[k2]], axis=1))
    Cs = np.broadcast_to(C, (len(k1), 3))
    return direct + _two_stage(camera, R, Cs, k1, X, world_nbrs, anchor, keep)


def poses_pose_free(camera: Camera, X, world_nbrs, anchor: Anchor, *, second=None, n_first: int = 5,
                    n_second: int = 7, keep: int = 20):
    """Poses from the pivot and two measured neighbours by P3P (module docstring).

    ``second`` (target index, uv [px]) is a second seed, used as the first neighbour; otherwise its
    is one of the pivot target's ``n_first`` nearest field neighbours, and the second
    neighbour's one of its ``n_second`` nearest. Returns the best-supported poses as
    :func:`poses_from_centre` does.
    """
    nb = anchor.nbr_uv
    if len(nb) < 3:
        return []
    # the second neighbour: the nearest one well off the pivot-first-neighbour line
    d1 = nb[0] - anchor.uv
    cross = np.abs(d1[0] * (nb[1:, 1] - anchor.uv[1]) - d1[1] * (nb[1:, 0] - anchor.uv[0]))
    sin = cross / (np.linalg.norm(d1) * np.linalg.norm(nb[1:] - anchor.uv, axis=1))
    off = np.flatnonzero(sin > 0.5)
    if len(off) == 0:
        return []
    j2 = 1 + int(off[0])
    first_uv = nb[0] if second is None else np.asarray(second[1], float)
    rays = camera.unproject(np.stack([anchor.uv, first_uv, nb[j2]]))
    k = anchor.targets
    m = world_nbrs.shape[1]
    c1 = (np.full((len(k), 1), int(second[0])) if second is not None else world_nbrs[k, 1:1 + min(n_first, m - 1)])
    c2 = world_nbrs[k, 1:1 + min(n_second, m - 1)]
    K0 = np.repeat(k, c1.shape[1] * c2.shape[1])
    K1 = np.repeat(c1.reshape(-1), c2.shape[1])
    K2 = np.repeat(c2, c1.shape[1], axis=0).reshape(-1)
    ok = (K1 != K2) & (K0 != K2) & (K0 != K1)
    K0, K1, K2 = K0[ok], K1[ok], K2[ok]
    if len(K0) == 0:
        return []
    R, C, src = p3p_batch(np.stack([X[K0], X[K1], X[K2]], axis=1), np.broadcast_to(rays, (len(K0), 3, 3)))
    if len(R) == 0:
        return []
    return _two_stage(camera, R, C, K0[src], X, world_nbrs, anchor, keep)


class Symmetry:
    """A rigid motion that maps much of the target field onto itself (a wrong identification's twin).

    ``X' = R X + t`` is a rotation about the field plane's normal and a shift in the plane;
    ``perm[k]`` is the target that target ``k`` lands on (-1 where none), and ``overlap`` the
    number of targets that land on one.
    """

    def __init__(self, R, t, perm, overlap: int):
        self.R = np.asarray(R, float)
        self.t = np.asarray(t, float)
        self.perm = np.asarray(perm, np.int64)
        self.overlap = int(overlap)

    def pose(self, R_world_to_camera, center_m):
        """The twin of a pose: what the camera would see with every target replaced by its image
        under the symmetry (``R R_T^T``, ``R_T C + t``)."""
        return np.asarray(R_world_to_camera, float) @ self.R.T, self.R @ np.asarray(center_m, float) + self.t


def _plane_motion(origin, B, theta, Pa, Pb):
    """The 3-D motion of a plane motion ``p -> Pb + R(theta) (p - Pa)`` in the frame ``(origin, B)``."""
    c, s = np.cos(theta), np.sin(theta)
    Rp = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    R = B @ Rp @ B.T
    t = origin - R @ origin + B @ (np.append(Pb, 0.0) - Rp @ np.append(Pa, 0.0))
    return R, t


def field_symmetries(X, *, tol: float = 0.15, min_repeat: float = 0.97, min_overlap: float = 0.2,
                     max_count: int = 400, seed: int = 0) -> list[Symmetry]:
    """The rigid motions in the field's plane under which its targets repeat (twins).

    Measured in the best-fit plane (the relief is left to the residuals of an identification):
    a motion maps target ``a`` (one of three near the centroid) onto a target ``b`` and turns the
    direction to ``a``'s nearest neighbour into the direction from ``b`` to one of its neighbours
    at the same distance. It is kept when ``a``'s six nearest neighbours land on targets, and
    of the targets that land inside the field (within 1.5 spacings of a target) at least
    ``min_repeat`` land on one (within ``tol`` spacings), at least ``min_overlap`` of all. A
    field with random gaps repeats only where its gaps do (about the fraction of targets kept),
    a regular grid everywhere it overlaps itself; a square sheet also under quarter turns.

    Parameters
    ----------
    X : (n, 3) ndarray
        Targets [m].

    Returns
    -------
    list of Symmetry
        Largest overlap first (at most ``max_count``), the identity excluded.
    """
    X = np.asarray(X, float)
    n = len(X)
    if n < 8:
        return []
    origin, B = plane_frame(X)
    P = (X - origin) @ B[:, :2]
    tree = cKDTree(P)
    try:
        facets = ConvexHull(P).equations                  # a . p + b <= 0 inside
    except QhullError:
        return []
    d, nn = tree.query(P, k=7)
    s = float(np.median(d[:, 1]))
    anchors = np.argsort(np.linalg.norm(P - P.mean(axis=0), axis=1))[:3]
    cands = []
    for a in anchors:
        da = P[nn[a, 1]] - P[a]
        la, phi = np.linalg.norm(da), np.arctan2(da[1], da[0])
        # every target b and every neighbour of b at a's nearest-neighbour distance
        rows, cols = np.nonzero(np.abs(d[:, 1:] - la) <= 0.1 * la)
        b = rows
        db = P[nn[rows, cols + 1]] - P[b]
        theta = np.arctan2(db[:, 1], db[:, 0]) - phi
        c, si = np.cos(theta), np.sin(theta)
        O = P[nn[a, 1:]] - P[a]                                            # (6, 2)
        mapped = P[b][:, None] + np.stack([c[:, None] * O[:, 0] - si[:, None] * O[:, 1],
                                           si[:, None] * O[:, 0] + c[:, None] * O[:, 1]], axis=2)
        hit = tree.query(mapped.reshape(-1, 2), distance_upper_bound=tol * s)[0].reshape(len(b), 6)
        ok = np.isfinite(hit).all(axis=1)
        cands += [(a, int(bb), float(th)) for bb, th in zip(b[ok], theta[ok], strict=True)]
    if not cands:
        return []
    A = np.array([c[0] for c in cands])
    Bt = np.array([c[1] for c in cands])
    TH = np.array([c[2] for c in cands])
    rng = np.random.default_rng(seed)
    out: list[Symmetry] = []
    seen: set = set()
    for size in (40, n):
        sample = np.sort(rng.choice(n, size, replace=False)) if size < n else np.arange(n)
        keep = np.zeros(len(A), bool)
        perms = np.full((len(A), len(sample)), -1, np.int64)
        step = max(1, 200000 // len(sample))
        for lo in range(0, len(A), step):
            sl = slice(lo, lo + step)
            c, si = np.cos(TH[sl])[:, None], np.sin(TH[sl])[:, None]
            Q = P[sample][None] - P[A[sl]][:, None]                         # (h, m, 2)
            M = P[Bt[sl]][:, None] + np.stack([c * Q[..., 0] - si * Q[..., 1], si * Q[..., 0] + c * Q[..., 1]],
                                              axis=2)
            dist, j = tree.query(M.reshape(-1, 2))
            on = (dist <= tol * s).reshape(M.shape[:2])
            inside = on | ((M @ facets[:, :2].T + facets[:, 2]).max(axis=2) <= 1e-9 * s)
            n_on = on.sum(axis=1)
            keep[sl] = (n_on >= min_repeat * np.maximum(inside.sum(axis=1), 1)) & (n_on >= min_overlap * len(sample))
            perms[sl] = np.where(on, j.reshape(M.shape[:2]), -1)
        A, Bt, TH, perms = A[keep], Bt[keep], TH[keep], perms[keep]
    for a, b, th, perm in zip(A, Bt, TH, perms, strict=True):
        key = perm.tobytes()
        if key in seen or np.array_equal(perm, np.arange(n)):
            continue
        seen.add(key)
        R, t = _plane_motion(origin, B, th, P[a], P[b])
        out.append(Symmetry(R, t, perm, int(np.sum(perm >= 0))))
    out.sort(key=lambda sym: -sym.overlap)
    return out[:max_count]


def marker_poses(camera: Camera, corners_px, marker_size_m: float):
    """Poses of a square marker relative to the camera from its four corners (OpenCV's IPPE).

    Parameters
    ----------
    corners_px : (4, 2) array_like
        The outer corners in OpenCV's order (top-left, top-right, bottom-right, bottom-left of
        the printed marker) [px].
    marker_size_m : float
        Its side [m].

    Returns
    -------
    list of (R_marker_to_camera (3, 3), centre (3,))
        In fieldcal's camera frame; the marker frame has ``x`` to the printed marker's right,
        ``y`` up and ``z`` out of its face. Up to two solutions (IPPE's).
    """
    h = 0.5 * float(marker_size_m)
    obj = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    img = ideal_pixels(np.asarray(corners_px, float).reshape(4, 2), camera)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2),
                                                 opencv_camera_matrix(camera), None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error:
        return []
    out = []
    for k in range(n):
        R_cv, _ = cv2.Rodrigues(np.asarray(rvecs[k], float).reshape(3, 1))
        out.append((FLIP_YZ @ R_cv, FLIP_YZ @ np.asarray(tvecs[k], float).ravel()))
    return out


def _local_normal(X, world_nbrs, t, normals=None):
    """The field's surface normal at target ``t``: the given normal, else the plane of its 12
    nearest targets (in the field's plane), else the field's plane."""
    if normals is not None:
        n = np.asarray(normals, float)[t]
        return n / np.linalg.norm(n)
    P = X[world_nbrs[t, :12]]
    s = singular_values_centred(P)
    _, B = plane_frame(P if s[2] < 0.2 * s[1] else X)
    return B[:, 2]


def poses_from_marker(camera: Camera, corners_px, marker_size_m: float, t: int, X, world_nbrs, anchor: Anchor, *,
                      normals=None, step_deg: float = 1.0, keep: int = 20):
    """Poses from one coded target's marker: its corners give the camera's pose relative to the
    marker; the marker's turn in the field's surface is searched (module docstring).

    The marker frame ``(x, y, z)`` relates to the world by a rotation that takes the surface
    normal at the target to ``z`` and is otherwise a free turn ``phi`` about it; for each
    ``phi`` (``step_deg`` apart), IPPE solution and sign of the normal,
    ``R = R_marker_to_camera R_world_to_marker(phi)``, ``C = X_t - R^T c`` with ``c`` the
    marker's centre in the camera frame. Returned as :func:`poses_from_centre` does (best local
    support first, the marker's target as the pivot).
    """
    sols = marker_poses(camera, corners_px, marker_size_m)
    if not sols:
        return []
    n = _local_normal(X, world_nbrs, t, normals)
    phi = np.radians(np.arange(0.0, 360.0, step_deg))
    Rs, Cs = [], []
    for sign in (1.0, -1.0):
        z = sign * n
        e1 = np.cross(z, [0.0, 0.0, 1.0] if abs(z[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        R0 = np.stack([e1, np.cross(z, e1), z])                         # world -> a marker frame
        c, s = np.cos(phi), np.sin(phi)
        Rz = np.zeros((len(phi), 3, 3))
        Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, s, -s, c, 1.0
        R_wm = Rz @ R0
        for R_mc, centre in sols:
            R = R_mc @ R_wm
            Rs.append(R)
            Cs.append(X[t] - np.einsum("hji,j->hi", R, centre))
    R = np.concatenate(Rs)
    C = np.concatenate(Cs)
    return _two_stage(camera, R, C, np.full(len(R), int(t)), X, world_nbrs, anchor, keep)
