"""Loading and validating a calibration session folder (CONTRACT section 3).

Everything is checked before anything is computed or written: the manifest against
``schemas/session.schema.json`` (errors name the JSON pointer of the bad field), every
path stays inside the session folder (no ``..``, no absolute paths, no links out), and the
CSV tables have their columns, unique ids and finite numbers (errors name file and row).
"""

from __future__ import annotations

import csv
import glob
import json
import math
import os
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from fieldcal.errors import InputError
from fieldcal.field.data import (
    DEFAULT_SIGMA_PX,
    DEFAULT_TARGET_SIGMA_MM,
    FieldData,
    FieldImage,
    FieldObservations,
    TargetField,
)
from fieldcal.model.camera import FIELD_PARAMS, GONIOMETER_PARAMS, Sensor
from fieldcal.session.schemas import validate_json

__all__ = [
    "Session", "load_session", "safe_path", "read_csv_rows", "read_targets_csv",
    "read_observations_csv", "read_marks_csv", "field_data_from_observations", "parse_acquired",
]

MANIFEST = "session.json"
OBSERVATIONS = "observations.csv"
MARKS = "marks.csv"


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
    extras: dict = field(default_factory=dict)
    check_points: tuple[str, ...] = ()

    def image_path(self, name: str) -> Path:
        """The file of an image named as in the session (checked to stay inside the folder)."""
        return safe_path(self.folder, name, "image")

    @property
    def parameter_set(self) -> tuple[str, ...]:
        """The method's set of estimable parameters (CONTRACT section 2)."""
        return FIELD_PARAMS if self.method == "field" else GONIOMETER_PARAMS


def parse_acquired(text: str, where: str) -> datetime:
    """An ISO 8601 date or date-time -> aware UTC datetime (a date means 00:00 UTC)."""
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
        return value.astimezone(UTC)
    except OverflowError:                  # e.g. 9999-12-31T23:59-23:00 is after the year 9999 in UTC
        raise InputError(f"'acquired' is out of range in UTC: {text!r} (at /acquired)", where) from None


def safe_path(folder: Path, relative: str, what: str) -> Path:
    """``folder / relative``, refused if it leaves the folder (absolute, ``..``, links out)."""
    where = str(Path(folder) / MANIFEST)
    rel = str(relative).replace("\\", "/")
    if not rel or rel.startswith("/") or os.path.isabs(rel) or (len(rel) > 1 and rel[1] == ":"):
        raise InputError(f"{what} path {relative!r} must be relative to the session folder", where)
    if ".." in rel.split("/"):
        raise InputError(f"{what} path {relative!r} leaves the session folder", where)
    if "\x00" in rel:
        raise InputError(f"{what} path {relative!r} contains a NUL character", where)
    base = Path(folder).resolve()
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


def _resolve_images(folder: Path, spec, where: str) -> list[FieldImage]:
    if isinstance(spec, str):
        safe_path(folder, spec, "images")  # the pattern itself must stay inside
        matches = sorted(glob.glob(str(Path(folder) / spec), recursive=False))
        out = []
        for m in matches:
            rel = Path(m).relative_to(folder).as_posix()
            safe_path(folder, rel, "image")
            if Path(m).is_file():
                out.append(FieldImage(rel, None))
        return out
    seen, out = set(), []
    for k, item in enumerate(spec):
        name = str(item["file"]).replace("\\", "/")
        safe_path(folder, name, f"images[{k}]")
        if name in seen:
            raise InputError(f"image {name!r} is listed twice (at /images/{k})", where)
        seen.add(name)
        out.append(FieldImage(name, item.get("station")))
    return out


def _no_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


def _unique_keys(pairs):
    keys = [k for k, _ in pairs]
    if len(set(keys)) != len(keys):
        dup = sorted({k for k in keys if keys.count(k) > 1})
        raise ValueError(f"duplicate key(s) {dup} in an object")
    return dict(pairs)


def _check_frame_paths(folder: Path, frames_path: Path) -> None:
    """Every frame that frames.csv names stays inside the session folder (path checks only)."""
    from fieldcal.goniometer.method import read_frames_csv

    frames = read_frames_csv(frames_path, strict=False)
    for name, line in zip(frames.column("file").to_pylist(), frames.column("line").to_pylist(), strict=True):
        if name:
            try:
                safe_path(folder, name, "frame")
            except InputError as err:
                raise InputError(err.reason, f"{frames_path}:{line}") from None


def load_session(folder) -> Session:
    """Read and validate ``folder/session.json`` and resolve the paths it names.

    Raises
    ------
    InputError
        One line naming the file and what is wrong (the JSON pointer for schema errors).
    """
    folder = Path(folder)
    where = str(folder / MANIFEST)
    if not folder.is_dir():
        raise InputError("session folder not found", str(folder))
    path = folder / MANIFEST
    if not path.is_file():
        raise InputError("missing (a session folder needs its session.json)", where)
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
    validate_json(manifest, "session", where)

    s = manifest["sensor"]
    sensor = Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"]))
    session_id = manifest.get("session_id") or folder.resolve().name
    if manifest.get("session_id") is None:
        validate_json({**manifest, "session_id": session_id}, "session",
                      where + f" (session_id defaults to the folder name {session_id!r})")
    method = manifest["method"]
    estimate = manifest.get("estimate")
    allowed = FIELD_PARAMS if method == "field" else GONIOMETER_PARAMS
    if estimate is not None:
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
        images=_resolve_images(folder, manifest["images"], where),
    )
    if method == "field":
        fld = manifest["field"]
        sess.targets_path = safe_path(folder, fld["targets"], "field.targets")
        if not sess.targets_path.is_file():
            raise InputError(f"the targets file {fld['targets']!r} does not exist (at /field/targets)", where)
        sess.target_diameter_mm = fld.get("target_diameter_mm")
        sess.target_polarity = fld.get("target_polarity", "dark")
        sess.coded = fld.get("coded")
        sess.check_points = tuple(str(t) for t in manifest.get("check_points") or ())
        if sess.coded is not None:
            from fieldcal.measure.coded import _dictionary

            try:
                _dictionary(sess.coded["dictionary"])
            except InputError as err:
                raise InputError(f"{err.reason} (at /field/coded/dictionary)", where) from None
        for name, attr in ((OBSERVATIONS, "observations_path"), (MARKS, "marks_path")):
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
        _check_frame_paths(folder, sess.frames_path)
    return sess


# ---------------------------------------------------------------------------- CSV tables
def read_csv_rows(path, required: tuple[str, ...], optional: tuple[str, ...] = ()):
    """Rows of a CSV file as dicts of stripped strings, with ``(line_number, row)`` pairs.

    Checks the header has every required column (extra columns are ignored) and that the
    file has at least one data row. Raises :class:`InputError` naming the file.
    """
    where = str(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header is None:
                raise InputError("empty file (expected a header line "
                                 f"{','.join(required + optional)})", where)
            header = [h.strip() for h in header]
            missing = [c for c in required if c not in header]
            if missing:
                raise InputError(f"missing column(s) {missing}; header is {header}", where)
            dup = sorted({h for h in header if header.count(h) > 1})
            if dup:
                raise InputError(f"duplicate column(s) {dup} in the header", where)
            idx = {c: header.index(c) for c in required + optional if c in header}
            rows = []
            for line_no, rec in enumerate(reader, start=2):
                if not rec or all(not x.strip() for x in rec):
                    continue
                if len(rec) < len(header):
                    rec = rec + [""] * (len(header) - len(rec))
                elif len(rec) > len(header):
                    raise InputError(f"row has {len(rec)} fields, the header has {len(header)}",
                                     f"{where}:{line_no}")
                rows.append((line_no, {c: rec[i].strip() for c, i in idx.items()}))
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", where) from None
    except csv.Error as err:
        raise InputError(f"not a valid CSV file ({err})", where) from None
    if not rows:
        raise InputError("no data rows", where)
    return rows


def _number(text: str, column: str, where: str, *, default=None) -> float:
    if text == "":
        if default is None:
            raise InputError(f"empty value in column {column!r}", where)
        return default
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{column!r} is not a number: {text!r}", where) from None
    if not math.isfinite(value):
        raise InputError(f"{column!r} is not finite: {text!r}", where)
    return value


def read_targets_csv(path) -> TargetField:
    """``targets.csv``: ``id,X,Y,Z,sigma_mm,code`` (X, Y, Z [m]; empty sigma_mm: 5 mm; empty code: plain)."""
    rows = read_csv_rows(path, ("id", "X", "Y", "Z"), ("sigma_mm", "code"))
    ids, xyz, sig, codes = [], [], [], []
    first_row: dict[str, int] = {}
    code_row: dict[int, int] = {}
    for line, r in rows:
        where = f"{path}:{line}"
        tid = r["id"]
        if not tid:
            raise InputError("empty target id", where)
        if tid in first_row:
            raise InputError(f"duplicate target id {tid!r} (first on line {first_row[tid]})", where)
        first_row[tid] = line
        xyz.append([_number(r[c], c, where) for c in ("X", "Y", "Z")])
        s = _number(r.get("sigma_mm", ""), "sigma_mm", where, default=DEFAULT_TARGET_SIGMA_MM)
        if s <= 0:
            raise InputError(f"sigma_mm must be positive, got {s}", where)
        sig.append(s)
        c = r.get("code", "")
        if c == "":
            codes.append(-1)
        else:
            try:
                code = int(c)
            except ValueError:
                raise InputError(f"'code' must be an ArUco id (a whole number), got {c!r}", where) from None
            if code < 0:
                raise InputError(f"'code' must be >= 0, got {code}", where)
            if code in code_row:
                raise InputError(f"code {code} already used on line {code_row[code]}", where)
            code_row[code] = line
            codes.append(code)
        ids.append(tid)
    return TargetField(np.array(ids), np.array(xyz), np.array(sig), np.array(codes))


def _image_index(images: list[FieldImage], allow_new: bool):
    index = {im.file: i for i, im in enumerate(images)}

    def lookup(name: str, where: str) -> int:
        name = name.replace("\\", "/")
        if name in index:
            return index[name]
        if not allow_new:
            raise InputError(f"image {name!r} is not one of the session's images", where)
        index[name] = len(images)
        images.append(FieldImage(name, None))
        return index[name]

    return lookup


def _image_target_rows(path, rows, targets: TargetField, images: list[FieldImage], allow_new: bool,
                       verb: str):
    """Yield ``(where, row, image index, target index)`` of ``image,target_id,...`` rows.

    Refuses an unknown image or target and a (image, target) pair given twice
    ("target 'T7' observed twice in 'images/a.tif'"); ``where`` is ``path:line``.
    """
    tindex = targets.index()
    lookup = _image_index(images, allow_new)
    seen: dict[tuple[int, int], int] = {}
    for line, r in rows:
        where = f"{path}:{line}"
        i = lookup(r["image"], where)
        if r["target_id"] not in tindex:
            raise InputError(f"target_id {r['target_id']!r} is not in targets.csv", where)
        t = tindex[r["target_id"]]
        if (i, t) in seen:
            raise InputError(f"target {r['target_id']!r} {verb} twice in {images[i].file!r} "
                             f"(first on line {seen[(i, t)]})", where)
        seen[(i, t)] = line
        yield where, r, i, t


def read_observations_csv(path, targets: TargetField, images: list[FieldImage], *,
                          default_sigma_px: float, allow_new_images: bool, sensor: Sensor | None = None):
    """``observations.csv``: ``image,target_id,u,v,sigma_px`` -> :class:`FieldObservations`.

    ``images`` is extended in place with images the file names (when ``allow_new_images``,
    i.e. the manifest's glob matched no file). A (image, target) pair may appear once.
    With ``sensor``, a point must lie on the image (``[-0.5, W-0.5] x [-0.5, H-0.5]`` px,
    CONTRACT section 1).
    """
    rows = read_csv_rows(path, ("image", "target_id", "u", "v"), ("sigma_px",))
    img, tgt, uv, sig = [], [], [], []
    for where, r, i, t in _image_target_rows(path, rows, targets, images, allow_new_images, "observed"):
        s = _number(r.get("sigma_px", ""), "sigma_px", where, default=default_sigma_px)
        if s <= 0:
            raise InputError(f"sigma_px must be positive, got {s}", where)
        u, v = _number(r["u"], "u", where), _number(r["v"], "v", where)
        if sensor is not None and not (-0.5 <= u <= sensor.width_px - 0.5 and -0.5 <= v <= sensor.height_px - 0.5):
            raise InputError(f"point ({u:g}, {v:g}) px is outside the {sensor.width_px} x "
                             f"{sensor.height_px} px image", where)
        img.append(i)
        tgt.append(t)
        uv.append((u, v))
        sig.append(s)
    return FieldObservations(np.array(img), np.array(tgt), np.array(uv), np.array(sig))


def read_marks_csv(path, targets: TargetField, images: list[FieldImage]) -> dict[int, tuple]:
    """``marks.csv``: ``image,target_id,u,v`` -> ``{image index: (target indices, uv (n,2))}``."""
    rows = read_csv_rows(path, ("image", "target_id", "u", "v"))
    out: dict[int, list] = {}
    for where, r, i, t in _image_target_rows(path, rows, targets, images, False, "marked"):
        out.setdefault(i, []).append((t, _number(r["u"], "u", where), _number(r["v"], "v", where)))
    result = {}
    for i, items in out.items():
        t = np.array([x[0] for x in items])
        result[i] = (t, np.array([(x[1], x[2]) for x in items]))
    return result


def field_data_from_observations(sess: Session) -> FieldData:
    """The :class:`FieldData` of a field session that carries ``observations.csv``."""
    if sess.method != "field":
        raise InputError("not a field-method session", str(sess.folder / MANIFEST))
    if sess.observations_path is None:
        raise InputError("no observations.csv in the session", str(sess.folder))
    targets = read_targets_csv(sess.targets_path)
    images = list(sess.images)
    allow_new = isinstance(sess.manifest["images"], str) and not images
    obs = read_observations_csv(sess.observations_path, targets, images,
                                default_sigma_px=sess.default_sigma_px, allow_new_images=allow_new,
                                sensor=sess.sensor)
    return FieldData(sensor=sess.sensor, targets=targets, images=images, obs=obs,
                     nominal_focal_mm=sess.nominal_focal_mm, default_sigma_px=sess.default_sigma_px,
                     meta={"camera_id": sess.camera_id, "session_id": sess.session_id})
