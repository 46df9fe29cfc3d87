"""A rerun answers from the lake only with a version that reads back whole (issue 24, class 1).

Once a version's folder is gone (an operator's ``rm``, a partial restore, a lost race with
gc), ``fieldcal run`` of the same inputs calibrates again and says why, instead of printing
the dead version with exit 0, and ``fieldcal fleet`` does likewise instead of "calibrated
already" for ever.
"""

import json
import shutil

import pytest

from fieldcal.lake.store import Lake
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.session_writer import write_field_session
from tests.flows.test_cli import env_for, fieldcal

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


@pytest.fixture(scope="module")
def calibrated(prefect_server, tmp_path_factory):
    """A lake holding one calibrated observation-only session: (lake, session folder, version)."""
    tmp = tmp_path_factory.mktemp("whole")
    folder = tmp / "sessions" / "2026-04-02-wall"
    write_field_session(folder, wide_field(seed=9), images=False, observations_csv=True, camera_id="cam-rm",
                        acquired="2026-04-02T10:00:00Z")
    proc = fieldcal("run", folder, "--lake", tmp / "lake", env=env_for(prefect_server, tmp), cwd=tmp)
    assert proc.returncode == 0, proc.stderr
    return tmp / "lake", folder, proc.stdout.strip()


def lake_without_the_version_folder(calibrated, dest):
    lake, _, version = calibrated
    shutil.copytree(lake, dest)
    (folder,) = (dest / "calibrations" / "cam-rm").iterdir()
    shutil.rmtree(folder)                                            # the operator's rm -r
    return dest, version


def test_run_recalibrates_when_the_version_it_would_answer_with_is_gone(calibrated, prefect_server, tmp_path):
    lake, version = lake_without_the_version_folder(calibrated, tmp_path / "lake")
    proc = fieldcal("run", calibrated[1], "--lake", lake, env=env_for(prefect_server, tmp_path), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    new = proc.stdout.strip()
    assert new != version and Lake(lake).whole(new) is None
    assert f"fieldcal run: version {version} of these inputs does not read back whole (its document " \
           f"calibrations/cam-rm/2026-04-02-wall/{version}.json is missing): calibrated again" in proc.stderr
    again = fieldcal("run", calibrated[1], "--lake", lake, env=env_for(prefect_server, tmp_path), cwd=tmp_path)
    assert (again.returncode, again.stdout.strip()) == (0, new)         # and now answered from the lake


def test_fleet_recalibrates_a_session_whose_version_is_gone(calibrated, prefect_server, tmp_path):
    lake, version = lake_without_the_version_folder(calibrated, tmp_path / "lake")
    out = fieldcal("fleet", calibrated[1].parent, "--lake", lake, "--format", "json",
                   env=env_for(prefect_server, tmp_path), cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    (entry,) = json.loads(out.stdout)["sessions"]
    assert entry["status"] == "committed" and entry["version"] != version, entry
    assert f"version {version} does not read back whole" in entry["reason"]
    assert Lake(lake).whole(entry["version"]) is None
