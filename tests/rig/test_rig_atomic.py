"""A rig version is committed atomically (issue 27, goal 3): the heads' documents and the rig
document are one version of the rig. A commit killed between the rig's row and the heads' one
catalog transaction (the commit point, :meth:`fieldcal.lake.store.Lake.commit_rig`) leaves
nothing any reader sees -- history, latest, compare, export, certificate, report, dashboard,
SQL, fleet -- and `gc` takes its parts as any uncommitted part; a rerun completes it (nothing
solved twice, one version per fingerprint)."""

from __future__ import annotations

import json

import pytest

from fieldcal.lake.check import check
from fieldcal.lake.gc import gc
from fieldcal.lake.store import Lake
from fieldcal.products.dashboard import write_dashboard
from fieldcal.rig_run import prepare_rig, run_rig, solve_rig
from fieldcal.synthetic.rig import two_head_rig, write_rig_session
from flows import cli


class Killed(BaseException):
    """The process ended here (no cleanup of the commit's parts runs)."""


@pytest.fixture(scope="module")
def outcome(tmp_path_factory):
    folder = write_rig_session(tmp_path_factory.mktemp("rigatomic") / "bar2-s1", two_head_rig(seed=21))
    prepared = prepare_rig(folder)
    return folder, prepared, solve_rig(prepared)


def _killed_between_rig_row_and_heads(lake_path, out, monkeypatch) -> tuple[str, list[str]]:
    """Commit, killed just before the heads' catalog transaction; the rig version and head versions
    it wrote (from the rigs table, raw)."""
    lake = Lake(lake_path)

    def killed(*args, **kwargs):
        raise Killed

    with monkeypatch.context() as m:
        m.setattr(Lake, "_commit_heads", killed)
        m.setattr(Lake, "_discard", lambda self, written, residuals_of: None)
        with pytest.raises(Killed):
            lake.commit_rig(out.heads, json.loads(json.dumps(out.rig_document)))
    (row,) = Lake(lake_path).tables.scan("rigs").to_pylist()          # the rig's row is written ...
    return row["version"], list(row["head_versions"])


def _cli(capsys, *argv) -> tuple[int, str, str]:
    status = cli.main([str(a) for a in argv])
    got = capsys.readouterr()
    return status, got.out, got.err


def test_no_reader_sees_the_heads_or_the_rig_of_an_interrupted_commit(tmp_path, outcome, monkeypatch, capsys):
    _, _, out = outcome
    lake_path = tmp_path / "lake"
    rig_version, heads = _killed_between_rig_row_and_heads(lake_path, out, monkeypatch)
    lake = Lake(lake_path)
    for v, cid in zip(heads, ("bar2-left", "bar2-right"), strict=True):   # ... and the heads' parts whole
        assert lake.storage.exists(lake.paths(cid, "bar2-s1", v)["document"])
    assert lake.catalog().num_rows == 0 and lake.rig_catalog().num_rows == 0
    assert lake.latest("bar2-left") is None and lake.latest("bar2-right") is None
    assert not lake.is_rig_version(rig_version)
    assert lake.rig_of({"version": heads[0], "rig": {"rig_id": "bar2"}}) is None
    status, text, _ = _cli(capsys, "history", "--lake", lake_path, "--format", "json")
    assert status == 0 and json.loads(text) == []
    status, text, _ = _cli(capsys, "history", "--lake", lake_path, "--format", "json", "--sql",
                           "SELECT version FROM rigs UNION ALL SELECT version FROM residuals")
    assert status == 0 and json.loads(text) == []
    status, _, err = _cli(capsys, "history", "--lake", lake_path, "--rig", "bar2")
    assert status == 2 and "'bar2'" in err
    status, text, err = _cli(capsys, "history", "--lake", lake_path, "--camera", "bar2-left", "--format", "json")
    assert status == 2 and text == "" and "'bar2-left' has no calibration" in err
    for argv in (("compare", rig_version, rig_version), ("compare", heads[0], heads[0]),
                 ("export", heads[0], "--format", "opencv", "--out", tmp_path / "x.yaml"),
                 ("certificate", heads[1], "--out", tmp_path / "cert"),
                 ("report", heads[1], "--out", tmp_path / "report"),
                 ("show", heads[0])):
        status, _, err = _cli(capsys, *argv, "--lake", lake_path)
        assert status == 2 and err.count("\n") == 1, (argv, err)
    assert write_dashboard(lake, tmp_path / "site")["cameras"] == 0
    assert check(lake) == []                                   # not damage: a commit that never happened
    doomed = gc(lake, grace_s=0, dry_run=True)                 # gc: uncommitted parts like any other
    assert lake.rig_path("bar2", "bar2-s1", rig_version) in doomed
    assert all(any(v in d for d in doomed) for v in heads)


def test_a_rerun_completes_the_interrupted_rig_version_without_solving(tmp_path, outcome, monkeypatch, capsys):
    folder, prepared, out = outcome
    lake_path = tmp_path / "lake"
    rig_version, heads = _killed_between_rig_row_and_heads(lake_path, out, monkeypatch)
    monkeypatch.setattr("fieldcal.rig_run.solve_rig", lambda *a, **k: pytest.fail("solved twice"))
    version, head_versions, outcome_ = run_rig(folder, Lake(lake_path), prepared=prepared)
    assert outcome_ is None and version.new and version == rig_version and head_versions == heads
    lake = Lake(lake_path)
    assert sorted(lake.catalog()["version"].to_pylist()) == sorted(heads)
    assert lake.rig_catalog()["version"].to_pylist() == [rig_version]
    assert lake.latest("bar2-left") == heads[0] and lake.rig_of(lake.load_document(heads[1]))["version"] == rig_version
    assert check(lake) == [] and gc(lake, grace_s=0) == []
    again, again_heads, none = run_rig(folder, Lake(lake_path), prepared=prepared)   # one version per fingerprint
    assert none is None and not again.new and again == rig_version and again_heads == heads
    assert Lake(lake_path).catalog().num_rows == 2
    status, text, err = _cli(capsys, "history", "--lake", lake_path, "--rig", "bar2", "--format", "json")
    assert status == 0 and [r["version"] for r in json.loads(text)] == [rig_version], err


def test_after_gc_took_the_interrupted_parts_a_rerun_makes_one_new_version(tmp_path, outcome, monkeypatch):
    folder, prepared, out = outcome
    lake_path = tmp_path / "lake"
    rig_version, heads = _killed_between_rig_row_and_heads(lake_path, out, monkeypatch)
    removed = gc(Lake(lake_path), grace_s=0)
    assert lake_path.joinpath(Lake.rig_path("bar2", "bar2-s1", rig_version)).exists() is False and removed
    version, head_versions, outcome_ = run_rig(folder, Lake(lake_path), prepared=prepared)
    assert outcome_ is not None and version.new and version != rig_version
    assert not set(head_versions) & set(heads)
    lake = Lake(lake_path)
    assert sorted(lake.catalog()["version"].to_pylist()) == sorted(head_versions)
    assert lake.rig_catalog()["version"].to_pylist() == [version]
    assert check(lake) == []


def test_a_lake_whose_heads_were_committed_before_the_rig_row_keeps_working(tmp_path, outcome):
    """The order before: the heads' catalog rows, then the rig row; a crash between the two left
    the heads committed: a rerun writes only the rig row."""
    folder, prepared, out = outcome
    lake = Lake(tmp_path / "lake")
    for head in out.heads:
        lake.commit(head["document"], head.get("arrays"), head.get("residuals"), array_attrs=head.get("array_attrs"))
    heads = lake.catalog()["version"].to_pylist()
    version, head_versions, _ = run_rig(folder, Lake(tmp_path / "lake"), prepared=prepared)
    assert sorted(head_versions) == sorted(heads) and Lake(tmp_path / "lake").catalog().num_rows == 2
    assert Lake(tmp_path / "lake").rig_catalog()["version"].to_pylist() == [version]
