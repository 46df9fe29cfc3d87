"""The columns of a goniometer frame's measurement: one Arrow schema, nothing else imported.

Its own module so that the lake (the observations table's schema, the data dictionary) can
name it without importing the method (SciPy's optimisers, OpenCV): the first commit of a
field session used to pay 0.18 s for that import.
"""

from __future__ import annotations

import pyarrow as pa

__all__ = ["MEASUREMENT_SCHEMA"]

MEASUREMENT_SCHEMA = pa.schema([
    pa.field("file", pa.string(), nullable=False,
             metadata={"doc": "frame path relative to the session folder, as frames.csv names it"}),
    pa.field("u_px", pa.float64(), metadata={"doc": "spot centroid, column [px]; NaN if none"}),
    pa.field("v_px", pa.float64(), metadata={"doc": "spot centroid, row [px]; NaN if none"}),
    pa.field("peak_dn", pa.float64(), metadata={"doc": "brightest pixel of the spot [DN]"}),
    pa.field("background_dn", pa.float64(), metadata={"doc": "median background [DN]"}),
    pa.field("noise_dn", pa.float64(), metadata={"doc": "robust background sigma [DN]"}),
    pa.field("threshold_dn", pa.float64(), metadata={"doc": "iterative threshold [DN]"}),
    pa.field("n_pixels", pa.int32(), metadata={"doc": "pixels in the spot's region"}),
    pa.field("snr", pa.float64(), metadata={"doc": "(peak - background) / noise"}),
    pa.field("flag", pa.string(), nullable=False, metadata={"doc": "one of FRAME_FLAGS"}),
    pa.field("reason", pa.string(), nullable=False, metadata={"doc": "empty when ok"}),
], metadata={"name": "fieldcal.goniometer_measurements/1",
             "doc": "One row per goniometer frame: the spot centroid and its quality flag."})
