"""Rig sessions on an object store (moto S3 on loopback, tests/conftest_s3.py), as single
sessions are (fieldcal/session/store.py): `fieldcal run s3://...` of a rig session (its small
files fetched for validation, nothing else copied), and the fleet with its root in the bucket,
a rig session of images among them measured on the Dask workers, each reading its image from
the store."""

from __future__ import annotations

import json

import pytest

from fieldcal.lake.store import Lake
from fieldcal.rig_run import prepare_rig, run_rig
from fieldcal.synthetic.rig import two_head_rig, write_rig_image_session, write_rig_session
from flows import cli
from tests import conftest_s3

s3_server, s3_lake = conftest_s3.s3_server, conftest_s3.s3_lake          # the moto fixtures


def _cli(capsys, *argv) -> tuple[int, str, str]:
    status = cli.main([str(a) for a in argv])
    got = capsys.readouterr()
    return status, got.out, got.err


def test_fieldcal_run_of_a_rig_session_on_s3(s3_lake, tmp_path, capsys, monkeypatch):
    url, options = s3_lake
    local = write_rig_session(tmp_path / "bar2-s1", two_head_rig(seed=21))
    lake = Lake(url, options)
    lake.fs.put(str(local) + "/", f"{url}/sessions/bar2/bar2-s1/", recursive=True)
    session = f"{url}/sessions/bar2/bar2-s1"
    text = json.dumps(options)
    status, out, err = _cli(capsys, "run", session, "--lake", f"{url}/lake", "--storage-options", text,
                            "--json", tmp_path / "rig.json")
    assert status == 0, err
    rig = json.loads((tmp_path / "rig.json").read_text())
    in_lake = Lake(f"{url}/lake", options)
    (row,) = in_lake.rig_catalog().to_pylist()
    assert out.strip() == row["version"] == rig["version"] and rig["session_id"] == "bar2-s1"
    assert sorted(in_lake.catalog()["version"].to_pylist()) == sorted(row["head_versions"])
    # the same inputs as the local copy of the session: the same fingerprint
    assert rig["inputs"]["fingerprint"] == prepare_rig(local).fingerprint
    status, again, err = _cli(capsys, "run", session, "--lake", f"{url}/lake", "--storage-options", text)
    assert status == 0 and again.strip() == row["version"], err                  # unchanged
    status, out, err = _cli(capsys, "run", f"{url}/sessions/bar2/nothing", "--lake", f"{url}/lake",
                            "--storage-options", text)
    assert status == 2 and out == "" and err.count("\n") == 1 and "nothing" in err
    (tmp_path / "bad.csv").write_text("id,X,Y,Z,sigma_mm,code\nW1,1,2\n")
    lake.fs.put(str(tmp_path / "bad.csv"), f"{session}/targets.csv")
    status, out, err = _cli(capsys, "run", session, "--lake", f"{url}/lake", "--storage-options", text)
    assert status == 2 and err.count("\n") == 1 and f"{session}/targets.csv" in err and "fieldcal-rig-" not in err


@pytest.mark.slow
@pytest.mark.usefixtures("prefect_server")
def test_the_fleet_measures_a_rig_session_of_images_on_s3_on_its_workers(s3_lake, tmp_path, monkeypatch):
    from flows import fleet
    from flows.fleet import recalibrate_fleet

    url, options = s3_lake
    monkeypatch.setenv("FIELDCAL_HASH_CACHE", str(tmp_path / "hashes.sqlite"))
    sr = two_head_rig(seed=7)
    info = write_rig_image_session(tmp_path / "sessions" / "bar2" / "bar2-img", sr, scale=0.2,
                                   exposures=range(0, 24, 3), seed=3)
    write_rig_session(tmp_path / "sessions" / "bar2" / "bar2-obs", two_head_rig(seed=22), acquired="2026-11-21")
    lake = Lake(url, options)
    lake.fs.put(str(tmp_path / "sessions") + "/", f"{url}/sessions/", recursive=True)
    mapped = []
    real = fleet._rig_mapper

    def spy(address):
        mapped.append(address)
        return real(address)

    monkeypatch.setattr(fleet, "_rig_mapper", spy)
    first = recalibrate_fleet(url, storage_options=options, n_workers=1)
    by = {s["session_id"]: s for s in first["sessions"]}
    assert set(by) == {"bar2-img", "bar2-obs"} and all(s["status"] == "committed" for s in by.values()), by
    assert by["bar2-img"]["n_images"] == 16 and by["bar2-img"]["n_left_out"] == 0
    assert sorted(a is not None for a in mapped) == [False, True]     # the images' session on the cluster
    rows = {r["session_id"]: r for r in Lake(url, options).rig_catalog().to_pylist()}
    assert {by[s]["version"] for s in by} == {rows[s]["version"] for s in rows}
    doc = Lake(url, options).load_rig_document(rows["bar2-img"]["version"])
    assert sum(h["n_observations"] for h in doc["stats"]["heads"].values()) > 1000
    # the same images measured here, from a local folder: the same rig
    version, _, outcome = run_rig(info["folder"], Lake(tmp_path / "local-lake"))
    local = Lake(tmp_path / "local-lake").load_rig_document(version)
    for a, b in zip(doc["heads"], local["heads"], strict=True):
        assert a["t_camera_in_rig_m"] == pytest.approx(b["t_camera_in_rig_m"], abs=1e-9)
    again = recalibrate_fleet(url, storage_options=options, n_workers=1)
    assert (again["n_found"], again["n_committed"], again["n_skipped"]) == (2, 0, 2)     # the next night
    assert {s["version"] for s in again["sessions"]} == {by[s]["version"] for s in by}
