"""End-to-end benchmark of the calibration flow: 72 full-size field images, 2 Dask workers.

Usage::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python bench/bench_flow.py [--images 72]

The session is the field paper's geometry at full size (Phase One iXU150-like camera,
8208 x 6280 px 16-bit TIFFs in the renderer's mix of layouts: tiled zstd, striped
uncompressed, tiled deflate BigTIFF, striped uncompressed BigTIFF; coded targets), rendered
once into ``bench/out/flow/paper72`` (about 10 minutes on two processes, ~6 GB) and reused.
``--images N`` above 72 (e.g. 300, ~27 GB): the 72 views once as rendered, then repeated
exposures from the same poses with fresh sensor noise (:func:`repeat_session`), written
once into ``bench/out/flow/paperN`` and reused.

Runs, each through :func:`flows.calibrate.calibrate_session` on one Prefect server that is
started first (its start is timed and reported separately):

1. **cold**: a fresh lake and hash store, the embedded default: the flow's local Dask
   cluster of 2 single-threaded workers inside the flow's process, measures all images,
   solves, commits;
2. **rerun**: the same session again, unchanged (the no-op: no image is read);
3. **processes**: a fresh lake, every image hashed again, the flow's local cluster made of
   2 single-threaded worker processes that it starts and stops (``fieldcal run --processes``);
4. **warm cluster**: a fresh lake with every image hashed again, on a standing 2-worker
   local cluster (processes) started beforehand (a deployment's situation), so the
   cluster's start is not in the flow's time.

For each: wall time, images per second, peak resident memory per worker (``VmHWM`` of the
worker process, its libraries included), and the share of the wall time outside
reading, extraction and solving::

    useful  = (sum of hashing + read-and-measure time over the images) / workers + solver time
    outside = wall - useful      (cluster start, Prefect, Dask, Parquet writes and reads,
                                  the Zarr/Parquet commit, idle workers)

Hashing the image bytes counts as reading. The images sit in the page cache (they were
just rendered or read), as in ``bench/README_extract.md``. Results go to
``bench/out/flow/results.json`` and, as a table, to standard output.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
if "--keep-freed-memory" in sys.argv:    # before any thread allocates (fieldcal.measure.heap)
    sys.path.insert(0, str(ROOT))
    from fieldcal.measure.heap import keep_freed_memory

    keep_freed_memory()
VIEWS = 72
"""Views of the field scene (``paper_field``); larger sessions repeat them (:func:`repeat_session`)."""


def _render_chunk(args):
    """Render some images of the session into a scratch folder (one process of the pool)."""
    folder, indices, seed = args
    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.session_writer import write_field_session

    write_field_session(folder, paper_field(seed=seed), images=True, coded=True, image_indices=indices,
                        seed=seed, camera_id="ixu150-bench", session_id="paper72")
    return indices


def render_session(folder: Path, n_images: int, procs: int, seed: int = 0) -> float:
    """Write the full-size session (images rendered by ``procs`` processes); returns seconds."""
    import multiprocessing

    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.session_writer import write_field_session

    t = time.perf_counter()
    sf = paper_field(seed=seed)
    step = len(sf.data.images) / n_images
    indices = sorted({int(i * step) for i in range(n_images)})
    scratch = folder.parent / (folder.name + "-parts")
    shutil.rmtree(scratch, ignore_errors=True)
    chunks = [(scratch / f"part{k}", indices[k::procs], seed) for k in range(procs)]
    with multiprocessing.get_context("spawn").Pool(procs) as pool:
        for done in pool.imap_unordered(_render_chunk, chunks):
            print(f"  rendered {len(done)} images", flush=True)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    for part, _, _ in chunks:
        for f in (part / "images").iterdir():
            os.replace(f, folder / "images" / f.name)
    shutil.rmtree(scratch)
    # the manifest and targets.csv listing every image (nothing rendered here)
    write_field_session(folder, sf, images=False, coded=True, image_indices=indices, seed=seed,
                        camera_id="ixu150-bench", session_id="paper72")
    return time.perf_counter() - t


def _repeat_chunk(args):
    """Write some repeated exposures (one process of the pool): the base view's pixels with
    fresh sensor noise (+-1 DN, uniform), in the renderer's TIFF layout of its position."""
    import numpy as np
    import tifffile

    from fieldcal.synthetic.session_writer import TIFF_LAYOUTS

    base, folder, jobs = args
    for k, source, seed in jobs:
        pixels = tifffile.imread(base / source)
        noise = np.random.default_rng(seed).integers(-1, 2, pixels.shape, dtype=np.int32)
        pixels = np.clip(pixels.astype(np.int32) + noise, 0, np.iinfo(pixels.dtype).max).astype(pixels.dtype)
        layout = TIFF_LAYOUTS[k % len(TIFF_LAYOUTS)]
        kw = {"tile": layout["tile"]} if layout["tile"] else {"rowsperstrip": 64}
        tifffile.imwrite(folder / f"images/repeat_{k:04d}.tif", pixels, photometric="minisblack",
                         bigtiff=layout["bigtiff"], metadata=None, compression=layout["compression"], **kw)
    return len(jobs)


def repeat_session(base: Path, folder: Path, n_images: int, procs: int) -> float:
    """A session of ``n_images`` frames from the rendered views of ``base``: every view once as
    rendered (hard links), then again as repeated exposures from the same pose with fresh
    sensor noise (new pixel content, so each frame is hashed and measured), in the
    renderer's mix of TIFF layouts. Rendering 300 new views would take ~40 min of both
    cores here (6.9-9.8 s per frame); a repeat takes ~1 s. Returns seconds."""
    import multiprocessing

    t = time.perf_counter()
    manifest = json.loads((base / "session.json").read_text())
    views = manifest["images"]
    (folder / "images").mkdir(parents=True, exist_ok=True)
    shutil.copy2(base / "targets.csv", folder / "targets.csv")
    entries, jobs = [], []
    for k in range(n_images):
        view = views[k % len(views)]
        if k < len(views):
            dst = folder / view["file"]
            if not dst.exists():
                os.link(base / view["file"], dst)
            entries.append(dict(view))
        else:
            entries.append({**view, "file": f"images/repeat_{k:04d}.tif"})
            if not (folder / entries[-1]["file"]).exists():
                jobs.append((k, view["file"], 1000 + k))
    with multiprocessing.get_context("spawn").Pool(procs) as pool:
        for done in pool.imap_unordered(_repeat_chunk, [(base, folder, jobs[i::procs]) for i in range(procs)]):
            print(f"  wrote {done} repeated exposures", flush=True)
    manifest.update(images=entries, session_id=f"paper{n_images}")
    (folder / "session.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return time.perf_counter() - t


def analyse(result: dict, wall_s: float) -> dict:
    """Wall time, throughput, memory and the share outside reading / extraction / solving."""
    m = result["measure"]
    t = result["timings"]
    out = {"wall_s": wall_s, "status": result["status"], "version": result["version"],
           "images": result["images"], "timings": t}
    n = result["images"]["total"]
    out["images_per_s"] = n / wall_s if wall_s > 0 else None
    solver = t.get("solver_s", 0.0)
    if m is None:
        out.update(useful_s=solver, outside_s=wall_s - solver, outside_share=(wall_s - solver) / wall_s)
        return out
    rows = m["rows"]
    w = m["n_workers"]
    hash_s = sum(r["hash_s"] for r in rows)
    measure_s = sum(r["measure_s"] for r in rows)
    write_s = sum(r["write_s"] for r in rows)
    task_s = sum(task["task_s"] for task in m["tasks"])
    useful = (hash_s + measure_s) / w + solver
    per_worker = {}
    for task in m["tasks"]:
        per_worker[task["worker"]] = max(per_worker.get(task["worker"], 0.0), task["rss_peak_mb"])
    measured = [r for r in rows if r["status"] == "measured"]
    out.update(
        n_workers=w, batches=m.get("batches"), n_tasks=len(m["tasks"]), estimate=m["estimate"],
        cluster_s=m["cluster_s"], hash_s_sum=hash_s, measure_s_sum=measure_s, parquet_write_s_sum=write_s,
        measure_s_median=statistics.median([r["measure_s"] for r in measured]) if measured else None,
        useful_s=useful, outside_s=wall_s - useful, outside_share=(wall_s - useful) / wall_s,
        peak_rss_mb_per_worker=per_worker,
        outside_items={
            "cluster start": m["cluster_s"],
            "Delta appends of observations (per worker)": write_s / w,
            "observations read back (Parquet)": t.get("read_observations_s", 0.0),
            "commit (Zarr, Parquet, JSON)": t.get("commit_s", 0.0),
            "validate + lookup": t.get("validate_s", 0.0) + t.get("lookup_s", 0.0),
            "flow run start + end": wall_s - t.get("total_s", wall_s),
            "warm-up of the flow's process (imports, kernels; in-process workers)": t.get("warm_s", 0.0),
            "cluster shutdown (before: and the sub-flow's start + end)":
                t.get("measure_s", 0.0) - m.get("body_s", 0.0) - t.get("warm_s", 0.0),
            "in tasks, besides hashing / measuring / writing (per worker)": (task_s - hash_s - measure_s - write_s) / w,
            **_waiting(m, w),
        })
    out["first_rows"] = [{k: r.get(k) for k in ("image", "status", "hash_s", "measure_s", "write_s")}
                         for r in rows[:w]]
    out["timeline"] = sorted((str(task["worker"]), round(task["start_unix"] - m["start_unix"], 3),
                              round(task["end_unix"] - m["start_unix"], 3), task["n"], round(task["submit_s"], 3))
                             for task in m["tasks"])
    known = sum(out["outside_items"].values())
    out["outside_items"]["the rest (flow bookkeeping)"] = out["outside_s"] - known
    return out


def _waiting(m: dict, w: int) -> dict:
    """Per worker [s]: the gaps before and between its tasks (Prefect's task runs, Dask's
    dispatch), and its tail (idle from its last task's end to the end of the fan-out)."""
    by_worker: dict = {}
    for task in m["tasks"]:
        by_worker.setdefault(task["worker"], []).append((task["start_unix"], task["end_unix"]))
    gaps = tail = 0.0
    for spans in by_worker.values():
        spans.sort()
        ends = [m["start_unix"]] + [end for _, end in spans[:-1]]
        gaps += sum(max(0.0, start - end) for (start, _), end in zip(spans, ends, strict=True))
        tail += max(0.0, m["end_unix"] - spans[-1][1])
    return {"workers waiting before / between tasks (per worker)": gaps / w,
            "workers idle after their last task (per worker)": tail / w}


def _sizes(d: dict) -> str:
    return ", ".join(str(x) for x in d["batches"])


def table(results: dict) -> str:
    runs = [("cold", "cold: 2 workers in the flow's process (default)"), ("rerun", "rerun, unchanged"),
            ("threads", "processes: the flow starts 2 worker processes"), ("warm", "warm: standing 2-process cluster")]
    runs = [(k, title) for k, title in runs if k in results]
    lines = ["| quantity | " + " | ".join(t for _, t in runs) + " |", "|---" * (len(runs) + 1) + "|"]

    def row(label, fn):
        cells = []
        for k, _ in runs:
            try:
                v = fn(results[k])
            except (KeyError, TypeError, ZeroDivisionError):
                v = None
            cells.append("-" if v is None else v)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")

    row("wall time [s]", lambda d: f"{d['wall_s']:.2f}" if d["wall_s"] < 10 else f"{d['wall_s']:.1f}")
    row("images per second", lambda d: f"{d['images_per_s']:.2f}" if d.get("measure_s_sum") else None)
    row("read + extract, sum over images [s]", lambda d: f"{d['measure_s_sum']:.1f}")
    row("hashing, sum over images [s]", lambda d: f"{d['hash_s_sum']:.1f}")
    row("read + extract per image, median [s]", lambda d: f"{d['measure_s_median']:.3f}")
    row("solver [s]", lambda d: f"{d['timings']['solver_s']:.1f}")
    row("outside reading / extraction / solving [s]", lambda d: f"{d['outside_s']:.1f}")
    row("**share outside**", lambda d: f"**{d['outside_share']:.1%}**" if d.get("measure_s_sum") else None)
    for key in ("warm-up of the flow's process (imports, kernels; in-process workers)", "cluster start",
                "cluster shutdown (before: and the sub-flow's start + end)", "flow run start + end",
                "Delta appends of observations (per worker)", "observations read back (Parquet)",
                "commit (Zarr, Parquet, JSON)",
                "validate + lookup", "in tasks, besides hashing / measuring / writing (per worker)",
                "workers waiting before / between tasks (per worker)",
                "workers idle after their last task (per worker)",
                "the rest (flow bookkeeping)"):
        row(f"&nbsp;&nbsp;{key} [s]", lambda d, key=key: f"{d['outside_items'][key]:.2f}")
    row("tasks (images per task)", lambda d: f"{d['n_tasks']} ({_sizes(d)})")
    row("peak RSS per worker process [MiB] (threads: of the whole flow process, solver included)",
        lambda d: ", ".join(f"{v:.0f}" for v in d["peak_rss_mb_per_worker"].values()) or None)
    row("time / first run", lambda d: f"**{d['wall_s'] / results['cold']['wall_s']:.1%}**")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(HERE / "out" / "flow"))
    ap.add_argument("--images", type=int, default=72)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep-freed-memory", action="store_true",
                    help="glibc keeps freed memory in this process too, set at its start, as `fieldcal run` "
                         "with in-process workers does (fieldcal.measure.heap)")
    ap.add_argument("--batch-size", type=int, default=None,
                    help="fixed batches of this many images in the cold run (default: one task per worker "
                         "thread pulling the images from a queue)")
    ap.add_argument("--render-procs", type=int, default=2)
    ap.add_argument("--skip", action="append", default=[], choices=("cold", "rerun", "threads", "warm"))
    args = ap.parse_args()
    out = Path(args.out)
    session = out / f"paper{args.images}"
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"images": args.images, "workers": args.workers}

    n_have = len(list((session / "images").glob("*.tif"))) if (session / "images").is_dir() else 0
    if args.images > VIEWS and (not (session / "session.json").is_file() or n_have < args.images):
        base = out / f"paper{VIEWS}"
        if not (base / "session.json").is_file():
            results["render_s"] = render_session(base, VIEWS, args.render_procs)
        print(f"writing {args.images} frames into {session} from the {VIEWS} views ...", flush=True)
        results["repeat_s"] = repeat_session(base, session, args.images, args.render_procs)
    elif not (session / "session.json").is_file() or n_have < args.images:
        print(f"rendering {args.images} full-size images into {session} ...", flush=True)
        shutil.rmtree(session, ignore_errors=True)
        results["render_s"] = render_session(session, args.images, args.render_procs)
    size = sum(f.stat().st_size for f in (session / "images").glob("*.tif"))
    results["session_bytes"] = size
    print(f"session: {session} ({size / 2**30:.2f} GiB)", flush=True)

    os.environ["FIELDCAL_HASH_CACHE"] = str(out / "hashes.sqlite")
    from flows.server import prefect_api, quiet_prefect

    quiet_prefect(verbose=False)
    t = time.perf_counter()
    with prefect_api() as url:
        results["prefect_server_s"] = time.perf_counter() - t
        results["prefect_api"] = url
        print(f"Prefect API {url} ready in {results['prefect_server_s']:.1f} s", flush=True)
        from flows.calibrate import calibrate_session

        lake = out / "lake-cold"
        if "cold" not in args.skip:
            shutil.rmtree(lake, ignore_errors=True)
            Path(os.environ["FIELDCAL_HASH_CACHE"]).unlink(missing_ok=True)
            t = time.perf_counter()
            r = calibrate_session(str(session), str(lake), n_workers=args.workers, batch_size=args.batch_size)
            results["cold"] = analyse(r, time.perf_counter() - t)
            print(f"cold: {results['cold']['wall_s']:.1f} s, outside share {results['cold']['outside_share']:.1%}",
                  flush=True)
        if "rerun" not in args.skip:
            t = time.perf_counter()
            r = calibrate_session(str(session), str(lake), n_workers=args.workers)
            results["rerun"] = analyse(r, time.perf_counter() - t)
            print(f"rerun: {results['rerun']['wall_s']:.2f} s ({r['status']})", flush=True)
        if "threads" not in args.skip:
            lake_t = out / "lake-processes"
            shutil.rmtree(lake_t, ignore_errors=True)
            t = time.perf_counter()
            r = calibrate_session(str(session), str(lake_t), n_workers=args.workers, rehash=True,
                                  cluster_kwargs={"processes": True})
            results["threads"] = analyse(r, time.perf_counter() - t)
            print(f"processes: {results['threads']['wall_s']:.1f} s, outside share "
                  f"{results['threads']['outside_share']:.1%}", flush=True)
        if "warm" not in args.skip:
            import distributed

            from flows.cluster import local_cluster_kwargs

            t = time.perf_counter()
            with distributed.LocalCluster(**local_cluster_kwargs(args.workers, {"processes": True})) as cluster:
                results["standing_cluster_start_s"] = time.perf_counter() - t
                lake_w = out / "lake-warm"
                shutil.rmtree(lake_w, ignore_errors=True)
                t = time.perf_counter()
                r = calibrate_session(str(session), str(lake_w), dask_address=cluster.scheduler_address,
                                      rehash=True)
                results["warm"] = analyse(r, time.perf_counter() - t)
            print(f"warm: {results['warm']['wall_s']:.1f} s, outside share "
                  f"{results['warm']['outside_share']:.1%}", flush=True)
    (out / "results.json").write_text(json.dumps(results, indent=2, default=str) + "\n")
    print()
    print(f"Prefect local server start (once, not in the times below): {results['prefect_server_s']:.1f} s")
    if "standing_cluster_start_s" in results:
        print(f"standing cluster start (before the warm run): {results['standing_cluster_start_s']:.1f} s")
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
