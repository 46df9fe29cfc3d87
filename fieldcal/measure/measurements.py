"""The ``measurements`` table: what every target detector returns, one row per target.

Schema ``measurements`` (``schemas/measurements.arrow.json``): the image, the kind of
target (``disc``, ``aruco``), its code, the position ``u_px, v_px`` in the pixel convention
of docs/conventions.md section 1 with its a-priori one-sigma ``sigma_px``, and
the quality figures the filters and the report use. The disc detector
(:mod:`fieldcal.measure.discs`), the ArUco detector (:mod:`fieldcal.measure.coded`) and
the per-image composition (:mod:`fieldcal.measure.targets`) build their tables here, and
both detectors take the a-priori precision of a centre from :func:`apriori_sigma`.
"""

from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError

__all__ = ["empty_measurements", "measurements_table", "apriori_sigma", "SIGMA_FLOOR_PX"]

SIGMA_FLOOR_PX = 0.003
"""What the precision model of :func:`apriori_sigma` leaves out [px] (rendering tests measure
0.003-0.004 px without noise)."""


def apriori_sigma(snr, diameter_px, psf_sigma_px: float = 0.8):
    """A-priori one-sigma precision of a disc's centre, per axis [px], from SNR and size.

    The Cramer-Rao bound of a disc's position in white noise: an edge blurred by
    ``s = sqrt(sigma_psf^2 + 1/12)`` (PSF and pixel) has ``sum (dI/dr)^2 = C^2 / (2 sqrt(pi) s)``
    per unit length; over the rim ``pi d``, half of it along each axis, so
    ``sigma = sqrt(4 sqrt(pi) s / (pi d)) / snr``; combined with a floor of
    :data:`SIGMA_FLOOR_PX` for what the model leaves out.

    Parameters
    ----------
    snr : (n,) array_like
        Contrast over the background noise.
    diameter_px : (n,) array_like
        Diameter of the disc's image [px].
    psf_sigma_px : float
        The blur's standard deviation [px].

    Returns
    -------
    (n,) ndarray
        Per-axis sigma [px].
    """
    s = math.sqrt(psf_sigma_px**2 + 1.0 / 12.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        sig = np.sqrt(4.0 * math.sqrt(math.pi) * s / (math.pi * np.maximum(diameter_px, 1.0)))
        sig = sig / np.maximum(snr, 1e-6)
    return np.hypot(sig, SIGMA_FLOOR_PX)


def empty_measurements() -> pa.Table:
    """A table of schema ``measurements`` with no rows."""
    return arrow_schema("measurements").empty_table()


def measurements_table(columns: dict, image_name: str = "") -> pa.Table:
    """A ``measurements`` table from a dict of columns (missing nullable columns are null).

    Parameters
    ----------
    columns : dict of str to (n,) array-like
        Columns by name; ``u_px`` sets the number of rows. NaN in a nullable float column
        becomes null. ``image`` and ``blob`` (0..n-1) are filled here.
    image_name : str
        Written to the ``image`` column.

    Raises
    ------
    InputError
        A required column is missing.
    """
    schema = arrow_schema("measurements")
    n = len(columns["u_px"])
    cols = {}
    for f in schema:
        if f.name == "image":
            cols["image"] = pa.repeat(pa.scalar(image_name, pa.string()), n)
        elif f.name == "blob":
            cols["blob"] = pa.array(np.arange(n, dtype=np.int32))
        elif f.name in columns:
            val = columns[f.name]
            if isinstance(val, (pa.Array, pa.ChunkedArray)):
                cols[f.name] = val.cast(f.type) if val.type != f.type else val
            elif isinstance(val, np.ndarray) and val.dtype.kind == "f" and f.nullable:
                cols[f.name] = pa.array(val, f.type, mask=~np.isfinite(val))
            else:
                cols[f.name] = pa.array(val, f.type)
        elif f.nullable:
            cols[f.name] = pa.nulls(n, f.type)
        else:
            raise InputError(f"measurements: column {f.name!r} is required")
    return pa.table(cols, schema=schema)
