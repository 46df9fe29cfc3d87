"""Dask worker preload: import the measuring code once, when the worker starts.

``dask worker --preload flows.worker`` (and the local clusters the flows start) load this
module in every worker process, so the first measuring task does not pay for importing
Prefect's task engine, fieldcal and OpenCV (several seconds per process), and the batch
size the flow derives from its first tasks measures the work rather than the imports.
It also gives OpenCV as many threads as the worker has Dask threads (one by default), so
that workers sharing a machine do not oversubscribe its cores.
"""

from __future__ import annotations

import cv2
import prefect.task_engine  # noqa: F401  (the engine that runs each task in the worker)
import prefect_dask.client  # noqa: F401

import fieldcal.goniometer.method  # noqa: F401
import fieldcal.measure.targets  # noqa: F401
import fieldcal.pipeline  # noqa: F401
import flows.calibrate  # noqa: F401


def dask_setup(worker) -> None:
    """Called by Dask when the worker starts: one OpenCV thread per Dask thread."""
    cv2.setNumThreads(max(1, int(worker.state.nthreads)))
