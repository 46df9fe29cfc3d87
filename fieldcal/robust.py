"""Robust statistics shared by the measuring, initialisation and adjustment steps."""

from __future__ import annotations

import numpy as np

__all__ = ["MAD_TO_SIGMA", "robust_sigma"]

MAD_TO_SIGMA = 1.4826
"""The standard deviation of a normal distribution over its median absolute deviation."""


def robust_sigma(deviations, axis=None, keepdims: bool = False):
    """``1.4826 x median(|deviations|)``: a standard deviation that ignores outliers.

    Parameters
    ----------
    deviations : array_like
        Deviations from the centre the caller chose (zero, the median, a prediction).
    axis, keepdims
        As in :func:`numpy.median`.
    """
    return MAD_TO_SIGMA * np.median(np.abs(deviations), axis=axis, keepdims=keepdims)
