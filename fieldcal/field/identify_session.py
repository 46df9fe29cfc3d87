"""Identification of the images that have too few seeds, in a robust order (issue 11).

Method
------
The images with three or more seeds (coded targets, hand marks) are identified first
(:func:`fieldcal.field.identify.identify_images`) and adjusted; the calibrated camera and
the oriented images then give *pose priors* for every other image
(:func:`identify_remaining`), in this order, each image's first accepted start winning:

1. **its own seeds** (three or more) with the calibrated camera;
2. **the station**: the images of one station (the manifest's ``station``) share a
   position, so an oriented image of the same station gives the centre and only the
   rotation is searched (:func:`fieldcal.field.pose_search.poses_from_centre`: two seeds
   give it directly, one seed or none a star tracker's pair search);
3. **a single coded target**: its marker's four corners (``corners_px``) and its size give the
   camera's pose relative to the marker (OpenCV's IPPE), up to the marker's turn in the
   field's surface, which is searched (:func:`fieldcal.field.pose_search.poses_from_marker`);
4. **pose-free**: P3P over triples of a pivot and its measured neighbours against the field's
   neighbourhoods (:func:`fieldcal.field.pose_search.poses_pose_free`), with the seeds as
   pivots where there are any, one pivot after the other;
5. **the neighbouring images**: without a station, the centres of the oriented images
   (clustered) are tried as in 2.

All pending images advance together, in *waves*: each takes its next untried start, the
cheap ones (1-3) first and the searches (4, 5) only when no image has a cheap start left;
the hypotheses of all of them are refined in one call
(:func:`fieldcal.field.identify.identify_views`). Newly oriented images give their station's
centre to the images still left; the loop ends when no image has a start left.

Verification
------------
Every start's best hypotheses (local support, then the targets they pair in the whole frame)
are refined (which checks the fit and the expected fraction, :mod:`fieldcal.field.identify`).
Each result's *evidence* (:func:`evidence`) is measured inside the area it identifies:

- ``n``: identified discs; ``extra``: measured discs left unexplained there; ``missed``:
  targets predicted there and not found. A right identification explains nearly every dot
  of its own area, a foreign image or a pose shifted along a repeating pattern does not;
- ``q``: the scatter of the identified points' residuals after the local correction (the
  median of the neighbours' residuals, which takes up what the camera model still lacks),
  each normalised by its expected sigma (the detector's sigma and the target's coordinate
  sigma seen from the pose); 1 at the noise.

A result is *admissible* when its seeds agree, its camera is on the side of the field the
oriented cameras are on (a flat field's mirror image fits as well, seen from behind),
``extra`` stays within what the oriented images show (their rate plus ``extra_sigmas`` Poisson
sigmas), ``missed`` within ``max_missed`` of ``n`` (real images miss targets in patches) and ``q``
within ``max_fit_factor`` of theirs. Where the field repeats
(:func:`fieldcal.field.pose_search.field_symmetries`: a regular grid shifted by its step, a
square sheet turned by a quarter), the best result's *twins* (its identities moved by each
symmetry, the pose moved with them) are refined and judged too. Among the admissible results
(grouped: two results are one when they share half of their identities) with at least
``max_ambiguity`` of the best evidence, the one that fits best (smallest ``q``) is accepted
when every other fits at least ``min_fit_ratio`` times worse (e.g. the relief, or the
unevenness of a sheet, that a twin puts in the wrong place); otherwise the image is
ambiguous: it is never accepted on a guess, and its competitors are judged again after the
next adjustment, whose camera may tell them apart.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import pyarrow as pa
from scipy.spatial import ConvexHull, QhullError, cKDTree

from fieldcal.field.geometry import plane_frame
from fieldcal.field.identify import (
    IdentifyOptions,
    ImageIdentification,
    identify_images,
    identify_views,
    measured_points,
)
from fieldcal.field.matching import ViewMatcher, local_correction
from fieldcal.field.pose_search import (
    Anchor,
    field_neighbours,
    field_symmetries,
    poses_from_centre,
    poses_from_marker,
    poses_pose_free,
)
from fieldcal.model.camera import Camera
from fieldcal.session.data import TargetField

__all__ = ["identify_remaining", "evidence", "Evidence", "PriorOptions", "REASON_AMBIGUOUS", "REASON_NO_START"]

REASON_AMBIGUOUS = "ambiguous"
REASON_NO_START = "not identified"


@dataclass(frozen=True)
class PriorOptions:
    """Settings of :func:`identify_remaining` (module docstring).

    Attributes
    ----------
    max_ambiguity : float
        Results with at least this fraction of the best evidence compete for the image.
    min_fit_ratio : float
        The accepted result must fit at least this much better (``q``) than every competitor.
    max_fit_factor : float
        Largest ``q`` relative to the oriented images' (at least 2).
    max_missed : float
        Largest share of missed targets (relative to the identified ones).
    extra_sigmas : float
        Unexplained discs allowed beyond the oriented images' rate, in Poisson sigmas.
    max_iterations : int
        Rounds of matching and pose refinement of a hypothesis at most.
    n_pivots : int
        Discs near the image centre tried as pivots when there are no seeds.
    n_refine : int
        Hypotheses per start refined.
    n_twins : int
        Twins (field symmetries) of an accepted result refined, the best-supported first.
    min_discs : int
        Images with fewer measured discs are not searched.
    """

    max_ambiguity: float = 0.6
    min_fit_ratio: float = 2.0
    max_fit_factor: float = 4.0
    max_missed: float = 0.5
    extra_sigmas: float = 3.0
    max_iterations: int = 6
    n_pivots: int = 2
    n_refine: int = 4
    n_twins: int = 12
    min_discs: int = 12


@dataclass(frozen=True)
class Evidence:
    """How well an identification explains its image (module docstring)."""

    n: int
    extra: int
    missed: int
    q: float

    @property
    def score(self) -> int:
        return self.n - self.extra - self.missed


@dataclass
class _Image:
    index: int
    name: str
    table: pa.Table
    uv_all: np.ndarray          # (rows, 2) [px]
    disc: np.ndarray            # (rows,) usable discs
    sigma_px: np.ndarray        # (rows,) the detector's sigma
    seeds_t: np.ndarray         # (s,) seed targets (markers named by their code, marks)
    seeds_uv: np.ndarray        # (s, 2)
    corners: list               # [(target, (4, 2) corners [px])] of the markers
    station: str | None
    tried: set = field(default_factory=set)     # prior centres and searches already tried
    hint: tuple | None = None                   # competitors of an earlier call: (start, poses)
    ambiguous: bool = False

    @property
    def uv(self) -> np.ndarray:
        return self.uv_all[self.disc]


def evidence(table: pa.Table, target: np.ndarray, R, C, camera: Camera, X, match_target, sigma_m,
             neighbours: int = 8, *, parsed=None) -> Evidence:
    """The evidence of an identification (module docstring).

    Parameters
    ----------
    table : pyarrow.Table
        The image's measurements.
    target : (rows,) int ndarray
        The identified target of every row (-1 for none).
    R, C : (3, 3), (3,) ndarrays
        The pose.
    camera : Camera
    X : (n, 3) ndarray
        Targets [m].
    match_target : (n,) bool ndarray
        Targets that appear as discs.
    sigma_m : (n,) ndarray
        Targets' coordinate sigmas [m].
    parsed : (uv (rows, 2), usable discs (rows,), sigma_px (rows,)), optional
        The table's columns, when the caller has them already.

    Returns
    -------
    Evidence
    """
    if parsed is None:
        kind, _, uv_all, usable = measured_points(table)
        parsed = (uv_all, (kind == "disc") & usable, _sigma(table))
    uv_all, disc, sig_all = parsed
    found = disc & (target >= 0)
    n = int(found.sum())
    if n < 4 or R is None:
        return Evidence(n, 0, 0, np.inf)
    try:
        facets = ConvexHull(uv_all[found]).equations            # a . p + b <= 0 inside
    except QhullError:
        return Evidence(n, 0, 0, np.inf)

    def inside(p):
        with np.errstate(invalid="ignore"):
            return (p @ facets[:, :2].T + facets[:, 2]).max(axis=1) <= 1e-9

    extra = disc & ~found & inside(uv_all)
    pred = _project_near(camera, X, R, C)
    ok = match_target & np.isfinite(pred).all(axis=1)
    ok[target[found]] = False
    k = np.flatnonzero(ok)
    missed = int(np.sum(inside(pred[k]))) if len(k) else 0
    t = target[found]
    res = uv_all[found] - pred[t]
    sig = sig_all[found]
    depth = np.abs((X[t] - C) @ R[2])
    prior = sigma_m[t] * camera.f_mm / depth / camera.sensor.pixel_mm
    if n > neighbours + 1:
        corr, _ = local_correction(pred[t], pred[t], res, np.arange(n), neighbours=neighbours)
        res = res - corr
    z2 = np.sum(res**2, axis=1) / (sig**2 + prior**2)
    return Evidence(n, int(extra.sum()), missed, float(np.sqrt(np.mean(z2) / 2.0)))


def _project_near(camera: Camera, X, R, C):
    """:meth:`Camera.project` of the targets within 1.5 times the frame's half-size in the ideal
    image (NaN for the others: a large field is mostly out of view)."""
    Xc = (X - C) @ np.asarray(R).T
    s = camera.sensor
    reach = 1.5 * 0.5 * np.array([s.width_px, s.height_px]) * s.pixel_mm
    with np.errstate(divide="ignore", invalid="ignore"):
        q = -camera.f_mm * Xc[:, :2] / Xc[:, 2:3]
    near = (Xc[:, 2] < 0) & (np.abs(q) <= reach).all(axis=1)
    out = np.full((len(X), 2), np.nan)
    if near.any():
        out[near] = s.mm_to_pixel(camera.distort(q[near], check=False))
    return out


def _sigma(table: pa.Table) -> np.ndarray:
    n = table.num_rows
    if "sigma_px" not in table.column_names:
        return np.full(n, 0.1)
    s = np.asarray(table.column("sigma_px").fill_null(np.nan).to_numpy(zero_copy_only=False), float)
    med = np.nanmedian(s) if np.isfinite(s).any() else 0.1
    return np.where(np.isfinite(s) & (s > 0), s, med)


@dataclass
class _Result:
    ident: ImageIdentification
    ev: Evidence
    ids: set

    @property
    def score(self) -> int:
        return self.ev.score


def _group(results: list[_Result]) -> list[_Result]:
    """Results that share at least half of their identities are one; each group's best fit."""
    groups: list[list[_Result]] = []
    for r in results:
        for g in groups:
            if len(r.ids & g[0].ids) >= 0.5 * min(len(r.ids), len(g[0].ids)):
                g.append(r)
                break
        else:
            groups.append([r])
    return [min(g, key=lambda r: (r.ev.q, -r.score)) for g in groups]


class _Context:
    """What every image's search shares: the camera, targets, neighbourhoods, settings."""

    def __init__(self, camera, targets: TargetField, sigma_m, codes_are_markers, options, prior, marker_size_m):
        self.camera = camera
        self.targets = targets
        self.X = np.asarray(targets.xyz_m, float)
        n = len(self.X)
        self.sigma_m = (np.full(n, 0.0) if sigma_m is None else
                        np.broadcast_to(np.asarray(sigma_m, float), (n,)).copy())
        self.coded = codes_are_markers
        self.options = options
        # a hypothesis that is right settles in a few rounds (the camera is calibrated); one that
        # keeps changing its pairs is wrong and is not followed further
        self.refine_options = replace(options, max_iterations=min(options.max_iterations, prior.max_iterations))
        self.prior = prior
        self.marker_size_m = marker_size_m
        tcodes = np.asarray(targets.codes, np.int64)
        self.match = tcodes < 0 if codes_are_markers else np.ones(n, bool)
        self.code_to_target = dict(zip(tcodes[tcodes >= 0].tolist(), np.flatnonzero(tcodes >= 0).tolist(), strict=True))
        self.world_nbrs = field_neighbours(self.X, min(100, n))
        self._symmetries = None
        self.rate0, self.q0 = 0.02, 1.0
        self.origin, B = plane_frame(self.X)
        self.front = B[:, 2]            # the side of the field's plane the cameras are on (calibrate_checks)
        self.front_known = False

    @property
    def symmetries(self):
        if self._symmetries is None:
            self._symmetries = field_symmetries(self.X[self.match])
        return self._symmetries

    def calibrate_checks(self, reference) -> None:
        """The evidence of the oriented images (their identification and pose): the rate of
        unexplained discs and the fit ``q`` that a right identification shows."""
        rates, qs, side = [], [], []
        for table, target, R, C in reference:
            side.append(float((C - self.origin) @ self.front))
            ev = evidence(table, target, R, C, self.camera, self.X, self.match, self.sigma_m)
            if ev.n >= self.options.min_identified and np.isfinite(ev.q):
                rates.append(ev.extra / ev.n)
                qs.append(ev.q)
        if rates:
            self.rate0, self.q0 = float(np.median(rates)), float(np.median(qs))
        if side:
            self.front = self.front * (1.0 if np.median(side) >= 0 else -1.0)
            self.front_known = True

    def in_front(self, C) -> bool:
        """Is a camera centre on the side of the field the oriented cameras are on? (A planar
        field's mirror image, seen from behind, would fit every dot as well.)"""
        return not self.front_known or float((np.asarray(C) - self.origin) @ self.front) > 0

    def admissible(self, ev: Evidence) -> bool:
        """Few unexplained discs (the oriented images' rate plus three Poisson sigmas), few missed
        targets (a quarter of the identified: real images miss targets in patches, to glare or
        blur), and a fit near the oriented images'."""
        allowed = self.rate0 * ev.n + self.prior.extra_sigmas * np.sqrt(self.rate0 * ev.n + 1.0)
        return bool(ev.n >= self.options.min_identified and ev.extra <= allowed
                    and ev.missed <= max(allowed, self.prior.max_missed * ev.n)
                    and ev.q <= self.prior.max_fit_factor * max(self.q0, 0.5))

    def results(self, items) -> list[list[_Result]]:
        """The poses of several images refined together (``items``: (image, poses, marks)), each
        with its evidence; only results whose seeds agree and whose camera is in front."""
        views = identify_views([img.table for img, _, _ in items], self.targets, self.camera,
                               [poses for _, poses, _ in items], marks=[m for _, _, m in items],
                               target_sigma_m=self.sigma_m, codes_are_markers=self.coded,
                               options=self.refine_options, names=[img.name for img, _, _ in items])
        out = []
        for (img, _, _), idents in zip(items, views, strict=True):
            rs = []
            for ident in idents:
                if not ident.ok or len(ident.wrong_marks) or len(ident.wrong_codes) or \
                        not self.in_front(ident.center_m):
                    continue
                ev = evidence(img.table, ident.target, ident.R_world_to_camera, ident.center_m, self.camera, self.X,
                              self.match, self.sigma_m, parsed=(img.uv_all, img.disc, img.sigma_px))
                rows = np.flatnonzero(ident.target >= 0)
                rs.append(_Result(ident, ev, set(zip(rows.tolist(), ident.target[rows].tolist(), strict=True))))
            out.append(rs)
        return out

    def _score(self, images: list[_Image], poses) -> list[np.ndarray]:
        """Targets each pose pairs with the first gates (:meth:`ViewMatcher.score`), per image."""
        vm = ViewMatcher(self.X, self.match, self.camera, self.options, [img.uv for img in images], self.sigma_m)
        image = np.array([k for k, p in enumerate(poses) for _ in p], np.int64)
        out = [np.zeros(0, np.int64) for _ in images]
        if len(image):
            flat = [q for p in poses for q in p]
            count = vm.score(image, np.stack([q[0] for q in flat]), np.stack([q[1] for q in flat]))[0]
            for k in range(len(images)):
                out[k] = count[image == k]
        return out

    def twins(self, img: _Image, res: _Result):
        """Poses of the result's twins under the field's symmetries, those that keep most of
        its identities first."""
        if not self.symmetries:
            return []
        match_index = np.flatnonzero(self.match)
        local = np.full(len(self.X), -1)
        local[match_index] = np.arange(len(match_index))
        t = res.ident.target[res.ident.target >= 0]
        t = local[t[self.match[t]]]
        kept = np.array([np.sum(sym.perm[t] >= 0) for sym in self.symmetries])
        order = np.argsort(-kept, kind="stable")
        order = order[kept[order] >= self.prior.max_ambiguity * len(t)][: self.prior.n_twins]
        return [self.symmetries[k].pose(res.ident.R_world_to_camera, res.ident.center_m) for k in order]

    def anchors(self, img: _Image) -> list[Anchor]:
        """Pivots: the seeds (their targets fixed), else discs near the image centre."""
        uv = img.uv
        tree = cKDTree(uv)
        k = min(41, len(uv))
        out = []
        for t, p in zip(img.seeds_t, img.seeds_uv, strict=True):
            d, j = tree.query(p, k=k)
            j = j[d > 1e-6][:40]
            out.append(Anchor(p, uv[j], [t]))
        if out:
            return out
        s = self.camera.sensor
        centre = np.array([(s.width_px - 1) / 2, (s.height_px - 1) / 2])
        _, piv = tree.query(centre, k=min(self.prior.n_pivots, len(uv)))
        for p in np.atleast_1d(piv):
            _, j = tree.query(uv[p], k=k)
            out.append(Anchor(uv[p], uv[j[1:]], np.flatnonzero(self.match)))
        return out

    def global_rank(self, img: _Image, hyps):
        """Hypotheses ordered by the targets they pair in the whole frame (first gate)."""
        if not hyps:
            return []
        uv_m = img.uv
        tree = cKDTree(uv_m)
        nn = tree.query(uv_m, k=2)[0][:, 1]
        gate = 0.3 * float(np.median(nn))
        Xm = self.X[self.match]
        R = np.stack([h[0] for h in hyps])
        C = np.stack([h[1] for h in hyps])
        uv = self.camera.project(Xm[None], R[:, None], C[:, None])            # (H, n, 2)
        s = self.camera.sensor
        inside = np.isfinite(uv).all(axis=2) & (uv[..., 0] > -0.5) & (uv[..., 1] > -0.5) & \
            (uv[..., 0] < s.width_px - 0.5) & (uv[..., 1] < s.height_px - 0.5)
        flat = np.where(inside[..., None], uv, -1e9).reshape(-1, 2)
        d, j = tree.query(flat, distance_upper_bound=gate)
        hit = (d <= gate).reshape(uv.shape[:2])
        j = j.reshape(uv.shape[:2])
        score = np.array([len(np.unique(j[h][hit[h]])) for h in range(len(hyps))])
        order = np.argsort(-score, kind="stable")
        return [(hyps[k][0], hyps[k][1], int(score[k])) for k in order]

    def _top_poses(self, img: _Image, hyps):
        poses = []
        for R, C, score in self.global_rank(img, hyps):
            if len(poses) >= self.prior.n_refine or score < self.options.min_identified:
                break
            if any(np.linalg.norm(C - C2) < 1e-3 * (1 + np.linalg.norm(C)) and np.abs(R - R2).max() < 1e-3
                   for R2, C2 in poses):
                continue
            poses.append((R, C))
        return poses

    def decide(self, items):
        """For several images (``items``: (image, hypotheses, marks)), refine the best hypotheses
        and the twins of the best result, all images together; per image the accepted
        identification (or None), the reason, and when ambiguous the poses of the competing
        results (to judge again later)."""
        results = self.results([(img, self._top_poses(img, hyps), m) for img, hyps, m in items])
        results = [[r for r in rs if self.admissible(r.ev)] for rs in results]
        twins, best = [], []
        for (img, _, _), rs in zip(items, results, strict=True):
            best.append(max(rs, key=lambda r: (r.score, -r.ev.q)) if rs else None)
            twins.append(self.twins(img, best[-1]) if rs else [])
        # the twins that pair nearly as many targets as the best result are refined too
        counts = self._score([img for img, _, _ in items], twins)
        twins = [[p for p, c in zip(tw, cnt, strict=True) if c >= self.prior.max_ambiguity * b.ev.n] if b else []
                 for tw, cnt, b in zip(twins, counts, best, strict=True)]
        more = self.results([(img, tw, m) for (img, _, m), tw in zip(items, twins, strict=True)])
        return [self._choose(rs + [r for r in rs2 if self.admissible(r.ev)]) if rs else (None, "", [])
                for rs, rs2 in zip(results, more, strict=True)]

    def _choose(self, results):
        """The best-fitting of the results with nearly the best evidence, unless another fits
        almost as well (module docstring)."""
        groups = _group(results)
        top = max(r.score for r in groups)
        contenders = sorted((r for r in groups if r.score >= self.prior.max_ambiguity * top), key=lambda r: r.ev.q)
        win = contenders[0]
        if len(contenders) > 1 and contenders[1].ev.q < self.prior.min_fit_ratio * win.ev.q:
            other = contenders[1]
            return None, (f"{REASON_AMBIGUOUS}: two different identifications fit almost equally "
                          f"({win.ev.n} targets, fit {win.ev.q:.2g}, and {other.ev.n}, fit {other.ev.q:.2g}; "
                          "a repeating pattern of targets?)"), \
                [(r.ident.R_world_to_camera, r.ident.center_m) for r in contenders]
        return win.ident, "", []


def _centres(img: _Image, oriented, stations):
    """Prior centres: the station's oriented images, else every oriented image (clustered)."""
    same = [C for i, (_, C) in oriented.items() if img.station is not None and stations[i] == img.station]
    if same:
        return "station", [np.mean(same, axis=0)]
    if not oriented:
        return "neighbours", []
    Cs = np.stack([C for _, C in oriented.values()])
    out: list[np.ndarray] = []
    span = max(float(np.ptp(Cs, axis=0).max()), 1e-9)
    for C in Cs:
        if all(np.linalg.norm(C - c) > 0.02 * span for c in out):
            out.append(C)
    return "neighbours", out


def _next_step(ctx: _Context, img: _Image, oriented, stations, cheap: bool):
    """The image's next untried start (module docstring), as ``(kind, hypotheses)``, or None.

    ``cheap``: only the starts that need no search (competitors of an earlier call judged again,
    the station's centre, a marker's corners); the pose-free pivots and the other images'
    centres follow when no image has a cheap start left. An image found ambiguous takes only
    cheap starts (a search would bring the same twins)."""
    if img.hint is not None:
        (kind, poses), img.hint = img.hint, None
        return kind, [(R, C) for R, C in poses]
    cheap = cheap or img.ambiguous
    kind, centres = _centres(img, oriented, stations)
    if kind == "station":
        for C in centres:
            key = tuple(np.round(C, 6))
            if key not in img.tried:
                img.tried.add(key)
                return kind, _centre_hyps(ctx, img, C)
    if "marker" not in img.tried and img.corners and ctx.marker_size_m is not None:
        img.tried.add("marker")
        hyps = _marker_hyps(ctx, img)
        if hyps:
            return "marker", hyps
    if cheap:
        return None
    second = (int(img.seeds_t[1]), img.seeds_uv[1]) if len(img.seeds_t) >= 2 else None
    anchors = ctx.anchors(img)
    for k, a in enumerate(anchors[:1] if second is not None else anchors):
        if ("pose-free", k) not in img.tried:
            img.tried.add(("pose-free", k))
            return "pattern", poses_pose_free(ctx.camera, ctx.X, ctx.world_nbrs, a, second=second)
    if kind != "station":
        for C in centres:
            key = tuple(np.round(C, 6))
            if key not in img.tried:
                img.tried.add(key)
                return kind, _centre_hyps(ctx, img, C)
    return None


def _centre_hyps(ctx: _Context, img: _Image, C):
    """Hypotheses for a prior centre (:func:`poses_from_centre` about every pivot)."""
    seeds = (img.seeds_t, img.seeds_uv) if len(img.seeds_t) else None
    hyps = []
    for a in ctx.anchors(img):
        hyps += poses_from_centre(ctx.camera, C, ctx.X, ctx.world_nbrs, a, seeds=seeds)
    return hyps


def _marker_hyps(ctx: _Context, img: _Image):
    """Hypotheses from the markers' corners (:func:`poses_from_marker`)."""
    anchors = {int(a.targets[0]): a for a in ctx.anchors(img) if len(a.targets) == 1}
    hyps = []
    for t, corners in img.corners:
        if t in anchors:
            hyps += poses_from_marker(ctx.camera, corners, ctx.marker_size_m, t, ctx.X, ctx.world_nbrs, anchors[t],
                                      normals=ctx.targets.normals)
    return hyps


def _own_seeds(ctx: _Context, pending: dict, marks, found: dict, reasons: dict) -> None:
    """The images with three or more seeds, identified from them with the calibrated camera."""
    idx = [i for i, img in pending.items() if len(img.seeds_t) >= 3]
    if not idx:
        return
    idents = identify_images([pending[i].table for i in idx], ctx.targets, ctx.camera,
                             marks=[marks.get(i) for i in idx], target_sigma_m=ctx.sigma_m,
                             codes_are_markers=ctx.coded, options=ctx.options, names=[pending[i].name for i in idx])
    for i, ident in zip(idx, idents, strict=True):
        if ident.ok:
            found[i] = (ident, "seeds")
        else:
            reasons[i] = ident.reason


def identify_remaining(camera: Camera, targets: TargetField, measurements: Mapping[str, pa.Table], names,
                       stations, oriented: dict, *, marks=None, target_sigma_m=None,
                       codes_are_markers: bool = True, options: IdentifyOptions | None = None,
                       prior: PriorOptions | None = None, reference=None, marker_size_m=None, hints=None,
                       progress: Callable[[str], None] | None = None):
    """Identify the images not yet oriented, with pose priors (module docstring).

    Parameters
    ----------
    camera : Camera
        The calibrated camera (first adjustment).
    targets : TargetField
        Targets (adjusted coordinates) with their codes.
    measurements : mapping of str to pyarrow.Table
        Every measured image's table, keyed by name.
    names : list of str
        The session's images, in order (index = image index).
    stations : list of str or None
        Each image's station (the manifest's ``station``).
    oriented : dict
        ``{image index: (R_world_to_camera, center_m)}`` of the oriented images; extended in
        place with every image this identifies.
    marks : dict, optional
        ``{image index: (target indices, uv)}`` (:func:`fieldcal.session.loader.read_marks_csv`).
    target_sigma_m, codes_are_markers, options
        As for :func:`fieldcal.field.identify.identify_image`.
    prior : PriorOptions, optional
    reference : dict, optional
        ``{image index: target of every row}`` of oriented images: what a right
        identification shows (their evidence sets the limits of the checks).
    marker_size_m : float, optional
        Side of the coded targets' markers [m] (the session's ``marker_size_mm``).
    hints : dict, optional
        ``{image index: (start, poses)}``: competing poses of images found ambiguous before,
        judged first; updated in place with this call's ambiguous images.
    progress : callable, optional

    Returns
    -------
    found : dict
        ``{image index: (ImageIdentification, start)}`` with ``start`` one of ``"seeds"``,
        ``"station"``, ``"marker"``, ``"neighbours"``, ``"pattern"``.
    reasons : dict
        ``{image index: reason}`` of the images still not identified.
    """
    marks = marks or {}
    hints = {} if hints is None else hints
    say = progress or (lambda _line: None)
    opt = options or IdentifyOptions()
    ctx = _Context(camera, targets, target_sigma_m, codes_are_markers, opt, prior or PriorOptions(), marker_size_m)
    ctx.calibrate_checks([(measurements[names[i]], t, *oriented[i]) for i, t in (reference or {}).items()
                          if i in oriented and names[i] in measurements])
    pending = {}
    for i, name in enumerate(names):
        if i in oriented or name not in measurements:
            continue
        pending[i] = _image_of(ctx, i, name, measurements[name], stations[i], marks.get(i))
        pending[i].hint = hints.pop(i, None)
    found, reasons = {}, {}
    _own_seeds(ctx, pending, marks, found, reasons)
    for i, (ident, _) in found.items():
        oriented[i] = (ident.R_world_to_camera, ident.center_m)
        del pending[i]
    for i, img in list(pending.items()):
        if len(img.uv) < ctx.prior.min_discs:
            reasons[i] = reasons.get(i) or f"only {len(img.uv)} discs measured: too few to search for a pose"
            del pending[i]
    _waves(ctx, pending, oriented, stations, marks, hints, found, reasons, lambda i, start, n: say(
        f"{names[i]}: identified from the {start} ({n} targets)"))
    for i, img in pending.items():
        if not reasons.get(i):
            reasons[i] = (f"{REASON_NO_START}: no pose prior or pattern match fits its "
                          f"{len(img.uv)} measured discs and {len(img.seeds_t)} seed(s)")
    return found, reasons


def _waves(ctx: _Context, pending, oriented, stations, marks, hints, found, reasons, say) -> None:
    """Every pending image takes its next start, all at once, until none has a start left
    (module docstring); ``pending``, ``oriented``, ``hints``, ``found``, ``reasons`` are updated."""
    while pending:
        for cheap in (True, False):
            steps = {i: st for i, img in pending.items()
                     if (st := _next_step(ctx, img, oriented, stations, cheap)) is not None}
            if steps:
                break
        if not steps:
            return
        decisions = ctx.decide([(pending[i], hyps, marks.get(i)) for i, (_, hyps) in steps.items()])
        for (i, (start, _)), (ident, reason, competitors) in zip(steps.items(), decisions, strict=True):
            if ident is not None:
                found[i] = (ident, start)
                oriented[i] = (ident.R_world_to_camera, ident.center_m)
                reasons.pop(i, None)
                hints.pop(i, None)
                del pending[i]
                say(i, start, ident.n_identified)
            elif competitors:      # ambiguous: judged again with a better camera (next call)
                hints[i] = (start, competitors)
                pending[i].ambiguous = True
                reasons[i] = reason
            else:
                reasons[i] = reasons.get(i) or reason


def _image_of(ctx: _Context, i, name, table, station, marks) -> _Image:
    kind, code, uv, usable = measured_points(table)
    disc = (kind == "disc") & usable
    rows = np.flatnonzero((kind == "aruco") & usable)
    t = np.array([ctx.code_to_target.get(int(c), -1) for c in code[rows]], np.int64)
    seeds_t, seeds_uv = t[t >= 0], uv[rows[t >= 0]]
    corners = []
    if "corners_px" in table.column_names:
        col = table.column("corners_px").to_pylist()
        for r, tt in zip(rows[t >= 0], seeds_t, strict=True):
            c = col[r]
            if c is not None and len(c) == 8 and np.all(np.isfinite(c)):
                corners.append((int(tt), np.asarray(c, float).reshape(4, 2)))
    if marks is not None:
        mt = np.asarray(marks[0], np.int64)
        new = ~np.isin(mt, seeds_t)
        seeds_t = np.concatenate([seeds_t, mt[new]])
        seeds_uv = np.concatenate([seeds_uv, np.asarray(marks[1], float).reshape(-1, 2)[new]])
    return _Image(i, name, table, uv, disc, _sigma(table), seeds_t, seeds_uv.reshape(-1, 2), corners, station)
