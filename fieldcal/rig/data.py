"""A rig's data: its heads, its exposures, and per head the field data of its images
(CONTRACT section 3, "Rig sessions").

Every head's images are a :class:`fieldcal.session.data.FieldData` of their own (the head's
sensor, the session's shared targets, the head's observations), so a head can be calibrated
alone exactly as a single camera is; ``image_exposure[h][i]`` names the exposure of image
``i`` of head ``h`` (an index into ``exposures``). A head has at most one image per exposure.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from fieldcal.errors import InputError
from fieldcal.model.camera import Sensor
from fieldcal.session.data import FieldData

__all__ = ["RigHead", "RigData"]


@dataclass(frozen=True)
class RigHead:
    """One camera of a rig: its id, sensor and nominal focal length [mm] (or None)."""

    camera_id: str
    sensor: Sensor
    nominal_focal_mm: float | None = None


@dataclass
class RigData:
    """Everything the rig adjustment needs.

    Attributes
    ----------
    rig_id : str
    heads : list of RigHead
    reference : int
        Index of the reference head (its camera frame is the rig frame).
    exposures : list of str
        Exposure names, in order.
    head_data : list of FieldData
        Per head, its images and observations (targets shared by all heads).
    image_exposure : list of (n_images_h,) int ndarray
        Per head, the exposure index of each of its images.
    """

    rig_id: str
    heads: list[RigHead]
    reference: int
    exposures: list[str]
    head_data: list[FieldData]
    image_exposure: list[np.ndarray]
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        self.image_exposure = [np.asarray(e, dtype=np.int64) for e in self.image_exposure]
        n = len(self.heads)
        if not (len(self.head_data) == len(self.image_exposure) == n):
            raise InputError(f"{n} heads but {len(self.head_data)} head data and "
                             f"{len(self.image_exposure)} exposure lists", "rig data")
        if not 0 <= self.reference < n:
            raise InputError(f"reference head index {self.reference} outside 0..{n - 1}", "rig data")
        for h, (d, e) in enumerate(zip(self.head_data, self.image_exposure, strict=True)):
            if len(e) != len(d.images):
                raise InputError(f"head {self.heads[h].camera_id!r}: {len(d.images)} images but "
                                 f"{len(e)} exposure indices", "rig data")
            if len(e) and (e.min() < 0 or e.max() >= len(self.exposures)):
                raise InputError(f"head {self.heads[h].camera_id!r}: exposure index out of range", "rig data")
            if len(np.unique(e)) != len(e):
                raise InputError(f"head {self.heads[h].camera_id!r} has two images of one exposure", "rig data")

    @property
    def n_heads(self) -> int:
        return len(self.heads)

    @property
    def targets(self):
        """The session's targets (shared by every head)."""
        return self.head_data[self.reference].targets

    def head_index(self) -> dict[str, int]:
        """``{camera_id: head index}``."""
        return {hd.camera_id: h for h, hd in enumerate(self.heads)}
