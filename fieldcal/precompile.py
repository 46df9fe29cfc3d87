"""Compile fieldcal's Numba kernels into Numba's disk cache once, ahead of the first run.

Numba compiles a kernel the first time a process calls it with a new specialisation
(array dtypes, layouts, read-only flags) and, with ``cache=True``, keeps the machine code
on disk (``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``); every later process,
a Dask worker included, loads it in milliseconds (:mod:`fieldcal.contract.compiled`). On a fresh
installation nothing is cached yet, and the first calibration paid for the compilation:
the first ``make demo`` of a fresh clone took 52 s, 19 s with the kernels precompiled
(the Prefect server up; bench/README.md, ``bench_first_run.py``).
``make`` runs this module once after installing (``python -m fieldcal.precompile``), and
again, after deleting the old cache files, when a kernel's source changes: Numba checks
only the file a kernel is defined in, and the camera model's terms
(:func:`fieldcal.model.camera.correction_terms`) are inlined into the bundle kernel, so a
change to them alone would leave the old machine code in use (the Makefile lists the
files). On the machines of a Dask cluster, run it once after installing fieldcal
(deploy/README.md).

It runs what a calibration runs, on small made-up inputs in a temporary folder:

- the measuring warm-up (:func:`fieldcal.measure.warm.warm_up_measuring`: the disc
  kernel on uint8 and uint16, writable and read-only images, each TIFF layout);
- :func:`fieldcal.pipeline.prepare` + :func:`fieldcal.pipeline.solve` of a small
  synthetic observation session (``wide_field``), targets fixed and targets adjusted:
  the bundle, normal-equation, Schur-complement, covariance and survey-consider kernels,
  with the array layouts a session read from its files gives them.

``tests/flows/test_readme_demo.py`` checks that ``fieldcal demo`` compiles nothing more
after it. Where a kernel cannot be compiled, the NumPy reference runs; this module then
says so (one line per kernel) and still exits 0.
"""

from __future__ import annotations

import multiprocessing
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from fieldcal.errors import one_line

__all__ = ["precompile", "main"]

_FINGERPRINT = "sha256:" + "0" * 64


def _measuring() -> dict[str, str]:
    """The measuring warm-up; the disc kernel's status."""
    from fieldcal.measure import disc_kernel
    from fieldcal.measure.warm import warm_up_measuring

    warm_up_measuring()
    return {"disc extraction": "compiled (numba)" if disc_kernel.available() else str(disc_kernel.problem())}


def _solving() -> dict[str, str]:
    """prepare + solve of a written synthetic observation session, targets fixed and adjusted;
    the solver kernels' statuses."""
    from fieldcal import pipeline
    from fieldcal.contract import compiled
    from fieldcal.synthetic.field import wide_field
    from fieldcal.synthetic.session_writer import write_field_session

    with tempfile.TemporaryDirectory(prefix="fieldcal-precompile-") as tmp:
        folder = Path(tmp) / "session"
        write_field_session(folder, wide_field(seed=0), images=False, observations_csv=True)
        for targets_adjusted in (False, True):
            prepared = pipeline.prepare(folder, pipeline.Settings(targets_adjusted=targets_adjusted))
            pipeline.solve(prepared, {}, fingerprint_=_FINGERPRINT)
    return compiled.statuses()


def precompile() -> dict[str, str]:
    """Run the measuring warm-up and a small adjustment so every kernel is compiled and cached.

    The two run in processes of their own at the same time (Numba compiles on one core:
    25-31 s instead of 40 s here).

    Returns
    -------
    dict
        Kernel name -> one line: ``"compiled (numba)"`` or why the NumPy reference runs.
    """
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as pool:
        parts = [pool.submit(_measuring), pool.submit(_solving)]
        return {**parts[0].result(), **parts[1].result()}


def main() -> int:
    """``python -m fieldcal.precompile``: compile, then one line per kernel on standard error.

    Exit status 0 also when a kernel cannot be compiled (the NumPy reference runs); 1, with
    one line, when the warm-up or the small solve fails (a broken installation)."""
    t0 = time.perf_counter()
    try:
        statuses = precompile()
    except KeyboardInterrupt:
        print("fieldcal precompile: interrupted (the kernels not cached yet compile on first use)", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - any failure: one line, not a traceback
        print(f"fieldcal precompile: failed ({type(err).__name__}: {one_line(err)})", file=sys.stderr)
        return 1
    for name, status in statuses.items():
        print(f"fieldcal precompile: {name}: {status}", file=sys.stderr)
    print(f"fieldcal precompile: done in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
