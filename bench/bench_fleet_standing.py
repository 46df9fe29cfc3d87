"""Worker processes against worker threads on *standing* clusters (issue 28, goal 3, a first look).

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_fleet_standing.py [N_SESSIONS]

N observations-only field sessions (the wide-angle camera, 24 images each, 4 cameras) under
one root; one Prefect test server; two local Dask clusters of 2 single-threaded workers
started once, one of threads in this process and one of worker processes (fieldcal's worker
settings), so that no run pays for starting workers (``bench/README_fleet.md``: 14-24 s for
two processes at load 8-10). One warm-up fleet on each (imports, kernels), then two rounds of
``recalibrate_fleet`` on each, interleaved, each into a fresh lake. Printed per run: the wall
time, the median of the sessions' ``solver_s`` (inside the solve task), of their
``total_s`` (the session flow's body) and of their runs (``seconds`` of the fleet's summary:
the sub-flow run from its creation to its result), and the load.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("FIELDCAL_REPORTS", "off")
os.environ["FIELDCAL_HASH_CACHE"] = "off"

import flows.fleet as fleet_flow  # noqa: E402

TIMINGS: list[dict] = []
_run_session = fleet_flow._run_session


def _recording(*args, **kwargs):
    out = _run_session(*args, **kwargs)
    if isinstance(out, dict):
        TIMINGS.append(out["timings"])
    return out


def main() -> None:
    import distributed
    from prefect.testing.utilities import prefect_test_harness

    from fieldcal.synthetic.field import wide_field
    from fieldcal.synthetic.session_writer import write_field_session
    from flows.cluster import local_cluster_kwargs

    n = int(sys.argv[1]) if len(sys.argv) > 1 else 12
    fleet_flow._run_session = _recording
    with tempfile.TemporaryDirectory(prefix="fieldcal-bench-standing-") as tmp:
        root = Path(tmp) / "sessions"
        for k in range(n):
            write_field_session(root / f"cam-{k % 4}" / f"2026-01-{k + 1:02d}", wide_field(seed=100 + k),
                                images=False, observations_csv=True, camera_id=f"cam-{k % 4}",
                                acquired=f"2026-01-{k + 1:02d}")
        with prefect_test_harness(server_startup_timeout=120):
            clusters = {m: distributed.LocalCluster(**local_cluster_kwargs(2, {"processes": m == "processes"}))
                        for m in ("threads", "processes")}
            try:
                for m, c in clusters.items():
                    fleet_flow.recalibrate_fleet(f"{tmp}/warm-{m}", root=str(root), dask_address=c.scheduler_address)
                for rnd in range(2):
                    for m in (("threads", "processes") if rnd == 0 else ("processes", "threads")):
                        TIMINGS.clear()
                        t = time.perf_counter()
                        s = fleet_flow.recalibrate_fleet(f"{tmp}/lake-{m}-{rnd}", root=str(root),
                                                         dask_address=clusters[m].scheduler_address)
                        wall = time.perf_counter() - t
                        print(f"{m:9s} round {rnd}: wall {wall:.1f} s, committed {s['n_committed']}, solver_s median "
                              f"{statistics.median(x['solver_s'] for x in TIMINGS):.2f}, session body median "
                              f"{statistics.median(x['total_s'] for x in TIMINGS):.2f}, session run median "
                              f"{statistics.median(e['seconds'] for e in s['sessions']):.2f}, "
                              f"load {os.getloadavg()[0]:.1f}", flush=True)
            finally:
                for c in clusters.values():
                    c.close()


if __name__ == "__main__":
    main()
