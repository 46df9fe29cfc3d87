"""Field calibration from measured images: identify, adjust, identify the rest, identify again, adjust again.

The measuring step (:func:`fieldcal.pipeline.measure`, one ``measurements`` table per
image) knows nothing of the targets' identities. This module turns those tables into a
calibration (:func:`calibrate_from_measurements`):

0. **A thin survey** (fewer than 6 surveyed targets, :func:`fieldcal.field.thin_start.is_thin`) with
   marks.csv: the identification by projection cannot work; every image is resected from its
   marked control points and the network grown by automatic referencing instead
   (:func:`fieldcal.field.thin_start.start_from_marks`; the steps below are not taken). Without
   marks, a session of coded targets starts from the markers instead
   (:func:`fieldcal.field.thin_start.start_from_codes`: relative orientation, no survey needed).
1. **First identification, nominal camera.** Every image is identified
   (:func:`fieldcal.field.identify.identify_images`, all images at once) with the camera the
   session describes: the nominal focal length (``lens.nominal_focal_mm``), principal point at
   the sensor centre, no distortion. It starts from the coded targets (ArUco markers named in
   targets.csv) or, in fields without coded targets, from the hand marks of marks.csv (docs/
   conventions.md section 3). Images whose measurement table is missing (the file could not be read or
   measured) or with too few identified targets are left out and reported.
2. **First adjustment** (:func:`fieldcal.field.adjustment.adjust_field`) of the identified points,
   each with the detector's a-priori ``sigma_px`` (the session's ``default_sigma_px`` where
   the detector gives none). With adjusted targets (the default), a point of a target that
   only one image sees has no redundancy: its residual is absorbed by the target's
   coordinates, so it can neither be checked nor add more than the survey's weak control
   (5 mm is ~0.6 px at the paper's 60 m). Such points are left out, and an image left with
   fewer than 6 points with them. (They would also drive the adjustment's gross-error
   scale, a median over all residuals, towards zero and start a cascade of rejections.)
3. **Pose priors** (:func:`fieldcal.field.identify_session.identify_remaining`): the calibrated
   camera and the oriented images start the images left out so far (their station, a marker's
   corners, a pose-free search, the other images' centres). While images remain and new ones
   were found, the adjustment is repeated with them (warm) and the rest tried again with its
   better camera (``MAX_PRIOR_ROUNDS``). An image found this way is admitted only by an
   adjustment it does not spoil (:func:`_admit`: when the adjustment fails, or the image's
   points are mostly rejected or scatter three times more than the others', the group is
   halved until the culprits are found; they are left out with the reason).
4. **Perspective eccentricity** (when the session gives ``target_diameter_mm``): the
   detector measures the centre of the imaged ellipse; with the calibrated camera and the
   poses :func:`fieldcal.field.eccentricity.correction_px` moves every disc's point to the image
   of its centre. The targets' normals are given (targets.csv's ``nx,ny,nz``, the session's
   ``field.target_normal``), the plane of a planar field, or estimated from the adjusted
   targets' local planes (:mod:`fieldcal.field.normals`); a disc whose normal is not
   determined is left out when such discs are few; else it keeps its point, and the largest
   move of the parameters its eccentricity can cause is added to their variances
   (:mod:`fieldcal.field.sensitivity`).
   ``data.meta["eccentricity"]`` says what was done (``max_px``, ``normals``, ``n_targets``),
   ``data.meta["target_normals"]`` holds the normals used.
5. **Second identification, calibrated camera**, from the adjusted poses (kept: they are the
   adjustment's, better than one image's resection) and target coordinates: the gates shrink
   to the measurement noise, and targets near the corners, where the nominal camera's missing
   distortion was too large, are found too. Images left out so far are tried again from their
   seeds.
6. **Final adjustment**: the result (unless step 7 follows). The markers' a-priori sigmas are first scaled by how
   much more their normalised residuals scatter than the discs' did in the first adjustment
   (a variance component, at least 1): the corner-based centres of markers measure worse
   than the detector's edge-line sigma says. It starts from the latest adjustment (a warm
   start: its interior orientation, poses and targets, with the suspects a cold start would
   have: the initialisers' outliers that were never readmitted and the gross errors), so it
   reaches the same optimum without the initial values and with fewer rounds.

6b. **Unsurveyed coded targets** (targets.csv rows with a code and empty ``X, Y, Z``): their
   markers in the adjusted images are identified by code, intersected from the adjusted poses
   and the adjustment is repeated (warm) with them as unsurveyed targets (:func:`_coded_unsurveyed`).
   The images are oriented from the surveyed targets only.

7. **Automatic referencing** (optional, ``referencing``; :mod:`fieldcal.field.referencing`):
   the discs no target names are matched across the adjusted images, become unsurveyed
   targets (``AR0001``, ...) and the adjustment is repeated from step 6's (warm).

The report has one entry per image of the session: ``image``, ``status`` (``"ok"`` or
``"left out"``), ``reason``, ``n_measured`` (rows of its measurement table), ``n_coded``
(markers whose code names a target), ``n_identified`` (second pass), and for diagnosis
``n_identified_first``, ``n_used`` (points given to the adjustment), ``n_marks``,
``wrong_marks`` (ids of marks that disagree with the identification), ``wrong_codes``,
``rms_px`` (identification residual after the local correction, second pass) and
``eccentricity_max_px``. The second pass's
:class:`~fieldcal.field.identify.ImageIdentification` of every measured image is in
``data.meta["identifications"]`` (keyed by image name).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np
import pyarrow as pa

from fieldcal.errors import GeometryError, InputError, one_line
from fieldcal.field.adjustment import (
    MIN_POINTS_PER_IMAGE,
    AdjustmentOptions,
    FieldResult,
    InitialValues,
    adjust_field,
)
from fieldcal.field.eccentricity import correction_px
from fieldcal.field.identify import IdentifyOptions, identify_images, measured_points
from fieldcal.field.identify_session import REASON_AMBIGUOUS, REASON_NO_START, PriorOptions, identify_remaining
from fieldcal.field.intersection import intersect_targets
from fieldcal.field.normals import (
    eccentricity_bound_px,
    measured_shape_vectors,
    normals_summary,
    plane_tolerance_m,
    resolve_normals,
)
from fieldcal.field.referencing import ReferencingOptions, reference_discs, track_ids
from fieldcal.field.sensitivity import eccentricity_bias_bounds, with_bias_bounds
from fieldcal.field.thin_start import is_thin, start_from_codes, start_from_marks
from fieldcal.model.camera import INDEX, Camera
from fieldcal.robust import robust_sigma
from fieldcal.session.data import FieldData, FieldObservations, TargetField
from fieldcal.session.loader import Session, scale_bars_among

__all__ = ["calibrate_from_measurements", "nominal_camera", "target_normals_of", "identification_summary",
           "reason_category"]

MIN_IMAGES = 3
MIN_POINTS = MIN_POINTS_PER_IMAGE
"""The adjustment's minimum of points per image."""


def nominal_camera(session: Session) -> Camera:
    """The session's nominal camera: ``lens.nominal_focal_mm``, principal point at the sensor
    centre, no distortion."""
    f = session.nominal_focal_mm
    if f is None:
        raise InputError("lens.nominal_focal_mm is needed to identify the targets in the images "
                         "(the nominal camera projects the surveyed targets)",
                         session.manifest_where)
    params = np.zeros(13)
    params[INDEX["f_mm"]] = float(f)
    return Camera(session.sensor, params)


def target_normals_of(targets: TargetField, normals=None):
    """Unit normals (n, 3) of the targets' planes: ``normals`` when given, else the
    ``targets.normals``, else the best-fit plane's normal when the field is planar (NaN rows:
    unknown); None when none is known (a field in 3-D without normals; :func:`_eccentricity`
    estimates them)."""
    if normals is not None:
        N = np.asarray(normals, float).reshape(-1, 3)
        if N.shape[0] not in (1, len(targets)):
            raise InputError(f"target normals must be (n, 3) with n = {len(targets)}, got {N.shape}")
    tn = resolve_normals(targets, normals, estimate=False)
    return tn.normals if tn.known.any() else None


def _sigma(table: pa.Table, rows: np.ndarray, default: float) -> np.ndarray:
    if "sigma_px" not in table.column_names:
        return np.full(len(rows), default)
    s = np.asarray(table.column("sigma_px").fill_null(np.nan).to_numpy(zero_copy_only=False), float)[rows]
    return np.where(np.isfinite(s) & (s > 0), s, default)


def _identify_all(run, targets, sigma_m, camera, poses, only=None, fixed_pose: bool = False):
    """Identify the measured images (``only``: these indices) at once; ``poses`` maps image
    index -> (R, C) or is empty; ``fixed_pose``: the poses are an adjustment's and are kept."""
    idx = [i for i, name in enumerate(run.names) if name in run.measurements and (only is None or i in only)]
    idents = identify_images([run.measurements[run.names[i]] for i in idx], targets, camera,
                             marks=[run.marks.get(i) for i in idx], init_poses=[poses.get(i) for i in idx],
                             target_sigma_m=sigma_m, codes_are_markers=run.coded, options=run.identify,
                             names=[run.names[i] for i in idx], fixed_pose=fixed_pose)
    return dict(zip(idx, idents, strict=True))


def _build(run, keep, idents, *, uv_override=None, bound_px=None, marker_factor=1.0, single_view=True):
    """FieldData of the identified points of the images ``keep`` (session image indices).

    ``uv_override`` ({image index: per measured row}) replaces the measured points;
    ``bound_px`` (the same) bounds their remaining systematic error [px] (:func:`_eccentricity`;
    inf: the point is left out), kept aligned with the observations in
    ``data.meta["eccentricity_bound_px"]``;
    ``marker_factor`` scales the markers' a-priori sigmas (see :func:`_marker_factor`);
    ``single_view=False`` leaves out the points of targets that only one of the images sees,
    and then the images left with fewer than :data:`MIN_POINTS` points.

    Returns
    -------
    data : FieldData
    marker : (m,) bool ndarray
        Whether each observation is a marker's centre.
    keep : list of int
        The images in ``data`` (session indices).
    dropped : dict
        ``{image index: reason}`` of images dropped for lack of multi-view points.
    """
    keep = list(keep)
    dropped: dict[int, str] = {}
    while True:
        data, marker = _assemble(run.session, run.targets, run.images, keep, idents, run.measurements,
                                 run.names, uv_override, bound_px, marker_factor, single_view)
        counts = np.bincount(data.obs.image, minlength=len(keep))
        weak = [i for n, i in enumerate(keep) if counts[n] < MIN_POINTS]
        if not weak:
            return data, marker, keep, dropped
        for i in weak:
            dropped[i] = (f"only {counts[keep.index(i)]} of its identified targets are seen in other images "
                          f"too (at least {MIN_POINTS} needed with adjusted targets)" if not single_view else
                          f"only {counts[keep.index(i)]} identified targets (at least {MIN_POINTS} needed)")
        keep = [i for i in keep if i not in weak]
        if not keep:
            return data, marker, keep, dropped


def _assemble(session, targets, images, keep, idents, measurements, names, uv_override, bound_px,
              marker_factor, single_view):
    img, tgt, uv, sig, mk, bd = [], [], [], [], [], []
    for n, i in enumerate(keep):
        table = measurements[names[i]]
        rows = np.flatnonzero(idents[i].target >= 0)
        if bound_px is not None and i in bound_px:            # inf: left out (:func:`_eccentricity`)
            rows = rows[np.isfinite(bound_px[i][rows])]
        kind, _, uv_all, _ = measured_points(table)
        marker = kind[rows] == "aruco"
        img.append(np.full(len(rows), n))
        tgt.append(idents[i].target[rows])
        uv.append(uv_override[i][rows] if uv_override is not None and i in uv_override else uv_all[rows])
        sig.append(_sigma(table, rows, session.default_sigma_px) * np.where(marker, marker_factor, 1.0))
        bd.append(bound_px[i][rows] if bound_px is not None and i in bound_px else np.zeros(len(rows)))
        mk.append(marker)
    if not img:
        img, tgt, uv, sig, mk, bd = [np.zeros(0, int)], [np.zeros(0, int)], [np.zeros((0, 2))], [np.zeros(0)], \
            [np.zeros(0, bool)], [np.zeros(0)]
    obs = FieldObservations(np.concatenate(img), np.concatenate(tgt), np.concatenate(uv),
                            np.concatenate(sig))
    marker, bound = np.concatenate(mk), np.concatenate(bd)
    if not single_view:
        views = np.bincount(obs.target, minlength=len(targets))
        multi = views[obs.target] >= 2
        obs, marker, bound = obs.take(multi), marker[multi], bound[multi]
    meta = {"camera_id": session.camera_id, "session_id": session.session_id}
    if bound_px is not None:
        meta["eccentricity_bound_px"] = bound
    data = FieldData(sensor=session.sensor, targets=targets, images=[images[i] for i in keep], obs=obs,
                     nominal_focal_mm=session.nominal_focal_mm, default_sigma_px=session.default_sigma_px,
                     meta=meta, scale_bars=scale_bars_among(session, targets))
    return data, marker


def _marker_factor(result: FieldResult, marker: np.ndarray) -> float:
    """How much worse the markers' centres are than their a-priori sigma says, relative to
    the discs: a variance component from the first adjustment, at least 1 (from 10 of each).

    The adjustment's data-snooping statistic ``T = v^T Q_vv^-1 v / sigma0^2`` of each point is
    its squared residual normalised by its own redundancy (a marker on a target seen in few
    images has a small residual however bad it is), so ``sqrt(mean T_markers / mean T_discs)``
    is the factor; where the statistic is missing the squared normalised residuals are used.
    """
    used = result.obs_used
    T = np.asarray(result.obs_test, float)
    if not np.all(np.isfinite(T[used])):
        z = result.residual_px / result.data.obs.sigma_px[:, None]
        T = np.sum(z**2, axis=1)
    a, b = used & marker, used & ~marker
    if a.sum() < 10 or b.sum() < 10:
        return 1.0
    return float(max(1.0, np.sqrt(np.mean(T[a]) / np.mean(T[b]))))


def _usable(idents, names, measurements):
    return [i for i in range(len(names)) if names[i] in measurements and i in idents and idents[i].ok]


def _check_enough(keep, names, idents, measurements, stage):
    if len(keep) >= MIN_IMAGES:
        return
    reasons = []
    for i, name in enumerate(names):
        if name not in measurements:
            reasons.append(f"{name}: not measured")
        elif i in idents and not idents[i].ok:
            reasons.append(f"{name}: {idents[i].reason}")
    more = "; ".join(reasons[:5]) + (f"; and {len(reasons) - 5} more" if len(reasons) > 5 else "")
    raise GeometryError(f"only {len(keep)} of {len(names)} images could be identified ({stage}); "
                        f"at least {MIN_IMAGES} are needed: {more}")


def calibrate_from_measurements(session: Session, measurements: Mapping[str, pa.Table],
                                options: AdjustmentOptions | None = None, *,
                                progress: Callable[[str], None] | None = None,
                                target_normals=None, eccentricity: bool = True, estimate_normals: bool = True,
                                identify: IdentifyOptions | None = None,
                                priors: PriorOptions | None = None,
                                referencing: ReferencingOptions | None = None,
                                ) -> tuple[FieldData, FieldResult, list[dict]]:
    """Identify the measured targets of every image and calibrate (module docstring).

    Parameters
    ----------
    session : Session
        A field session with images (:func:`fieldcal.session.loader.load_session`).
    measurements : mapping of str to pyarrow.Table
        The ``measurements`` table of every image that could be measured, keyed by the image's
        name in the session (``images/x.tif``). A missing image is left out and reported.
    options : AdjustmentOptions, optional
        Passed to both adjustments.
    progress : callable, optional
        Called with one line per stage.
    target_normals : (n, 3) or (3,) array_like, optional
        Normals of the targets' planes (NaN rows unknown); they replace the session's
        (targets.csv, ``field.target_normal``). Unknown normals come from a planar field's plane
        or the local planes of a 3-D field's targets (:mod:`fieldcal.field.normals`).
    eccentricity : bool
        Apply the perspective-eccentricity correction to disc centres when it can be computed
        (``field.target_diameter_mm`` in the session).
    estimate_normals : bool
        Estimate the unknown normals of a 3-D field (:mod:`fieldcal.field.normals`); False
        leaves them unknown (their discs uncorrected, with the eccentricity bound in their sigmas).
    identify, priors : IdentifyOptions, PriorOptions, optional
        Settings of :func:`fieldcal.field.identify.identify_image` (gates, ``min_identified``) and
        of :func:`fieldcal.field.identify_session.identify_remaining`.
    referencing : ReferencingOptions, optional
        Automatic referencing (step 7; off when None): the discs no target names are matched
        across the adjusted images (:func:`fieldcal.field.referencing.reference_discs`), get
        ids of their own (``AR0001``, ...) and join the adjustment as unsurveyed targets.

    Returns
    -------
    data, result : FieldData, FieldResult
        The final adjustment and its observations (eccentricity removed where applied).
    report : list of dict
        One entry per image of the session (module docstring).

    Raises
    ------
    InputError
        Not a field session, no nominal focal length, unreadable targets.csv / marks.csv.
    GeometryError
        Fewer than 3 images could be identified from their seeds or, with a thin survey, resected
        from their marks (the message lists why), or the adjustment cannot calibrate.
    """
    if session.method != "field":
        raise InputError("not a field-method session", session.manifest_where)
    run = _Run(session, measurements, options or AdjustmentOptions(), progress or (lambda _line: None),
               identify or IdentifyOptions(), priors or PriorOptions())
    if is_thin(run.targets) and (run.marks or (run.coded and np.any(run.all_targets.codes >= 0))):
        return _thin(run, referencing, coded=not run.marks)
    first, keep1, marker1, res1 = _first_pass(run)
    state = _Oriented(run, res1, keep1, first)
    starts = {i: "seeds" for i in keep1}
    prior_reasons = _with_priors(run, state, starts)
    prior_reasons.update(state.rejected)
    # 5: every image again with the calibrated camera, from the adjusted poses
    second = _identify_all(run, state.targets, state.sigma_m, state.camera, state.poses, fixed_pose=True,
                           only={i for i in range(len(run.names)) if i not in state.rejected})
    keep2 = _usable(second, run.names, measurements)
    _check_enough(keep2, run.names, second, measurements, "calibrated camera")
    uv_override, bound_px, ecc_max, ecc_summary, normals = _eccentricity(
        run, second, keep2, state.camera, state.targets, state.sigma_m, target_normals, eccentricity,
        estimate_normals)
    # 6: the final adjustment
    factor = _marker_factor(res1, marker1)
    if factor > 1.0:
        run.say(f"markers' centres scatter {factor:.2f} x more than their a-priori sigma says, relative "
                "to the discs: their sigmas are scaled by that")

    def build(keep):
        return _build(run, keep, second, uv_override=uv_override, bound_px=bound_px, marker_factor=factor,
                      single_view=not run.options.targets_adjusted)

    data, result, keep2 = _final_adjustment(run, state, build, keep2, state.probation, second)
    data, result = _coded_unsurveyed(run, data, result, keep2, factor)
    data, result = _referenced(run, data, result, second, keep2, referencing)
    result = _with_eccentricity_bound(run, data, result, ecc_summary)
    data.meta["marker_sigma_factor"] = factor
    data.meta["identifications"] = {run.names[i]: second[i] for i in second}
    if ecc_max:
        data.meta["eccentricity_max_px"] = float(max(ecc_max.values()))
    data.meta["eccentricity"] = ecc_summary
    data.meta["target_normals"] = normals
    report = _report(run, data, first, second, keep2, starts, prior_reasons, ecc_max)
    data.meta["identification"] = summary = identification_summary(report)
    run.say("images used: " + f"{summary['used']} of {summary['images']}" +
            "".join(f"; left out, {k}: {v}" for k, v in summary["left_out"].items()) +
            " (started from: " + ", ".join(f"{k} {v}" for k, v in summary["started_from"].items()) + ")")
    return data, result, report


def _thin(run: _Run, referencing: ReferencingOptions | None, coded: bool = False):
    """0: a survey too thin to identify targets by projection (:func:`fieldcal.field.thin_start.is_thin`):
    the images are resected from their marked control points (or, without marks, oriented from
    their coded targets: ``coded``) and the network grown by automatic referencing
    (:func:`fieldcal.field.thin_start.start_from_marks`, :func:`~fieldcal.field.thin_start.start_from_codes`);
    scale_bars.csv joins."""
    sess = run.session
    bars = None if sess.scale_bars_path is None else (lambda targets: scale_bars_among(sess, targets))
    common = {"referencing": referencing, "scale_bars": bars, "say": run.say, "progress": run.progress}
    if coded:
        st = start_from_codes(sess, run.measurements, run.all_targets, run.options, run.working_options,
                              run.nominal, **common)
    else:
        st = start_from_marks(sess, run.measurements, run.targets, run.marks, run.options, run.working_options,
                              run.nominal, **common)
    data = st.data
    data.meta.update(referenced_targets=st.n_tracks, marker_sigma_factor=1.0, identifications={},
                     eccentricity=st.eccentricity, target_normals=None)
    data.meta["identification"] = summary = identification_summary(st.report)
    start = "their coded targets" if coded else "the marked control points"
    run.say(f"images used: {summary['used']} of {summary['images']} (started from {start})")
    return data, st.result, st.report


def _with_eccentricity_bound(run, data: FieldData, result: FieldResult, ecc_summary: dict) -> FieldResult:
    """``result`` with what the uncorrected discs' eccentricity can do added in quadrature to
    the sigmas (:mod:`fieldcal.field.sensitivity`; recorded in ``ecc_summary["bias_bound"]``)."""
    bound = data.meta.get("eccentricity_bound_px")
    if bound is None or len(bound) != len(result.data.obs) or not np.any(bound > 0):
        return result
    result, moves = with_bias_bounds(result, eccentricity_bias_bounds(
        result, bound > 0, run.session.target_diameter_mm / 2000.0))
    ecc_summary["bias_bound"] = moves
    run.say("the uncorrected discs can move f by up to "
            f"{1000 * moves.get('f_mm', float('nan')):.3g} um: added in quadrature to its sigma "
            f"(now {1000 * result.sigma['f_mm']:.3g} um)")
    return result


REASON_MISFIT = "does not fit the other images"
WORKING_SIGMA_TOL = 0.01
"""The working adjustments (they orient images for the identification) stop when a step is
below this many sigmas: a hundredth of the noise, far below the identification's gates."""
WORKING_TAU = 1e-9
"""LM's initial damping of the working adjustments. With adjusted targets the datum is held
only by the survey (mm) against the images (microns): in scaled variables the normal
matrix's weakest directions are ~1e-6 of its diagonal, and the default damping (1e-6) slows
LM along them for several iterations; the final adjustment keeps the session's ``tau``."""


def _misfits(result: FieldResult, keep, probation) -> dict:
    """Images on probation (identified from pose priors) that do not fit the adjustment: most of
    their points rejected, or their normalised residuals three times the other images'."""
    if not probation:
        return {}
    img, used = result.data.obs.image, result.obs_used
    z2 = np.sum((result.residual_px / result.data.obs.sigma_px[:, None]) ** 2, axis=1)
    n_img = len(keep)
    n_all = np.bincount(img, minlength=n_img)
    n_used = np.bincount(img[used], minlength=n_img)
    rms = np.sqrt(np.bincount(img[used], weights=z2[used], minlength=n_img) / np.maximum(n_used, 1))
    ref = [n for n, i in enumerate(keep) if i not in probation and n_used[n]]
    m0 = float(np.median(rms[ref] if ref else rms[n_used > 0]))
    out = {}
    for n, i in enumerate(keep):
        if i in probation and (n_used[n] < 0.5 * n_all[n] or rms[n] > 3.0 * m0):
            out[i] = (f"{REASON_MISFIT}: {n_all[n] - n_used[n]} of its {n_all[n]} points rejected, normalised "
                      f"residuals {rms[n] / max(m0, 1e-12):.1f} x the other images' (a wrong identification?)")
    return out


def _admit(fixed, candidates, attempt):
    """Admit the ``candidates`` (images identified from pose priors) by adjustments they do not spoil.

    ``attempt(images, probation)`` adjusts ``fixed`` plus some candidates and returns
    ``(misfits, None)`` (a dict of image -> reason: all of ``probation`` when the adjustment
    fails, else :func:`_misfits`) or ``({}, outcome)``. All candidates are tried at once; a group
    that fails is split in halves until the images that spoil it are found (group testing: one
    adjustment when all fit, a few per bad image otherwise). Returns the last successful
    outcome (None if there was none) and the rejected images with their reasons.
    """
    groups, admitted, rejected, outcome = ([sorted(candidates)] if candidates else []), [], {}, None
    while groups:
        group = groups.pop(0)
        out, got = attempt(list(fixed) + admitted + group, set(group))
        if got is not None:
            outcome, admitted = got, admitted + group
        elif len(group) > 1 and set(out) >= set(group):      # failed as a whole: which ones?
            groups[:0] = [group[: len(group) // 2], group[len(group) // 2:]]
        else:
            rejected.update(out)
            rest = [i for i in group if i not in out]
            if rest:
                groups.insert(0, rest)
    return outcome, rejected


def _referenced(run, data: FieldData, result: FieldResult, second, keep, options: ReferencingOptions | None):
    """7: automatic referencing (:mod:`fieldcal.field.referencing`). The usable discs of the
    images ``keep`` (``data``'s images, in order) that the identification ``second`` left
    unnamed are matched across the adjusted images; each track becomes an unsurveyed target
    (``AR0001``, ...; ``data.meta["referenced_targets"]``) and the adjustment is repeated from
    this one (its camera, poses and targets; the tracks at their intersections). ``options``
    None: off (``data``, ``result`` unchanged)."""
    if options is None:
        return data, result
    uv, sig = [], []
    for i in keep:
        table = run.measurements[run.names[i]]
        kind, _, uv_all, usable = measured_points(table)
        rows = np.flatnonzero((second[i].target < 0) & (kind == "disc") & usable)
        uv.append(uv_all[rows])
        sig.append(_sigma(table, rows, run.session.default_sigma_px))
    tracks = reference_discs(result.camera, result.R_world_to_camera, result.center_m, uv, options)
    run.say(f"automatic referencing: {len(tracks)} unsurveyed target(s) found in {len(keep)} images "
            f"({len(tracks.image)} points)")
    data.meta["referenced_targets"] = len(tracks)
    if not len(tracks):
        return data, result
    ids = track_ids(len(tracks), run.all_targets.ids.tolist() + data.targets.ids.tolist())
    first = len(data.targets)
    new = FieldObservations(tracks.image, first + tracks.track,
                            np.stack([uv[m][p] for m, p in zip(tracks.image, tracks.point, strict=True)]),
                            np.array([sig[m][p] for m, p in zip(tracks.image, tracks.point, strict=True)]))
    data = replace(data, targets=data.targets.with_unsurveyed(ids))
    return _adjust_with(run, data, result, new, tracks.X_m, "the automatic referencing")


def _adjust_with(run, data: FieldData, result: FieldResult, new: FieldObservations, X_new_m, what: str):
    """``data`` (its targets already extended by the new, unsurveyed ones) with the observations
    ``new`` appended, adjusted again from ``result`` (warm: its camera, poses and targets; the
    new targets at ``X_new_m``, NaN: not placed)."""
    old = data.obs
    obs = FieldObservations(np.concatenate([old.image, new.image]), np.concatenate([old.target, new.target]),
                            np.concatenate([old.uv_px, new.uv_px]), np.concatenate([old.sigma_px, new.sigma_px]))
    data = replace(data, obs=obs, scale_bars=scale_bars_among(run.session, data.targets))
    bound = data.meta.get("eccentricity_bound_px")
    if bound is not None and len(bound) == len(old):        # the new points: markers and discs with no bound
        data.meta["eccentricity_bound_px"] = np.concatenate([bound, np.zeros(len(new))])
    init = InitialValues(np.asarray(result.params, float).copy(), result.R_world_to_camera, result.center_m,
                         np.concatenate([~result.obs_used, np.zeros(len(new), bool)]),
                         np.full(len(data.images), np.nan), f"the adjustment before {what} (warm start)",
                         lm_tau=result.lsq.mu, targets_m=np.vstack([result.targets_m, X_new_m]))
    result = adjust_field(data, run.options, progress=run.progress, initial=init)
    return data, result


def _coded_unsurveyed(run, data: FieldData, result: FieldResult, keep, marker_factor: float):
    """6b: the coded targets targets.csv lists without coordinates (CONTRACT section 3). Their
    markers in the adjusted images ``keep`` (``data``'s images, in order) are identified by
    their code, as a surveyed coded target's are; each such target is intersected from the
    adjusted poses (:func:`fieldcal.field.intersection.intersect_targets`) and joins the
    adjustment as an unsurveyed target (its own id), which is repeated from ``result`` (warm).
    Only targets seen in two or more of the images join (one view neither places a target nor
    checks its point). ``data.meta["coded_unsurveyed_targets"]``: how many were intersected
    (joined with coordinates)."""
    full = run.all_targets
    uns = np.flatnonzero(~full.surveyed & (full.codes >= 0))
    if not len(uns):
        return data, result
    slot = {int(full.codes[j]): n for n, j in enumerate(uns)}
    first = len(data.targets)
    img, tgt, uv, sig = [], [], [], []
    for n, i in enumerate(keep):
        table = run.measurements[run.names[i]]
        kind, code, uv_all, usable = measured_points(table)
        rows = np.flatnonzero((kind == "aruco") & usable & np.isin(code, list(slot)))
        rows = rows[np.unique(code[rows], return_index=True)[1]]     # one point per code and image
        img.append(np.full(len(rows), n))
        tgt.append(first + np.array([slot[int(c)] for c in code[rows]], np.int64))
        uv.append(uv_all[rows])
        sig.append(_sigma(table, rows, run.session.default_sigma_px) * marker_factor)
    new = FieldObservations(np.concatenate(img), np.concatenate(tgt).astype(np.int64), np.concatenate(uv),
                            np.concatenate(sig))
    views = np.bincount(new.target - first, minlength=len(uns))
    new = new.take(views[new.target - first] >= 2)               # one view: no intersection, no redundancy
    data.meta["coded_unsurveyed_targets"] = 0
    if not len(new):
        run.say(f"none of the {len(uns)} unsurveyed coded target(s) of targets.csv is seen in two adjusted images")
        return data, result
    ids, codes = full.ids[uns], full.codes[uns]
    data = replace(data, targets=data.targets.with_unsurveyed(ids, codes))
    X, _ = intersect_targets(replace(data, obs=new), result.params, result.R_world_to_camera, result.center_m,
                             np.ones(len(new), bool))
    placed = np.isfinite(X[first:]).all(axis=1)        # the others: their points left out (adjustment.UNPLACED)
    data.meta["coded_unsurveyed_targets"] = int(placed.sum())
    run.say(f"{int(placed.sum())} of {len(uns)} unsurveyed coded target(s) of targets.csv intersected from the "
            f"adjusted images ({int(np.sum(placed[new.target - first]))} points): they join the adjustment")
    return _adjust_with(run, data, result, new, X[first:], "the unsurveyed coded targets")


def _final_adjustment(run, state, build, keep, probation, second):
    """6: the adjustment, the images identified from pose priors and not adjusted yet admitted
    as :func:`_admit` says (an image that spoils it is left out)."""
    fixed = [i for i in keep if i not in probation]

    def attempt(images, group):
        data, _, kept, dropped = build(sorted(images))
        for i, why in dropped.items():
            second[i].reason = why
        _check_enough(kept, run.names, second, run.measurements, "calibrated camera")
        try:
            result = adjust_field(data, run.options, progress=run.progress, initial=state.warm_start(data, kept),
                                  initial_targets_m=state.res.targets_m)
        except GeometryError as err:
            if not group:
                raise
            return {i: f"{REASON_MISFIT}: the adjustment with it failed ({one_line(err)})" for i in group}, None
        out = _misfits(result, kept, group)
        return (out, None) if out else ({}, (data, result, kept))

    outcome, rejected = _admit(fixed, [i for i in keep if i in probation], attempt)
    for i, why in rejected.items():
        second[i].reason = why
        run.say(f"{run.names[i]}: left out, {why}")
    if outcome is None:
        outcome = attempt(fixed, set())[1]
    return outcome


class _Run:
    """What every stage of :func:`calibrate_from_measurements` shares."""

    def __init__(self, session, measurements, options, say, identify, priors):
        self.session = session
        self.measurements = measurements
        self.options = options
        # the adjustments that only orient images for the identification hold what the
        # data cannot determine (min_t 1) and skip the variance components: a camera that
        # predicts well from a few images matters there, its honest sigma only at the end.
        # They stop within WORKING_SIGMA_TOL sigmas of their optimum (far inside the gates)
        # and start LM with little damping (WORKING_TAU: why)
        self.working_options = replace(options, min_t=max(options.min_t, 1.0), variance_components=False,
                                       sigma_tol=max(options.sigma_tol, WORKING_SIGMA_TOL),
                                       tau=min(options.tau, WORKING_TAU))
        self.say = say
        self.progress = None if say is None else say
        self.identify = identify
        self.priors = priors
        self.nominal = nominal_camera(session)
        self.targets, self.all_targets, keep = _surveyed_only(session.targets(), say)
        marks_targets = self.all_targets
        self.surveyed = keep
        self.images = list(session.images)
        self.names = [im.file for im in self.images]
        self.stations = [im.station for im in self.images]
        self.marks = _marks_of(session.marks(marks_targets), keep) if session.marks_path is not None else {}
        self.coded = session.coded is not None
        size = (session.coded or {}).get("marker_size_mm")
        self.marker_size_m = float(size) / 1000.0 if size else None


def _surveyed_only(targets, say):
    """From photographs, targets are identified by their surveyed coordinates: unsurveyed rows of
    targets.csv are left out of the identification, with a line saying so (coded ones join
    after the final adjustment by their code, step 6b; plain ones' discs through automatic
    referencing, step 7, under ids of its own).
    Returns ``(surveyed targets, all targets, mask)``."""
    keep = targets.surveyed
    if keep.all():
        return targets, targets, keep
    if say is not None:
        coded = int(np.sum(~keep & (targets.codes >= 0)))
        if keep.sum() < MIN_POINTS_PER_IMAGE:
            say(f"{int((~keep).sum())} unsurveyed target(s) of targets.csv and {int(keep.sum())} surveyed: too few to "
                "identify targets by projection; the images are oriented from marks.csv's control points or the "
                f"{coded} coded target(s), the plain ones join through automatic referencing")
        else:
            say(f"{int((~keep).sum())} unsurveyed target(s) of targets.csv: the images are oriented from the "
                f"surveyed ones; the {coded} coded one(s) join by their code, the plain ones through automatic "
                "referencing (when on: fieldcal run turns it on for them)")
    normals = None if targets.normals is None else targets.normals[keep]
    sub = replace(targets, ids=targets.ids[keep], xyz_m=targets.xyz_m[keep], sigma_mm=targets.sigma_mm[keep],
                  codes=targets.codes[keep], normals=normals)
    return sub, targets, keep


def _marks_of(marks: dict, keep) -> dict:
    """marks.csv's ``{image: (target indices, uv)}`` over the surveyed targets ``keep`` only."""
    new = np.cumsum(keep) - 1
    out = {}
    for i, (t, uv) in marks.items():
        m = keep[t]
        out[i] = (new[t[m]], uv[m])
    return out


def _first_pass(run: _Run):
    """1-2: the images with seeds, nominal camera; the first adjustment."""
    first = _identify_all(run, run.targets, run.targets.sigma_mm / 1000.0, run.nominal, {})
    keep1 = _usable(first, run.names, run.measurements)
    _check_enough(keep1, run.names, first, run.measurements, "nominal camera")
    data1, marker1, keep1, dropped1 = _build(run, keep1, first, single_view=not run.options.targets_adjusted)
    for i, why in dropped1.items():
        first[i].reason = why
    _check_enough(keep1, run.names, first, run.measurements, "nominal camera")
    run.say(f"identification with the nominal camera (f {run.nominal.f_mm:g} mm): {len(keep1)} of "
            f"{len(run.names)} images, {len(data1.obs)} points")
    res1 = adjust_field(data1, run.working_options, progress=run.progress)
    run.say(f"first adjustment: f {res1.params[0]:.5f} mm, rmse {res1.stats()['rmse_px']:.3g} px (it starts the "
            "identification of the other images; the final adjustment chooses the parameters again)")
    return first, keep1, marker1, res1


class _Oriented:
    """The latest adjustment during the identification: its camera, adjusted targets, their
    sigmas, and the poses of every image oriented so far (adjusted or identified)."""

    def __init__(self, run: _Run, res: FieldResult, keep, idents):
        self.run = run
        self.idents = dict(idents)
        self.poses: dict = {}
        self.rejected: dict = {}            # images left out by the adjustment's check, with the reason
        self.probation: set = set()         # images identified from priors and not admitted yet
        self.update(res, keep)

    def update(self, res: FieldResult, keep) -> None:
        self.res, self.keep = res, list(keep)
        self.camera = res.camera
        self.targets = replace(self.run.targets, xyz_m=np.asarray(res.targets_m, float))
        prior = self.run.targets.sigma_mm / 1000.0
        if res.sigma_targets_m is not None:     # adjusted targets: their a-posteriori sigma
            s = np.sqrt(np.mean(np.asarray(res.sigma_targets_m, float) ** 2, axis=1))
            self.sigma_m = np.where(np.isfinite(s), s, prior)
        else:
            self.sigma_m = prior
        self.poses.update({i: (res.R_world_to_camera[n], res.center_m[n]) for n, i in enumerate(self.keep)})

    def warm_start(self, data: FieldData, keep) -> InitialValues:
        """The latest adjustment as the start of one of ``data`` (images ``keep``): its interior,
        its poses (identified ones for images it did not have), and as suspects (readmitted
        when they fit) the points it never readmitted and its gross errors; the snooping tests
        every other point again, as after a cold start."""
        R = np.stack([self.poses[i][0] for i in keep])
        C = np.stack([self.poses[i][1] for i in keep])
        old, used = self.res.data, self.res.obs_used
        # suspects as a cold start would have them: the initialisers' suspects that were never
        # readmitted, and the gross errors (its gross-error rule); the others are tested afresh
        z = np.hypot(*(self.res.residual_px / old.obs.sigma_px[:, None]).T)
        s = max(float(robust_sigma(z[used] / np.sqrt(2.0))), 1e-12)
        gross = ~used & ~(z <= self.run.options.robust_k * s * np.sqrt(2.0))
        if self.res.initial is not None:
            gross |= ~used & np.asarray(self.res.initial.outliers, bool)
        rejected = {(old.images[m].file, int(t)) for m, t in
                    zip(old.obs.image[gross], old.obs.target[gross], strict=True)}
        outliers = np.array([(data.images[m].file, int(t)) in rejected
                             for m, t in zip(data.obs.image, data.obs.target, strict=True)], bool)
        return InitialValues(np.asarray(self.res.params, float).copy(), R, C, outliers,
                             np.full(len(keep), np.nan), "the previous adjustment (warm start)",
                             lm_tau=self.res.lsq.mu)

    def readjust(self, found) -> bool:
        """Adjust again with the images ``found`` added (warm start), each admitted only by an
        adjustment it does not spoil (:func:`_admit`; the others are ``rejected``). False when
        none is admitted."""
        run = self.run
        self.idents.update(found)

        def attempt(images, group):
            data, _, keep, _ = _build(run, sorted(images), self.idents, single_view=not run.options.targets_adjusted)
            try:
                res = adjust_field(data, run.working_options, initial=self.warm_start(data, keep),
                                   initial_targets_m=self.res.targets_m)
            except GeometryError as err:
                return {i: f"{REASON_MISFIT}: the adjustment with it failed ({one_line(err)})" for i in group}, None
            out = _misfits(res, keep, group)
            return (out, None) if out else ({}, (res, keep))

        outcome, rejected = _admit(self.keep, sorted(found), attempt)
        for i, why in rejected.items():
            self.rejected[i] = why
            self.poses.pop(i, None)
            run.say(f"{run.names[i]}: left out, {why}")
        if outcome is None:
            return False
        self.update(*outcome)
        run.say(f"adjustment with {len(self.keep)} images: f {self.res.params[0]:.5f} mm, "
                f"rmse {self.res.stats()['rmse_px']:.3g} px")
        return True


MAX_PRIOR_ROUNDS = 4
"""Rounds of identification with pose priors, each followed by an adjustment when images remain."""


def _with_priors(run: _Run, state: _Oriented, starts) -> dict:
    """3: the calibrated camera and the oriented images start the images left out so far; while
    images remain and new ones were found, the adjustment is repeated with them (a better
    camera) and the rest tried again. Returns the reasons of the images still left out."""
    reasons: dict = {}
    hints: dict = {}
    for _ in range(MAX_PRIOR_ROUNDS):
        pending = [i for i, name in enumerate(run.names) if name in run.measurements and i not in state.poses]
        if not pending:
            break
        oriented = dict(state.poses)
        reference = {i: state.idents[i].target for i in oriented if i in state.idents}
        found, reasons = identify_remaining(state.camera, state.targets, run.measurements, run.names, run.stations,
                                            oriented, marks=run.marks, target_sigma_m=state.sigma_m,
                                            codes_are_markers=run.coded, options=run.identify, prior=run.priors,
                                            reference=reference, marker_size_m=run.marker_size_m, hints=hints)
        if not found:
            break
        for i, (ident, start) in found.items():
            starts[i] = start
            state.poses[i] = (ident.R_world_to_camera, ident.center_m)
            state.probation.add(i)
        run.say(f"identification with pose priors (calibrated camera): {len(found)} more image(s) ("
                + ", ".join(f"{k} {v}" for k, v in _count(s for _, s in found.values()).items()) + ")")
        # the images found are admitted by an adjustment they do not spoil: this one, when images
        # remain to be tried with its better camera, else the final adjustment
        if len(found) == len(pending):
            break
        state.probation -= set(found)
        if not state.readjust({i: ident for i, (ident, _) in found.items()}):
            break
    return reasons


def _towards(run: _Run, second, keep2, n_targets):
    """Per target, the mean centre of the images that see it (NaN when none) [m]."""
    acc, cnt = np.zeros((n_targets, 3)), np.zeros(n_targets)
    for i in keep2:
        t = second[i].target[second[i].target >= 0]
        np.add.at(acc, t, np.asarray(second[i].center_m, float))
        np.add.at(cnt, t, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return acc / cnt[:, None]


def _shape_views(run: _Run, second, keep2):
    """Per image: its pose, the targets identified as discs and their ellipses' shape vectors
    (:func:`fieldcal.field.normals.choose_by_shapes`)."""
    views = []
    for i in keep2:
        table = run.measurements[run.names[i]]
        kind = np.asarray(table.column("kind").to_numpy(zero_copy_only=False))
        rows = np.flatnonzero((second[i].target >= 0) & (kind == "disc"))
        cols = [np.asarray(table.column(c).fill_null(np.nan).to_numpy(zero_copy_only=False), float)[rows]
                if c in table.column_names else np.full(len(rows), np.nan)
                for c in ("major_px", "minor_px", "angle_deg")]
        views.append((second[i].R_world_to_camera, second[i].center_m, second[i].target[rows],
                      measured_shape_vectors(*cols)))
    return views


LEAVE_OUT_FRACTION = 0.05
"""Disc centres whose normal is not determined are left out of the final adjustment when they
are at most this fraction of the disc centres; otherwise they stay, and the largest bias they
can cause widens the parameters' sigmas (:mod:`fieldcal.field.sensitivity`)."""


def _eccentricity(run: _Run, second, keep2, cam, adjusted, sigma_m, target_normals, eccentricity, estimate=True):
    """4: perspective eccentricity of the discs, with the calibrated camera and the new poses.

    The normals are resolved (:func:`fieldcal.field.normals.resolve_normals`: given, planar
    fit, or estimated from the adjusted targets' local planes). A disc whose normal is not
    determined is left out when such discs are few (:data:`LEAVE_OUT_FRACTION`), else it keeps
    its point and after the final adjustment the largest move of every parameter its
    eccentricity can cause is added in quadrature to its variance
    (:mod:`fieldcal.field.sensitivity`). Returns
    ``(uv_override, bound_px, ecc_max, summary, normals)`` (the
    :class:`~fieldcal.field.normals.TargetNormals`, None when not applied).
    """
    diameter_mm = run.session.target_diameter_mm
    ecc_max: dict[int, float] = {}
    if not (eccentricity and diameter_mm):
        why = "not asked" if not eccentricity else "no field.target_diameter_mm in the session"
        return None, None, ecc_max, {"max_px": None, "normals": "none", "applied": False, "reason": why}, None
    tol = plane_tolerance_m(sigma_m)
    if target_normals is not None:          # given for every row of targets.csv: the surveyed ones
        N = np.asarray(target_normals, float)
        if N.ndim == 2 and len(N) == len(run.surveyed) != len(run.targets):
            target_normals = N[run.surveyed]
    tn = resolve_normals(run.targets, target_normals, xyz_m=adjusted.xyz_m, tol_m=tol, estimate=estimate,
                         towards_m=_towards(run, second, keep2, len(run.targets)),
                         shapes=(cam, _shape_views(run, second, keep2), diameter_mm / 2000.0))
    radius_m = diameter_mm / 2000.0
    uv_override, bound_px, all_e, bounds, seen = {}, {}, [], [], np.zeros(len(run.targets), bool)
    for i in keep2:
        kind, _, uv_all, _ = measured_points(run.measurements[run.names[i]])
        rows = np.flatnonzero((second[i].target >= 0) & (kind == "disc"))
        t = second[i].target[rows]
        seen[t] = True
        R, C = second[i].R_world_to_camera, second[i].center_m
        known = tn.known[t]
        e = np.zeros((len(rows), 2))
        if known.any():
            e[known] = correction_px(cam, R, C, adjusted.xyz_m[t[known]], tn.normals[t[known]], radius_m)
        e = np.where(np.isfinite(e), e, 0.0)
        uv = uv_all.copy()
        uv[rows] = uv_all[rows] - e
        uv_override[i] = uv
        extra = np.zeros(len(uv_all))
        if (~known).any():
            b = eccentricity_bound_px(cam, R, C, adjusted.xyz_m[t[~known]], radius_m)
            extra[rows[~known]] = b
            bounds.append(b)
        bound_px[i] = extra
        norm = np.hypot(e[:, 0], e[:, 1])
        ecc_max[i] = float(norm.max()) if len(norm) else 0.0
        all_e.append(norm)
    all_e = np.concatenate(all_e) if all_e else np.zeros(0)
    summary = {"max_px": float(all_e.max()) if len(all_e) else 0.0, **normals_summary(tn.source, seen),
               "applied": bool(len(all_e) and all_e.max() > 0)}
    if bounds:
        b = np.concatenate(bounds)
        summary["uncorrected_bound_max_px"] = float(b.max())
        if len(b) <= LEAVE_OUT_FRACTION * len(all_e):
            for i in bound_px:
                bound_px[i][bound_px[i] > 0] = np.inf
            summary["n_left_out"] = len(b)
            run.say(f"{len(b)} disc centres of targets whose normal is not determined (eccentricity up to "
                    f"{b.max():.4f} px): left out of the final adjustment")
        else:
            run.say(f"{len(b)} disc centres of targets whose normal is not determined: not corrected (their "
                    f"eccentricity up to {b.max():.4f} px bounds the parameters' bias)")
    if len(all_e):
        run.say(f"perspective eccentricity removed from {int(np.sum(all_e > 0))} disc centres (normals: "
                f"{summary['normals']}): median {np.median(all_e):.4f} px, max {all_e.max():.4f} px")
    return uv_override, bound_px, ecc_max, summary, tn


def _report(run: _Run, data, first, second, keep2, starts, prior_reasons, ecc_max) -> list[dict]:
    """One entry per image of the session (module docstring)."""
    used = np.bincount(data.obs.image, minlength=len(keep2))
    n_used = {i: int(used[n]) for n, i in enumerate(keep2)}
    report = []
    for i, name in enumerate(run.names):
        table = run.measurements.get(name)
        entry = {"image": name, "n_measured": 0 if table is None else int(table.num_rows),
                 "n_coded": 0, "n_identified": 0, "n_identified_first": 0,
                 "n_marks": int(len(run.marks[i][0])) if i in run.marks else 0,
                 "n_used": n_used.get(i, 0), "wrong_marks": [], "wrong_codes": [], "rms_px": None,
                 "eccentricity_max_px": None, "start": None}
        if table is None:
            entry.update(status="left out", reason="not measured (the image could not be read or measured)")
            report.append(entry)
            continue
        a, b = first.get(i), second.get(i)
        entry["n_identified_first"] = int(a.n_identified) if a is not None and a.ok else 0
        ident = b if b is not None else a
        entry.update(n_coded=int(ident.n_coded), n_identified=int(ident.n_identified) if i in keep2 else 0,
                     wrong_marks=[str(run.targets.ids[t]) for t in ident.wrong_marks],
                     wrong_codes=[int(c) for c in ident.wrong_codes],
                     rms_px=None if not np.isfinite(ident.rms_px) else float(ident.rms_px),
                     eccentricity_max_px=ecc_max.get(i))
        if i in keep2:
            notes = []
            if entry["wrong_marks"]:
                notes.append(f"mark(s) {', '.join(entry['wrong_marks'])} disagree with the identification "
                             "(not used)")
            if entry["wrong_codes"]:
                notes.append(f"marker code(s) {', '.join(map(str, entry['wrong_codes']))} disagree with "
                             "the identification (not used)")
            entry.update(status="ok", reason="; ".join(notes), start=starts.get(i))
        else:
            reason = ident.reason if b is not None and i in starts else prior_reasons.get(i) or ident.reason
            entry.update(status="left out", reason=reason)
        report.append(entry)
    return report


def _count(items) -> dict:
    out: dict = {}
    for x in items:
        out[x] = out.get(x, 0) + 1
    return out


def reason_category(reason: str) -> str:
    """A short category of a left-out image's reason (for the run's summary)."""
    for prefix, cat in (("not measured", "not measured"), (REASON_AMBIGUOUS, "ambiguous"),
                        (REASON_NO_START, "no pose fits"), ("only", "too few targets"), (REASON_MISFIT, "does not fit"),
                        ("no coded targets", "no seeds"), ("the identified points do not fit", "does not fit")):
        if reason.startswith(prefix):
            return cat
    return "other"


def identification_summary(report: list[dict]) -> dict:
    """Images used, left out by reason category, and how the used ones were started."""
    used = [r for r in report if r["status"] == "ok"]
    return {"images": len(report), "used": len(used),
            "left_out": _count(reason_category(r["reason"]) for r in report if r["status"] != "ok"),
            "started_from": _count(r.get("start") or "seeds" for r in used)}
