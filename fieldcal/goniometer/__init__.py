"""The laboratory goniometer method (Yuan et al. 2016, Acta Geodaetica et Cartographica Sinica 45(5)).
"""

from fieldcal.goniometer.method import (
    MEASUREMENT_SCHEMA,
    GoniometerResult,
    along_axis_difference_px,
    calibrate,
    measure_frame,
    measure_session,
    measurements_table,
    min_sum_linear,
    min_sum_rigorous,
    read_frames_csv,
)

__all__ = ["MEASUREMENT_SCHEMA", "GoniometerResult", "along_axis_difference_px", "calibrate",
           "measure_frame", "measure_session", "measurements_table", "min_sum_linear", "min_sum_rigorous",
           "read_frames_csv"]
