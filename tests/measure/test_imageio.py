"""Reading TIFFs: every layout the contract allows, and one clear line for anything else."""

import gc
import hashlib
import os
import weakref

import numpy as np
import pytest
import tifffile

from fieldcal.contract.fingerprint import sha256_file
from fieldcal.errors import ImageError, InputError
from fieldcal.measure.imageio import (
    ImageFile,
    decode_threads,
    probe_image,
    read_file,
    read_image,
    set_decode_threads,
    stat_stamp,
)

RNG = np.random.default_rng(0)
IMG16 = RNG.integers(0, 65535, (120, 160), dtype=np.uint16)


@pytest.mark.parametrize("kw", [
    {},                                              # striped, uncompressed
    {"tile": (64, 64), "compression": "zstd"},      # tiled, zstd
    {"compression": "deflate", "rowsperstrip": 7},  # striped, deflate
    {"compression": "lzw"},
    {"bigtiff": True, "tile": (32, 32)},
])
@pytest.mark.parametrize("source", ["path", "bytes read once"])
def test_reads_16bit_layouts_exactly(tmp_path, kw, source):
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, IMG16, **kw)
    out = read_image(p if source == "path" else read_file(p), expect_size=(160, 120))
    assert out.dtype == np.uint16 and np.array_equal(out, IMG16)


@pytest.mark.parametrize("kw", [{}, {"tile": (64, 64), "compression": "zstd"}, {"byteorder": ">"},
                                {"compression": "deflate", "rowsperstrip": 7}])
def test_one_pass_hash_is_the_file_hash_and_the_pixels_are_decoded_from_those_bytes(tmp_path, kw):
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, IMG16, **kw)
    st = os.stat(p)
    f = read_file(p)
    assert f.sha256 == sha256_file(p) == hashlib.sha256(p.read_bytes()).hexdigest()
    assert f.stamp == stat_stamp(st) and f.path == str(p) and f.data.size == st.st_size
    p.unlink()                                          # nothing is read from the file again
    out = read_image(f, expect_size=(160, 120), maxworkers=2)
    assert np.array_equal(out, IMG16) and out.flags.writeable and out.flags.c_contiguous
    # an uncompressed native-order image is a view of the bytes read, not a copy
    assert np.shares_memory(out, f.data) == (kw == {})
    assert probe_image(f).compression == ("NONE" if "compression" not in kw else kw["compression"].upper())


@pytest.mark.parametrize("kw", [{}, {"tile": (64, 64), "compression": "zstd"}])
def test_the_bytes_read_are_freed_with_their_image_file_without_waiting_for_the_garbage_collector(tmp_path, kw):
    # tifffile's handle and the stream over the bytes form a reference cycle; the bytes of every
    # frame used to live until Python's cyclic collector ran (a worker's peak memory grew
    # with the number of frames)
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, IMG16, **kw)
    gc.collect()
    gc.disable()
    try:
        f = read_file(p)
        probe_image(f)
        out = read_image(f)
        data = weakref.ref(f.data)
        del f
        if kw:                              # decoded: the bytes go with the ImageFile
            assert data() is None
        del out                             # uncompressed: the pixels are a view of the bytes
        assert data() is None
    finally:
        gc.enable()


def test_read_file_names_a_missing_file_and_a_folder(tmp_path):
    with pytest.raises(ImageError, match="nope.tif: file not found"):
        read_file(tmp_path / "nope.tif")
    with pytest.raises(ImageError, match="is a directory, not a file"):
        read_file(tmp_path)


def test_decode_threads_are_set_for_the_process():
    before = decode_threads()
    try:
        set_decode_threads(3)
        assert decode_threads() == 3
        with pytest.raises(InputError, match="decode threads must be an integer >= 1, got 0"):
            set_decode_threads(0)
    finally:
        set_decode_threads(before)


def test_reads_8bit_and_rgb_as_luminance(tmp_path):
    rgb = RNG.integers(0, 255, (40, 50, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "rgb.tif", rgb, photometric="rgb")
    out = read_image(tmp_path / "rgb.tif")
    expect = np.rint(rgb @ np.array([0.299, 0.587, 0.114]))
    assert out.dtype == np.uint8 and np.abs(out.astype(float) - expect).max() <= 1


@pytest.mark.parametrize("make, match", [
    (lambda p: p.write_bytes(b""), "empty file"),
    (lambda p: p.write_bytes(b"this is not a tiff at all"), "not a readable TIFF"),
    (lambda p: tifffile.imwrite(p, np.zeros((8, 8), np.float32)), "unsupported sample type float32"),
    (lambda p: tifffile.imwrite(p, np.zeros((8, 8), np.uint32)), "unsupported sample type uint32"),
])
@pytest.mark.parametrize("source", ["path", "bytes read once"])
def test_bad_files_give_one_line_naming_the_file(tmp_path, make, match, source):
    p = tmp_path / "bad.tif"
    make(p)
    with pytest.raises(ImageError, match=match) as info:
        read_image(p if source == "path" else read_file(p))
    assert str(p) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("kw", [{}, {"tile": (64, 64), "compression": "zstd"}])
def test_truncated_file_is_reported(tmp_path, kw):
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, IMG16, **kw)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageError, match="t.tif"):
        read_image(p)
    with pytest.raises(ImageError, match="t.tif"):
        read_image(read_file(p))
    assert isinstance(read_file(p), ImageFile)          # reading the bytes is not decoding them


def test_wrong_size_and_missing_file(tmp_path):
    tifffile.imwrite(tmp_path / "s.tif", IMG16)
    with pytest.raises(ImageError, match="sensor is 100 x 100"):
        read_image(tmp_path / "s.tif", expect_size=(100, 100))
    with pytest.raises(ImageError, match="file not found"):
        probe_image(tmp_path / "nope.tif")
