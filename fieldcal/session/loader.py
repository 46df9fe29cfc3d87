"""Loading and validating a calibration session folder (docs/conventions.md section 3).

Everything is checked before anything is computed or written: the manifest against
``schemas/session.schema.json`` (errors name the JSON pointer of the bad field), every
path stays inside the session folder (no ``..``, no absolute paths, no links out), every
photograph is listed once, and the CSV tables (:mod:`fieldcal.session.tables`) have their
columns, unique ids and finite numbers (errors name file and row).

- ``session_id`` defaults to the name of the session folder as given (not following a
  link): :func:`default_session_id`, the one place that says so.
- An image is named by its path relative to the session folder in one spelling
  (:func:`fieldcal.contract.names.normal_file_name`). Two entries that are one photograph
  are refused: the same name spelled twice (``images/a.tif``, ``images/./a.tif``), the same
  file reached twice (a symbolic or hard link), or two files with the same bytes (a copy).
  Copies are found by size, then a 64 KiB sample from the middle of the file, then the
  SHA-256 of the whole file; only files that agree on the first two are read whole. The
  same photograph in another encoding (other compression, a byte appended, tiles instead
  of strips) has other bytes but the same pixels: a band of rows in the middle of every
  image is decoded, and images whose bands agree are decoded whole and compared by the
  SHA-256 of their pixels (issue 24).
- The ``images`` glob is matched inside the session folder (the folder's own name is
  never a pattern: ``runs/g[1]`` is a folder, not a choice of ``g1``).
- A session on an object store (:mod:`fieldcal.session.store`) is loaded from a local
  folder holding its small files only, with its :class:`~fieldcal.session.store.SessionStore`
  (``store``): the images are matched, found and compared in the store's listing, and read
  from the store where they are measured (:meth:`Session.read_image`); the tables the
  later steps need are read into memory at once (:meth:`Session.marks`, ...), so that the
  session works after its local folder is gone, on any machine.
"""

from __future__ import annotations

import copy
import glob
import hashlib
import itertools
import json
import os
import posixpath
import stat
from collections import defaultdict
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from fieldcal.contract.fingerprint import sha256_file
from fieldcal.contract.names import normal_file_name
from fieldcal.contract.schemas import shown, validate_json
from fieldcal.errors import InputError
from fieldcal.measure.imageio import ImageFile, read_file
from fieldcal.model.camera import FIELD_PARAMS, GONIOMETER_PARAMS, Sensor
from fieldcal.session.data import DEFAULT_SIGMA_PX, FieldData, FieldImage, ScaleBars, TargetField, normal_problem
from fieldcal.session.store import SessionStore, distinct_by_md5, glob_names, sample_digest
from fieldcal.session.tables import (
    MARKS_COLUMNS,
    MAX_IMAGES,
    check_size,
    read_csv_table,
    read_marks_csv,
    read_observations_csv,
    read_scale_bars_csv,
    read_targets_csv,
)

__all__ = [
    "Session", "load_session", "safe_path", "default_session_id", "check_distinct_files",
    "read_targets_csv", "read_observations_csv", "read_marks_csv", "field_data_from_observations",
    "parse_acquired", "read_manifest", "check_acquired_not_ahead", "ACQUIRED_AHEAD", "with_field_normal",
]

MANIFEST = "session.json"
OBSERVATIONS = "observations.csv"
MARKS = "marks.csv"
SCALE_BARS = "scale_bars.csv"


@dataclass
class Session:
    """A validated session folder.

    Attributes
    ----------
    folder : Path
        The session folder (resolved).
    manifest : dict
        session.json as read.
    images : list of FieldImage
        Images named as the session lists them (relative paths, forward slashes); for a glob,
        the matching files in sorted order.
    store : SessionStore or None
        Where the images are when the session is on an object store (``folder`` then holds
        its small files only, while it is loaded); None: in ``folder``.
    """

    folder: Path
    manifest: dict
    method: str
    camera_id: str
    session_id: str
    acquired: datetime
    sensor: Sensor
    nominal_focal_mm: float | None
    default_sigma_px: float
    estimate: tuple[str, ...] | None
    images: list[FieldImage]
    targets_path: Path | None = None
    observations_path: Path | None = None
    marks_path: Path | None = None
    frames_path: Path | None = None
    target_diameter_mm: float | None = None
    target_polarity: str = "dark"
    coded: dict | None = None
    target_normal: tuple[float, float, float] | None = None
    extras: dict = field(default_factory=dict)
    check_points: tuple[str, ...] = ()
    store: SessionStore | None = None
    scale_bars_path: Path | None = None
    strict_targets: bool = False
    datum: str = "auto"
    board_model: str = "auto"
    _read: dict = field(default_factory=dict, repr=False, compare=False)   # tables read once

    def targets(self) -> TargetField:
        """targets.csv of a field session, read once (every call returns a fresh copy)."""
        if self.targets_path is None:
            raise InputError("not a field-method session (no targets.csv)", str(self.folder / MANIFEST))
        if "targets" not in self._read:
            self._read["targets"] = with_field_normal(read_targets_csv(self.targets_path), self.target_normal)
        return copy.deepcopy(self._read["targets"])

    def marks(self, targets: TargetField | None = None) -> dict:
        """marks.csv of a field session over ``targets`` (default: :meth:`targets`)
        (:func:`read_marks_csv`); the file is read once, so this works where the session's
        folder is not (a worker); ``{}`` without one."""
        if self.marks_path is None:
            return {}
        if "marks.csv" not in self._read:
            self._read["marks.csv"] = read_csv_table(self.marks_path, MARKS_COLUMNS, kind="marks.csv")
        return read_marks_csv(self.marks_path, self.targets() if targets is None else targets, list(self.images),
                              table=self._read["marks.csv"])

    def image_path(self, name: str) -> Path:
        """The local file of an image named as in the session (checked to stay inside the
        folder). A session on an object store has none: :meth:`read_image`."""
        if self.store is not None:
            raise InputError(f"image {name!r} is on an object store, not a local file", self.store.url_of(name))
        return safe_path(self.folder, name, "image")

    @property
    def location(self) -> str:
        """The session folder as a user named it: its local path or its URL."""
        return self.store.url if self.store is not None else str(self.folder)

    @property
    def manifest_where(self) -> str:
        """session.json's path or URL, for messages."""
        return self.store.url_of(MANIFEST) if self.store is not None else str(self.folder / MANIFEST)

    def read_image(self, name: str) -> ImageFile:
        """An image's bytes, read once and hashed as read, from wherever the session is
        (:func:`fieldcal.measure.imageio.read_file`, :meth:`SessionStore.read_image`)."""
        if self.store is not None:
            safe_path(self.folder, name, "image")          # the name's checks; nothing is read here
            return self.store.read_image(name)
        return read_file(self.image_path(name))

    def image_size(self, name: str) -> int:
        """An image file's size [bytes] as listed or stat'ed; 0 when it cannot be told."""
        if self.store is not None:
            return int(self.store.files.get(name, 0))
        try:
            return os.stat(self.image_path(name)).st_size
        except (OSError, ValueError, InputError):
            return 0

    def missing_image(self, name: str) -> str | None:
        """Why an image cannot be read (``"file not found"``, ``"not a regular file"``), or None."""
        if self.store is not None:
            if name in self.store.files:
                return None
            return "not a regular file" if self.store.has_folder(name) else "file not found"
        path = self.image_path(name)
        if os.path.isfile(path):
            return None
        return "file not found" if not os.path.lexists(path) else "not a regular file"

    def has_image_folder(self, name: str) -> bool:
        """Whether the folder an image is listed in exists (on a store: holds some file)."""
        if self.store is not None:
            return self.store.has_folder(posixpath.dirname(name))
        return self.image_path(name).parent.is_dir()

    @property
    def parameter_set(self) -> tuple[str, ...]:
        """The method's set of estimable parameters (docs/conventions.md section 2)."""
        return FIELD_PARAMS if self.method == "field" else GONIOMETER_PARAMS


ACQUIRED_AHEAD = timedelta(days=1)
"""How far after now a session's ``acquired`` may be (clocks and time zones); later is a typo
that would stay the camera's latest calibration until then (docs/reliability_inputs.md)."""


def check_acquired_not_ahead(acquired: datetime, now: datetime, where: str) -> None:
    """InputError when ``acquired`` is more than :data:`ACQUIRED_AHEAD` after ``now``."""
    if acquired > now + ACQUIRED_AHEAD:
        raise InputError(f"'acquired' {acquired.isoformat().replace('+00:00', 'Z')} is after now "
                         f"({now.replace(microsecond=0).isoformat().replace('+00:00', 'Z')}) plus "
                         f"{ACQUIRED_AHEAD.days} day: a typo? (at /acquired)", where)


def with_field_normal(targets: TargetField, normal) -> TargetField:
    """``targets`` with the session's ``field.target_normal`` for every target whose normal
    targets.csv does not give (per-target normals take precedence, docs/conventions.md section 3)."""
    if normal is None:
        return targets
    N = np.full((len(targets), 3), np.nan) if targets.normals is None else targets.normals.copy()
    unknown = ~np.isfinite(N).all(axis=1)
    N[unknown] = np.asarray(normal, float)
    return replace(targets, normals=N)


def parse_acquired(text: str, where: str) -> datetime:
    """An ISO 8601 date or date-time -> aware UTC datetime (a date means 00:00 UTC).

    A time more than :data:`ACQUIRED_AHEAD` after now is refused (:func:`check_acquired_not_ahead`)."""
    t = text.strip()
    if t.endswith("Z"):
        t = t[:-1] + "+00:00"
    try:
        value = datetime.fromisoformat(t)
    except ValueError:
        raise InputError(f"'acquired' is not an ISO 8601 date or time: {text!r} (at /acquired)",
                         where) from None
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    try:
        value = value.astimezone(UTC)
    except OverflowError:                  # e.g. 9999-12-31T23:59-23:00 is after the year 9999 in UTC
        raise InputError(f"'acquired' is out of range in UTC: {text!r} (at /acquired)", where) from None
    check_acquired_not_ahead(value, datetime.now(UTC), where)
    return value


def safe_path(folder: Path, relative: str, what: str, *, base: Path | None = None) -> Path:
    """``folder / relative``, refused if it leaves the folder (absolute, ``..``, links out).

    ``base``: ``Path(folder).resolve()`` when the caller has it already (checking many
    paths of one folder resolves the folder once)."""
    where = str(Path(folder) / MANIFEST)
    rel = str(relative).replace("\\", "/")
    if not rel or rel.startswith("/") or os.path.isabs(rel) or (len(rel) > 1 and rel[1] == ":"):
        raise InputError(f"{what} path {relative!r} must be relative to the session folder", where)
    if ".." in rel.split("/"):
        raise InputError(f"{what} path {relative!r} leaves the session folder", where)
    if "\x00" in rel:
        raise InputError(f"{what} path {relative!r} contains a NUL character", where)
    base = Path(folder).resolve() if base is None else base
    full = (base / rel)
    try:
        resolved = full.resolve()
        full.exists()                      # surfaces a name the OS refuses (too long, ...)
    except (OSError, RuntimeError) as err:  # RuntimeError: a symlink loop
        raise InputError(f"{what} path {relative!r} cannot be used: "
                         f"{getattr(err, 'strerror', None) or err}", where) from None
    if resolved != base and base not in resolved.parents:
        raise InputError(f"{what} path {relative!r} leads outside the session folder (link?)", where)
    return full


def _resolve_images(folder: Path, spec, where: str, store: SessionStore | None = None) -> list[FieldImage]:
    """The session's images, named in their one spelling (module docstring); none listed twice."""
    if isinstance(spec, str):
        safe_path(folder, spec, "images")  # the pattern itself must stay inside
        pattern = spec.replace("\\", "/")
        if store is not None:
            matches = glob_names(pattern, store.files)[:MAX_IMAGES + 1]
        else:
            matches = sorted(itertools.islice(glob.iglob(pattern, root_dir=folder), MAX_IMAGES + 1))
        if len(matches) > MAX_IMAGES:
            raise InputError(f"images {shown(spec)} matches more than {MAX_IMAGES} files (fieldcal's "
                             "limit for one session) (at /images)", where)
        out = []
        base = Path(folder).resolve()
        for rel in matches:
            safe_path(folder, rel, "image", base=base)
            if (rel in store.files) if store is not None else (folder / rel).is_file():
                out.append(FieldImage(normal_file_name(rel, "image", where), None))
        return out
    first: dict[str, int] = {}
    out = []
    base = Path(folder).resolve()
    for k, item in enumerate(spec):
        safe_path(folder, item["file"].replace("\\", "/"), f"images[{k}]", base=base)
        name = normal_file_name(item["file"], f"images[{k}]", where)
        if name in first:
            spelled = "" if item["file"] == name else f" (as {shown(item['file'])})"
            raise InputError(f"image {shown(name)} is listed twice{spelled}: at /images/{first[name]} "
                             f"and /images/{k}", where)
        first[name] = k
        out.append(FieldImage(name, item.get("station")))
    return out


def _sample_digest(path: Path, size: int) -> str:
    """SHA-256 of at most 64 KiB from the middle of a file (where photographs differ)."""
    n = min(size, 1 << 16)
    with open(path, "rb") as fh:
        fh.seek((size - n) // 2)
        return hashlib.sha256(fh.read(n)).hexdigest()


def check_distinct_files(folder: Path, names: list[str], where: str, what: str = "image",
                         store: SessionStore | None = None) -> None:
    """Refuse two names of one photograph: one file reached twice (a link), the same bytes, or the
    same decoded pixels (another encoding).

    Parameters
    ----------
    folder : Path
        The session folder.
    names : list of str
        Session-relative names in their normal spelling, each once.
    where : str
        The file that lists them, for the message.

    Files that are missing, empty or not regular are skipped here: measuring reports them.
    Only files of equal size whose middle 64 KiB agree are read whole (module docstring);
    then the same pixels in another encoding (:func:`_check_distinct_pixels`).
    With a ``store`` the sizes come from its listing, files its MD5s tell apart are not read
    (:func:`fieldcal.session.store.distinct_by_md5`), and the samples are ranged reads (an
    object store has no links); the pixels are not compared there (that would read every
    image on the flow's machine: docs/deployment.md).
    """
    if store is not None:
        known = distinct_by_md5(store, names)
        sizes = {n: store.files[n] for n in names if store.files.get(n) and n not in known}
        _same_bytes(sizes, lambda n, size: sample_digest(store, n, size), store.sha256, where, what)
        return
    by_file: dict[tuple[int, int], str] = {}
    by_size: dict[str, int] = {}
    for name in names:
        try:
            st = os.stat(folder / name)
        except (OSError, ValueError):
            continue
        if not stat.S_ISREG(st.st_mode) or st.st_size == 0:
            continue
        key = (st.st_dev, st.st_ino)
        if key in by_file:
            raise InputError(f"{what} {shown(name)} is the file {shown(by_file[key])} again (a link): "
                             "a photograph counts once", where)
        by_file[key] = name
        by_size[name] = st.st_size
    _same_bytes(by_size, lambda n, size: _sample_digest(folder / n, size), lambda n: sha256_file(folder / n),
                where, what)
    _check_distinct_pixels(folder, list(by_size), where, what)


def _same_bytes(sizes: dict[str, int], sample, whole, where: str, what: str) -> None:
    """Refuse two names of equal bytes: by ``sizes`` ``{name: size}``, then ``sample(name,
    size)`` (digest of the middle), then ``whole(name)`` (SHA-256) for those that agree."""
    by_size: dict[int, list[str]] = defaultdict(list)
    for name, size in sizes.items():
        by_size[size].append(name)
    for size, group in by_size.items():
        if len(group) < 2:
            continue
        by_sample: dict[str, list[str]] = defaultdict(list)
        for name in group:
            try:
                by_sample[sample(name, size)].append(name)
            except OSError:                  # unreadable: measuring reports it
                continue
        for same in (g for g in by_sample.values() if len(g) > 1):
            by_hash: dict[str, str] = {}
            for name in same:
                try:
                    h = whole(name)
                except (OSError, InputError):
                    continue
                if h in by_hash:
                    raise InputError(f"{what} {shown(name)} has the same bytes as {shown(by_hash[h])} "
                                     f"(SHA-256 {h[:12]}...): a photograph counts once", where)
                by_hash[h] = name


def _check_distinct_pixels(folder: Path, names: list[str], where: str, what: str) -> None:
    """Refuse two files with the same decoded pixels: one photograph in two encodings (another
    compression, a byte appended, striped or tiled), which would count twice and shrink the
    sigmas. Every image's middle band of rows is decoded
    (:func:`fieldcal.measure.imageio.pixel_sample_digest`: only its strips or tiles are read);
    images whose bands agree are decoded whole and compared by the SHA-256 of their pixels."""
    from fieldcal.measure.imageio import pixel_digest, pixel_sample_digest

    by_sample: dict[str, list[str]] = defaultdict(list)
    for name in names:
        d = pixel_sample_digest(folder / name)
        if d is not None:
            by_sample[d].append(name)
    for same in (g for g in by_sample.values() if len(g) > 1):
        by_pixels: dict[str, str] = {}
        for name in same:
            h = pixel_digest(folder / name)
            if h is None:
                continue
            if h in by_pixels:
                raise InputError(f"{what} {shown(name)} has the same pixels as {shown(by_pixels[h])} in another "
                                 f"encoding (pixels' SHA-256 {h[:12]}...): a photograph counts once", where)
            by_pixels[h] = name


def default_session_id(manifest: dict, folder) -> str:
    """The session's id: the manifest's ``session_id``, else the name of the session folder.

    The folder's name is taken as given (``os.path.abspath``, not following links), so a
    folder and the fleet's scan of it (:mod:`flows.fleet`) agree. This is the one place that
    defines the default (docs/conventions.md section 3).
    """
    sid = manifest.get("session_id")
    if sid is not None:
        return sid
    return os.path.basename(os.path.abspath(os.fspath(folder)).rstrip("/"))


def _no_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def _unique_keys(pairs):
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise ValueError(f"duplicate key(s) {dup} in an object")
    return dict(pairs)


def _check_frame_paths(folder: Path, frames_path: Path, store: SessionStore | None = None) -> None:
    """Every frame that frames.csv names stays inside the session folder (path checks only)."""
    from fieldcal.session.frames import read_frames_csv

    check_size(frames_path, "frames.csv")
    frames = read_frames_csv(frames_path, strict=False)
    if frames.num_rows > MAX_IMAGES:
        raise InputError(f"more than {MAX_IMAGES} frames (fieldcal's limit for one session)", str(frames_path))
    first: dict[str, int] = {}
    for name, line in zip(frames.column("file").to_pylist(), frames.column("line").to_pylist(), strict=True):
        if name:
            try:
                safe_path(folder, name, "frame")
                normal = normal_file_name(name, "frame")
            except InputError as err:
                raise InputError(err.reason, f"{frames_path}:{line}") from None
            if normal in first:
                raise InputError(f"frame {shown(normal)} is listed twice (as {shown(name)}; first on line "
                                 f"{first[normal]})", f"{frames_path}:{line}")
            first[normal] = line
    check_distinct_files(folder, list(first), str(frames_path), "frame", store)


def read_manifest(folder) -> dict:
    """``folder/session.json`` parsed as strict JSON (no NaN, no duplicate keys), not yet
    validated against the schema.

    Raises
    ------
    InputError
        The folder or its manifest is missing, too large, or not a JSON object.
    """
    folder = Path(folder)
    where = str(folder / MANIFEST)
    if not folder.is_dir():
        raise InputError("session folder not found", str(folder))
    path = folder / MANIFEST
    if not path.is_file():
        raise InputError("missing (a session folder needs its session.json)", where)
    check_size(path, MANIFEST, where)
    try:
        manifest = json.loads(path.read_text(encoding="utf-8-sig"), parse_constant=_no_constant,
                              object_pairs_hook=_unique_keys)
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", where) from None
    except json.JSONDecodeError as err:
        raise InputError(f"invalid JSON: {err.msg} at line {err.lineno} column {err.colno}", where) from None
    except (ValueError, RecursionError) as err:    # NaN, duplicate keys, huge numbers, deep nesting
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(f"invalid JSON: {text[:200]}", where) from None
    if not isinstance(manifest, dict):
        raise InputError("must be a JSON object", where)
    return manifest


def load_session(folder, store: SessionStore | None = None) -> Session:
    """Read and validate ``folder/session.json`` and resolve the paths it names.

    ``store``: the session is on an object store and ``folder`` holds its small files
    (module docstring).

    Raises
    ------
    InputError
        One line naming the file and what is wrong (the JSON pointer for schema errors).
    """
    folder = Path(folder)
    where = str(folder / MANIFEST)
    manifest = read_manifest(folder)
    validate_json(manifest, "session", where)
    if "rig" in manifest:
        raise InputError("a rig session (it has a 'rig'): read it with fieldcal.rig.load_rig_session", where)

    s = manifest["sensor"]
    sensor = Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"]))
    session_id = default_session_id(manifest, folder)
    if manifest.get("session_id") is None:
        validate_json({**manifest, "session_id": session_id}, "session",
                      where + f" (session_id defaults to the folder name {session_id!r})")
    method = manifest["method"]
    estimate = manifest.get("estimate")
    allowed = FIELD_PARAMS if method == "field" else GONIOMETER_PARAMS
    if estimate is not None:
        if not estimate:
            raise InputError(f"estimate is empty: a calibration must estimate some of {list(allowed)} "
                             "(leave 'estimate' out for the method's full set) (at /estimate)", where)
        bad = [p for p in estimate if p not in allowed]
        if bad:
            raise InputError(f"estimate names {bad}, not estimable by the {method} method "
                             f"(allowed: {list(allowed)}) (at /estimate)", where)
    sess = Session(
        folder=folder, manifest=manifest, method=method, camera_id=manifest["camera_id"],
        session_id=session_id, acquired=parse_acquired(manifest["acquired"], where),
        sensor=sensor, nominal_focal_mm=(manifest.get("lens") or {}).get("nominal_focal_mm"),
        default_sigma_px=float(manifest.get("default_sigma_px", DEFAULT_SIGMA_PX)),
        estimate=tuple(estimate) if estimate is not None else None,
        images=_resolve_images(folder, manifest["images"], where, store), store=store,
    )
    if method == "field":
        fld = manifest["field"]
        sess.targets_path = safe_path(folder, fld["targets"], "field.targets")
        if not sess.targets_path.is_file():
            raise InputError(f"the targets file {fld['targets']!r} does not exist (at /field/targets)", where)
        sess.target_diameter_mm = fld.get("target_diameter_mm")
        sess.target_polarity = fld.get("target_polarity", "dark")
        sess.coded = fld.get("coded")
        if fld.get("target_normal") is not None:
            if (why := normal_problem(fld["target_normal"])) is not None:
                raise InputError(f"field.target_normal {why} (at /field/target_normal)", where)
            n = np.asarray(fld["target_normal"], float)
            sess.target_normal = tuple(float(x) for x in n / np.linalg.norm(n))
        sess.check_points = tuple(str(t) for t in manifest.get("check_points") or ())
        sess.strict_targets = bool(fld.get("strict_targets", False))
        sess.datum = str(fld.get("datum", "auto"))
        sess.board_model = str(fld.get("board_model", "auto"))     # fieldcal.field.board (beyond the contract)
        if sess.coded is not None:
            from fieldcal.measure.coded import aruco_dictionary

            try:
                aruco_dictionary(sess.coded["dictionary"])
            except InputError as err:
                raise InputError(f"{err.reason} (at /field/coded/dictionary)", where) from None
        check_distinct_files(folder, [im.file for im in sess.images], where, store=store)
        for name, attr in ((OBSERVATIONS, "observations_path"), (MARKS, "marks_path"),
                           (SCALE_BARS, "scale_bars_path")):
            p = safe_path(folder, name, name)
            if p.is_file():
                setattr(sess, attr, p)
    else:
        if manifest.get("check_points"):
            raise InputError("check_points are surveyed targets of the field method; a goniometer "
                             "session has none (at /check_points)", where)
        sess.frames_path = safe_path(folder, manifest["frames"], "frames")
        if not sess.frames_path.is_file():
            raise InputError(f"the frames file {manifest['frames']!r} does not exist (at /frames)", where)
        _check_frame_paths(folder, sess.frames_path, store)
    return sess


def field_data_from_observations(sess: Session) -> FieldData:
    """The :class:`FieldData` of a field session that carries ``observations.csv``."""
    if sess.method != "field":
        raise InputError("not a field-method session", str(sess.folder / MANIFEST))
    if sess.observations_path is None:
        raise InputError("no observations.csv in the session", str(sess.folder))
    targets = sess.targets()
    if "observations" not in sess._read:
        images = list(sess.images)
        allow_new = isinstance(sess.manifest["images"], str) and not images
        unlisted = None if sess.strict_targets else []
        obs = read_observations_csv(sess.observations_path, targets, images,
                                    default_sigma_px=sess.default_sigma_px, allow_new_images=allow_new,
                                    sensor=sess.sensor, unlisted=unlisted)
        sess._read["observations"] = (images, obs, unlisted or [])
    images, obs, unlisted = copy.deepcopy(sess._read["observations"])
    targets = targets.with_unsurveyed(unlisted)
    meta = {"camera_id": sess.camera_id, "session_id": sess.session_id}
    if unlisted:
        meta["unlisted_targets"] = list(unlisted)
    return FieldData(sensor=sess.sensor, targets=targets, images=images, obs=obs,
                     nominal_focal_mm=sess.nominal_focal_mm, default_sigma_px=sess.default_sigma_px,
                     meta=meta, scale_bars=scale_bars_of(sess, targets))


def scale_bars_of(sess: Session, targets: TargetField) -> ScaleBars | None:
    """``scale_bars.csv`` of the session over ``targets`` (None when the session has none)."""
    if sess.scale_bars_path is None:
        return None
    return read_scale_bars_csv(sess.scale_bars_path, targets)


def scale_bars_among(sess: Session, targets: TargetField) -> ScaleBars | None:
    """The bars of ``scale_bars.csv`` (over the session's targets.csv, :func:`scale_bars_of`)
    whose two ends are among ``targets`` (by id), as indices into ``targets``: from photographs
    the adjustment holds the targets found in the images, a subset (None: no file or no such
    bar)."""
    listed = sess.targets()
    bars = scale_bars_of(sess, listed)
    if bars is None:
        return None
    index = targets.index()
    a = np.array([index.get(str(listed.ids[k]), -1) for k in bars.from_target], np.int64)
    b = np.array([index.get(str(listed.ids[k]), -1) for k in bars.to_target], np.int64)
    keep = (a >= 0) & (b >= 0)
    if not keep.any():
        return None
    return ScaleBars(a[keep], b[keep], bars.length_mm[keep], bars.sigma_mm[keep])
