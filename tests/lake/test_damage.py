"""One damaged object never stops the commits; ``fieldcal lake repair`` restores consistency.

Issue 24, classes 1 and 3: for each kind of damage (a zero-byte, garbage or deleted table
file, a truncated commit, a checkpoint hint naming a missing checkpoint, a lost document,
a lost Zarr group or version folder), a commit of another camera still succeeds and names
the damage in one plain line, and ``lake repair --apply`` leaves a lake that ``lake check``
finds sound, every whole version in the catalog, nothing deleted (damaged files are in the
quarantine), and commits that work.
"""

import shutil
import uuid

import pyarrow.parquet as pq
import pytest

from fieldcal.lake.check import check
from fieldcal.lake.repair import repair
from fieldcal.lake.store import Lake
from flows import cli
from tests import conftest_s3
from tests.lake.test_lake import field_document, residual_table
from tests.lake.test_lake_faults import data_file_of, make_lake

s3_server = conftest_s3.s3_server
KINDS = ["zero-byte catalog file", "garbage catalog file", "deleted catalog file", "zero-byte residual file",
         "truncated catalog commit", "missing checkpoint", "lost document", "lost zarr group", "lost version folder"]


def damage(root, versions, kind) -> str:
    """Damage the lake; returns the version hit."""
    v = versions[("cam-b", "s2")]
    paths = Lake.paths("cam-b", "s2", v)
    if kind.endswith("catalog file"):
        f = data_file_of(root, "catalog", v)
        f.unlink() if kind.startswith("deleted") else f.write_bytes(b"" if kind.startswith("zero") else b"garbage")
    elif kind == "zero-byte residual file":
        data_file_of(root, "residuals", v).write_bytes(b"")
    elif kind == "truncated catalog commit":
        v = versions[("cam-c", "s2")]                               # the last commit of the catalog
        log = sorted((root / "catalog" / "_delta_log").glob("*.json"))[-1]
        log.write_bytes(log.read_bytes()[: len(log.read_bytes()) * 2 // 3])
    elif kind == "missing checkpoint":
        Lake(root).tables.optimize("catalog")
        for p in (root / "catalog" / "_delta_log").glob("*.checkpoint.parquet"):
            p.unlink()
    elif kind == "lost document":
        (root / paths["document"]).unlink()
    elif kind == "lost zarr group":
        shutil.rmtree(root / paths["zarr"])
    else:
        shutil.rmtree(root / paths["zarr"])
        (root / paths["document"]).unlink()
    return v


def run(capsys, *args) -> tuple[int, str, str]:
    """``fieldcal ARGS`` in this process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    status = cli.main([str(a) for a in args])
    out = capsys.readouterr()
    return status, out.out, out.err


@pytest.mark.parametrize("kind", KINDS)
def test_commits_go_on_and_repair_restores_a_consistent_lake(tmp_path, kind, capsys):
    root = tmp_path / "lake"
    _, versions = make_lake(root)
    before = {v: (root / Lake.paths(c, s, v)["document"]).read_bytes() for (c, s), v in versions.items()}
    hit = damage(root, versions, kind)
    lake = Lake(root)
    new = lake.commit(field_document("cam-z", "s9", seed=99), {}, residual_table(5))   # goal 3: commits go on
    assert new.new and lake.whole(new) is None
    assert all("\x1b" not in str(p) and " 0: " not in str(p) for p in lake.problems)
    if kind != "missing checkpoint":                                  # a bad hint moved aside is no damage
        assert check(Lake(root)) != []                                 # lake check tells what repair is for

    listed = repair(Lake(root))                                        # a dry run lists, changes nothing
    assert listed != [] or kind == "missing checkpoint"                # a writer moved the bad hint aside
    assert repair(Lake(root)) == listed
    status, out, err = run(capsys, "lake", "repair", "--lake", root, "--apply")
    assert status == 0 and out.endswith("no damage left\n"), out + err
    assert "\x1b" not in out + err
    lake = Lake(root)
    assert check(lake) == [] and lake.problems == []
    catalogued = set(lake.catalog()["version"].to_pylist())
    if kind in ("lost zarr group", "lost version folder"):
        assert catalogued == set(versions.values()) - {hit} | {str(new)}
        (kept,) = (root / "quarantine").glob(f"*-{hit}/catalog-row.json")       # the row is kept, not deleted
        assert hit in kept.read_text()
    else:
        assert catalogued == set(versions.values()) | {str(new)}          # every whole version catalogued
    if kind == "lost document":
        assert (root / Lake.paths("cam-b", "s2", hit)["document"]).read_bytes() == before[hit]
    if (kind.endswith("file") and not kind.startswith("deleted")) or kind == "truncated catalog commit":
        assert list((root / "quarantine").rglob("*")) != []              # moved, never deleted
    assert repair(lake, apply=False) == []                                # nothing left to do
    again = lake.commit(field_document("cam-b", "s2", seed=11, f_mm=50.001, acquired="2026-02-10"), {},
                        residual_table(11, seed=1))
    if kind in ("lost zarr group", "lost version folder"):
        assert again.new                                                  # its session calibrates again
    else:
        assert (str(again), again.new) == (versions[("cam-b", "s2")], False)


@pytest.mark.parametrize("kind", ["truncated catalog commit", "missing checkpoint", "zero-byte catalog file"])
def test_repair_before_any_commit_heals_the_log_and_restores_the_rows(tmp_path, kind):
    root = tmp_path / "lake"
    _, versions = make_lake(root)
    damage(root, versions, kind)
    assert [str(r) for r in repair(Lake(root))] != []
    done = repair(Lake(root), apply=True)
    assert all("\x1b" not in str(r) for r in done)
    lake = Lake(root)
    assert check(lake) == [] and set(lake.catalog()["version"].to_pylist()) == set(versions.values())
    assert lake.commit(field_document("cam-z", "s9", seed=99), {}, residual_table(5)).new


def test_every_reader_says_what_it_skipped(tmp_path, capsys):
    """``show``, ``history --fleet``, ``export``, ``compare`` on a lake with a garbage catalog
    file: each answers (exit 0) and names the skipped file once, in one plain line."""
    root = tmp_path / "lake"
    _, versions = make_lake(root)
    data_file_of(root, "catalog", versions[("cam-b", "s2")]).write_bytes(b"garbage")
    runs = {"show": ("show", "latest", "--camera", "cam-b", "--lake", root),
            "history --fleet": ("history", "--fleet", "--lake", root),
            "history": ("history", "--lake", root),
            "export": ("export", "latest", "--camera", "cam-b", "--format", "json", "--out",
                       tmp_path / "cam-b.json", "--lake", root)}
    for what, args in runs.items():
        status, _, err = run(capsys, *args)
        assert status == 0, (what, err)
        skipped = [line for line in err.splitlines() if "skipped catalog: catalog/part-" in line]
        assert len(skipped) == 1 and "\x1b" not in err, (what, err)
        assert skipped[0].startswith(f"fieldcal {args[0]}: skipped ")


def test_delta_rs_errors_become_one_plain_line():
    """Colour codes, delta-rs's ``↳`` between causes and a Rust backtrace, as met above."""
    from fieldcal.errors import one_line

    raw = ("Generic LocalFileSystem error\n  \x1b[31m↳\x1b[0m Requested range was invalid \x1b[31m↳\x1b[0m "
           "Wanted range starting at 0, but object was only 0 bytes long")
    assert one_line(raw) == ("Generic LocalFileSystem error: Requested range was invalid: Wanted range "
                             "starting at 0, but object was only 0 bytes long")
    raw = ("Kernel error: Json error: Truncated record whilst reading escape 0: <unknown> 1: <unknown>\n"
           "  12: start_thread at ./nptl/pthread_create.c:442:8 13: clone3 at ./misc/clone3.S:81:0")
    assert one_line(raw) == "Kernel error: Json error: Truncated record whilst reading escape"
    assert one_line("targets.csv:4: 10: not a number") == "targets.csv:4: 10: not a number"


def test_commits_go_on_and_repair_works_on_s3(s3_server):
    """A zero-byte catalog file and a lost document on moto S3: a commit goes on, repair
    quarantines the file (an object move), restores the document and the hidden row."""
    import s3fs

    url, options = s3_server.url(f"damage-{uuid.uuid4().hex[:8]}"), s3_server.storage_options
    lake = Lake(url, options)
    v1 = lake.commit(field_document("cam-a", "s1"), {}, residual_table())
    v2 = lake.commit(field_document("cam-b", "s1", seed=1), {}, residual_table())
    fs = s3fs.S3FileSystem(key="testing", secret="testing", endpoint_url=s3_server.endpoint_url)
    prefix = url.removeprefix("s3://")
    (hit,) = [a["path"] for a in lake.tables.files("catalog")
              if v2 in pq.read_table(fs.open(f"{prefix}/catalog/{a['path']}"), columns=["version"])["version"]
              .to_pylist()]
    fs.pipe_file(f"{prefix}/catalog/{hit}", b"")
    fs.rm_file(f"{prefix}/{Lake.paths('cam-a', 's1', v1)['document']}")
    v3 = Lake(url, options).commit(field_document("cam-c", "s1", seed=2), {}, residual_table())
    assert v3.new
    done = repair(Lake(url, options), apply=True)
    assert len(done) == 3, done                      # the file, the document, the hidden row
    lake = Lake(url, options)
    assert check(lake) == [] and set(lake.catalog()["version"].to_pylist()) == {v1, v2, str(v3)}
    assert fs.find(f"{prefix}/quarantine") != []
