"""The Dask worker preload: threads for OpenCV and the TIFF codecs, the compiled kernel loaded."""

import sys
from types import SimpleNamespace

import cv2

from fieldcal.measure import disc_kernel, heap, warm
from fieldcal.measure.imageio import decode_threads, set_decode_threads
from flows import worker


def test_worker_setup_gives_each_dask_thread_one_opencv_and_one_codec_thread_and_loads_the_kernel(monkeypatch):
    from flows import calibrate

    before = (cv2.getNumThreads(), decode_threads())
    monkeypatch.setattr(heap, "_DONE", {})              # not applied yet, as in a new worker process
    monkeypatch.setattr(calibrate, "_WARMED", set())
    try:
        worker.dask_setup(SimpleNamespace(state=SimpleNamespace(nthreads=2)))
        assert calibrate._WARMED == {"field"}           # a measuring task does not warm up again
        assert cv2.getNumThreads() == 2 and decode_threads() == 2
        assert disc_kernel.problem() is None and disc_kernel.available()   # loaded before any task
        if sys.platform.startswith("linux"):
            assert heap._DONE == {"ok": True}                 # glibc told by the setup, not by this test
            assert heap.keep_freed_memory() is True
    finally:
        cv2.setNumThreads(before[0])
        set_decode_threads(before[1])


def test_in_process_workers_are_warmed_once_and_a_task_does_not_warm_again(monkeypatch):
    import threading

    from flows import calibrate, cluster

    monkeypatch.delenv(cluster.ADDRESS_ENV, raising=False)
    assert cluster.in_process(None, None) and cluster.in_process(None, {"processes": False})
    assert not cluster.in_process(None, {"processes": True})
    assert not cluster.in_process("tcp://127.0.0.1:8786", None)
    # the same question of a task runner the command line hands to the flow
    assert cluster.runner_in_process(cluster.task_runner(None, 2, None))
    assert not cluster.runner_in_process(cluster.task_runner(None, 2, {"processes": True}))
    assert not cluster.runner_in_process(cluster.task_runner("tcp://127.0.0.1:8786"))
    calls = []
    monkeypatch.setattr(calibrate, "_WARMED", set())
    monkeypatch.setattr(warm, "warm_up_measuring", lambda: calls.append(1) or True)
    before = (cv2.getNumThreads(), decode_threads())
    try:
        calibrate.warm_process("field", None)                 # the flow, before the cluster starts
        tasks = [threading.Thread(target=calibrate.warm_process, args=("field", 1)) for _ in range(2)]
        for t in tasks:
            t.start()
        for t in tasks:
            t.join(timeout=10)
    finally:
        cv2.setNumThreads(before[0])
        set_decode_threads(before[1])
    assert calls == [1] and "field" in calibrate._WARMED
