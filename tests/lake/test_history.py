"""History queries over a small synthetic lake: one camera over time, the fleet, any SQL."""

import csv
import datetime as dt
import io
import json

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from fieldcal.errors import InputError
from fieldcal.lake import history
from fieldcal.lake.store import Lake, new_version
from fieldcal.session.schemas import arrow_schema
from tests.lake.test_lake import field_document, goniometer_document, residual_table

UTC = dt.UTC

# (camera, session, acquired, f_mm, residual rows); cam-a drifts by +10 um over the year
SESSIONS = [
    ("cam-a", "s1", "2026-01-10T09:30:00Z", 50.000, 10),
    ("cam-a", "s2", "2026-04-10T09:30:00Z", 50.004, 12),
    ("cam-a", "s3", "2026-07-10T09:30:00Z", 50.010, 14),
    ("cam-b", "s1", "2026-02-01", 35.000, 16),
    ("cam-b", "s2", "2026-08-01", 35.002, 18),
]


@pytest.fixture(scope="module")
def lake(tmp_path_factory):
    root = tmp_path_factory.mktemp("history-lake")
    lake = Lake(root)
    for cam, ses, acquired, f_mm, n in SESSIONS:
        lake.commit(field_document(cam, ses, f_mm=f_mm, acquired=acquired), {},
                    residual_table(n, n_rejected=1))
    # cam-a s2 solved again with new settings: a forced, later version of the same session
    lake.commit(field_document("cam-a", "s2", f_mm=50.005, acquired="2026-04-10T09:30:00Z"),
                {}, residual_table(12, n_rejected=3), force=True)
    lake.commit(goniometer_document("cam-g", "lab-1", acquired="2026-03-01"), {},
                {"image": ["images/F000.tif"], "u_px": [1.0], "v_px": [2.0], "du_px": [0.1],
                 "dv_px": [0.0], "sigma_px": [0.05], "used": [True], "reason": [None],
                 "axis": ["x"], "angle_deg": [-10.0]})
    # an uncommitted leftover (a crashed run): must not show in any view
    ghost = new_version(field_document("cam-a", "s9")["inputs"]["fingerprint"])
    path = root / "residuals" / "camera_id=cam-a" / "session_id=s9" / f"version={ghost}"
    path.mkdir(parents=True)
    pq.write_table(residual_table(5), path / "residuals.parquet")
    # cached observations of two images
    for i in range(2):
        lake.write_observations("cam-a", "s1", f"images/IMG_{i}.tif", f"{i:064x}",
                                pa.table({"image": [f"images/IMG_{i}.tif"] * 3,
                                          "target_id": ["T1", "T2", "T3"], "u_px": [1.0, 2, 3],
                                          "v_px": [4.0, 5, 6], "sigma_px": [0.1] * 3}))
    return lake


def test_camera_history_is_ordered_by_acquisition_with_drift(lake):
    t = history.camera_history(lake, "cam-a")
    assert t["session_id"].to_pylist() == ["s1", "s2", "s3"]
    assert t["f_mm"].to_pylist() == [50.000, 50.005, 50.010]  # s2: its latest (forced) version
    # 1e-12 mm: float subtraction of numbers near 50 mm
    assert t["delta_f_mm"].to_pylist() == pytest.approx([0.0, 0.005, 0.010], abs=1e-12)
    assert t["forced"].to_pylist() == [False, True, False]
    assert t["acquired"].to_pylist()[0] == dt.datetime(2026, 1, 10, 9, 30, tzinfo=UTC)
    assert {"sigma_f_mm", "xp_mm", "sigma_yp_mm", "delta_yp_mm", "rmse_px"} <= set(t.column_names)

    every = history.camera_history(lake, "cam-a", ["f_mm", "k1"], all_versions=True)
    assert every["session_id"].to_pylist() == ["s1", "s2", "s2", "s3"]
    assert every["f_mm"].to_pylist() == [50.000, 50.004, 50.005, 50.010]
    assert "delta_k1" in every.column_names and "xp_mm" not in every.column_names

    own = history.camera_history(lake, "cam-a", ["rmse_px", "n_rejected"])
    assert own.column_names.count("rmse_px") == 1 and "delta_rmse_px" in own.column_names
    assert history.camera_history(lake, "cam-zz").num_rows == 0
    with pytest.raises(InputError, match="unknown numeric catalog column 'focal'"):
        history.camera_history(lake, "cam-a", ["focal"])


def test_fleet_takes_the_latest_calibration_per_camera_in_range(lake):
    t = history.fleet(lake)
    assert t.select(["camera_id", "session_id"]).to_pylist() == [
        {"camera_id": "cam-a", "session_id": "s3"}, {"camera_id": "cam-b", "session_id": "s2"},
        {"camera_id": "cam-g", "session_id": "lab-1"}]
    assert t.schema.names == arrow_schema("catalog").names

    h1 = history.fleet(lake, "2026-01-01", "2026-06-30")
    assert dict(zip(h1["camera_id"].to_pylist(), h1["f_mm"].to_pylist(), strict=True)) == \
        {"cam-a": 50.005, "cam-b": 35.000, "cam-g": 80.02}
    # a date as the end includes that whole day (s1 was acquired at 09:30 on the 10th)
    jan = history.fleet(lake, end=dt.date(2026, 1, 10))
    assert jan["session_id"].to_pylist() == ["s1"] and jan["camera_id"].to_pylist() == ["cam-a"]
    assert history.fleet(lake, end="2026-01-10T09:00:00Z").num_rows == 0
    assert history.fleet(lake, start=dt.datetime(2026, 7, 1)).column("camera_id").to_pylist() == \
        ["cam-a", "cam-b"]
    with pytest.raises(InputError, match="before start"):
        history.fleet(lake, "2026-05-01", "2026-04-01")


def test_sql_over_catalog_residuals_and_observations(lake):
    per_camera = history.sql(lake, """
        SELECT camera_id, count(DISTINCT version) AS versions, count(*) AS rows,
               count(*) FILTER (WHERE NOT used) AS rejected
        FROM residuals GROUP BY camera_id ORDER BY camera_id""")
    # cam-a: 10 + 12 + 14 + 12 (forced s2) rows, 1 + 1 + 1 + 3 rejected; the ghost is not seen
    assert per_camera.to_pylist() == [
        {"camera_id": "cam-a", "versions": 4, "rows": 48, "rejected": 6},
        {"camera_id": "cam-b", "versions": 2, "rows": 34, "rejected": 2},
        {"camera_id": "cam-g", "versions": 1, "rows": 1, "rejected": 0}]
    joined = history.sql(lake, """
        SELECT c.session_id, max(r.angle_deg) AS a FROM residuals r JOIN catalog c USING (version)
        WHERE c.method = 'goniometer' GROUP BY ALL""")
    assert joined.to_pylist() == [{"session_id": "lab-1", "a": -10.0}]
    drift = history.sql(lake, "SELECT camera_id FROM catalog GROUP BY camera_id "
                              "HAVING max(f_mm) - min(f_mm) > ? ORDER BY 1", [0.003])
    assert drift["camera_id"].to_pylist() == ["cam-a"]
    obs = history.sql(lake, "SELECT camera_id, session_id, count(*) AS n FROM observations "
                            "GROUP BY ALL")
    assert obs.to_pylist() == [{"camera_id": "cam-a", "session_id": "s1", "n": 6}]
    with pytest.raises(InputError, match="sql: .*nonexistent"):
        history.sql(lake, "SELECT nonexistent FROM catalog")


def test_empty_lake_gives_empty_results_with_columns(tmp_path):
    empty = Lake(tmp_path / "nothing-here")
    cat = history.sql(empty, "SELECT * FROM catalog")
    assert cat.num_rows == 0 and cat.schema.names == arrow_schema("catalog").names
    res = history.sql(empty, "SELECT * FROM residuals")
    assert res.num_rows == 0 and {"camera_id", "version", "du_px", "used"} <= set(res.column_names)
    obs = history.sql(empty, "SELECT * FROM observations")
    assert obs.num_rows == 0 and {"camera_id", "session_id", "u_px"} <= set(obs.column_names)
    assert history.fleet(empty).num_rows == 0
    hist = history.camera_history(empty, "cam-a")
    assert hist.num_rows == 0 and "delta_f_mm" in hist.column_names


def test_formatters_round_trip(lake):
    t = history.camera_history(lake, "cam-a", ["f_mm"])
    rows = list(csv.DictReader(io.StringIO(history.to_csv(t))))
    assert [float(r["f_mm"]) for r in rows] == t["f_mm"].to_pylist()  # full precision
    assert rows[0]["acquired"] == "2026-01-10T09:30:00Z" and rows[1]["forced"] == "true"

    records = json.loads(history.to_json(t))
    assert [r["f_mm"] for r in records] == t["f_mm"].to_pylist()
    assert records[0]["acquired"] == "2026-01-10T09:30:00Z" and records[0]["forced"] is False
    assert records[0]["sigma_fit_px"] is None

    text = history.to_text(t)
    lines = text.splitlines()
    assert len(lines) == t.num_rows + 2 and lines[0].split()[:3] == ["camera_id", "session_id",
                                                                      "version"]
    assert "50.005" in lines[3] and set(lines[1]) <= {"-", " "}
    assert history.format_table(t, "json") == history.to_json(t)
    with pytest.raises(InputError, match="format must be one of text, csv, json"):
        history.format_table(t, "xml")
