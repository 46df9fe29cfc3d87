"""Dask worker preload: import the measuring code and load its compiled kernels once, when the worker starts.

``dask worker --preload flows.worker`` (and the local clusters the flows start) load this
module in every worker process, so the first measuring task does not pay for importing
Prefect's task engine, fieldcal and OpenCV (several seconds per process), nor for
loading the disc kernel, the TIFF codecs and OpenCV's detector
(:func:`fieldcal.measure.warm.warm_up_measuring`; the kernel comes from Numba's cache).
It also gives OpenCV and the TIFF codecs as many threads as the worker has Dask threads
(one by default), so that workers sharing a machine do not oversubscribe its cores.
"""

from __future__ import annotations

import prefect.task_engine  # noqa: F401  (the engine that runs each task in the worker)
import prefect_dask.client  # noqa: F401

import fieldcal.goniometer.method  # noqa: F401
import fieldcal.pipeline  # noqa: F401
from fieldcal.measure.heap import keep_freed_memory
from flows.calibrate import warm_process


def dask_setup(worker) -> None:
    """Called by Dask when the worker starts: freed frame memory kept for the next frame
    (:func:`fieldcal.measure.heap.keep_freed_memory`, before the worker's threads first
    allocate), then :func:`flows.calibrate.warm_process`: one OpenCV and one codec thread
    per Dask thread and the measuring path warmed up (the compiled disc kernel loaded, or
    the one-line reason it cannot be), once: the measuring tasks do not repeat it."""
    keep_freed_memory()
    warm_process("field", max(1, int(worker.state.nthreads)))
