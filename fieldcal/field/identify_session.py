"""Identification of the images that have too few seeds, in a robust order (issue 11).

Method
------
The images with three or more seeds (coded targets, hand marks) are identified first
(:func:`fieldcal.field.identify.identify_image`) and adjusted; the calibrated camera and
the oriented images then give *pose priors* for every other image
(:func:`identify_remaining`), in this order, each image's first accepted start winning:

1. **its own seeds** (three or more) with the calibrated camera;
2. **the station**: the images of one station (the manifest's ``station``) share a
   position, so an oriented image of the same station gives the centre and only the
   rotation is searched (:func:`fieldcal.field.pose_search.poses_from_centre`: two seeds
   give it directly, one seed or none a star tracker's pair search);
3. **the neighbouring images**: without a station, the centres of the oriented images
   (clustered) are tried the same way;
4. **pose-free**: P3P over triples of the pivot and its measured neighbours against the field's
   neighbourhoods (:func:`fieldcal.field.pose_search.poses_pose_free`), with the seeds as
   pivots where there are any.

Newly oriented images add their centres for the images still left; the loop ends when a
round orients none.

Verification. A start's best hypotheses (local support, then the targets they pair in the
whole frame) are refined by :func:`identify_image` (which checks the fit and the expected
fraction); the results are grouped (two results are one when they share half of their
identities) and scored by their *evidence*: identified points minus the measured discs
left unexplained inside the identified area minus the targets predicted there and not
found. A right identification explains nearly everything inside its own area, a pose
shifted along a repeating pattern leaves the pattern's gaps unexplained. The best result is
accepted when its seeds all agree, its evidence is at least ``1 - max_unexplained`` of its
points, and no other group reaches ``max_ambiguity`` of its evidence; a periodic field where
a shift fits almost as well is left out as ambiguous, never accepted on a guess, and an
image of another field fits no hypothesis.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
from scipy.spatial import Delaunay, QhullError, cKDTree

from fieldcal.field.data import TargetField
from fieldcal.field.identify import IdentifyOptions, ImageIdentification, identify_image, measured_points
from fieldcal.field.pose_search import Anchor, field_neighbours, poses_from_centre, poses_pose_free
from fieldcal.model.camera import Camera

__all__ = ["identify_remaining", "evidence", "PriorOptions", "REASON_AMBIGUOUS", "REASON_NO_START"]

REASON_AMBIGUOUS = "ambiguous"
REASON_NO_START = "not identified"


@dataclass(frozen=True)
class PriorOptions:
    """Settings of :func:`identify_remaining` (module docstring).

    Attributes
    ----------
    max_unexplained : float
        Largest share of unexplained measured discs plus missed targets, relative to the
        identified points, inside the identified area.
    max_ambiguity : float
        A second, different identification with this fraction of the best one's evidence
        makes the image ambiguous.
    n_pivots : int
        Discs near the image centre tried as pivots when there are no seeds.
    n_refine : int
        Hypotheses per start refined by :func:`identify_image`.
    min_discs : int
        Images with fewer measured discs are not searched.
    """

    max_unexplained: float = 0.25
    max_ambiguity: float = 0.6
    n_pivots: int = 2
    n_refine: int = 4
    min_discs: int = 12


@dataclass
class _Image:
    index: int
    name: str
    table: pa.Table
    uv: np.ndarray              # (n, 2) usable discs [px]
    seeds_t: np.ndarray         # (s,) seed targets (markers named by their code, marks)
    seeds_uv: np.ndarray        # (s, 2)
    station: str | None
    tried: set = field(default_factory=set)     # prior centres and searches already tried
    seeds_reason: str = ""


def evidence(ident: ImageIdentification, table: pa.Table, camera: Camera, X, match_target) -> tuple[int, int]:
    """(identified discs, unexplained discs + missed targets inside the identified area)."""
    kind, _, uv_all, usable = measured_points(table)
    disc = (kind == "disc") & usable
    found = disc & (ident.target >= 0)
    n = int(found.sum())
    if n < 4 or ident.R_world_to_camera is None:
        return n, 0
    try:
        hull = Delaunay(uv_all[found])
    except QhullError:
        return n, 0
    extra = disc & ~found & (hull.find_simplex(np.where(np.isfinite(uv_all), uv_all, -1e9)) >= 0)
    pred = camera.project(X, ident.R_world_to_camera, ident.center_m)
    ok = match_target & np.isfinite(pred).all(axis=1)
    ok[ident.target[found]] = False
    k = np.flatnonzero(ok)
    missed = int(np.sum(hull.find_simplex(pred[k]) >= 0)) if len(k) else 0
    return n, int(extra.sum()) + missed


def _group(results):
    """Group refined results that share at least half of their identities; best group first."""
    groups: list[list] = []
    for res in results:
        ident = res[0]
        ids = set(zip(np.flatnonzero(ident.target >= 0).tolist(), ident.target[ident.target >= 0].tolist(),
                      strict=True))
        for g in groups:
            if len(ids & g[0][1]) >= 0.5 * min(len(ids), len(g[0][1])):
                g.append((res, ids))
                break
        else:
            groups.append([(res, ids)])
    best = [max(g, key=lambda x: x[0][1])[0] for g in groups]
    return sorted(best, key=lambda r: -r[1])


class _Context:
    """What every image's search shares: the camera, targets, neighbourhoods, settings."""

    def __init__(self, camera, targets: TargetField, sigma_m, codes_are_markers, options, prior):
        self.camera = camera
        self.targets = targets
        self.X = np.asarray(targets.xyz_m, float)
        self.sigma_m = sigma_m
        self.coded = codes_are_markers
        self.options = options
        self.prior = prior
        tcodes = np.asarray(targets.codes, np.int64)
        self.match = tcodes < 0 if codes_are_markers else np.ones(len(self.X), bool)
        self.code_to_target = {int(c): k for k, c in enumerate(tcodes) if c >= 0}
        self.world_nbrs = field_neighbours(self.X, min(100, len(self.X)))

    def refine(self, img: _Image, pose, marks):
        ident = identify_image(img.table, self.targets, self.camera, marks=marks, init_pose=pose,
                               target_sigma_m=self.sigma_m, codes_are_markers=self.coded,
                               options=self.options, where=img.name, seed=img.index)
        if not ident.ok or len(ident.wrong_marks) or len(ident.wrong_codes):
            return None
        n, unexplained = evidence(ident, img.table, self.camera, self.X, self.match)
        return ident, n - unexplained, n, unexplained

    def anchors(self, img: _Image) -> list[Anchor]:
        """Pivots: the seeds (their targets fixed), else discs near the image centre."""
        tree = cKDTree(img.uv)
        k = min(41, len(img.uv))
        out = []
        for t, uv in zip(img.seeds_t, img.seeds_uv, strict=True):
            d, j = tree.query(uv, k=k)
            j = j[d > 1e-6][:40]
            out.append(Anchor(uv, img.uv[j], [t]))
        if out:
            return out
        s = self.camera.sensor
        centre = np.array([(s.width_px - 1) / 2, (s.height_px - 1) / 2])
        _, piv = tree.query(centre, k=min(self.prior.n_pivots, len(img.uv)))
        for p in np.atleast_1d(piv):
            _, j = tree.query(img.uv[p], k=k)
            out.append(Anchor(img.uv[p], img.uv[j[1:]], np.flatnonzero(self.match)))
        return out

    def global_rank(self, img: _Image, hyps):
        """Hypotheses ordered by the targets they pair in the whole frame (first gate)."""
        if not hyps:
            return []
        tree = cKDTree(img.uv)
        nn = tree.query(img.uv, k=2)[0][:, 1]
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
        """Refine the best hypotheses; the accepted identification or a reason."""
        results = []
        seen = []
        for R, C, score in self.global_rank(img, hyps):
            if len(seen) >= self.prior.n_refine or score < self.options.min_identified:
                break
            if any(np.linalg.norm(C - C2) < 1e-3 * (1 + np.linalg.norm(C)) and np.abs(R - R2).max() < 1e-3
                   for R2, C2 in seen):
                continue
            seen.append((R, C))
            res = self.refine(img, (R, C), marks)
            if res is not None:
                results.append(res)
        if not results:
            return None, ""
        ranked = _group(results)
        ident, ev, n, unexplained = ranked[0]
        if unexplained > self.prior.max_unexplained * n:
            return None, ""
        if len(ranked) > 1 and ranked[1][1] >= self.prior.max_ambiguity * ev:
            return None, (f"{REASON_AMBIGUOUS}: two different identifications fit almost equally "
                          f"({n} and {ranked[1][2]} targets; a repeating pattern of targets?)")
        return ident, ""


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


def _search(ctx: _Context, img: _Image, oriented, stations, marks):
    """One image: its seeds, the station, the neighbours, the pose-free match (module docstring)."""
    why = img.seeds_reason
    if len(img.seeds_t) >= 3 and "seeds" not in img.tried:
        img.tried.add("seeds")
        ident = identify_image(img.table, ctx.targets, ctx.camera, marks=marks, target_sigma_m=ctx.sigma_m,
                               codes_are_markers=ctx.coded, options=ctx.options, where=img.name, seed=img.index)
        if ident.ok:
            return ident, "seeds", ""
        why = img.seeds_reason = ident.reason
    if len(img.uv) < ctx.prior.min_discs:
        return None, "", why or f"only {len(img.uv)} discs measured: too few to search for a pose"
    anchors = ctx.anchors(img)
    seeds = (img.seeds_t, img.seeds_uv) if len(img.seeds_t) else None
    kind, centres = _centres(img, oriented, stations)
    for C in centres:
        key = tuple(np.round(C, 6))
        if key in img.tried:
            continue
        img.tried.add(key)
        hyps = []
        for a in anchors:
            hyps += poses_from_centre(ctx.camera, C, ctx.X, ctx.world_nbrs, a, seeds=seeds)
        ident, reason = ctx.decide(img, hyps, marks)
        if ident is not None:
            return ident, kind, ""
        why = why or reason
    if "pose-free" in img.tried:
        return None, "", why
    img.tried.add("pose-free")
    hyps = []
    second = (int(img.seeds_t[1]), img.seeds_uv[1]) if len(img.seeds_t) >= 2 else None
    for a in anchors[:1] if second is not None else anchors:
        hyps += poses_pose_free(ctx.camera, ctx.X, ctx.world_nbrs, a, second=second)
    ident, reason = ctx.decide(img, hyps, marks)
    if ident is not None:
        return ident, "pattern", ""
    return None, "", why or reason


def identify_remaining(camera: Camera, targets: TargetField, measurements: Mapping[str, pa.Table], names,
                       stations, oriented: dict, *, marks=None, target_sigma_m=None,
                       codes_are_markers: bool = True, options: IdentifyOptions | None = None,
                       prior: PriorOptions | None = None,
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
        As for :func:`identify_image`.
    prior : PriorOptions, optional
    progress : callable, optional

    Returns
    -------
    found : dict
        ``{image index: (ImageIdentification, start)}`` with ``start`` one of ``"seeds"``,
        ``"station"``, ``"neighbours"``, ``"pattern"``.
    reasons : dict
        ``{image index: reason}`` of the images still not identified.
    """
    marks = marks or {}
    say = progress or (lambda _line: None)
    ctx = _Context(camera, targets, target_sigma_m, codes_are_markers, options or IdentifyOptions(),
                   prior or PriorOptions())
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
            ident, start, why = _search(ctx, pending[i], oriented, stations, marks.get(i))
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
    if marks is not None:
        mt = np.asarray(marks[0], np.int64)
        new = ~np.isin(mt, seeds_t)
        seeds_t = np.concatenate([seeds_t, mt[new]])
        seeds_uv = np.concatenate([seeds_uv, np.asarray(marks[1], float).reshape(-1, 2)[new]])
    return _Image(i, name, table, uv[disc], seeds_t, seeds_uv.reshape(-1, 2), station)
