"""The versioned lake on a local filesystem: versions, catalog, claims, cache, fingerprints.

The documents are small synthetic ones made here (no solver); the multi-process tests use
the ``spawn`` start method so the children share nothing with the test process but the lake.
"""

import datetime as dt
import hashlib
import json
import multiprocessing
import os
import queue
import re
import stat
from pathlib import Path

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest
import zarr

import fieldcal
from fieldcal.errors import InputError, LakeError
from fieldcal.lake.store import Lake, new_version, observations_key, version_time
from fieldcal.model.camera import FIELD_PARAMS, GONIOMETER_PARAMS, PARAM_NAMES
from fieldcal.model.rotations import R_world_to_camera_from_opk
from fieldcal.session.fingerprint import (
    canonical_json,
    code_version,
    fingerprint,
    is_fingerprint,
    sha256_file,
)

VERSION_RE = re.compile(r"^\d{8}T\d{6}Z-[0-9a-f]{8}-[0-9a-f]{4}$")


# --------------------------------------------------------------------------------------
# synthetic documents (also used by test_history.py and test_lake_s3.py)
# --------------------------------------------------------------------------------------
def field_document(camera_id="cam-a", session_id="s1", *, seed=0, f_mm=50.0,
                   acquired="2026-11-20T09:30:00Z", n_images=3):
    """A field-method calibration document; the fingerprint depends on all arguments."""
    rng = np.random.default_rng(seed)
    params = dict.fromkeys(PARAM_NAMES, 0.0)
    params.update(f_mm=f_mm, xp_mm=0.012, yp_mm=-0.021, k1=-2.5e-5, k2=1.0e-8, p1=1.5e-6,
                  p2=-2.0e-6, a1=3.0e-5, a2=-1.0e-5)
    sigma = dict.fromkeys(PARAM_NAMES)
    sigma.update({n: float(s) for n, s in zip(FIELD_PARAMS, rng.uniform(1e-7, 1e-3, 10),
                                              strict=True)})
    sigma["k3"] = None  # held fixed in this session
    images = []
    for i in range(n_images):
        opk = rng.uniform(-0.2, 0.2, 3)
        images.append({
            "file": f"images/IMG_{i:04d}.tif", "station": f"S{i % 2}",
            "center_m": rng.normal(0.0, 5.0, 3).tolist(),
            "rotation_world_to_camera": R_world_to_camera_from_opk(*opk).tolist(),
            "sigma_center_m": [0.004, 0.005, None] if i == 0 else [0.004, 0.005, 0.006],
            "n_observations": 100 + i, "rmse_px": 0.2 + 0.01 * i,
        })
    return {
        "schema": "fieldcal.calibration/1", "camera_id": camera_id, "session_id": session_id,
        "method": "field", "created": "2026-11-22T10:00:00Z", "acquired": acquired,
        "sensor": {"width_px": 820, "height_px": 628, "pixel_size_um": 5.3},
        "model": "fieldcal-brown/1", "parameters": params, "sigma": sigma,
        "stats": {"n_images": n_images, "n_targets": 40, "n_observations": 300 + n_images,
                  "n_rejected": 2, "rmse_px": 0.21, "max_px": 0.9, "mean_abs_u_px": 0.15,
                  "mean_abs_v_px": 0.14, "sigma0": 1.02, "iterations": 8, "solver": "lmqn",
                  "targets_adjusted": True,
                  "fixed_parameters": {"k3": "correlation 0.998 with k2"}},
        "images": images,
        "inputs": {"fingerprint": fingerprint({"camera_id": camera_id, "session_id": session_id,
                                               "seed": seed, "f_mm": f_mm,
                                               "n_images": n_images})},
    }


def goniometer_document(camera_id="cam-g", session_id="lab-1", *, seed=0,
                        acquired="2026-03-01"):
    rng = np.random.default_rng(seed)
    params = dict.fromkeys(PARAM_NAMES, 0.0)
    params.update(f_mm=80.02, xp_mm=0.003, yp_mm=0.001, k0=1.0e-4, k1=-1.0e-5, b1=2.0e-5)
    sigma = dict.fromkeys(PARAM_NAMES)
    sigma.update({n: 1e-5 for n in GONIOMETER_PARAMS})
    frames = [{"file": f"images/F{i:03d}.tif", "axis": "xy"[i % 2],
               "angle_deg": float(a), "u_px": float(u), "v_px": float(v)}
              for i, (a, u, v) in enumerate(zip(np.linspace(-10, 10, 6), rng.uniform(0, 800, 6),
                                                rng.uniform(0, 600, 6), strict=True))]
    return {
        "schema": "fieldcal.calibration/1", "camera_id": camera_id, "session_id": session_id,
        "method": "goniometer", "created": "2026-03-02T08:00:00+00:00", "acquired": acquired,
        "sensor": {"width_px": 820, "height_px": 628, "pixel_size_um": 6.4},
        "model": "fieldcal-brown/1", "parameters": params, "sigma": sigma,
        "stats": {"n_frames": 6, "n_angles": 6, "fx_mm": 80.02, "fy_mm": 80.03, "px_mm": 0.003,
                  "py_mm": 0.001, "sigma_axes": {"fx_mm": 0.001, "fy_mm": 0.001, "px_mm": None,
                                                 "py_mm": 0.0002},
                  "sigma_fit_px": 0.05, "fixed_parameters": {"a1": "method", "a2": "method"}},
        "images": frames,
        "inputs": {"fingerprint": fingerprint({"camera_id": camera_id, "seed": seed})},
    }


def residual_table(n=20, *, seed=0, n_rejected=2):
    """Field residuals: n rows over 3 images, the first n_rejected rows rejected."""
    rng = np.random.default_rng(seed)
    used = np.arange(n) >= n_rejected
    du, dv = rng.normal(0.0, 0.2, n), rng.normal(0.0, 0.2, n)
    return pa.table({
        "image": [f"images/IMG_{i % 3:04d}.tif" for i in range(n)],
        "target_id": [f"T{i}" for i in range(n)],
        "u_px": rng.uniform(0, 820, n), "v_px": rng.uniform(0, 628, n),
        "du_px": du, "dv_px": dv, "sigma_px": np.full(n, 0.1), "used": used,
        "reason": [None if u else "blunder w=6.1" for u in used],
        "normalized_residual": np.hypot(du, dv) / 0.1,
    })


def lake_files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


# --------------------------------------------------------------------------------------
# version ids
# --------------------------------------------------------------------------------------
def test_version_ids_encode_time_and_fingerprint_and_sort_by_time():
    fp = fingerprint({"a": 1})
    t1 = dt.datetime(2026, 11, 22, 10, 0, 0, tzinfo=dt.UTC)
    t2 = t1 + dt.timedelta(seconds=1)
    v1, v2 = new_version(fp, t1), new_version(fp, t2)
    assert VERSION_RE.match(v1) and v1.startswith("20261122T100000Z-" + fp[7:15] + "-")
    assert sorted([v2, v1]) == [v1, v2]
    assert version_time(v2) == t2
    with pytest.raises(InputError, match="not a version id"):
        version_time("2026-11-22")


def test_forced_commits_in_the_same_second_get_distinct_versions(tmp_path):
    lake = Lake(tmp_path)
    doc = field_document()
    versions = [lake.commit(doc, {}, residual_table(), force=True) for _ in range(6)]
    assert len(set(versions)) == 6 and all(v.new for v in versions)
    assert sorted(lake.catalog()["version"].to_pylist()) == sorted(versions)


# --------------------------------------------------------------------------------------
# round trip of every part
# --------------------------------------------------------------------------------------
def test_field_commit_round_trip(tmp_path):
    lake = Lake(tmp_path)
    doc = field_document()
    cov = np.diag(np.arange(1.0, 11.0)) * 1e-6
    corr = np.eye(10)
    res = residual_table()
    version = lake.commit(doc, {"covariance": cov, "correlation": corr,
                                "extra/weights": np.arange(5)},
                          res, array_attrs={"covariance": {"names": list(FIELD_PARAMS)},
                                            "correlation": {"names": list(FIELD_PARAMS)}})
    assert version.new and VERSION_RE.match(version)

    # the document: what was given, plus version, code version
    stored = lake.load_document(version)
    assert stored["version"] == version and stored["code_version"] == code_version()
    for key in ("parameters", "sigma", "stats", "images", "inputs", "created", "acquired"):
        assert stored[key] == doc[key]

    # the catalog row
    cat = lake.catalog()
    assert cat.num_rows == 1
    row = cat.to_pylist()[0]
    assert row["version"] == version and row["camera_id"] == "cam-a" and row["method"] == "field"
    assert row["f_mm"] == 50.0 and row["k1"] == -2.5e-5 and row["sigma_k3"] is None
    assert row["sigma_f_mm"] == doc["sigma"]["f_mm"]
    assert row["acquired"] == dt.datetime(2026, 11, 20, 9, 30, tzinfo=dt.UTC)
    assert row["created"] == dt.datetime(2026, 11, 22, 10, 0, tzinfo=dt.UTC)
    assert row["fixed_parameters"] == ["k3"] and row["forced"] is False
    assert (row["n_images"], row["n_observations"], row["n_rejected"]) == (3, 303, 2)
    assert row["rmse_px"] == 0.21 and row["sigma0"] == 1.02 and row["sigma_fit_px"] is None
    assert row["fingerprint"] == doc["inputs"]["fingerprint"]
    assert row["code_version"].startswith(fieldcal.__version__)
    assert row["residuals_path"] == (f"residuals/camera_id=cam-a/session_id=s1/version={version}"
                                     "/residuals.parquet")

    # the residuals: given columns exact, missing nullable goniometer columns null
    back = lake.read_residuals(version)
    for name in res.column_names:
        assert back[name].to_pylist() == res[name].to_pylist()
    assert back["axis"].null_count == res.num_rows and back["angle_deg"].null_count == res.num_rows

    # the arrays
    g = lake.open_zarr(version)
    assert g.attrs["document"] == stored
    assert list(g["parameters"].attrs["names"]) == list(PARAM_NAMES)
    np.testing.assert_array_equal(g["parameters"][:], [doc["parameters"][n] for n in PARAM_NAMES])
    sig = g["sigma"][:]
    assert np.isnan(sig[PARAM_NAMES.index("k3")]) and sig[0] == doc["sigma"]["f_mm"]
    np.testing.assert_array_equal(g["covariance"][:], cov)
    assert list(g["covariance"].attrs["names"]) == list(FIELD_PARAMS)
    np.testing.assert_array_equal(g["extra/weights"][:], np.arange(5))
    np.testing.assert_array_equal(g["exterior/center_m"][:],
                                  [im["center_m"] for im in doc["images"]])
    np.testing.assert_array_equal(g["exterior/rotation_world_to_camera"][:],
                                  [im["rotation_world_to_camera"] for im in doc["images"]])
    sigma_c = g["exterior/sigma_center_m"][:]
    assert np.isnan(sigma_c[0, 2]) and sigma_c[1, 2] == 0.006
    assert list(g["exterior/center_m"].attrs["images"]) == [im["file"] for im in doc["images"]]


def test_correction_field_follows_the_contract_formula(tmp_path):
    """The derived correction field against CONTRACT section 2 written out independently."""
    lake = Lake(tmp_path)
    doc = field_document()
    g = lake.open_zarr(lake.commit(doc, {}, residual_table()))
    field, gu, gv = g["correction_field"][:], g["grid_u_px"][:], g["grid_v_px"][:]
    assert field.shape == (gv.size, gu.size, 2) and gu[0] == 0 and gu[-1] == 819 and gv[-1] == 627
    p = doc["parameters"]
    d = 5.3e-3
    uu, vv = np.meshgrid(gu, gv)
    xb = (uu - 409.5) * d - p["xp_mm"]
    yb = -(vv - 313.5) * d - p["yp_mm"]
    r2 = xb**2 + yb**2
    radial = p["k0"] + p["k1"] * r2 + p["k2"] * r2**2 + p["k3"] * r2**3
    dx = (xb * radial + p["p1"] * (r2 + 2 * xb**2) + 2 * p["p2"] * xb * yb
          + p["b1"] * xb + p["b2"] * yb)
    dy = (yb * radial + p["p2"] * (r2 + 2 * yb**2) + 2 * p["p1"] * xb * yb
          + p["a1"] * xb + p["a2"] * yb)
    # 1e-9 px: the same arithmetic in a different order, far below any measurement
    np.testing.assert_allclose(field[..., 0], dx / d, rtol=0, atol=1e-9)
    np.testing.assert_allclose(field[..., 1], -dy / d, rtol=0, atol=1e-9)
    assert np.abs(field).max() > 0.05  # not trivially zero: 8 orders above the tolerance


def test_goniometer_commit_round_trip(tmp_path):
    lake = Lake(tmp_path)
    doc = goniometer_document()
    # per-angle rows averaging several frames: no single image, no target
    res = {"image": [None] * 6, "u_px": [f["u_px"] for f in doc["images"]],
           "v_px": [f["v_px"] for f in doc["images"]], "du_px": [0.01] * 6, "dv_px": [-0.02] * 6,
           "sigma_px": [0.05] * 6, "used": [True] * 6, "reason": [None] * 6,
           "axis": [f["axis"] for f in doc["images"]],
           "angle_deg": [f["angle_deg"] for f in doc["images"]]}
    version = lake.commit(doc, {}, res)
    row = lake.catalog().to_pylist()[0]
    assert row["method"] == "goniometer" and row["n_frames"] == 6 and row["sigma_fit_px"] == 0.05
    assert row["rmse_px"] is None and row["n_images"] == 6
    assert row["fixed_parameters"] == ["a1", "a2"]
    assert row["acquired"] == dt.datetime(2026, 3, 1, tzinfo=dt.UTC)
    g = lake.open_zarr(version)
    assert "exterior" not in list(g.group_keys())
    back = lake.read_residuals(version)
    assert back["axis"].to_pylist() == res["axis"] and back["image"].null_count == 6
    assert lake.load_document(version)["stats"]["sigma_axes"]["px_mm"] is None


def test_outputs_open_with_plain_pyarrow_duckdb_and_zarr(tmp_path):
    lake = Lake(tmp_path)
    v1 = lake.commit(field_document("cam-a", "s1"), {}, residual_table(20))
    v2 = lake.commit(field_document("cam-b", "s7"), {}, residual_table(30, seed=1))

    catalog = pq.read_table(tmp_path / "catalog")
    assert sorted(catalog["version"].to_pylist()) == sorted([v1, v2])

    part = ds.partitioning(pa.schema([("camera_id", pa.string()), ("session_id", pa.string()),
                                      ("version", pa.string())]), flavor="hive")
    res = ds.dataset(tmp_path / "residuals", format="parquet", partitioning=part).to_table()
    assert res.num_rows == 50
    assert sorted(set(res["version"].to_pylist())) == sorted([v1, v2])

    counts = duckdb.sql(
        "SELECT camera_id, session_id, count(*) AS n, sum(CASE WHEN used THEN 0 ELSE 1 END) "
        f"FROM read_parquet('{tmp_path}/residuals/*/*/*/*.parquet', hive_partitioning = true) "
        "GROUP BY ALL ORDER BY camera_id").fetchall()
    assert counts == [("cam-a", "s1", 20, 2), ("cam-b", "s7", 30, 2)]
    f_mm = duckdb.sql(f"SELECT f_mm FROM read_parquet('{tmp_path}/catalog/*.parquet')").fetchall()
    assert f_mm == [(50.0,), (50.0,)]

    group = zarr.open_group(str(tmp_path / "calibrations" / "cam-b" / "s7" / f"{v2}.zarr"),
                            mode="r")
    assert group.attrs["document"]["version"] == v2
    assert group["exterior/center_m"].shape == (3, 3)
    doc = json.loads((tmp_path / "calibrations" / "cam-b" / "s7" / f"{v2}.json").read_text())
    assert doc["version"] == v2 and doc["session_id"] == "s7"


# --------------------------------------------------------------------------------------
# validation before writing
# --------------------------------------------------------------------------------------
def _drop(doc, *path):
    d = doc
    for key in path[:-1]:
        d = d[key]
    del d[path[-1]]
    return doc


@pytest.mark.parametrize("mutate, match", [
    (lambda d: _drop(d, "stats", "rmse_px"), "'rmse_px' is a required property"),
    (lambda d: _drop(d, "sigma", "b2"), "'b2' is a required property"),
    (lambda d: d["images"][0].update(center_m=[1.0, 2.0]), r"images/0/center_m"),
    (lambda d: d["parameters"].update(f_mm=float("nan")), "NaN and infinity"),
    (lambda d: d.update(method="tripod"), "method"),
    (lambda d: d.update(camera_id="cam/a"), "camera_id"),
    (lambda d: d["inputs"].update(fingerprint="md5:abc"), "fingerprint"),
    (lambda d: d.update(acquired="last tuesday"), "not an ISO 8601 date or time"),
    (lambda d: d.update(version="v1"), "version must look like"),
])
def test_bad_documents_are_refused_before_anything_is_written(tmp_path, mutate, match):
    doc = field_document()
    mutate(doc)
    with pytest.raises(InputError, match=match):
        Lake(tmp_path / "lake").commit(doc, {}, residual_table())
    assert not (tmp_path / "lake").exists()


@pytest.mark.parametrize("make, match", [
    (lambda t: t.drop_columns(["sigma_px"]), "column 'sigma_px' is missing"),
    (lambda t: t.set_column(8, "reason", pa.nulls(t.num_rows, pa.string())),
     "reason must be null exactly when used is true"),
    (lambda t: t.set_column(2, "u_px", pa.array(["a"] * t.num_rows)), "u_px"),
    (lambda t: t.append_column("version", pa.array(["x"] * t.num_rows)), "partition keys"),
    (lambda t: None, "a residual table is required"),
])
def test_bad_residual_tables_are_refused(tmp_path, make, match):
    with pytest.raises(InputError, match=match):
        Lake(tmp_path).commit(field_document(), {}, make(residual_table()))
    assert lake_files(tmp_path) == []


def test_bad_arrays_are_refused(tmp_path):
    lake = Lake(tmp_path)
    with pytest.raises(InputError, match="needs attrs 'names' with 10 entries"):
        lake.commit(field_document(), {"covariance": np.eye(10)}, residual_table())
    with pytest.raises(InputError, match=r"exterior/center_m.*shape \(3, 3\)"):
        lake.commit(field_document(), {"exterior/center_m": np.zeros((2, 3))}, residual_table())
    with pytest.raises(InputError, match="must be numeric"):
        lake.commit(field_document(), {"notes": np.array(["a"], dtype=object)}, residual_table())
    assert lake_files(tmp_path) == []


# --------------------------------------------------------------------------------------
# versions: immutable, recognised, forced
# --------------------------------------------------------------------------------------
def test_committed_version_is_immutable(tmp_path):
    lake = Lake(tmp_path)
    doc = field_document()
    version = lake.commit(doc, {}, residual_table())
    before = {p: (tmp_path / p).read_bytes() for p in lake_files(tmp_path)
              if not p.startswith("_claims")}
    again = field_document(f_mm=51.0)
    again["version"] = str(version)
    with pytest.raises(LakeError, match="already committed.*immutable"):
        lake.commit(again, {}, residual_table(), force=True)
    after = {p: (tmp_path / p).read_bytes() for p in lake_files(tmp_path)
             if not p.startswith("_claims")}
    assert after == before
    assert lake.load_document(version)["parameters"]["f_mm"] == 50.0


def test_same_fingerprint_is_recognised_and_force_makes_a_new_version(tmp_path):
    lake = Lake(tmp_path)
    doc = field_document()
    fp = doc["inputs"]["fingerprint"]
    assert lake.find_committed(fp) is None
    v1 = lake.commit(doc, {}, residual_table())
    assert v1.new and lake.find_committed(fp) == v1
    v_same = lake.commit(doc, {}, residual_table())
    assert v_same == v1 and not v_same.new
    assert lake.catalog().num_rows == 1
    v2 = lake.commit(doc, {}, residual_table(), force=True)
    assert v2.new and v2 != v1 and lake.find_committed(fp) == v2
    assert lake.catalog()["forced"].to_pylist() == [False, True]
    other = field_document(seed=1)
    assert lake.find_committed(other["inputs"]["fingerprint"]) is None


def test_latest_and_sessions(tmp_path):
    lake = Lake(tmp_path)
    assert lake.latest("cam-a") is None and lake.sessions_with_calibration() == []
    va1 = lake.commit(field_document("cam-a", "s1"), {}, residual_table())
    va2 = lake.commit(field_document("cam-a", "s2"), {}, residual_table())
    vb1 = lake.commit(field_document("cam-b", "s1"), {}, residual_table())
    assert lake.latest("cam-a") == va2 and lake.latest("cam-a", "s1") == va1
    assert lake.latest("cam-b") == vb1 and lake.latest("cam-c") is None
    assert lake.sessions_with_calibration() == [("cam-a", "s1"), ("cam-a", "s2"), ("cam-b", "s1")]
    with pytest.raises(LakeError, match="is not committed"):
        lake.load_document(new_version(fingerprint({})))


# --------------------------------------------------------------------------------------
# failures and crashes
# --------------------------------------------------------------------------------------
def _crashing_commit(root, storage_options=None):
    """Child process: write every part of a version, then die before the catalog row."""
    def crash(self, rel, data):
        os._exit(17)

    Lake._write_catalog_row = crash
    Lake(root, storage_options).commit(field_document(), {}, residual_table())


def test_crash_before_the_catalog_row_leaves_no_visible_version(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    child = ctx.Process(target=_crashing_commit, args=(str(tmp_path),))
    child.start()
    child.join(120)
    assert child.exitcode == 17
    lake = Lake(tmp_path)
    leftovers = [p for p in lake_files(tmp_path) if p.startswith(("calibrations", "residuals"))]
    assert any(p.endswith(".json") for p in leftovers) and any(".zarr/" in p for p in leftovers)
    assert lake.catalog().num_rows == 0 and lake.latest("cam-a") is None
    doc = field_document()
    assert lake.find_committed(doc["inputs"]["fingerprint"]) is None

    # a re-commit takes over the dead process's claim and completes
    version = lake.commit(doc, {}, residual_table())
    assert version.new and lake.catalog()["version"].to_pylist() == [version]
    claims = sorted((tmp_path / "_claims" / "fingerprint").rglob("*.json"))
    assert [c.name for c in claims] == ["000000.json", "000001.json"]

    # gc removes the crashed version's parts, nothing of the committed one
    (crashed,) = {re.search(r"\d{8}T\d{6}Z-[0-9a-f]{8}-[0-9a-f]{4}", p).group(0)
                  for p in leftovers}
    assert crashed != version
    assert lake.gc(grace_s=3600.0) == [f"_claims/version/{version}"]  # the crash is too young
    assert sorted(lake.gc(grace_s=0.0)) == sorted([
        f"calibrations/cam-a/s1/{crashed}.json", f"calibrations/cam-a/s1/{crashed}.zarr",
        f"residuals/camera_id=cam-a/session_id=s1/version={crashed}",
        f"_claims/version/{crashed}"])
    assert not any(crashed in p for p in lake_files(tmp_path))
    assert lake.load_document(version)["version"] == version
    assert lake.open_zarr(version)["parameters"].shape == (13,)


def test_failed_catalog_write_releases_the_claim_and_cleans_up(tmp_path, monkeypatch):
    lake = Lake(tmp_path)

    def fail(self, rel, data):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Lake, "_write_catalog_row", fail)
    with pytest.raises(LakeError, match="cannot commit to .*Permission denied") as info:
        lake.commit(field_document(), {}, residual_table())
    assert "\n" not in str(info.value)
    assert lake.catalog().num_rows == 0
    assert not [p for p in lake_files(tmp_path) if p.startswith(("calibrations", "residuals"))]
    claim = json.loads(next((tmp_path / "_claims" / "fingerprint").rglob("*.json")).read_text())
    assert claim["released"] is True
    monkeypatch.undo()
    version = lake.commit(field_document(), {}, residual_table())
    assert version.new and lake.catalog().num_rows == 1


def test_destination_that_cannot_be_written_fails_cleanly(tmp_path):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("x")
    lake = Lake(blocker / "lake")
    with pytest.raises(LakeError, match="cannot commit to .*not-a-dir/lake: Not a directory") \
            as info:
        lake.commit(field_document(), {}, residual_table())
    assert "\n" not in str(info.value)
    assert lake.catalog().num_rows == 0
    with pytest.raises(LakeError, match="cannot write"):
        lake.write_observations("cam-a", "s1", "images/a.tif", "0" * 64, pa.table({"u": [1.0]}))


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0,
                    reason="root ignores directory permissions")
def test_read_only_directory_fails_cleanly(tmp_path):
    root = tmp_path / "lake"
    root.mkdir()
    root.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        with pytest.raises(LakeError, match="Permission denied"):
            Lake(root).commit(field_document(), {}, residual_table())
        assert Lake(root).catalog().num_rows == 0
    finally:
        root.chmod(stat.S_IRWXU)


# --------------------------------------------------------------------------------------
# concurrency: several processes, one lake
# --------------------------------------------------------------------------------------
def _commit_worker(root, camera_id, sessions, seed, barrier, queue):
    lake = Lake(root, poll_s=0.05)
    barrier.wait(600)  # start together (spawned children import slowly on a loaded machine)
    out = []
    for session_id in sessions:
        v = lake.commit(field_document(camera_id, session_id, seed=seed), {},
                        residual_table(seed=seed))
        out.append((str(v), v.new))
    queue.put((camera_id, out))


def _run_workers(root, jobs):
    """Run ``_commit_worker`` per job in spawned processes; a failed child fails the test."""
    ctx = multiprocessing.get_context("spawn")
    barrier, results = ctx.Barrier(len(jobs)), ctx.Queue()
    procs = [ctx.Process(target=_commit_worker, args=(str(root), cam, sessions, seed, barrier,
                                                      results))
             for cam, sessions, seed in jobs]
    for p in procs:
        p.start()
    out = []
    try:
        while len(out) < len(procs):
            try:
                out.append(results.get(timeout=1.0))
            except queue.Empty:
                failed = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
                assert not failed, f"commit worker(s) failed with exit code(s) {failed}"
        for p in procs:
            p.join(60)
            assert p.exitcode == 0
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
                p.join(10)
    return out


def test_concurrent_commits_of_different_sessions_lose_no_row(tmp_path):
    jobs = [(f"cam-{i}", ["s1", "s2", "s3"], i) for i in range(3)]
    results = _run_workers(tmp_path, jobs)
    made = sorted(v for _, out in results for v, new in out if new)
    assert len(made) == 9
    cat = Lake(tmp_path).catalog()
    assert sorted(cat["version"].to_pylist()) == made
    pairs = zip(cat["camera_id"].to_pylist(), cat["session_id"].to_pylist(), strict=True)
    assert sorted(pairs) == [(f"cam-{i}", f"s{j}") for i in range(3) for j in (1, 2, 3)]


def test_concurrent_commits_of_the_same_inputs_make_one_version(tmp_path):
    jobs = [("cam-a", ["s1"], 0)] * 4
    results = _run_workers(tmp_path, jobs)
    outs = [out[0] for _, out in results]
    versions = {v for v, _ in outs}
    assert len(versions) == 1, outs
    assert sum(new for _, new in outs) == 1
    cat = Lake(tmp_path).catalog()
    assert cat["version"].to_pylist() == list(versions)
    claims = list((tmp_path / "_claims" / "fingerprint").rglob("*.json"))
    assert [c.name for c in claims] == ["000000.json"]


# --------------------------------------------------------------------------------------
# observations cache
# --------------------------------------------------------------------------------------
def test_observations_cache_round_trip_and_rerun_reads_no_image(tmp_path):
    lake = Lake(tmp_path)
    images = {}
    for i in range(3):
        p = tmp_path / "session" / "images" / f"IMG_{i}.tif"
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(bytes([i]) * 1000)
        images[f"images/IMG_{i}.tif"] = p
    measured = []

    def measure(path):  # stands in for reading and measuring the image
        measured.append(path)
        return pa.table({"u_px": [1.0 * len(measured)], "v_px": [2.0]})

    def run():
        tables = {}
        for name, path in images.items():
            sha = sha256_file(path)
            cached = lake.read_observations("cam-a", "s1", name, sha)
            if cached is None:
                cached = measure(path)
                lake.write_observations("cam-a", "s1", name, sha, cached)
            tables[name] = cached
        return tables

    first = run()
    assert len(measured) == 3
    second = run()
    assert len(measured) == 3  # nothing measured again
    assert {k: t["u_px"].to_pylist() for k, t in second.items()} == \
        {k: t["u_px"].to_pylist() for k, t in first.items()}
    images["images/IMG_1.tif"].write_bytes(b"changed")
    run()
    assert measured[-1] == images["images/IMG_1.tif"] and len(measured) == 4
    assert lake.sessions_with_observations() == [("cam-a", "s1")]
    files = sorted(p.name for p in (tmp_path / "observations" / "camera_id=cam-a" /
                                    "session_id=s1").iterdir())
    assert len(files) == 4 and files[0].startswith("images_IMG_0.tif-")
    assert lake.has_observations("cam-a", "s1", "images/IMG_0.tif",
                                 sha256_file(images["images/IMG_0.tif"]))
    assert not lake.has_observations("cam-a", "s1", "images/IMG_0.tif", "f" * 64)


def test_observations_key_and_bad_arguments(tmp_path):
    sha = hashlib.sha256(b"x").hexdigest()
    assert observations_key("images/a b.tif", sha) == f"images_a_b.tif-{sha}"
    with pytest.raises(InputError, match="64 lower-case hex"):
        observations_key("images/a.tif", "sha256:" + sha)
    lake = Lake(tmp_path)
    with pytest.raises(InputError, match="partition keys"):
        lake.write_observations("cam-a", "s1", "a.tif", sha, pa.table({"camera_id": ["x"]}))
    with pytest.raises(InputError, match="camera_id must match"):
        lake.has_observations("../etc", "s1", "a.tif", sha)


# --------------------------------------------------------------------------------------
# fingerprints
# --------------------------------------------------------------------------------------
def test_sha256_file_streams_large_files_exactly(tmp_path):
    data = np.random.default_rng(3).integers(0, 256, 3 * 2**20 + 17, dtype=np.uint8).tobytes()
    p = tmp_path / "big.bin"
    p.write_bytes(data)
    assert sha256_file(p) == hashlib.sha256(data).hexdigest()
    with pytest.raises(InputError, match="file not found"):
        sha256_file(tmp_path / "missing.tif")


def test_fingerprint_is_canonical_and_sensitive():
    table_bytes = b"id,X,Y,Z\n1,0,0,0\n"
    a = {"images": {"b.tif": "11" * 32, "a.tif": "22" * 32}, "targets": table_bytes,
         "settings": {"sigma_px": 0.1, "estimate": ["f_mm", "k1"]}, "grid": np.arange(4.0)}
    b = {"settings": {"estimate": ["f_mm", "k1"], "sigma_px": 0.1}, "grid": np.arange(4.0),
         "targets": "sha256:" + hashlib.sha256(table_bytes).hexdigest(),
         "images": {"a.tif": "22" * 32, "b.tif": "11" * 32}}
    assert fingerprint(a) == fingerprint(b) and is_fingerprint(fingerprint(a))
    assert fingerprint(a) != fingerprint({**a, "settings": {"sigma_px": 0.2,
                                                            "estimate": ["f_mm", "k1"]}})
    assert fingerprint(a) != fingerprint({**a, "grid": np.arange(4.0, dtype=np.float32)})
    t1 = pa.table({"x": [1, 2, 3]})
    t2 = pa.concat_tables([pa.table({"x": [1]}), pa.table({"x": [2, 3]})])
    assert fingerprint({"t": t1}) == fingerprint({"t": t2})  # chunking does not matter
    assert canonical_json({"b": 1, "a": [1.5, None]}) == b'{"a":[1.5,null],"b":1}'
    with pytest.raises(InputError, match="non-finite"):
        fingerprint({"x": float("nan")})
    with pytest.raises(InputError, match="sha256_file"):
        fingerprint({"targets": Path("targets.csv")})


def test_code_version_names_the_package_version():
    v = code_version()
    assert v == fieldcal.__version__ or re.fullmatch(re.escape(fieldcal.__version__)
                                                     + r"\+g[0-9a-f]{12}", v)
