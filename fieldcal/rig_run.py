"""One rig session's calibration as plain steps: prepare (validate, nothing written), solve, commit.

A rig session (CONTRACT section 3, "Rig sessions") that carries ``observations.csv`` is
calibrated by :func:`fieldcal.rig.adjust_rig`; one without it is measured from its images first
(:mod:`fieldcal.rig.from_images`: every head identified as a single camera is, the images a
head could not identify alone started from the rig's other heads); its results are one calibration document per
head and the rig document (:mod:`fieldcal.rig.document`), committed to the lake as one version
of the rig by :meth:`fieldcal.lake.store.Lake.commit_rig`.

Fingerprints: the rig's is that of its inputs (session.json, targets.csv, observations.csv or
the SHA-256 of every image) and settings; each head's is the rig's with the head's id, so that a head's version is
recognised as the same inputs and a rerun finds it.
"""

from __future__ import annotations

import os
import posixpath
import shutil
import tempfile
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field

from fieldcal.analysis.correction import correction_arrays
from fieldcal.contract.fingerprint import fingerprint, sha256_bytes, sha256_file
from fieldcal.errors import InputError
from fieldcal.field.adjustment import AdjustmentOptions
from fieldcal.pipeline import Settings
from fieldcal.rig.data import RigData
from fieldcal.rig.session import RigSession, load_rig_session, rig_data_from_observations
from fieldcal.session.loader import safe_path
from fieldcal.session.store import is_url, open_store

__all__ = ["RigPrepared", "RigOutcome", "prepare_rig", "measure_rig", "solve_rig", "run_rig"]


@dataclass
class RigPrepared:
    """A validated rig session, its data and its inputs' fingerprint (``local``: for a session on
    an object store, the temporary folder holding its small files while the run needs them)."""

    session: RigSession
    settings: Settings
    data: RigData | None
    fingerprint: str
    to_measure: list = field(default_factory=list)
    report: list = field(default_factory=list)
    local: object = field(default=None, repr=False)


@dataclass
class RigOutcome:
    """What :func:`solve_rig` produced: per head what :meth:`Lake.commit_rig` takes, the rig
    document (its versions filled in at the commit) and a human summary."""

    heads: list
    rig_document: dict
    summary: list
    result: object = None


def prepare_rig(folder, settings: Settings | None = None, storage_options: dict | None = None) -> RigPrepared:
    """Validate a rig session and read its observations; nothing is written.

    ``folder``: a local path or an fsspec URL (``s3://...``), ``storage_options`` the fsspec
    options of its store. A session on a store is listed once and its small files fetched into
    a temporary folder (kept while the returned :class:`RigPrepared` lives); its images are read
    from the store where they are measured (:func:`measure_rig`), never copied. Their part of the
    fingerprint is, for a local session, every image's SHA-256; on a store, what the store's
    listing says of each object (size and ETag, the MD5 of an object written in one part), so
    that an unchanged session is found without reading its images.

    Raises
    ------
    InputError
        One line naming the file and what is wrong (also: a rig session of images without
        coded targets, or whose images' folder does not exist, or with unsurveyed targets).
    """
    settings = settings or Settings()
    if settings.solver not in ("lmqn", "lm"):
        raise InputError(f"solver must be 'lmqn' or 'lm', got {settings.solver!r}", "settings")
    if not is_url(folder):
        return _prepare_rig(load_rig_session(folder), settings)
    from fieldcal.lake import secrets

    store = open_store(str(folder), storage_options, resolve=secrets.resolve)   # redacted credentials: env
    tmp = tempfile.mkdtemp(prefix="fieldcal-rig-")
    local = os.path.join(tmp, store.name)
    try:
        store.fetch_small_files(local)
        prepared = _prepare_rig(load_rig_session(local, store=store), settings)
    except InputError as e:                  # named by the URL, not by the temporary copy
        shutil.rmtree(tmp, ignore_errors=True)
        where = e.where.replace(local, store.url) if e.where else e.where
        raise type(e)(e.reason.replace(local, store.url), where) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    prepared.local = weakref.finalize(prepared, shutil.rmtree, tmp, ignore_errors=True)   # removed with it
    return prepared


def _prepare_rig(sess: RigSession, settings: Settings) -> RigPrepared:
    parts = {"session": sha256_bytes((sess.folder / "session.json").read_bytes()),
             "targets": sha256_bytes(sess.targets_path.read_bytes()), "settings": settings.to_dict(), "kind": "rig"}
    if sess.observations_path is not None:
        data = rig_data_from_observations(sess)
        parts["observations"] = sha256_bytes(sess.observations_path.read_bytes())
        return RigPrepared(sess, settings, data, fingerprint(parts))
    if sess.coded is None:
        raise InputError("a rig session measured from its images needs coded targets (field.coded; marks.csv "
                         "is not supported for rigs)", sess.where)
    _refuse_unsurveyed(sess, sess.targets())                        # validated now
    names = [im.file for im in sess.images]
    _check_image_folders(sess, names)
    if sess.store is not None:
        st = sess.store
        parts["images"] = {n: {"size": st.files[n], "etag": st.md5.get(n)} for n in names if n in st.files}
    else:
        parts["images"] = {n: sha256_file(safe_path(sess.folder, n, "image")) for n in names
                           if safe_path(sess.folder, n, "image").is_file()}
    return RigPrepared(sess, settings, None, fingerprint(parts), to_measure=names)


def _refuse_unsurveyed(sess: RigSession, targets) -> None:
    """Bad input (for now): unsurveyed targets in a rig session of images (the rig adjustment
    estimates them from observations, :func:`fieldcal.rig.session.rig_data_from_observations`,
    but the identification of a rig's images does not place them yet)."""
    bad = targets.ids[~targets.surveyed]
    if len(bad):
        raise InputError(f"{len(bad)} unsurveyed target(s) ({', '.join(map(str, bad[:3]))}"
                         f"{', ...' if len(bad) > 3 else ''}): a rig session of images needs every target "
                         "surveyed (unsurveyed targets are supported in rig sessions with observations.csv "
                         "and for single cameras)", str(sess.targets_path))


def _check_image_folders(sess: RigSession, names) -> None:
    """Bad input: a folder the session's images are listed in does not exist."""
    folders: dict = {}
    if sess.store is not None:          # an object store has no folders: one holding some file
        for name in names:
            folders.setdefault(posixpath.dirname(name), []).append(name)
        for rel, listed in folders.items():
            if not sess.store.has_folder(rel):
                raise InputError(f"no such folder; the session lists {len(listed)} image(s) in it ({listed[0]}"
                                 f"{', ...' if len(listed) > 1 else ''})", sess.store.url_of(rel) + "/")
        return
    for name in names:
        folders.setdefault(safe_path(sess.folder, name, "image").parent, []).append(name)
    for folder, listed in folders.items():
        if not folder.is_dir():
            raise InputError(f"no such folder; the session lists {len(listed)} image(s) in it ({listed[0]}"
                             f"{', ...' if len(listed) > 1 else ''})", str(folder) + "/")


def measure_one(sess: RigSession, name: str):
    """``(name, measurements or None, why)`` of one image of a rig session, read where this runs
    (on a store: from the store, :meth:`RigSession.read_image`); a failure to read or measure is
    its reason, not an exception (a Dask worker's task)."""
    from fieldcal.errors import FieldcalError
    from fieldcal.rig.from_images import measure_rig_image

    try:
        return name, measure_rig_image(sess, name, source=sess.read_image(name)), None
    except (FieldcalError, OSError) as e:
        return name, None, str(e)


def measure_rig(prepared: RigPrepared, *, progress: Callable[[str], None] | None = None,
                target_normals=None, mapper: Callable | None = None) -> RigData:
    """Measure and identify a rig session's images (:mod:`fieldcal.rig.from_images`); sets and
    returns ``prepared.data`` (and ``prepared.report``, one entry per image). An image that cannot
    be read or measured is left out (its reason in the report). ``mapper(function, sessions,
    names)``: where the images are measured (e.g. the Dask workers, :func:`flows.fleet.calibrate_rig`;
    default: here, one after the other) -- each reads its image itself, from the store for a
    session on one."""
    from fieldcal.rig.adjustment import RigOptions
    from fieldcal.rig.from_images import rig_data_from_measurements

    sess, st = prepared.session, prepared.settings
    names = list(prepared.to_measure)
    done = list((mapper or map)(measure_one, [sess] * len(names), names))
    measurements = {n: m for n, m, _ in done if m is not None}
    failed = {n: why for n, m, why in done if m is None}
    options = AdjustmentOptions(targets_adjusted=st.targets_adjusted, estimate=sess.estimate, method=st.solver)
    data, report = rig_data_from_measurements(
        sess, measurements, options=options, progress=progress, target_normals=target_normals,
        rig_options=RigOptions(targets_adjusted=st.targets_adjusted, estimate=sess.estimate, method=st.solver))
    for r in report:
        if r["image"] in failed:
            r["reason"] = failed[r["image"]]
    prepared.data, prepared.report = data, report
    return data


def solve_rig(prepared: RigPrepared, *, progress: Callable[[str], None] | None = None,
              mapper: Callable | None = None) -> RigOutcome:
    """Adjust the rig and make its documents (module docstring); ``mapper``: of :func:`measure_rig`."""
    from fieldcal.rig.adjustment import RigOptions, adjust_rig
    from fieldcal.rig.document import head_arrays, head_document, head_residual_table, rig_document

    sess, st = prepared.session, prepared.settings
    if prepared.data is None:
        measure_rig(prepared, progress=progress, mapper=mapper)
    options = RigOptions(targets_adjusted=st.targets_adjusted, estimate=sess.estimate, method=st.solver)
    res = adjust_rig(prepared.data, options, progress=progress)
    acquired = sess.acquired.strftime("%Y-%m-%dT%H:%M:%SZ")
    heads = []
    for h, hd in enumerate(prepared.data.heads):
        fp = fingerprint({"rig": prepared.fingerprint, "camera_id": hd.camera_id})
        arrays, attrs = head_arrays(res, h)
        doc = head_document(res, h, session_id=sess.session_id, fingerprint=fp, acquired=acquired)
        heads.append({"document": doc, "arrays": arrays | correction_arrays(doc), "array_attrs": attrs,
                      "residuals": head_residual_table(res, h)})
    rig = rig_document(res, session_id=sess.session_id, head_versions=[""] * len(heads),
                       fingerprint=prepared.fingerprint, acquired=acquired)
    return RigOutcome(heads, rig, _summary(prepared, res), res)


def _summary(prepared: RigPrepared, res) -> list[str]:
    st = res.stats()
    lines = [f"rig {prepared.data.rig_id} / {prepared.session.session_id}: {len(prepared.data.heads)} heads, "
             f"{st['n_exposures']} exposures, {st['n_images']} images, {st['n_observations']} points "
             f"({st['n_rejected']} rejected), sigma0 {st['sigma0']:.3f}"]
    for h, hd in enumerate(prepared.data.heads):
        hs = st["heads"][hd.camera_id]
        f, sf = res.state.params[h][0], res.sigma[h].get("f_mm")
        rot, t = res.sigma_rotation_arcsec[h], res.sigma_t_mm[h]
        rel = ("reference" if h == prepared.data.reference else
               f"sigma rotation {', '.join(f'{v:.2g}' for v in rot)} arcsec, "
               f"lever arm {', '.join(f'{v:.2g}' for v in t)} mm")
        lines.append(f"  {hd.camera_id}: f {f:.5f} ± {sf:.2g} mm, rmse {hs['rmse_px']:.3g} px; {rel}")
    return lines


def run_rig(folder, lake, *, settings: Settings | None = None, force: bool = False,
            progress: Callable[[str], None] | None = None, prepared: RigPrepared | None = None,
            storage_options: dict | None = None, mapper: Callable | None = None):
    """Prepare (unless ``prepared`` is given), solve and commit a rig session; returns ``(rig
    version, head versions, outcome)`` (``outcome`` None when nothing was solved: the same inputs
    were committed already, the version's ``.new`` False, or an interrupted commit of them was
    completed, ``.new`` True; :meth:`~fieldcal.lake.store.Lake.complete_rig`)."""
    prepared = prepared if prepared is not None else prepare_rig(folder, settings, storage_options)
    if not force:
        done = lake.complete_rig(prepared.fingerprint)
        if done is not None:
            return done[0], done[1], None
    outcome = solve_rig(prepared, progress=progress, mapper=mapper)
    version, heads = lake.commit_rig(outcome.heads, outcome.rig_document, force=force)
    return version, heads, outcome
