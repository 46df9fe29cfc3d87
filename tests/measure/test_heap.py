"""The memory of one image kept for the next (:mod:`fieldcal.measure.heap`)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

ALLOCATE = """
    import json, resource, sys, threading
    from fieldcal.measure.heap import keep_freed_memory

    kept = keep_freed_memory() if sys.argv[1] == "keep" else None   # before any other thread exists
    import numpy as np
    faults = []

    def frames():                 # three 100 MB frames in a worker thread, one after the other
        for _ in range(3):
            before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            pixels = np.ones(50_000_000, np.uint16)          # every page written
            faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
            del pixels

    t = threading.Thread(target=frames)
    t.start()
    t.join()
    print(json.dumps({"kept": kept, "again": keep_freed_memory() if kept else None, "faults": faults}))
"""


def _run(mode: str) -> dict:
    import json

    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")   # no BLAS threads either
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(ALLOCATE), mode], capture_output=True, text=True,
                         cwd=ROOT, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_a_freed_frame_is_reused_by_the_next_without_fresh_pages():
    kept = _run("keep")
    assert kept["kept"] is True and kept["again"] is True
    assert all(n < 10 for n in kept["faults"][1:]), kept          # the same memory, no page faults
    # without it, each frame's memory goes back to the kernel and comes back as fresh pages
    # (at least one fault per 2 MB huge page of the 100 MB)
    default = _run("none")
    assert all(n >= 50 for n in default["faults"]), default
