"""A catalog row always points to a whole version (issue 24, class 1).

- A commit reads every part back before its catalog row: a part lost in between (an
  operator's ``rm``, a concurrent gc, the storage) fails the commit, no row points to it.
- gc judges age by the store's clock (file times on the store), never by the writer's
  clock in the version id: a writer a day behind commits while gc runs, nothing is lost.
- A rerun answers from the lake only with a version that reads back whole; otherwise it
  calibrates again and says why.
- ``fieldcal lake repair`` restores consistency for each kind of damage it handles.
"""

import datetime as dt
import os
import shutil
import time

import pytest

import fieldcal.lake.store as store_mod
from fieldcal.errors import LakeError
from fieldcal.lake.check import check
from fieldcal.lake.ids import new_version, utcnow
from fieldcal.lake.store import Lake
from fieldcal.lake.tables import Tables
from tests.lake.test_lake import field_document, residual_table

DAY_S = 86400.0


def writer_a_day_behind(monkeypatch) -> None:
    """Version ids made by a host whose clock is a day (and an hour) behind the store's."""
    monkeypatch.setattr(store_mod, "new_version",
                        lambda fp, when=None: new_version(fp, utcnow() - dt.timedelta(days=1, hours=1)))


def during_commit(monkeypatch, action) -> None:
    """Run ``action(version)`` right after a commit's residual rows, before its catalog row."""
    original = Tables.append

    def append(self, name, table, info=None, **kwargs):
        done = original(self, name, table, info, **kwargs)
        if name == "residuals":
            action(info["version"])
        return done

    monkeypatch.setattr(Tables, "append", append)


def parts_of(root, version):
    return sorted(p for p in root.rglob(f"{version}*") if "_delta_log" not in p.parts)


def test_gc_during_a_commit_of_a_writer_a_day_behind_loses_nothing(tmp_path, monkeypatch):
    root = tmp_path / "lake"
    writer_a_day_behind(monkeypatch)
    removed = []
    during_commit(monkeypatch, lambda v: removed.extend(Lake(root).gc(grace_s=3600.0)))
    v = Lake(root).commit(field_document(), {}, residual_table())
    assert v.new and v.startswith((utcnow() - dt.timedelta(days=1, hours=1)).strftime("%Y%m%d"))
    assert removed == []                 # the version id says a day old; its files are seconds old
    lake = Lake(root)
    assert lake.whole(v) is None and check(lake) == []
    assert lake.read_residuals(v).num_rows == residual_table().num_rows


def test_gc_removes_parts_older_than_the_grace_by_the_store_clock(tmp_path):
    """A version id from the future (a writer ahead) does not keep old parts for ever, and
    an id from the past does not doom fresh ones: only the files' times on the store count."""
    root = tmp_path / "lake"
    lake = Lake(root)
    lake.commit(field_document(), {}, residual_table())
    folder = root / "calibrations" / "cam-a" / "s1"
    old = folder / "20990101T000000Z-00000000-0000.zarr"      # an id from the future, files old
    fresh = folder / "20000101T000000Z-00000000-0001.json"    # an id from the past, file fresh
    old.mkdir()
    (old / "zarr.json").write_text("{}")
    fresh.write_text("{}")
    two_days_ago = time.time() - 2 * DAY_S
    for p in (old / "zarr.json", old):
        os.utime(p, (two_days_ago, two_days_ago))
    assert lake.gc(grace_s=DAY_S, dry_run=True) == [str(old.relative_to(root))]
    assert lake.gc(grace_s=DAY_S) == [str(old.relative_to(root))]
    assert not old.exists() and fresh.exists()
    assert check(Lake(root)) == []


@pytest.mark.parametrize("loss", ["document", "zarr group", "zarr chunk", "document bytes", "residual rows"])
def test_a_commit_whose_parts_are_lost_before_its_catalog_row_is_not_committed(tmp_path, monkeypatch, loss):
    root = tmp_path / "lake"

    def lose(version):
        doc = next(root.rglob(f"{version}.json"))
        group = next(root.rglob(f"{version}.zarr"))
        if loss == "document":
            doc.unlink()
        elif loss == "document bytes":
            doc.write_text(doc.read_text().replace('"cam-a"', '"cam-b"', 1))
        elif loss == "zarr group":
            shutil.rmtree(group)
        elif loss == "zarr chunk":
            next(p for p in (group / "parameters").rglob("*") if p.is_file() and p.parent.name == "c").unlink()
        else:
            Lake(root).tables.delete("residuals", f"version = '{version}'")

    during_commit(monkeypatch, lose)
    with pytest.raises(LakeError, match=r"not committed to .*: .* when read back before the commit"):
        Lake(root).commit(field_document(), {}, residual_table())
    lake = Lake(root)
    assert lake.catalog().num_rows == 0
    assert [p for p in (root / "calibrations").rglob("*") if p.is_file()] == []   # its parts removed
    monkeypatch.undo()
    v = lake.commit(field_document(), {}, residual_table())                     # the next one commits
    assert v.new and lake.whole(v) is None


@pytest.mark.parametrize("loss", ["folder", "document", "zarr group", "zarr chunk"])
def test_a_rerun_recalibrates_when_the_committed_version_does_not_read_back(tmp_path, loss):
    root = tmp_path / "lake"
    lake = Lake(root)
    v1 = lake.commit(field_document(), {}, residual_table())
    doc, group = root / Lake.paths("cam-a", "s1", v1)["document"], root / Lake.paths("cam-a", "s1", v1)["zarr"]
    if loss in ("folder", "zarr group"):
        shutil.rmtree(group)
    if loss in ("folder", "document"):
        doc.unlink()
    if loss == "zarr chunk":
        next(p for p in (group / "sigma").rglob("*") if p.is_file() and p.parent.name == "c").write_bytes(b"x")
    lake = Lake(root)
    assert lake.find_committed(field_document()["inputs"]["fingerprint"]) is None
    assert v1 in lake.not_whole and lake.whole(v1) == lake.not_whole[v1]
    v2 = lake.commit(field_document(), {}, residual_table())
    assert v2.new and v2 != v1 and lake.whole(v2) is None
    again = Lake(root).commit(field_document(), {}, residual_table())
    assert (str(again), again.new) == (str(v2), False)          # one whole version per fingerprint again
