"""One bad file never takes the lake down; hostile names are refused; gc globs nothing.

Issue 17: a damaged table file, a catalogued version whose folder is gone, a truncated
residual file, a missing Zarr chunk. Readers skip what they cannot read and say so,
every other camera keeps working, ``fieldcal lake check`` lists each damaged object and
what depends on it, and a missing chunk is an error naming it (never zeros).
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from fieldcal.analysis.correction import correction_arrays
from fieldcal.errors import InputError, LakeError
from fieldcal.lake import history
from fieldcal.lake.check import check
from fieldcal.lake.store import Lake
from fieldcal.products.report import fleet_summary
from tests.lake.test_lake import field_document, field_measurements, lake_files, residual_table

ROOT = Path(__file__).resolve().parents[2]
CAMERAS = ("cam-a", "cam-b", "cam-c")


def make_lake(root: Path) -> tuple[Lake, dict]:
    """Two versions per camera (sessions s1, s2), each its own commit and files."""
    lake = Lake(root)
    versions = {}
    for i, cam in enumerate(CAMERAS):
        for j, ses in enumerate(("s1", "s2")):
            v = lake.commit(field_document(cam, ses, seed=10 * i + j, f_mm=50.0 + 0.001 * j,
                                           acquired=f"2026-0{j + 1}-10"), {},
                            residual_table(10 + j, seed=i))
            versions[(cam, ses)] = str(v)
    return lake, versions


def data_file_of(root: Path, table: str, version: str) -> Path:
    """The one data file of a table that holds rows of ``version``."""
    hits = [p for p in (root / table).rglob("*.parquet") if "_delta_log" not in p.parts
            and version in pq.read_table(p, columns=["version"])["version"].to_pylist()]
    assert len(hits) == 1, hits
    return hits[0]


def cli(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flows.cli", *map(str, args)], capture_output=True,
                          text=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT), **(env or {})),
                          timeout=300)


# --------------------------------------------------------------------------------------
# damaged files
# --------------------------------------------------------------------------------------
@pytest.fixture
def damaged(tmp_path):
    """cam-b's s2 catalog file is garbage, cam-c's s2 residual file truncated, cam-a's s1
    version folder gone: ``(root, versions)``."""
    root = tmp_path / "lake"
    _, versions = make_lake(root)
    data_file_of(root, "catalog", versions[("cam-b", "s2")]).write_bytes(b"not parquet at all")
    res = data_file_of(root, "residuals", versions[("cam-c", "s2")])
    res.write_bytes(res.read_bytes()[: res.stat().st_size // 2])
    for p in (root / "calibrations" / "cam-a" / "s1").iterdir():
        if p.is_dir():
            import shutil

            shutil.rmtree(p)
        else:
            p.unlink()
    return root, versions


def test_readers_skip_and_report_damaged_files_and_other_cameras_work(damaged):
    root, versions = damaged
    lake = Lake(root)
    cat = lake.catalog()
    assert versions[("cam-b", "s2")] not in cat["version"].to_pylist()
    assert cat.num_rows == 5
    assert len(lake.problems) == 1 and "not parquet" not in str(lake.problems[0]) \
        and str(lake.problems[0]).startswith("catalog: catalog/part-")
    assert history.camera_history(lake, "cam-a")["version"].to_pylist() == \
        [versions[("cam-a", "s1")], versions[("cam-a", "s2")]]
    assert history.camera_history(lake, "cam-b")["version"].to_pylist() == [versions[("cam-b", "s1")]]
    assert history.fleet(lake)["version"].to_pylist() == [
        versions[("cam-a", "s2")], versions[("cam-b", "s1")], versions[("cam-c", "s2")]]
    n = history.sql(lake, "SELECT camera_id, count(*) AS n FROM residuals GROUP BY ALL ORDER BY 1")
    assert n.to_pylist() == [{"camera_id": "cam-a", "n": 21}, {"camera_id": "cam-b", "n": 10},
                             {"camera_id": "cam-c", "n": 10}]  # cam-c s2's 11 rows unreadable
    with pytest.raises(LakeError, match=f"version {versions[('cam-c', 's2')]}: residuals unreadable"):
        lake.read_residuals(versions[("cam-c", "s2")])
    with pytest.raises(LakeError, match=f"version {versions[('cam-a', 's1')]}: its document .* is missing"):
        lake.load_document(versions[("cam-a", "s1")])
    assert lake.load_document(versions[("cam-a", "s2")])["version"] == versions[("cam-a", "s2")]

    # the fleet comparison: cam-a's previous version is gone, cam-c compares, cam-b has one left
    fleet = {r["camera_id"]: r for r in fleet_summary(lake).to_pylist()}
    assert fleet["cam-a"]["verdict"].startswith("cannot compare: ") and "missing" in fleet["cam-a"]["verdict"]
    assert fleet["cam-b"]["verdict"] == "only one calibration"
    assert fleet["cam-c"]["p_value"] is not None


def test_lake_check_lists_every_damaged_object_and_what_depends_on_it(damaged):
    root, versions = damaged
    damage = check(Lake(root))
    text = "\n".join(str(d) for d in damage)
    assert len(damage) == 5, text
    vb, vc, va = versions[("cam-b", "s2")], versions[("cam-c", "s2")], versions[("cam-a", "s1")]
    assert f"versions {vb} .. {vb}, are hidden from every reader" in text
    assert f"version {vb} is hidden from every reader (`fieldcal lake repair --apply` restores it)" in text
    assert f"residuals of camera cam-c (versions {vc} .. {vc}) cannot be read" in text.replace(
        "row(s) of ", "").replace("11 ", "")
    assert f"calibrations/cam-a/s1/{va}.json: missing -> version {va}" in text
    assert f"calibrations/cam-a/s1/{va}.zarr" in text
    assert check(Lake(make_lake(root.parent / "sound")[0].url)) == []


def test_cli_keeps_working_on_a_damaged_lake(damaged):
    root, versions = damaged
    out = cli("history", "--lake", root, "--camera", "cam-a", "--format", "json")
    assert out.returncode == 0, out.stderr
    assert [r["version"] for r in json.loads(out.stdout)] == [versions[("cam-a", "s1")],
                                                               versions[("cam-a", "s2")]]
    assert out.stderr == ""  # the damaged file holds none of cam-a's rows: it is not read
    out = cli("history", "--lake", root, "--camera", "cam-b", "--format", "json")
    assert out.returncode == 0, out.stderr
    assert [r["version"] for r in json.loads(out.stdout)] == [versions[("cam-b", "s1")]]
    assert out.stderr.startswith("fieldcal history: skipped catalog: catalog/part-")
    assert len(out.stderr.splitlines()) == 1
    for args in (("history", "--lake", root), ("show", "latest", "--camera", "cam-c", "--lake", root),
                 ("history", "--lake", root, "--sql", "SELECT count(*) FROM residuals")):
        out = cli(*args)
        assert out.returncode == 0, (args, out.stderr)
    out = cli("show", versions[("cam-a", "s1")], "--lake", root)
    assert out.returncode == 1 and "is missing" in out.stderr and len(out.stderr.splitlines()) == 1
    out = cli("lake", "check", "--lake", root)
    assert out.returncode == 1 and len(out.stdout.splitlines()) == 5      # the 4, and the version hidden
    assert "5 damaged object(s)" in out.stderr


def test_a_missing_or_damaged_zarr_chunk_is_an_error_naming_it(tmp_path):
    lake = Lake(tmp_path)
    cov = np.zeros((10, 10))  # an all-zero chunk is written too: missing never means zero
    v = lake.commit(field_document(), {"covariance": cov}, residual_table(),
                    array_attrs={"covariance": {"names": [f"p{i}" for i in range(10)]}})
    zarr_dir = tmp_path / "calibrations" / "cam-a" / "s1" / f"{v}.zarr"
    assert (zarr_dir / "covariance" / "c" / "0" / "0").is_file()
    (zarr_dir / "sigma" / "c" / "0").unlink()
    with pytest.raises(LakeError, match=rf"chunk .*{v}\.zarr/sigma/c/0 is missing"):
        lake.open_zarr(v)
    from fieldcal.analysis.uncertainty import Calibration

    with pytest.raises(LakeError, match="sigma/c/0 is missing"):
        Calibration.from_lake(lake, v)
    doc2 = field_document(seed=3)
    v2 = lake.commit(doc2, correction_arrays(doc2), residual_table())
    chunk = tmp_path / "calibrations" / "cam-a" / "s1" / f"{v2}.zarr" / "correction_field" / "c" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[-1] ^= 0xFF
    chunk.write_bytes(bytes(data))
    with pytest.raises(LakeError, match="correction_field (cannot be read|does not match)"):
        lake.open_zarr(v2)


# --------------------------------------------------------------------------------------
# hostile names
# --------------------------------------------------------------------------------------
HOSTILE = ["cam\n", "cam\x00a", "cam\x1b[31m", "cam[ab]", "cam*", "cam?", "a/b", "..",
           "../etc", "x" * 200, "", " cam", "cam\\a"]


@pytest.mark.parametrize("bad", HOSTILE)
def test_hostile_ids_are_refused_with_one_line_before_anything_is_written(tmp_path, bad):
    lake = Lake(tmp_path / "lake")
    for field in ("camera_id", "session_id"):
        doc = field_document()
        doc[field] = bad
        with pytest.raises(InputError, match=f"{field} must be 1-128 of letters") as info:
            lake.commit(doc, {}, residual_table())
        assert "\n" not in str(info.value) and len(str(info.value)) < 300
    with pytest.raises(InputError, match="camera_id must be") as info:
        lake.latest(bad)
    assert "\n" not in str(info.value)
    with pytest.raises(InputError, match="session_id must be"):
        lake.write_observations("cam-a", bad, "images/a.tif", "0" * 64, field_measurements())
    assert not (tmp_path / "lake").exists()


@pytest.mark.parametrize("bad", ["images/a\n.tif", "/etc/passwd", "images/../../x.tif", "a\\b.tif",
                                 "i" * 1025])
def test_hostile_image_names_are_refused(tmp_path, bad):
    with pytest.raises(InputError, match="image name must be") as info:
        Lake(tmp_path).write_observations("cam-a", "s1", bad, "0" * 64, field_measurements())
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("odd_name", ["lake*", "lake-*"])
def test_gc_never_touches_a_lake_whose_path_a_glob_would_match(tmp_path, odd_name):
    """A lake at x/lake* beside x/lakea: gc of the first leaves the second whole."""
    odd, plain = tmp_path / odd_name, tmp_path / odd_name.replace("*", "a")
    lake_odd, lake_plain = Lake(odd), Lake(plain)
    lake_odd.commit(field_document("cam-a", "s1"), {}, residual_table())
    v = lake_plain.commit(field_document("cam-a", "s2"), {}, residual_table())
    # a crashed commit's leftovers in the plain lake, old enough for any grace
    stale = plain / "calibrations" / "cam-a" / "s9" / "20200101T000000Z-00000000-0000.json"
    stale.parent.mkdir(parents=True)
    stale.write_text("{}")
    before = lake_files(plain)
    assert lake_odd.gc(grace_s=0.0) == []
    assert lake_files(plain) == before
    assert lake_plain.load_document(v)["version"] == v and lake_plain.catalog().num_rows == 1
    assert lake_plain.gc(grace_s=0.0) == ["calibrations/cam-a/s9/20200101T000000Z-00000000-0000.json"]


@pytest.mark.parametrize("odd_name", ["lake[ab]", "lake%41", "lake#1", "lake?", "lake^", "lake|x"])
def test_a_lake_path_delta_cannot_use_is_refused_with_one_line(tmp_path, odd_name):
    """delta-rs reads a local path as a URL: x/lake[ab] would fail half-way, x/lake%41 would
    be written at x/lakeA. Such a path is refused before anything is read or written."""
    (tmp_path / "lakeA").mkdir()
    with pytest.raises(InputError, match="Delta Lake cannot keep tables there") as info:
        Lake(tmp_path / odd_name)
    assert "\n" not in str(info.value)
    if odd_name == "lake[ab]":  # the command says it in one line too
        out = cli("history", "--lake", tmp_path / odd_name)
        assert out.returncode == 2 and len(out.stderr.splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lakeA"]


def test_gc_command_is_a_dry_run_unless_told(tmp_path):
    lake = Lake(tmp_path)
    lake.commit(field_document(), {}, residual_table())
    stale = tmp_path / "calibrations" / "cam-a" / "s1" / "20200101T000000Z-00000000-0000.zarr"
    stale.mkdir(parents=True)
    (stale / "zarr.json").write_text("{}")
    two_days_ago = time.time() - 2 * 86400     # gc goes by the files' times (issue 24)
    for p in (stale / "zarr.json", stale):
        os.utime(p, (two_days_ago, two_days_ago))
    out = cli("gc", "--lake", tmp_path)
    assert out.returncode == 0 and "would remove calibrations/cam-a/s1/2020" in out.stdout
    assert stale.exists()
    out = cli("gc", "--lake", tmp_path, "--apply", "--grace-s", "60")
    assert out.returncode == 0 and "1 part(s) of uncommitted versions removed" in out.stdout
    assert not stale.exists() and lake.catalog().num_rows == 1


def test_gc_refuses_to_run_on_a_damaged_catalog(tmp_path):
    """A hidden catalog row must not make gc delete that version's parts."""
    lake, versions = make_lake(tmp_path)
    data_file_of(tmp_path, "catalog", versions[("cam-b", "s1")]).write_bytes(b"")
    with pytest.raises(LakeError, match="gc stops: the catalog .* is damaged"):
        Lake(tmp_path).gc(grace_s=0.0)
    assert len(lake_files(tmp_path / "calibrations")) > 0



