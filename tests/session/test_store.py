"""Sessions on an object store (moto S3 on loopback): validated from their small files, images
read from the store where they are measured, never copied (issue 28, goal 1).

The reference of every remote result is the same session loaded from local disk.
"""

import glob
import os
import pickle

import pytest

from fieldcal import batch, pipeline
from fieldcal.contract.fingerprint import sha256_file
from fieldcal.errors import ImageError, InputError
from fieldcal.session.store import SessionStore, glob_names
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.session_writer import write_field_session


def upload(s3_server, local, prefix: str) -> str:
    """Put a local session folder under ``prefix`` of the test bucket; its URL."""
    import fsspec

    url = s3_server.url(prefix)
    fs, path = fsspec.core.url_to_fs(url, **s3_server.storage_options)
    fs.put(str(local) + "/", path + "/", recursive=True)
    return url


@pytest.fixture(scope="module")
def gonio(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gonio") / "lab-remote"
    write_session(folder, "canon5d2", seed=31, raster_scale=0.25, frames_per_angle=1, camera_id="cam-remote")
    return folder


def test_glob_names_match_what_glob_finds_on_disk(tmp_path):
    names = ["images/a.tif", "images/b.TIF", "images/.hidden.tif", "images/sub/c.tif", "images/[x].tif",
             "x.tif", "images/d1.tif", "images/d2.tif", "other/a.tif"]
    for n in names:
        (tmp_path / n).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / n).write_bytes(b"1")
    for pattern in ["images/*.tif", "images/*", "*/*.tif", "images/d?.tif", "images/[ab]*", "images/.*",
                    "images/[[]x].tif", "images/*/*.tif", "*.tif", "images/a.tif", "images/nothing.tif"]:
        on_disk = sorted(p for p in glob.glob(pattern, root_dir=tmp_path) if (tmp_path / p).is_file())
        assert glob_names(pattern, names) == on_disk, pattern


def test_a_session_on_s3_is_prepared_from_its_small_files_and_its_frames_are_read_from_the_store(
        s3_server, gonio):
    url = upload(s3_server, gonio, "stores/lab-remote")
    local = pipeline.prepare(gonio)
    reads = []
    with pytest.MonkeyPatch.context() as mp:     # validating reads no image: the listing's MD5s tell them apart
        mp.setattr(SessionStore, "read_range", lambda self, *a: reads.append(a))
        mp.setattr(SessionStore, "read_image", lambda self, *a: reads.append(a))
        remote = pipeline.prepare(url, storage_options=s3_server.storage_options)
    assert reads == []
    sess = remote.session
    assert sess.store is not None and sess.location == url and sess.session_id == "lab-remote"
    assert remote.to_measure == local.to_measure and remote.tables == local.tables
    # the temporary folder of small files is gone: nothing local is left for a worker to need
    assert not os.path.exists(sess.folder)
    with pytest.raises(InputError, match="on an object store, not a local file"):
        sess.image_path(remote.to_measure[0])

    shipped = pickle.loads(pickle.dumps(remote))                 # as a task's argument travels
    name = remote.to_measure[0]
    image = shipped.session.read_image(name)
    assert image.path == f"{url}/{name}" and image.stamp is None
    assert image.sha256 == sha256_file(gonio / name) == pipeline.image_hash(shipped, name)
    assert shipped.session.image_size(name) == os.path.getsize(gonio / name)
    assert pipeline.measure(shipped, name, image).equals(pipeline.measure(local, name))
    hashes = {n: sha256_file(gonio / n) for n in local.to_measure}
    assert pipeline.input_fingerprint(shipped, hashes) == pipeline.input_fingerprint(local, hashes)


def test_missing_and_copied_images_on_s3_are_found_in_the_listing(s3_server, gonio, tmp_path):
    import shutil

    copy = tmp_path / "lab-copy"
    shutil.copytree(gonio, copy)
    frames = sorted((copy / "images").glob("*.tif"))
    frames[0].unlink()
    url = upload(s3_server, copy, "stores/lab-missing")
    remote = pipeline.prepare(url, storage_options=s3_server.storage_options)
    name = f"images/{frames[0].name}"
    assert batch.missing_images(remote) == {name: "file not found"}
    with pytest.raises(ImageError, match="file not found"):
        remote.session.read_image(name)

    shutil.copy(frames[1], frames[0])                           # the same bytes under two names
    url = upload(s3_server, copy, "stores/lab-dup")
    with pytest.raises(InputError, match=f"^{url}/frames.csv: frame .* has the same bytes as"):
        pipeline.prepare(url, storage_options=s3_server.storage_options)


def test_a_remote_field_session_keeps_its_marks_and_names_bad_input_by_its_url(s3_server, tmp_path):
    folder = tmp_path / "cam-m" / "2026-05-01"
    write_field_session(folder, wide_field(seed=3), images=False, marks_csv=True, image_indices=range(4),
                        coded=False, camera_id="cam-m")
    (folder / "images").mkdir(exist_ok=True)
    (folder / "images" / "notes.txt").write_text("images not taken yet")   # a store has no empty folders
    url = upload(s3_server, folder, "stores/cam-m/2026-05-01")
    remote = pipeline.prepare(url, storage_options=s3_server.storage_options)
    local = pipeline.prepare(folder)
    marks, ref = remote.session.marks(), local.session.marks()   # read at prepare: the folder is gone
    assert not os.path.exists(remote.session.folder) and sorted(marks) == sorted(ref) and marks
    for k in ref:
        assert (marks[k][0] == ref[k][0]).all() and (marks[k][1] == ref[k][1]).all()

    (folder / "session.json").write_text('{"schema": "fieldcal.session/1"}')
    url = upload(s3_server, folder, "stores/cam-m/broken")
    with pytest.raises(InputError, match=f"^{url}/session.json: .*required propert"):
        pipeline.prepare(url, storage_options=s3_server.storage_options)
    with pytest.raises(InputError, match="session folder not found"):
        pipeline.prepare(s3_server.url("stores/nothing-here"), storage_options=s3_server.storage_options)
