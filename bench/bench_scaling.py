"""Scaling of the fleet over standing worker processes, against one bare process (issue 28, goal 3).

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_scaling.py            # ~8-10 min, quiet
    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_scaling.py --full     # more sessions

Sessions (written once into ``bench/out/scaling/``, reused): image sessions (the field
paper's geometry at a quarter of the resolution, 12 rendered images each in the renderer's
TIFF mix, coded targets) and observations-only sessions (the wide-angle camera, 24 images,
~3200 points each), under two roots. Then, with one Prefect server started first (not
counted):

- **bare**: one fresh Python process (``--bare``, no Prefect, no Dask) warms up as a worker
  does (:func:`flows.calibrate.warm_process`, not counted) and measures every image of the
  image sessions (:func:`fieldcal.batch.measure_many_into_lake`: read, hash, decode,
  extract, one append per session to a local lake): images/s;
- **1 and 2 standing worker processes**: a :class:`distributed.LocalCluster` of single-threaded
  worker processes (fieldcal's worker settings: the preload :mod:`flows.worker`, one BLAS
  thread), started before and warmed by one fleet (not counted); then ``recalibrate_fleet``
  of the image root and of the observations root into a fresh lake, ``--rounds`` times,
  the two cluster sizes alternating.

Printed: one table row per cluster size and kind of session (median wall time over the
rounds, speed-up 1 -> 2, images/s per worker of the whole fleet run and of its measuring
tasks alone against the bare process), and the per-task breakdown asked for by the issue
(each worker's BLAS / OpenMP threads and OpenCV threads, the preload's time, the size and
pickling time of the tasks' arguments, per-image hash and measure time in the bare process
and in the workers). Results also go to ``bench/out/scaling/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("FIELDCAL_REPORTS", "off")
os.environ["FIELDCAL_HASH_CACHE"] = "off"
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")   # no telemetry from the bench's server
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
OUT = HERE / "out" / "scaling"
PICKS = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]      # 12 images: 2 attitudes per station


def make_sessions(n_img: int, n_obs: int) -> tuple[Path, Path]:
    """``(image root, observations root)`` (written once, reused)."""
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    img, obs = OUT / "images", OUT / "observations"
    for k in range(n_img):
        f = img / f"cam-img{k}" / "2026-09-01"
        if not (f / "session.json").is_file():
            t = time.perf_counter()
            write_field_session(f, scaled_field(paper_field(seed=200 + k), 0.25), image_indices=PICKS, coded=True,
                                seed=200 + k, camera_id=f"cam-img{k}", acquired="2026-09-01")
            print(f"  rendered {f} in {time.perf_counter() - t:.0f} s", flush=True)
    for k in range(n_obs):
        f = obs / f"cam-w{k % 4}" / f"2026-08-{k + 1:02d}"
        if not (f / "session.json").is_file():
            write_field_session(f, wide_field(seed=100 + k), images=False, observations_csv=True,
                                camera_id=f"cam-w{k % 4}", acquired=f"2026-08-{k + 1:02d}")
    return img, obs


def warm_root(img_root: Path, obs_root: Path) -> Path:
    """A root of one image and one observations session (copies), to warm a cluster with."""
    import shutil

    warm = OUT / "warm"
    for root in (img_root, obs_root):
        first = session_folders(root)[0]
        target = warm / first.relative_to(root)
        if not (target / "session.json").is_file():
            shutil.copytree(first, target)
    return warm


def session_folders(root: Path) -> list[Path]:
    return sorted(p.parent for p in root.glob("*/*/session.json"))


# --------------------------------------------------------------------------------------
# the bare process
# --------------------------------------------------------------------------------------
def bare(img_root: Path) -> dict:
    """In this process (no Prefect, no Dask): warm up, then measure every image of ``img_root``."""
    from fieldcal import batch, pipeline
    from fieldcal.lake.store import Lake
    from flows.calibrate import warm_process

    t = time.perf_counter()
    warm_process("field", 1)
    warm_s = time.perf_counter() - t
    rows = []
    with tempfile.TemporaryDirectory(prefix="fieldcal-bare-") as tmp:
        lake = Lake(Path(tmp) / "lake")
        t = time.perf_counter()
        for folder in session_folders(img_root):
            prepared = pipeline.prepare(str(folder))
            rows += batch.measure_many_into_lake(prepared, list(prepared.to_measure), lake, {})
        wall = time.perf_counter() - t
    return {"warm_s": warm_s, "wall_s": wall, "n_images": len(rows),
            "n_measured": sum(r["status"] == "measured" for r in rows),
            "hash_s": [r["hash_s"] for r in rows], "measure_s": [r["measure_s"] for r in rows],
            "cpu_s": time.process_time()}


def run_bare(img_root: Path) -> dict:
    """:func:`bare` in a fresh process with the workers' thread settings."""
    from flows.cluster import THREAD_ENV

    env = dict(os.environ, **THREAD_ENV, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, __file__, "--bare", str(img_root)], env=env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# --------------------------------------------------------------------------------------
# the per-task breakdown
# --------------------------------------------------------------------------------------
def blas_threads() -> list[dict]:
    """The thread counts of the OpenBLAS libraries loaded in this process (found in its memory
    map, asked through their own ``*openblas_get_num_threads*``)."""
    import ctypes

    libs = sorted({line.split()[-1] for line in Path("/proc/self/maps").read_text().splitlines()
                   if "openblas" in line.lower() and ".so" in line})
    out = []
    for lib in libs:
        handle = ctypes.CDLL(lib)
        for sym in ("openblas_get_num_threads", "scipy_openblas_get_num_threads64_", "openblas_get_num_threads64_"):
            if hasattr(handle, sym):
                out.append({"api": Path(lib).name, "threads": int(getattr(handle, sym)())})
                break
    return out


def worker_facts() -> dict:
    """Run on a worker: its threads (OpenBLAS pools, OpenCV, Numba) and what it imported."""
    import cv2
    import numba

    pools = blas_threads()
    return {"pid": os.getpid(), "pools": pools, "opencv_threads": cv2.getNumThreads(),
            "numba_threads": numba.get_num_threads(), "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "n_modules": len(sys.modules), "prefect_imported": "prefect.task_engine" in sys.modules,
            "cpu_s": time.process_time()}


def argument_cost(img_root: Path, obs_root: Path) -> dict:
    """Pickled size [bytes] and pickling time [s] of one measuring task's ``prepared`` argument."""
    import cloudpickle

    from fieldcal import pipeline

    out = {}
    for kind, root in (("image", img_root), ("observations", obs_root)):
        prepared = pipeline.prepare(str(session_folders(root)[0]))
        t = time.perf_counter()
        blob = cloudpickle.dumps(prepared, protocol=pickle.HIGHEST_PROTOCOL)
        dump_s = time.perf_counter() - t
        t = time.perf_counter()
        pickle.loads(blob)
        out[kind] = {"bytes": len(blob), "dumps_s": dump_s, "loads_s": time.perf_counter() - t}
    return out


# --------------------------------------------------------------------------------------
# the fleet on standing clusters
# --------------------------------------------------------------------------------------
def start_cluster(n: int):
    import distributed

    from flows.cluster import local_cluster_kwargs

    t = time.perf_counter()
    c = distributed.LocalCluster(**local_cluster_kwargs(n, {"processes": True}))
    with distributed.Client(c.scheduler_address) as client:
        client.wait_for_workers(n, timeout=180)
    return c, time.perf_counter() - t


STALL_S = 30.0
"""A fleet run with no session ending for this long dumps the flow process's stacks (``--stacks``)."""
_last = [time.monotonic(), 0]


def watch_stalls() -> None:
    """Thread: when no session ended for :data:`STALL_S` during a fleet run, write every
    thread's stack of this process to ``bench/out/scaling/stall-K.txt`` (at most 3)."""
    import faulthandler
    import threading

    def loop():
        while _last[1] < 3:
            time.sleep(1.0)
            if RUNNING[0] and time.monotonic() - _last[0] > STALL_S:
                with open(OUT / f"stall-{_last[1]}.txt", "w") as f:
                    faulthandler.dump_traceback(f, all_threads=True)
                _last[0], _last[1] = time.monotonic(), _last[1] + 1

    threading.Thread(target=loop, daemon=True, name="stall-watch").start()


RUNNING = [False]


def fleet_run(address: str, root: Path, lake: str) -> dict:
    import flows.fleet as fleet_flow

    record: list[dict] = []
    run_session = fleet_flow._run_session

    def recording(*args, **kwargs):
        out = run_session(*args, **kwargs)
        _last[0] = time.monotonic()
        if isinstance(out, dict):
            record.append(out)
        return out

    fleet_flow._run_session = recording
    _last[0], RUNNING[0] = time.monotonic(), True
    try:
        t = time.perf_counter()
        s = fleet_flow.recalibrate_fleet(lake, root=str(root), dask_address=address)
        wall = time.perf_counter() - t
    finally:
        fleet_flow._run_session = run_session
        RUNNING[0] = False
    rows = [r for out in record for r in (out.get("measure") or {}).get("rows", [])]
    tasks = [t for out in record for t in (out.get("measure") or {}).get("tasks", [])]
    return {"wall_s": wall, "n_committed": s["n_committed"], "n_failed": s["n_failed"],
            "n_images": sum(r["status"] == "measured" for r in rows),
            "hash_s": [r["hash_s"] for r in rows], "measure_s": [r["measure_s"] for r in rows],
            "task_s": [t["task_s"] for t in tasks], "rss_peak_mb": [t["rss_peak_mb"] for t in tasks],
            "solver_s": [out["timings"].get("solver_s", 0.0) for out in record],
            "session_s": [out["timings"].get("total_s", 0.0) for out in record],
            "load": os.getloadavg()[0]}


def med(xs) -> float:
    return statistics.median(xs) if xs else float("nan")


def table(res: dict) -> str:
    b = res["bare"]
    bare_ips = b["n_images"] / b["wall_s"]
    lines = ["| sessions | worker processes | wall [s] (rounds) | speed-up 1 -> 2 | images/s per worker "
             "(whole fleet) | images/s per worker (measuring tasks) | vs bare process | load |",
             "|---|---|---|---|---|---|---|---|"]
    for kind in ("image", "observations"):
        walls = {n: [r["wall_s"] for r in res["runs"][str(n)][kind]] for n in (1, 2)}
        for n in (1, 2):
            runs = res["runs"][str(n)][kind]
            w = med(walls[n])
            speed = f"{med(walls[1]) / w:.2f}x" if n == 2 else ""
            loads = ", ".join(f"{r['load']:.1f}" for r in runs)
            if kind == "image":
                n_img = runs[0]["n_images"]
                whole = n_img / w / n
                tasks = n_img / (med([sum(r["task_s"]) for r in runs]) or float("nan"))
                cells = f"{whole:.2f} | {tasks:.2f} | {whole / bare_ips:.2f} (tasks {tasks / bare_ips:.2f})"
            else:
                cells = "- | - | -"
            lines.append(f"| {kind} ({res['n_sessions'][kind]}) | {n} | {w:.1f} "
                         f"({', '.join(f'{x:.1f}' for x in walls[n])}) | {speed} | {cells} | {loads} |")
    lines.append(f"| image ({res['n_sessions']['image']}), bare process | - | {b['wall_s']:.1f} | | "
                 f"{bare_ips:.2f} | | 1.00 | {res['bare_load']:.1f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="8 image and 24 observation sessions (default 4 and 12)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--stacks", action="store_true", help=f"dump the stacks when no session ends for {STALL_S:g} s")
    ap.add_argument("--bare", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.stacks:
        OUT.mkdir(parents=True, exist_ok=True)
        watch_stalls()
    if args.bare:
        print(json.dumps(bare(Path(args.bare))))
        return
    from prefect.testing.utilities import prefect_test_harness

    t0 = time.perf_counter()
    n_img, n_obs = (8, 24) if args.full else (4, 12)
    img_root, obs_root = make_sessions(n_img, n_obs)
    warm = warm_root(img_root, obs_root)
    res = {"n_sessions": {"image": n_img, "observations": n_obs}, "load_start": os.getloadavg()[0],
           "runs": {"1": {"image": [], "observations": []}, "2": {"image": [], "observations": []}}}
    res["bare"] = run_bare(img_root)
    res["bare_load"] = os.getloadavg()[0]
    print(f"bare process: {res['bare']['n_images']} images in {res['bare']['wall_s']:.1f} s "
          f"(warm-up {res['bare']['warm_s']:.1f} s), load {res['bare_load']:.1f}", flush=True)
    res["arguments"] = argument_cost(img_root, obs_root)
    with tempfile.TemporaryDirectory(prefix="fieldcal-bench-scaling-") as tmp, \
            prefect_test_harness(server_startup_timeout=180):
        import distributed

        clusters = {}
        try:
            for n in (1, 2):
                clusters[n], start_s = start_cluster(n)
                res.setdefault("cluster_start_s", {})[str(n)] = start_s
                print(f"{n} worker process(es) started in {start_s:.1f} s", flush=True)
            for n, c in clusters.items():
                with distributed.Client(c.scheduler_address) as client:
                    res.setdefault("workers_before", {})[str(n)] = list(client.run(worker_facts).values())
                fleet_run(c.scheduler_address, warm, f"{tmp}/warm-{n}")     # imports, kernels, caches
            for rnd in range(args.rounds):
                for n in ((1, 2) if rnd % 2 == 0 else (2, 1)):
                    for kind, root in (("image", img_root), ("observations", obs_root)):
                        r = fleet_run(clusters[n].scheduler_address, root, f"{tmp}/lake-{n}-{kind}-{rnd}")
                        res["runs"][str(n)][kind].append(r)
                        print(f"round {rnd}: {n} process(es), {kind}: {r['wall_s']:.1f} s, {r['n_committed']} "
                              f"committed, {r['n_failed']} failed, load {r['load']:.1f}", flush=True)
            for n, c in clusters.items():
                with distributed.Client(c.scheduler_address) as client:
                    res.setdefault("workers_after", {})[str(n)] = list(client.run(worker_facts).values())
        finally:
            for c in clusters.values():
                c.close()
    res["total_s"] = time.perf_counter() - t0
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps(res, indent=1))
    print()
    print(table(res))
    print()
    b = res["bare"]
    w = [x for n in ("1", "2") for r in res["runs"][n]["image"] for x in r["measure_s"]]
    wh = [x for n in ("1", "2") for r in res["runs"][n]["image"] for x in r["hash_s"]]
    print(f"per image, median [s]: measure {med(b['measure_s']):.3f} (bare) / {med(w):.3f} (workers); "
          f"hash {med(b['hash_s']):.4f} / {med(wh):.4f}")
    for kind, a in res["arguments"].items():
        print(f"task argument `prepared`, {kind} session: {a['bytes'] / 1e3:.0f} kB pickled, "
              f"dumps {a['dumps_s'] * 1e3:.1f} ms, loads {a['loads_s'] * 1e3:.1f} ms")
    for n in ("1", "2"):
        for f in res["workers_after"][n]:
            pools = ", ".join(f"{p['api']} {p['threads']}" for p in f["pools"])
            print(f"{n}-process cluster, worker pid {f['pid']}: pools {pools}; OpenCV {f['opencv_threads']}, "
                  f"Numba {f['numba_threads']} thread(s)")
        print(f"{n}-process cluster started in {res['cluster_start_s'][n]:.1f} s (not counted)")
    peaks = [x for n in ("1", "2") for r in res["runs"][n]["image"] for x in r["rss_peak_mb"]]
    print(f"peak RSS of a worker (image sessions): {max(peaks):.0f} MiB; whole bench {res['total_s']:.0f} s")


if __name__ == "__main__":
    main()
