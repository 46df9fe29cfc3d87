"""The field method's data: surveyed targets, images and identified image observations.

Plain containers over numpy arrays, shared by the session loader, the synthetic
generator, identification and the adjustment. Pixel coordinates follow docs/conventions.md
section 1; world coordinates are metres; target sigmas millimetres.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pyarrow as pa

from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor
from fieldcal.session.schemas import arrow_schema

__all__ = ["TargetField", "FieldImage", "FieldObservations", "FieldData", "normal_problem"]

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
    """Surveyed targets.

    Attributes
    ----------
    ids : (n,) ndarray of str
        Unique target ids.
    xyz_m : (n, 3) ndarray
        Surveyed world coordinates [m].
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
class FieldData:
    """Everything the field adjustment needs."""

    sensor: Sensor
    targets: TargetField
    images: list[FieldImage]
    obs: FieldObservations
    nominal_focal_mm: float | None = None
    default_sigma_px: float = DEFAULT_SIGMA_PX
    meta: dict = field(default_factory=dict)

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
