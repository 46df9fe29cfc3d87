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
4. **the neighbouring images**: without a station, the centres of the oriented images
   (clustered) are tried as in 2;
5. **pose-free**: P3P over triples of a pivot and its measured neighbours against the field's
   neighbourhoods (:func:`fieldcal.field.pose_search.poses_pose_free`), with the seeds as
   pivots where there are any.

Newly oriented images add their centres for the images still left; the loop ends when a
round orients none.

Verification
------------
Every start's best hypotheses (local support, then the targets they pair in the whole frame)
are refined together (:func:`fieldcal.field.identify.identify_from_poses`, which checks the
fit and the expected fraction) with gates from the known noise (the oriented images'), not
from the residuals of the hypothesis itself (a wrong one would widen its own gates). Each
result's *evidence* (:func:`evidence`) is measured inside the area it identifies:

- ``n``: identified discs; ``extra``: measured discs left unexplained there; ``missed``:
  targets predicted there and not found. A right identification explains nearly every dot
  of its own area, a foreign image or a pose shifted along a repeating pattern does not;
- ``q``: the scatter of the identified points' residuals after the local correction (the
  median of the neighbours' residuals, which takes up what the camera model still lacks),
  each normalised by its expected sigma (the detector's sigma and the target's coordinate
  sigma seen from the pose); 1 at the noise.

A result is *admissible* when its seeds agree, ``extra + missed`` stays within what the
oriented images show (their rate plus three Poisson sigmas) and ``q`` within
``max_fit_factor`` of theirs. Where the field repeats (:func:`fieldcal.field.pose_search.field_symmetries`:
a regular grid shifted by its step, a square sheet turned by a quarter), the accepted
result's *twins* (its identities moved by each symmetry, the pose moved with them) are
refined and judged too. Among the admissible results (grouped: two results are one when
they share half of their identities) with at least ``max_ambiguity`` of the best evidence,
the one that fits best (smallest ``q``) is accepted when every other fits at least
``min_fit_ratio`` times worse (e.g. the relief or the unevenness of a sheet that a twin puts
in the wrong place); otherwise the image is left out as ambiguous, never accepted on a guess.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np
import pyarrow as pa
from scipy.spatial import ConvexHull, QhullError, cKDTree

from fieldcal.field.data import TargetField
from fieldcal.field.geometry import plane_frame
from fieldcal.field.identify import (
    IdentifyOptions,
    ImageIdentification,
    identify_from_poses,
    identify_image,
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
    seeds_reason: str = ""

    @property
    def uv(self) -> np.ndarray:
        return self.uv_all[self.disc]


def evidence(table: pa.Table, target: np.ndarray, R, C, camera: Camera, X, match_target, sigma_m,
             neighbours: int = 8) -> Evidence:
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

    Returns
    -------
    Evidence
    """
    kind, _, uv_all, usable = measured_points(table)
    disc = (kind == "disc") & usable
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
    pred = camera.project(X, R, C)
    ok = match_target & np.isfinite(pred).all(axis=1)
    ok[target[found]] = False
    k = np.flatnonzero(ok)
    missed = int(np.sum(inside(pred[k]))) if len(k) else 0
    t = target[found]
    res = uv_all[found] - pred[t]
    sig = _sigma(table)[found]
    depth = np.abs((X[t] - C) @ R[2])
    prior = sigma_m[t] * camera.f_mm / depth / camera.sensor.pixel_mm
    if n > neighbours + 1:
        corr, _ = local_correction(pred[t], pred[t], res, np.arange(n), neighbours=neighbours)
        res = res - corr
    z2 = np.sum(res**2, axis=1) / (sig**2 + prior**2)
    return Evidence(n, int(extra.sum()), missed, float(np.sqrt(np.mean(z2) / 2.0)))


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
        self.code_to_target = {int(c): k for k, c in enumerate(tcodes) if c >= 0}
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

    def results(self, img: _Image, poses, marks) -> list[_Result]:
        """Each pose refined (all at once) with its evidence; only results whose seeds agree."""
        if not poses:
            return []
        idents = identify_from_poses(img.table, self.targets, self.camera, poses, marks=marks,
                                     target_sigma_m=self.sigma_m, codes_are_markers=self.coded,
                                     options=self.refine_options, where=img.name)
        out = []
        for ident in idents:
            if not ident.ok or len(ident.wrong_marks) or len(ident.wrong_codes) or not self.in_front(ident.center_m):
                continue
            ev = evidence(img.table, ident.target, ident.R_world_to_camera, ident.center_m, self.camera, self.X,
                          self.match, self.sigma_m)
            rows = np.flatnonzero(ident.target >= 0)
            out.append(_Result(ident, ev, set(zip(rows.tolist(), ident.target[rows].tolist(), strict=True))))
        return out

    def _score(self, img: _Image, R, C) -> np.ndarray:
        """Targets each pose pairs with the first gates (:meth:`ViewMatcher.score`)."""
        vm = ViewMatcher(self.X, self.match, self.camera, self.options, [img.uv], self.sigma_m)
        return vm.score(np.zeros(len(R), np.int64), R, C)[0]

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

    def decide(self, img: _Image, hyps, marks):
        """Refine the best hypotheses and their twins: the accepted identification (or None), the
        reason, and when ambiguous the poses of the competing results (to judge again later)."""
        poses = []
        for R, C, score in self.global_rank(img, hyps):
            if len(poses) >= self.prior.n_refine or score < self.options.min_identified:
                break
            if any(np.linalg.norm(C - C2) < 1e-3 * (1 + np.linalg.norm(C)) and np.abs(R - R2).max() < 1e-3
                   for R2, C2 in poses):
                continue
            poses.append((R, C))
        results = [r for r in self.results(img, poses, marks) if self.admissible(r.ev)]
        if not results:
            return None, "", []
        best = max(results, key=lambda r: (r.score, -r.ev.q))
        twins = self.twins(img, best)
        if twins:       # refine the twins that pair nearly as many targets as the best start
            R = np.stack([p[0] for p in twins])
            C = np.stack([p[1] for p in twins])
            count = self._score(img, R, C)
            twins = [p for p, c in zip(twins, count, strict=True) if c >= self.prior.max_ambiguity * best.ev.n]
        results += [r for r in self.results(img, twins, marks) if self.admissible(r.ev)]
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


def _centre_hyps(ctx: _Context, img: _Image, centres, anchors):
    """Hypotheses for each prior centre not tried yet (:func:`poses_from_centre`)."""
    seeds = (img.seeds_t, img.seeds_uv) if len(img.seeds_t) else None
    for C in centres:
        key = tuple(np.round(C, 6))
        if key in img.tried:
            continue
        img.tried.add(key)
        hyps = []
        for a in anchors:
            hyps += poses_from_centre(ctx.camera, C, ctx.X, ctx.world_nbrs, a, seeds=seeds)
        yield hyps


def _marker_hyps(ctx: _Context, img: _Image):
    """Hypotheses from the markers' corners (:func:`poses_from_marker`), once."""
    if "marker" in img.tried or not img.corners or ctx.marker_size_m is None:
        return
    img.tried.add("marker")
    anchors = {int(a.targets[0]): a for a in ctx.anchors(img) if len(a.targets) == 1}
    hyps = []
    for t, corners in img.corners:
        if t in anchors:
            hyps += poses_from_marker(ctx.camera, corners, ctx.marker_size_m, t, ctx.X, ctx.world_nbrs, anchors[t],
                                      normals=ctx.targets.normals)
    yield hyps


def _pose_free_hyps(ctx: _Context, img: _Image, anchors):
    """Hypotheses of the pose-free search, one pivot after the other, once."""
    if "pose-free" in img.tried:
        return
    img.tried.add("pose-free")
    second = (int(img.seeds_t[1]), img.seeds_uv[1]) if len(img.seeds_t) >= 2 else None
    for a in anchors[:1] if second is not None else anchors:
        yield poses_pose_free(ctx.camera, ctx.X, ctx.world_nbrs, a, second=second)


def _search(ctx: _Context, img: _Image, oriented, stations, marks, hints):
    """One image: its seeds, then the starts of the module docstring until one is accepted.

    An ambiguous result ends the image's search in this round (another start would bring the
    same twins); its competitors are kept in ``hints`` and judged first in the next round,
    when a better camera may tell them apart."""
    why = img.seeds_reason
    if len(img.seeds_t) >= 3 and "seeds" not in img.tried:
        img.tried.add("seeds")
        ident = _own_seeds(ctx, img, marks)
        if ident.ok:
            return ident, "seeds", ""
        why = img.seeds_reason = ident.reason
    if len(img.uv) < ctx.prior.min_discs:
        return None, "", why or f"only {len(img.uv)} discs measured: too few to search for a pose"
    anchors = ctx.anchors(img)
    kind, centres = _centres(img, oriented, stations)
    starts = []
    if img.index in hints:
        start, poses = hints.pop(img.index)
        starts.append((start, iter([[(R, C) for R, C in poses]])))
    if kind == "station":
        starts.append((kind, _centre_hyps(ctx, img, centres, anchors)))
    starts += [("marker", _marker_hyps(ctx, img)), ("pattern", _pose_free_hyps(ctx, img, anchors))]
    if kind != "station":
        starts.append((kind, _centre_hyps(ctx, img, centres, anchors)))
    for start, hyps_lists in starts:
        for hyps in hyps_lists:
            ident, reason, competitors = ctx.decide(img, hyps, marks)
            if ident is not None:
                return ident, start, ""
            if competitors:
                hints[img.index] = (start, competitors)
                return None, "", reason
            why = why or reason
    return None, "", why


def _own_seeds(ctx: _Context, img: _Image, marks) -> ImageIdentification:
    """The image's own seeds with the calibrated camera."""
    return identify_image(img.table, ctx.targets, ctx.camera, marks=marks, target_sigma_m=ctx.sigma_m,
                          codes_are_markers=ctx.coded, options=ctx.options, where=img.name, seed=img.index)


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
    found, reasons = {}, {}
    while pending:
        # the images of a station with an oriented image first, then by number of seeds
        order = sorted(pending, key=lambda i: (not any(stations[j] == stations[i] and stations[i] is not None
                                                       for j in oriented), -len(pending[i].seeds_t), i))
        progressed = False
        for i in order:
            ident, start, why = _search(ctx, pending[i], oriented, stations, marks.get(i), hints)
            if ident is None:
                reasons[i] = why
                continue
            found[i] = (ident, start)
            oriented[i] = (ident.R_world_to_camera, ident.center_m)
            reasons.pop(i, None)
            del pending[i]
            progressed = True
            say(f"{names[i]}: identified from the {start} ({ident.n_identified} targets)")
        if not progressed:
            break
    for i in pending:
        if not reasons.get(i):
            reasons[i] = (f"{REASON_NO_START}: no pose prior or pattern match fits its "
                          f"{len(pending[i].uv)} measured discs and {len(pending[i].seeds_t)} seed(s)")
    return found, reasons


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
