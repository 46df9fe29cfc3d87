"""The real-data tests skip, with the reason, when ../shared/data is absent (issue 12).

The tests of ``tests/realdata.py``'s data sets run in a separate pytest pointed at an empty
folder (``FIELDCAL_SHARED_DATA``): every one of them is skipped with a reason that names the
data set, the folder and what to set, and none fails or errors. A data set present but
incomplete names the missing part.
"""

import os
import subprocess
import sys
from pathlib import Path

from tests import realdata

ROOT = Path(__file__).resolve().parents[1]
REAL = ["tests/field/test_dbat_photos.py",
        "tests/field/test_adjustment.py::test_calib1_default_lands_near_opencv_and_a_free_shear_drifts",
        "tests/field/test_adjustment.py::test_dbat_sheet_agrees_with_opencv_on_the_same_points"]


def run_real_data_tests(data: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, FIELDCAL_SHARED_DATA=str(data), OPENBLAS_NUM_THREADS="1")
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rs", *REAL],
                          capture_output=True, text=True, cwd=ROOT, env=env, timeout=600)


def test_without_the_data_the_real_data_tests_skip_with_the_reason(tmp_path):
    proc = run_real_data_tests(tmp_path)
    assert proc.returncode == 0, proc.stdout[-3000:]
    last = proc.stdout.strip().splitlines()[-1]
    assert "6 skipped" in last and "passed" not in last and "failed" not in last and "error" not in last, last
    reasons = [line for line in proc.stdout.splitlines() if line.startswith("SKIPPED")]
    assert len(reasons) == 6
    for line in reasons:
        assert f"not found in {tmp_path} (missing " in line and "FIELDCAL_SHARED_DATA" in line, line
    assert sum("real data dbat-camcal" in r for r in reasons) == 5
    assert sum("real data opencv-calib1" in r for r in reasons) == 1


def test_an_incomplete_data_set_names_what_is_missing(tmp_path, monkeypatch):
    monkeypatch.setattr(realdata, "DATA", tmp_path)
    (tmp_path / "dbat-camcal").mkdir()
    for name in ("images.txt", "objpts-pm.txt", "markpts.txt"):
        (tmp_path / "dbat-camcal" / name).write_text("")
    assert realdata.missing("dbat-camcal").startswith(f"real data dbat-camcal not found in {tmp_path} "
                                                      "(missing images);")
    (tmp_path / "dbat-camcal" / "images").mkdir()
    assert realdata.missing("dbat-camcal") is None
    assert "missing calib1_inputs.dat" in realdata.missing("opencv-calib1")
