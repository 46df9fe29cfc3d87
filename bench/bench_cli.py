"""What each path of ``fieldcal run`` costs, from a shell: refusals, reruns, the Prefect server.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_cli.py [--rounds 3]

Every figure is the wall time of a real ``fieldcal`` process (Python start and imports
included), on one small observations-only session (the wide-angle camera: 24 images, 3200
points) in a fresh lake, in rounds so that the machine's load spreads over the paths:

- **bad session** (a missing folder; a targets.csv with text in a number): refused with exit
  status 2, Prefect's API pointing at a port where nothing listens;
- **rerun, unchanged**: the version is answered from the lake (no server; the API points
  nowhere either);
- **run, no server running**: no ``PREFECT_API_URL``: the command starts the local server
  and leaves it running (its start is part of this figure; the first round with a fresh
  ``PREFECT_HOME``, whose database is created then, the others after ``fieldcal server stop``);
- **run, local server kept**: the next command finds that server (``--force``: a new version);
- **run, standing server**: ``PREFECT_API_URL`` of a ``prefect server start`` (``--force``);
- **in-process, no Prefect**: ``pipeline.prepare`` + ``solve`` + ``Lake.commit`` in one
  process (the work itself; the difference to the runs above is the command's and
  Prefect's overhead).

Results go to ``bench/out/cli/results.json`` and, as a table, to standard output.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))
PREFECT = str(Path(sys.executable).with_name("prefect"))


def timed(argv, env, expect: int) -> float:
    t = time.perf_counter()
    out = subprocess.run(argv, env=env, capture_output=True, text=True, cwd=ROOT)
    dt = time.perf_counter() - t
    if out.returncode != expect:
        raise SystemExit(f"{' '.join(map(str, argv))}: exit {out.returncode}, expected {expect}: {out.stderr}")
    return dt


def in_process(session: Path, lake: Path) -> float:
    code = ("import sys, time\nt = time.perf_counter()\nfrom fieldcal import pipeline\n"
            "from fieldcal.lake.store import Lake\np = pipeline.prepare(sys.argv[1])\n"
            "o = pipeline.solve(p, {}, fingerprint_=pipeline.input_fingerprint(p, {}))\n"
            "Lake(sys.argv[2]).commit(o.document, o.arrays, o.residuals, force=True, array_attrs=o.array_attrs)\n"
            "print(time.perf_counter() - t)\n")
    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", code, str(session), str(lake)], check=True, capture_output=True,
                   env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
    return time.perf_counter() - t


def standing_server(home: Path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = dict(os.environ, PREFECT_HOME=str(home), PREFECT_UI_ENABLED="false",
               PREFECT_SERVER_ANALYTICS_ENABLED="false")
    proc = subprocess.Popen([PREFECT, "server", "start", "--host", "127.0.0.1", "--port", str(port)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    import httpx

    url = f"http://127.0.0.1:{port}/api"
    while True:
        try:
            if httpx.get(f"{url}/health", timeout=5).status_code == 200:
                return proc, url
        except httpx.HTTPError:
            time.sleep(0.5)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=str(HERE / "out" / "cli"))
    args = ap.parse_args()
    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    from fieldcal.synthetic.field import wide_field
    from fieldcal.synthetic.session_writer import write_field_session

    session = out / "wall"
    write_field_session(session, wide_field(seed=1), images=False, observations_csv=True, camera_id="cam-bench")
    bad = out / "bad"
    shutil.copytree(session, bad)
    lines = (bad / "targets.csv").read_text().splitlines()
    lines[3] = lines[3].split(",")[0] + ",not-a-number,1,2,,"
    (bad / "targets.csv").write_text("\n".join(lines) + "\n")
    base = {k: v for k, v in os.environ.items() if not k.startswith(("PREFECT_", "FIELDCAL_"))}
    base.update(OPENBLAS_NUM_THREADS="1", FIELDCAL_HASH_CACHE=str(out / "hashes.sqlite"),
                FIELDCAL_SERVER_LINGER_S="3600")
    nowhere = dict(base, PREFECT_API_URL="http://127.0.0.1:9/api", PREFECT_HOME=str(out / "nowhere"))
    lake = out / "lake"
    server, url = standing_server(out / "standing-home")
    standing = dict(base, PREFECT_API_URL=url, PREFECT_HOME=str(out / "standing-home"))
    res: dict[str, list[float]] = {}
    try:
        local = dict(base, PREFECT_HOME=str(out / "local-home"))
        for r in range(args.rounds):
            first = ("run, no server yet, fresh PREFECT_HOME (starts the local server, creates its database)" if r == 0
                     else "run, no server running (starts the local server)")
            res.setdefault(first, []).append(timed([FIELDCAL, "run", session, "--lake", lake, "--force"], local, 0))
            res.setdefault("run, local server kept", []).append(
                timed([FIELDCAL, "run", session, "--lake", lake, "--force"], local, 0))
            res.setdefault("run, standing server (PREFECT_API_URL)", []).append(
                timed([FIELDCAL, "run", session, "--lake", lake, "--force"], standing, 0))
            res.setdefault("rerun, unchanged (no server)", []).append(
                timed([FIELDCAL, "run", session, "--lake", lake], nowhere, 0))
            res.setdefault("bad session: missing folder (no server)", []).append(
                timed([FIELDCAL, "run", out / "missing", "--lake", lake], nowhere, 2))
            res.setdefault("bad session: text in targets.csv (no server)", []).append(
                timed([FIELDCAL, "run", bad, "--lake", lake], nowhere, 2))
            res.setdefault("in-process, no Prefect (prepare + solve + commit)", []).append(
                in_process(session, out / "lake-plain"))
            subprocess.run([FIELDCAL, "server", "stop"], env=local, capture_output=True)
            print(f"round {r + 1}: " + ", ".join(f"{v[-1]:.1f}" for v in res.values()), flush=True)
    finally:
        os.killpg(server.pid, signal.SIGINT)
        server.wait(timeout=60)
    load = os.getloadavg()
    (out / "results.json").write_text(json.dumps({"seconds": res, "loadavg": load}, indent=2))
    print(f"\nload average at the end: {load[0]:.1f} / {load[1]:.1f} / {load[2]:.1f}")
    print("| path | wall time [s], median (min-max) |\n|---|---|")
    for name, v in res.items():
        print(f"| {name} | {statistics.median(v):.1f} ({min(v):.1f}-{max(v):.1f}) |")


if __name__ == "__main__":
    main()
