"""Coded targets: ArUco ids and centres, the 16 -> 8 bit stretch, and exclusion of discs.

Markers are drawn here with exact truth: the canonical marker (OpenCV's
``generateImageMarker``) mapped through a homography, 10 x 10 samples per pixel, a
Gaussian PSF and noise; the true centre is the image of the marker's centre, the true
corners the images of its outer corners.
"""

import math

import cv2
import numpy as np
import pytest
import tifffile
from scipy import ndimage

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import InputError
from fieldcal.measure.coded import (
    detect_aruco,
    diagonal_crossing,
    marker_exclusion_polygons,
    to_uint8,
)
from fieldcal.measure.targets import measure_image

CELLS = {}


def marker_cells(code, dictionary="DICT_4X4_1000"):
    """(6, 6) bool, True = black, row 0 at the top (OpenCV's canonical image)."""
    if code not in CELLS:
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
        CELLS[code] = cv2.aruco.generateImageMarker(d, code, 6, borderBits=1) < 128
    return CELLS[code]


def homography(centre, side_px, angle_deg, tilt=(0.0, 0.0)):
    """Marker cell coordinates (x right, y down, [0, 6]^2) -> pixel coordinates."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    k = side_px / 6.0
    A = np.array([[k * c, -k * s, 0.0], [k * s, k * c, 0.0], [0.0, 0.0, 1.0]])
    T0 = np.array([[1.0, 0.0, -3.0], [0.0, 1.0, -3.0], [0.0, 0.0, 1.0]])       # centre at 0
    P = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [tilt[0], tilt[1], 1.0]])  # perspective
    T1 = np.array([[1.0, 0.0, centre[0]], [0.0, 1.0, centre[1]], [0.0, 0.0, 1.0]])
    return T1 @ A @ P @ T0


def apply_h(H, xy):
    p = np.c_[xy, np.ones(len(xy))] @ H.T
    return p[:, :2] / p[:, 2:]


def render_markers(shape, markers, *, white=42000.0, black=3000.0, bg=30000.0, psf=0.8,
                   noise_dn=200.0, seed=0, supersample=16):
    """uint16 image of markers [(code, H)], each on white paper with a one-cell quiet zone."""
    rng = np.random.default_rng(seed)
    Hh, Ww = shape
    img = np.full(shape, bg)
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    for code, H in markers:
        outline = apply_h(H, np.array([[-1.0, -1.0], [7.0, -1.0], [7.0, 7.0], [-1.0, 7.0]]))
        u0, v0 = np.floor(outline.min(0)).astype(int) - 2
        u1, v1 = np.ceil(outline.max(0)).astype(int) + 3
        uu = (np.arange(u0, u1)[:, None] + off[None, :]).ravel()
        vv = (np.arange(v0, v1)[:, None] + off[None, :]).ravel()
        U, V = np.meshgrid(uu, vv)
        q = apply_h(np.linalg.inv(H), np.c_[U.ravel(), V.ravel()])
        x, y = q[:, 0], q[:, 1]
        paper = (x >= -1) & (x < 7) & (y >= -1) & (y < 7)
        inside = (x >= 0) & (x < 6) & (y >= 0) & (y < 6)
        ink = np.zeros(x.size, bool)
        ink[inside] = marker_cells(code)[np.floor(y[inside]).astype(int), np.floor(x[inside]).astype(int)]
        # each sample: the paper's value where the paper is, the background elsewhere
        win = np.repeat(np.repeat(img[v0:v1, u0:u1], s, axis=0), s, axis=1).ravel()
        val = np.where(paper, np.where(ink, black, white), win)
        img[v0:v1, u0:u1] = val.reshape(v1 - v0, s, u1 - u0, s).mean(axis=(1, 3))
    img = ndimage.gaussian_filter(img, psf, truncate=5.0)
    img += rng.normal(0.0, noise_dn, shape)
    return np.clip(np.rint(img), 0, 65535).astype(np.uint16)


def truth(H):
    return apply_h(H, np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])), apply_h(H, np.array([[3.0, 3.0]]))[0]


@pytest.fixture(scope="module")
def marker_scene():
    rng = np.random.default_rng(1)
    markers = []
    for k, code in enumerate([3, 17, 250, 999, 512, 42]):
        centre = (120 + 230 * (k % 3) + rng.uniform(-5, 5), 120 + 240 * (k // 3) + rng.uniform(-5, 5))
        H = homography(centre, rng.uniform(110, 140), rng.uniform(-180, 180),
                       tilt=rng.uniform(-1e-3, 1e-3, 2))
        markers.append((code, H))
    img = render_markers((480, 700), markers, seed=2, supersample=10)
    return img, markers


# --------------------------------------------------------------------------------------
def test_to_uint8_stretches_percentiles_and_passes_8bit_through():
    rng = np.random.default_rng(0)
    img = rng.integers(10000, 20000, (200, 300)).astype(np.uint16)
    img[:10, :10] = 0
    img[-10:, -10:] = 65535
    out = to_uint8(img)
    assert out.dtype == np.uint8 and out.shape == img.shape
    assert out[:10, :10].max() == 0 and out[-10:, -10:].min() == 255    # saturate outside
    mid = img[50:150, 50:250].astype(float)
    o = out[50:150, 50:250].astype(float)
    assert np.corrcoef(mid.ravel(), o.ravel())[0, 1] > 0.999             # linear inside
    assert 0 <= o.min() < 10 and 245 < o.max() <= 255                   # 0.5-99.5 % -> 0-255
    img8 = rng.integers(0, 255, (20, 20)).astype(np.uint8)
    assert to_uint8(img8) is img8


def test_diagonal_crossing_of_a_perspective_square():
    H = homography((50.0, 60.0), 80.0, 25.0, tilt=(2e-3, -1e-3))
    corners, centre = truth(H)
    assert np.allclose(diagonal_crossing(corners[None])[0], centre, atol=1e-9)


@pytest.mark.parametrize("refine", ["edges", "subpix"])
def test_ids_and_centres(marker_scene, refine):
    img, markers = marker_scene
    t = detect_aruco(img, refine=refine, image_name="images/m.tif")
    assert t.schema.equals(arrow_schema("measurements"), check_metadata=False)
    assert sorted(t["code"].to_pylist()) == sorted(c for c, _ in markers)
    assert set(t["kind"].to_pylist()) == {"aruco"} and set(t["method"].to_pylist()) == {"aruco"}
    errs, cerrs = [], []
    for row in t.to_pylist():
        H = dict(markers)[row["code"]]
        corners, centre = truth(H)
        errs.append(np.array([row["u_px"], row["v_px"]]) - centre)
        cerrs.append(np.array(row["corners_px"]).reshape(4, 2) - corners)
        side = np.linalg.norm(corners - np.roll(corners, -1, 0), axis=1).mean()
        assert row["diameter_px"] == pytest.approx(side, abs=0.5)
        assert row["snr"] > 100 and not row["truncated"] and not row["saturated"]
    e, ec = np.array(errs), np.array(cerrs).reshape(-1, 2)
    rms_c = float(np.sqrt(np.mean(np.sum(e**2, 1))))
    rms_k = float(np.sqrt(np.mean(np.sum(ec**2, 1))))
    print(f"\n{refine}: centre rms {rms_c:.4f} px, corner rms {rms_k:.4f} px")
    if refine == "edges":
        assert rms_c < 0.02 and rms_k < 0.03      # measured ~0.005 / ~0.01 at SNR ~200
    else:
        assert rms_c < 0.1 and rms_k < 0.3        # cornerSubPix: corners pulled by the blur


def test_downscaled_detection_agrees_with_full_resolution():
    # markers of ~190 px (the paper's 184 px): detected on a reduced image, refined at full
    # resolution, they land where full-resolution detection puts them
    rng = np.random.default_rng(5)
    markers = [(code, homography((170 + 280 * k + rng.uniform(-3, 3), 170 + rng.uniform(-3, 3)),
                                 rng.uniform(180, 200), rng.uniform(-180, 180)))
               for k, code in enumerate([7, 333, 999])]
    img = render_markers((340, 900), markers, seed=6, supersample=8)
    found = {}
    for ds in (1, 2, 3):
        t = detect_aruco(img, downscale=ds)
        found[ds] = {r["code"]: np.array([r["u_px"], r["v_px"]]) for r in t.to_pylist()}
        assert sorted(found[ds]) == [7, 333, 999]
    for ds in (2, 3):
        for k, uv in found[ds].items():
            centre = truth(dict(markers)[k])[1]
            assert np.linalg.norm(uv - found[1][k]) < 0.02          # both refined at full res
            assert np.linalg.norm(uv - centre) < 0.05     # 8 x 8 samples quantise the edges


def test_no_markers_and_bad_arguments():
    flat = np.full((100, 100), 2000, np.uint16)
    t = detect_aruco(flat)
    assert t.num_rows == 0 and t.schema.equals(arrow_schema("measurements"), check_metadata=False)
    with pytest.raises(InputError, match="unknown ArUco dictionary 'DICT_9X9'"):
        detect_aruco(flat, dictionary="DICT_9X9")
    with pytest.raises(InputError, match="refine must be 'edges' or 'subpix'"):
        detect_aruco(flat, refine="contour")
    with pytest.raises(InputError, match="downscale must be an integer"):
        detect_aruco(flat, downscale=0)


def test_measure_image_reports_markers_and_no_discs_inside_them(tmp_path, marker_scene):
    from tests.measure.test_targets import ellipse_coverage

    img, markers = marker_scene
    discs = np.array([[330.5, 330.2], [620.0, 30.7], [20.3, 420.1]])
    cov = sum(ellipse_coverage(img.shape, c, 9.0) for c in discs)
    cov = ndimage.gaussian_filter(cov, 0.8)
    both = np.rint(img * (1.0 - 0.9 * cov)).astype(np.uint16)
    p = tmp_path / "scene.tif"
    tifffile.imwrite(p, both)
    t = measure_image(p, polarity="dark", coded={"type": "aruco", "dictionary": "DICT_4X4_1000"},
                      name="images/scene.tif")
    kinds = t["kind"].to_pylist()
    assert kinds.count("aruco") == len(markers)
    assert t["blob"].to_pylist() == list(range(t.num_rows))
    disc_rows = [r for r in t.to_pylist() if r["kind"] == "disc"]
    uv = np.array([[r["u_px"], r["v_px"]] for r in disc_rows]).reshape(-1, 2)
    # every disc reported lies outside the markers, and is one of the drawn discs
    polys = marker_exclusion_polygons(t)
    assert len(polys) == len(markers)
    for q in uv:
        assert np.min(np.linalg.norm(discs - q, axis=1)) < 0.5
    # without the markers' exclusion, the marker cells would give no disc either (shape filter)
    t2 = measure_image(p, polarity="dark")
    assert set(t2["kind"].to_pylist()) <= {"disc"}
    for r in t2.to_pylist():
        assert np.min(np.linalg.norm(discs - [r["u_px"], r["v_px"]], axis=1)) < 0.5


def test_rendered_paper_markers():
    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.render import render_image, scaled_field

    sf = scaled_field(paper_field(), 0.25)
    r = render_image(sf, 5, seed=3)
    tr = r.truth.to_pylist()
    want = {row["code"]: row for row in tr if row["kind"] == "aruco" and row["fully_inside"]}
    t = detect_aruco(r.pixels)
    got = {row["code"]: row for row in t.to_pylist()}
    assert set(want) <= set(got) and len(want) >= 3
    assert set(got) <= {row["code"] for row in tr if row["kind"] == "aruco"}   # no wrong ids
    e = np.array([[got[c]["u_px"] - want[c]["u_ellipse_px"], got[c]["v_px"] - want[c]["v_ellipse_px"]]
                  for c in want])
    rms_c = float(np.sqrt(np.mean(np.sum(e**2, 1))))
    print(f"\nrendered paper image 5: {len(want)} markers, centre rms {rms_c:.4f} px")
    # the renderer samples 8 x 8 per pixel, which quantises near-axis-aligned edges to 1/8 px:
    # ~0.03 px per side; well within 0.1 px here
    assert rms_c < 0.1
