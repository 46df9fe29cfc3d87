"""Benchmark of the solve step from images: identification vs adjustment, 72-image session.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_identify.py [--rounds 3] [--old REF]

The session is the paper scenario (``paper_field(seed=0)``, 72 images, coded targets) rendered
at raster scale 0.25 (2052 x 1570 px; the targets keep their size in pixels, so every image
shows the same targets as at full size and the solve step has the same work) and measured by
the pipeline's measuring step once; the measurement tables are cached under
``bench/out/identify`` (rendering takes a few minutes with 2 processes).

Timed, each in a fresh subprocess (interleaved rounds, the best of each):

- ``solve``: :func:`fieldcal.pipeline.solve` on the cached measurements, the whole step a
  user waits for (identify, adjust, identify again, adjust again), with its parts from the
  progress lines' time stamps;
- ``solve@REF`` (``--old``): the same with the library of git revision ``REF`` (``git archive``
  into a scratch folder), to compare before / after in one run; the calibrations are compared.

Variants of the session (``--variants``) take away coded targets, so that most images show
0, 1 or 2 markers; they report how many images each code version used.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
OUT = HERE / "out" / "identify"


def _render_chunk(args):
    folder, indices, scale = args
    import pyarrow.parquet as pq

    from fieldcal.pipeline import measure, prepare
    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    sf = scaled_field(paper_field(seed=0), scale)
    write_field_session(folder, sf, images=True, coded=True, image_indices=indices, seed=0,
                        camera_id="ixu150-bench", session_id="paper72", supersample=4)
    prepared = prepare(folder)
    for name in prepared.to_measure:
        pq.write_table(measure(prepared, name), folder / (Path(name).stem + ".parquet"))
    return indices


def prepare_session(folder: Path, procs: int = 2, scale: float = 0.25) -> None:
    """Render and measure the 72 images once (cached)."""
    import multiprocessing
    import shutil

    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    if (folder / "done").exists():
        return
    t = time.perf_counter()
    sf = scaled_field(paper_field(seed=0), scale)
    indices = list(range(len(sf.data.images)))
    scratch = folder.parent / (folder.name + "-parts")
    shutil.rmtree(scratch, ignore_errors=True)
    chunks = [(scratch / f"part{k}", indices[k::procs], scale) for k in range(procs)]
    with multiprocessing.get_context("spawn").Pool(procs) as pool:
        for done in pool.imap_unordered(_render_chunk, chunks):
            print(f"  rendered and measured {len(done)} images", flush=True)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "measurements").mkdir(parents=True, exist_ok=True)
    for part, _, _ in chunks:
        for f in (part / "images").iterdir():
            os.replace(f, folder / "images" / f.name)
        for f in part.glob("*.parquet"):
            os.replace(f, folder / "measurements" / f.name)
    shutil.rmtree(scratch)
    write_field_session(folder, sf, images=False, coded=True, image_indices=indices, seed=0,
                        camera_id="ixu150-bench", session_id="paper72")
    (folder / "done").write_text(f"{time.perf_counter() - t:.1f} s\n")


CHILD = r"""
import json, sys, time
from pathlib import Path
import numpy as np
import pyarrow.parquet as pq
t0 = time.perf_counter()
from fieldcal.pipeline import prepare, solve
folder = Path(sys.argv[1])
drop = json.loads(sys.argv[2])
prepared = prepare(folder)
meas = {}
for name in prepared.to_measure:
    tab = pq.read_table(folder / "measurements" / (Path(name).stem + ".parquet"))
    if drop:
        code = tab.column("code").to_pylist()
        keep = [c is None or c not in drop.get(name, []) for c in code]
        import pyarrow as pa
        tab = tab.filter(pa.array(keep))
    meas[name] = tab
stamps = []
def progress(line):
    stamps.append((time.perf_counter(), line))
t = time.perf_counter()
c = time.process_time()
out = solve(prepared, meas, fingerprint_="sha256:" + "0" * 64, progress=progress)
dt = time.perf_counter() - t
cpu = time.process_time() - c
doc = out.document
print(json.dumps({"solve_s": dt, "cpu_s": cpu, "import_s": t - t0, "params": doc["parameters"],
                  "sigma": doc["sigma"], "n_images": doc["stats"]["n_images"],
                  "n_observations": doc["stats"]["n_observations"],
                  "left_out": len(out.left_out),
                  "summary": doc["stats"].get("identification"),
                  "stamps": [(s - t, line) for s, line in stamps]}))
"""


def run_child(folder: Path, pythonpath: str, drop: dict) -> dict:
    env = dict(os.environ, PYTHONPATH=pythonpath, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", CHILD, str(folder), json.dumps(drop)], env=env,
                         capture_output=True, text=True, cwd=pythonpath)
    if out.returncode:
        return {"error": out.stderr.strip().splitlines()[-1] if out.stderr.strip() else "failed"}
    return json.loads(out.stdout.strip().splitlines()[-1])


def old_library(ref: str) -> str:
    """The library of git revision ``ref`` in a scratch folder (its path)."""
    scratch = Path(tempfile.mkdtemp(prefix="fieldcal-old-"))
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "fieldcal", "schemas"],
                             capture_output=True, check=True).stdout
    subprocess.run(["tar", "-x", "-C", str(scratch)], input=archive, check=True)
    return str(scratch)


def drop_codes(folder: Path, keep_max: int, seed: int = 0) -> dict:
    """Codes to remove per image so that all but every sixth image shows at most ``keep_max``
    markers (a session where most images have 0, 1 or 2 coded targets in view)."""
    import numpy as np
    import pyarrow.parquet as pq

    rng = np.random.default_rng(seed)
    drop = {}
    files = sorted((folder / "measurements").glob("*.parquet"))
    for k, f in enumerate(files):
        if k % 6 == 0:
            continue
        codes = [c for c in pq.read_table(f).column("code").to_pylist() if c is not None]
        if len(codes) > keep_max:
            drop["images/" + f.stem + ".tif"] = [int(c) for c in rng.choice(codes, len(codes) - keep_max,
                                                                            replace=False)]
    return drop


def _ratios(results: dict) -> None:
    """New / old per round (the two ran back to back), wall and CPU."""
    keys = list(results)
    for key in keys:
        if not key.startswith("new"):
            continue
        other = [k for k in keys if k.startswith("old") and k.split(", ", 1)[1] == key.split(", ", 1)[1]]
        if not other:
            continue
        pairs = [(a, b) for a, b in zip(results[key], results[other[0]], strict=False)
                 if "error" not in a and "error" not in b]
        if pairs:
            wall = [a["solve_s"] / b["solve_s"] for a, b in pairs]
            cpu = [a.get("cpu_s", np.nan) / b.get("cpu_s", np.nan) for a, b in pairs]
            print(f"{key.split(', ', 1)[1]}: new/old per round, wall {', '.join(f'{r:.2f}' for r in wall)}; "
                  f"CPU {', '.join(f'{r:.2f}' for r in cpu)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--old", default=None, help="git revision to compare with (e.g. layout)")
    ap.add_argument("--variants", type=int, nargs="*", default=[], help="at most N markers per image")
    args = ap.parse_args()
    folder = OUT / "paper72"
    prepare_session(folder)
    libs = {"new": str(ROOT)}
    if args.old:
        libs[f"old ({args.old})"] = old_library(args.old)
    results: dict = {}
    for variant in [None] + list(args.variants):
        drop = {} if variant is None else drop_codes(folder, variant)
        for r in range(args.rounds):
            for label, path in libs.items():
                res = run_child(folder, path, drop)
                key = f"{label}, " + ("all codes" if variant is None else f"<= {variant} codes in 5/6 images")
                results.setdefault(key, []).append(res)
                print(f"round {r}: {key}: " + (res.get("error") or
                      f"{res['solve_s']:.2f} s, {res['n_images']} images, f {res['params']['f_mm']:.5f}"),
                      flush=True)
    print("\n| run | solve step [s] (best) | CPU [s] (best) | images used | observations | f_mm |")
    print("|---|---|---|---|---|---|")
    for key, rows in results.items():
        ok = [x for x in rows if "error" not in x]
        if not ok:
            print(f"| {key} | failed: {rows[0]['error']} | | | | |")
            continue
        best = min(ok, key=lambda x: x["solve_s"])
        cpu = min(x.get("cpu_s", np.nan) for x in ok)
        print(f"| {key} | {best['solve_s']:.2f} | {cpu:.2f} | {best['n_images']} | {best['n_observations']} | "
              f"{best['params']['f_mm']:.5f} |")
    _ratios(results)
    for key, rows in results.items():
        ok = [x for x in rows if "error" not in x]
        if ok:
            best = min(ok, key=lambda x: x["solve_s"])
            print(f"\n{key}: stages")
            prev = 0.0
            for s, line in best["stamps"]:
                print(f"  {s:7.2f} s (+{s - prev:5.2f})  {line[:110]}")
                prev = s
    (OUT / "results.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
