"""The change test and the acceptance of each version, stored in the lake at the commit (issue 29).

Documents without a covariance (sigmas only, :func:`tests.lake.test_lake.field_document`):
the comparison runs on them as on any calibration; what is tested here is which pairs are
compared, when, and what readers pick.
"""

import pytest

from fieldcal.analysis.compare import judge
from fieldcal.lake.store import Lake
from fieldcal.products import report, status
from tests.lake.test_lake import field_document, residual_table


@pytest.fixture
def counted(monkeypatch):
    """The pairs compared (``status.compare_calibrations`` counted)."""
    calls = []
    real = status.compare_calibrations

    def compare(a, b, **kw):
        calls.append((a.version, b.version))
        return real(a, b, **kw)

    monkeypatch.setattr(status, "compare_calibrations", compare)
    return calls


def commit(lake, camera, session, acquired, f_mm=50.0, **kw):
    v = lake.commit(field_document(camera, session, f_mm=f_mm, acquired=acquired, **kw), {}, residual_table())
    return v, status.record_commit(lake, v)


def test_the_commit_stores_the_change_test_and_history_fleet_only_reads_it(tmp_path, counted):
    lake = Lake(tmp_path)
    v1, r1 = commit(lake, "cam-a", "s1", "2026-01-01")
    assert r1["previous"] is None and r1["comparison"] is None and r1["assessment"]["verdict"] in ("PASS", "FAIL")
    v2, r2 = commit(lake, "cam-a", "s2", "2026-02-01", f_mm=50.02)
    assert r2["previous"] == v1 and counted == [(v1, v2)]
    assert r2["comparison"]["version_a"] == v1 and r2["comparison"]["version_b"] == v2
    (row,) = report.fleet_summary(Lake(tmp_path)).to_pylist()
    assert counted == [(v1, v2)]                        # read, not compared again
    assert (row["previous_version"], row["version"]) == (v1, v2)
    assert row["flagged"] == judge(r2["comparison"], 2.0, 0.01)["flagged"]
    assessed = status.assessments(Lake(tmp_path), [v1, v2], compute=False)
    assert set(assessed) == {v1, v2} and len(assessed[v2]["radial"]["dr_um"]) == len(status.RADII_FRACTIONS)


def test_a_backfill_compares_its_new_neighbours_and_readers_pick_the_pair_of_the_order(tmp_path, counted):
    lake = Lake(tmp_path)
    v_jan, _ = commit(lake, "cam-a", "jan", "2026-01-01")
    v_mar, _ = commit(lake, "cam-a", "mar", "2026-03-01", f_mm=50.03)
    v_feb, r = commit(lake, "cam-a", "feb", "2026-02-01", f_mm=50.01)   # committed last, acquired between
    assert (r["previous"], r["next"]) == (v_jan, v_mar)
    assert counted == [(v_jan, v_mar), (v_jan, v_feb), (v_feb, v_mar)]
    (row,) = report.fleet_summary(lake).to_pylist()
    assert (row["previous_version"], row["version"]) == (v_feb, v_mar)    # not the stale (jan, mar)
    assert len(counted) == 3
    assert row["max_change_um"] == pytest.approx(status.changes(lake, [(v_feb, v_mar)])[(v_feb, v_mar)]["max_um"])


def test_a_rerun_of_a_session_replaces_it_as_a_neighbour(tmp_path, counted):
    lake = Lake(tmp_path)
    v1, _ = commit(lake, "cam-a", "s1", "2026-01-01")
    commit(lake, "cam-a", "s2", "2026-02-01", f_mm=50.02)
    v2b, r = commit(lake, "cam-a", "s2", "2026-02-01", f_mm=50.03, seed=5)   # s2 again (other inputs)
    assert r["previous"] == v1
    (row,) = report.fleet_summary(lake).to_pylist()
    assert (row["previous_version"], row["version"]) == (v1, v2b) and len(counted) == 2


def test_fill_computes_once_what_an_older_lake_lacks_with_progress(tmp_path, counted):
    lake = Lake(tmp_path)
    vs = [lake.commit(field_document("cam-a", f"s{k}", f_mm=50 + 0.01 * k, acquired=f"2026-0{k + 1}-01"), {},
                      residual_table()) for k in range(3)]
    lake.commit(field_document("cam-b", "s0"), {}, residual_table())
    seen = []
    counts = status.fill(lake, progress=lambda done, total: seen.append((done, total)))
    assert counted == [(vs[1], vs[2])] and counts["pairs"] == 1 and counts["versions"] == 2
    assert counts["computed"] == 3 and counts["failed"] == 0 and seen[-1] == (3, 3)
    everything = status.fill(Lake(tmp_path), everything=True)
    assert counted[1:] == [(vs[0], vs[1])] and everything["computed"] == 3   # the rest, once
    assert status.fill(Lake(tmp_path), everything=True)["computed"] == 0
    report.fleet_summary(lake)
    assert len(counted) == 2


def test_neighbours_are_of_the_same_camera_when_cameras_share_session_ids(tmp_path, counted):
    lake = Lake(tmp_path)
    a1, _ = commit(lake, "cam-a", "s1", "2026-01-01")
    b1, _ = commit(lake, "cam-b", "s1", "2026-01-15")
    lake.tables.optimize("catalog")                  # one file holds both cameras' rows
    a2, ra = commit(lake, "cam-a", "s2", "2026-02-01", f_mm=50.01)
    b2, rb = commit(lake, "cam-b", "s2", "2026-02-15", f_mm=50.02)
    assert (ra["previous"], rb["previous"]) == (a1, b1) and counted == [(a1, a2), (b1, b2)]
    rows = {r["camera_id"]: r for r in report.fleet_summary(lake).to_pylist()}
    assert rows["cam-b"]["previous_version"] == b1 and len(counted) == 2
