"""Reading a session's CSV tables: the reader before issue 17 against the bounded, vectorised one.

Candidates (each in its own process, so that its peak memory can be read; interleaved rounds):

- ``old``: ``read_targets_csv`` / ``read_observations_csv`` of commit 5c66e73 (Python csv,
  a dict per row, a check per cell), loaded from git;
- ``new``: :mod:`fieldcal.session.tables` as a user gets it (pyarrow splits quote-free files);
- ``new-python``: the same with Python's csv tokeniser (what a file with quotes costs).

Files: targets.csv of the paper's size (2 000 targets), of the limit (100 000) and of
1 000 000 (over the limit: the new reader refuses it); observations.csv of the paper's size
(72 images x 2 000 = 144 000 points) and of 2 000 000 (the limit); a 10-million-row
targets.csv (the issue's file; ``old`` is not run on it: the issue measured 8 min 55 s and
12.4 GB). Times are the best of the rounds [s]; memory the peak resident set during the
call above the resident set before it (Linux: VmHWM reset through /proc/self/clear_refs) [MiB].

Usage: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_session_tables.py [--rounds 3]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OLD_COMMIT = "5c66e73"

CHILD = r"""
import json, sys, time, types, subprocess
sys.path.insert(0, {root!r})
import numpy as np
from fieldcal.session.data import FieldImage
from fieldcal.errors import InputError
cand, kind, path, targets_path = sys.argv[1:5]
if cand == "old":
    src = subprocess.run(["git", "-C", {root!r}, "show", {old!r} + ":fieldcal/session/loader.py"],
                         capture_output=True, text=True, check=True).stdout
    mod = types.ModuleType("old_loader"); sys.modules["old_loader"] = mod
    exec(compile(src, "old_loader.py", "exec"), mod.__dict__)
    read_t, read_o = mod.read_targets_csv, mod.read_observations_csv
else:
    from fieldcal.session import tables
    kw = {{"tokeniser": "python" if cand == "new-python" else "auto"}}
    read_t = lambda p: tables.read_targets_csv(p, **kw)
    read_o = lambda *a, **k: tables.read_observations_csv(*a, **k, **kw)
targets = None
if kind == "observations":
    targets = read_t(targets_path) if cand == "old" else tables.read_targets_csv(targets_path)
def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key):
            return int(line.split()[1])
base = status("VmRSS:")
open("/proc/self/clear_refs", "w").write("5")       # reset the peak (VmHWM) to the current size
t0 = time.perf_counter()
try:
    if kind == "targets":
        n = len(read_t(path))
    else:
        n = len(read_o(path, targets, [], default_sigma_px=0.1, allow_new_images=True))
    out = "read"
except InputError as e:
    n, out = 0, "refused: " + e.reason[:60]
dt = time.perf_counter() - t0
peak = status("VmHWM:")
print(json.dumps({{"s": dt, "mib": (peak - base) / 1024, "n": n, "out": out}}))
"""


def write_targets(path: Path, n: int, rng) -> None:
    xyz = np.round(rng.normal(0, 30, (n, 3)), 4)
    with open(path, "w") as fh:
        fh.write("id,X,Y,Z,sigma_mm,code\n")
        for k in range(0, n, 100_000):
            block = xyz[k:k + 100_000]
            fh.writelines(f"T{k + i},{x},{y},{z},2,\n" for i, (x, y, z) in enumerate(block.tolist()))


def write_observations(path: Path, n_images: int, n_targets: int, rng) -> None:
    with open(path, "w") as fh:
        fh.write("image,target_id,u,v,sigma_px\n")
        for i in range(n_images):
            uv = np.round(rng.uniform(0, 8000, (n_targets, 2)), 3)
            fh.writelines(f"images/IMG_{i:04d}.tif,T{t},{u},{v},\n" for t, (u, v) in enumerate(uv.tolist()))


def run(cand: str, kind: str, path: Path, targets_path: Path) -> dict:
    code = CHILD.format(root=str(ROOT), old=OLD_COMMIT)
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code, cand, kind, str(path), str(targets_path)],
                         capture_output=True, text=True, env=env, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        files = {}
        for n in (2_000, 100_000, 1_000_000, 10_000_000):
            files[f"targets {n}"] = ("targets", tmp / f"t{n}.csv")
            write_targets(files[f"targets {n}"][1], n, rng)
        files["observations 144000"] = ("observations", tmp / "o144k.csv")
        write_observations(files["observations 144000"][1], 72, 2_000, rng)
        files["observations 2000000"] = ("observations", tmp / "o2m.csv")
        write_observations(files["observations 2000000"][1], 1_000, 2_000, rng)
        targets_for_obs = tmp / "t2000.csv"
        results: dict[tuple[str, str], list[dict]] = {}
        for _ in range(args.rounds):
            for name, (kind, path) in files.items():
                for cand in ("old", "new", "new-python"):
                    if cand == "old" and name == "targets 10000000":
                        continue
                    results.setdefault((name, cand), []).append(run(cand, kind, path, targets_for_obs))
        print("| file | MiB on disk | candidate | time [s] | peak memory [MiB] | outcome |")
        print("|---|---|---|---|---|---|")
        for (name, cand), rs in results.items():
            size = files[name][1].stat().st_size / 2**20
            best = min(r["s"] for r in rs)
            mem = max(r["mib"] for r in rs)
            out = rs[0]["out"] if rs[0]["out"] != "read" else f"read {rs[0]['n']} rows"
            print(f"| {name} | {size:.1f} | {cand} | {best:.3f} | {mem:.0f} | {out} |")


if __name__ == "__main__":
    main()
