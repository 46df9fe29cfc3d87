"""The catalog's commit point as an append once per fingerprint (issue 28, goal 4).

A commit appends its catalog row with a Delta transaction identifier naming its fingerprint
instead of a MERGE over the catalog: the same guarantees (one version per fingerprint, the
loser of a race finds the winner's version and leaves nothing, time travel), with no scan
of the catalog on the way; a catalog from before is searched until ``lake optimize`` gives
it the identifiers of its rows.
"""

import datetime as dt

import deltalake
import pytest

from fieldcal.lake.store import Lake
from fieldcal.lake.tables import EVERY_KEY_ONCE, table_schema
from tests.lake.test_lake import field_document, residual_table, version_files


class MergeLake(Lake):
    """The commit path before issue 28 (what an older fieldcal wrote: rows without identifiers)."""

    CATALOG_BY_MERGE = True


def test_a_new_version_is_committed_without_reading_the_catalog(tmp_path, monkeypatch):
    lake = Lake(tmp_path)
    first = lake.commit(field_document(seed=1), {}, residual_table())

    def scan(*args, **kwargs):
        raise AssertionError("the catalog was scanned for the fingerprint")

    monkeypatch.setattr(Lake, "find_committed", scan)
    second = Lake(tmp_path).commit(field_document(seed=2), {}, residual_table())
    assert first.new and second.new
    monkeypatch.undo()
    assert sorted(Lake(tmp_path).catalog()["version"].to_pylist()) == sorted([first, second])
    again = Lake(tmp_path).commit(field_document(seed=2), {}, residual_table())
    assert not again.new and again == second


def test_the_loser_of_a_race_at_the_append_returns_the_winners_version_and_leaves_nothing(tmp_path, monkeypatch):
    """Deterministic race: the second commit's pre-check passed, then the first commits
    between its look at the catalog and its append; Delta's conflict check fails the second
    append, whose retry finds the first's identifier."""
    Lake(tmp_path).commit(field_document(seed=5), {}, residual_table())   # the tables exist
    real = deltalake.write_deltalake
    winner = {}

    def racing(target, data, *args, **kwargs):
        if not winner and "catalog" in str(target.table_uri):
            winner["v"] = None                       # once: the winner's own append goes through
            winner["v"] = Lake(tmp_path).commit(field_document(seed=6), {}, residual_table())
        return real(target, data, *args, **kwargs)

    monkeypatch.setattr(deltalake, "write_deltalake", racing)
    loser = Lake(tmp_path).commit(field_document(seed=6), {}, residual_table())
    assert winner["v"].new and not loser.new and loser == winner["v"]
    monkeypatch.undo()
    lake = Lake(tmp_path)
    cat = lake.catalog()
    assert cat.num_rows == 2 and cat["version"].to_pylist().count(str(loser)) == 1
    residual_versions = set(lake.tables.scan("residuals", columns=["version"])["version"].to_pylist())
    assert residual_versions == set(cat["version"].to_pylist())      # the loser's rows removed
    assert len(version_files(tmp_path)) == 4                          # two versions: .json + .zarr each


def test_forced_versions_stay_and_the_next_commit_finds_the_latest(tmp_path):
    lake = Lake(tmp_path)
    a = lake.commit(field_document(seed=3), {}, residual_table(), force=True)
    b = Lake(tmp_path).commit(field_document(seed=3), {}, residual_table(), force=True)
    c = Lake(tmp_path).commit(field_document(seed=3), {}, residual_table())
    assert a.new and b.new and a != b and not c.new and c == b


def test_a_catalog_from_before_is_searched_until_optimize_adopts_its_fingerprints(tmp_path):
    lake = Lake(tmp_path)
    deltalake.DeltaTable.create(lake.tables.storage.delta_uri("catalog"), table_schema("catalog"),
                                storage_options=lake.tables.storage.delta_options)   # no identifiers
    old = MergeLake(tmp_path).commit(field_document(seed=8), {}, residual_table())
    fp = Lake(tmp_path).row(str(old))["fingerprint"]
    assert Lake(tmp_path).tables.has_key("catalog", fp) is None         # cannot tell from the log
    same = Lake(tmp_path).commit(field_document(seed=8), {}, residual_table())
    assert not same.new and same == old                                 # found in the rows
    before_adopt = dt.datetime.now(dt.UTC)

    fresh = Lake(tmp_path)
    report = fresh.tables.optimize("catalog")
    assert report["table"] == "catalog"
    assert fresh.tables.open("catalog").transaction_version(EVERY_KEY_ONCE) is not None
    assert Lake(tmp_path).tables.has_key("catalog", fp) is True
    new = Lake(tmp_path).commit(field_document(seed=9), {}, residual_table())
    assert new.new and Lake(tmp_path).tables.has_key("catalog", Lake(tmp_path).row(str(new))["fingerprint"])
    assert not Lake(tmp_path).commit(field_document(seed=8), {}, residual_table()).new
    assert Lake(tmp_path).catalog()["version"].to_pylist().count(str(old)) == 1
    # time travel across the adopting commit: as of before it, the one old row
    assert Lake(tmp_path).catalog(as_of=before_adopt)["version"].to_pylist() == [str(old)]
    assert Lake(tmp_path).tables.optimize("catalog")["table"] == "catalog"      # adopting again: nothing


@pytest.mark.parametrize("force", [False, True])
def test_merge_and_append_paths_agree_on_what_a_commit_returns(tmp_path, force):
    a = MergeLake(tmp_path / "merge").commit(field_document(seed=4), {}, residual_table(), force=force)
    b = Lake(tmp_path / "txn").commit(field_document(seed=4), {}, residual_table(), force=force)
    assert a.new == b.new is True
    ra, rb = MergeLake(tmp_path / "merge").row(str(a)), Lake(tmp_path / "txn").row(str(b))
    assert {k: v for k, v in ra.items() if k not in ("version", "committed", "zarr_path", "document_path",
                                                     "residuals_path")} == \
        {k: v for k, v in rb.items() if k not in ("version", "committed", "zarr_path", "document_path",
                                                  "residuals_path")}
