"""Bad images, as the flow meets them: ``pipeline.measure`` per image, then ``pipeline.solve``.

Every kind of bad image the reliability issue lists (truncated, zero bytes, not a TIFF,
float or 32-bit samples, a header claiming a gigantic size, the wrong size for the sensor,
all black, saturated) must give one line naming the file and the reason
(:class:`~fieldcal.errors.ImageError`); the flow then leaves the image out and goes on
(the calibration uses the good images and lists the bad ones with their reasons), and a
session with no usable image stops with a :class:`~fieldcal.errors.GeometryError` that
names them. A header claiming 100000 x 100000 16-bit pixels is refused without allocating
them. Goniometer frames are never fatal: ``measure`` flags them instead.

The field session is the wide-angle scenario at raster scale 0.15 (900 x 600 px), four
rendered images (~3 s); the goniometer session is the Canon scenario at 1/8 scale (~1 s).
"""

import io
import json
import re
import shutil
import struct
import tracemalloc

import cv2
import numpy as np
import pytest
import tifffile

from fieldcal import pipeline
from fieldcal.errors import GeometryError, ImageError
from fieldcal.measure.imageio import MAX_PIXELS, read_image
from fieldcal.measure.targets import MAX_SATURATED_FRACTION
from fieldcal.synthetic.field import wide_field
from fieldcal.synthetic.goniometer import write_session
from fieldcal.synthetic.render import scaled_field
from fieldcal.synthetic.session_writer import write_field_session

W, H = 900, 600          # the field session's sensor (wide scenario at raster scale 0.15)


# --------------------------------------------------------------------------------------
# hand-made TIFF headers
# --------------------------------------------------------------------------------------
def crafted_tiff(width, height, *, bits=16, samples=1, depth=None, data=b"\0" * 64) -> bytes:
    """A classic little-endian TIFF of one strip whose header says what we like.

    The pixel data is only ``data`` (64 bytes by default), whatever the header claims.
    """
    tags = [(256, 4, width), (257, 4, height), (258, 3, bits), (259, 3, 1), (262, 3, 1),
            (273, 4, 0), (277, 3, samples), (278, 4, height), (279, 4, len(data))]
    if depth is not None:
        tags.append((32997, 4, depth))                    # SGI ImageDepth: a volume
    tags.sort()
    data_offset = 8 + 2 + 12 * len(tags) + 4
    out = bytearray(b"II*\0" + struct.pack("<I", 8) + struct.pack("<H", len(tags)))
    for tag, typ, value in tags:
        value = data_offset if tag == 273 else value
        out += struct.pack("<HHIHH" if typ == 3 else "<HHII", tag, typ, 1, *((value, 0) if typ == 3 else (value,)))
    return bytes(out + struct.pack("<I", 0) + data)


def tiff_bytes(array, **kw) -> bytes:
    buf = io.BytesIO()
    tifffile.imwrite(buf, array, **kw)
    return buf.getvalue()


# every kind of bad image: (name, make(good pixels, good file bytes) -> bytes or None, reason)
BAD = [
    ("truncated", lambda px, raw: raw[: len(raw) // 2], r"cannot decode pixels .*truncated or corrupt"),
    ("zero_bytes", lambda px, raw: b"", r"empty file \(0 bytes\)"),
    ("not_a_tiff", lambda px, raw: b"P5\n900 600\n65535\n" + px.tobytes(), r"not a readable TIFF"),
    ("png", lambda px, raw: cv2.imencode(".png", px)[1].tobytes(), r"not a readable TIFF"),
    ("float32", lambda px, raw: tiff_bytes(px.astype(np.float32)), r"unsupported sample type float32"),
    ("uint32", lambda px, raw: tiff_bytes(px.astype(np.uint32)), r"unsupported sample type uint32"),
    ("int16", lambda px, raw: tiff_bytes((px // 2).astype(np.int16)), r"unsupported sample type int16"),
    ("two_samples", lambda px, raw: tiff_bytes(np.stack([px, px], -1), photometric="minisblack",
                                               planarconfig="contig"),
     r"unsupported number of samples per pixel \(2\)"),
    ("gigantic_header", lambda px, raw: crafted_tiff(100_000, 100_000),
     r"implausible image size 100000 x 100000 in the header"),
    ("volume_header", lambda px, raw: crafted_tiff(W, H, depth=100_000),
     r"a volume of 100000 planes \(ImageDepth\) is not a single 2-D image"),
    ("wrong_size", lambda px, raw: tiff_bytes(px[: H // 2, : W // 2]),
     rf"image is {W // 2} x {H // 2} px, the session's sensor is {W} x {H} px"),
    ("all_black", lambda px, raw: tiff_bytes(np.zeros_like(px)), r"blank image: every pixel is 0 \(all black\)"),
    ("saturated", lambda px, raw: tiff_bytes(np.full_like(px, 65535)),
     r"blank image: every pixel is 65535 \(saturated\)"),
    ("saturated_8bit", lambda px, raw: tiff_bytes(np.full(px.shape, 255, np.uint8)),
     r"blank image: every pixel is 255 \(saturated\)"),
    ("over_exposed", lambda px, raw: tiff_bytes(np.clip(px.astype(float) * 20, 0, 65535).astype(np.uint16)),
     r"over-exposed: \d+ % of the pixels are saturated at 65535"),
    ("missing", lambda px, raw: None, r"file not found"),
]


@pytest.fixture(scope="module")
def field(tmp_path_factory):
    """A field session of four good rendered images and one of every bad kind, prepared."""
    sf = scaled_field(wide_field(seed=3), 0.15)
    assert (sf.camera.sensor.width_px, sf.camera.sensor.height_px) == (W, H)
    folder = tmp_path_factory.mktemp("field") / "wall"
    info = write_field_session(folder, sf, image_indices=[0, 3, 6, 9], seed=1, compression_mix=False)
    good = info["images"]
    raw = (folder / good[0]).read_bytes()
    px = tifffile.imread(folder / good[0])
    assert px.dtype == np.uint16 and 0 < px.min() < px.max() < 65535   # a normal exposure
    manifest = json.loads((folder / "session.json").read_text())
    for name, make, _ in BAD:
        data = make(px, raw)
        if data is not None:
            (folder / "images" / f"bad_{name}.tif").write_bytes(data)
        manifest["images"].append({"file": f"images/bad_{name}.tif"})
    (folder / "session.json").write_text(json.dumps(manifest))
    prepared = pipeline.prepare(folder)
    return {"sf": sf, "folder": folder, "good": good, "prepared": prepared}


def measure_all(prepared):
    """What the flow does: measure every image, leave out (and report) those that raise."""
    measurements, left_out = {}, []
    for name in prepared.to_measure:
        try:
            measurements[name] = pipeline.measure(prepared, name)
        except ImageError as err:
            left_out.append({"image": name, "status": "left out", "reason": str(err)})
    return measurements, left_out


# --------------------------------------------------------------------------------------
# field images
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("name, reason", [(n, r) for n, _, r in BAD], ids=[n for n, _, _ in BAD])
def test_each_bad_image_is_one_line_naming_the_file_and_the_reason(field, name, reason):
    path = field["folder"] / "images" / f"bad_{name}.tif"
    with pytest.raises(ImageError, match=reason) as info:
        pipeline.measure(field["prepared"], f"images/bad_{name}.tif")
    text = str(info.value)
    assert text.startswith(f"{path}: ") and "\n" not in text
    assert info.value.where == str(path)


def test_good_images_are_measured_and_a_normal_exposure_is_not_refused(field):
    for name in field["good"]:
        table = pipeline.measure(field["prepared"], name)
        assert table.num_rows >= 50                   # the wide wall: 100-200 targets per image
    # a bright exposure with a few saturated pixels (targets' highlights) is still measured
    px = tifffile.imread(field["folder"] / field["good"][0])
    bright = px.astype(np.int64) + (65535 - int(np.percentile(px, 99.5)))
    share = np.mean(np.clip(bright, 0, 65535) == 65535)
    assert 0.001 < share < MAX_SATURATED_FRACTION
    p = field["folder"] / "images" / "bright.tif"
    tifffile.imwrite(p, np.clip(bright, 0, 65535).astype(np.uint16))
    try:
        table = pipeline.measure(field["prepared"], "images/bright.tif")
    finally:
        p.unlink()
    assert table.num_rows >= 50


def test_bad_images_are_left_out_with_their_reason_and_the_run_goes_on(field, tmp_path):
    prepared = field["prepared"]
    measurements, left_out = measure_all(prepared)
    assert sorted(measurements) == sorted(field["good"])
    assert {r["image"] for r in left_out} == {f"images/bad_{n}.tif" for n, _, _ in BAD}
    out = pipeline.solve(prepared, measurements, fingerprint_="sha256:" + "0" * 64, left_out=left_out)
    doc = out.document
    assert doc["stats"]["n_images"] == len(field["good"])
    assert set(doc["stats"]["left_out_images"]) == {f"images/bad_{n}.tif" for n, _, _ in BAD}
    by_image = {r["image"]: r["reason"] for r in out.left_out}
    for name, _, reason in BAD:
        assert re.search(reason, by_image[f"images/bad_{name}.tif"])
    # the bad images change nothing: the same calibration as a session of the good images alone
    folder = tmp_path / "good-only"
    shutil.copytree(field["folder"], folder)
    manifest = json.loads((folder / "session.json").read_text())
    manifest["images"] = [{"file": n} for n in field["good"]]
    (folder / "session.json").write_text(json.dumps(manifest))
    clean = pipeline.prepare(folder)
    ref = pipeline.solve(clean, {n: pipeline.measure(clean, n) for n in clean.to_measure},
                         fingerprint_="sha256:" + "0" * 64).document
    assert ref["stats"]["left_out_images"] == []
    for k, v in ref["parameters"].items():
        assert doc["parameters"][k] == pytest.approx(v, rel=1e-9, abs=1e-15), k
    assert abs(doc["parameters"]["f_mm"] - field["sf"].camera.f_mm) < 0.05   # 0.2 %: a sane calibration


def test_a_session_of_only_bad_images_stops_with_a_diagnosis_naming_them(field, tmp_path):
    folder = tmp_path / "all-bad"
    shutil.copytree(field["folder"], folder)
    manifest = json.loads((folder / "session.json").read_text())
    manifest["images"] = [im for im in manifest["images"] if im["file"].startswith("images/bad_")]
    (folder / "session.json").write_text(json.dumps(manifest))
    prepared = pipeline.prepare(folder)
    measurements, left_out = measure_all(prepared)
    assert measurements == {} and len(left_out) == len(BAD)
    with pytest.raises(GeometryError, match=rf"only 0 of {len(BAD)} images could be identified") as info:
        pipeline.solve(prepared, measurements, fingerprint_="sha256:" + "0" * 64, left_out=left_out)
    text = str(info.value)
    assert "\n" not in text and "images/bad_truncated.tif: not measured" in text


# --------------------------------------------------------------------------------------
# a header claiming a gigantic size: refused without allocating it
# --------------------------------------------------------------------------------------
def _peak_bytes(fn):
    tracemalloc.start()
    try:
        fn()
    except ImageError:
        pass
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


def test_gigantic_header_is_refused_without_allocating_it(field, tmp_path):
    claimed_bytes = 100_000 * 100_000 * 2
    assert 100_000 * 100_000 > MAX_PIXELS
    prepared = field["prepared"]
    peak = _peak_bytes(lambda: pipeline.measure(prepared, "images/bad_gigantic_header.tif"))
    # tracemalloc sees numpy's buffers: reading one good 900 x 600 16-bit image shows them
    control = _peak_bytes(lambda: read_image(field["folder"] / field["good"][0]))
    assert control >= W * H * 2
    assert peak < 5_000_000 < claimed_bytes          # 5 MB: headers and tifffile's bookkeeping
    # the same without a sensor to compare with (library use): the header alone is refused
    p = tmp_path / "huge.tif"
    p.write_bytes(crafted_tiff(100_000, 100_000))
    assert _peak_bytes(lambda: read_image(p)) < 5_000_000
    with pytest.raises(ImageError, match="implausible image size"):
        read_image(p)
    # a volume header of the sensor's size: the pixel count alone would not bound it
    v = tmp_path / "volume.tif"
    v.write_bytes(crafted_tiff(W, H, depth=100_000))
    assert _peak_bytes(lambda: read_image(v, expect_size=(W, H))) < 5_000_000
    with pytest.raises(ImageError, match="a volume of 100000 planes"):
        read_image(v, expect_size=(W, H))


# --------------------------------------------------------------------------------------
# goniometer frames: flagged, never fatal
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def gonio(tmp_path_factory):
    folder = tmp_path_factory.mktemp("gonio") / "lab"
    truth = write_session(folder, "canon5d2", seed=2, raster_scale=0.125)
    return truth, pipeline.prepare(folder)


GONIO_BAD = [
    ("truncated", lambda good: good.read_bytes()[:300], "unreadable", r"cannot decode pixels|not a readable TIFF"),
    ("zero_bytes", lambda good: b"", "unreadable", r"empty file \(0 bytes\)"),
    ("float32", lambda good: tiff_bytes(tifffile.imread(good).astype(np.float32)), "unreadable",
     r"unsupported sample type float32"),
    ("gigantic_header", lambda good: crafted_tiff(100_000, 100_000), "unreadable", r"implausible image size"),
    ("wrong_size", lambda good: tiff_bytes(tifffile.imread(good)[:100, :100]), "unreadable",
     r"image is 100 x 100 px, the session's sensor is"),
    ("all_black", lambda good: tiff_bytes(np.zeros_like(tifffile.imread(good))), "missing", r"no spot"),
    ("saturated", lambda good: tiff_bytes(np.full_like(tifffile.imread(good), 65535)), "missing", r"no spot"),
]


@pytest.mark.parametrize("name, make, flag, reason", GONIO_BAD, ids=[g[0] for g in GONIO_BAD])
def test_bad_goniometer_frames_are_flagged_with_their_reason(gonio, name, make, flag, reason):
    truth, prepared = gonio
    frame = prepared.to_measure[0]
    path = prepared.session.image_path(frame)
    good = path.read_bytes()
    try:
        bad = make(path)
        path.write_bytes(bad)
        row = pipeline.measure(prepared, frame).to_pylist()[0]
    finally:
        path.write_bytes(good)
    assert row["file"] == frame and row["flag"] == flag
    assert re.search(reason, row["reason"]) and "\n" not in row["reason"]
    assert np.isnan(row["u_px"]) and np.isnan(row["v_px"])
    assert pipeline.measure(prepared, frame).to_pylist()[0]["flag"] == "ok"      # the original
