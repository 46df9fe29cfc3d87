"""The README's ``fieldcal demo`` line runs as written (issue 13, goal 6).

Split from tests/flows/test_readme.py, which runs every other line of the README's
"Command line" section in order, so that the two long tests can run on two workers.
"""

import shlex
import subprocess

import pytest

from fieldcal.lake.store import Lake
from tests.flows.test_readme import FIELDCAL, readme_env, readme_lines

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def test_the_demo_line_of_the_readme_runs_as_written(prefect_server, tmp_path):
    lines = [ln for ln in readme_lines() if shlex.split(ln)[1] == "demo"]
    assert lines, "the README shows no demo line"
    for line in lines:
        argv = [FIELDCAL] + [str(tmp_path / "out") if a == "DIR" else a
                             for a in shlex.split(line, comments=True)[1:]]
        out = subprocess.run(argv, env=readme_env(prefect_server, tmp_path), cwd=tmp_path, capture_output=True,
                             text=True, timeout=900)
        assert out.returncode == 0, f"{line}\n{out.stderr[-2000:]}"
    lake = Lake(tmp_path / "out" / "lake")
    assert len(lake.catalog()) >= 2                  # the demo's goniometer and field sessions at least
