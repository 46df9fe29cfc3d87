"""Loading and validating a rig session (CONTRACT section 3, "Rig sessions").

A rig session is a field session whose ``session.json`` has a ``rig`` (its id, its heads with
their sensors and nominal lenses, the reference head) in place of ``camera_id``, ``sensor``
and ``lens``, and whose ``images`` are a list in which every image names its head
(``camera``) and its exposure (``exposure``). Checked before anything is computed or written,
each failure one :class:`~fieldcal.errors.InputError` naming the file and the JSON pointer:

- the manifest against ``schemas/session.schema.json`` (which holds the rig's shape);
- head ids unique, the reference one of them, every image's ``camera`` a head of the rig;
- a head has at most one image per exposure, every head and the reference at least one image;
- paths as for one camera (:func:`fieldcal.session.loader.safe_path`, one photograph listed once);
- no free network (``field.datum``) and no ``scale_bars.csv``: a rig's datum is its surveyed
  targets (weighted control); unsurveyed targets (empty X, Y, Z, or ids targets.csv does not list
  unless ``field.strict_targets``) are estimated as for one camera.

The observations (``observations.csv``) name images as the manifest lists them; each point
must lie on its own head's sensor.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np

from fieldcal.contract.names import normal_file_name
from fieldcal.contract.schemas import shown, validate_json
from fieldcal.errors import InputError
from fieldcal.model.camera import FIELD_PARAMS, Sensor
from fieldcal.rig.data import RigData, RigHead
from fieldcal.session.data import DEFAULT_SIGMA_PX, FieldData, FieldImage, FieldObservations
from fieldcal.session.loader import (
    MANIFEST,
    OBSERVATIONS,
    SCALE_BARS,
    check_distinct_files,
    default_session_id,
    parse_acquired,
    read_manifest,
    read_observations_csv,
    read_targets_csv,
    safe_path,
)
from fieldcal.session.store import SessionStore, is_url

__all__ = ["RigSession", "load_rig_session", "rig_data_from_observations", "is_rig_session"]


@dataclass
class RigSession:
    """A validated rig session folder.

    Attributes
    ----------
    images : list of FieldImage
        Every image of the session, in the manifest's order.
    image_head, image_exposure : (n_images,) int ndarray
        Per image, the index of its head (into ``heads``) and of its exposure (into ``exposures``).
    """

    folder: Path
    manifest: dict
    rig_id: str
    session_id: str
    acquired: datetime
    heads: list[RigHead]
    reference: int
    exposures: list[str]
    images: list[FieldImage]
    image_head: np.ndarray
    image_exposure: np.ndarray
    default_sigma_px: float
    estimate: tuple[str, ...] | None
    targets_path: Path
    observations_path: Path | None = None
    target_diameter_mm: float | None = None
    target_polarity: str = "dark"
    coded: dict | None = None
    strict_targets: bool = False
    store: SessionStore | None = None
    _read: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def where(self) -> str:
        return str(self.folder / MANIFEST)

    def read_image(self, name: str):
        """An image of a session on an object store, read from the store (the bytes hashed as they
        arrive, :meth:`fieldcal.session.store.SessionStore.read_image`); None for a local session
        (its file is read where it is measured)."""
        return self.store.read_image(name) if self.store is not None else None

    def targets(self):
        """targets.csv, read once (a fresh copy every call)."""
        if "targets" not in self._read:
            self._read["targets"] = read_targets_csv(self.targets_path)
        return copy.deepcopy(self._read["targets"])


def is_rig_session(folder, storage_options: dict | None = None, resolve=None) -> bool:
    """Whether ``folder/session.json`` is a JSON object with a ``rig`` (False when unreadable:
    the single-camera loader then reports what is wrong); ``folder`` may be an fsspec URL
    (``storage_options``: its store's; ``resolve``: as :class:`~fieldcal.session.store.SessionStore`'s,
    e.g. :func:`fieldcal.lake.secrets.resolve`)."""
    if is_url(str(folder)):
        return _is_rig_on_store(str(folder), storage_options, resolve)
    try:
        return "rig" in read_manifest(Path(folder))
    except InputError:
        return False


def _is_rig_on_store(url: str, storage_options: dict | None, resolve) -> bool:
    import json

    import fsspec

    options = resolve(storage_options) if resolve is not None else storage_options
    try:
        fs, path = fsspec.core.url_to_fs(f"{url.rstrip('/')}/{MANIFEST}", **(options or {}))
        manifest = json.loads(fs.cat_file(path))
    except Exception:  # noqa: BLE001 - unreadable: the single-camera loader says what is wrong
        return False
    return isinstance(manifest, dict) and "rig" in manifest


def load_rig_session(folder, store: SessionStore | None = None) -> RigSession:
    """Read and validate a rig session (module docstring); ``store``: the session is on an object
    store and ``folder`` holds its small files (as :func:`fieldcal.session.loader.load_session`).

    Raises
    ------
    InputError
        One line naming the file and what is wrong.
    """
    folder = Path(folder)
    where = str(folder / MANIFEST)
    manifest = read_manifest(folder)
    if "rig" not in manifest:
        raise InputError("not a rig session (no 'rig' in the manifest)", where)
    for key in ("camera_id", "sensor", "lens"):
        if key in manifest:
            raise InputError(f"a rig session names its cameras, sensors and lenses in /rig/cameras: "
                             f"'{key}' is not allowed beside 'rig' (at /{key})", where)
    validate_json(manifest, "session", where)
    rig = manifest["rig"]
    heads = _heads(rig, where)
    ids = [h.camera_id for h in heads]
    if rig["reference"] not in ids:
        raise InputError(f"the reference {shown(rig['reference'])} is not one of the rig's cameras "
                         f"{ids} (at /rig/reference)", where)
    images, image_head, image_exposure, exposures = _images(folder, manifest["images"], ids, where)
    for h, hid in enumerate(ids):
        if not np.any(image_head == h):
            raise InputError(f"camera {hid!r} of the rig has no image (at /images)", where)
    estimate = manifest.get("estimate")
    if estimate is not None and (bad := [p for p in estimate if p not in FIELD_PARAMS]):
        raise InputError(f"estimate names {bad}, not estimable by the field method (allowed: "
                         f"{list(FIELD_PARAMS)}) (at /estimate)", where)
    fld = manifest["field"]
    targets_path = safe_path(folder, fld["targets"], "field.targets")
    if not targets_path.is_file():
        raise InputError(f"the targets file {fld['targets']!r} does not exist (at /field/targets)", where)
    check_distinct_files(folder, [im.file for im in images], where, store=store)
    obs_path = safe_path(folder, OBSERVATIONS, OBSERVATIONS)
    _refuse_single_camera_only(folder, fld, where)
    return RigSession(
        folder=folder, manifest=manifest, rig_id=rig["rig_id"],
        session_id=default_session_id(manifest, folder),
        acquired=parse_acquired(manifest["acquired"], where), heads=heads, reference=ids.index(rig["reference"]),
        exposures=exposures, images=images, image_head=image_head, image_exposure=image_exposure,
        default_sigma_px=float(manifest.get("default_sigma_px", DEFAULT_SIGMA_PX)),
        estimate=tuple(estimate) if estimate is not None else None, targets_path=targets_path,
        observations_path=obs_path if obs_path.is_file() else None,
        target_diameter_mm=fld.get("target_diameter_mm"), target_polarity=fld.get("target_polarity", "dark"),
        coded=fld.get("coded"), strict_targets=bool(fld.get("strict_targets", False)), store=store)


def _refuse_single_camera_only(folder: Path, fld: dict, where: str) -> None:
    """Bad input (for now): what only the single camera's adjustment handles -- a free network
    (``field.datum`` 'free') and scale bars (``scale_bars.csv``); a rig's datum is its surveyed
    targets as weighted control (:func:`fieldcal.rig.adjustment.adjust_rig`)."""
    if fld.get("datum", "auto") != "auto":
        raise InputError(f"field.datum {shown(fld['datum'])} is for single cameras only: a rig's datum is its "
                         "surveyed targets (at /field/datum)", where)
    if safe_path(folder, SCALE_BARS, SCALE_BARS).is_file():
        raise InputError("scale bars are supported for single cameras only: a rig's datum is its surveyed targets "
                         f"(remove {SCALE_BARS} from the rig session)", str(folder / SCALE_BARS))


def _heads(rig: dict, where: str) -> list[RigHead]:
    heads, first = [], {}
    for k, cam in enumerate(rig["cameras"]):
        cid = cam["camera_id"]
        if cid in first:
            raise InputError(f"camera {cid!r} is listed twice in the rig: at /rig/cameras/{first[cid]} "
                             f"and /rig/cameras/{k}", where)
        first[cid] = k
        s = cam["sensor"]
        heads.append(RigHead(cid, Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"])),
                             (cam.get("lens") or {}).get("nominal_focal_mm")))
    return heads


def _images(folder: Path, spec: list, ids: list[str], where: str):
    """The images with their head and exposure indices, and the exposures in order of appearance."""
    images, heads, exps, exposures = [], [], [], {}
    first: dict[str, int] = {}
    pairs: dict[tuple[int, int], int] = {}
    base = Path(folder).resolve()
    for k, item in enumerate(spec):
        safe_path(folder, item["file"].replace("\\", "/"), f"images[{k}]", base=base)
        name = normal_file_name(item["file"], f"images[{k}]", where)
        if name in first:
            raise InputError(f"image {shown(name)} is listed twice: at /images/{first[name]} and /images/{k}", where)
        first[name] = k
        if item["camera"] not in ids:
            raise InputError(f"image {shown(name)} names camera {shown(item['camera'])}, not one of the rig's "
                             f"{ids} (at /images/{k}/camera)", where)
        h = ids.index(item["camera"])
        e = exposures.setdefault(item["exposure"], len(exposures))
        if (h, e) in pairs:
            raise InputError(f"camera {item['camera']!r} has two images of exposure {item['exposure']!r}: "
                             f"/images/{pairs[(h, e)]} and /images/{k} (a head takes one image per exposure)",
                             where)
        pairs[(h, e)] = k
        images.append(FieldImage(name, item.get("station")))
        heads.append(h)
        exps.append(e)
    return images, np.array(heads, np.int64), np.array(exps, np.int64), list(exposures)


def rig_data_from_observations(sess: RigSession) -> RigData:
    """The :class:`RigData` of a rig session that carries ``observations.csv`` (every point on
    its own head's sensor)."""
    if sess.observations_path is None:
        raise InputError("no observations.csv in the rig session", str(sess.folder))
    targets = sess.targets()
    images = list(sess.images)
    unlisted = None if sess.strict_targets else []      # ids targets.csv does not list: unsurveyed, as for one camera
    obs = read_observations_csv(sess.observations_path, targets, images, default_sigma_px=sess.default_sigma_px,
                                allow_new_images=False, unlisted=unlisted)
    targets = targets.with_unsurveyed(unlisted or [])
    head_data, head_exp = [], []
    for h, head in enumerate(sess.heads):
        idx = np.flatnonzero(sess.image_head == h)
        local = np.full(len(images), -1, np.int64)
        local[idx] = np.arange(len(idx))
        keep = local[obs.image] >= 0
        o = FieldObservations(local[obs.image[keep]], obs.target[keep], obs.uv_px[keep], obs.sigma_px[keep])
        s = head.sensor
        u, v = o.uv_px[:, 0], o.uv_px[:, 1]
        off = ~((u >= -0.5) & (u <= s.width_px - 0.5) & (v >= -0.5) & (v <= s.height_px - 0.5))
        if off.any():
            k = int(np.argmax(off))
            raise InputError(f"point ({u[k]:g}, {v[k]:g}) px of {images[idx[o.image[k]]].file!r} is outside "
                             f"camera {head.camera_id!r}'s {s.width_px} x {s.height_px} px image",
                             str(sess.observations_path))
        head_data.append(FieldData(sensor=s, targets=targets, images=[images[i] for i in idx], obs=o,
                                   nominal_focal_mm=head.nominal_focal_mm, default_sigma_px=sess.default_sigma_px,
                                   meta={"camera_id": head.camera_id, "session_id": sess.session_id}))
        head_exp.append(sess.image_exposure[idx])
    meta = {"session_id": sess.session_id, **({"unlisted_targets": list(unlisted)} if unlisted else {})}
    return RigData(sess.rig_id, list(sess.heads), sess.reference, list(sess.exposures), head_data, head_exp,
                   meta=meta)
