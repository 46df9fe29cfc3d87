"""Reading TIFFs: every layout the contract allows, and one clear line for anything else."""

import numpy as np
import pytest
import tifffile

from fieldcal.errors import ImageError
from fieldcal.measure.imageio import probe_image, read_image

RNG = np.random.default_rng(0)
IMG16 = RNG.integers(0, 65535, (120, 160), dtype=np.uint16)


@pytest.mark.parametrize("kw", [
    {},                                              # striped, uncompressed
    {"tile": (64, 64), "compression": "zstd"},      # tiled, zstd
    {"compression": "deflate", "rowsperstrip": 7},  # striped, deflate
    {"compression": "lzw"},
    {"bigtiff": True, "tile": (32, 32)},
])
def test_reads_16bit_layouts_exactly(tmp_path, kw):
    p = tmp_path / "a.tif"
    tifffile.imwrite(p, IMG16, **kw)
    out = read_image(p, expect_size=(160, 120))
    assert out.dtype == np.uint16 and np.array_equal(out, IMG16)


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
def test_bad_files_give_one_line_naming_the_file(tmp_path, make, match):
    p = tmp_path / "bad.tif"
    make(p)
    with pytest.raises(ImageError, match=match) as info:
        read_image(p)
    assert str(p) in str(info.value) and "\n" not in str(info.value)


def test_truncated_file_is_reported(tmp_path):
    p = tmp_path / "t.tif"
    tifffile.imwrite(p, IMG16)
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageError, match="t.tif"):
        read_image(p)


def test_wrong_size_and_missing_file(tmp_path):
    tifffile.imwrite(tmp_path / "s.tif", IMG16)
    with pytest.raises(ImageError, match="sensor is 100 x 100"):
        read_image(tmp_path / "s.tif", expect_size=(100, 100))
    with pytest.raises(ImageError, match="file not found"):
        probe_image(tmp_path / "nope.tif")
