"""Corrected images: the remap tables against the model, an analytic image through the whole
chain, and the TIFF in and out."""

import json

import numpy as np
import pytest
import tifffile

from fieldcal.errors import ImageError, InputError
from fieldcal.model.camera import Camera, Sensor, correct
from fieldcal.products.undistort import output_camera_matrix, undistort_file, undistort_image, undistort_maps
from fieldcal.synthetic.field import WIDE_ANGLE

CAM = Camera.from_dict(Sensor(600, 400, 39.0), WIDE_ANGLE)      # ~3 px of barrel distortion


def _output_pixel_of(camera, uv_in, K):
    """Where the ray of input pixels lands in the corrected image (the model, closed form)."""
    q = correct(camera.sensor.pixel_to_mm(uv_in), camera.params)      # ideal point [mm], y up
    scale = camera.f_mm / K[0, 0]
    return np.stack([q[..., 0] / scale + K[0, 2], -q[..., 1] / scale + K[1, 2]], axis=-1)


def test_maps_send_each_output_pixel_to_the_input_pixel_of_its_ray():
    mu, mv, K = undistort_maps(CAM)
    assert mu.shape == (400, 600) and mu.dtype == np.float32
    back = _output_pixel_of(CAM, np.stack([mu, mv], -1).astype(float), K)
    vv, uu = np.mgrid[0:400, 0:600]
    inside = (mu >= 0) & (mu <= 599) & (mv >= 0) & (mv <= 399)
    assert inside.mean() > 0.98
    # float32 maps hold ~3e-5 px at these magnitudes: 1e-3 px is generous
    assert np.abs(back[..., 0] - uu)[inside].max() < 1e-3
    assert np.abs(back[..., 1] - vv)[inside].max() < 1e-3
    # the distortion is real: the maps are not the identity
    assert np.abs(mu - uu).max() > 1.0


def test_rows_of_the_maps_are_the_same_as_the_whole():
    mu, mv, _ = undistort_maps(CAM)
    mu2, mv2, _ = undistort_maps(CAM, rows=(100, 137))
    np.testing.assert_array_equal(mu2, mu[100:137])
    np.testing.assert_array_equal(mv2, mv[100:137])
    with pytest.raises(InputError, match="rows must satisfy"):
        undistort_maps(CAM, rows=(10, 500))


def _pattern(u, v):
    return 2000.0 + 1500.0 * np.sin(u / 11.0) * np.cos(v / 9.0)


def test_an_analytic_image_comes_out_undistorted():
    K = output_camera_matrix(CAM)
    vv, uu = np.mgrid[0:400, 0:600].astype(float)
    out_uv = _output_pixel_of(CAM, np.stack([uu, vv], -1), K)
    taken = _pattern(out_uv[..., 0], out_uv[..., 1])     # what the distorting camera records
    out, K2 = undistort_image(taken.astype(np.float32), CAM, interpolation="cubic")
    np.testing.assert_array_equal(K2, K)
    mu, mv, _ = undistort_maps(CAM)
    inside = (mu > 2) & (mu < 597) & (mv > 2) & (mv < 397)
    err = np.abs(out - _pattern(uu, vv))[inside]
    # cubic interpolation of a pattern of period 2 pi 9 px: 1 % of its 1500 amplitude
    assert err.max() < 15.0
    # without the correction the image is off by the distortion (tens of grey levels)
    assert np.abs(taken - _pattern(uu, vv))[inside].max() > 10 * err.max()


def test_undistort_file_keeps_dtype_and_channels_and_records_the_camera(tmp_path):
    rng = np.random.default_rng(0)
    gray = rng.integers(0, 65535, (400, 600), dtype=np.uint16)
    rgb = rng.integers(0, 255, (400, 600, 3), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "g.tif", gray)
    tifffile.imwrite(tmp_path / "c.tif", rgb, photometric="rgb")
    info = undistort_file(CAM, tmp_path / "g.tif", tmp_path / "g_out.tif", provenance={"version": "v1"})
    out = tifffile.imread(tmp_path / "g_out.tif")
    assert out.dtype == np.uint16 and out.shape == (400, 600)
    with tifffile.TiffFile(tmp_path / "g_out.tif") as tif:
        meta = json.loads(tif.pages.first.description)
    assert meta["K"] == info["K"] and meta["provenance"] == {"version": "v1"}
    assert meta["K"][0][0] == pytest.approx(CAM.f_mm / CAM.sensor.pixel_mm)
    undistort_file(CAM, tmp_path / "c.tif", tmp_path / "c_out.tif", interpolation="nearest")
    out = tifffile.imread(tmp_path / "c_out.tif")
    assert out.dtype == np.uint8 and out.shape == (400, 600, 3)
    # nearest neighbour only moves pixels: every output value exists in the input channel
    assert np.isin(out[..., 1], rgb[..., 1]).all()


def test_undistort_refuses_images_of_another_size_and_unknown_options(tmp_path):
    tifffile.imwrite(tmp_path / "small.tif", np.zeros((40, 60), np.uint8))
    with pytest.raises(ImageError, match="image is 60 x 40 px but the calibration's sensor is 600 x 400"):
        undistort_file(CAM, tmp_path / "small.tif", tmp_path / "o.tif")
    with pytest.raises(ImageError, match="file not found"):
        undistort_file(CAM, tmp_path / "missing.tif", tmp_path / "o.tif")
    with pytest.raises(InputError, match="interpolation must be one of"):
        undistort_image(np.zeros((400, 600)), CAM, interpolation="area")
    with pytest.raises(InputError, match="f_px must be a positive number"):
        output_camera_matrix(CAM, -5.0)


def test_undistort_file_keeps_a_two_channel_image_and_refuses_unsupported_dtypes(tmp_path):
    two = np.random.default_rng(1).integers(0, 255, (400, 600, 2), dtype=np.uint8)
    tifffile.imwrite(tmp_path / "two.tif", two, photometric="minisblack", planarconfig="contig")
    undistort_file(CAM, tmp_path / "two.tif", tmp_path / "two_out.tif")
    assert tifffile.imread(tmp_path / "two_out.tif").shape == (400, 600, 2)
    with pytest.raises(ImageError, match="cv2.remap cannot resample uint32 images"):
        undistort_image(np.zeros((400, 600), np.uint32), CAM)
