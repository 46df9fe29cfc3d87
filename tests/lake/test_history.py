"""History queries over a small synthetic lake: one camera over time, the fleet, any SQL."""

import csv
import datetime as dt
import io
import json

import pyarrow as pa
import pytest

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError
from fieldcal.lake import history
from fieldcal.lake.parts import conform_residuals
from fieldcal.lake.store import Lake, new_version
from tests.lake.test_lake import field_document, field_measurements, goniometer_document, residual_table

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
    # an uncommitted leftover (a crashed run): its residual rows must not show in any view
    ghost = new_version(field_document("cam-a", "s9")["inputs"]["fingerprint"])
    rows = conform_residuals(residual_table(5), "ghost")
    keys = {"camera_id": ["cam-a"] * 5, "session_id": ["s9"] * 5, "version": [ghost] * 5}
    lake.tables.append("residuals", pa.table({**keys, **{c: rows[c] for c in rows.column_names}}))
    # cached observations of two images
    for i in range(2):
        lake.write_observations("cam-a", "s1", f"images/IMG_{i}.tif", f"{i:064x}",
                                field_measurements(f"images/IMG_{i}.tif", n=3, seed=i))
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
    obs = history.sql(lake, "SELECT camera_id, session_id, count(*) AS n FROM observations_field "
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
    obs = history.sql(empty, "SELECT * FROM observations_field")
    assert obs.num_rows == 0 and {"camera_id", "session_id", "u_px"} <= set(obs.column_names)
    spots = history.sql(empty, "SELECT * FROM observations_goniometer")
    assert spots.num_rows == 0 and {"camera_id", "file", "peak_dn"} <= set(spots.column_names)
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


def test_fleet_pairs_take_the_version_before_the_latest_from_one_query(lake):
    t = history.fleet_pairs(lake).to_pylist()
    by_cam = {r["camera_id"]: r for r in t}
    hist_a = history.camera_history(lake, "cam-a")["version"].to_pylist()
    assert by_cam["cam-a"]["version"] == hist_a[-1]
    assert by_cam["cam-a"]["previous_version"] == hist_a[-2]  # s2's latest (the forced one)
    hist_b = history.camera_history(lake, "cam-b")["version"].to_pylist()
    assert (by_cam["cam-b"]["version"], by_cam["cam-b"]["previous_version"]) == (hist_b[1], hist_b[0])
    assert by_cam["cam-g"]["previous_version"] is None  # one calibration only
    assert [r["version"] for r in t] == history.fleet(lake)["version"].to_pylist()


@pytest.mark.parametrize("query", [
    "COPY (SELECT * REPLACE (9.99 AS f_mm) FROM catalog) TO '{lake}/catalog/x.parquet'",
    "SELECT * FROM read_csv('/etc/passwd')",
    "SELECT * FROM read_parquet('{lake}/catalog/*.parquet')",
    "ATTACH '{lake}/evil.db'",
    "INSTALL httpfs",
    "CREATE TABLE t AS SELECT 1",
    "SET enable_external_access = true",
    "SELECT 1; COPY (SELECT 1) TO '{lake}/x.csv'",
])
def test_sql_is_read_only_and_sees_nothing_beyond_the_views(lake, query):
    root = lake.uri("")
    before = sorted(p for p in __import__("pathlib").Path(root).rglob("*"))
    with pytest.raises(InputError, match="read-only"):
        history.sql(lake, query.format(lake=root))
    assert sorted(p for p in __import__("pathlib").Path(root).rglob("*")) == before


def test_as_of_answers_as_the_lake_was_then(tmp_path):
    import time

    lake = Lake(tmp_path)
    v1 = lake.commit(field_document("cam-a", "s1", f_mm=50.0), {}, residual_table(10))
    time.sleep(0.05)  # commit times are milliseconds apart at least
    then = dt.datetime.now(UTC)
    time.sleep(0.05)
    v2 = lake.commit(field_document("cam-a", "s2", f_mm=50.1), {}, residual_table(12))
    assert history.camera_history(lake, "cam-a")["version"].to_pylist() == [v1, v2]
    assert history.camera_history(lake, "cam-a", as_of=then)["version"].to_pylist() == [v1]
    assert history.fleet(lake, as_of=then.isoformat())["version"].to_pylist() == [v1]
    n = history.sql(lake, "SELECT count(*) AS n FROM residuals", as_of=then)
    assert n["n"].to_pylist() == [10]
    assert lake.catalog(as_of=then)["version"].to_pylist() == [v1]
    before_all = then - dt.timedelta(days=1)
    assert history.sql(lake, "SELECT count(*) AS n FROM catalog", as_of=before_all)["n"].to_pylist() == [0]
    with pytest.raises(InputError, match="not an ISO 8601"):
        history.fleet(lake, as_of="yesterday-ish")


def _cli(args, capsys):
    from flows.cli import main

    status = main(args)
    out = capsys.readouterr()
    return status, out.out, out.err


def test_history_fits_a_terminal_by_default_and_shows_more_on_request(lake, capsys):
    url = lake.uri("")
    for extra in ([], ["--camera", "cam-a"], ["--fleet"]):
        status, out, err = _cli(["history", "--lake", url, *extra], capsys)
        assert status == 0 and max(map(len, out.splitlines())) <= 100, (extra, out)
    status, out, _ = _cli(["history", "--lake", url, "--wide"], capsys)
    assert status == 0 and out.splitlines()[0].split() == history.fleet(lake).column_names
    status, out, _ = _cli(["history", "--lake", url, "--columns", "camera_id,sigma0"], capsys)
    assert out.splitlines()[0].split() == ["camera_id", "sigma0"] and len(out.splitlines()) == 2 + 3
    status, out, err = _cli(["history", "--lake", url, "--columns", "camera_id,nope"], capsys)
    assert status == 2 and "no column 'nope'" in err and "sigma0" in err
    status, out, _ = _cli(["history", "--lake", url, "--format", "csv"], capsys)        # scripts: everything
    assert out.splitlines()[0].split(",") == history.fleet(lake).column_names


def test_history_of_a_camera_says_it_shows_the_latest_of_each_session(lake, capsys):
    url = lake.uri("")
    status, out, err = _cli(["history", "--lake", url, "--camera", "cam-a"], capsys)
    assert status == 0 and len(out.splitlines()) == 2 + 3
    assert "latest version of each session (3); 1 earlier version(s)" in err and "--all-versions" in err
    status, out, err = _cli(["history", "--lake", url, "--camera", "cam-a", "--all-versions"], capsys)
    assert len(out.splitlines()) == 2 + 4 and err == ""
    status, out, err = _cli(["history", "--lake", url, "--camera", "cam-b"], capsys)   # nothing hidden
    assert err == ""


def test_every_column_history_shows_is_in_the_data_dictionary(lake):
    from fieldcal.lake.dictionary import HISTORY_DOCS, column_docs, data_dictionary
    from fieldcal.products.report import FLEET_SCHEMA

    text = data_dictionary()
    catalog = column_docs("catalog")
    shown = set(history.camera_history(lake, "cam-a", ("f_mm", "k1")).column_names) | set(FLEET_SCHEMA.names)
    for name in shown:
        key = "delta_<name>" if name.startswith("delta_") else name
        assert catalog.get(key) or HISTORY_DOCS.get(key), name
        assert f"`{key}`" in text, name
    assert "`changed`" in text and "none: no quantity did" in text
