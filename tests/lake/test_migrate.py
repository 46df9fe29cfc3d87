"""``fieldcal lake migrate``: a lake made by the first layout's own code, brought over and
verified row for row (every version, observation and residual, with version ids,
fingerprints and timestamps)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fieldcal.errors import LakeError
from fieldcal.lake import history
from fieldcal.lake.migrate import OldLake, migrate, verify
from fieldcal.lake.store import Lake
from fieldcal.model.camera import FIELD_PARAMS
from tests.lake import legacy_store
from tests.lake.test_lake import (
    field_document,
    field_measurements,
    goniometer_document,
    residual_table,
    spot_measurement,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def old_lake(tmp_path):
    """A lake of the first layout, made by its own code: ``(root, versions)``."""
    root = tmp_path / "old"
    old = legacy_store.Lake(root)
    versions = [old.commit(field_document("cam-a", "s1"), {"covariance": np.eye(10) * 1e-6},
                           residual_table(12), array_attrs={"covariance": {"names": list(FIELD_PARAMS)}}),
                old.commit(field_document("cam-a", "s1"), {}, residual_table(12, seed=1), force=True),
                old.commit(field_document("cam-b", "s2", f_mm=35.0, acquired="2026-05-01"), {},
                           residual_table(7, seed=2)),
                old.commit(goniometer_document(), {},
                           {"image": [None], "u_px": [1.0], "v_px": [2.0], "du_px": [0.1],
                            "dv_px": [float("nan")], "sigma_px": [0.05], "used": [True],
                            "reason": [None], "axis": ["x"], "angle_deg": [-10.0]})]
    for i in range(3):
        old.write_observations("cam-a", "s1", f"images/IMG_{i}.tif", f"{i:064x}",
                               field_measurements(f"images/IMG_{i}.tif", n=i, seed=i))
    old.write_observations("cam-g", "lab-1", "images/F000.tif", "f" * 64, spot_measurement())
    return root, [str(v) for v in versions]


def test_migrate_brings_every_version_residual_and_observation(old_lake, tmp_path):
    root, versions = old_lake
    old = OldLake(root)
    lake = Lake(tmp_path / "new")
    report = migrate(old, lake)
    assert (report.versions, report.residual_rows, report.observation_images,
            report.observation_rows) == (4, 32, 4, 4)
    cat = lake.catalog()
    assert cat["version"].to_pylist() == versions
    assert cat["forced"].to_pylist() == [False, True, False, False]
    olds = {r["version"]: r for r in old.catalog()}
    for row in cat.to_pylist():
        o = olds[row["version"]]
        for col in ("fingerprint", "created", "committed", "acquired", "code_version", "f_mm", "sigma_k3"):
            assert row[col] == o[col], col
    assert np.array_equal(lake.open_zarr(versions[0])["covariance"][:], np.eye(10) * 1e-6)
    assert lake.read_residuals(versions[3])["dv_px"].to_pylist()[0] != 0.0  # NaN kept
    assert lake.read_observations("cam-a", "s1", "images/IMG_0.tif", f"{0:064x}").num_rows == 0
    assert lake.read_observations("cam-g", "lab-1", "images/F000.tif", "f" * 64).num_rows == 1
    assert history.sql(lake, "SELECT count(*) AS n FROM residuals")["n"].to_pylist() == [32]
    # the same inputs are recognised after the move
    assert lake.commit(field_document("cam-b", "s2", f_mm=35.0, acquired="2026-05-01"), {},
                       residual_table(7, seed=2)) == versions[2]
    # run again: nothing to do, still verified
    assert migrate(old, lake).versions == 0


def test_verification_finds_a_difference(old_lake, tmp_path):
    root, versions = old_lake
    old = OldLake(root)
    lake = Lake(tmp_path / "new")
    migrate(old, lake)
    doc_path = root / "calibrations" / "cam-b" / "s2" / f"{versions[2]}.json"
    doc = json.loads(doc_path.read_text())
    doc["stats"]["rmse_px"] = 0.5
    doc_path.write_text(json.dumps(doc))
    with pytest.raises(LakeError, match=f"version {versions[2]}: the documents differ"):
        verify(old, lake)


def test_migrate_command(old_lake, tmp_path):
    root, versions = old_lake
    out = subprocess.run([sys.executable, "-m", "flows.cli", "lake", "migrate", str(root), "--lake",
                          str(tmp_path / "new")], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=300)
    assert out.returncode == 0, out.stderr
    assert "versions 4, residual rows 32" in out.stdout and "verified" in out.stdout
    assert Lake(tmp_path / "new").catalog()["version"].to_pylist() == versions
    out = subprocess.run([sys.executable, "-m", "flows.cli", "lake", "migrate", str(root), "--lake",
                          str(root)], capture_output=True, text=True, cwd=ROOT,
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=300)
    assert out.returncode == 1 and "into a new lake" in out.stderr


def test_a_lake_of_the_first_layout_is_refused_not_read_as_empty(old_lake, tmp_path):
    root, _ = old_lake
    with pytest.raises(LakeError, match="first layout.*fieldcal lake migrate"):
        Lake(root)
    out = subprocess.run([sys.executable, "-m", "flows.cli", "history", "--lake", str(root), "--camera", "cam-a"],
                         capture_output=True, text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                         timeout=300)
    assert out.returncode == 1 and len(out.stderr.strip().splitlines()) == 1
    assert "first layout" in out.stderr and "lake migrate" in out.stderr
    before = sorted(p.relative_to(root) for p in root.rglob("*"))
    migrated = tmp_path / "new"
    migrate(OldLake(root), Lake(migrated))
    assert sorted(p.relative_to(root) for p in root.rglob("*")) == before      # the old lake untouched
    assert len(Lake(migrated).catalog()) == 4
