"""The laboratory goniometer method (Yuan et al. 2016, Acta Geodaetica et Cartographica Sinica 45(5)).

Modules, in the order the method runs: :mod:`~fieldcal.goniometer.frames` (frames.csv, the
spot of each frame, the mean per angle), :mod:`~fieldcal.goniometer.minsum` (principal
distance and point per sweep, eq. 1-7), :mod:`~fieldcal.goniometer.chain` (the distortion
fit, eq. 8-10, and the precision), :mod:`~fieldcal.goniometer.result` (the calibration) and
:mod:`~fieldcal.goniometer.method` (:func:`calibrate`, the steps in order).
"""

from fieldcal.goniometer.chain import along_axis_difference_px
from fieldcal.goniometer.frames import (
    MEASUREMENT_SCHEMA,
    average_frames,
    measure_frame,
    measure_session,
    measurements_table,
    read_frames_csv,
)
from fieldcal.goniometer.method import calibrate
from fieldcal.goniometer.minsum import min_sum_linear, min_sum_rigorous
from fieldcal.goniometer.result import GoniometerResult

__all__ = ["MEASUREMENT_SCHEMA", "GoniometerResult", "along_axis_difference_px", "average_frames",
           "calibrate", "measure_frame", "measure_session", "measurements_table", "min_sum_linear",
           "min_sum_rigorous", "read_frames_csv"]
