"""Frames measured by two threads of one process, with and without freed memory kept.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_heap.py [--rounds 3] [--frames 72]

Each round runs two fresh processes, alternated: ``default`` (glibc's allocator as it
comes) and ``kept`` (:func:`fieldcal.measure.heap.keep_freed_memory` first, before any
thread exists). Each process
warms the measuring path up (:func:`fieldcal.measure.warm.warm_up_measuring`), then two
threads read, hash, decode and measure the frames of ``bench/out/flow/paper72`` (written by
``bench_flow.py``), odd and even ones, as two in-process Dask workers would. Reported per
process: wall time, CPU time, the first frame of each thread, minor page faults and peak
resident memory.

The same setting as :func:`fieldcal.measure.heap.keep_freed_memory`, which a Dask worker
process applies at its start (``flows.worker``); see ``bench/README_flow.md``, fourth stop.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

CHILD = """
import json, resource, sys, threading, time
mode, folder, n = sys.argv[1], sys.argv[2], int(sys.argv[3])
if mode == "kept":            # before any thread exists (and before NumPy's import)
    from fieldcal.measure.heap import keep_freed_memory
    assert keep_freed_memory()
from pathlib import Path
from fieldcal.measure.imageio import read_file
from fieldcal.measure.targets import measure_image
from fieldcal.measure.warm import warm_up_measuring
warm_up_measuring()
frames = sorted(Path(folder, "images").glob("*.tif"))[:n]
firsts = [None, None]

def work(k):
    for i, path in enumerate(frames[k::2]):
        t = time.perf_counter()
        measure_image(read_file(path))
        if i == 0:
            firsts[k] = time.perf_counter() - t

ru0 = resource.getrusage(resource.RUSAGE_SELF)
t, c = time.perf_counter(), time.process_time()
threads = [threading.Thread(target=work, args=(k,)) for k in (0, 1)]
for th in threads:
    th.start()
for th in threads:
    th.join()
ru1 = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"wall_s": time.perf_counter() - t, "cpu_s": time.process_time() - c, "first_s": firsts,
                  "faults": ru1.ru_minflt - ru0.ru_minflt, "peak_mib": ru1.ru_maxrss / 1024, "frames": len(frames)}))
"""


def run(mode: str, folder: Path, frames: int) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, mode, str(folder), str(frames)], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    if out.returncode != 0:
        raise SystemExit(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=72)
    ap.add_argument("--session", default=str(HERE / "out" / "flow" / "paper72"))
    args = ap.parse_args()
    folder = Path(args.session)
    if not (folder / "session.json").is_file():
        raise SystemExit(f"{folder}: no session; run bench/bench_flow.py first (it renders the frames)")
    results: dict = {"default": [], "kept": []}
    for r in range(args.rounds):
        for mode in (("default", "kept") if r % 2 == 0 else ("kept", "default")):
            res = run(mode, folder, args.frames)
            results[mode].append(res)
            print(f"round {r + 1} {mode:8s} wall {res['wall_s']:.2f} s, CPU {res['cpu_s']:.2f} s, first frames "
                  f"{res['first_s'][0]:.2f} / {res['first_s'][1]:.2f} s, {res['faults']} page faults, "
                  f"peak {res['peak_mib']:.0f} MiB", flush=True)
    print()
    print("| allocator | wall [s], median (min-max) | CPU [s] | first frame per thread [s] | minor page faults | "
          "peak RSS [MiB] |")
    print("|---|---|---|---|---|---|")
    for mode, rows in results.items():
        def rng(key, fmt="{:.2f}", rows=rows):
            v = [row[key] for row in rows]
            return f"{fmt.format(statistics.median(v))} ({fmt.format(min(v))}-{fmt.format(max(v))})"
        firsts = [x for row in rows for x in row["first_s"]]
        print(f"| {mode} | {rng('wall_s')} | {rng('cpu_s')} | {min(firsts):.2f}-{max(firsts):.2f} | "
              f"{rng('faults', '{:.0f}')} | {rng('peak_mib', '{:.0f}')} |")
    (HERE / "out" / "heap.json").write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
