"""Target identification: which surveyed target each measured blob of one image is.

Method
------
The measurements of an image (:func:`fieldcal.measure.targets.measure_image`: discs and ArUco
markers) carry no identities except the markers' codes. A few *seeds* give the first
correspondences: the coded targets (a marker's code names its target through
``targets.codes``; its measured centre is that target's observation) and, for fields
without coded targets, the hand marks of ``marks.csv`` (docs/conventions.md section 3). Then:

1. **Pose from the seeds.** Candidate poses: the given approximate pose (``init_pose``,
   e.g. from an adjustment), OpenCV's SQPnP of all seeds, and their resection
   (:func:`fieldcal.field.resection.resect`, with RANSAC from 6 seeds on); when none of these is
   convincing (most of the expected targets matched, every seed near its target), also the
   resections of the seeds without one of them and the P3P poses of every triple (so one
   wrong mark among four cannot spoil the start). P3P is Grunert's solution with the real
   part of every root of its quartic (:func:`_grunert_distances`): near the "danger
   cylinder" a little noise turns the right pair of roots complex, and OpenCV's P3P then
   loses the right pose. Each candidate is scored by the number of targets it pairs (step
   2 with the wide first gate).
2. **Projection and matching.** All surveyed targets are projected with the pose
   (:meth:`Camera.project`); a prediction and a measured point are paired when each is the
   other's nearest neighbour (``scipy.spatial.cKDTree``), they are within the prediction's
   gate, and no second candidate lies within the gate on either side (ambiguous pairs stay
   unidentified). Plain targets are matched to discs; coded targets only through their
   markers' codes (``codes_are_markers``).
3. **Local correction and gates.** The residuals of the paired points (measured minus
   projected) contain what the camera model does not yet know: with the nominal camera of
   a first pass, the whole lens distortion, smooth over the image. Each prediction is
   moved by the median residual of its ``neighbours`` nearest paired points (its own
   residual left out), and the gate of each prediction is
   ``gate_factor * sqrt(s^2 + spread^2 + prior^2)``, ``s`` the robust (MAD) scale of the
   paired points' corrected residuals, ``spread`` the MAD of the neighbours' residuals (large
   where the distortion changes fast, e.g. extrapolating into a corner) and ``prior`` the
   target's coordinate sigma seen from the camera (``target_sigma_m``), clipped to
   ``[min_gate_px, first gate]``. The first gate is ``first_gate_fraction`` (0.3) of the
   distance from a prediction to its nearest neighbouring prediction (at most
   ``gate_px``): half of that would already be ambiguous.
4. **Iteration.** The pose is re-resected from the pairs (and the markers that agree with
   it), the targets re-projected and re-matched, until the set of pairs is stable
   (``max_iterations``). The best-scored candidate is refined first; when it does not end
   in a fit (step 5), the next ones (up to ``max_starts``).
5. **Checks.** A seed whose target ends up farther than ``max(3 gate, 0.25 spacing)`` from
   the seed's point is *wrong* (a mark with a wrong id, a marker whose code is wrong in
   targets.csv): it is reported and not used. The image is not usable (``reason``) when
   fewer than ``min_identified`` targets are identified, or the start was wrong: the pairs'
   residuals after the local correction exceed ``max_rms_fraction`` of the target spacing
   (a right identification fits to the noise, a chance one to a good part of the spacing),
   fewer than ``min_fraction`` of the targets expected in the frame are paired, or most
   seeds disagree. After a wrong start no identity is kept.

Everything per image is vectorised (projections, KD-tree queries, corrections); the only
loops are over candidate poses and iterations.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import cv2
import numpy as np
import pyarrow as pa
from scipy.spatial import cKDTree

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.geometry import is_collinear
from fieldcal.field.matching import ViewMatcher, local_correction, mutual_nearest
from fieldcal.field.pose_search import grunert_distances
from fieldcal.field.resection import resect
from fieldcal.model.camera import Camera
from fieldcal.model.opencv_frames import FLIP_YZ, ideal_pixels, opencv_camera_matrix, pose_from_opencv
from fieldcal.session.data import TargetField

__all__ = ["ImageIdentification", "IdentifyOptions", "identify_image", "identify_images", "identify_from_poses",
           "identify_views", "mutual_nearest", "local_correction", "measured_points", "DEFAULT_MIN_IDENTIFIED"]

DEFAULT_MIN_IDENTIFIED = 8
"""Fewer identified targets than this and an image is left out (the adjustment needs 6)."""

_MAX_TRIPLES = 200


@dataclass
class ImageIdentification:
    """The identification of one image.

    Attributes
    ----------
    target : (n_rows,) int ndarray
        Target index (into the :class:`TargetField`) of every row of the measurement table,
        -1 where the row is not identified. When the start was wrong (``reason`` says the
        points do not fit, too few of the expected targets were found, or the seeds disagree)
        every row is -1.
    R_world_to_camera : (3, 3) ndarray or None
        The image's pose from the identified points (None when no pose was found).
    center_m : (3,) ndarray or None
        Camera centre [m].
    n_identified : int
        Rows identified (discs and markers).
    n_coded : int
        Markers whose code names a surveyed target.
    n_seeds : int
        Seeds used to start: coded targets plus marks.
    gate_px : float
        Median gate of the last matching [px].
    rms_px : float
        RMS of the identified points' residuals after the local correction [px]
        (``sqrt(mean(du^2 + dv^2))``).
    residual_px : (n_rows, 2) ndarray
        Measured minus projected pixel of every identified row (before the local
        correction; NaN elsewhere) [px].
    wrong_marks : (k,) int ndarray
        Target indices of marks that disagree with the identification.
    wrong_codes : (k,) int ndarray
        Codes of markers that disagree with the identification (their target's survey or
        code is wrong, or the marker is a false detection).
    iterations : int
        Rounds of resection and matching.
    reason : str
        Empty when the image is usable; otherwise why it is not.
    """

    target: np.ndarray
    R_world_to_camera: np.ndarray | None
    center_m: np.ndarray | None
    n_identified: int
    n_coded: int
    n_seeds: int
    gate_px: float
    rms_px: float
    residual_px: np.ndarray
    wrong_marks: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    wrong_codes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    iterations: int = 0
    reason: str = ""

    @property
    def ok(self) -> bool:
        """Whether the image is usable for the adjustment."""
        return self.reason == ""


# ---------------------------------------------------------------------------- building blocks
def measured_points(measurements: pa.Table):
    """Columns of a ``measurements`` table as arrays: ``kind`` (str), ``code`` (-1 for
    discs), ``uv`` (n, 2) [px], ``usable`` (finite and not truncated at the border)."""
    n = measurements.num_rows
    names = measurements.column_names
    for c in ("kind", "u_px", "v_px"):
        if c not in names:
            raise InputError(f"measurements table lacks the column {c!r}")
    kind = np.asarray(measurements.column("kind").to_pylist(), dtype=object).astype(str) if n else np.zeros(0, str)
    code = (np.asarray(measurements.column("code").fill_null(-1).to_numpy(zero_copy_only=False), np.int64)
            if "code" in names else np.full(n, -1, np.int64))
    uv = np.stack([measurements.column("u_px").to_numpy(zero_copy_only=False).astype(float),
                   measurements.column("v_px").to_numpy(zero_copy_only=False).astype(float)], axis=1)
    usable = np.isfinite(uv).all(axis=1)
    if "truncated" in names:
        usable &= ~np.asarray(measurements.column("truncated").fill_null(False)
                              .to_numpy(zero_copy_only=False), bool)
    return kind, code, uv.reshape(n, 2), usable


def _opencv_inputs(X, uv, camera):
    origin = X.mean(axis=0)
    obj = np.ascontiguousarray(X - origin, np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(ideal_pixels(uv, camera), np.float64).reshape(-1, 1, 2)
    return origin, obj, img, opencv_camera_matrix(camera)


def _grunert_distances(X, rays):
    """Distances ``(s1, s2, s3)`` along unit ``rays`` (3, 3) to world points ``X`` (3, 3): the
    finite, positive ones of :func:`fieldcal.field.pose_search.grunert_distances` (every root's
    real part). Returns an (k, 3) array."""
    s, good = grunert_distances(np.asarray(X, float)[None], np.asarray(rays, float)[None])
    return s[0][good[0]]


def _p3p_poses(X, uv, camera):
    """Poses (fieldcal convention) that fit three points (:func:`_grunert_distances`, the
    points in the camera frame aligned with the world by Kabsch's rotation, then refined by
    ``cv2.solvePnPRefineLM``)."""
    rays = camera.unproject(uv)                      # fieldcal camera frame
    origin, obj, img, K = _opencv_inputs(X, uv, camera)
    Xl = X - origin
    out = []
    for s in _grunert_distances(Xl, rays):
        Pc = rays * s[:, None]
        H = (Xl - Xl.mean(axis=0)).T @ (Pc - Pc.mean(axis=0))
        U, _, Vt = np.linalg.svd(H)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T                           # Pc = R (Xl - Cl)
        Cl = Xl.mean(axis=0) - R.T @ Pc.mean(axis=0)
        R_cv = FLIP_YZ @ R
        rv, _ = cv2.Rodrigues(R_cv)
        tv = -R_cv @ Cl
        try:
            rv, tv = cv2.solvePnPRefineLM(obj, img, K, None, rv.reshape(3, 1), tv.reshape(3, 1).copy())
        except cv2.error:
            pass
        R2, C2 = pose_from_opencv(rv, tv)
        if np.all(np.isfinite(R2)) and np.all(np.isfinite(C2)):
            out.append((R2, C2 + origin))
    return out


# ---------------------------------------------------------------------------- starts
def _candidate_poses(seed_X, seed_uv, camera, init_pose, threshold_px, where):
    """The first candidates: the given pose and the resection of all seeds."""
    cands = []
    if init_pose is not None:
        cands.append((np.asarray(init_pose[0], float), np.asarray(init_pose[1], float)))
    n = len(seed_X)
    if n >= 3 and not is_collinear(seed_X):
        # SQPnP's global optimum of all seeds, unchecked (resect refuses a pose that puts a
        # wrong seed behind the camera; as a start for the triples it is still useful)
        origin, obj, img, K = _opencv_inputs(seed_X, seed_uv, camera)
        try:
            ok, rv, tv = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                R, C = pose_from_opencv(rv, tv)
                cands.append((R, C + origin))
        except cv2.error:
            pass
    if n >= 4 and not is_collinear(seed_X):
        for ransac in ((False, True) if n >= 6 else (False,)):
            try:
                r = resect(seed_X, seed_uv, camera, ransac=ransac, where=where,
                           threshold_px=threshold_px, min_inliers=min(6, n))
                cands.append((r.R_world_to_camera, r.center_m))
            except GeometryError:
                pass
    return cands


def _subset_poses(seed_X, seed_uv, camera, where, rng):
    """Fallback candidates: the seeds less one (resection), and every triple (P3P)."""
    n = len(seed_X)
    cands = []
    if n >= 5:
        for k in range(n):
            keep = np.arange(n) != k
            if is_collinear(seed_X[keep]):
                continue
            try:
                r = resect(seed_X[keep], seed_uv[keep], camera, where=where)
                cands.append((r.R_world_to_camera, r.center_m))
            except GeometryError:
                pass
    triples = list(itertools.combinations(range(n), 3))
    if len(triples) > _MAX_TRIPLES:
        triples = [triples[i] for i in rng.choice(len(triples), _MAX_TRIPLES, replace=False)]
    for tri in triples:
        tri = list(tri)
        if is_collinear(seed_X[tri]):
            continue
        cands.extend(_p3p_poses(seed_X[tri], seed_uv[tri], camera))
    return cands


@dataclass(frozen=True)
class IdentifyOptions:
    """Settings of :func:`identify_image` (module docstring, steps 1-5).

    Attributes
    ----------
    gate_px : float, optional
        Upper bound of the gate [px]; default ``first_gate_fraction`` of the local spacing of
        the predictions only.
    min_identified : int
        Fewer identified targets and the image is not usable (``reason`` says so); >= 4.
    gate_factor, min_gate_px, first_gate_fraction, neighbours, max_iterations
        The matcher's settings (module docstring, steps 2-4).
    min_fraction : float
        The image is not usable when fewer than this fraction of the plain targets the final
        pose puts well inside the frame (at most the number of measured discs) are
        identified: a pose from wrong seeds matches only a few by chance.
    max_rms_fraction : float
        The image is not usable when the RMS of the identified points' residuals, after the
        local correction, exceeds this fraction of the targets' spacing in the image (a right
        identification fits to the measurement noise, a wrong one to a good part of the spacing).
    max_starts : int
        When the best-scored start is not convincing (step 1), up to this many of the best
        candidate poses are refined, and the first that fits is kept.
    """

    gate_px: float | None = None
    min_identified: int = DEFAULT_MIN_IDENTIFIED
    gate_factor: float = 5.0
    min_gate_px: float = 1.0
    first_gate_fraction: float = 0.3
    neighbours: int = 8
    max_iterations: int = 12
    min_fraction: float = 0.3
    max_rms_fraction: float = 0.05
    max_starts: int = 3

    def __post_init__(self):
        if self.min_identified < 4:
            raise InputError(f"min_identified must be at least 4, got {self.min_identified}")


@dataclass
class _Seeds:
    """The seeds of one image: coded targets (marker rows whose code names a target) and marks."""

    coded_rows: np.ndarray     # (c,) rows of the measurement table
    coded_t: np.ndarray        # (c,) their targets
    t: np.ndarray              # (s,) targets of all seeds, markers first
    uv: np.ndarray             # (s, 2) [px]
    is_mark: np.ndarray        # (s,) bool
    n_marks: int


def _seeds_of(kind, code, uv_all, usable, tcodes, n_targets, marks, where) -> _Seeds:
    code_to_target = dict(zip(tcodes[tcodes >= 0].tolist(), np.flatnonzero(tcodes >= 0).tolist(), strict=True))
    marker_rows = np.flatnonzero((kind == "aruco") & usable)
    marker_t = np.array([code_to_target.get(int(c), -1) for c in code[marker_rows]], np.int64)
    coded_rows, coded_t = marker_rows[marker_t >= 0], marker_t[marker_t >= 0]
    seed_t, seed_uv, n_marks = [coded_t], [uv_all[coded_rows]], 0
    if marks is not None:
        mt, muv = np.asarray(marks[0], np.int64).reshape(-1), np.asarray(marks[1], float).reshape(-1, 2)
        if len(mt) != len(muv):
            raise InputError(f"marks: {len(mt)} target indices but {len(muv)} points", where or None)
        if len(mt) and (mt.min() < 0 or mt.max() >= n_targets):
            raise InputError("marks: target index out of range", where or None)
        new = ~np.isin(mt, coded_t)               # a marked coded target: the marker is better
        seed_t.append(mt[new])
        seed_uv.append(muv[new])
        n_marks = int(new.sum())
    t = np.concatenate(seed_t).astype(np.int64)
    return _Seeds(coded_rows, coded_t, t, np.concatenate(seed_uv).reshape(-1, 2),
                  np.arange(len(t)) >= len(coded_t), n_marks)


@dataclass
class _Image:
    """One image's measurement table as arrays, its usable discs and its seeds."""

    kind: np.ndarray
    code: np.ndarray
    uv_all: np.ndarray
    disc_rows: np.ndarray
    sd: _Seeds

    @property
    def n_rows(self) -> int:
        return len(self.kind)

    @property
    def discs(self) -> np.ndarray:
        return self.uv_all[self.disc_rows]

    @property
    def coded(self):
        """The markers whose code names a target: (targets, uv)."""
        return self.sd.coded_t, self.uv_all[self.sd.coded_rows]

    def failed(self, reason: str) -> ImageIdentification:
        n = self.n_rows
        return ImageIdentification(np.full(n, -1, np.int64), None, None, 0, len(self.sd.coded_t), len(self.sd.t),
                                   np.nan, np.nan, np.full((n, 2), np.nan), reason=reason)


def _image_of(measurements: pa.Table, tcodes, n_targets: int, marks, where: str) -> _Image:
    kind, code, uv_all, usable = measured_points(measurements)
    sd = _seeds_of(kind, code, uv_all, usable, tcodes, n_targets, marks, where)
    return _Image(kind, code, uv_all, np.flatnonzero((kind == "disc") & usable), sd)


def _no_start(im: _Image) -> ImageIdentification:
    n_seeds = len(im.sd.t)
    if n_seeds == 0:
        return im.failed("no coded targets seen and no marks: nothing to start the identification from")
    return im.failed(f"only {n_seeds} seed(s) (coded targets and marks); at least 3 (better 4) are needed")


def _view_matcher(targets: TargetField, camera, opt, images, target_sigma_m, codes_are_markers) -> ViewMatcher:
    X = np.asarray(targets.xyz_m, float)
    tcodes = np.asarray(targets.codes, np.int64)
    match_target = tcodes < 0 if codes_are_markers else np.ones(len(X), bool)
    if target_sigma_m is not None:
        target_sigma_m = np.broadcast_to(np.asarray(target_sigma_m, float), (len(X),))
    return ViewMatcher(X, match_target, camera, opt, [im.discs for im in images], target_sigma_m)


def identify_image(measurements: pa.Table, targets: TargetField, camera: Camera, *,
                   marks=None, init_pose=None, target_sigma_m=None, codes_are_markers: bool = True,
                   options: IdentifyOptions | None = None, where: str = "",
                   seed: int = 0) -> ImageIdentification:
    """Identify the measured targets of one image (see the module docstring).

    Parameters
    ----------
    measurements : pyarrow.Table
        The image's ``measurements`` table (:func:`fieldcal.measure.targets.measure_image`).
    targets : TargetField
        The surveyed targets (or adjusted coordinates in a second pass); ``codes`` names the
        coded targets.
    camera : Camera
        The interior orientation to project with: the nominal one (principal point at the
        centre, no distortion) in a first pass, the calibrated one afterwards.
    marks : (target indices (k,), uv (k, 2) [px]), optional
        Hand-identified targets of this image (``marks.csv``, as
        :func:`fieldcal.session.loader.read_marks_csv` returns them per image).
    init_pose : (R_world_to_camera (3, 3), center_m (3,)), optional
        An approximate pose (e.g. from an adjustment, or a pose prior); tried as a candidate.
        Without it at least 3 seeds are needed.
    target_sigma_m : float or (n,) array_like, optional
        One-sigma uncertainty of each target's coordinates [m] (survey, or adjustment). Seen
        from the pose it widens the target's gate (in quadrature with the residual scale),
        so that a target known worse than its neighbours is not missed.
    codes_are_markers : bool
        Coded targets are seen as ArUco markers and identified by their codes only (the
        session has ``field.coded``); ``False`` matches every target to discs.
    options : IdentifyOptions, optional
        The matcher's settings and the checks' limits.
    where : str
        The image's name, for messages.
    seed : int
        Seeds the choice of triples when there are many seeds.

    Returns
    -------
    ImageIdentification
    """
    opt = options or IdentifyOptions()
    X = np.asarray(targets.xyz_m, float)
    im = _image_of(measurements, np.asarray(targets.codes, np.int64), len(X), marks, where)
    if init_pose is None and len(im.sd.t) < 3:
        return _no_start(im)
    vm = _view_matcher(targets, camera, opt, [im], target_sigma_m, codes_are_markers)
    cands, scores, convincing = _starting_poses(vm, im, X, init_pose, opt, where, seed)
    if not cands:
        return im.failed("no pose could be computed from the seeds (collinear or inconsistent)")
    best = _best_refined(vm, im, cands, scores, convincing, opt)
    return _finish(vm, 0, best, im, init_pose, opt)


def identify_images(tables, targets: TargetField, camera: Camera, *, marks=None, init_poses=None,
                    target_sigma_m=None, codes_are_markers: bool = True, options: IdentifyOptions | None = None,
                    names=None, fixed_pose: bool = False) -> list[ImageIdentification]:
    """Identify many images at once: :func:`identify_image` of each, vectorised over images.

    Each image starts from ``init_poses[k]`` when given, else from OpenCV's SQPnP of its seeds;
    the starts that pair most of the targets they put in the frame (and agree with the seeds)
    are refined together (:class:`fieldcal.field.matching.ViewMatcher`); every other image
    goes through :func:`identify_image` (all candidate starts, subsets of the seeds).

    Parameters
    ----------
    tables : list of pyarrow.Table
        The images' ``measurements`` tables.
    targets, camera, target_sigma_m, codes_are_markers, options
        As for :func:`identify_image`.
    marks : list, optional
        Per image, its marks or None.
    init_poses : list, optional
        Per image, an approximate pose ``(R_world_to_camera, center_m)`` or None.
    names : list of str, optional
        The images' names, for messages.
    fixed_pose : bool
        The ``init_poses`` are an adjustment's: they are kept (not re-estimated from one image).

    Returns
    -------
    list of ImageIdentification
    """
    opt = options or IdentifyOptions()
    n = len(tables)
    marks = marks if marks is not None else [None] * n
    init_poses = init_poses if init_poses is not None else [None] * n
    names = names if names is not None else [""] * n
    X = np.asarray(targets.xyz_m, float)
    tcodes = np.asarray(targets.codes, np.int64)
    ims = [_image_of(t, tcodes, len(X), marks[k], names[k]) for k, t in enumerate(tables)]
    starts = []
    for k, im in enumerate(ims):
        if init_poses[k] is not None:
            starts.append((k, np.asarray(init_poses[k][0], float), np.asarray(init_poses[k][1], float)))
        elif len(im.sd.t) >= 3 and not is_collinear(X[im.sd.t]):
            pose = _sqpnp(X[im.sd.t], im.sd.uv, camera)
            if pose is not None:
                starts.append((k, *pose))
    out: list = [None] * n
    if starts:
        vm = _view_matcher(targets, camera, opt, ims, target_sigma_m, codes_are_markers)
        img = np.array([s[0] for s in starts])
        R, C = np.stack([s[1] for s in starts]), np.stack([s[2] for s in starts])
        count, expected, uv, _ = vm.score(img, R, C)
        good = [v for v, k in enumerate(img) if count[v] >= max(opt.min_identified, 0.5 * expected[v])
                and (len(ims[k].sd.t) == 0 or _seeds_agree(uv[v], ims[k].sd))]
        if good:
            ref = vm.refine(img[good], R[good], C[good], coded=[im.coded for im in ims],
                            update_pose=not fixed_pose)
            for v, k in enumerate(img[good]):
                out[k] = _finish(vm, k, ref.view(v), ims[k], init_poses[k], opt)
    for k in range(n):
        if out[k] is None:
            out[k] = identify_image(tables[k], targets, camera, marks=marks[k], init_pose=init_poses[k],
                                    target_sigma_m=target_sigma_m, codes_are_markers=codes_are_markers,
                                    options=opt, where=names[k], seed=k)
    return out


def identify_from_poses(measurements: pa.Table, targets: TargetField, camera: Camera, poses, *, marks=None,
                        target_sigma_m=None, codes_are_markers: bool = True, options: IdentifyOptions | None = None,
                        where: str = "") -> list[ImageIdentification]:
    """Refine each of several approximate poses of one image to an identification of its own.

    Steps 2-5 of the module docstring for every pose (vectorised over the poses), without
    choosing among them: the caller compares the results (e.g. hypotheses of a pose search).
    ``poses`` is a list of ``(R_world_to_camera, center_m)``; the other arguments are those of
    :func:`identify_image`. Returns one :class:`ImageIdentification` per pose.
    """
    return identify_views([measurements], targets, camera, [poses], marks=[marks], target_sigma_m=target_sigma_m,
                          codes_are_markers=codes_are_markers, options=options, names=[where])[0]


def identify_views(tables, targets: TargetField, camera: Camera, poses, *, marks=None, target_sigma_m=None,
                   codes_are_markers: bool = True, options: IdentifyOptions | None = None,
                   names=None) -> list[list[ImageIdentification]]:
    """:func:`identify_from_poses` for several images at once (one refinement of all their views).

    ``tables`` are the images' measurement tables, ``poses[k]`` the approximate poses of image
    ``k`` (a list), ``marks[k]`` its marks or None. Returns, per image, one
    :class:`ImageIdentification` per pose.
    """
    opt = options or IdentifyOptions()
    n = len(tables)
    marks = marks if marks is not None else [None] * n
    names = names if names is not None else [""] * n
    X = np.asarray(targets.xyz_m, float)
    tcodes = np.asarray(targets.codes, np.int64)
    ims = [_image_of(t, tcodes, len(X), marks[k], names[k]) for k, t in enumerate(tables)]
    image = np.array([k for k in range(n) for _ in poses[k]], np.int64)
    out: list[list[ImageIdentification]] = [[] for _ in range(n)]
    if not len(image):
        return out
    vm = _view_matcher(targets, camera, opt, ims, target_sigma_m, codes_are_markers)
    flat = [p for k in range(n) for p in poses[k]]
    ref = vm.refine(image, np.stack([np.asarray(p[0], float) for p in flat]),
                    np.stack([np.asarray(p[1], float) for p in flat]), coded=[im.coded for im in ims])
    for v, k in enumerate(image):
        out[k].append(_finish(vm, k, ref.view(v), ims[k], flat[v], opt))
    return out


def _sqpnp(seed_X, seed_uv, camera):
    """OpenCV's SQPnP pose of the seeds (fieldcal convention), or None."""
    origin, obj, img, K = _opencv_inputs(seed_X, seed_uv, camera)
    try:
        ok, rv, tv = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        return None
    if not ok:
        return None
    R, C = pose_from_opencv(rv, tv)
    return R, C + origin


def _spacing_at(uv, t):
    """Distance from the predictions of targets ``t`` to their nearest other finite prediction [px]."""
    finite = np.isfinite(uv).all(axis=1)
    out = np.full(len(t), np.inf)
    if finite.sum() < 2:
        return out
    ok = finite[t]
    if ok.any():
        d, _ = cKDTree(uv[finite]).query(uv[t[ok]], k=2)
        out[ok] = d[:, 1]
    return out


def _seeds_agree(uv, sd: _Seeds) -> bool:
    """Do all seeds lie within a quarter spacing of their targets' predictions ``uv`` (n, 2)?"""
    pred = uv[sd.t]
    if np.isfinite(uv).all(axis=1).sum() < 2 or not np.isfinite(pred).all():
        return False
    return bool(np.all(np.hypot(*(sd.uv - pred).T) <= 0.25 * _spacing_at(uv, sd.t)))


def _starting_poses(vm: ViewMatcher, im: _Image, X, init_pose, opt: IdentifyOptions, where, seed):
    """Step 1: candidate poses, their scores, and whether the best is convincing."""
    sd = im.sd
    meas = vm.measured[0]
    # a generous threshold for the seeds' RANSAC: the nominal camera's distortion is in them
    disc_spacing = float(np.median(cKDTree(meas).query(meas, k=2)[0][:, 1])) if len(meas) >= 2 else np.inf
    seed_thr = float(np.clip(0.3 * disc_spacing, 4.0, 1e4)) if np.isfinite(disc_spacing) else 50.0
    sX, suv = X[sd.t], sd.uv

    def scored(poses):
        if not poses:
            return [], np.zeros(0), None
        count, expected, uv, _ = vm.score(np.zeros(len(poses), np.int64), np.stack([p[0] for p in poses]),
                                          np.stack([p[1] for p in poses]))
        return list(count), expected, uv

    if init_pose is not None:   # a convincing approximate pose needs no seeds' candidates
        pose = (np.asarray(init_pose[0], float), np.asarray(init_pose[1], float))
        count, expected, uv = scored([pose])
        if count[0] >= max(opt.min_identified, 0.5 * expected[0]) and (len(sd.t) == 0 or _seeds_agree(uv[0], sd)):
            return [pose], count, True
    cands = _candidate_poses(sX, suv, vm.camera, init_pose, seed_thr, where)
    scores, expected, uv = scored(cands)
    convincing = False
    if cands:
        b = int(np.argmax(scores))
        convincing = scores[b] >= max(opt.min_identified, 0.5 * expected[b]) and _seeds_agree(uv[b], sd)
    if not convincing and len(sd.t) >= 3:
        more = _subset_poses(sX, suv, vm.camera, where, np.random.default_rng(seed))
        cands += more
        scores += scored(more)[0]
    return cands, scores, convincing


def _best_refined(vm: ViewMatcher, im: _Image, cands, scores, convincing, opt: IdentifyOptions) -> dict:
    """Step 4's choice: the best-scored start, or up to ``max_starts`` of them (refined together):
    the first in score order that fits, else the one with most pairs."""
    order = np.argsort(scores, kind="stable")[::-1]
    picked: list[int] = []
    for k in order[: 1 if convincing else opt.max_starts]:
        C = cands[k][1]
        if any(np.linalg.norm(C - cands[j][1]) < 1e-6 * (1 + np.linalg.norm(C)) for j in picked):
            continue
        picked.append(int(k))
    ref = vm.refine(np.zeros(len(picked), np.int64), np.stack([cands[k][0] for k in picked]),
                    np.stack([cands[k][1] for k in picked]), coded=[im.coded])
    best = None
    for v, k in enumerate(picked):
        st = ref.view(v)
        if best is None or (st["fits"], len(st["tm"])) > (best["fits"], len(best["tm"])):
            best = st
        if st["fits"] and len(st["tm"]) >= max(opt.min_identified, 0.5 * scores[k]):
            break
    return best


def _finish(vm: ViewMatcher, image: int, best, im: _Image, init_pose, opt: IdentifyOptions) -> ImageIdentification:
    """The identities of the rows, the markers and marks checked against the pose (step 5)."""
    sd, kind, code, uv_all, disc_rows = im.sd, im.kind, im.code, im.uv_all, im.disc_rows
    meas = vm.measured[image]
    R, C, uv, gate, s = best["R"], best["C"], best["uv"], best["gate"], best["s"]
    tm, jm, e = best["tm"], best["jm"], best["e"]
    target = np.full(im.n_rows, -1, np.int64)
    target[disc_rows[jm]] = tm
    residual = np.full((im.n_rows, 2), np.nan)
    residual[disc_rows[jm]] = meas[jm] - uv[tm]
    wrong_codes, e_codes = np.zeros(0, np.int64), np.zeros(0)
    if len(sd.coded_t):     # markers: identified by code, kept when they agree with the pose
        # a coded target's correction comes from the discs around it
        c_corr, c_spread = _correction_at(meas, best, sd.coded_t, opt)
        cres = uv_all[sd.coded_rows] - uv[sd.coded_t]
        ce = np.hypot(*(cres - c_corr).T)
        cgate = np.clip(opt.gate_factor * np.hypot(s if np.isfinite(s) else 0.0, c_spread), opt.min_gate_px,
                        np.inf)
        cgate = np.maximum(cgate, vm.seed_tolerance(gate[sd.coded_t], _spacing_at(uv, sd.coded_t)))
        agree = np.isfinite(ce) & (ce <= cgate)
        # a coded target matched as a disc too (codes_are_markers=False): the marker wins
        twice = np.isin(target, sd.coded_t[agree]) & (kind == "disc")
        target[twice] = -1
        residual[twice] = np.nan
        target[sd.coded_rows[agree]] = sd.coded_t[agree]
        residual[sd.coded_rows[agree]] = cres[agree]
        wrong_codes, e_codes = code[sd.coded_rows[~agree]], ce[agree]
    wrong_marks = np.zeros(0, np.int64)
    if sd.n_marks:          # marks: compared with the prediction of their target
        mt, muv = sd.t[sd.is_mark], sd.uv[sd.is_mark]
        m_corr, _ = _correction_at(meas, best, mt, opt)
        d = np.hypot(*(muv - uv[mt] - m_corr).T)
        tol = vm.seed_tolerance(gate[mt], _spacing_at(uv, mt))
        wrong_marks = mt[~(np.isfinite(d) & (d <= tol))]
    n_id = int(np.sum(target >= 0))
    e_all = np.concatenate([e, e_codes])
    rms = float(np.sqrt(np.mean(e_all**2))) if len(e_all) else np.nan
    gate_med = float(np.median(gate[tm])) if len(tm) else np.nan
    n_wrong = len(wrong_marks) + len(wrong_codes)
    reason = _verdict(vm, best, n_id, rms, len(disc_rows), n_wrong, len(sd.t), init_pose, opt)
    if reason and n_id >= opt.min_identified:      # a wrong start: none of its identities is trusted
        target[:] = -1
        residual[:] = np.nan
        n_id = 0
    return ImageIdentification(target, R, C, n_id, len(sd.coded_t), len(sd.t), gate_med, rms, residual,
                               wrong_marks=np.asarray(wrong_marks, np.int64),
                               wrong_codes=np.asarray(wrong_codes, np.int64), iterations=best["iterations"],
                               reason=reason)


def _verdict(vm: ViewMatcher, best, n_id, rms, n_discs, n_wrong, n_seeds, init_pose, opt: IdentifyOptions) -> str:
    """Why the image is not usable ("" when it is): step 5's checks."""
    uv, inside, tm = best["uv"], best["inside"], best["tm"]
    # targets the pose puts in the frame, away from the border, that could have been matched
    s_ = vm.camera.sensor
    margin = 0.5 * best["spacing"] if inside.sum() > 1 else 0.0
    margin = min(margin, 0.1 * min(s_.width_px, s_.height_px))
    with np.errstate(invalid="ignore"):
        well_inside = inside & (uv[:, 0] > margin) & (uv[:, 1] > margin) & \
            (uv[:, 0] < s_.width_px - 1 - margin) & (uv[:, 1] < s_.height_px - 1 - margin)
    expected = min(int(np.sum(well_inside & vm.match_target)), n_discs)
    if n_id < opt.min_identified:
        return f"only {n_id} target(s) identified, at least {opt.min_identified} needed"
    if not best["fits"]:
        return (f"the identified points do not fit one pose (RMS {rms:.3g} px after the local "
                f"correction, spacing of the targets {best['spacing']:.3g} px): the start (marks, "
                "codes or nominal focal length) is probably wrong")
    if len(tm) < opt.min_fraction * expected:
        return (f"only {len(tm)} of about {expected} targets expected in the frame identified: the "
                "start (marks, codes or nominal focal length) is probably wrong")
    if n_seeds and init_pose is None and n_wrong > 0.5 * n_seeds:
        return (f"{n_wrong} of the {n_seeds} seeds (marks and coded targets) disagree with the "
                "identification: the marks or codes are unreliable")
    return ""


def _correction_at(meas, best, t, opt: IdentifyOptions):
    """Local correction and spread at the predictions of targets ``t`` from the pairs."""
    uv, tm, jm = best["uv"], best["tm"], best["jm"]
    if len(tm) < 4:
        return np.zeros((len(t), 2)), np.zeros(len(t))
    res = meas[jm] - uv[tm]
    pos = np.full(len(uv), -1)
    pos[tm] = np.arange(len(tm))
    at = np.where(np.isfinite(uv[t]), uv[t], 0.0)
    return local_correction(at, uv[tm], res, pos[t], neighbours=opt.neighbours)
