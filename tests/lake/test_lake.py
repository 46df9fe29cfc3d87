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
import pyarrow.parquet as pq
import pytest
import zarr

import fieldcal
from fieldcal.analysis.correction import correction_arrays
from fieldcal.contract.fingerprint import (
    canonical_json,
    code_version,
    fingerprint,
    is_fingerprint,
    sha256_file,
)
from fieldcal.errors import InputError, LakeError
from fieldcal.lake import history
from fieldcal.lake.store import Lake, new_version, observations_key, version_time
from fieldcal.lake.tables import Tables
from fieldcal.model.camera import FIELD_PARAMS, GONIOMETER_PARAMS, PARAM_NAMES
from fieldcal.model.rotations import R_world_to_camera_from_opk

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


def field_measurements(image="images/IMG_0000.tif", n=3, *, seed=0):
    """A field image's measured targets (schemas/measurements.arrow.json), n rows."""
    from fieldcal.contract.schemas import arrow_schema

    rng = np.random.default_rng(seed)
    rows = [{"image": image, "blob": i, "kind": "disc", "code": None,
             "u_px": float(rng.uniform(0, 820)), "v_px": float(rng.uniform(0, 628)),
             "sigma_px": 0.05, "diameter_px": 12.0, "major_px": 12.5, "minor_px": 11.5,
             "angle_deg": 30.0, "roundness": 0.92, "edge_rms_px": 0.1, "contrast": 90.0,
             "snr": 40.0, "saturated": False, "truncated": False, "method": "ellipse",
             "corners_px": None} for i in range(n)]
    return pa.Table.from_pylist(rows, schema=arrow_schema("measurements"))


def spot_measurement(file="images/F000.tif", u_px=400.0):
    """A goniometer frame's spot (fieldcal.contract.goniometer_schema.MEASUREMENT_SCHEMA), one row."""
    from fieldcal.goniometer.method import measurements_table

    return measurements_table([{"file": file, "u_px": u_px, "v_px": 300.0, "peak_dn": 900.0,
                                "flag": "ok", "reason": ""}])


def same_rows(a: pa.Table, b: pa.Table) -> bool:
    """Equal column names, types and values (NaN equal to NaN; metadata ignored)."""
    def plain(t):
        return [{k: ("nan" if isinstance(v, float) and v != v else v) for k, v in r.items()}
                for r in t.to_pylist()]
    return a.schema.equals(b.schema, check_metadata=False) and plain(a) == plain(b)


def lake_files(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if p.is_file())


def version_files(root: Path) -> list[str]:
    """The documents and Zarr groups of the lake (one entry per version part)."""
    base = root / "calibrations"
    return sorted(str(p.relative_to(root)) for p in base.glob("*/*/*")) if base.exists() else []


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
    assert row["residuals_path"] == "residuals"  # the Delta table, rows of this version

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


def test_the_lake_stores_the_correction_field_it_is_given_and_computes_none(tmp_path):
    """Issue 25, goal 1: the lake stores what it is given; the grid comes from the solve step."""
    lake = Lake(tmp_path)
    g = lake.open_zarr(lake.commit(field_document(), {}, residual_table()))
    assert not {"correction_field", "grid_u_px", "grid_v_px"} & set(g.array_keys())
    doc = field_document(seed=3)
    given = correction_arrays(doc)
    g = lake.open_zarr(lake.commit(doc, given, residual_table()))
    for name, arr in given.items():
        np.testing.assert_array_equal(g[name][:], arr)


def test_correction_field_follows_the_contract_formula(tmp_path):
    """The correction field the solve step hands in (analysis.correction), as stored, against
    CONTRACT section 2 written out independently."""
    lake = Lake(tmp_path)
    doc = field_document()
    g = lake.open_zarr(lake.commit(doc, correction_arrays(doc), residual_table()))
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


def test_outputs_open_with_plain_deltalake_pyarrow_duckdb_and_zarr(tmp_path):
    from deltalake import DeltaTable

    lake = Lake(tmp_path)
    v1 = lake.commit(field_document("cam-a", "s1"), {}, residual_table(20))
    v2 = lake.commit(field_document("cam-b", "s7"), {}, residual_table(30, seed=1))

    catalog = DeltaTable(str(tmp_path / "catalog")).to_pyarrow_table()
    assert sorted(catalog["version"].to_pylist()) == sorted([v1, v2])
    res = DeltaTable(str(tmp_path / "residuals")).to_pyarrow_table()
    assert res.num_rows == 50 and sorted(set(res["version"].to_pylist())) == sorted([v1, v2])
    assert DeltaTable(str(tmp_path / "residuals")).metadata().partition_columns == ["camera_id"]

    con = duckdb.connect()
    con.register("residuals", res)
    counts = con.sql("SELECT camera_id, session_id, count(*) AS n, "
                     "sum(CASE WHEN used THEN 0 ELSE 1 END) FROM residuals "
                     "GROUP BY ALL ORDER BY camera_id").fetchall()
    assert counts == [("cam-a", "s1", 20, 2), ("cam-b", "s7", 30, 2)]
    # each data file is plain Parquet too
    files = DeltaTable(str(tmp_path / "catalog")).file_uris()
    assert sum(pq.read_table(f).num_rows for f in files) == 2

    group = zarr.open_group(str(tmp_path / "calibrations" / "cam-b" / "s7" / f"{v2}.zarr"),
                            mode="r")
    assert group.attrs["document"]["version"] == v2
    assert group["exterior/center_m"].shape == (3, 3)
    doc = json.loads((tmp_path / "calibrations" / "cam-b" / "s7" / f"{v2}.json").read_text())
    assert doc["version"] == v2 and doc["session_id"] == "s7"
    # the data dictionary names every table and column
    readme = (tmp_path / "README.md").read_text()
    for name in ("catalog", "residuals", "observations_field", "observations_goniometer"):
        assert f"### {name}" in readme
    for column in ("sigma_f_mm", "du_px", "normalized_residual", "diameter_px", "peak_dn"):
        assert f"| `{column}` |" in readme
    assert "[mm^-2]" in readme and "Polars" in readme and "Spark" in readme


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
    (lambda t: t.append_column("version", pa.array(["x"] * t.num_rows)), "added by the lake"),
    (lambda t: t.append_column("colour", pa.array(["x"] * t.num_rows)), "not in schemas/residuals"),
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
    before = {p: (tmp_path / p).read_bytes() for p in lake_files(tmp_path)}
    again = field_document(f_mm=51.0)
    again["version"] = str(version)
    with pytest.raises(LakeError, match="already committed.*immutable"):
        lake.commit(again, {}, residual_table(), force=True)
    after = {p: (tmp_path / p).read_bytes() for p in lake_files(tmp_path)}
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
    def crash(self, name, *args, **kwargs):
        if name == "catalog":
            os._exit(17)
        raise AssertionError(f"unexpected insert into {name}")

    Tables.append_once = crash
    Lake(root, storage_options).commit(field_document(), {}, residual_table())


def _residual_versions(lake: Lake) -> list[str]:
    """Versions with rows in the residuals table (visible or not)."""
    return sorted(set(lake.tables.scan("residuals", columns=["version"])["version"].to_pylist()))


def test_crash_before_the_catalog_row_leaves_no_visible_version(tmp_path):
    ctx = multiprocessing.get_context("spawn")
    child = ctx.Process(target=_crashing_commit, args=(str(tmp_path),))
    child.start()
    child.join(120)
    assert child.exitcode == 17
    lake = Lake(tmp_path)
    leftovers = version_files(tmp_path)
    (crashed,) = {re.search(r"\d{8}T\d{6}Z-[0-9a-f]{8}-[0-9a-f]{4}", p).group(0) for p in leftovers}
    assert sorted(Path(p).suffix for p in leftovers) == [".json", ".zarr"]
    assert _residual_versions(lake) == [crashed]           # written, but not visible:
    assert lake.catalog().num_rows == 0 and lake.latest("cam-a") is None
    assert history.sql(lake, "SELECT count(*) AS n FROM residuals")["n"].to_pylist() == [0]
    doc = field_document()
    assert lake.find_committed(doc["inputs"]["fingerprint"]) is None

    # a re-commit completes without waiting for anything of the dead process
    version = lake.commit(doc, {}, residual_table())
    assert version.new and version != crashed and lake.catalog()["version"].to_pylist() == [version]

    # gc removes the crashed version's parts, nothing of the committed one
    assert lake.gc(grace_s=3600.0) == []  # the crash is too young
    assert sorted(lake.gc(grace_s=0.0, dry_run=True)) == sorted(
        [f"calibrations/cam-a/s1/{crashed}.json", f"calibrations/cam-a/s1/{crashed}.zarr",
         f"residuals: version={crashed}"])
    assert _residual_versions(lake) == sorted([crashed, version])  # a dry run removes nothing
    lake.gc(grace_s=0.0)
    assert not any(crashed in p for p in lake_files(tmp_path) if "_delta_log" not in p)
    assert _residual_versions(lake) == [version]
    assert lake.load_document(version)["version"] == version
    assert lake.open_zarr(version)["parameters"].shape == (13,)
    assert lake.read_residuals(version).num_rows == 20


def test_failed_catalog_commit_cleans_up_and_the_next_commit_succeeds(tmp_path, monkeypatch):
    lake = Lake(tmp_path)

    def fail(self, name, *args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(Tables, "append_once", fail)
    with pytest.raises(LakeError, match="cannot commit to .*Permission denied") as info:
        lake.commit(field_document(), {}, residual_table())
    assert "\n" not in str(info.value)
    assert lake.catalog().num_rows == 0
    assert version_files(tmp_path) == [] and _residual_versions(lake) == []
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
    with pytest.raises(LakeError, match="cannot write .*not-a-dir/lake"):
        lake.write_observations("cam-a", "s1", "images/a.tif", "0" * 64, field_measurements())


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
    lake = Lake(root)
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
    lake = Lake(tmp_path)
    cat = lake.catalog()
    assert sorted(cat["version"].to_pylist()) == made
    pairs = zip(cat["camera_id"].to_pylist(), cat["session_id"].to_pylist(), strict=True)
    assert sorted(pairs) == [(f"cam-{i}", f"s{j}") for i in range(3) for j in (1, 2, 3)]
    assert _residual_versions(lake) == made


def test_concurrent_commits_of_the_same_inputs_make_one_version(tmp_path):
    jobs = [("cam-a", ["s1"], 0)] * 5
    results = _run_workers(tmp_path, jobs)
    outs = [out[0] for _, out in results]
    versions = {v for v, _ in outs}
    assert len(versions) == 1, outs
    assert sum(new for _, new in outs) == 1
    (version,) = versions
    lake = Lake(tmp_path)
    assert lake.catalog()["version"].to_pylist() == [version]
    # the losers removed their own parts: only the winner's remain
    assert version_files(tmp_path) == [f"calibrations/cam-a/s1/{version}.json",
                                       f"calibrations/cam-a/s1/{version}.zarr"]
    assert _residual_versions(lake) == [version]


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

    def measure(name):  # stands in for reading and measuring the image
        measured.append(name)
        return field_measurements(name, n=len(measured) % 3, seed=len(measured))

    def run():
        tables = {}
        for name, path in images.items():
            sha = sha256_file(path)
            cached = lake.read_observations("cam-a", "s1", name, sha)
            if cached is None:
                cached = measure(name)
                lake.write_observations("cam-a", "s1", name, sha, cached)
            tables[name] = cached
        return tables

    first = run()
    assert len(measured) == 3 and first["images/IMG_2.tif"].num_rows == 0  # nothing found
    second = run()
    assert len(measured) == 3  # nothing measured again, the empty image neither
    for name, t in first.items():
        assert same_rows(second[name], t), name
    fresh = Lake(tmp_path).read_observations("cam-a", "s1", "images/IMG_0.tif",
                                             sha256_file(images["images/IMG_0.tif"]))
    assert same_rows(fresh, first["images/IMG_0.tif"])
    images["images/IMG_1.tif"].write_bytes(b"changed")
    run()
    assert measured[-1] == "images/IMG_1.tif" and len(measured) == 4
    assert lake.sessions_with_observations() == [("cam-a", "s1")]
    assert len(lake.cached_observations("cam-a", "s1")) == 4
    assert observations_key("images/IMG_0.tif", sha256_file(images["images/IMG_0.tif"])) in \
        lake.cached_observations("cam-a", "s1")
    assert lake.has_observations("cam-a", "s1", "images/IMG_0.tif",
                                 sha256_file(images["images/IMG_0.tif"]))
    assert not lake.has_observations("cam-a", "s1", "images/IMG_0.tif", "f" * 64)
    # a new instance has nothing memoised: the key-only probe answers
    sha0 = sha256_file(images["images/IMG_0.tif"])
    probe = Lake(tmp_path)
    assert probe.has_observations("cam-a", "s1", "images/IMG_0.tif", sha0)
    assert not probe.has_observations("cam-a", "s1", "images/IMG_0.tif", "f" * 64)     # another content
    assert not probe.has_observations("cam-a", "s1", "images/IMG_1.tif", sha0)         # another image
    assert not probe.has_observations("cam-a", "s2", "images/IMG_0.tif", sha0)         # another session
    assert not probe.has_observations("cam-b", "s1", "images/IMG_0.tif", sha0)         # another camera
    assert probe._obs_cache == {}                                                       # no session was read


def test_an_image_cached_twice_reads_back_once_in_row_order(tmp_path):
    """Two runs caching the same image at once leave its rows twice in the table; a session's
    read gives each image's rows once, in row order, beside the other images' (written in
    between and in one batch with them)."""
    lake = Lake(tmp_path)
    a, b, c = (field_measurements(f"images/{n}.tif", n=k, seed=k) for n, k in (("A", 5), ("B", 7), ("C", 0)))
    lake.write_observations("cam-a", "s1", "images/A.tif", "a" * 64, a)
    lake.write_observations_many("cam-a", "s1", [("images/B.tif", "b" * 64, b), ("images/A.tif", "a" * 64, a),
                                                 ("images/C.tif", "c" * 64, c)])
    lake.write_observations("cam-a", "s1", "images/B.tif", "b" * 64, b)
    n = history.sql(lake, "SELECT count(*) AS n FROM observations_field")["n"].to_pylist()
    assert n == [2 * 5 + 2 * 7 + 1]                       # C, with nothing found, is one marker row
    fresh = Lake(tmp_path)
    for name, sha, table in (("images/A.tif", "a", a), ("images/B.tif", "b", b), ("images/C.tif", "c", c)):
        back = fresh.read_observations("cam-a", "s1", name, sha * 64)
        assert back.num_rows == table.num_rows and same_rows(back, table), name


def test_goniometer_spots_have_their_own_table(tmp_path):
    lake = Lake(tmp_path)
    for i in range(3):
        lake.write_observations("cam-g", "lab-1", f"images/F{i:03d}.tif", f"{i:064x}",
                                spot_measurement(f"images/F{i:03d}.tif", u_px=100.0 + i))
    lake.write_observations("cam-a", "s1", "images/IMG_0.tif", "e" * 64, field_measurements())
    back = lake.read_observations("cam-g", "lab-1", "images/F001.tif", f"{1:064x}")
    assert same_rows(back, spot_measurement("images/F001.tif", u_px=101.0))
    assert back.schema.metadata == spot_measurement().schema.metadata  # its documentation
    spots = history.sql(lake, "SELECT image, u_px FROM observations_goniometer ORDER BY image")
    assert spots["u_px"].to_pylist() == [100.0, 101.0, 102.0]
    targets = history.sql(lake, "SELECT count(*) AS n FROM observations_field")
    assert targets["n"].to_pylist() == [3]
    assert lake.sessions_with_observations() == [("cam-a", "s1"), ("cam-g", "lab-1")]


def test_observations_key_and_bad_arguments(tmp_path):
    sha = hashlib.sha256(b"x").hexdigest()
    assert observations_key("images/a b.tif", sha) == f"images_a_b.tif-{sha}"
    with pytest.raises(InputError, match="64 lower-case hex"):
        observations_key("images/a.tif", "sha256:" + sha)
    lake = Lake(tmp_path)
    with pytest.raises(InputError, match="added by the lake"):
        lake.write_observations("cam-a", "s1", "a.tif", sha,
                                field_measurements().append_column("camera_id", pa.array(["x"] * 3)))
    with pytest.raises(InputError, match="columns of schemas/measurements"):
        lake.write_observations("cam-a", "s1", "a.tif", sha, pa.table({"u": [1.0]}))
    with pytest.raises(InputError, match="camera_id must be"):
        lake.has_observations("../etc", "s1", "a.tif", sha)
    assert lake_files(tmp_path) == []


def test_many_images_of_both_kinds_are_one_append_per_table_and_checked_before_any(tmp_path):
    sha = [hashlib.sha256(bytes([i])).hexdigest() for i in range(3)]
    lake = Lake(tmp_path)
    bad = [("a.tif", sha[0], field_measurements()), ("b.tif", sha[1], pa.table({"u": [1.0]}))]
    with pytest.raises(InputError, match="b.tif"):
        lake.write_observations_many("cam-a", "s1", bad)
    assert lake_files(tmp_path) == []                   # the good first item was not written either
    items = [("images/a.tif", sha[0], field_measurements()), ("images/f.tif", sha[1], spot_measurement()),
             ("images/b.tif", sha[2], field_measurements(n=2))]
    kinds = lake.write_observations_many("cam-a", "s1", items)
    assert kinds == ["observations_field", "observations_goniometer", "observations_field"]
    for kind, named in (("observations_field", "2 images"), ("observations_goniometer", "images/f.tif")):
        assert [c["image"] for c in lake.tables.log(kind) if c.get("action") == "observations"] == [named]
    fresh = Lake(tmp_path)
    for name, key, table in items:
        assert fresh.has_observations("cam-a", "s1", name, key)
        assert fresh.read_observations("cam-a", "s1", name, key).num_rows == table.num_rows


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
