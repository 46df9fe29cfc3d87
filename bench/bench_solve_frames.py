"""The solve step of the 300-frame session (``bench_flow.py --images 300``) in a fresh process.

Usage (after ``bench_flow.py --images 300`` has measured the frames into ``--lake``)::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_solve_frames.py [--session S] [--lake L]

Reads the cached observations of every frame from the lake and times
:func:`fieldcal.pipeline.solve` (identification, adjustments, blunder rounds, covariance),
the step a user waits for after the images are measured. Run it once per code version
(``PYTHONPATH``) and alternate the versions.
"""

import argparse
import os
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "flow"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--session", default=str(OUT / "paper300"))
    ap.add_argument("--lake", default=str(OUT / "lake-cold"))
    ap.add_argument("--hashes", default=str(OUT / "hashes.sqlite"))
    args = ap.parse_args()
    os.environ["FIELDCAL_HASH_CACHE"] = args.hashes
    from fieldcal import batch, pipeline
    from fieldcal.lake.store import Lake
    from flows.hashcache import known_hashes

    prepared = pipeline.prepare(args.session)
    lake = Lake(args.lake)
    plan = batch.plan_session(prepared, lake, known_hashes(prepared), force=True)
    if plan.todo:
        raise SystemExit(f"{len(plan.todo)} frame(s) not measured in {args.lake}: run bench_flow.py first")
    measurements = batch.read_observations(prepared, lake, dict(plan.cached))
    t, c = time.perf_counter(), time.process_time()
    out = pipeline.solve(prepared, measurements, fingerprint_="sha256:" + "0" * 64)
    doc = out.document
    print(f"solve {time.perf_counter() - t:.2f} s (CPU {time.process_time() - c:.2f} s): "
          f"{doc['stats']['n_images']} images, {doc['stats']['n_observations']} points, "
          f"f {doc['parameters']['f_mm']:.6f} mm")


if __name__ == "__main__":
    main()
