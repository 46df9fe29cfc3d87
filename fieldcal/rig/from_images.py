"""A rig session from its images: every head measured and identified exactly as one camera is,
then the heads whose images showed too little started from the rig's other heads.

1. **Measure** every image with the single camera's measuring step
   (:func:`fieldcal.measure.targets.measure_image`, the head's sensor, the session's polarity
   and coded targets): one ``measurements`` table per image.
2. **Each head alone** (:func:`head_session`: the head as a single-camera session of its own
   images, sensor and nominal lens, the session's targets): identified and calibrated by
   :func:`fieldcal.field.from_images.calibrate_from_measurements`, the single camera's whole
   procedure (coded targets as seeds, pose priors, second identification, final adjustment).
   An image it could not identify (no code in view, too few targets) is left out for now.
3. **The rig** (:func:`fieldcal.rig.adjust_rig`) from every head's identified points.
4. **Started from the rig's other heads**: an image left out in step 2 whose exposure the rig
   oriented gets the pose the rig predicts for it (the rig pose of its exposure composed with
   its head's relative orientation, :func:`fieldcal.rig.poses.head_pose`) and its head's
   calibrated camera, and is identified from there with the pose held
   (:func:`fieldcal.field.identify.identify_images`, ``fixed_pose``: the gates are those of
   the single camera's second identification), their discs' perspective eccentricity removed
   as the single camera's step 4 does (when the targets' normals are known). Images with at least
   :data:`fieldcal.field.adjustment.MIN_POINTS_PER_IMAGE` identified points join their head,
   and the rig is adjusted again (step 3) with them.

A head that cannot be calibrated alone at all (fewer than three images identified) stops the
run with a one-line reason: its relative orientation would have no initial value.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

import numpy as np
import pyarrow as pa

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.adjustment import MIN_POINTS_PER_IMAGE, AdjustmentOptions
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.field.identify import identify_images, measured_points
from fieldcal.model.camera import Camera
from fieldcal.rig.data import RigData
from fieldcal.rig.poses import head_pose
from fieldcal.rig.session import RigSession
from fieldcal.session.data import FieldData, FieldObservations
from fieldcal.session.loader import Session

__all__ = ["head_session", "measure_rig_image", "rig_data_from_measurements", "REASON_FROM_RIG"]

REASON_FROM_RIG = "started from the rig's other heads"
"""How an image identified in step 4 (module docstring) was started."""


def head_session(sess: RigSession, h: int) -> Session:
    """Head ``h`` of a rig session as a single camera's session: its images, sensor and nominal
    lens, the session's targets, polarity and coded targets."""
    head = sess.heads[h]
    idx = np.flatnonzero(sess.image_head == h)
    return Session(folder=sess.folder, manifest=sess.manifest, method="field", camera_id=head.camera_id,
                   session_id=sess.session_id, acquired=sess.acquired, sensor=head.sensor,
                   nominal_focal_mm=head.nominal_focal_mm, default_sigma_px=sess.default_sigma_px,
                   estimate=sess.estimate, images=[sess.images[i] for i in idx], targets_path=sess.targets_path,
                   target_diameter_mm=sess.target_diameter_mm, target_polarity=sess.target_polarity,
                   coded=sess.coded)


def measure_rig_image(sess: RigSession, name: str, source=None) -> pa.Table:
    """The ``measurements`` table of one image of a rig session (its head's sensor); ``source``
    the file's bytes already read, else the file in the session folder."""
    from fieldcal.measure.targets import measure_image
    from fieldcal.session.loader import safe_path

    k = [im.file for im in sess.images].index(name)
    sensor = sess.heads[int(sess.image_head[k])].sensor
    path = safe_path(sess.folder, name, "image") if source is None else source
    return measure_image(path, polarity=sess.target_polarity, sensor=sensor, coded=sess.coded, name=name)


def _rig_data(sess: RigSession, heads: list[FieldData]) -> RigData:
    """The rig's data from every head's identified observations (images by name)."""
    exposure = {im.file: int(sess.image_exposure[k]) for k, im in enumerate(sess.images)}
    return RigData(sess.rig_id, list(sess.heads), sess.reference, list(sess.exposures), heads,
                   [np.array([exposure[im.file] for im in d.images], np.int64) for d in heads],
                   meta={"session_id": sess.session_id})


def _alone(sess: RigSession, measurements: Mapping[str, pa.Table], options: AdjustmentOptions, say,
           target_normals=None):
    """Step 2: every head alone; ``(head data, per head {image name: report entry})``."""
    heads, reports = [], []
    for h, head in enumerate(sess.heads):
        hs = head_session(sess, h)
        mine = {im.file: measurements[im.file] for im in hs.images if im.file in measurements}
        try:
            data, _, report = calibrate_from_measurements(hs, mine, options, target_normals=target_normals)
        except GeometryError as e:
            raise GeometryError(f"camera {head.camera_id!r} of the rig cannot be calibrated alone (its relative "
                                f"orientation needs initial values): {e}") from None
        say(f"{head.camera_id}: alone, {len(data.images)} of {len(hs.images)} images identified")
        heads.append(data)
        reports.append({r["image"]: r for r in report})
    return heads, reports


def _without_eccentricity(sess: RigSession, kind, rows, uv, target, camera, R, C, targets, normals):
    """The disc centres ``uv`` (rows ``rows`` of an image's table) moved to the images of the
    discs' centres (:func:`fieldcal.field.eccentricity.correction_px`), as the single camera's step 4."""
    from fieldcal.field.eccentricity import correction_px

    if normals is None or not sess.target_diameter_mm:
        return uv
    disc = kind[rows] == "disc"
    e = correction_px(camera, R, C, targets.xyz_m[target[disc]], normals[target[disc]],
                      sess.target_diameter_mm / 2000.0)
    out = uv.copy()
    out[disc] -= np.where(np.isfinite(e), e, 0.0)
    return out


def _from_rig(sess: RigSession, measurements, heads: list[FieldData], res, say,
              target_normals=None) -> tuple[list[FieldData], dict]:
    """Step 4: the images left out so far, identified from the poses the rig predicts."""
    from fieldcal.field.from_images import target_normals_of

    st, added = res.state, {}
    targets = heads[sess.reference].targets
    normals = target_normals_of(targets, target_normals)
    out = list(heads)
    for h, d in enumerate(heads):
        have = {im.file for im in d.images}
        todo = [k for k in np.flatnonzero(sess.image_head == h)
                if sess.images[k].file not in have and sess.images[k].file in measurements
                and res.exposure_used[sess.image_exposure[k]]]
        if not todo:
            continue
        e = sess.image_exposure[todo]
        R, C = head_pose(st.R_world_to_rig[e], st.C_rig_m[e], st.R_camera_to_rig[h], st.t_camera_in_rig_m[h])
        camera = Camera(d.sensor, st.params[h])
        names = [sess.images[k].file for k in todo]
        idents = identify_images([measurements[n] for n in names], targets, camera,
                                 init_poses=list(zip(R, C, strict=True)), target_sigma_m=targets.sigma_mm / 1000.0,
                                 codes_are_markers=sess.coded is not None, names=names, fixed_pose=True)
        img, tgt, uv, sig, images = [d.obs.image], [d.obs.target], [d.obs.uv_px], [d.obs.sigma_px], list(d.images)
        for k, name, ident, R_k, C_k in zip(todo, names, idents, R, C, strict=True):
            rows = np.flatnonzero(ident.target >= 0)
            if not ident.ok or len(rows) < MIN_POINTS_PER_IMAGE:
                continue
            table = measurements[name]
            kind, _, uv_all, _ = measured_points(table)
            s = (np.asarray(table.column("sigma_px").fill_null(np.nan).to_numpy(zero_copy_only=False), float)[rows]
                 if "sigma_px" in table.column_names else np.full(len(rows), np.nan))
            img.append(np.full(len(rows), len(images)))
            tgt.append(ident.target[rows])
            uv.append(_without_eccentricity(sess, kind, rows, uv_all[rows], ident.target[rows], camera, R_k, C_k,
                                            targets, normals))
            sig.append(np.where(np.isfinite(s) & (s > 0), s, sess.default_sigma_px))
            images.append(sess.images[k])
            added[name] = int(len(rows))
        if len(images) > len(d.images):
            obs = FieldObservations(np.concatenate(img), np.concatenate(tgt), np.concatenate(uv), np.concatenate(sig))
            out[h] = replace(d, images=images, obs=obs)
            say(f"{sess.heads[h].camera_id}: {len(images) - len(d.images)} more image(s) identified from the "
                "rig's other heads")
    return out, added


def rig_data_from_measurements(sess: RigSession, measurements: Mapping[str, pa.Table], *,
                               options: AdjustmentOptions | None = None, rig_options=None,
                               progress: Callable[[str], None] | None = None, target_normals=None):
    """The rig's identified observations from its images' measurements (module docstring).

    Parameters
    ----------
    sess : RigSession
    measurements : mapping of str to pyarrow.Table
        The ``measurements`` table of every image that could be measured, by image name.
    options : AdjustmentOptions, optional
        Of each head's calibration alone (step 2).
    rig_options : fieldcal.rig.RigOptions, optional
        Of the rig adjustment of step 3.
    target_normals : (n, 3) array_like, optional
        As for :func:`~fieldcal.field.from_images.calibrate_from_measurements` (the perspective
        eccentricity correction of each head's disc centres).

    Returns
    -------
    data : RigData
        Every head's identified points (steps 2 and 4).
    report : list of dict
        One entry per image of the session: ``image``, ``camera_id``, ``exposure``, ``status``
        (``"ok"`` or ``"left out"``), ``started_from`` (``"the head alone"`` or
        :data:`REASON_FROM_RIG`), ``n_identified``, ``reason``.

    Raises
    ------
    GeometryError
        A head that cannot be calibrated alone, or a rig the observations cannot determine.
    """
    from fieldcal.rig.adjustment import adjust_rig

    if sess.coded is None:
        raise InputError("a rig session measured from its images needs coded targets (field.coded): marks.csv "
                         "is not supported for rigs", str(sess.folder / "session.json"))
    say = progress or (lambda _line: None)
    heads, reports = _alone(sess, measurements, options or AdjustmentOptions(), say, target_normals)
    res = adjust_rig(_rig_data(sess, heads), rig_options)
    heads, added = _from_rig(sess, measurements, heads, res, say, target_normals)
    report = []
    used = {im.file: h for h, d in enumerate(heads) for im in d.images}
    for k, im in enumerate(sess.images):
        h = int(sess.image_head[k])
        alone = reports[h].get(im.file, {})
        ok = im.file in used
        report.append({"image": im.file, "camera_id": sess.heads[h].camera_id,
                       "exposure": sess.exposures[sess.image_exposure[k]], "status": "ok" if ok else "left out",
                       "started_from": REASON_FROM_RIG if im.file in added else "the head alone" if ok else None,
                       "n_identified": added.get(im.file, alone.get("n_identified")),
                       "reason": None if ok else (alone.get("reason") or "not measured")})
    return _rig_data(sess, heads), report
