"""One session's calibration as plain steps: prepare, measure (per image), solve.

The Prefect flows (``flows/``) fan :func:`measure` out over the images and run
:func:`solve` once; the same functions serve notebooks and tests without Prefect.

- :func:`prepare` validates the session (manifest, tables, paths) and lists the images
  to measure. Nothing is written; bad input raises :class:`InputError` naming the file.
  The session is a local folder or an fsspec URL (:mod:`fieldcal.session.store`): then
  only its small files are fetched, and its images are read where they are measured.
- :func:`measure` turns one image into a measurement table: target centroids and coded
  targets (field method) or the collimator spot (goniometer). A bad image raises
  :class:`ImageError`; the flow reports it and goes on without that image.
- :func:`solve` turns all measurements into an :class:`Outcome`: the calibration
  document (docs/conventions.md section 4, without its version: the lake assigns it), the arrays and
  the residual table the lake stores, and a human summary.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from fieldcal.analysis.correction import correction_arrays
from fieldcal.contract.fingerprint import fingerprint, sha256_file
from fieldcal.errors import GeometryError, InputError
from fieldcal.model.camera import PARAM_NAMES
from fieldcal.session.document import calibration_document
from fieldcal.session.loader import Session, field_data_from_observations, load_session, scale_bars_of
from fieldcal.session.store import is_url, open_store

if TYPE_CHECKING:
    from fieldcal.field.adjustment import FieldResult
    from fieldcal.session.data import FieldData

# The solvers (SciPy, ~1-2 s to import) are imported where they are used, so that
# validating a session (`prepare`) answers in well under a second.

__all__ = ["Settings", "Prepared", "Outcome", "prepare", "measure", "solve", "image_hash",
           "input_fingerprint", "drop_sparse_images"]


@dataclass(frozen=True)
class Settings:
    """What a run may change besides the session (part of the inputs' fingerprint).

    ``check_fraction`` withholds a random, stratified fraction of the surveyed targets as
    check points (seeded by ``check_seed``; :mod:`fieldcal.field.check_points`), besides
    those the session names. ``cross_validate`` recalibrates without each station
    (:mod:`fieldcal.field.cross_validation`; one warm re-adjustment per station) and stores
    how far the correction field moves in ``stats.cross_validation``.
    """

    targets_adjusted: bool = True
    solver: str = "lmqn"
    rigorous_goniometer: bool = False
    check_fraction: float = 0.0
    check_seed: int = 0
    cross_validate: bool = False

    def to_dict(self) -> dict:
        out = {"targets_adjusted": self.targets_adjusted, "solver": self.solver,
               "rigorous_goniometer": self.rigorous_goniometer}
        if self.check_fraction > 0:           # only then: the fingerprints of other runs stay
            out.update(check_fraction=self.check_fraction, check_seed=self.check_seed)
        if self.cross_validate:
            out["cross_validate"] = True
        return out


@dataclass
class Prepared:
    """A validated session and what is to be measured."""

    session: Session
    settings: Settings
    to_measure: list[str]                 # image names (relative paths) to measure
    tables: dict[str, bytes] = field(default_factory=dict)   # name -> bytes of each table file
    frames: pa.Table | None = None        # goniometer: frames.csv as read
    field_data: object = None             # observation-only field session: FieldData as read (parsed once)

    @property
    def method(self) -> str:
        return self.session.method


@dataclass
class Outcome:
    """Everything one calibration produced, ready for :meth:`fieldcal.lake.store.Lake.commit`."""

    document: dict
    arrays: dict
    array_attrs: dict
    residuals: pa.Table
    summary: list[str]
    left_out: list[dict]
    result: object = None


def image_hash(prepared: Prepared, name: str) -> str:
    """SHA-256 of an image's bytes (the key of its cached measurements)."""
    if prepared.session.store is not None:
        return prepared.session.read_image(name).sha256
    return sha256_file(prepared.session.image_path(name))


def prepare(folder, settings: Settings | None = None, storage_options: dict | None = None) -> Prepared:
    """Validate a session folder; nothing is written (see the module docstring).

    ``folder``: a local path or an fsspec URL; ``storage_options``: the fsspec options of
    that URL's store. A session on a store is listed once and its small files fetched into
    a temporary folder for the loader, removed before this returns (the returned session
    needs no local file: :mod:`fieldcal.session.loader`).
    """
    settings = settings or Settings()
    if settings.solver not in ("lmqn", "lm"):
        raise InputError(f"solver must be 'lmqn' or 'lm', got {settings.solver!r}", "settings")
    if not (0.0 <= settings.check_fraction < 1.0):
        raise InputError(f"check_fraction must lie in [0, 1), got {settings.check_fraction}", "settings")
    if not is_url(folder):
        return _prepare(load_session(folder), settings)
    from fieldcal.lake import secrets

    store = open_store(str(folder), storage_options, resolve=secrets.resolve)   # redacted credentials: env
    with tempfile.TemporaryDirectory(prefix="fieldcal-session-") as tmp:
        local = os.path.join(tmp, store.name)
        store.fetch_small_files(local)
        try:
            return _prepare(load_session(local, store=store), settings)
        except InputError as e:           # named by the URL, not by the temporary copy
            where = e.where.replace(local, store.url) if e.where else e.where
            raise type(e)(e.reason.replace(local, store.url), where) from None


def _prepare(sess: Session, settings: Settings) -> Prepared:
    """:func:`prepare` of a loaded session: the tables read into memory, once."""
    tables = {"session.json": (sess.folder / "session.json").read_bytes()}
    if sess.method == "field":
        targets = sess.targets()                                # validates now (read once)
        unknown = sorted(set(sess.check_points) - set(targets.ids.tolist()))
        if unknown:
            raise InputError(f"check_points {unknown[:5]} are not in {sess.targets_path.name} (at /check_points)",
                             str(sess.folder / "session.json"))
        tables[sess.targets_path.name] = sess.targets_path.read_bytes()
        if sess.scale_bars_path is not None:
            tables["scale_bars.csv"] = sess.scale_bars_path.read_bytes()
        field_data = None
        if sess.observations_path is not None:
            field_data = field_data_from_observations(sess)     # validates now, kept for solve
            tables["observations.csv"] = sess.observations_path.read_bytes()
            to_measure = []
        else:
            if not sess.images:
                raise InputError("no images match the session's 'images' and there is no "
                                 "observations.csv", str(sess.folder / "session.json"))
            to_measure = [im.file for im in sess.images]
            if sess.scale_bars_path is not None:
                scale_bars_of(sess, targets)                    # validates now (ids of targets.csv)
            if sess.marks_path is not None:
                sess.marks()                                    # validates now (read once)
                tables["marks.csv"] = sess.marks_path.read_bytes()
            elif sess.coded is None:
                raise InputError("images without coded targets need marks.csv (a few hand-identified "
                                 "targets per image) to be identified", str(sess.folder / "session.json"))
        _check_image_folders(sess, to_measure)
        return Prepared(sess, settings, to_measure, tables, field_data=field_data)
    from fieldcal.session.frames import read_frames_csv

    frames = read_frames_csv(sess.frames_path, strict=False)
    tables[sess.frames_path.name] = sess.frames_path.read_bytes()
    names = [str(f) for f in frames.column("file").to_pylist()]
    _check_image_folders(sess, names)
    return Prepared(sess, settings, names, tables, frames)


def _check_image_folders(sess, names) -> None:
    """Bad input: a folder the session's images are listed in does not exist (one image's file
    missing is that image's problem, reported and left out; a missing ``images/`` is the session's)."""
    folders: dict = {}
    for name in names:
        folders.setdefault(os.path.dirname(os.path.normpath(name)), []).append(name)
    for folder, listed in folders.items():
        if not sess.has_image_folder(listed[0]):
            where = (sess.store.url_of(folder) + "/" if sess.store is not None
                     else os.fspath(sess.image_path(listed[0]).parent) + os.sep)
            raise InputError(f"no such folder; the session lists {len(listed)} image(s) in it "
                             f"({listed[0]}{', ...' if len(listed) > 1 else ''})", where)


def measure(prepared: Prepared, name: str, source=None) -> pa.Table:
    """Measure one image of the session (see the module docstring).

    ``source``: the image file's bytes already read and hashed
    (:func:`fieldcal.measure.imageio.read_file`), decoded without reading the file again;
    default: read the image from the session folder.
    """
    sess = prepared.session
    path = source if source is not None else sess.read_image(name) if sess.store is not None else sess.image_path(name)
    if prepared.method == "goniometer":
        from fieldcal.goniometer import method as goniometer

        row = goniometer.measure_frame(path, sess.sensor, name=name)
        return goniometer.measurements_table([row])
    from fieldcal.measure.targets import measure_image

    return measure_image(path, polarity=sess.target_polarity, sensor=sess.sensor, coded=sess.coded,
                         name=name)


def input_fingerprint(prepared: Prepared, image_hashes: Mapping[str, str]) -> str:
    """The inputs' fingerprint: the session's identity, tables, image contents and settings
    (canonical JSON, SHA-256). Two folders with the same files are two sessions when their
    ``session_id`` differs (a default one is the folder's name), so each gets its version."""
    sess = prepared.session
    return fingerprint({
        "session": {"camera_id": sess.camera_id, "session_id": sess.session_id},
        "tables": {k: v for k, v in sorted(prepared.tables.items())},
        "images": dict(sorted(image_hashes.items())),
        "settings": prepared.settings.to_dict(),
    })


def solve(prepared: Prepared, measurements: Mapping[str, pa.Table], *, fingerprint_: str,
          progress: Callable[[str], None] | None = None, left_out: list[dict] | None = None) -> Outcome:
    """Calibrate from the measurements (see the module docstring)."""
    left_out = list(left_out or [])
    if prepared.method == "goniometer":
        return _solve_goniometer(prepared, measurements, fingerprint_, left_out)
    return _solve_field(prepared, measurements, fingerprint_, progress, left_out)


# ---------------------------------------------------------------------------- field method
def drop_sparse_images(data: FieldData, min_points: int | None = None) -> tuple[FieldData, list[dict]]:
    """Leave out the images with fewer observations than an image needs to be oriented.

    Parameters
    ----------
    data : fieldcal.session.data.FieldData
        The field data of an observations-only session (every image it lists).
    min_points : int, optional
        Default :data:`fieldcal.field.adjustment.MIN_POINTS_PER_IMAGE`.

    Returns
    -------
    (FieldData, list of dict)
        The data without those images (observations re-indexed), and one
        ``{image, status, reason}`` per image left out, as for an image session.
    """
    from fieldcal.field.adjustment import MIN_POINTS_PER_IMAGE

    need = MIN_POINTS_PER_IMAGE if min_points is None else int(min_points)
    counts = np.bincount(data.obs.image, minlength=len(data.images)) if len(data.obs) else \
        np.zeros(len(data.images), int)
    keep = counts >= need
    if keep.all():
        return data, []
    left = [{"image": data.images[i].file, "status": "left out",
             "reason": f"only {int(counts[i])} observed target(s); an image needs at least {need}"}
            for i in np.flatnonzero(~keep)]
    new_index = np.cumsum(keep) - 1
    sel = keep[data.obs.image]
    o = data.obs
    obs = type(o)(new_index[o.image[sel]], o.target[sel], o.uv_px[sel], o.sigma_px[sel])
    images = [im for im, k in zip(data.images, keep, strict=True) if k]
    return replace(data, images=images, obs=obs), left


def _field_result(prepared, measurements, progress, left_out):
    from fieldcal.field.adjustment import MIN_IMAGES, AdjustmentOptions, adjust_field

    sess = prepared.session
    options = AdjustmentOptions(targets_adjusted=prepared.settings.targets_adjusted,
                                estimate=sess.estimate, method=prepared.settings.solver,
                                check_points=sess.check_points, check_fraction=prepared.settings.check_fraction,
                                check_seed=prepared.settings.check_seed, datum=sess.datum,
                                board_model=sess.board_model)
    if sess.observations_path is not None:
        data, left = drop_sparse_images(prepared.field_data or field_data_from_observations(sess))
        if left and len(data.images) < MIN_IMAGES:
            more = f" (and {len(left) - 1} more image(s) left out)" if len(left) > 1 else ""
            raise GeometryError(f"{left[0]['image']}: {left[0]['reason']}{more}; {len(data.images)} image(s) "
                                f"remain, the field method needs at least {MIN_IMAGES}")
        left_out.extend(left)
        return data, adjust_field(data, options, progress=progress)
    from fieldcal.field.from_images import calibrate_from_measurements
    from fieldcal.field.referencing import ReferencingOptions

    targets = sess.targets()        # unsurveyed plain targets listed: their discs by automatic referencing
    plain_unsurveyed = bool(np.any(~targets.surveyed & (targets.codes < 0)))
    data, result, report = calibrate_from_measurements(sess, dict(measurements), options, progress=progress,
                                                       referencing=ReferencingOptions() if plain_unsurveyed else None)
    known = {r.get("image") for r in left_out}
    left_out.extend(r for r in report if r.get("status") != "ok" and r.get("image") not in known)
    return data, result


ECCENTRICITY_OBSERVATIONS = {"max_px": None, "normals": "none", "applied": False,
                             "reason": "observations.csv: image points measured elsewhere are used as given"}
"""``stats.eccentricity`` of a session of observations.csv (no image of ours measured them)."""


def _solve_field(prepared, measurements, fp, progress, left_out) -> Outcome:
    sess = prepared.session
    data, res = _field_result(prepared, measurements, progress, left_out)
    res: FieldResult
    stats = res.stats()
    stats["left_out_images"] = [r.get("image") for r in left_out]
    stats["left_out"] = [{"image": r.get("image"), "reason": r.get("reason")} for r in left_out]
    if "identification" in data.meta:
        stats["identification"] = data.meta["identification"]
    stats["eccentricity"] = data.meta.get("eccentricity", ECCENTRICITY_OBSERVATIONS)
    for key in ("referenced_targets", "coded_unsurveyed_targets"):       # from photographs (issue 26)
        if key in data.meta:
            stats[key] = data.meta[key]
    if prepared.settings.cross_validate:
        from fieldcal.field.cross_validation import cross_validate_by_station

        stats["cross_validation"] = cross_validate_by_station(res, progress=progress).to_dict()
    doc = calibration_document(
        camera_id=sess.camera_id, session_id=sess.session_id, version="", method="field",
        sensor=sess.sensor, parameters=res.params, sigma=res.sigma, stats=stats,
        images=res.images_section(), fingerprint=fp,
        extra={"acquired": sess.acquired.strftime("%Y-%m-%dT%H:%M:%SZ")})
    names = res.covariance_names
    arrays = {"covariance": res.covariance, "correlation": res.correlation_interior, **correction_arrays(doc)}
    attrs = {"covariance": {"names": names, "units": "a-posteriori, parameter units; rotations rad, centres m"},
             "correlation": {"names": list(res.estimate)}}
    if res.sigma_targets_m is not None:
        arrays["targets/xyz_m"] = res.targets_m
        arrays["targets/sigma_m"] = res.sigma_targets_m
        attrs["targets/xyz_m"] = {"ids": [str(t) for t in data.targets.ids]}
        arrays["targets/survey_residual_mm"] = res.survey_residual_mm        # surveyed - adjusted
        arrays["targets/survey_used"] = res.survey_used.astype("int8")
    cp = res.check_points
    if cp is not None and len(cp.ids):
        arrays["check_points/error_mm"] = cp.error_mm                         # intersected - surveyed
        arrays["check_points/sigma_mm"] = np.sqrt(np.einsum("kii->ki", cp.cov_mm2))
        attrs["check_points/error_mm"] = {"ids": [str(t) for t in cp.ids],
                                          "what": "intersected minus surveyed coordinates [mm]"}
    summary = _field_summary(sess, res, stats)
    return Outcome(doc, arrays, attrs, res.residual_table(), summary, left_out, res)


def _field_summary(sess, res: FieldResult, st: dict | None = None) -> list[str]:
    """The summary lines of a field result; ``st``: its :meth:`FieldResult.stats`, when made already."""
    st = res.stats() if st is None else st
    lines = [f"{sess.camera_id} / {sess.session_id}: field method, {st['n_images']} images, "
             f"{st['n_targets']} targets, {st['n_observations']} points ({st['n_rejected']} rejected)",
             f"rmse {st['rmse_px']:.3g} px, sigma0 {st['sigma0']:.3f}, {st['iterations']} iterations ({st['solver']})"]
    for j, n in enumerate(PARAM_NAMES):
        s = res.sigma.get(n)
        lines.append(f"  {n:6s} {res.params[j]: .6e}" + (f"  ± {s:.2e}" if s is not None else "  (fixed)"))
    if res.fixed_parameters:
        lines.append("held fixed: " + ", ".join(f"{k} ({v})" for k, v in res.fixed_parameters.items()))
    cp = st.get("check_points")
    if cp and cp.get("n"):
        lines.append(f"check points: {cp['n']} in object space, RMS {cp['rms_mm']:.3g} mm (predicted "
                     f"{cp['rms_mm_predicted']:.3g}); {cp['n_observations']} image points, RMS "
                     f"{cp['rms_px']:.3g} px (predicted {cp['rms_px_predicted']:.3g})")
    return lines


# ---------------------------------------------------------------------------- goniometer
def _solve_goniometer(prepared, measurements, fp, left_out) -> Outcome:
    sess = prepared.session
    from fieldcal.goniometer import method as goniometer

    rows = [measurements[n] for n in prepared.to_measure if n in measurements]
    if not rows:
        raise GeometryError("no goniometer frame could be measured")
    table = pa.concat_tables(rows)
    res = goniometer.calibrate(sess.sensor, prepared.frames, table, nominal_focal_mm=sess.nominal_focal_mm,
                               rigorous=prepared.settings.rigorous_goniometer)
    fields = res.document_fields()
    sigma = {k: v for k, v in fields["sigma"].items() if v is not None}
    doc = calibration_document(
        camera_id=sess.camera_id, session_id=sess.session_id, version="", method="goniometer",
        sensor=sess.sensor, parameters=res.parameters, sigma=sigma, stats=fields["stats"],
        images=fields["images"], fingerprint=fp,
        extra={"acquired": sess.acquired.strftime("%Y-%m-%dT%H:%M:%SZ")})
    left_out = left_out + [{"image": r.get("file"), "status": "left out", "reason": r.get("reason")}
                           for r in res.rejected]
    arrays = res.arrays()
    attrs = {"covariance": {"names": list(PARAM_NAMES)}, "correlation": {"names": list(PARAM_NAMES)}}
    return Outcome(doc, arrays, attrs, res.lake_residuals(), list(res.report_lines()), left_out, res)

