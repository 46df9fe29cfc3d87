"""Inputs have size bounds (issue 17): what cannot be a real session is refused with one line.

A 10-million-row targets.csv used to take 8 min 55 s and 12.4 GB (parsed three times). Now
every session file has a largest size checked from ``stat`` before it is read, the tables a
largest row count checked while reading (both tokenisers), a session at most
:data:`~fieldcal.session.tables.MAX_IMAGES` images, and a field session's tables are read
once per :class:`~fieldcal.session.loader.Session`. Large files are made sparse or from a
few repeated bytes, so these tests take well under a second each; memory is bounded with
tracemalloc (Python allocations: the bytes read).
"""

import json
import shutil
import tracemalloc

import numpy as np
import pytest

from fieldcal import pipeline
from fieldcal.errors import InputError
from fieldcal.session import loader, tables
from fieldcal.session.tables import MAX_BYTES, MAX_ROWS, read_csv_table, read_targets_csv
from tests.field.test_bad_geometry import CONVERGENT, wall, write_obs_session


@pytest.fixture(scope="module")
def template(tmp_path_factory):
    return write_obs_session(tmp_path_factory.mktemp("limits") / "s", wall(relief_m=1.0), CONVERGENT)


def sparse(path, size: int):
    with open(path, "wb") as fh:
        fh.truncate(size)


@pytest.mark.parametrize("name", ["targets.csv", "observations.csv", "session.json"])
def test_a_file_beyond_its_size_limit_is_refused_before_it_is_read(template, tmp_path, name):
    folder = shutil.copytree(template, tmp_path / "s")
    sparse(folder / name, 1 << 30)                                  # 1 GiB, nothing on disk
    tracemalloc.start()
    try:
        with pytest.raises(InputError, match=rf"{name}: file of 1024\.0 MiB; a {name} is at most "
                                             rf"{MAX_BYTES[name] >> 20} MiB") as info:
            pipeline.prepare(folder)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert "\n" not in str(info.value)
    assert peak < 4 << 20                    # 4 MiB: the session's small files, never the big one


def test_frames_csv_beyond_its_size_limit_is_refused(tmp_path):
    folder = tmp_path / "g"
    folder.mkdir()
    (folder / "session.json").write_text(json.dumps({
        "schema": "fieldcal.session/1", "method": "goniometer", "camera_id": "cam-lab", "acquired": "2026-11-20",
        "sensor": {"width_px": 700, "height_px": 460, "pixel_size_um": 50.0}, "frames": "frames.csv",
        "images": "images/*.tif"}))
    sparse(folder / "frames.csv", MAX_BYTES["frames.csv"] + 1)
    with pytest.raises(InputError, match=r"frames\.csv: file of 16\.0 MiB; a frames\.csv is at most 16 MiB"):
        pipeline.prepare(folder)


@pytest.mark.parametrize("quoted", [False, True], ids=["arrow", "python"])
def test_a_targets_csv_with_more_rows_than_a_field_has_is_refused(tmp_path, quoted):
    """100 001 rows of 8 bytes: under the size limit, over the row limit (the Python
    tokeniser, chosen by the quote in the header, stops at the first row too many)."""
    p = tmp_path / "targets.csv"
    header = '"id",X,Y,Z\n' if quoted else "id,X,Y,Z\n"
    p.write_bytes(header.encode() + b"T,0,0,0\n" * (MAX_ROWS["targets.csv"] + 1))
    with pytest.raises(InputError, match=r"targets\.csv: more than 100000 rows \(fieldcal's limit for a "
                                         r"targets\.csv"):
        read_targets_csv(p)


def test_a_field_of_the_largest_size_is_read_exactly(tmp_path):
    """100 000 targets (the limit): every value as written (the shortest repr round-trips)."""
    n = MAX_ROWS["targets.csv"]
    rng = np.random.default_rng(3)
    xyz = rng.normal(0, 100, (n, 3))
    sigma = rng.uniform(0.5, 5, n)
    p = tmp_path / "targets.csv"
    p.write_text("id,X,Y,Z,sigma_mm,code\n" + "".join(
        f"W{k:06d},{x!r},{y!r},{z!r},{s!r},{k if k % 1000 == 0 else ''}\n"
        for k, ((x, y, z), s) in enumerate(zip(xyz.tolist(), sigma.tolist(), strict=True))))
    t = read_targets_csv(p)
    assert len(t) == n and t.ids[0] == "W000000" and t.ids[-1] == f"W{n - 1:06d}"
    np.testing.assert_array_equal(t.xyz_m, xyz)
    np.testing.assert_array_equal(t.sigma_mm, sigma)
    np.testing.assert_array_equal(np.flatnonzero(t.codes >= 0), np.arange(0, n, 1000))


def test_more_observations_than_the_limit_are_refused(tmp_path, monkeypatch):
    monkeypatch.setitem(tables.MAX_ROWS, "observations.csv", 50)
    p = tmp_path / "observations.csv"
    p.write_text("image,target_id,u,v\n" + "images/a.tif,T,1,1\n" * 51)
    with pytest.raises(InputError, match=r"observations\.csv: more than 50 rows"):
        read_csv_table(p, ("image", "target_id", "u", "v"), kind="observations.csv")


def test_a_glob_matching_more_images_than_a_session_has_is_refused(template, tmp_path, monkeypatch):
    monkeypatch.setattr(loader, "MAX_IMAGES", 5)
    folder = shutil.copytree(template, tmp_path / "s")
    (folder / "images").mkdir()
    for k in range(6):
        (folder / "images" / f"i{k}.tif").write_bytes(bytes([k]))
    with pytest.raises(InputError, match=r"session\.json: images 'images/\*\.tif' matches more than 5 files"):
        loader.load_session(folder)


def test_a_session_lists_at_most_10000_images_in_its_manifest(template, tmp_path):
    folder = shutil.copytree(template, tmp_path / "s")
    m = json.loads((folder / "session.json").read_text())
    m["images"] = [{"file": f"images/i{k}.tif"} for k in range(10_001)]
    (folder / "session.json").write_text(json.dumps(m))
    with pytest.raises(InputError, match=r"session\.json: .* is too long \(at /images\)"):
        loader.load_session(folder)


def test_a_field_session_reads_its_targets_once(template, tmp_path, monkeypatch):
    """prepare, the observations and solve share one read of targets.csv (it was three)."""
    calls = []
    real = loader.read_targets_csv
    monkeypatch.setattr(loader, "read_targets_csv", lambda p: calls.append(p) or real(p))
    prepared = pipeline.prepare(shutil.copytree(template, tmp_path / "s"))
    outcome = pipeline.solve(prepared, {}, fingerprint_="sha256:" + "0" * 64)
    assert outcome.document["stats"]["n_observations"] > 0
    assert len(calls) == 1
    a, b = prepared.session.targets(), prepared.session.targets()
    a.xyz_m[0, 0] = 1e9                                      # each call gets its own copy
    assert b.xyz_m[0, 0] != 1e9
