"""The calibration document ``fieldcal.calibration/1`` (docs/conventions.md section 4).

One function assembles it from the method's result and the session, so both methods
produce the same frame (schema, ids, version, sensor, model, all 13 parameters with a
``null`` sigma for the ones not estimated, inputs' fingerprint).
"""

from __future__ import annotations

import math
from datetime import UTC, datetime

import numpy as np

from fieldcal.model.camera import MODEL, PARAM_NAMES, Sensor

__all__ = ["SCHEMA", "calibration_document", "utc_now_iso", "json_number"]

SCHEMA = "fieldcal.calibration/1"


def utc_now_iso() -> str:
    """The current time as ``YYYY-MM-DDTHH:MM:SSZ``."""
    return datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def json_number(value):
    """A float for JSON: NaN and infinities become ``None`` (JSON has no NaN)."""
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def _plain(obj):
    """Numpy scalars/arrays inside nested containers -> plain JSON values."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return json_number(obj)
    return obj


def calibration_document(*, camera_id: str, session_id: str, version: str, method: str,
                         sensor: Sensor, parameters, sigma: dict, stats: dict, images: list,
                         fingerprint: str, created: str | None = None, extra: dict | None = None
                         ) -> dict:
    """The calibration document of docs/conventions.md section 4.

    Parameters
    ----------
    parameters : (13,) array_like
        Values in :data:`fieldcal.model.camera.PARAM_NAMES` order.
    sigma : dict
        A-posteriori sigma per estimated parameter name; names not in it are ``null``.
    stats, images : the method-specific parts (see the contract).
    extra : dict, optional
        Additional top-level keys (kept after the contract's keys).
    """
    p = np.asarray(parameters, dtype=float)
    doc = {
        "schema": SCHEMA,
        "camera_id": camera_id,
        "session_id": session_id,
        "version": version,
        "method": method,
        "created": created or utc_now_iso(),
        "sensor": sensor.to_dict(),
        "model": MODEL,
        "parameters": {n: float(v) for n, v in zip(PARAM_NAMES, p, strict=True)},
        "sigma": {n: json_number(sigma.get(n)) for n in PARAM_NAMES},
        "stats": _plain(stats),
        "images": _plain(images),
        "inputs": {"fingerprint": fingerprint},
    }
    if extra:
        doc.update(_plain(extra))
    return doc
