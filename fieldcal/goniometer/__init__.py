"""The laboratory goniometer method (Yuan et al. 2016, Acta Geodaetica et Cartographica Sinica 45(5)).

Modules, in the order the method runs: :mod:`~fieldcal.goniometer.frames` (frames.csv, the
spot of each frame, the mean per angle), :mod:`~fieldcal.goniometer.minsum` (principal
distance and point per sweep, eq. 1-7), :mod:`~fieldcal.goniometer.chain` (the distortion
fit, eq. 8-10, and the precision), :mod:`~fieldcal.goniometer.result` (the calibration) and
:mod:`~fieldcal.goniometer.method` (:func:`calibrate`, the steps in order);
:mod:`~fieldcal.contract.goniometer_schema` the columns of a frame's measurement.
"""

import importlib

_EXPORTS = {"along_axis_difference_px": "chain", "MEASUREMENT_SCHEMA": "frames", "average_frames": "frames",
            "measure_frame": "frames", "measure_session": "frames", "measurements_table": "frames",
            "calibrate": "method", "min_sum_linear": "minsum",
            "min_sum_rigorous": "minsum", "GoniometerResult": "result"}
"""Names of the package and the module that defines each, imported on first use (PEP 562):
importing a light module of the package (:mod:`~fieldcal.contract.goniometer_schema`) does not
import the method's SciPy and OpenCV."""

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"fieldcal.goniometer.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'fieldcal.goniometer' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
