"""The Dask worker preload: threads for OpenCV and the TIFF codecs, the compiled kernel loaded."""

from types import SimpleNamespace

import cv2

from fieldcal.measure import disc_kernel
from fieldcal.measure.imageio import decode_threads, set_decode_threads
from flows import worker


def test_worker_setup_gives_each_dask_thread_one_opencv_and_one_codec_thread_and_loads_the_kernel():
    before = (cv2.getNumThreads(), decode_threads())
    try:
        worker.dask_setup(SimpleNamespace(state=SimpleNamespace(nthreads=2)))
        assert cv2.getNumThreads() == 2 and decode_threads() == 2
        assert disc_kernel.problem() is None and disc_kernel.available()   # loaded before any task
    finally:
        cv2.setNumThreads(before[0])
        set_decode_threads(before[1])
