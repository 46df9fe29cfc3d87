"""``python -m fieldcal.precompile`` (what ``make`` runs after installing).

That it compiles every kernel a calibration uses is checked where a real first run
happens: tests/flows/test_readme_demo.py runs the demo against a cache it filled.
"""

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_precompile_without_compiled_kernels_says_why_per_kernel_and_succeeds():
    # FIELDCAL_NUMBA=0 stands for a platform where Numba cannot compile: the NumPy
    # references run, the installation must not fail, and each kernel says why
    env = dict(os.environ, FIELDCAL_NUMBA="0", PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "fieldcal.precompile"], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("fieldcal precompile: ")]
    kernels = {ln.split(": ")[1]: ln.split(": ", 2)[2] for ln in lines[:-1]}
    assert set(kernels) == {"disc extraction", "bundle residuals and blocks", "image residuals of all observations",
                            "block-sparse normal equations", "survey consider matrix"}
    assert set(kernels.values()) == {"switched off by FIELDCAL_NUMBA=0"}
    assert lines[-1].startswith("fieldcal precompile: done in ")


def test_a_failing_precompile_says_so_in_one_line_and_fails(monkeypatch, capsys):
    from fieldcal import precompile

    def broken():
        raise OSError("[Errno 28] No space left on device:\n'/tmp/fieldcal-precompile-x'")

    monkeypatch.setattr(precompile, "precompile", broken)
    assert precompile.main() == 1
    err = capsys.readouterr().err
    assert err == ("fieldcal precompile: failed (OSError: [Errno 28] No space left on device: "
                   "'/tmp/fieldcal-precompile-x')\n")


def test_the_makefile_refills_the_cache_when_any_compiled_source_changes():
    # Numba checks only the file a kernel is defined in; a function compiled into a kernel
    # from another file (the camera model's terms, inlined into the bundle kernel) must be
    # a prerequisite of the Makefile's precompile target, or a change to it alone would
    # leave the old machine code in use. Every function any fieldcal module hands to
    # numba.njit, found by importing them all with njit recording its arguments' files:
    script = r"""
import importlib, inspect, pkgutil, numba, fieldcal
real, seen = numba.njit, set()
def njit(*a, **k):
    if a and callable(a[0]):
        seen.add(inspect.getsourcefile(a[0]))
        return real(*a, **k)
    decorate = real(*a, **k)
    def wrap(fn):
        seen.add(inspect.getsourcefile(fn))
        return decorate(fn)
    return wrap
numba.njit = njit
for m in pkgutil.walk_packages(fieldcal.__path__, "fieldcal."):
    importlib.import_module(m.name)
print("\n".join(sorted(seen)))
"""
    out = subprocess.run([sys.executable, "-c", script], env=dict(os.environ, PYTHONPATH=str(ROOT)), cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    compiled = {str(Path(f).resolve().relative_to(ROOT)) for f in out.stdout.split()}
    assert {"fieldcal/model/camera.py", "fieldcal/measure/disc_kernel.py"} <= compiled   # the scan sees both kinds
    make = subprocess.run(["make", "-np", "-f", "Makefile"], cwd=ROOT, capture_output=True, text=True, timeout=60)
    line = next(ln for ln in make.stdout.splitlines() if ln.startswith("KERNEL_SOURCES := "))
    listed = set(line.split(":= ", 1)[1].split())
    assert compiled <= listed, f"compiled from files the Makefile does not list: {sorted(compiled - listed)}"
