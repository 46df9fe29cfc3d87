"""Figures of issue 14 (the lake on Delta Lake): history and commits as the lake grows.

Lakes of 10^2, 10^3, 10^4 and 10^5 versions over 200 cameras (50 for the smallest). The
bulk of each lake is made by an append equivalent to the commit path: the catalog rows and
residual rows of many versions per Delta append (what ``Lake.commit`` writes, without the
per-version documents); the last two versions of every camera are made by ``Lake.commit``
itself (documents, Zarr groups), so that ``history --fleet`` compares real calibrations.
Then the tables are compacted (as the automatic maintenance would have).

Timed (the function each command calls; best of ``--repeat``):

- ``history --camera``: :func:`fieldcal.lake.history.camera_history` of one camera;
- ``history --fleet``: :func:`fieldcal.products.report.fleet_summary`, first and again. Since
  issue 29 every commit stores its change test and acceptance (:mod:`fieldcal.products.status`,
  what the flow does after ``Lake.commit``): the real commits do it, and the bulk versions get
  rows of the same size in the ``comparisons`` and ``assessments`` tables (as if each had been
  committed so), so the tables are as large as a lake of that many versions makes them;
- ``lake fill``: the derived tables removed (a lake made before issue 29), then
  :func:`fieldcal.products.status.fill` (each camera's latest and its pair), then
  ``history --fleet`` again;
- ``dashboard``: :func:`fieldcal.products.dashboard.write_dashboard` of every camera;
- ``history --sql``: a per-camera aggregate over the catalog;
- one commit (``Lake.commit``, a new session of one camera), interleaved with one commit
  of the first layout's code (``tests/lake/legacy_store.py``) on an old lake of the same
  size ("before"); and the first layout's ``history --camera`` on its lake.
- ``fieldcal history --camera`` as a command (a new process: imports included).

``--s3 N``: a lake of N versions made locally by the same code, copied object by object to a
moto S3 server on loopback, and timed there (reads, fleet, one commit on S3).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_lake.py [--sizes 100 1000 10000 100000]
[--s3 10000]``; results are copied into ``bench/README_lake.md``.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from fieldcal.analysis.uncertainty import Calibration  # noqa: E402
from fieldcal.contract.fingerprint import code_version, fingerprint  # noqa: E402
from fieldcal.lake import history  # noqa: E402
from fieldcal.lake.parts import catalog_row, conform_residuals  # noqa: E402
from fieldcal.lake.store import Lake  # noqa: E402
from fieldcal.model.camera import PARAM_NAMES  # noqa: E402
from fieldcal.products import status  # noqa: E402
from fieldcal.products.dashboard import write_dashboard  # noqa: E402
from fieldcal.products.report import fleet_summary  # noqa: E402

RESIDUAL_ROWS = 20
"""Residual rows per bulk version (real calibrations have thousands; the catalog is what grows)."""
SQL = ("SELECT camera_id, count(*) AS n, avg(f_mm) AS f_mm, stddev_samp(f_mm) AS sd_f_mm, "
       "max(rmse_px) AS worst_rmse_px FROM catalog GROUP BY camera_id ORDER BY camera_id")


def document(camera: int, session: int, *, seed: int) -> dict:
    """A field calibration document of camera ``camera``'s session ``session``."""
    rng = np.random.default_rng(seed)
    params = dict.fromkeys(PARAM_NAMES, 0.0)
    params.update(f_mm=50.0 + 0.002 * session + 0.01 * camera, xp_mm=0.01, yp_mm=-0.02,
                  k1=-2.5e-5, k2=1.0e-8, p1=1.5e-6, p2=-2.0e-6, a1=3e-5, a2=-1e-5)
    sigma = dict.fromkeys(PARAM_NAMES)
    for n in ("f_mm", "xp_mm", "yp_mm", "k1", "k2", "p1", "p2", "a1", "a2"):
        sigma[n] = float(abs(params[n]) * 1e-3 + 1e-6)
    acquired = dt.datetime(2020, 1, 1, tzinfo=dt.UTC) + dt.timedelta(days=7 * session)
    return {"schema": "fieldcal.calibration/1", "camera_id": f"cam-{camera:04d}",
            "session_id": f"s{session:05d}", "method": "field", "created": acquired.isoformat(),
            "acquired": acquired.isoformat(),
            "sensor": {"width_px": 820, "height_px": 628, "pixel_size_um": 5.3},
            "model": "fieldcal-brown/1", "parameters": params, "sigma": sigma,
            "stats": {"n_images": 3, "n_targets": 40, "n_observations": 300, "n_rejected": 2,
                      "rmse_px": float(0.2 + 0.01 * rng.random()), "max_px": 0.9,
                      "mean_abs_u_px": 0.15, "mean_abs_v_px": 0.14, "sigma0": 1.0, "iterations": 8,
                      "solver": "lmqn", "targets_adjusted": True, "fixed_parameters": {}},
            "images": [{"file": f"images/IMG_{i}.tif", "station": "S1", "center_m": [0.0, -60.0 + i, 20.0],
                        "rotation_world_to_camera": np.eye(3).tolist(),
                        "sigma_center_m": [0.01, 0.01, 0.01], "n_observations": 100, "rmse_px": 0.2}
                       for i in range(3)],
            "inputs": {"fingerprint": fingerprint({"camera": camera, "session": session, "seed": seed})},
            "code_version": code_version()}


def residuals(seed: int, n: int = RESIDUAL_ROWS) -> pa.Table:
    rng = np.random.default_rng(seed)
    return pa.table({"image": [f"images/IMG_{i % 3}.tif" for i in range(n)],
                     "target_id": [f"T{i}" for i in range(n)], "u_px": rng.uniform(0, 820, n),
                     "v_px": rng.uniform(0, 628, n), "du_px": rng.normal(0, 0.2, n),
                     "dv_px": rng.normal(0, 0.2, n), "sigma_px": np.full(n, 0.1),
                     "used": np.ones(n, bool), "reason": pa.nulls(n, pa.string())})


def bulk(lake: Lake, pairs: list[tuple[int, int]], batch: int = 5000) -> None:
    """Catalog and residual rows of many versions per append (documents not written)."""
    res_template = conform_residuals(residuals(0), "bench")
    for start in range(0, len(pairs), batch):
        rows, res = [], []
        for cam, ses in pairs[start:start + batch]:
            doc = document(cam, ses, seed=cam * 100003 + ses)
            doc["version"] = f"20200101T000000Z-{doc['inputs']['fingerprint'][7:15]}-{ses % 65536:04x}"
            paths = Lake.paths(doc["camera_id"], doc["session_id"], doc["version"])
            rows.append(catalog_row(doc, dt.datetime.fromisoformat(doc["created"]), False, paths, "bench"))
            n = res_template.num_rows
            keys = {"camera_id": [doc["camera_id"]] * n, "session_id": [doc["session_id"]] * n,
                    "version": [doc["version"]] * n}
            res.append(pa.table({**keys, **{c: res_template[c] for c in res_template.column_names}}))
        lake.tables.append("catalog", pa.concat_tables(rows), {"action": "bench bulk"})
        lake.tables.append("residuals", pa.concat_tables(res), {"action": "bench bulk"})


def commit_and_record(lake: Lake, doc: dict, res: pa.Table) -> str:
    """``Lake.commit``, then the change test and the assessment, as the flow does."""
    v = lake.commit(doc, {}, res)
    status.record_commit(lake, v, Calibration.from_document(dict(doc, version=str(v))), res)
    return v


def bulk_derived(lake: Lake, batch: int = 5000) -> None:
    """Rows of the derived tables for the bulk versions (each version against the one before
    it, each version's assessment), copied from a real commit's rows with the versions
    replaced: what commits that each stored their test would have left."""
    comp = lake.tables.scan("comparisons").slice(0, 1).to_pylist()[0]
    acc = lake.tables.scan("assessments").slice(0, 1).to_pylist()[0]
    cat = lake.catalog(sort=False).select(["camera_id", "version", "acquired"]).to_pylist()
    real = set(lake.tables.scan("assessments", columns=["version"])["version"].to_pylist())
    by_cam: dict = {}
    for r in sorted(cat, key=lambda r: (r["camera_id"], r["acquired"])):
        by_cam.setdefault(r["camera_id"], []).append(r["version"])
    pairs = [(a, b) for seq in by_cam.values() for a, b in zip(seq[:-1], seq[1:], strict=True) if b not in real]
    versions = [r["version"] for r in cat if r["version"] not in real]
    for start in range(0, max(len(pairs), len(versions)), batch):
        part = pairs[start:start + batch]
        if part:
            lake.tables.append("comparisons", pa.table({
                "version_a": [a for a, _ in part], "version_b": [b for _, b in part],
                "settings": [comp["settings"]] * len(part), "computed": [comp["computed"]] * len(part),
                "result": [comp["result"].replace(comp["version_b"], b) for _, b in part]}), {"action": "bench"})
        vpart = versions[start:start + batch]
        if vpart:
            lake.tables.append("assessments", pa.table({
                "version": vpart, "camera_id": [acc["camera_id"]] * len(vpart),
                "settings": [acc["settings"]] * len(vpart), "computed": [acc["computed"]] * len(vpart),
                "verdict": [acc["verdict"]] * len(vpart), "radial": [acc["radial"]] * len(vpart),
                "result": [acc["result"]] * len(vpart)}),
                {"action": "bench"})


def make_lake(root: Path, n_versions: int, n_cameras: int, storage_options=None) -> tuple[Lake, float]:
    """A lake of ``n_versions`` versions; returns it and the seconds the real commits took each
    (the commit and the stored change test and assessment)."""
    lake = Lake(str(root), storage_options)
    per_cam = n_versions // n_cameras
    pairs = [(c, s) for s in range(per_cam - 2) for c in range(n_cameras)]
    bulk(lake, pairs)
    t = time.perf_counter()
    for s in (per_cam - 2, per_cam - 1):
        for c in range(n_cameras):
            commit_and_record(lake, document(c, s, seed=c * 100003 + s), residuals(s))
    commit_s = (time.perf_counter() - t) / (2 * n_cameras)
    bulk_derived(lake)
    for name in ("catalog", "residuals", "comparisons", "assessments"):
        lake.tables.optimize(name)
    return lake, commit_s


def make_old_lake(root: Path, n_versions: int, n_cameras: int, storage_options=None):
    """A lake of the first layout: one catalog file per version (written directly), a few
    residual files; the old ``history --camera`` reads every catalog file."""
    from tests.lake import legacy_store

    old = legacy_store.Lake(str(root), storage_options)
    per_cam = n_versions // n_cameras
    for c in range(n_cameras):
        for s in range(per_cam):
            doc = document(c, s, seed=c * 100003 + s)
            doc["version"] = f"20200101T000000Z-{doc['inputs']['fingerprint'][7:15]}-{s % 65536:04x}"
            paths = legacy_store.Lake._paths(doc["camera_id"], doc["session_id"], doc["version"])
            row = catalog_row(doc, dt.datetime.fromisoformat(doc["created"]), False, paths, "bench")
            old._store.write(paths["catalog"], legacy_store._parquet_bytes(row))
    return old


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def fill_costs(url: str, storage_options) -> dict:
    """The lake as made before issue 29 (derived tables removed), ``fill``, the fleet after it."""
    lake = Lake(url, storage_options)
    for name in ("comparisons", "assessments"):
        if lake.is_local:
            import shutil

            shutil.rmtree(lake.uri(name), ignore_errors=True)
        else:
            lake.fs.rm(lake.storage.path(name), recursive=True)
    t = time.perf_counter()
    counts = status.fill(Lake(url, storage_options))
    fill_s = time.perf_counter() - t
    t = time.perf_counter()
    fleet_summary(Lake(url, storage_options))
    return {"fill_s": fill_s, "fill_computed": counts["computed"], "fleet_after_fill_s": time.perf_counter() - t}


def commit_costs(lake: Lake, old, repeat: int, tag: int) -> tuple[float, float]:
    """Median seconds of one new commit (with its stored change test and assessment, as the
    flow makes it) and one first-layout commit, interleaved."""
    new_t, old_t = [], []
    for i in range(repeat):
        doc = document(9000 + tag, 90000 + i, seed=tag * 7 + i)
        t = time.perf_counter()
        commit_and_record(lake, doc, residuals(i, 2000))
        new_t.append(time.perf_counter() - t)
        if old is not None:
            doc = document(9500 + tag, 90000 + i, seed=tag * 7 + i)
            t = time.perf_counter()
            old.commit(doc, {}, residuals(i, 2000))
            old_t.append(time.perf_counter() - t)
    return statistics.median(new_t), (statistics.median(old_t) if old_t else float("nan"))


def old_camera_history(old) -> float:
    """The first layout's ``history --camera``: read every catalog file, filter one camera."""
    t = time.perf_counter()
    cat = old.catalog()
    _ = [r for r in cat.select(["camera_id", "version"]).to_pylist() if r["camera_id"] == "cam-0007"]
    return time.perf_counter() - t


def cli_camera(url: str) -> float:
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "flows.cli", "history", "--lake", url, "--camera", "cam-0007"],
                   check=True, capture_output=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    return time.perf_counter() - t


def measure(n: int, root, repeat: int, *, storage_options=None, old_options=None,
            made: tuple[str, float, float] | None = None, fill: bool = True) -> dict:
    """Time one lake of ``n`` versions; ``made`` = (url, make_s, commit_s) of a lake already made."""
    cams = 200 if n >= 1000 else 50
    local = storage_options is None
    if made is None:
        t = time.perf_counter()
        lake, commit_bulk_s = make_lake(root / f"new-{n}", n, cams)
        made = (lake.url, time.perf_counter() - t, commit_bulk_s)
    url, make_s, commit_bulk_s = made
    lake = Lake(url, storage_options)
    out = {"versions": lake.catalog().num_rows, "cameras": cams, "make_s": make_s,
           "commit_in_bulk_s": commit_bulk_s}
    # a fresh Lake each time: the table is loaded from its log, as by a new command
    out["camera_s"] = best(lambda: history.camera_history(Lake(url, storage_options), "cam-0007"),
                           repeat)
    out["sql_s"] = best(lambda: history.sql(Lake(url, storage_options), SQL), repeat)
    t = time.perf_counter()
    fleet = fleet_summary(Lake(url, storage_options))
    out["fleet_first_s"] = time.perf_counter() - t
    out["fleet_compared"] = sum(1 for v in fleet["p_value"].to_pylist() if v is not None)
    out["fleet_again_s"] = best(lambda: fleet_summary(Lake(url, storage_options)), repeat)
    with tempfile.TemporaryDirectory(prefix="bench-dashboard-") as site:
        t = time.perf_counter()
        write_dashboard(Lake(url, storage_options), site)
        out["dashboard_s"] = time.perf_counter() - t
    old = None
    if n <= 10000:
        if local:
            old = make_old_lake(root / f"old-{n}", n, cams)
            out["old_camera_s"] = min(old_camera_history(old) for _ in range(max(1, repeat // 2)))
        else:  # the first layout's commit on S3 only (making an old 10^4 lake there takes hours)
            from tests.lake import legacy_store

            old = legacy_store.Lake(f"{root}/old-{n}", old_options)
    out["commit_s"], out["old_commit_s"] = commit_costs(lake, old, repeat, n % 97)
    if fill:                          # last: it removes the derived tables first
        out.update(fill_costs(url, storage_options))
    if local:
        out["cli_camera_s"] = min(cli_camera(url) for _ in range(2))
    return out


def upload(folder: Path, client, bucket: str, prefix: str) -> int:
    """Copy a lake folder to ``s3://bucket/prefix`` object by object; returns the count.

    A Delta table's log names its files relative to the table root, and the Zarr groups and
    documents are plain objects, so the copy is the same lake on the object store."""
    files = [f for f in sorted(folder.rglob("*")) if f.is_file()]
    for f in files:
        client.upload_file(str(f), bucket, f"{prefix}/{f.relative_to(folder).as_posix()}")
    return len(files)


def s3_measure(n: int, repeat: int, *, local_too: bool = False, fill: bool = False) -> list[tuple[str, dict]]:
    """The lake made locally by the same code (bulk appends, real commits, compaction), copied
    to a moto S3 server on loopback, then timed there (reads, fleet, one commit on S3).

    Making it on S3 directly means 400 commits through moto, over an hour here. ``local_too``:
    the local lake it was made from is timed too (one lake made for both); ``fill``: also
    ``lake fill`` on S3 (400 objects' worth of reads per camera pair: ~20 minutes here)."""
    import logging

    import boto3
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        endpoint = f"http://{host}:{port}"
        client = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1",
                              aws_access_key_id="t", aws_secret_access_key="t")
        client.create_bucket(Bucket="bench-lake")
        options = {"endpoint_url": endpoint, "key": "t", "secret": "t",
                   "client_kwargs": {"region_name": "us-east-1"}}
        with tempfile.TemporaryDirectory(prefix="bench-lake-s3-") as tmp:
            cams = 200 if n >= 1000 else 50
            t = time.perf_counter()
            lake, commit_bulk_s = make_lake(Path(tmp) / "lake", n, cams)
            made_local_s = time.perf_counter() - t
            t = time.perf_counter()
            count = upload(Path(tmp) / "lake", client, "bench-lake", f"new-{n}")
            print(f"made locally in {made_local_s:.0f} s, {count} objects copied to S3 in "
                  f"{time.perf_counter() - t:.0f} s", flush=True)
            out = []
            if local_too:
                out.append(("local", measure(n, Path(tmp), repeat, made=(lake.url, made_local_s, commit_bulk_s))))
        out.append(("moto S3", measure(n, "s3://bench-lake", repeat, storage_options=options, old_options=options,
                                       made=(f"s3://bench-lake/new-{n}", made_local_s, commit_bulk_s), fill=fill)))
        return out
    finally:
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[100, 1000, 10000, 100000])
    ap.add_argument("--s3", type=int, default=0, help="also a lake of this many versions on moto S3")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--s3-fill", action="store_true", help="also time `lake fill` on S3 (long)")
    args = ap.parse_args()
    cols = ["versions", "cameras", "make_s", "camera_s", "sql_s", "fleet_first_s", "fleet_compared",
            "fleet_again_s", "dashboard_s", "fill_s", "fill_computed", "fleet_after_fill_s", "commit_s",
            "old_commit_s", "old_camera_s", "cli_camera_s"]
    print("| where | " + " | ".join(cols) + " |")
    print("|---" * (len(cols) + 1) + "|")
    with tempfile.TemporaryDirectory(prefix="bench-lake-") as tmp:
        for n in args.sizes:
            if n != args.s3:
                r = measure(n, Path(tmp), args.repeat)
                print("| local | " + " | ".join(_fmt(r.get(c)) for c in cols) + " |", flush=True)
    if args.s3:
        for where, r in s3_measure(args.s3, args.repeat, local_too=args.s3 in args.sizes, fill=args.s3_fill):
            print(f"| {where} | " + " | ".join(_fmt(r.get(c)) for c in cols) + " |", flush=True)


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if v == v else "-"
    return str(v)


if __name__ == "__main__":
    main()
