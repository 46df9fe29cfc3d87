"""A fleet night on an object store: sessions and lake on S3 (moto), a standing cluster (issue 28, goal 5).

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_fleet_night.py [--scale 0.25] [--obs 100]

The root holds 10 image sessions (the field paper's geometry at ``--scale`` of its
resolution, 12 rendered images each in the renderer's TIFF mix, coded targets; rendered once
into ``bench/out/night/``) and ``--obs`` observations-only sessions (the wide-angle camera, 24
images, ~3200 points each), uploaded to a moto S3 server that runs in a process of its own
on loopback (not counted). The server counts every request it answers and the bytes in
and out, by kind (GET, PUT, HEAD, LIST, POST, DELETE) and by area (the sessions' prefix or
the lake's): a WSGI layer around moto's application. A standing cluster of 2 single-threaded
worker processes (fieldcal's worker settings; the store's credentials in their environment)
is started and warmed by a fleet of one observations session before the clock starts; then
one ``recalibrate_fleet`` of the whole root into an empty lake on S3 (the storage options the
flow is given hold no secret).

Printed: wall time, images/s, the share of the workers' time outside reading (with
hashing), extraction and solving, peak memory per worker (the measuring tasks' peak RSS
and each worker's own at the end), S3 requests and bytes per image and per observations
session. Results also go to ``bench/out/night/results.json``.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
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
OUT = HERE / "out" / "night"
BUCKET = "fieldcal-night"
REGION = "us-east-1"
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing"}
PICKS = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]      # 12 images: 2 attitudes per station
N_IMG = 10


# --------------------------------------------------------------------------------------
# the counting S3 server (its own process)
# --------------------------------------------------------------------------------------
class Counting:
    """WSGI layer around moto's application: requests and bytes by (kind, area).

    ``GET /_bench/counts`` answers the counts as JSON; ``POST /_bench/reset`` zeroes them."""

    def __init__(self, app):
        self.app = app
        self.lock = threading.Lock()
        self.reset()

    def reset(self) -> None:
        self.n, self.bytes_in, self.bytes_out = (collections.Counter() for _ in range(3))

    @staticmethod
    def kind(environ) -> str:
        method, query = environ["REQUEST_METHOD"], environ.get("QUERY_STRING", "")
        if method == "GET" and ("list-type" in query or "prefix=" in query or "delimiter" in query):
            return "LIST"
        return method

    def __call__(self, environ, start_response):
        path = environ.get("PATH_INFO", "")
        if path.startswith("/_bench/"):
            with self.lock:
                if path == "/_bench/reset":
                    self.reset()
                body = json.dumps({"n": self.n, "bytes_in": self.bytes_in, "bytes_out": self.bytes_out}).encode()
            start_response("200 OK", [("Content-Type", "application/json"), ("Content-Length", str(len(body)))])
            return [body]
        key = f"{self.kind(environ)} {'sessions' if '/sessions/' in path or path.endswith('/sessions') else 'lake'}"
        n_in = int(environ.get("CONTENT_LENGTH") or 0)
        chunks = list(self.app(environ, start_response))
        with self.lock:
            self.n[key] += 1
            self.bytes_in[key] += n_in
            self.bytes_out[key] += sum(len(c) for c in chunks)
        return chunks


def serve_moto(port: int) -> None:
    import logging

    from moto.moto_server.werkzeug_app import DomainDispatcherApplication, MotoRequestHandler, create_backend_app
    from werkzeug.serving import make_server

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    app = Counting(DomainDispatcherApplication(create_backend_app))
    make_server("127.0.0.1", port, app, True, request_handler=MotoRequestHandler).serve_forever()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def counts(endpoint: str, reset: bool = False) -> dict:
    import httpx

    r = (httpx.post(f"{endpoint}/_bench/reset", timeout=30) if reset else httpx.get(f"{endpoint}/_bench/counts",
                                                                                     timeout=30))
    return r.json()


# --------------------------------------------------------------------------------------
# sessions
# --------------------------------------------------------------------------------------
def make_sessions(scale: float, n_obs: int) -> Path:
    """The local root (written once, reused): 10 image sessions and ``n_obs`` observation sessions."""
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    root = OUT / f"sessions-{scale:g}"
    for k in range(N_IMG):
        f = root / f"cam-img{k}" / "2026-09-01"
        same = HERE / "out" / "scaling" / "images" / f"cam-img{k}" / "2026-09-01"   # bench_scaling.py's, if made
        if not (f / "session.json").is_file() and scale == 0.25 and (same / "session.json").is_file():
            shutil.copytree(same, f)
        if not (f / "session.json").is_file():
            t = time.perf_counter()
            write_field_session(f, scaled_field(paper_field(seed=200 + k), scale), image_indices=PICKS, coded=True,
                                seed=200 + k, camera_id=f"cam-img{k}", acquired="2026-09-01")
            print(f"  rendered {f} in {time.perf_counter() - t:.0f} s", flush=True)
    for k in range(n_obs):
        f = root / f"cam-w{k % 20}" / f"2026-10-{k // 20 + 1:02d}"
        if not (f / "session.json").is_file():
            write_field_session(f, wide_field(seed=1000 + k), images=False, observations_csv=True,
                                camera_id=f"cam-w{k % 20}", acquired=f"2026-10-{k // 20 + 1:02d}")
    return root


def frame_facts(root: Path) -> dict:
    import tifffile

    tifs = sorted(root.glob("cam-img*/*/**/*.tif*"))
    with tifffile.TiffFile(tifs[0]) as t:
        shape = t.pages[0].shape
    return {"frame_shape": list(shape), "n_tiff": len(tifs), "tiff_bytes": sum(p.stat().st_size for p in tifs)}


# --------------------------------------------------------------------------------------
# the night
# --------------------------------------------------------------------------------------
def worker_memory() -> dict:
    """Run on a worker: its resident memory now and its peak [MiB]."""
    import resource

    import psutil

    return {"pid": os.getpid(), "rss_mb": psutil.Process().memory_info().rss / 2**20,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run_night(address: str, root_url: str, lake_url: str, options: dict) -> tuple[float, dict, list]:
    import flows.fleet as fleet_flow

    record: list[dict] = []
    run_session = fleet_flow._run_session

    def recording(*args, **kwargs):
        out = run_session(*args, **kwargs)
        if isinstance(out, dict):
            record.append(out)
        return out

    fleet_flow._run_session = recording
    try:
        t = time.perf_counter()
        summary = fleet_flow.recalibrate_fleet(lake_url, root=root_url, storage_options=options,
                                               dask_address=address)
        return time.perf_counter() - t, summary, record
    finally:
        fleet_flow._run_session = run_session


def report(res: dict) -> str:
    n_img = res["n_images"]
    n_obs = res["n_obs_sessions"]
    c = res["s3"]
    lines = [f"frames {res['frames']['frame_shape']} (scale {res['scale']:g}), {res['frames']['n_tiff']} TIFF, "
             f"{res['frames']['tiff_bytes'] / 2**20:.0f} MiB; {N_IMG} image sessions, {n_obs} observation sessions",
             f"wall {res['wall_s']:.1f} s; {res['n_committed']} committed, {res['n_failed']} failed; "
             f"{n_img / res['wall_s']:.2f} images/s over the night's wall time; load {res['load_start']:.1f} -> "
             f"{res['load_end']:.1f}",
             f"worker time ({res['n_workers']} x wall): reading+hashing {res['read_s']:.1f} s, extraction "
             f"{res['extract_s']:.1f} s, solving {res['solve_s']:.1f} s; outside them "
             f"{100 * res['outside_share']:.0f} %",
             f"image sessions: flow body median {res['img_session_s']:.1f} s; observation sessions: "
             f"{res['obs_session_s']:.2f} s (solver {res['obs_solver_s']:.2f} s)",
             "peak RSS per worker [MiB]: " + ", ".join(f"{m['peak_rss_mb']:.0f}" for m in res["workers"])
             + f" (measuring tasks' peak {res['task_peak_mb']:.0f})",
             "", "| S3 requests | n | per image | MiB in | MiB out | MiB out per image |", "|---|---|---|---|---|---|"]
    for k in sorted(c["n"]):
        lines.append(f"| {k} | {c['n'][k]} | {c['n'][k] / n_img:.1f} | {c['bytes_in'][k] / 2**20:.1f} | "
                     f"{c['bytes_out'][k] / 2**20:.1f} | {c['bytes_out'][k] / 2**20 / n_img:.2f} |")
    tot = sum(c["n"].values())
    lines.append(f"| all | {tot} | {tot / n_img:.1f} | {sum(c['bytes_in'].values()) / 2**20:.1f} | "
                 f"{sum(c['bytes_out'].values()) / 2**20:.1f} | {sum(c['bytes_out'].values()) / 2**20 / n_img:.2f} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=float, default=0.25,
                    help="frame scale of the field paper's camera, 8208 x 6280 px at 1 (0.25)")
    ap.add_argument("--obs", type=int, default=100, help="observation sessions (100)")
    ap.add_argument("--moto", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.moto:
        serve_moto(args.moto)
        return
    import distributed
    import fsspec
    import httpx
    from prefect.testing.utilities import prefect_test_harness

    from flows.cluster import local_cluster_kwargs

    t0 = time.perf_counter()
    local = make_sessions(args.scale, args.obs)
    res = {"scale": args.scale, "n_obs_sessions": args.obs, "frames": frame_facts(local)}
    port = free_port()
    endpoint = f"http://127.0.0.1:{port}"
    moto = subprocess.Popen([sys.executable, __file__, "--moto", str(port)], stdout=subprocess.DEVNULL)
    env_before = {k: os.environ.get(k) for k in CREDENTIALS}
    os.environ.update(CREDENTIALS)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                counts(endpoint)
                break
            except httpx.HTTPError:
                assert moto.poll() is None and time.monotonic() < deadline, "the moto server did not start"
                time.sleep(0.3)
        options = {"endpoint_url": endpoint, "client_kwargs": {"region_name": REGION}}
        import boto3

        boto3.client("s3", endpoint_url=endpoint, region_name=REGION).create_bucket(Bucket=BUCKET)
        fs = fsspec.filesystem("s3", **options)
        t = time.perf_counter()
        fs.put(str(local) + "/", f"{BUCKET}/sessions/", recursive=True)
        res["upload_s"] = time.perf_counter() - t
        warm_local = OUT / "warm"
        if not (warm_local / "cam-warm" / "2026-01-01" / "session.json").is_file():
            from fieldcal.synthetic.field import wide_field
            from fieldcal.synthetic.session_writer import write_field_session

            write_field_session(warm_local / "cam-warm" / "2026-01-01", wide_field(seed=7), images=False,
                                observations_csv=True, camera_id="cam-warm", acquired="2026-01-01")
        fs.put(str(warm_local) + "/", f"{BUCKET}/warm/sessions/", recursive=True)
        print(f"uploaded in {res['upload_s']:.1f} s", flush=True)
        with prefect_test_harness(server_startup_timeout=180):
            kwargs = local_cluster_kwargs(2, {"processes": True})
            kwargs["env"] = dict(kwargs["env"], **CREDENTIALS)
            with distributed.LocalCluster(**kwargs) as cluster, distributed.Client(cluster.scheduler_address) as cl:
                cl.wait_for_workers(2, timeout=180)
                run_night(cluster.scheduler_address, f"s3://{BUCKET}/warm/sessions", f"s3://{BUCKET}/warm/lake",
                          options)
                counts(endpoint, reset=True)
                res["load_start"] = os.getloadavg()[0]
                wall, summary, record = run_night(cluster.scheduler_address, f"s3://{BUCKET}/sessions",
                                                  f"s3://{BUCKET}/lake", options)
                res["load_end"] = os.getloadavg()[0]
                res["s3"] = counts(endpoint)
                res["workers"] = list(cl.run(worker_memory).values())
    finally:
        moto.terminate()
        moto.wait(timeout=30)
        for k, v in env_before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    rows = [r for out in record for r in (out.get("measure") or {}).get("rows", [])]
    tasks = [t for out in record for t in (out.get("measure") or {}).get("tasks", [])]
    img = [o for o in record if o.get("method") == "field" and (o.get("measure") or {}).get("rows")]
    obs = [o for o in record if not (o.get("measure") or {}).get("rows")]
    res.update(wall_s=wall, n_committed=summary["n_committed"], n_failed=summary["n_failed"], n_workers=2,
               n_images=sum(r["status"] == "measured" for r in rows),
               read_s=sum(r["hash_s"] for r in rows), extract_s=sum(r["measure_s"] for r in rows),
               solve_s=sum(o["timings"].get("solver_s", 0.0) for o in record),
               task_peak_mb=max((t["rss_peak_mb"] for t in tasks), default=float("nan")),
               img_session_s=sorted(o["timings"]["total_s"] for o in img)[len(img) // 2] if img else float("nan"),
               obs_session_s=sorted(o["timings"]["total_s"] for o in obs)[len(obs) // 2] if obs else float("nan"),
               obs_solver_s=sorted(o["timings"].get("solver_s", 0) for o in obs)[len(obs) // 2] if obs else 0.0,
               total_s=time.perf_counter() - t0,
               sessions=[{k: o.get(k) for k in ("camera_id", "session_id", "status", "timings")} for o in record])
    res["outside_share"] = 1 - (res["read_s"] + res["extract_s"] + res["solve_s"]) / (res["n_workers"] * wall)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps(res, indent=1, default=str))
    print()
    print(report(res))
    print(f"\nwhole bench {res['total_s']:.0f} s (upload {res['upload_s']:.0f} s, not counted)")


if __name__ == "__main__":
    main()
