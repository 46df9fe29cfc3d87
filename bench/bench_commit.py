"""Figures of issue 28, goal 4: what one commit costs, on a local lake and on S3 (moto), by step.

A lake of ``--versions`` versions over ``--cameras`` cameras is made locally by the code of
``bench_lake.py`` (bulk appends, then real commits, compaction, and ``--after`` more real
commits so that the catalog has small files since its compaction, as between two
maintenances), then copied object by object to a moto S3 server on loopback. Each round
commits one new version (a new session, 2000 residual rows, no arrays: the catalog, not the
payload, is what the commit path has to find its way through) to each lake with each
candidate, interleaved (candidate order rotated every round), through a fresh ``Lake`` (as
the flow's commit task makes one):

- ``merge``: the catalog row inserted by a Delta MERGE "insert unless a row has this
  fingerprint or version", after a scan of the catalog for the fingerprint, and the Zarr
  group written object after object through a Zarr store (the commit path before issue 28);
- ``txn``: the catalog row appended with a Delta transaction identifier naming the
  fingerprint (:meth:`fieldcal.lake.tables.Tables.append` ``once=``), the fingerprint
  looked up in the snapshot's transaction identifiers (no scan of the catalog); on S3 the
  Zarr group's objects PUT at once (:meth:`fieldcal.lake.storage.Storage.write_many`).

Per step (seconds, median of the rounds): the pre-check for the fingerprint, the document,
the Zarr group, the residuals' append, the catalog's commit, the data dictionary; and the
whole ``Lake.commit``. The load is printed before and after.

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_commit.py [--versions 1000]
[--cameras 50] [--rounds 7] [--no-s3]``; results are copied into ``bench/README_lake.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import bench_lake as bl  # noqa: E402

from fieldcal.lake.store import Lake  # noqa: E402

STEPS = {"precheck": "find_committed", "document": "_reserve", "zarr": "_write_zarr",
         "dictionary": "_write_dictionary"}


class MergeLake(Lake):
    """The commit path before issue 28: a catalog scan for the fingerprint, then a MERGE."""

    CATALOG_BY_MERGE = True

    def _write_zarr(self, rel: str, arrays: dict, doc: dict) -> None:
        """The Zarr group written through a Zarr store, object after object (before issue 28)."""
        import zarr

        store = self._store.zarr_store(rel, read_only=False)
        try:
            self._fill_group(zarr.open_group(store=store, mode="w", zarr_format=3), arrays, doc)
        finally:
            store.close()


def timed(times: dict, lake: Lake):
    """Wrap the lake's steps so that each adds its seconds to ``times``."""
    def wrap(obj, attr, key):
        fn = getattr(obj, attr)

        def inner(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                times[key] += time.perf_counter() - t
        setattr(obj, attr, inner)

    for key, attr in STEPS.items():
        wrap(lake, attr, key)
    tables = lake.tables
    for attr in ("append", "append_once", "insert_unless"):
        fn = getattr(tables, attr)

        def inner(name, *a, _fn=fn, _attr=attr, **k):
            t = time.perf_counter()
            try:
                return _fn(name, *a, **k)
            finally:
                if not (name == "catalog" and _attr == "append"):     # inside append_once
                    times[name] += time.perf_counter() - t
        setattr(tables, attr, inner)
    return lake


def one_commit(cls, url, options, k: int) -> dict:
    times: dict = defaultdict(float)
    lake = timed(times, cls(url, options))
    doc = bl.document(k % 50, 1000 + k, seed=7_000_003 + k)
    t = time.perf_counter()
    v = lake.commit(doc, {}, bl.residuals(k, 2000))
    times["total"] = time.perf_counter() - t
    assert v.new, "a new session must make a new version"
    return dict(times)


@contextlib.contextmanager
def moto():
    from moto.server import ThreadedMotoServer

    logging.getLogger("werkzeug").setLevel(logging.ERROR)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        yield f"http://{host}:{port}"
    finally:
        server.stop()


def make(root: Path, n_versions: int, n_cameras: int, after: int) -> Lake:
    lake, _ = bl.make_lake(root, n_versions, n_cameras)
    for k in range(after):
        bl.commit_and_record(lake, bl.document(k % n_cameras, 900 + k, seed=k), bl.residuals(k))
    return lake


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--versions", type=int, default=1000)
    ap.add_argument("--cameras", type=int, default=50)
    ap.add_argument("--after", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--no-s3", action="store_true")
    args = ap.parse_args()
    print(f"load before: {os.getloadavg()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="fieldcal-bench-commit-") as tmp, contextlib.ExitStack() as stack:
        t = time.perf_counter()
        lake = make(Path(tmp) / "lake", args.versions, args.cameras, args.after)
        print(f"made a lake of {args.versions} versions in {time.perf_counter() - t:.0f} s", flush=True)
        lakes = [("local", lake.url, None)]
        if not args.no_s3:
            import boto3

            endpoint = stack.enter_context(moto())
            client = boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1",
                                  aws_access_key_id="testing", aws_secret_access_key="testing")
            client.create_bucket(Bucket="bench-commit")
            n = bl.upload(Path(lake.url), client, "bench-commit", "lake")
            print(f"copied {n} objects to moto", flush=True)
            lakes.append(("moto S3", "s3://bench-commit/lake",
                          {"endpoint_url": endpoint, "key": "testing", "secret": "testing",
                           "client_kwargs": {"region_name": "us-east-1"}}))
        cands = [("merge", MergeLake), ("txn", Lake)]
        got: dict = defaultdict(list)
        k = 0
        for r in range(args.rounds):
            order = cands if r % 2 == 0 else cands[::-1]
            for where, url, options in lakes:
                for name, cls in order:
                    k += 1
                    got[(where, name)].append(one_commit(cls, url, options, k))
        print(f"load after: {os.getloadavg()}")
        keys = ["precheck", "document", "zarr", "residuals", "catalog", "dictionary", "total"]
        print("| lake | candidate | " + " | ".join(f"{c} [s]" for c in keys) + " |")
        print("|---|---|" + "---|" * len(keys))
        for (where, name), rows in got.items():
            med = [statistics.median(row.get(c, 0.0) for row in rows) for c in keys]
            print(f"| {where} | {name} | " + " | ".join(f"{m:.3f}" for m in med) + " |")
        for where, _, _ in lakes:
            a = [r["total"] for r in got[(where, "merge")]]
            b = [r["total"] for r in got[(where, "txn")]]
            ratio = statistics.median(x / y for x, y in zip(a, b, strict=True))
            print(f"{where}: merge / txn = {ratio:.2f} (median of the rounds' ratios; "
                  f"txn {min(b):.3f}-{max(b):.3f} s, merge {min(a):.3f}-{max(a):.3f} s)")


if __name__ == "__main__":
    main()
