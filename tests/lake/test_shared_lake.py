"""A lake a team shares: every file the lake writes honours the process umask (issue 24, class 6).

Documents, ``README.md``, published reports and quarantine records were written 0600 (from
``tempfile.mkstemp``) while Delta and Zarr files were 0644: another user's ``show``,
``export`` and ``lake check`` failed with "Permission denied". The lake is made by a child
process with a given umask; every file and folder must have the mode that umask gives, and
a second user (``nobody``, through ``setpriv``) reads the lake with ``show``, ``export``,
``history`` and ``lake check``.
"""

import os
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MAKE = """
import sys
from fieldcal.lake.store import Lake
from tests.lake.test_lake import field_document, residual_table
lake = Lake(sys.argv[1])
v = lake.commit(field_document("cam-a", "s1"), {}, residual_table())
lake.commit(field_document("cam-a", "s2", seed=1, f_mm=50.1, acquired="2026-12-01"), {}, residual_table())
lake.tables.quarantine(lake.paths("cam-a", "s1", v)["document"], "a test")   # a quarantine record
lake.storage.write(lake.paths("cam-a", "s1", v)["document"], lake.storage.read(
    "quarantine/" + lake.storage.listdir("quarantine")[0] + "/" + lake.paths("cam-a", "s1", v)["document"]))
lake.storage.write("reports/cam-a/page.html", b"<html></html>")                 # as publish writes
"""


def make_lake(root: Path, umask: int) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    subprocess.run([sys.executable, "-c", MAKE, str(root)], check=True, cwd=ROOT, env=env, timeout=120,
                   preexec_fn=lambda: os.umask(umask))


@pytest.fixture
def shared_tmp():
    """A folder others may enter (pytest's tmp_path is private to its user)."""
    path = Path(tempfile.mkdtemp(prefix="fieldcal-shared-", dir="/tmp"))
    path.chmod(0o755)
    yield path
    shutil.rmtree(path, ignore_errors=True)


@pytest.mark.parametrize("umask", [0o022, 0o002, 0o027, 0o077], ids=oct)
def test_every_file_and_folder_gets_the_mode_of_the_umask(shared_tmp, umask):
    root = shared_tmp / "lake"
    make_lake(root, umask)
    paths = [root, *root.rglob("*")]
    kinds = {p.suffix or p.name for p in paths if p.is_file()}
    assert {".json", ".md", ".parquet", ".html"} <= kinds              # documents, README, Delta, reports
    wrong = {str(p.relative_to(root)): oct(stat.S_IMODE(p.stat().st_mode)) for p in paths
             if stat.S_IMODE(p.stat().st_mode) != (0o777 if p.is_dir() else 0o666) & ~umask}
    assert wrong == {}


def test_a_second_user_reads_the_shared_lake(shared_tmp):
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv(1) to act as a second user")
    root = shared_tmp / "lake"
    make_lake(root, 0o022)
    home = shared_tmp / "home"
    home.mkdir()
    os.chown(home, 65534, 65534)
    as_nobody = ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]
    probe = subprocess.run([*as_nobody, sys.executable, "-c", "import fieldcal"], capture_output=True, cwd=ROOT,
                           env=dict(os.environ, PYTHONPATH=str(ROOT), HOME=str(home)))
    if probe.returncode != 0:
        pytest.skip(f"the second user cannot run this checkout's Python: {probe.stderr[-200:]!r}")
    env = dict(os.environ, PYTHONPATH=str(ROOT), HOME=str(home), PYTHONDONTWRITEBYTECODE="1")
    env.pop("FIELDCAL_LAKE", None)
    for args in (["show", "latest", "--camera", "cam-a"], ["history", "--camera", "cam-a"], ["lake", "check"],
                 ["export", "latest", "--camera", "cam-a", "--format", "json"]):
        out = subprocess.run([*as_nobody, sys.executable, "-m", "flows.cli", *args, "--lake", str(root)],
                             capture_output=True, text=True, cwd=home, env=env, timeout=300)
        assert out.returncode == 0, (args, out.stderr)
        assert "Permission denied" not in out.stderr and "damaged" not in out.stderr
