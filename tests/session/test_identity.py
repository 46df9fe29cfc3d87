"""Which session a run is, and which photographs it has (issue 17).

- Two copies of one session folder without a ``session_id`` (``wall-a``, ``wall-b``) are two
  sessions: the session's identity (camera_id, session_id) is part of the inputs'
  fingerprint, so the second run makes its own version instead of being credited with the
  first's. The same folder run twice is still recognised as unchanged.
- ``session_id`` defaults to the folder's name as given (one definition:
  :func:`fieldcal.session.loader.default_session_id`, also used by the fleet's scan).
- A photograph counts once: the same file under two spellings of its path, through a
  symbolic or hard link, or as a byte-identical copy is refused with one line before
  anything is measured (:func:`fieldcal.session.loader.check_distinct_files`).

The end-to-end tests go through the library (``pipeline`` and the lake, without Prefect);
the last one runs ``fieldcal run`` twice as a user would.
"""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fieldcal import pipeline
from fieldcal.errors import InputError
from fieldcal.lake.store import Lake
from fieldcal.session.loader import default_session_id, load_session
from tests.field.test_bad_geometry import CONVERGENT, wall, write_obs_session

ROOT = Path(__file__).resolve().parents[2]
FIELDCAL = str(Path(sys.executable).with_name("fieldcal"))


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """An observation-only field session without a session_id (solves in about a second)."""
    folder = write_obs_session(tmp_path_factory.mktemp("template") / "wall", wall(relief_m=1.0), CONVERGENT)
    assert "session_id" not in json.loads((folder / "session.json").read_text())
    return folder


def run(folder, lake) -> tuple[str, bool]:
    """One session through the library: prepare, (measure), fingerprint, the no-op check, solve, commit."""
    prepared = pipeline.prepare(folder)
    hashes = {n: pipeline.image_hash(prepared, n) for n in prepared.to_measure}
    fp = pipeline.input_fingerprint(prepared, hashes)
    lk = Lake(str(lake))
    existing = lk.find_committed(fp)
    if existing is not None:
        return existing, False
    measurements = {n: pipeline.measure(prepared, n) for n in prepared.to_measure}
    outcome = pipeline.solve(prepared, measurements, fingerprint_=fp)
    v = lk.commit(outcome.document, outcome.arrays, outcome.residuals, array_attrs=outcome.array_attrs)
    return str(v), bool(v.new)


def test_two_copies_of_a_session_folder_get_a_version_each(session, tmp_path):
    a, b = shutil.copytree(session, tmp_path / "wall-a"), shutil.copytree(session, tmp_path / "wall-b")
    lake = tmp_path / "lake"
    va, new_a = run(a, lake)
    vb, new_b = run(b, lake)
    assert new_a and new_b and va != vb
    cat = Lake(str(lake)).catalog()
    assert sorted(zip(cat["session_id"].to_pylist(), cat["version"].to_pylist(), strict=True)) == \
        [("wall-a", va), ("wall-b", vb)]
    assert Lake(str(lake)).latest("cam-geometry", "wall-b") == vb
    assert run(b, lake) == (vb, False)                   # the same folder again: unchanged
    assert run(a, lake) == (va, False)


def test_the_fingerprint_holds_the_session_identity_and_nothing_of_the_path(session, tmp_path):
    def fp(folder):
        return pipeline.input_fingerprint(pipeline.prepare(folder), {})

    a = shutil.copytree(session, tmp_path / "x" / "wall-a")
    moved = shutil.copytree(session, tmp_path / "y" / "wall-a")      # same name elsewhere: same session
    b = shutil.copytree(session, tmp_path / "x" / "wall-b")
    assert fp(a) == fp(moved) != fp(b)
    before = fp(b)
    renamed = b.rename(tmp_path / "x" / "wall-c")          # a new name is a new session
    assert fp(renamed) not in (before, fp(a))


def test_session_id_defaults_to_the_folder_name_as_given(session, tmp_path, monkeypatch):
    a = shutil.copytree(session, tmp_path / "wall-a")
    link = tmp_path / "campaign-7"
    link.symlink_to(a, target_is_directory=True)
    assert load_session(a).session_id == "wall-a"
    assert load_session(str(a) + "/").session_id == "wall-a"
    assert load_session(link).session_id == "campaign-7"     # the name the user gave, as the fleet sees it
    monkeypatch.chdir(a)
    assert load_session(".").session_id == "wall-a"
    assert default_session_id({"session_id": "s-1"}, a) == "s-1"
    assert default_session_id({}, "bucket/prefix/wall-b") == "wall-b"


@pytest.mark.parametrize("name", ["wall a", "wall\nb", "g[1]", "wall-\u202e", "x" * 129])
def test_a_folder_name_that_is_not_an_id_is_refused_when_it_would_be_the_session_id(session, tmp_path, name):
    folder = shutil.copytree(session, tmp_path / name)
    with pytest.raises(InputError, match=r"(?s)session\.json \(session_id defaults to the folder name .*\): "
                                         r".* is not an id: .* \(at /session_id\)"):
        load_session(folder)
    m = json.loads((folder / "session.json").read_text())
    (folder / "session.json").write_text(json.dumps({**m, "session_id": "wall-a"}))
    assert load_session(folder).session_id == "wall-a"       # an explicit id makes the folder usable


@pytest.mark.slow
def test_fieldcal_run_of_two_copies_prints_two_versions(prefect_server, session, tmp_path):
    env = dict(os.environ, PREFECT_API_URL=prefect_server, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1",
               FIELDCAL_HASH_CACHE=str(tmp_path / "hashes.sqlite"), PYTHONPATH=str(ROOT))
    env.pop("FIELDCAL_LAKE", None)
    lake = tmp_path / "lake"
    printed = []
    for name in ("wall-a", "wall-b"):            # (reruns are unchanged: the library test above)
        folder = shutil.copytree(session, tmp_path / name)
        proc = subprocess.run([FIELDCAL, "run", str(folder), "--lake", str(lake)], capture_output=True,
                              text=True, env=env, cwd=tmp_path, timeout=300)
        assert proc.returncode == 0, proc.stderr
        printed.append(proc.stdout.strip())
    assert printed[0] != printed[1]
    cat = Lake(str(lake)).catalog()
    assert sorted(zip(cat["session_id"].to_pylist(), cat["version"].to_pylist(), strict=True)) == \
        [("wall-a", printed[0]), ("wall-b", printed[1])]


# --------------------------------------------------------------------------------------
# a photograph counts once
# --------------------------------------------------------------------------------------
def image_session(root: Path, images=("a", "b", "c"), listed=None) -> Path:
    """A field session with marks.csv whose images are small distinct files (prepare only lists
    them; the duplicate check reads them)."""
    folder = root / "s"
    (folder / "images").mkdir(parents=True)
    for k, name in enumerate(images):
        (folder / "images" / f"{name}.tif").write_bytes(bytes([k + 1]) * 70_000)   # > the 64 KiB sample
    (folder / "targets.csv").write_text("id,X,Y,Z\n" + "".join(f"T{k},{k},0,{k % 3}\n" for k in range(6)))
    (folder / "marks.csv").write_text("image,target_id,u,v\n" + "".join(
        f"images/{n}.tif,T{k},{10 + k},{20 + k}\n" for n in images for k in range(4)))
    manifest = {"schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-1",
                "acquired": "2026-11-20", "sensor": {"width_px": 100, "height_px": 80, "pixel_size_um": 5.0},
                "lens": {"nominal_focal_mm": 20.0}, "field": {"targets": "targets.csv"},
                "images": listed if listed is not None else "images/*.tif"}
    (folder / "session.json").write_text(json.dumps(manifest))
    return folder


def refused(folder, match, file="session.json"):
    with pytest.raises(InputError, match=match) as info:
        pipeline.prepare(folder)
    assert "\n" not in str(info.value) and str(info.value).startswith(str(folder / file))


def test_distinct_images_of_equal_size_and_equal_middle_are_accepted(tmp_path):
    folder = image_session(tmp_path)
    for name in ("a", "b"):                 # same size, same middle 64 KiB, different last byte
        (folder / "images" / f"{name}.tif").write_bytes(b"\0" * 100_000 + name.encode())
    assert pipeline.prepare(folder).to_measure == ["images/a.tif", "images/b.tif", "images/c.tif"]


@pytest.mark.parametrize("spelling", ["images/./a.tif", "./images/a.tif", "images//a.tif", "images\\a.tif"])
def test_one_image_listed_under_two_spellings_is_refused(tmp_path, spelling):
    listed = [{"file": "images/a.tif"}, {"file": "images/b.tif"}, {"file": spelling}]
    folder = image_session(tmp_path, listed=listed)
    refused(folder, r"image 'images/a\.tif' is listed twice \(as .*\): at /images/0 and /images/2")


def test_spellings_are_one_name_everywhere(tmp_path):
    listed = [{"file": "./images/a.tif"}, {"file": "images//b.tif"}, {"file": "images/c.tif"}]
    folder = image_session(tmp_path, listed=listed)
    with open(folder / "marks.csv", "a") as fh:
        fh.write("images/./a.tif,T5,1,2\n")            # the marks name it the plain way and another
    prepared = pipeline.prepare(folder)
    assert prepared.to_measure == ["images/a.tif", "images/b.tif", "images/c.tif"]
    with open(folder / "marks.csv", "a") as fh:
        fh.write("images/a.tif,T5,3,4\n")
    refused(folder, r"marks\.csv:\d+: target 'T5' marked twice in 'images/a\.tif' \(first on line 14\)",
            "marks.csv")


@pytest.mark.parametrize("how", ["symlink", "hardlink", "copy"])
def test_the_same_photograph_under_two_names_is_refused(tmp_path, how):
    folder = image_session(tmp_path)
    twin = folder / "images" / "d.tif"
    {"symlink": lambda: twin.symlink_to("a.tif"), "hardlink": lambda: os.link(folder / "images" / "a.tif", twin),
     "copy": lambda: shutil.copyfile(folder / "images" / "a.tif", twin)}[how]()
    match = (r"image 'images/d\.tif' has the same bytes as 'images/a\.tif' \(SHA-256 [0-9a-f]{12}\.\.\.\)"
             if how == "copy" else r"image '.*' is the file '.*' again \(a link\)")
    refused(folder, match + ": a photograph counts once")


def test_observations_under_two_spellings_of_one_image_are_one_image(tmp_path):
    folder = write_obs_session(tmp_path / "s", wall(relief_m=1.0), CONVERGENT)
    text = (folder / "observations.csv").read_text()
    head, *rows = text.splitlines()
    first = rows[0].split(",")
    spelled = ",".join(["./" + first[0]] + first[1:])
    (folder / "observations.csv").write_text("\n".join([head, *rows, spelled]) + "\n")
    refused(folder, rf"observations\.csv:{len(rows) + 2}: target '{first[1]}' observed twice in "
                    rf"'{first[0]}' \(first on line 2\)", "observations.csv")
    (folder / "observations.csv").write_text("\n".join([head, *rows[1:], spelled]) + "\n")
    data = pipeline.prepare(folder)
    from fieldcal.session.loader import field_data_from_observations
    names = [im.file for im in field_data_from_observations(data.session).images]
    assert first[0] in names and len(names) == len(set(names)) == len(CONVERGENT)


def test_a_goniometer_frame_listed_twice_under_two_spellings_is_refused(tmp_path):
    folder = tmp_path / "g"
    (folder / "images").mkdir(parents=True)
    rows = [(f"images/{a}{w}.tif", a, w) for a in "xy" for w in (-10, 0, 10)]
    for k, (f, _, _) in enumerate(rows):
        (folder / f).write_bytes(bytes([k + 1]) * 100)
    (folder / "session.json").write_text(json.dumps({
        "schema": "fieldcal.session/1", "method": "goniometer", "camera_id": "cam-lab", "acquired": "2026-11-20",
        "sensor": {"width_px": 700, "height_px": 460, "pixel_size_um": 50.0}, "frames": "frames.csv",
        "images": "images/*.tif"}))
    text = "file,axis,angle_deg\n" + "".join(f"{f},{a},{w}\n" for f, a, w in rows)
    (folder / "frames.csv").write_text(text + "./images/x0.tif,x,0\n")
    refused(folder, r"frames\.csv:8: frame 'images/x0\.tif' is listed twice \(as '\./images/x0\.tif'; "
                    r"first on line 3\)", "frames.csv")
    (folder / "frames.csv").write_text(text)
    shutil.copyfile(folder / "images" / "x0.tif", folder / "images" / "x10.tif")
    refused(folder, r"frame 'images/x10\.tif' has the same bytes as 'images/x0\.tif'", "frames.csv")


# --------------------------------------------------------------------------------------
# the same pixels in another encoding (issue 24, class 7)
# --------------------------------------------------------------------------------------
def tiff_session(root: Path) -> Path:
    """:func:`image_session` with real 80 x 100 16-bit TIFFs of noise (distinct photographs)."""
    import numpy as np
    import tifffile

    folder = image_session(root)
    rng = np.random.default_rng(24)
    for name in ("a", "b", "c"):
        tifffile.imwrite(folder / "images" / f"{name}.tif", rng.integers(0, 4096, (80, 100), dtype=np.uint16))
    return folder


def _resave(src: Path, dst: Path, how: str) -> None:
    import numpy as np
    import tifffile

    pixels = tifffile.imread(src)
    if how == "byte appended":
        dst.write_bytes(src.read_bytes() + b"\0")
    elif how == "big-endian":
        tifffile.imwrite(dst, pixels, byteorder=">")
    elif how == "tiled zstd":
        tifffile.imwrite(dst, pixels, compression="zstd", tile=(16, 16))
    elif how == "rgb":
        tifffile.imwrite(dst, np.stack([pixels] * 3, axis=-1), photometric="rgb", compression="zlib")
    else:
        tifffile.imwrite(dst, pixels, compression=how, rowsperstrip=7)


@pytest.mark.parametrize("how", ["zlib", "lzw", "byte appended", "big-endian", "tiled zstd", "rgb"])
def test_the_same_pixels_in_another_encoding_are_refused(tmp_path, how):
    folder = tiff_session(tmp_path)
    twin = folder / "images" / "d.tif"
    _resave(folder / "images" / "b.tif", twin, how)
    assert twin.read_bytes() != (folder / "images" / "b.tif").read_bytes()
    refused(folder, r"image 'images/d\.tif' has the same pixels as 'images/b\.tif' in another encoding "
                    r"\(pixels' SHA-256 [0-9a-f]{12}\.\.\.\): a photograph counts once")


def test_images_that_agree_in_the_middle_band_only_are_distinct(tmp_path):
    import tifffile

    folder = tiff_session(tmp_path)
    pixels = tifffile.imread(folder / "images" / "a.tif")
    pixels[0, 0] += 1                                   # outside the sampled band: another photograph
    tifffile.imwrite(folder / "images" / "d.tif", pixels, compression="zlib")
    assert pipeline.prepare(folder).to_measure == [f"images/{n}.tif" for n in "abcd"]
    from fieldcal.measure.imageio import pixel_digest, pixel_sample_digest

    a, d = folder / "images" / "a.tif", folder / "images" / "d.tif"
    assert pixel_sample_digest(a) == pixel_sample_digest(d) and pixel_digest(a) != pixel_digest(d)


def test_a_goniometer_frame_in_another_encoding_is_refused(tmp_path):
    import numpy as np
    import tifffile

    folder = tmp_path / "g"
    (folder / "images").mkdir(parents=True)
    rows = [(f"images/{a}{w}.tif", a, w) for a in "xy" for w in (-10, 0, 10)]
    rng = np.random.default_rng(5)
    for f, _, _ in rows:
        tifffile.imwrite(folder / f, rng.integers(0, 255, (46, 70), dtype=np.uint8))
    (folder / "session.json").write_text(json.dumps({
        "schema": "fieldcal.session/1", "method": "goniometer", "camera_id": "cam-lab", "acquired": "2026-11-20",
        "sensor": {"width_px": 70, "height_px": 46, "pixel_size_um": 50.0}, "frames": "frames.csv",
        "images": "images/*.tif"}))
    (folder / "frames.csv").write_text("file,axis,angle_deg\n" + "".join(f"{f},{a},{w}\n" for f, a, w in rows))
    assert len(pipeline.prepare(folder).to_measure) == 6
    _resave(folder / "images" / "x0.tif", folder / "images" / "x10.tif", "zlib")
    refused(folder, r"frame 'images/x10\.tif' has the same pixels as 'images/x0\.tif'", "frames.csv")
