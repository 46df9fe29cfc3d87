"""A rig version in the lake (fieldcal.lake.store.Lake.commit_rig): the heads' parts, the rig's
row, then every head's catalog row in one transaction (the commit point); a failure before it
leaves nothing committed (tests/rig/test_rig_atomic.py: a kill, no reader sees it, a rerun completes it)."""

from __future__ import annotations

import pytest

from fieldcal.errors import LakeError
from fieldcal.lake.store import Lake
from fieldcal.rig_run import prepare_rig, run_rig, solve_rig
from fieldcal.synthetic.rig import two_head_rig, write_rig_session


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    folder = write_rig_session(tmp_path_factory.mktemp("rig") / "bar2-s1", two_head_rig(seed=21))
    prepared = prepare_rig(folder)
    return folder, prepared, solve_rig(prepared)


def test_a_failed_rig_row_leaves_nothing_committed_and_a_rerun_commits_one_version(tmp_path, outcome, monkeypatch):
    folder, prepared, out = outcome
    lake = Lake(tmp_path / "lake")
    real = lake.tables.append

    def failing(name, table, info=None, **kwargs):
        if name == "rigs":
            raise LakeError("simulated failure of the rig row")
        return real(name, table, info, **kwargs)

    monkeypatch.setattr(lake.tables, "append", failing)
    with pytest.raises(LakeError, match="simulated failure"):
        lake.commit_rig(out.heads, out.rig_document)
    assert lake.catalog().num_rows == 0 and lake.rig_catalog().num_rows == 0       # neither heads nor rig
    assert not list((tmp_path / "lake" / "calibrations").rglob("*.json"))         # the parts were removed
    monkeypatch.setattr(lake.tables, "append", real)
    version, head_versions, _ = run_rig(folder, lake, prepared=prepared)
    assert sorted(head_versions) == sorted(lake.catalog()["version"].to_pylist()) and lake.catalog().num_rows == 2
    assert lake.rig_catalog()["version"].to_pylist() == [version]
    assert [h["version"] for h in lake.load_rig_document(version)["heads"]] == head_versions


def test_a_failed_head_leaves_no_catalog_row(tmp_path, outcome, monkeypatch):
    _, _, out = outcome
    lake = Lake(tmp_path / "lake")
    real = lake.tables.append

    def failing(name, table, info=None, **kwargs):
        if name == "catalog":
            raise OSError(28, "No space left on device")
        return real(name, table, info, **kwargs)

    monkeypatch.setattr(lake.tables, "append", failing)
    with pytest.raises(LakeError, match="No space left"):
        lake.commit_rig(out.heads, out.rig_document)
    monkeypatch.setattr(lake.tables, "append", real)
    assert lake.catalog().num_rows == 0 and lake.rig_catalog().num_rows == 0
    assert not list((tmp_path / "lake" / "calibrations").rglob("*.json"))    # the parts were removed


def test_the_heads_fingerprints_are_in_the_catalogs_log_so_a_head_is_not_committed_twice(tmp_path, outcome):
    """Issue 28: the catalog's commit point is an append once per fingerprint, looked up in the
    log; the rig's one transaction records every head's fingerprint there too."""
    _, _, out = outcome
    lake = Lake(tmp_path / "lake")
    _, heads = lake.commit_rig(out.heads, out.rig_document)
    fresh = Lake(tmp_path / "lake")
    for head, version in zip(out.heads, heads, strict=True):
        fp = head["document"]["inputs"]["fingerprint"]
        assert fresh.tables.has_key("catalog", fp) is True
        again = fresh.commit(head["document"], head.get("arrays"), head.get("residuals"),
                             array_attrs=head.get("array_attrs"))
        assert not again.new and again == version
    assert Lake(tmp_path / "lake").catalog().num_rows == len(heads)
