"""The measurement of one session image: its coded targets and its discs.

:func:`measure_image` is what the field method runs per image (the flow fans it out over
the session's images): read the TIFF (:mod:`fieldcal.measure.imageio`), refuse an image
with nothing to measure (blank or over-exposed), detect the session's ArUco markers when
it has coded targets (:mod:`fieldcal.measure.coded`), then the discs outside them
(:mod:`fieldcal.measure.discs`); one ``measurements`` table
(:mod:`fieldcal.measure.measurements`) of both, ``blob`` numbered through.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import pyarrow as pa

from fieldcal.errors import ImageError, InputError
from fieldcal.measure.coded import detect_aruco, marker_exclusion_polygons
from fieldcal.measure.discs import detect_targets
from fieldcal.measure.imageio import ImageFile, read_image
from fieldcal.measure.measurements import empty_measurements
from fieldcal.model.camera import Sensor

__all__ = ["measure_image", "MAX_SATURATED_FRACTION"]


def measure_image(path, *, polarity: str = "dark", sensor: Sensor | None = None,
                  coded: dict | None = None, name: str | None = None, **detect_kw) -> pa.Table:
    """Read one session image and measure its targets: ArUco markers and discs.

    Parameters
    ----------
    path : str, path-like or ImageFile
        The TIFF file, or its bytes already read (and hashed) by
        :func:`fieldcal.measure.imageio.read_file`: decoded from memory, not read again.
    polarity : {"dark", "bright"}
        The session's ``target_polarity``.
    sensor : Sensor, optional
        The session's sensor; an image of another size is an error.
    coded : dict, optional
        The session's ``field.coded`` (``{"type": "aruco", "dictionary": ...}``); when given,
        markers are detected first and discs inside them are not reported.
    name : str, optional
        The image's name in the session (``images/x.tif``); default the path with forward
        slashes.
    **detect_kw
        Passed to :func:`detect_targets` (diameter range, method, filters).

    Returns
    -------
    pyarrow.Table
        Schema ``measurements``: the markers (``kind="aruco"``) then the discs, ``blob``
        numbered through.

    Raises
    ------
    ImageError
        The file is missing, corrupt, unsupported or of the wrong size, blank (every pixel
        the same: all black, saturated) or over-exposed (more than
        :data:`MAX_SATURATED_FRACTION` of the pixels at the sample type's maximum); one
        line naming it.
    """
    where = path.path if isinstance(path, ImageFile) else os.fspath(path)
    image_name = name if name is not None else where.replace(os.sep, "/")
    expect = None if sensor is None else (sensor.width_px, sensor.height_px)
    pixels = read_image(path, expect_size=expect)
    _check_exposure(pixels, where)
    tables = []
    exclude = list(detect_kw.pop("exclude", None) or [])
    try:
        if coded is not None:
            if coded.get("type", "aruco") != "aruco":
                raise InputError(f"coded targets of type {coded.get('type')!r} are not supported "
                                 "(only 'aruco')")
            markers = detect_aruco(pixels, dictionary=coded.get("dictionary", "DICT_4X4_1000"),
                                   image_name=image_name)
            tables.append(markers)
            exclude += marker_exclusion_polygons(markers)
        discs = detect_targets(pixels, polarity=polarity, exclude=exclude or None,
                               image_name=image_name, **detect_kw)
        tables.append(discs)
    except (cv2.error, MemoryError, FloatingPointError, np.linalg.LinAlgError) as err:
        msg = str(err).strip().splitlines()
        raise ImageError(f"cannot measure targets ({type(err).__name__}: "
                         f"{msg[0][:160] if msg else ''})", where) from None
    table = pa.concat_tables(tables) if tables else empty_measurements()
    return table.set_column(table.schema.get_field_index("blob"), "blob",
                            pa.array(np.arange(table.num_rows, dtype=np.int32)))


MAX_SATURATED_FRACTION = 0.5
"""An image with more of its pixels at the sample type's maximum is refused as over-exposed."""


def _check_exposure(pixels: np.ndarray, where: str) -> None:
    """Refuse an image with nothing to measure: blank (one value) or mostly saturated.

    Raises :class:`ImageError` naming the file; a measurement of such an image would only be
    an empty table, left out later with a misleading reason.
    """
    top = np.iinfo(pixels.dtype).max
    lo, hi = int(pixels.min()), int(pixels.max())
    if lo == hi:
        what = "all black" if hi == 0 else "saturated" if hi == top else "no contrast"
        raise ImageError(f"blank image: every pixel is {hi} ({what}); nothing to measure", where)
    if hi == top:
        share = np.count_nonzero(pixels == top) / pixels.size
        if share > MAX_SATURATED_FRACTION:
            raise ImageError(f"over-exposed: {100 * share:.0f} % of the pixels are saturated at {top}",
                             where)
