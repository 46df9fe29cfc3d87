"""From photographs with a thin survey: resection from the marked control points, then referencing.

The identification (:mod:`fieldcal.field.identify`) finds targets by projecting their surveyed
coordinates; an image needs :data:`~fieldcal.field.adjustment.MIN_POINTS_PER_IMAGE` (6) of
them. A sheet with four control points and every other target unsurveyed (issue 26 goal 6:
PhotoModeler's and DBAT's calibration sheet) has too few: there the network is started from
the control points alone and grown by automatic referencing (:mod:`fieldcal.field.referencing`):

1. **Control points.** Each image's marks (marks.csv) of surveyed targets: a mark is snapped to
   the nearest measured point within :data:`SNAP_PX` (its measured centre and sigma); a mark no
   measured point is near (a ringed control target whose centre the detector does not measure)
   is taken as measured, with the session's ``default_sigma_px``: marks are then expected to be
   measured points (for example another program's subpixel marks), not rough clicks.
2. **Resection** of every image from its marked control points (four or more,
   :func:`fieldcal.field.resection.resect`: IPPE for coplanar points) with the nominal camera
   (``lens.nominal_focal_mm``, principal point at the centre, no distortion). Why resection and
   not relative orientation (:mod:`fieldcal.field.relative_orientation`): every image has its
   four known points, which give its pose at once in the survey's frame; a relative orientation
   needs correspondences of the plain discs first, and finding those is what needs the poses.
3. **Referencing and adjustment, in rounds** (:data:`GATES_PX`): the discs no mark names are
   matched across the oriented images with a gate that starts wide (the nominal camera's
   missing distortion) and shrinks as the camera is adjusted; each round adjusts the control
   points and the tracks (unsurveyed targets, ids ``AR0001``, ...) from the last round's camera
   and poses (the first round only ``f, xp, yp, k1, k2``: :data:`FIRST_ROUND`). The last round
   uses the session's referencing options and the final adjustment options.
4. **Perspective eccentricity** (when the session gives ``field.target_diameter_mm``): the
   targets' normals are the given ones or, for a planar field, the plane of the adjusted targets
   (:func:`fieldcal.field.normals.resolve_normals`; in 3-D the best-supported local plane of the
   adjusted targets, :func:`~fieldcal.field.normals.estimate_normals`); every point of a
   target with a normal is moved to the image of its centre
   (:func:`fieldcal.field.eccentricity.correction_px`) and the adjustment repeated (warm). A
   target without a normal keeps its measured centre (reported in ``summary``).

Without marks, a session of coded targets (surveyed or not) starts from the markers instead of
steps 1-2 (:func:`start_from_codes`: the codes name the points, the adjustment's bootstrap orients
the images by relative orientation and resection), then grows the same way (steps 3-4; markers
have no eccentricity).

The datum is the session's (weighted control, or ``field.datum`` ``"free"`` with the control
points' coordinates only as the start); ``scale_bars.csv`` joins the last adjustment.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa

from fieldcal.errors import GeometryError
from fieldcal.field.adjustment import MIN_POINTS_PER_IMAGE, AdjustmentOptions, FieldResult, InitialValues, adjust_field
from fieldcal.field.eccentricity import correction_px
from fieldcal.field.identify import measured_points
from fieldcal.field.normals import plane_tolerance_m, resolve_normals
from fieldcal.field.referencing import ReferencingOptions, reference_discs, track_ids
from fieldcal.field.resection import resect
from fieldcal.model.camera import Camera
from fieldcal.session.data import FieldData, FieldObservations, TargetField

__all__ = ["SNAP_PX", "GATES_PX", "CODED_GATES_PX", "MIN_IMAGES", "is_thin", "ThinStart", "start_from_marks",
           "start_from_codes"]

SNAP_PX = 3.0
"""A mark is the measured point nearest it within this distance [px]."""
GATES_PX = (20.0, 6.0, 2.0)
"""Referencing gates of the rounds before the last [px]: the nominal camera's error where the
pose from four marks leaves it (a few to ~15 px of uncorrected distortion between the control
points, which the resection absorbs at the corners), then a first adjusted camera's, then a few
times the noise; the last round uses the session's :class:`ReferencingOptions`. A gate must stay
well below half the discs' spacing in the image (~70 px on the rendered sheet, ~100 px on DBAT's):
at 40 px one rendered draw's first round took wrong tracks and its adjustment failed."""
MIN_IMAGES = 3


def is_thin(targets: TargetField) -> bool:
    """Too few surveyed targets for an image to be identified by projection (fewer than
    :data:`~fieldcal.field.adjustment.MIN_POINTS_PER_IMAGE`)."""
    return int(np.sum(targets.surveyed)) < MIN_POINTS_PER_IMAGE


@dataclass
class ThinStart:
    """The result of :func:`start_from_marks`.

    Attributes
    ----------
    data : FieldData
        The control points' and the referenced discs' observations of the oriented images.
    result : FieldResult
        The last adjustment.
    report : list of dict
        One entry per image of the session (as :mod:`fieldcal.field.from_images` reports).
    n_tracks : int
        Referenced targets in ``data``.
    eccentricity : dict
        ``stats.eccentricity`` of the document (``max_px``, ``normals``, ``applied``, ``reason``).
    """

    data: FieldData
    result: FieldResult
    report: list[dict]
    n_tracks: int
    eccentricity: dict


def _sigma(table: pa.Table, rows, default: float) -> np.ndarray:
    if "sigma_px" not in table.column_names:
        return np.full(len(rows), default)
    s = np.asarray(table.column("sigma_px").fill_null(np.nan).to_numpy(zero_copy_only=False), float)[rows]
    return np.where(np.isfinite(s) & (s > 0), s, default)


@dataclass
class _View:
    """One image: its control observations, its unnamed discs and its pose."""

    index: int                  # in the session's images
    control_t: np.ndarray       # target indices (into the surveyed targets)
    control_uv: np.ndarray
    control_sigma: np.ndarray
    n_snapped: int
    disc_uv: np.ndarray         # the usable discs no mark names
    disc_sigma: np.ndarray
    R: np.ndarray | None = None
    C: np.ndarray | None = None


def _view(index, table, marks, default_sigma) -> _View:
    """Step 1 for one image: the marks snapped to measured points, the other discs."""
    kind, _, uv_all, usable = measured_points(table)
    t, muv = marks
    rows = np.flatnonzero(usable)
    uv, sig = np.asarray(muv, float).reshape(-1, 2).copy(), np.full(len(t), float(default_sigma))
    named = np.zeros(len(uv_all), bool)
    snapped = 0
    if len(rows):
        d = np.linalg.norm(uv[:, None] - uv_all[rows][None], axis=2)
        for k in range(len(t)):
            j = int(np.argmin(d[k]))
            if d[k, j] <= SNAP_PX and not named[rows[j]]:
                named[rows[j]] = True
                uv[k], sig[k] = uv_all[rows[j]], _sigma(table, [rows[j]], default_sigma)[0]
                snapped += 1
    free = np.flatnonzero(usable & ~named & (kind == "disc"))
    return _View(index, np.asarray(t, np.int64), uv, sig, snapped, uv_all[free], _sigma(table, free, default_sigma))


def _resect(view: _View, X, camera: Camera, name: str):
    """Step 2: the pose of one image from its control points; a reason when it has none."""
    if len(view.control_t) < 4:
        return f"only {len(view.control_t)} marked control point(s): resection needs 4"
    try:
        r = resect(X[view.control_t], view.control_uv, camera, where=name)
    except GeometryError as err:
        return str(err)
    view.R, view.C = r.R_world_to_camera, r.center_m
    return None


def _data(session_like: dict, targets: TargetField, views, tracks, images, X_start_m) -> tuple[FieldData, np.ndarray]:
    """FieldData of the control points and the tracks (targets: the surveyed ones, then one per
    track) and the start of the targets' coordinates."""
    img, tgt, uv, sig = [], [], [], []
    for n, v in enumerate(views):
        img.append(np.full(len(v.control_t), n))
        tgt.append(v.control_t)
        uv.append(v.control_uv)
        sig.append(v.control_sigma)
    n0 = len(targets)
    if tracks is not None and len(tracks):
        img.append(tracks.image)
        tgt.append(n0 + tracks.track)
        uv.append(np.stack([views[m].disc_uv[p] for m, p in zip(tracks.image, tracks.point, strict=True)]))
        sig.append(np.array([views[m].disc_sigma[p] for m, p in zip(tracks.image, tracks.point, strict=True)]))
    obs = FieldObservations(np.concatenate(img), np.concatenate(tgt).astype(np.int64), np.concatenate(uv),
                            np.concatenate(sig))
    n_tr = 0 if tracks is None else len(tracks)
    ids = track_ids(n_tr, session_like["listed_ids"])         # never an id targets.csv lists
    all_targets = targets.with_unsurveyed(ids)
    X0 = X_start_m if tracks is None else np.vstack([X_start_m, tracks.X_m])
    data = FieldData(sensor=session_like["sensor"], targets=all_targets, images=[images[v.index] for v in views],
                     obs=obs, nominal_focal_mm=session_like["nominal_focal_mm"],
                     default_sigma_px=session_like["default_sigma_px"], meta=dict(session_like["meta"]))
    return data, X0


FIRST_ROUND = ("f_mm", "xp_mm", "yp_mm", "k1", "k2")
"""The camera parameters of the first round, which starts from the nominal camera: the dominant
terms (the others held at 0 until the tracks are cleaner and the camera closer; a full set from
so far away can leave LM where the normal equations are not positive definite)."""


def _first_estimate(options: AdjustmentOptions):
    """:data:`FIRST_ROUND` within the session's ``estimate`` (when it gives one)."""
    return tuple(p for p in FIRST_ROUND if options.estimate is None or p in options.estimate)


def _round(data, X0, params, views, options, how, progress) -> FieldResult:
    init = InitialValues(np.asarray(params, float).copy(), np.stack([v.R for v in views]),
                         np.stack([v.C for v in views]), np.zeros(len(data.obs), bool),
                         np.full(len(views), np.nan), how, targets_m=X0)
    return adjust_field(data, options, progress=progress, initial=init)


def start_from_marks(session, measurements: Mapping[str, pa.Table], targets: TargetField, marks: dict,
                     options: AdjustmentOptions, working_options: AdjustmentOptions, nominal: Camera, *,
                     referencing: ReferencingOptions | None = None, scale_bars: Callable | None = None,
                     say: Callable[[str], None] = lambda _line: None,
                     progress: Callable[[str], None] | None = None) -> ThinStart:
    """Calibrate from photographs whose survey is thin (module docstring).

    ``targets``: the surveyed targets (marks' target indices refer to them); ``marks``:
    ``{image index: (target indices, uv)}``; ``scale_bars``: called with the final targets, returns
    the :class:`~fieldcal.session.data.ScaleBars` between them (or None;
    :func:`fieldcal.session.loader.scale_bars_among`).

    Raises
    ------
    GeometryError
        Fewer than :data:`MIN_IMAGES` images could be resected from their marks (the reasons listed).
    """
    names = [im.file for im in session.images]
    X = targets.xyz_m
    views, reasons = [], {}
    for i, name in enumerate(names):
        if name not in measurements:
            reasons[i] = "not measured (the image could not be read or measured)"
            continue
        if i not in marks:
            reasons[i] = "no marks of surveyed control points in marks.csv (the survey is too thin to identify targets)"
            continue
        v = _view(i, measurements[name], marks[i], session.default_sigma_px)
        why = _resect(v, X, nominal, name)
        if why is None:
            views.append(v)
        else:
            reasons[i] = why
    if len(views) < MIN_IMAGES:
        raise GeometryError(f"the survey has {len(X)} targets, too few to identify targets in the images; only "
                            f"{len(views)} image(s) could be resected from their marked control points (at least "
                            f"{MIN_IMAGES} needed): {_reasons(names, reasons)}")
    say(f"thin survey ({len(X)} surveyed targets): {len(views)} images resected from their marked control points "
        f"({sum(v.n_snapped for v in views)} of {sum(len(v.control_t) for v in views)} marks on measured points)")
    grow = _Growth(session, targets, X, nominal, GATES_PX, "resection from the marked control points",
                   "resection from marks")
    return _grow(grow, measurements, views, reasons, options, working_options, referencing, scale_bars, say,
                 progress, {i: len(m[0]) for i, m in marks.items()})


def start_from_codes(session, measurements: Mapping[str, pa.Table], targets: TargetField,
                     options: AdjustmentOptions, working_options: AdjustmentOptions, nominal: Camera, *,
                     referencing: ReferencingOptions | None = None, scale_bars: Callable | None = None,
                     say: Callable[[str], None] = lambda _line: None,
                     progress: Callable[[str], None] | None = None) -> ThinStart:
    """Calibrate from photographs of coded targets that no survey (or too thin a one) places.

    ``targets``: every target of targets.csv (surveyed or not). Each image's markers whose code
    a coded target of ``targets`` carries are its control observations (one per code); an image
    with fewer than :data:`~fieldcal.field.adjustment.MIN_POINTS_PER_IMAGE` is left out. The
    network of the coded targets is started by :func:`fieldcal.field.adjustment.adjust_field`'s
    own bootstrap (:mod:`fieldcal.field.initial`: the relative orientation of the best pair, then
    resection and intersection on the growing network; or resection on three or more surveyed
    targets), adjusted with :data:`FIRST_ROUND`, and grown by automatic referencing of the plain
    discs as :func:`start_from_marks` does (gates :data:`CODED_GATES_PX`: the first camera is
    adjusted already). Why relative orientation and not a DLT on bar-scaled points: the markers'
    codes give the correspondences at once, which is all a relative orientation needs; a DLT needs
    six or more points in the survey's frame in one image, which a free network has not.

    Raises
    ------
    GeometryError
        Fewer than :data:`MIN_IMAGES` images see enough coded targets (the reasons listed).
    """
    names = [im.file for im in session.images]
    coded = np.flatnonzero(targets.codes >= 0)
    slot = {int(c): n for n, c in enumerate(targets.codes[coded])}
    seen = [_coded_view(i, measurements[name], slot, session.default_sigma_px) if name in measurements else None
            for i, name in enumerate(names)]
    n_views = np.bincount(np.concatenate([v.control_t for v in seen if v is not None] + [np.zeros(0, np.int64)]),
                          minlength=len(coded))
    placed = n_views >= 2                                      # one view neither places a target nor checks it
    sub = _subset(targets, coded[placed])
    views, reasons = [], {}
    for i, v in enumerate(seen):
        if v is None:
            reasons[i] = "not measured (the image could not be read or measured)"
            continue
        v = _only(v, placed)
        if len(v.control_t) >= MIN_POINTS_PER_IMAGE:
            views.append(v)
        else:
            reasons[i] = (f"only {len(v.control_t)} coded target(s) of targets.csv seen that another image sees "
                          f"too: an image needs {MIN_POINTS_PER_IMAGE} to join the network")
    if len(views) < MIN_IMAGES:
        raise GeometryError(f"the survey has {int(np.sum(targets.surveyed))} targets, too few to identify targets "
                            f"in the images, and only {len(views)} image(s) see {MIN_POINTS_PER_IMAGE} or more coded "
                            f"targets (at least {MIN_IMAGES} needed): {_reasons(names, reasons)}")
    like = _like(session)
    data, _ = _data(like, sub, views, None, list(session.images), sub.xyz_m)
    first = adjust_field(data, replace(working_options, estimate=_first_estimate(options)))
    for n, v in enumerate(views):
        v.R, v.C = first.R_world_to_camera[n], first.center_m[n]
    X_start = np.asarray(first.targets_m, float)
    placed = np.isfinite(X_start).all(axis=1)                 # not placed: rays from one station only
    if not placed.all():
        sub, X_start = _subset(sub, np.flatnonzero(placed)), X_start[placed]
        views = [_only(v, placed) for v in views]
    say(f"coded targets only ({len(sub)} listed, {int(np.sum(sub.surveyed))} surveyed): {len(views)} images "
        f"oriented from their {len(data.obs)} marker points ({first.initial.how}); f {first.params[0]:.5f} mm")
    grow = _Growth(session, sub, X_start, first.camera, CODED_GATES_PX,
                   "the adjustment of the coded targets", "coded targets", warm_control=True)
    return _grow(grow, measurements, views, reasons, options, working_options, referencing, scale_bars, say,
                 progress, {})


CODED_GATES_PX = (6.0, 2.0)
"""Referencing gates of the rounds before the last when the network starts from coded targets:
the camera is adjusted from the markers already (its error where discs lie is a few px at most)."""


def _reasons(names, reasons: dict) -> str:
    return "; ".join(f"{names[i]}: {r}" for i, r in list(reasons.items())[:5])


def _subset(targets: TargetField, rows) -> TargetField:
    normals = None if targets.normals is None else targets.normals[rows]
    return replace(targets, ids=targets.ids[rows], xyz_m=targets.xyz_m[rows], sigma_mm=targets.sigma_mm[rows],
                   codes=targets.codes[rows], normals=normals)


def _coded_view(index, table, slot: dict, default_sigma) -> _View:
    """One image's markers whose codes name targets (``slot``: code -> target index), one per
    code, and its usable plain discs."""
    kind, code, uv_all, usable = measured_points(table)
    rows = np.flatnonzero((kind == "aruco") & usable & np.isin(code, list(slot)))
    rows = rows[np.unique(code[rows], return_index=True)[1]]
    free = np.flatnonzero(usable & (kind == "disc"))
    return _View(index, np.array([slot[int(c)] for c in code[rows]], np.int64), uv_all[rows],
                 _sigma(table, rows, default_sigma), len(rows), uv_all[free], _sigma(table, free, default_sigma))


def _only(v: _View, keep) -> _View:
    """``v`` with the control points of the targets ``keep`` only, renumbered among them (its pose kept)."""
    new = np.cumsum(keep) - 1
    k = keep[v.control_t]
    return _View(v.index, new[v.control_t[k]], v.control_uv[k], v.control_sigma[k], int(k.sum()), v.disc_uv,
                 v.disc_sigma, v.R, v.C)


def _like(session) -> dict:
    return {"sensor": session.sensor, "nominal_focal_mm": session.nominal_focal_mm,
            "default_sigma_px": session.default_sigma_px,
            "meta": {"camera_id": session.camera_id, "session_id": session.session_id},
            "listed_ids": session.targets().ids.tolist()}


@dataclass
class _Growth:
    """How a network grows: the session, its control targets and their start, the camera to
    start from, the gates of the rounds before the last, and how the start is named."""

    session: object
    targets: TargetField
    X_start_m: np.ndarray
    camera: Camera
    gates_px: tuple
    how: str
    start: str
    warm_control: bool = False      # each round starts the control targets where the last left them


def _grow(g: _Growth, measurements, views, reasons, options, working_options, referencing, scale_bars, say,
          progress, n_marks: dict) -> ThinStart:
    """Step 3 and 4 (module docstring): referencing and adjustment in rounds, then eccentricity."""
    session, images = g.session, list(g.session.images)
    like = _like(session)
    final_ref = referencing or ReferencingOptions()
    params, result, tracks, X_start = g.camera.params, None, None, g.X_start_m
    first = replace(working_options, estimate=_first_estimate(options))
    rounds = [(replace(final_ref, gate_px=gate), first if k == 0 and g.start != "coded targets" else working_options)
              for k, gate in enumerate(g.gates_px)]
    rounds.append((final_ref, options))
    for k, (ref, opts) in enumerate(rounds):
        cam = g.camera if result is None else result.camera
        tracks = reference_discs(cam, np.stack([v.R for v in views]), np.stack([v.C for v in views]),
                                 [v.disc_uv for v in views], ref)
        data, X0 = _data(like, g.targets, views, tracks, images, X_start)
        if k == len(rounds) - 1 and scale_bars is not None:
            data = replace(data, scale_bars=scale_bars(data.targets))
            n_bars = 0 if data.scale_bars is None else len(data.scale_bars)
            say(f"scale bars: {n_bars} between targets of the network (a bar to a listed unsurveyed plain "
                "target cannot be used: referencing gives its disc an id of its own)")
        how = g.how if result is None else "the previous round (warm start)"
        result = _round(data, X0, params, views, opts, how, progress if k == len(rounds) - 1 else None)
        params = result.params
        if g.warm_control:
            X_start = np.asarray(result.targets_m, float)[:len(g.targets)]
        for n, v in enumerate(views):
            v.R, v.C = result.R_world_to_camera[n], result.center_m[n]
        say(f"referencing round {k + 1} (gate {ref.gate_px:g} px): {len(tracks)} unsurveyed targets, "
            f"{len(tracks.image)} points; f {result.params[0]:.5f} mm, rmse {result.stats()['rmse_px']:.3g} px")
    data, result, ecc = _eccentricity(session, data, result, options, progress, say)
    report = _report(session, measurements, n_marks, views, reasons, data, result, g.start)
    return ThinStart(data, result, report, len(tracks), ecc)


def _eccentricity(session, data: FieldData, result: FieldResult, options, progress, say):
    """Step 4: the discs' perspective eccentricity removed, the adjustment repeated (warm)."""
    diameter_mm = session.target_diameter_mm
    if not diameter_mm:
        return data, result, {"max_px": None, "normals": "none", "applied": False,
                              "reason": "no field.target_diameter_mm in the session"}
    X = np.asarray(result.targets_m, float)
    towards = np.zeros_like(X)
    np.add.at(towards, data.obs.target, result.center_m[data.obs.image])
    towards /= np.maximum(np.bincount(data.obs.target, minlength=len(X)), 1)[:, None]
    tn = resolve_normals(data.targets, xyz_m=X, estimate=True, tol_m=plane_tolerance_m(result.sigma_targets_m),
                         towards_m=towards)
    disc = tn.known & ((data.targets.codes < 0) if session.coded is not None else True)   # a marker has no eccentricity
    o = data.obs
    e = np.zeros((len(o), 2))
    for n in range(len(data.images)):
        k = np.flatnonzero((o.image == n) & disc[o.target])
        if len(k):
            e[k] = correction_px(result.camera, result.R_world_to_camera[n], result.center_m[n], X[o.target[k]],
                                 tn.normals[o.target[k]], diameter_mm / 2000.0)
    e = np.where(np.isfinite(e), e, 0.0)
    norm = np.hypot(e[:, 0], e[:, 1])
    sources = sorted(set(tn.source[np.unique(o.target)].tolist()))
    summary = {"max_px": float(norm.max()) if len(norm) else 0.0, "normals": ", ".join(sources),
               "applied": bool(norm.max() > 0) if len(norm) else False}
    if not summary["applied"]:
        summary["reason"] = "no target's normal is known (a field in 3-D without normals)"
        return data, result, summary
    n_unknown = int(np.sum(~tn.known[np.unique(o.target)]))
    if n_unknown:
        summary["n_uncorrected_targets"] = n_unknown
    data = replace(data, obs=FieldObservations(o.image, o.target, o.uv_px - e, o.sigma_px))
    init = InitialValues(np.asarray(result.params, float).copy(), result.R_world_to_camera, result.center_m,
                         ~result.obs_used, np.full(len(data.images), np.nan),
                         "the adjustment before the eccentricity correction (warm start)", targets_m=X)
    say(f"perspective eccentricity removed from {int(np.sum(norm > 0))} points (normals: {summary['normals']}): "
        f"median {np.median(norm):.4f} px, max {norm.max():.4f} px")
    return data, adjust_field(data, options, progress=progress, initial=init), summary


def _report(session, measurements, n_marks: dict, views, reasons, data, result, start: str) -> list[dict]:
    """One entry per image, in the shape :mod:`fieldcal.field.from_images` reports."""
    at = {v.index: n for n, v in enumerate(views)}
    used = np.bincount(data.obs.image[result.obs_used], minlength=len(views))
    out = []
    for i, im in enumerate(session.images):
        table = measurements.get(im.file)
        n = at.get(i)
        coded = 0 if n is None or start != "coded targets" else int(len(views[n].control_t))
        entry = {"image": im.file, "n_measured": 0 if table is None else int(table.num_rows), "n_coded": coded,
                 "n_identified": 0 if n is None else int(np.sum(data.obs.image == n)),
                 "n_identified_first": 0, "n_marks": int(n_marks.get(i, 0)),
                 "n_used": 0 if n is None else int(used[n]), "wrong_marks": [], "wrong_codes": [], "rms_px": None,
                 "eccentricity_max_px": None, "start": None if n is None else start,
                 "status": "ok" if n is not None else "left out", "reason": "" if n is not None else reasons[i]}
        out.append(entry)
    return out
