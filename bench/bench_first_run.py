"""A fresh clone's first minutes: ``make`` (the install) and the first ``make demo``, before/after.

Clones this repository once per commit into ``--work``, then in each clone times
``make .venv/.installed`` (pip from its cache, and, since ``fieldcal.precompile``, the
compilation of the Numba kernels into their disk cache) and then the first ``make demo``
(its sessions' runs included). The installs run one after the other, then the demos, so
the load falls on both alike. Start the local Prefect server first (``fieldcal server
start --linger 3600``) so that no demo pays for starting it.

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_first_run.py --before afd74e1 --after HEAD
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _timed(argv, cwd: Path, log: Path) -> float:
    t = time.perf_counter()
    with open(log, "w") as out:
        subprocess.run(argv, cwd=cwd, stdout=out, stderr=subprocess.STDOUT, check=True)
    return time.perf_counter() - t


def _runs(log: Path) -> str:
    """The demo's per-session seconds, from its output."""
    lines = [ln.split(":")[0].strip() + " " + ln.split(" in ")[1].split(" ")[0]
             for ln in log.read_text().splitlines() if ": committed " in ln]
    return ", ".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="commit of the 'before' clone")
    ap.add_argument("--after", default="HEAD", help="commit of the 'after' clone (default HEAD)")
    ap.add_argument("--work", default="/tmp/fieldcal-bench-first-run")
    args = ap.parse_args(argv)
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    clones = {}
    for name, commit in (("before", args.before), ("after", args.after)):
        clones[name] = work / name
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clones[name])], check=True)
        subprocess.run(["git", "checkout", "-q", commit], cwd=clones[name], check=True)
    install = {n: _timed(["make", ".venv/.installed"], c, work / f"{n}.install.log") for n, c in clones.items()}
    demo = {n: _timed(["make", "demo"], c, work / f"{n}.demo.log") for n, c in clones.items()}
    print(f"# first run of a fresh clone, {time.strftime('%Y-%m-%d %H:%M')}, load "
          f"{os.getloadavg()[0]:.2f}\n")
    print("| clone | install [s] | first demo [s] | install + demo [s] | the demo's runs [s] |")
    print("|---|---|---|---|---|")
    for n in clones:
        print(f"| {n} ({args.before if n == 'before' else args.after}) | {install[n]:.1f} | {demo[n]:.1f} | "
              f"{install[n] + demo[n]:.1f} | {_runs(work / f'{n}.demo.log')} |")
    print(f"\nfirst demo after / before: {demo['after'] / demo['before']:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
