"""Disc targets: detection, sub-pixel centres, quality figures and filters.

Most tests run on small images made here, with exact truth: area-sampled ellipses
(supersampled coverage with an anti-aliased edge), a Gaussian PSF and Gaussian noise. The
accuracy figures of the issue are measured on the project's renderer
(``fieldcal.synthetic.render``) at a reduced raster, against the exact image of each centre.
"""

import math

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
import tifffile
from scipy import ndimage
from scipy.spatial import cKDTree

from fieldcal.contract.schemas import arrow_schema
from fieldcal.errors import ImageError, InputError
from fieldcal.measure.disc_windows import hat_sums, squared_centroid
from fieldcal.measure.discs import DEFAULT_METHOD, METHODS, detect_targets
from fieldcal.measure.imageio import read_file
from fieldcal.measure.targets import measure_image
from tests.measure.peers import opencv_blob_centres

BG, FIG = 40000.0, 4000.0


# --------------------------------------------------------------------------------------
# test images with exact truth
# --------------------------------------------------------------------------------------
def ellipse_coverage(shape, centre, a, b=None, angle_deg=0.0, supersample=16):
    """Fraction of each pixel covered by an ellipse (pixel (u, v) covers [u-.5, u+.5] x ...).

    Supersampled; each sample is anti-aliased by its signed distance to the outline
    (first order), which makes the coverage exact to ~1e-4 px in position.
    """
    b = a if b is None else b
    H, W = shape
    cu, cv = centre
    h = int(math.ceil(max(a, b))) + 2
    u0, v0 = int(math.floor(cu)) - h, int(math.floor(cv)) - h
    n = 2 * h + 2
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    uu = (u0 + np.arange(n))[:, None] + off[None, :]           # (n, s)
    vv = (v0 + np.arange(n))[:, None] + off[None, :]
    x = uu.reshape(1, n * s) - cu
    y = vv.reshape(n * s, 1) - cv
    c, sn = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    xr, yr = c * x + sn * y, -sn * x + c * y
    F = (xr / a) ** 2 + (yr / b) ** 2 - 1.0
    grad = np.hypot(2 * xr / a**2, 2 * yr / b**2) + 1e-12
    cov = np.clip(0.5 - F / grad * s, 0.0, 1.0)
    cov = cov.reshape(n, s, n, s).mean(axis=(1, 3))
    out = np.zeros(shape)
    r0, r1 = max(v0, 0), min(v0 + n, H)
    c0, c1 = max(u0, 0), min(u0 + n, W)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = cov[r0 - v0:r1 - v0, c0 - u0:c1 - u0]
    return out


def render_discs(shape, centres, radius=12.0, *, minor=None, angles=None, psf=0.8, bg=BG,
                 fig=FIG, noise_dn=200.0, seed=0, clip=65535):
    """uint16 image of dark (fig < bg) or bright (fig > bg) ellipses, blurred, noisy."""
    rng = np.random.default_rng(seed)
    n = len(centres)
    radius = np.broadcast_to(np.asarray(radius, float), (n,))
    minor = radius if minor is None else np.broadcast_to(np.asarray(minor, float), (n,))
    angles = np.zeros(n) if angles is None else np.broadcast_to(np.asarray(angles, float), (n,))
    cov = np.zeros(shape)
    for (cu, cv), a, b, t in zip(centres, radius, minor, angles, strict=True):
        cov += ellipse_coverage(shape, (cu, cv), a, b, t)
    if psf > 0:
        cov = ndimage.gaussian_filter(cov, psf, mode="constant", truncate=5.0)
    img = bg + (fig - bg) * cov
    if noise_dn > 0:
        img = img + rng.normal(0.0, noise_dn, shape)
    return np.clip(np.rint(img), 0, clip).astype(np.uint16)


def grid_centres(n_side, pitch, margin, rng):
    """Centres on a grid, each moved by a random sub-pixel offset."""
    g = margin + pitch * np.arange(n_side)
    uu, vv = np.meshgrid(g, g)
    c = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    return c + rng.uniform(-0.5, 0.5, c.shape)


def match(table, truth, radius=2.0):
    """Indices into the table's rows of the nearest detection of each truth point (-1: none)."""
    uv = np.stack([table["u_px"].to_numpy(), table["v_px"].to_numpy()], axis=1)
    if len(uv) == 0:
        return np.full(len(truth), -1), uv
    d, j = cKDTree(uv).query(truth, distance_upper_bound=radius)
    j[~np.isfinite(d)] = -1
    return j, uv


def rms(e):
    """RMS of 2-D errors sqrt(mean(du^2 + dv^2)) [px] (CONTRACT's rmse_px)."""
    return float(np.sqrt(np.mean(np.sum(np.asarray(e) ** 2, axis=1))))


# --------------------------------------------------------------------------------------
# the generator itself
# --------------------------------------------------------------------------------------
def test_generator_coverage_is_exact():
    # the pixel coverage converges (16 vs 64 samples per pixel side agree), has the
    # ellipse's area, and is symmetric about a centre placed on a pixel centre or corner.
    # (The centroid of pixel coverages is *not* the centre in general: pixels cut by the
    # outline weigh their area at the pixel's centre, ~1e-3 px for these sizes; that is
    # part of what the detector has to cope with.)
    rng = np.random.default_rng(1)
    vv, uu = np.mgrid[:64, :64]
    for _ in range(4):
        c = rng.uniform(30, 34, 2)
        a, b, t = rng.uniform(6, 14), rng.uniform(4, 6), rng.uniform(0, 180)
        cov = ellipse_coverage((64, 64), c, a, b, t)
        fine = ellipse_coverage((64, 64), c, a, b, t, supersample=64)
        assert np.abs(cov - fine).max() < 5e-3                    # per pixel, 16 vs 64 samples
        assert cov.sum() == pytest.approx(math.pi * a * b, rel=2e-4)
        for sym in ((32.0, 31.0), (32.5, 30.5)):
            cs = ellipse_coverage((64, 64), sym, a, b, t)
            centroid = np.array([(cs * uu).sum(), (cs * vv).sum()]) / cs.sum()
            assert np.abs(centroid - sym).max() < 1e-9


# --------------------------------------------------------------------------------------
# conventions and the table
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", METHODS)
def test_pixel_convention_disc_at_24_5(method):
    # a disc centred on the corner shared by pixels (24, 24) and (25, 25): the centre of the
    # top-left pixel is (0, 0), so the disc is found at (24.5, 24.5), not (25, 25) or (24, 24)
    img = render_discs((50, 50), [(24.5, 24.5)], radius=10.0, noise_dn=0.0)
    t = detect_targets(img, method=method)
    assert t.num_rows == 1
    assert t["u_px"][0].as_py() == pytest.approx(24.5, abs=1e-3)    # noise-free: exact to 1e-3
    assert t["v_px"][0].as_py() == pytest.approx(24.5, abs=1e-3)
    img = render_discs((60, 50), [(20.0, 33.0)], radius=10.0, noise_dn=0.0)
    t = detect_targets(img, method=method)
    assert (t["u_px"][0].as_py(), t["v_px"][0].as_py()) == pytest.approx((20.0, 33.0), abs=1e-3)


def test_table_has_the_measurements_schema_and_the_image_name():
    img = render_discs((60, 60), [(30.2, 29.7)], radius=9.0)
    t = detect_targets(img, image_name="images/a.tif")
    assert t.schema.equals(arrow_schema("measurements"), check_metadata=False)
    row = t.to_pylist()[0]
    assert row["image"] == "images/a.tif" and row["kind"] == "disc" and row["code"] is None
    assert row["blob"] == 0 and row["method"] == DEFAULT_METHOD
    assert row["corners_px"] is None
    assert row["diameter_px"] == pytest.approx(18.0, abs=0.3)     # the 50 % level of the edge
    assert row["roundness"] == pytest.approx(1.0, abs=0.03)
    assert row["snr"] == pytest.approx((BG - FIG) / 200.0, rel=0.15)
    assert row["contrast"] == pytest.approx(BG - FIG, rel=0.03)
    flat = np.full((40, 40), 1000, np.uint16)
    empty = detect_targets(flat)
    assert empty.num_rows == 0 and empty.schema.equals(t.schema)


# --------------------------------------------------------------------------------------
# accuracy and detection on made images, every method, against OpenCV's blob detector
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def grid_image():
    rng = np.random.default_rng(2)
    centres = grid_centres(7, 52.0, 30.0, rng)
    radius = rng.uniform(10.0, 14.0, len(centres))               # 20-28 px discs
    img = render_discs((372, 372), centres, radius, noise_dn=220.0, seed=3)   # SNR ~165
    return img, centres, radius


@pytest.mark.parametrize("method", METHODS)
def test_accuracy_and_detection_on_a_grid(grid_image, method):
    img, centres, _ = grid_image
    t = detect_targets(img, method=method)
    j, uv = match(t, centres)
    assert (j >= 0).all()                                         # all 49 found
    assert t.num_rows == len(centres)                             # and nothing else
    err = uv[j] - centres
    # 0.02 px is the requirement; at SNR ~165 both methods reach ~0.005 px
    assert rms(err) < 0.01
    ocv = opencv_blob_centres(img)
    jb = cKDTree(ocv).query(centres)[1]
    print(f"\n{method}: rms {rms(err):.4f} px; SimpleBlobDetector rms {rms(ocv[jb] - centres):.4f} px")
    assert rms(err) <= rms(ocv[jb] - centres)                     # at least as accurate


def test_apriori_sigma_matches_the_scatter():
    # 100 discs at SNR ~20: the per-axis scatter of the centres against the a-priori sigma
    rng = np.random.default_rng(4)
    centres = grid_centres(10, 40.0, 24.0, rng)
    img = render_discs((410, 410), centres, 11.0, noise_dn=1800.0, seed=5)
    t = detect_targets(img)
    j, uv = match(t, centres)
    assert (j >= 0).all()
    scatter = np.sqrt(np.mean((uv[j] - centres) ** 2))
    sigma = np.median(t["sigma_px"].to_numpy()[j])
    assert 0.6 < scatter / sigma < 1.5                            # Cramer-Rao: close to 1
    assert 0.01 < sigma < 0.05


@pytest.mark.parametrize("method", METHODS)
def test_ellipses_axes_angle_and_centre(method):
    rng = np.random.default_rng(6)
    centres = grid_centres(4, 60.0, 35.0, rng)
    angles = rng.uniform(0.0, 180.0, len(centres))
    img = render_discs((250, 250), centres, 15.0, minor=6.0, angles=angles, noise_dn=150.0, seed=7)
    t = detect_targets(img, method=method)
    j, uv = match(t, centres)
    assert (j >= 0).all() and t.num_rows == len(centres)
    assert rms(uv[j] - centres) < 0.015                           # oblique discs, SNR ~240
    maj, mnr = t["major_px"].to_numpy()[j], t["minor_px"].to_numpy()[j]
    assert np.abs(maj - 30.0).max() < 0.4 and np.abs(mnr - 12.0).max() < 0.4
    dang = np.abs((t["angle_deg"].to_numpy()[j] - angles + 90.0) % 180.0 - 90.0)
    assert dang.max() < 1.0
    assert np.allclose(t["roundness"].to_numpy()[j], 0.4, atol=0.02)


def test_centroid_upsampling_closed_form_equals_explicit_bilinear_grid():
    # the centroid method's "bilinear interpolation onto a finer grid, squared weights" is
    # computed in closed form; here it is done the long way on an explicit k-times grid
    rng = np.random.default_rng(8)
    Y = rng.uniform(0.0, 1.0, (3, 9, 9)).astype(np.float32)
    Y[:, [0, -1], :] = 0.0
    Y[:, :, [0, -1]] = 0.0
    support = np.ones_like(Y, bool)
    for k in (1, 3, 4):
        cu, cv = squared_centroid(Y, support, k)
        for w in range(3):
            x = np.arange(0, 8 * k + 1) / k                       # fine grid in pixel units
            i0 = np.minimum(np.floor(x).astype(int), 7)
            f = x - i0
            Yw = Y[w].astype(float)
            # bilinear interpolation on the product grid
            A = (Yw[i0][:, i0] * np.outer(1 - f, 1 - f) + Yw[i0 + 1][:, i0] * np.outer(f, 1 - f)
                 + Yw[i0][:, i0 + 1] * np.outer(1 - f, f) + Yw[i0 + 1][:, i0 + 1] * np.outer(f, f))
            W2 = A**2
            ref_u = (W2 * x[None, :]).sum() / W2.sum()
            ref_v = (W2 * x[:, None]).sum() / W2.sum()
            assert cu[w] == pytest.approx(ref_u, abs=1e-6)
            assert cv[w] == pytest.approx(ref_v, abs=1e-6)
    assert hat_sums(None) == pytest.approx((2 / 3, 1 / 6))


# --------------------------------------------------------------------------------------
# polarity, saturation, truncation, clutter, filters
# --------------------------------------------------------------------------------------
def test_polarity():
    rng = np.random.default_rng(9)
    centres = grid_centres(3, 50.0, 30.0, rng)
    bright = render_discs((160, 160), centres, 10.0, bg=3000.0, fig=30000.0, noise_dn=150.0)
    tb = detect_targets(bright, polarity="bright")
    j, uv = match(tb, centres)
    assert (j >= 0).all() and tb.num_rows == 9 and rms(uv[j] - centres) < 0.01
    assert detect_targets(bright, polarity="dark").num_rows == 0   # the gaps are not discs
    dark = render_discs((160, 160), centres, 10.0, noise_dn=150.0)
    assert detect_targets(dark, polarity="bright").num_rows == 0


def test_saturation_flag():
    # bright discs: two overexposed (clipped at 65535), two not
    centres = [(30.3, 30.1), (90.6, 30.4), (30.2, 90.7), (90.1, 90.5)]
    img = render_discs((120, 120), centres[:2], 10.0, bg=2000.0, fig=90000.0, noise_dn=100.0)
    img2 = render_discs((120, 120), centres[2:], 10.0, bg=2000.0, fig=40000.0, noise_dn=100.0)
    img = np.maximum(img, img2)
    t = detect_targets(img, polarity="bright")
    j, _ = match(t, np.array(centres))
    assert (j >= 0).all()
    sat = t["saturated"].to_numpy(zero_copy_only=False)[j]
    assert sat.tolist() == [True, True, False, False]
    # a dark disc on a saturated (blown-out) wall
    img = render_discs((60, 60), [(30.4, 29.6)], 10.0, bg=70000.0, fig=5000.0, noise_dn=100.0)
    assert detect_targets(img)["saturated"][0].as_py() is True


def test_partial_discs_at_the_border_are_flagged_truncated():
    centres = [(4.0, 40.0), (60.0, 2.5), (95.0, 60.0), (40.3, 40.6), (75.7, 30.2)]
    img = render_discs((100, 100), centres, 9.0, noise_dn=150.0)
    t = detect_targets(img)
    j, _ = match(t, np.array(centres), radius=4.0)
    trunc = t["truncated"].to_numpy(zero_copy_only=False)
    found = j >= 0
    assert found[3:].all() and not trunc[j[3:]].any()             # whole discs: not flagged
    assert trunc[j[found[:3].nonzero()[0]]].all()                  # cut by the border: flagged
    assert t.num_rows == found.sum()


def test_clutter_gives_no_false_detections():
    rng = np.random.default_rng(10)
    H, W = 320, 420
    centres = np.array([[60.3, 60.7], [200.2, 250.6], [340.8, 70.1], [330.4, 260.3]])
    img = render_discs((H, W), centres, 11.0, noise_dn=0.0).astype(float)
    clutter = np.zeros((H, W))
    vv, uu = np.mgrid[:H, :W]
    clutter[(np.abs(uu - 0.4 * vv - 120) < 1.5)] = 1.0            # a thin slanted line
    clutter[150:156, 10:300] = 1.0                               # a thick horizontal bar
    clutter[20:44, 150:174] = 1.0                                # squares, 24 and 14 px,
    clutter[230:244, 60:74] = 1.0
    sq = (np.abs((uu - 300) + (vv - 200)) + np.abs((uu - 300) - (vv - 200))) < 20   # and rotated
    clutter[sq] = 1.0
    clutter[250:262, 380:412] = 1.0                              # a 12 x 32 rectangle
    clutter[280:320, 150:260] = 1.0                              # a large dark area
    clutter = ndimage.gaussian_filter(clutter, 0.8)
    img = img - (BG - FIG) * clutter
    img += rng.normal(0, 300.0, img.shape)
    img = np.clip(np.rint(img), 0, 65535).astype(np.uint16)
    for method in METHODS:
        t = detect_targets(img, method=method, return_rejected=True)
        acc = t.filter(pc.equal(t["reject"], ""))
        j, uv = match(acc, centres)
        assert (j >= 0).all()
        assert acc.num_rows == len(centres), acc.select(["u_px", "v_px", "diameter_px",
                                                         "edge_rms_px", "roundness"]).to_pylist()
        assert set(t["reject"].to_pylist()) - {""} <= {"overflow", "shape", "roundness", "small",
                                                        "large", "snr", "contrast", "no fit"}
    # pure noise: nothing
    noise = np.clip(rng.normal(30000, 300, (200, 200)), 0, 65535).astype(np.uint16)
    assert detect_targets(noise).num_rows == 0


def test_diameter_range_and_exclusion_zones():
    centres = np.array([[40.2, 40.6], [120.7, 40.3], [40.5, 120.1], [120.3, 120.8]])
    radii = np.array([3.0, 8.0, 14.0, 30.0])                      # 6, 16, 28, 60 px
    img = render_discs((200, 200), centres, radii, noise_dn=150.0)
    t = detect_targets(img, min_diameter_px=10, max_diameter_px=40)
    j, _ = match(t, centres)
    assert (j >= 0).tolist() == [False, True, True, False]
    t = detect_targets(img, min_diameter_px=5, max_diameter_px=64)
    assert (match(t, centres)[0] >= 0).all()
    square = np.array([[100.0, 100.0], [140.0, 100.0], [140.0, 140.0], [100.0, 140.0]])
    t = detect_targets(img, min_diameter_px=5, max_diameter_px=64, exclude=[square])
    assert (match(t, centres)[0] >= 0).tolist() == [True, True, True, False]


def test_bad_arguments_say_what_is_wrong():
    img = np.zeros((20, 20), np.uint16)
    with pytest.raises(InputError, match="uint8 or uint16, got float32"):
        detect_targets(img.astype(np.float32))
    with pytest.raises(InputError, match="2-D array"):
        detect_targets(np.zeros((4, 20, 20), np.uint16))
    with pytest.raises(InputError, match="polarity must be one of 'dark', 'bright'"):
        detect_targets(img, polarity="black")
    with pytest.raises(InputError, match="method must be one of"):
        detect_targets(img, method="hough")
    with pytest.raises(InputError, match="smaller than min_diameter_px"):
        detect_targets(img, min_diameter_px=20, max_diameter_px=10)


# --------------------------------------------------------------------------------------
# images on disk
# --------------------------------------------------------------------------------------
def test_measure_image_reads_fills_the_name_and_reports_bad_files(tmp_path):
    from fieldcal.model.camera import Sensor

    img = render_discs((80, 100), [(30.3, 40.2), (70.6, 40.9)], 9.0)
    p = tmp_path / "images" / "a.tif"
    p.parent.mkdir()
    tifffile.imwrite(p, img, compression="zstd", tile=(32, 32))
    t = measure_image(p, polarity="dark", sensor=Sensor(100, 80, 5.3), name="images/a.tif")
    assert t.num_rows == 2 and set(t["image"].to_pylist()) == {"images/a.tif"}
    assert t["blob"].to_pylist() == [0, 1]
    # the same from the bytes read once for hashing (the flow's path): the same table
    assert measure_image(read_file(p), polarity="dark", sensor=Sensor(100, 80, 5.3),
                         name="images/a.tif").equals(t)
    with pytest.raises(ImageError, match="the session's sensor is 120 x 80 px"):
        measure_image(p, sensor=Sensor(120, 80, 5.3))
    bad = tmp_path / "bad.tif"
    bad.write_bytes(b"II*\x00garbage")
    with pytest.raises(ImageError, match="bad.tif") as err:
        measure_image(bad)
    assert "\n" not in str(err.value)
    flt = tmp_path / "float.tif"
    tifffile.imwrite(flt, img.astype(np.float32))
    with pytest.raises(ImageError, match="unsupported sample type float32"):
        measure_image(flt)


# --------------------------------------------------------------------------------------
# the figures on rendered paper-like images
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rendered_paper():
    from fieldcal.synthetic.field import paper_field
    from fieldcal.synthetic.render import render_image, scaled_field

    sf = scaled_field(paper_field(), 0.25)         # 2052 x 1570 px, discs ~27 px
    r = render_image(sf, 5, psf_sigma_px=0.8, seed=11, coded=False)
    return sf, r


def test_rendered_paper_image_accuracy_and_detection_rate(rendered_paper):
    from fieldcal.field.eccentricity import correction_px

    sf, r = rendered_paper
    tr = {k: np.asarray(v) for k, v in r.truth.to_pydict().items() if k != "corners_px"}
    inside = tr["fully_inside"]
    exact = np.stack([tr["u_px"], tr["v_px"]], axis=1)
    ell = np.stack([tr["u_ellipse_px"], tr["v_ellipse_px"]], axis=1)
    ti = tr["target_index"]
    ecc = correction_px(sf.camera, sf.R_world_to_camera[5], sf.center_m[5],
                        sf.targets_true.xyz_m[ti], sf.targets_true.normals[ti],
                        sf.target_diameter_mm / 2000.0)
    well = inside & ~tr["saturated"]
    figures = {}
    for method in METHODS:
        t = detect_targets(r.pixels, method=method, min_diameter_px=12)
        j, uv = match(t, exact)
        rate = np.mean(j[inside] >= 0)
        ok = well & (j >= 0)
        ok &= ~t["truncated"].to_numpy(zero_copy_only=False)[np.maximum(j, 0)]
        corrected = uv[j[ok]] - ecc[ok]
        figures[method] = (rate, rms(corrected - exact[ok]), rms(uv[j[ok]] - ell[ok]))
        assert rate >= 0.99                                        # the issue: >= 99 %
        assert rms(corrected - exact[ok]) <= 0.02                  # the issue: <= 0.02 px
        assert t.num_rows - (j >= 0).sum() <= np.sum(~inside)      # no false detections
    ocv = opencv_blob_centres(r.pixels)
    jb = match(pa.table({"u_px": ocv[:, 0], "v_px": ocv[:, 1]}), exact)[0]
    okb = well & (jb >= 0)
    blob = (np.mean(jb[inside] >= 0), rms(ocv[jb[okb]] - ecc[okb] - exact[okb]))
    print("\nrendered paper image 5 (scale 0.25): detection rate, RMS vs exact centre after "
          "eccentricity correction, RMS vs ellipse centre")
    for m, (rate, e_c, e_e) in figures.items():
        print(f"  {m:9s} {rate:.4f} {e_c:.4f} px {e_e:.4f} px")
    print(f"  SimpleBlobDetector {blob[0]:.4f} {blob[1]:.4f} px")
    assert figures[DEFAULT_METHOD][1] <= blob[1]                   # at least as accurate
