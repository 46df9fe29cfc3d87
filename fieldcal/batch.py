"""One session as a batch job: what is known already, what is left to measure, in which batches.

The plain decisions of a calibration run, without any workflow engine, so that a notebook,
the Prefect flows (``flows/``) and the command line make them the same way:

- :func:`measure_settings` and :func:`measurement_key`: the key of an image's cached
  observations in the lake, the SHA-256 of the image's content hash combined with what in
  the session decides how it is measured (method, sensor, target polarity, coded-target
  dictionary). An image is measured again when its bytes change or when the session
  changes how it is measured, never otherwise.
- :func:`plan_session`: from the image hashes known without reading an image (a
  caller's hash store), which images are missing, which have cached observations, which
  must be measured, and whether the whole run is a no-op (:attr:`SessionPlan.unchanged`:
  a version with the same fingerprint of inputs and settings is committed already).
- :func:`measure_into_lake`: hash (when unknown), look up and measure one image, and write
  its observations into the lake; a bad image is a row with status ``"bad"``, not an
  exception. :func:`measure_many_into_lake`: the same for a sequence of images, with one
  lake append for all of them (or one per ``append_every_s`` of measuring).
- :func:`read_observations`: the cached observations of the measured images, for the solve.
- :func:`pull_chunks`: the images in the pieces that measuring tasks pull, one at a
  time, from a queue they share (self-scheduling: one task per worker thread, the
  threads finish within one piece of each other); :func:`assign_batches`: where fixed
  batches go (``--batch-size``).

The lake is used through its public methods only (``find_committed``, ``cached_keys``,
``has_observations``, ``write_observations_many``, ``read_observations``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from fieldcal import pipeline
from fieldcal.contract.fingerprint import canonical_json, sha256_bytes
from fieldcal.errors import ImageError, InputError, LakeError, one_line

__all__ = ["measure_settings", "measurement_key", "SessionPlan", "plan_session", "missing_images",
           "unchanged_version", "cached_observations", "measure_into_lake", "measure_many_into_lake",
           "read_observations", "pull_chunks", "assign_batches", "image_seconds", "PIECES_PER_TASK",
           "PRIOR_IMAGE_S", "MIN_PULL_S", "APPEND_EVERY_S", "MISSING",
           "UNREADABLE"]

PRIOR_BYTES_PER_S = 300e6
"""Work per image before any is measured: the file's bytes at this rate [bytes/s]. The bench
frames (60-103 MB) take 0.19-0.38 s each to read, hash, decode and measure on one core
(``bench/README_flow.md``): 270-540 MB/s."""
PRIOR_IMAGE_S = 0.004
"""Work per image besides its bytes [s]: opening, the TIFF's header, detection (a goniometer
session's 180 frames of 5 kB measure in ~4 ms each)."""
MIN_PULL_S = 0.25
"""Least expected work in one piece a measuring task pulls [s] (:func:`pull_chunks`): a
pull is a round trip to the Dask scheduler (~1-5 ms), negligible against a full-size frame
(one per pull) but not against a goniometer's 5 ms frames (~50 per pull)."""
APPEND_EVERY_S = 30.0
"""A measuring task appends its observations to the lake after this much measuring [s] (and
at its end): a task killed late loses at most this much work (``fieldcal run`` picks the
rest up again from the lake)."""
MISSING = "missing"
"""The stand-in hash of a listed image whose file is absent (part of the fingerprint)."""
UNREADABLE = "unreadable"
"""The stand-in hash of an image that could not be read or measured."""
META_KEYS = (b"fieldcal.image", b"fieldcal.content_sha256", b"fieldcal.image_sha256", b"fieldcal.measure")
"""Schema metadata the lake and :func:`measure_into_lake` add to an observations file."""


# --------------------------------------------------------------------------------------
# keys
# --------------------------------------------------------------------------------------
def measure_settings(prepared: pipeline.Prepared) -> dict:
    """What in a session decides how its images are measured (part of the observations' key)."""
    sess = prepared.session
    out = {"method": sess.method, "sensor": sess.sensor.to_dict()}
    if sess.method == "field":
        out["target_polarity"] = sess.target_polarity
        out["coded"] = sess.coded
    return out


def measurement_key(image_sha256: str, settings: dict) -> str:
    """The observations' cache key: SHA-256 of the image's hash and the measuring settings.

    Parameters
    ----------
    image_sha256 : str
        64 hex digits of the image file's content.
    settings : dict
        :func:`measure_settings` of the session.

    Returns
    -------
    str
        64 lower-case hex digits.
    """
    return sha256_bytes(canonical_json({"image_sha256": image_sha256, "measure": settings}))


# --------------------------------------------------------------------------------------
# what is known before anything is read
# --------------------------------------------------------------------------------------
@dataclass
class SessionPlan:
    """What a run of one session has to do, decided before any image is read.

    Attributes
    ----------
    hashes : dict
        ``{image: sha256}`` known so far (from the caller's hash store); a missing file has
        the stand-in :data:`MISSING`.
    missing : dict
        ``{image: reason}`` of listed images whose file is absent (left out).
    cached : dict
        ``{image: key}`` of images whose observations are in the lake already.
    present : set
        ``(image, key)`` of every image of the session with observations in the lake, read
        once by the plan: a measuring task that learns an image's hash by reading it finds
        out from this set whether it is cached, without asking the lake per image.
    todo : list of str
        Images to hash and/or measure, in the session's order.
    fingerprint : str or None
        The inputs' fingerprint when every image's hash is known, else None.
    unchanged : str or None
        The committed version made from this fingerprint (the run is a no-op), else None.
    not_whole : dict
        ``{version: reason}`` of committed versions of this fingerprint that do not read
        back whole (:meth:`Lake.committed_whole`): the run calibrates again (issue 24).
    """

    hashes: dict[str, str]
    missing: dict[str, str]
    cached: dict[str, str] = field(default_factory=dict)
    present: set[tuple[str, str]] = field(default_factory=set)
    todo: list[str] = field(default_factory=list)
    fingerprint: str | None = None
    unchanged: str | None = None
    not_whole: dict[str, str] = field(default_factory=dict)


def missing_images(prepared: pipeline.Prepared, known: dict[str, str] | None = None) -> dict[str, str]:
    """``{image: reason}`` of the images to measure whose file is absent or not a regular file.

    Images whose hash is ``known`` (their file was seen unchanged) are not checked again.
    """
    out = {}
    for name in prepared.to_measure:
        if known and name in known:
            continue
        reason = prepared.session.missing_image(name)
        if reason is not None:
            out[name] = reason
    return out


def unchanged_version(prepared: pipeline.Prepared, lake, hashes: dict[str, str]) -> tuple[str, str | None]:
    """The no-op check: ``(fingerprint, committed version or None)`` for these image hashes.

    ``hashes`` must name every image of ``prepared.to_measure`` (stand-ins for missing or
    unreadable ones); the fingerprint covers the tables, the image contents and the settings
    (:func:`fieldcal.pipeline.input_fingerprint`).
    """
    fp = pipeline.input_fingerprint(prepared, hashes)
    return fp, lake.find_committed(fp)


def cached_observations(prepared: pipeline.Prepared, lake, hashes: dict[str, str],
                        names=None, present: set[tuple[str, str]] | None = None) -> dict[str, str]:
    """``{image: key}`` of the images (default: all with a known hash) cached in the lake.

    One read of the session's cached observation keys (:meth:`Lake.cached_keys`), whatever
    the number of images, unless they are given (``present``).
    """
    sess = prepared.session
    msettings = measure_settings(prepared)
    keys = {n: measurement_key(hashes[n], msettings) for n in (names if names is not None else hashes)
            if hashes.get(n) not in (None, MISSING, UNREADABLE)}
    if not keys:
        return {}
    if present is None:
        present = lake.cached_keys(sess.camera_id, sess.session_id)
    return {name: key for name, key in keys.items() if (name, key) in present}


def plan_session(prepared: pipeline.Prepared, lake, known: dict[str, str] | None = None, *,
                 force: bool = False, find_cached: bool = True) -> SessionPlan:
    """Decide what a run of ``prepared`` into ``lake`` has to do (see :class:`SessionPlan`).

    Parameters
    ----------
    prepared : fieldcal.pipeline.Prepared
        The validated session.
    lake : fieldcal.lake.store.Lake
    known : dict, optional
        ``{image: sha256}`` known without reading the images (e.g. remembered by file stamp).
    force : bool
        A new version is wanted: no no-op check.
    find_cached : bool
        Also look up the cached observations (False: only the no-op check, e.g. to answer a
        rerun before anything else starts).
    """
    hashes = {n: known[n] for n in prepared.to_measure if known and n in known}
    missing = missing_images(prepared, hashes)
    hashes.update({n: MISSING for n in missing})
    plan = SessionPlan(hashes=hashes, missing=missing)
    if len(hashes) == len(prepared.to_measure):
        plan.fingerprint, found = unchanged_version(prepared, lake, hashes)
        plan.not_whole = dict(lake.not_whole)
        if not force:
            plan.unchanged = found
    if plan.unchanged is not None or not find_cached:
        return plan
    plan.present = lake.cached_keys(prepared.session.camera_id, prepared.session.session_id)
    plan.cached = cached_observations(prepared, lake, hashes, present=plan.present)
    plan.todo = [n for n in prepared.to_measure if n not in missing and n not in plan.cached]
    return plan


# --------------------------------------------------------------------------------------
# measuring
# --------------------------------------------------------------------------------------
def measure_into_lake(prepared: pipeline.Prepared, name: str, lake, sha256: str | None = None) -> dict:
    """Hash (unless ``sha256`` is given), look up and, when not cached, measure one image.

    The observations go into the lake's observation tables (keyed by
    :func:`measurement_key`), with the image's own SHA-256 and the measuring settings in
    the file's metadata.

    Returns
    -------
    dict
        ``image, sha256, key, status ("measured" | "cached" | "bad"), reason, n_rows,
        hash_s, measure_s, write_s`` (times [s]).
    """
    return measure_many_into_lake(prepared, [name], lake, {name: sha256} if sha256 else None)[0]


def measure_many_into_lake(prepared: pipeline.Prepared, names: Iterable[str], lake,
                           known: dict[str, str] | None = None, *,
                           present: set[tuple[str, str]] | None = None,
                           on_image: Callable[[dict], None] | None = None,
                           append_every_s: float | None = None) -> list[dict]:
    """:func:`measure_into_lake` for several images, their observations in one lake append.

    Parameters
    ----------
    names : iterable of str
        Images to hash (unless their hash is in ``known``), look up and measure, in order
        (a list, or a generator that pulls them from a queue).
    present : set, optional
        ``(image, key)`` cached in the lake, as read by :func:`plan_session`
        (:attr:`SessionPlan.present`): an image is looked up there instead of in the lake
        (one Delta scan per image). None: ask the lake for each image. An image measured by
        two runs at once is stored twice and read once (:mod:`fieldcal.lake.observations`).
    on_image : callable, optional
        Called with each image's row as soon as the image is done (progress; its
        observations are written with the others at the end).
    append_every_s : float, optional
        Also append what is measured so far once this much time [s] went into measuring
        since the last append (a long sequence does not hold all its work until the end).

    The observations measured so far are written (one append per table,
    :meth:`Lake.write_observations_many`) when the list is done, and also when measuring
    stops on an exception, so that nothing measured is lost. Returns one row per image
    (see :func:`measure_into_lake`); ``write_s`` is the append's time shared by the
    images written.
    """
    rows, pending, work_s = [], [], 0.0
    try:
        for name in names:
            row, table = _measure_one(prepared, name, lake, (known or {}).get(name), present)
            rows.append(row)
            work_s += row["hash_s"] + row["measure_s"]
            if table is not None:
                pending.append((row, table))
            if on_image is not None:
                on_image(row)
            if append_every_s is not None and work_s >= append_every_s and pending:
                _write_pending(prepared, lake, pending)
                pending, work_s = [], 0.0
    finally:
        _write_pending(prepared, lake, pending)
    return rows


def _measure_one(prepared: pipeline.Prepared, name: str, lake, sha256: str | None,
                 present: set | None) -> tuple[dict, object]:
    """``(row, table or None)``: one image hashed (if needed), looked up and measured."""
    row = {"image": name, "sha256": sha256, "key": None, "status": None, "reason": None, "n_rows": 0,
           "hash_s": 0.0, "measure_s": 0.0, "write_s": 0.0}
    sess = prepared.session
    t = time.perf_counter()
    source = None
    if sha256 is None:
        try:     # one read, from wherever the session is: the bytes hashed here are the ones decoded below
            source = sess.read_image(name)
        except (InputError, OSError) as e:
            row.update(status="bad", reason=getattr(e, "reason", None) or one_line(e))
            return row, None
        row["sha256"] = source.sha256
        row["hash_s"] = time.perf_counter() - t
    msettings = measure_settings(prepared)
    row["key"] = key = measurement_key(row["sha256"], msettings)
    if ((name, key) in present if present is not None
            else lake.has_observations(sess.camera_id, sess.session_id, name, key)):
        row["status"] = "cached"
        return row, None
    t = time.perf_counter()
    try:
        table = pipeline.measure(prepared, name, source)
    except ImageError as e:
        row.update(status="bad", reason=e.reason, measure_s=time.perf_counter() - t)
        return row, None
    row["measure_s"] = time.perf_counter() - t
    meta = dict(table.schema.metadata or {})
    meta.update({b"fieldcal.image_sha256": row["sha256"].encode(), b"fieldcal.measure": canonical_json(msettings)})
    row.update(status="measured", n_rows=int(table.num_rows))
    return row, table.replace_schema_metadata(meta)


def _write_pending(prepared: pipeline.Prepared, lake, pending: list) -> None:
    """One lake append of the measured images' observations; each row gets its share of the time."""
    if not pending:
        return
    sess = prepared.session
    t = time.perf_counter()
    lake.write_observations_many(sess.camera_id, sess.session_id,
                                 [(row["image"], row["key"], table) for row, table in pending])
    share = (time.perf_counter() - t) / len(pending)
    for row, _ in pending:
        row["write_s"] = share


def read_observations(prepared: pipeline.Prepared, lake, keys: dict[str, str]) -> dict:
    """``{image: table}``: the cached observations of the images in ``keys`` (metadata removed).

    Raises
    ------
    LakeError
        An observation file named in ``keys`` is not in the lake (removed during the run?).
    """
    sess = prepared.session
    out = {}
    for name, key in keys.items():
        table = lake.read_observations(sess.camera_id, sess.session_id, name, key)
        if table is None:
            raise LakeError(f"the observations of {name} are missing from {lake.url} (removed during the run?)")
        meta = {k: v for k, v in (table.schema.metadata or {}).items() if k not in META_KEYS}
        out[name] = table.replace_schema_metadata(meta or None)
    return out


# --------------------------------------------------------------------------------------
# batch sizes
# --------------------------------------------------------------------------------------
def image_seconds(file_bytes: list[int]) -> float:
    """Expected work per image [s] before any is measured: :data:`PRIOR_IMAGE_S` and the mean
    file size at :data:`PRIOR_BYTES_PER_S` (files of size 0, unreadable, are left out; none
    left: 0)."""
    sizes = [int(b) for b in file_bytes if b and b > 0]
    return PRIOR_IMAGE_S + (sum(sizes) / len(sizes)) / PRIOR_BYTES_PER_S if sizes else 0.0


PIECES_PER_TASK = 4
"""Least pieces per measuring task when several tasks share a queue (:func:`pull_chunks`)."""


def pull_chunks(names: list[str], image_s: float, min_pull_s: float | None = None,
                n_tasks: int = 1) -> list[list[str]]:
    """The images, in order, in the pieces measuring tasks pull from their shared queue.

    Self-scheduling: the flow starts one measuring task per worker thread, and each takes
    the next piece whenever it is ready for one, so the threads stay busy to the end and
    finish within one piece of each other whatever the images cost, with one task (one
    Prefect task run, ~0.25 s of the worker's CPU) per thread. Each piece holds
    ``ceil(min_pull_s / image_s)`` images (one full-size frame, or ~50 of a goniometer's
    small frames), so that the pull's round trip stays small against the work, but with
    ``n_tasks`` tasks sharing the queue no more than ``ceil(len(names) / (n_tasks *
    PIECES_PER_TASK))``: every task gets work even when the estimate is low. (Small field
    frames, 5.6 MB, were estimated at 0.023 s against 0.15 s measured: 12 images went in
    one or two pieces (12, or 11 and 1), and one of two worker processes measured them;
    ``bench/README_fleet.md``.)

    Parameters
    ----------
    names : list of str
        Images to measure, in the order they are to be taken.
    image_s : float
        Expected work per image [s] (:func:`image_seconds`); 0: everything in one piece.
    min_pull_s : float, optional
        Default :data:`MIN_PULL_S`.
    n_tasks : int
        Tasks that pull from the queue (one per worker thread).
    """
    if not names:
        return []
    min_pull_s = MIN_PULL_S if min_pull_s is None else min_pull_s
    k = len(names) if image_s <= 0 else max(1, math.ceil(min_pull_s / image_s))
    if n_tasks > 1:
        k = min(k, max(1, math.ceil(len(names) / (n_tasks * PIECES_PER_TASK))))
    return [names[i:i + k] for i in range(0, len(names), k)]


def assign_batches(sizes: list[int], n_slots: int) -> list[int]:
    """The worker thread (slot) each batch is placed on: every batch, in order, on the slot
    with the fewest images so far (the first such slot on a tie).

    A Dask scheduler places tasks it cannot tell apart (one key prefix, one mean duration)
    on the worker with the fewest tasks, so a sequence 35, 18, 9, 4, 2, 1, 1 over two
    workers became 35 + 9 + 2 + 1 images against 18 + 4 + 1, and a batch waited behind
    the long one while the other worker idled, until work stealing moved it 1-2 s later
    (``bench/README_flow.md``). Placed by images instead: 35 against 18 + 9 + 4 + 2 + 1 + 1.
    (The flow's default, the images pulled from a queue by one task per thread, needs no
    placement of batches: :func:`pull_chunks`.)

    Parameters
    ----------
    sizes : list of int
        Images per batch, in submission order.
    n_slots : int
        Worker threads.

    Returns
    -------
    list of int
        Per batch, its slot (0 .. n_slots - 1).
    """
    load = [0] * max(1, int(n_slots))
    slots = []
    for size in sizes:
        k = load.index(min(load))
        load[k] += size
        slots.append(k)
    return slots
