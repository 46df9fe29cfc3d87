"""A field session's input types: surveyed targets, images and identified image observations.

Plain containers over numpy arrays, made by the session loader and shared by the synthetic
generator, identification and the adjustment. Pixel coordinates follow docs/conventions.md
section 1; world coordinates are metres; target sigmas millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pyarrow as pa

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor

__all__ = ["TargetField", "FieldImage", "FieldObservations", "FieldData", "ScaleBars", "normal_problem"]

DEFAULT_TARGET_SIGMA_MM = 5.0
DEFAULT_SIGMA_PX = 0.1
NORMAL_NORM_TOLERANCE = 0.01
"""How far from 1 the length of a given target normal may be (rounded unit vectors pass)."""


def normal_problem(normal) -> str | None:
    """Why ``normal`` (3 numbers) is not a target's unit normal (docs/conventions.md section 3),
    or None when it is one (its length within :data:`NORMAL_NORM_TOLERANCE` of 1)."""
    n = np.asarray(normal, float)
    if n.shape != (3,) or not np.all(np.isfinite(n)):
        return f"must be 3 finite numbers, got {np.asarray(normal).tolist()}"
    length = float(np.linalg.norm(n))
    if abs(length - 1.0) > NORMAL_NORM_TOLERANCE:
        return f"must be a unit vector, got {n.tolist()} of length {length:.4g}"
    return None


@dataclass
class TargetField:
    """The field's targets: surveyed ones and unsurveyed ones (tie points).

    An **unsurveyed** target (CONTRACT section 3: empty ``X, Y, Z`` in targets.csv, or an id
    that only the image points name) has NaN coordinates: the adjustment estimates them
    with no survey prior.

    Attributes
    ----------
    ids : (n,) ndarray of str
        Unique target ids.
    xyz_m : (n, 3) ndarray
        Surveyed world coordinates [m]; NaN rows for unsurveyed targets.
    sigma_mm : (n,) ndarray
        One-sigma accuracy of each surveyed coordinate [mm].
    codes : (n,) ndarray of int
        ArUco id of a coded target, -1 for a plain circular target.
    normals : (n, 3) ndarray or None
        Unit normal of each target's plane, pointing to the side it is seen from (known
        for synthetic fields; given in targets.csv or session.json; the renderer and the
        eccentricity correction use it). A row of NaN: that target's normal is unknown.
    """

    ids: np.ndarray
    xyz_m: np.ndarray
    sigma_mm: np.ndarray
    codes: np.ndarray
    normals: np.ndarray | None = None

    def __post_init__(self):
        self.ids = np.asarray(self.ids).astype(str)
        self.xyz_m = np.asarray(self.xyz_m, dtype=float).reshape(-1, 3)
        n = len(self.ids)
        self.sigma_mm = np.broadcast_to(np.asarray(self.sigma_mm, dtype=float), (n,)).copy()
        self.codes = np.broadcast_to(np.asarray(self.codes, dtype=np.int64), (n,)).copy()
        if self.xyz_m.shape[0] != n:
            raise InputError(f"{n} target ids but {self.xyz_m.shape[0]} coordinate rows")
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=float).reshape(n, 3)

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def surveyed(self) -> np.ndarray:
        """(n,) bool: the targets with surveyed coordinates (the others are unsurveyed)."""
        return np.isfinite(self.xyz_m).all(axis=1)

    def with_unsurveyed(self, ids, codes=-1) -> TargetField:
        """These targets and the unsurveyed targets ``ids`` appended (NaN coordinates; ``codes``
        their ArUco ids, -1: plain)."""
        ids = np.asarray(list(ids), dtype=str)
        if not len(ids):
            return self
        n = len(ids)
        normals = None if self.normals is None else np.vstack([self.normals, np.full((n, 3), np.nan)])
        return replace(self, ids=np.concatenate([self.ids, ids]),
                       xyz_m=np.vstack([self.xyz_m, np.full((n, 3), np.nan)]),
                       sigma_mm=np.concatenate([self.sigma_mm, np.full(n, DEFAULT_TARGET_SIGMA_MM)]),
                       codes=np.concatenate([self.codes, np.broadcast_to(np.asarray(codes, np.int64), (n,))]),
                       normals=normals)

    def index(self) -> dict[str, int]:
        """``{id: row}``."""
        return {t: i for i, t in enumerate(self.ids)}


@dataclass(frozen=True)
class FieldImage:
    """One image of the session: its name (path relative to the session, forward slashes)."""

    file: str
    station: str | None = None


@dataclass
class FieldObservations:
    """Identified image points: image ``image[k]`` sees target ``target[k]`` at ``uv_px[k]``.

    Attributes
    ----------
    image : (m,) int ndarray
        Index into the session's image list.
    target : (m,) int ndarray
        Index into the :class:`TargetField`.
    uv_px : (m, 2) ndarray
        Measured pixel coordinates [px].
    sigma_px : (m,) ndarray
        A-priori one-sigma accuracy of u and v [px].
    """

    image: np.ndarray
    target: np.ndarray
    uv_px: np.ndarray
    sigma_px: np.ndarray

    def __post_init__(self):
        self.image = np.asarray(self.image, dtype=np.int64)
        self.target = np.asarray(self.target, dtype=np.int64)
        self.uv_px = np.asarray(self.uv_px, dtype=float).reshape(-1, 2)
        self.sigma_px = np.broadcast_to(np.asarray(self.sigma_px, dtype=float), self.image.shape).copy()

    def __len__(self) -> int:
        return len(self.image)

    def take(self, mask_or_index) -> FieldObservations:
        """A subset of the observations."""
        return FieldObservations(self.image[mask_or_index], self.target[mask_or_index],
                                 self.uv_px[mask_or_index], self.sigma_px[mask_or_index])


@dataclass
class ScaleBars:
    """Distances between targets measured independently (``scale_bars.csv``, CONTRACT section 3).

    Attributes
    ----------
    from_target, to_target : (b,) int ndarray
        Indices into the :class:`TargetField`.
    length_mm, sigma_mm : (b,) ndarray
        The measured distance and its one-sigma accuracy [mm].
    """

    from_target: np.ndarray
    to_target: np.ndarray
    length_mm: np.ndarray
    sigma_mm: np.ndarray

    def __post_init__(self):
        self.from_target = np.asarray(self.from_target, dtype=np.int64).reshape(-1)
        self.to_target = np.asarray(self.to_target, dtype=np.int64).reshape(-1)
        self.length_mm = np.asarray(self.length_mm, dtype=float).reshape(-1)
        self.sigma_mm = np.asarray(self.sigma_mm, dtype=float).reshape(-1)

    def __len__(self) -> int:
        return len(self.from_target)


@dataclass
class FieldData:
    """Everything the field adjustment needs."""

    sensor: Sensor
    targets: TargetField
    images: list[FieldImage]
    obs: FieldObservations
    nominal_focal_mm: float | None = None
    default_sigma_px: float = DEFAULT_SIGMA_PX
    meta: dict = field(default_factory=dict)
    scale_bars: ScaleBars | None = None

    def with_obs(self, obs: FieldObservations) -> FieldData:
        return replace(self, obs=obs)

    def observation_table(self) -> pa.Table:
        """The observations as a table of schema ``observations`` (docs/conventions.md section 3, observations.csv)."""
        return pa.table({
            "image": pa.array([self.images[i].file for i in self.obs.image], pa.string()),
            "target_id": pa.array(self.targets.ids[self.obs.target], pa.string()),
            "u_px": self.obs.uv_px[:, 0], "v_px": self.obs.uv_px[:, 1],
            "sigma_px": self.obs.sigma_px,
        }, schema=arrow_schema("observations"))
