"""What image-by-image progress costs (``flows.image_events``): a worker's report and its way to the flow.

A task on a real Dask cluster (in-process workers, the default of ``fieldcal run``, and
worker processes) reports N images, as ``flows.calibrate.measure_batch`` does after each
image; the flow counts them (:class:`flows.image_events.ImageCounts`). Printed: the
worker's time per report, and how long after the task's end the flow has counted the last
image. Beside it, for scale: one full-size image takes 0.2-0.4 s to read and measure.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_image_events.py [--images 2000]
"""

from __future__ import annotations

import argparse
import threading
import time


def report_many(run: str, n: int) -> tuple[float, float]:
    """In a Dask task: report ``n`` images; returns (seconds per report, end time on the wall clock)."""
    from flows import image_events

    t = time.perf_counter()
    for k in range(n):
        image_events.report_image(run, f"images/{k:05d}.tif", "measured")
    return (time.perf_counter() - t) / n, time.time()


def measure(processes: bool, n: int) -> dict:
    import distributed

    from flows import image_events
    from flows.cluster import local_cluster_kwargs

    with distributed.LocalCluster(**local_cluster_kwargs(1, {"processes": processes})) as lc, \
            distributed.Client(lc) as client:
        all_counted = threading.Event()

        def on_change(done, **_):
            if done == n:
                all_counted.set()

        counts = image_events.ImageCounts(n, on_change, client)
        per_report_s, end_unix = client.submit(report_many, counts.run, n, pure=False).result()
        all_counted.wait(60)
        lag_s = time.time() - end_unix
        counted = counts.counts()["done"]
        counts.close()
    return {"per_report_us": per_report_s * 1e6, "lag_ms": lag_s * 1e3, "counted": counted}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=2000)
    args = ap.parse_args()
    print("| workers | images reported | per report, on the worker [us] | last one counted after the task's end [ms] |")
    print("|---|---|---|---|")
    for processes in (False, True):
        r = measure(processes, args.images)
        print(f"| {'processes' if processes else 'threads of this process'} | {r['counted']} / {args.images} "
              f"| {r['per_report_us']:.0f} | {r['lag_ms']:.0f} |")


if __name__ == "__main__":
    main()
