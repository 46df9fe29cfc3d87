"""The README's ``fieldcal demo`` line runs as written (issue 13, goal 6).

Split from tests/flows/test_readme.py, which runs every other line of the README's
"Command line" section in order, so that the two long tests can run on two workers.
It runs against a Numba cache of its own, filled first by ``python -m fieldcal.precompile``
(what ``make`` runs after installing): the demo, a fresh user's first calibration, must
find every compiled kernel it uses there and compile nothing.
"""

import shlex
import subprocess
import sys

import pytest

from fieldcal.lake.store import Lake
from tests.flows.test_readme import FIELDCAL, readme_env, readme_lines

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def test_the_demo_line_of_the_readme_runs_as_written(prefect_server, tmp_path):
    lines = [ln for ln in readme_lines() if shlex.split(ln)[1] == "demo"]
    assert lines, "the README shows no demo line"
    cache = tmp_path / "numba-cache"
    env = dict(readme_env(prefect_server, tmp_path), NUMBA_CACHE_DIR=str(cache))
    pre = subprocess.run([sys.executable, "-m", "fieldcal.precompile"], env=env, cwd=tmp_path, capture_output=True,
                         text=True, timeout=600)
    assert pre.returncode == 0, pre.stderr[-2000:]
    kernels = [ln for ln in pre.stderr.splitlines() if ln.startswith("fieldcal precompile: ") and "done in" not in ln]
    assert len(kernels) == 5 and all(ln.endswith(": compiled (numba)") for ln in kernels), pre.stderr
    compiled = sorted(p.relative_to(cache) for p in cache.rglob("*.nbc"))
    assert compiled
    for line in lines:
        argv = [FIELDCAL] + [str(tmp_path / "out") if a == "DIR" else a
                             for a in shlex.split(line, comments=True)[1:]]
        out = subprocess.run(argv, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=900)
        assert out.returncode == 0, f"{line}\n{out.stderr[-2000:]}"
    lake = Lake(tmp_path / "out" / "lake")
    assert len(lake.catalog()) >= 2                  # the demo's goniometer and field sessions at least
    # the demo's image session ran (it measures discs and identifies codes) ...
    assert "field-images: committed" in out.stdout, out.stdout[-2000:]
    # ... and nothing was compiled that precompile had left out
    assert sorted(p.relative_to(cache) for p in cache.rglob("*.nbc")) == compiled
