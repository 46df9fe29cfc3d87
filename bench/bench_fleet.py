"""The fleet in parallel: 24 sessions through one ``recalibrate_fleet`` against the same work one by one.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_fleet.py [--rounds 2] [--cli]

The fleet (issue 13, goal 3): 20 observations-only field sessions (the wide-angle camera,
24 images and ~3200 points each, 5 cameras, different seeds) and 4 sessions of rendered
images (the field paper's geometry at a quarter of the resolution, 12 images each with
coded targets; rendered once into ``bench/out/fleet/sessions`` and reused), under one root.
Each run starts from an empty lake and an empty hash store, with one Prefect server started
first (not counted) and 2 Dask workers:

- **fleet, threads**: ``recalibrate_fleet`` (what ``fieldcal fleet`` runs): sessions
  several at once on one local cluster of 2 single-threaded workers in the flow's process;
- **fleet, processes**: the same with 2 worker processes (``--processes``);
- **one by one**: ``calibrate_session`` for each session in turn, in one process, each with
  its own local cluster as ``fieldcal run`` makes it (the work of 24 ``fieldcal run``
  without the 24 process starts);
- with ``--cli``: **24 x ``fieldcal run``**, one command per session, as a shell loop would.

Rounds interleave the candidates (the machine is shared); the table gives each one's
wall times and their ratio to the fleet. Results go to ``bench/out/fleet/results.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
N_OBS, N_IMG = 20, 4


def make_sessions(root: Path) -> list[Path]:
    """The 24 session folders (written once, reused)."""
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    folders = []
    for k in range(N_OBS):
        f = root / f"cam-w{k % 5}" / f"2026-08-{k + 1:02d}"
        if not (f / "session.json").is_file():
            write_field_session(f, wide_field(seed=100 + k), images=False, observations_csv=True,
                                camera_id=f"cam-w{k % 5}", acquired=f"2026-08-{k + 1:02d}")
        folders.append(f)
    picks = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]      # 2 attitudes per station
    for k in range(N_IMG):
        f = root / f"cam-img{k}" / "2026-09-01"
        if not (f / "session.json").is_file():
            t = time.perf_counter()
            write_field_session(f, scaled_field(paper_field(seed=200 + k), 0.25), image_indices=picks, coded=True,
                                seed=200 + k, camera_id=f"cam-img{k}", acquired="2026-09-01")
            print(f"  rendered {f} in {time.perf_counter() - t:.0f} s", flush=True)
        folders.append(f)
    return folders


def fresh(out: Path, name: str) -> Path:
    lake = out / name
    shutil.rmtree(lake, ignore_errors=True)
    (out / "hashes.sqlite").unlink(missing_ok=True)
    return lake


def run_fleet(out: Path, root: Path, processes: bool) -> tuple[float, dict]:
    from flows.fleet import recalibrate_fleet

    lake = fresh(out, "lake-fleet")
    t = time.perf_counter()
    summary = recalibrate_fleet(str(lake), str(root), n_workers=2,
                                cluster_kwargs={"processes": True} if processes else None)
    wall = time.perf_counter() - t
    assert summary["n_committed"] == N_OBS + N_IMG, summary
    return wall, {"per_session_s": [s["seconds"] for s in summary["sessions"]]}


def run_one_by_one(out: Path, folders: list[Path]) -> tuple[float, dict]:
    from flows import cluster
    from flows.calibrate import calibrate_session

    lake = fresh(out, "lake-one")
    t = time.perf_counter()
    per = []
    for f in folders:
        t1 = time.perf_counter()
        r = calibrate_session.with_options(task_runner=cluster.task_runner(None, 2))(str(f), str(lake))
        assert r["status"] == "committed"
        per.append(time.perf_counter() - t1)
    return time.perf_counter() - t, {"per_session_s": per}


def run_cli(out: Path, folders: list[Path], api: str) -> tuple[float, dict]:
    lake = fresh(out, "lake-cli")
    env = dict(os.environ, PREFECT_API_URL=api)
    t = time.perf_counter()
    for f in folders:
        subprocess.run([FIELDCAL, "run", str(f), "--lake", str(lake)], env=env, check=True, capture_output=True)
    return time.perf_counter() - t, {}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(HERE / "out" / "fleet"))
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--cli", action="store_true", help="also 24 x `fieldcal run` (one round)")
    args = ap.parse_args()
    out = Path(args.out)
    root = out / "sessions"
    folders = make_sessions(root)
    os.environ["FIELDCAL_HASH_CACHE"] = str(out / "hashes.sqlite")
    os.environ.setdefault("PREFECT_HOME", str(out / "prefect-home"))
    from fieldcal import progress
    from flows.server import prefect_api, quiet_prefect

    quiet_prefect(verbose=False)
    res: dict[str, list[float]] = {}
    t = time.perf_counter()
    with prefect_api() as api, progress.quiet():
        print(f"Prefect API {api} ready in {time.perf_counter() - t:.1f} s", flush=True)
        for r in range(args.rounds):
            for name, fn in (("fleet, threads (default)", lambda: run_fleet(out, root, False)),
                             ("one by one (calibrate_session per session)", lambda: run_one_by_one(out, folders)),
                             ("fleet, processes", lambda: run_fleet(out, root, True))):
                wall, _ = fn()
                res.setdefault(name, []).append(wall)
                print(f"round {r + 1}: {name}: {wall:.1f} s (load {os.getloadavg()[0]:.1f})", flush=True)
        if args.cli:
            wall, _ = run_cli(out, folders, api)
            res["24 x `fieldcal run`"] = [wall]
            print(f"24 x fieldcal run: {wall:.1f} s", flush=True)
    ref = statistics.median(res["fleet, threads (default)"])
    (out / "results.json").write_text(json.dumps({"seconds": res, "loadavg": os.getloadavg()}, indent=2) + "\n")
    print(f"\n{N_OBS} observations-only sessions + {N_IMG} image sessions (12 images each), 2 workers; "
          f"load average {os.getloadavg()[0]:.1f}")
    print("| run | wall time [s] (rounds) | median / fleet |\n|---|---|---|")
    for name, v in res.items():
        print(f"| {name} | {', '.join(f'{x:.1f}' for x in v)} | {statistics.median(v) / ref:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
