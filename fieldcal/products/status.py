"""Where each calibration of the fleet stands: its change test and its acceptance, kept in the lake.

Two derived tables of the lake (:mod:`fieldcal.lake.tables`) hold what ``history --fleet`` and
the dashboard (:mod:`fieldcal.products.dashboard`) show, so that they read it instead of
computing it (a comparison needs both calibrations' documents and Zarr groups: 0.1-0.3 s
each from a local lake, ~2.7 s from S3):

- ``comparisons``: the change test (:func:`fieldcal.analysis.compare.compare_calibrations`)
  of a version against the previous calibration of its camera, as its
  :meth:`~fieldcal.analysis.compare.Comparison.record` (independent of the level and the
  tolerance: :func:`fieldcal.analysis.compare.judge` gives the verdict at any). Keyed by the
  pair: "previous" follows :mod:`fieldcal.lake.order` (acquisition time, ties by commit
  order), and a commit out of order (a backfill) adds the pairs of its new neighbours; a
  reader picks the pair of the current order.
- ``assessments``: the acceptance (:func:`fieldcal.products.certificate.acceptance`) of each
  version without its change criterion (that one comes from ``comparisons``, so that a
  backfill never leaves a stale verdict), and the radial distortion at
  :data:`RADII_FRACTIONS` of the sensor's half diagonal with its sigma (from the covariance).

:func:`record_commit` computes both when a version is committed (the flow calls it with the
calibration still in memory): the version against its previous one, and the next one against
this version when the commit came out of order. :func:`changes` and :func:`assessments` read
them, computing (and remembering) what is missing, e.g. pairs of two commits that raced;
:func:`fill` computes them once for a lake made before they existed (``fieldcal lake fill``).
Nothing here is needed for a version to exist: a failure is reported, never raised into a
commit.
"""

from __future__ import annotations

import json

import numpy as np

from fieldcal.analysis.compare import compare_calibrations
from fieldcal.analysis.uncertainty import Calibration, radial_curve
from fieldcal.errors import InputError, LakeError, one_line
from fieldcal.lake import order
from fieldcal.products.certificate import DEFAULT_CONFIG, acceptance

__all__ = ["COMPARISON_TEST", "COMPARISON_SETTINGS", "RADII_FRACTIONS", "record_commit", "changes",
           "assessments", "assessment_settings", "assess", "fill"]

COMPARISON_TEST = "holm-family/2"
"""The definition of the stored change test; change it when the test changes (old rows are
then not reused)."""
GRID = (41, 31)
COMPARISON_SETTINGS = json.dumps({"grid": list(GRID), "test": COMPARISON_TEST}, sort_keys=True)
"""The ``settings`` of the stored comparisons."""
ASSESSMENT_TEST = "acceptance/2"
"""The definition of the stored assessments (acceptance/2, issue 30: the check points' chi-square
criterion, the image-space check-point RMS off by default, criteria named with their symbols);
old rows of another definition are not reused."""
RADII_FRACTIONS = (0.25, 0.5, 0.75, 1.0)
"""Where the radial distortion is kept: fractions of the sensor's half diagonal."""


def assessment_settings(config: dict | None = None) -> str:
    """The ``settings`` of stored assessments made with a certificate configuration."""
    acc = (config or DEFAULT_CONFIG)["acceptance"]
    return json.dumps({"acceptance": acc, "radii": list(RADII_FRACTIONS), "test": ASSESSMENT_TEST},
                      sort_keys=True)


def _calibration(lake, version: str, cals: dict) -> Calibration:
    if version not in cals:
        cals[version] = Calibration.from_lake(lake, version)
    return cals[version]


def _compare(lake, va: str, vb: str, cals: dict) -> dict:
    """The record of ``va`` against ``vb``, or ``{"error": reason}`` (not remembered)."""
    try:
        return compare_calibrations(_calibration(lake, va, cals), _calibration(lake, vb, cals), grid=GRID).record()
    except (InputError, LakeError) as e:
        return {"error": one_line(e)}


def assess(cal: Calibration, residuals, config: dict | None = None) -> dict:
    """The assessment of one calibration (module docstring): ``camera_id``, ``verdict``
    (PASS / FAIL of the criteria other than the change), ``rows`` (every criterion) and
    ``radial`` (``r_mm``, ``dr_um``, ``sigma_um`` at :data:`RADII_FRACTIONS`)."""
    acc = acceptance(cal, residuals, config or DEFAULT_CONFIG, change=None)
    r_mm = np.asarray(RADII_FRACTIONS) * cal.sensor.half_diagonal_mm
    dr, sigma = radial_curve(cal, r_mm)
    rows = [{k: (v if isinstance(v, (str, int, float, bool, type(None))) else float(v)) for k, v in r.items()}
            for r in acc["rows"]]
    return {"camera_id": str(cal.document.get("camera_id")), "verdict": acc["verdict"], "rows": rows,
            "radial": {"r_mm": r_mm.tolist(), "dr_um": (1000 * dr).tolist(), "sigma_um": (1000 * sigma).tolist()}}


def _camera_rows(lake, camera_id: str) -> list[dict]:
    """The catalog rows of one camera (``equal`` only skips files: the filter keeps its rows)."""
    import pyarrow.dataset as ds

    cols = ["camera_id", "session_id", "version", "acquired", "created", "committed"]
    return lake.catalog(filter=ds.field("camera_id") == camera_id, equal={"camera_id": camera_id},
                        sort=False).select(cols).to_pylist()


def record_commit(lake, version: str, calibration: Calibration | None = None, residuals=None) -> dict:
    """Compute and store the change test and the assessment of a version just committed.

    Parameters
    ----------
    lake : fieldcal.lake.store.Lake
    version : str
        The committed version.
    calibration : Calibration, optional
        Its calibration, when at hand (else read from the lake).
    residuals : pyarrow.Table, optional
        Its residual table, when at hand.

    Returns
    -------
    dict
        ``previous`` (the version it was compared with, or None), ``comparison`` (the
        record, None without a previous one, ``{"error": ...}`` when it could not be made),
        ``next`` (a later session's version compared with this one, after a backfill),
        ``assessment`` (:func:`assess`, or ``{"error": ...}``).
    """
    cals = {} if calibration is None else {version: calibration}
    out = {"previous": None, "comparison": None, "next": None, "assessment": None}
    try:
        cal = _calibration(lake, version, cals)
        out["assessment"] = assess(cal, lake.read_residuals(version) if residuals is None else residuals)
        lake.remember_assessments(assessment_settings(), {version: out["assessment"]})
        prev, nxt = order.neighbours(_camera_rows(lake, str(cal.document.get("camera_id"))), version)
    except (InputError, LakeError) as e:
        out["assessment"] = {"error": one_line(e)}
        return out
    fresh = {}
    for pair in ((prev, version), (version, nxt)):
        if None not in pair:
            fresh[pair] = _compare(lake, *pair, cals)
    lake.remember_comparisons(COMPARISON_SETTINGS, {p: r for p, r in fresh.items() if "error" not in r})
    out.update(previous=prev, next=nxt, comparison=fresh.get((prev, version)))
    return out


def changes(lake, pairs, *, compute: bool = True) -> dict:
    """``{(version_a, version_b): record}`` of the given pairs: stored ones read, the others
    compared (with ``compute``) and remembered; a pair that cannot be compared maps to
    ``{"error": reason}``."""
    pairs = list(dict.fromkeys(pairs))
    found = lake.cached_comparisons(COMPARISON_SETTINGS, versions_b={b for _, b in pairs}) if pairs else {}
    out = {p: found[p] for p in pairs if p in found}
    if compute:
        cals: dict = {}
        fresh = {p: _compare(lake, *p, cals) for p in pairs if p not in out}
        lake.remember_comparisons(COMPARISON_SETTINGS, {p: r for p, r in fresh.items() if "error" not in r})
        out.update(fresh)
    return out


def assessments(lake, versions, config: dict | None = None, *, compute: bool = True, brief: bool = False) -> dict:
    """``{version: assessment}`` (:func:`assess`): stored ones read, the others computed (with
    ``compute``) and remembered; one that cannot be made maps to ``{"error": reason}``.
    ``brief``: of the stored ones only ``camera_id``, ``verdict`` and ``radial``."""
    settings = assessment_settings(config)
    versions = list(dict.fromkeys(versions))
    out = lake.cached_assessments(settings, versions, brief=brief) if versions else {}
    if compute:
        fresh = {}
        for v in versions:
            if v in out:
                continue
            try:
                fresh[v] = assess(Calibration.from_lake(lake, v), lake.read_residuals(v), config)
            except (InputError, LakeError) as e:
                fresh[v] = {"error": one_line(e)}
        lake.remember_assessments(settings, {v: r for v, r in fresh.items() if "error" not in r})
        out.update(fresh)
    return out


def _wanted(lake, everything: bool) -> tuple[list, list]:
    """``(pairs, versions)`` a fill computes: every consecutive pair and version of each
    camera, or (not ``everything``) each camera's latest and the pair that ends in it."""
    cols = ["camera_id", "session_id", "version", "acquired", "created", "committed"]
    by_camera: dict = {}
    for row in lake.catalog(sort=False).select(cols).to_pylist():
        by_camera.setdefault(row["camera_id"], []).append(row)
    pairs, versions = [], []
    for camera in sorted(by_camera):
        seq = [r["version"] for r in order.session_latest(by_camera[camera])]
        if not everything:
            seq = seq[-2:]
        pairs += list(zip(seq[:-1], seq[1:], strict=True))
        versions += seq if everything else seq[-1:]
    return pairs, versions


def fill(lake, *, everything: bool = False, progress=None, chunk: int = 20) -> dict:
    """Compute the comparisons and assessments a lake lacks (``fieldcal lake fill``).

    By default what ``history --fleet`` and the dashboard read first: each camera's latest
    version and its pair with the previous one; ``everything``: every consecutive pair and
    every version. Results are appended ``chunk`` at a time (an interrupted fill keeps what
    it did). ``progress(done, total)`` is called after each chunk. Returns the counts
    ``pairs``, ``versions`` (wanted), ``computed`` (new rows) and ``failed`` (with a reason
    each in ``errors``).
    """
    pairs, versions = _wanted(lake, everything)
    have_pairs = lake.cached_comparisons(COMPARISON_SETTINGS, versions_b={b for _, b in pairs}) if pairs else {}
    have_versions = lake.cached_assessments(assessment_settings(), versions) if versions else {}
    todo = [("pair", p) for p in pairs if p not in have_pairs] + [("version", v) for v in versions
                                                                  if v not in have_versions]
    counts = {"pairs": len(pairs), "versions": len(versions), "computed": 0, "failed": 0, "errors": []}
    for start in range(0, len(todo), chunk):
        part = todo[start:start + chunk]
        got = {**changes(lake, [x for k, x in part if k == "pair"]),
               **assessments(lake, [x for k, x in part if k == "version"])}
        for key, result in got.items():
            if "error" in result:
                counts["failed"] += 1
                counts["errors"].append(f"{key}: {result['error']}")
            else:
                counts["computed"] += 1
        if progress is not None:
            progress(min(start + chunk, len(todo)), len(todo))
    return counts
