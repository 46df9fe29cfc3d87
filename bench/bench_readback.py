"""Figures of issue 24 (class 1): what reading a version back costs.

A local lake of ``--versions`` versions over 20 cameras (made by ``Lake.commit``), then:

- one commit (``Lake.commit``, a new session) with the read-back before the catalog row and
  without it (``Lake._read_back`` replaced by a no-op: the code before issue 24), interleaved,
  ``--repeat`` times each; the median;
- a rerun's answer (``Lake.find_committed``: the catalog lookup and, since issue 24, the
  read-back of the version found) against the catalog lookup alone;
- ``fieldcal fleet``'s selection (:func:`fieldcal.fleet.select_sessions`) of every session
  of the lake, each latest version read back, against the same without (``Lake.whole``
  replaced by a no-op).

``--s3 N``: first, one commit with and without the read-back on a moto S3 server (a lake of
N versions).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_readback.py [--versions 200] [--repeat 15]
[--s3 20]``;
results are copied into ``bench/README_lake.md``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pyarrow.dataset as ds  # noqa: E402

from fieldcal import fleet  # noqa: E402
from fieldcal.lake.store import Lake  # noqa: E402
from tests.lake.test_lake import field_document, residual_table  # noqa: E402


def timed(fn) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def commits_on_s3(n_versions: int, repeat: int) -> None:
    """One commit with and without the read-back on a moto S3 server on loopback."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    try:
        host, port = server.get_host_and_port()
        endpoint = f"http://{host}:{port}"
        boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1", aws_access_key_id="k",
                     aws_secret_access_key="s").create_bucket(Bucket="bench-readback")
        opts = {"endpoint_url": endpoint, "key": "k", "secret": "s", "client_kwargs": {"region_name": "us-east-1"}}
        url = "s3://bench-readback/lake"
        lake = Lake(url, opts)
        for i in range(n_versions):
            lake.commit(field_document(f"cam-{i % 20:02d}", f"s{i // 20:03d}", seed=i), {}, residual_table(200, seed=i))
        real = Lake._read_back
        times: dict[bool, list[float]] = {True: [], False: []}
        for k in range(repeat):
            for on in (True, False):
                Lake._read_back = real if on else (lambda self, *args: None)
                doc = field_document("cam-00", f"new{k}{int(on)}", seed=10_000 + 2 * k + on)
                times[on].append(timed(lambda d=doc, k=k: Lake(url, opts).commit(d, {}, residual_table(200, seed=k))))
        Lake._read_back = real
        print(f"commit on moto S3 ({n_versions} versions): {statistics.median(times[True]):.3f} s with the "
              f"read-back, {statistics.median(times[False]):.3f} s without (median of {repeat})")
        rows = Lake(url, opts).catalog().to_pylist()
        found = [fleet.FoundSession(f"/x/{r['camera_id']}/{r['session_id']}", r["camera_id"],
                                    r["session_id"], acquired=r["acquired"]) for r in rows]
        t = timed(lambda: fleet.select_sessions(found, Lake(url, opts)))
        print(f"fleet selection of {len(found)} sessions on moto S3: {t:.2f} s")
    finally:
        server.stop()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--versions", type=int, default=200)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--s3", type=int, default=0, help="also commits on moto S3 with a lake of this many versions")
    a = ap.parse_args()
    print(f"load: {os.getloadavg()[0]:.1f}")
    if a.s3:
        commits_on_s3(a.s3, a.repeat)
    if not a.versions:
        return
    with tempfile.TemporaryDirectory() as tmp:
        lake = Lake(Path(tmp) / "lake")
        docs = []
        for i in range(a.versions):
            doc = field_document(f"cam-{i % 20:02d}", f"s{i // 20:03d}", seed=i)
            docs.append(doc)
            lake.commit(doc, {}, residual_table(200, seed=i))
        real = Lake._read_back
        with_rb, without = [], []
        for k in range(a.repeat):
            for on, out in ((True, with_rb), (False, without)):
                Lake._read_back = real if on else (lambda self, *args: None)
                doc = field_document("cam-00", f"new{k}{int(on)}", seed=10_000 + 2 * k + on)
                out.append(timed(lambda d=doc, k=k: Lake(lake.url).commit(d, {}, residual_table(200, seed=k))))
        Lake._read_back = real
        print(f"commit: {statistics.median(with_rb):.3f} s with the read-back, "
              f"{statistics.median(without):.3f} s without (median of {a.repeat})")
        fps = [d["inputs"]["fingerprint"] for d in docs[:a.repeat]]
        look = [timed(lambda f=f: Lake(lake.url).catalog(filter=ds.field("fingerprint") == f,
                                                          equal={"fingerprint": f})) for f in fps]
        find = [timed(lambda f=f: Lake(lake.url).find_committed(f)) for f in fps]
        print(f"rerun's answer: {statistics.median(find):.3f} s with the read-back, "
              f"{statistics.median(look):.3f} s the lookup alone")
        rows = Lake(lake.url).catalog().to_pylist()
        found = [fleet.FoundSession(f"/x/{r['camera_id']}/{r['session_id']}", r["camera_id"], r["session_id"],
                                    acquired=r["acquired"]) for r in rows]
        real_whole = Lake.whole
        sel = timed(lambda: fleet.select_sessions(found, Lake(lake.url)))
        assert all(s.version for s in found), "every session is calibrated: none selected"
        Lake.whole = lambda self, version, row=None: None
        alone = timed(lambda: fleet.select_sessions(found, Lake(lake.url)))
        Lake.whole = real_whole
        print(f"fleet selection of {len(found)} sessions: {sel:.2f} s with the read-backs, "
              f"{alone:.2f} s without")


if __name__ == "__main__":
    main()
