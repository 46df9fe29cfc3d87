"""The renderer of synthetic field sessions: exact coverage, truth, markers, noise, files.

Independent references made here: the image of a disc without distortion is the conic
``H^-T diag(1, 1, -r^2) H^-1`` of the plane's homography ``H`` (its centre and second
moments in closed form); with distortion, the area centroid of the distorted ellipse to
second order (``g(c) + 1/2 H_g : Sigma + Dg Sigma grad|J| / |J|``, derivatives of the
camera's ``distort`` by central differences).
"""

import csv
import json
from datetime import datetime

import cv2
import numpy as np
import pytest
from scipy import ndimage

from fieldcal.errors import InputError
from fieldcal.measure.imageio import probe_image, read_image
from fieldcal.model.camera import Camera, Sensor
from fieldcal.session.data import FieldData, FieldImage, FieldObservations, TargetField
from fieldcal.session.loader import (
    field_data_from_observations,
    load_session,
    read_marks_csv,
    read_targets_csv,
)
from fieldcal.synthetic import field as syn
from fieldcal.synthetic import render, session_writer


# ------------------------------------------------------------------------------------------
# helpers: a field of one target, and the closed-form image of a disc
# ------------------------------------------------------------------------------------------
def one_target_field(camera, X, normal, C, aim, diameter_mm, code=-1, marker_mm=100.0):
    tt = TargetField(["A"], np.array([X], float), 5.0, [code], np.array([normal], float))
    R = syn.look_at(C, aim)[None]
    Cs = np.array([C], float)
    uv = camera.project(tt.xyz_m, R[0], Cs[0])
    data = FieldData(camera.sensor, tt, [FieldImage("images/a.tif", "S1")],
                     FieldObservations([0], [0], uv, 0.1))
    return syn.SyntheticField("one", camera, tt, R, Cs, uv, data, diameter_mm, marker_mm)


def conic_of_disc(sf, radius_m):
    """Ideal-plane image of the disc (no distortion): ellipse centre c [mm], its covariance
    Sigma [mm^2] (per unit area) and the image of the disc's centre [mm]."""
    R, C = sf.R_world_to_camera[0], sf.center_m[0]
    X, n = sf.targets_true.xyz_m[0], sf.targets_true.normals[0]
    e1 = np.array([1.0, 0.0, 0.0]) - n[0] * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    f = sf.camera.f_mm
    H = np.diag([-f, -f, 1.0]) @ np.column_stack([R @ e1, R @ e2, R @ (X - C)])
    Hi = np.linalg.inv(H)
    Q = Hi.T @ np.diag([1.0, 1.0, -radius_m ** 2]) @ Hi
    A, b, d = Q[:2, :2], Q[:2, 2], Q[2, 2]
    c = np.linalg.solve(A, -b)
    kappa = c @ A @ c - d                       # (x - c)^T (A / kappa) (x - c) = 1
    return c, np.linalg.inv(A / kappa) / 4.0, H[:2, 2] / H[2, 2]


def second_order_centroid(camera, c, Sigma, h=1e-3):
    """Area centroid [px] of g(E), g: ideal point [mm] -> measured pixel, E: ellipse (c, Sigma)."""
    def g(q):
        return camera.sensor.mm_to_pixel(camera.distort(np.asarray(q, float)))
    e = np.eye(2) * h

    def D(q):
        return np.stack([(g(q + e[k]) - g(q - e[k])) / (2 * h) for k in range(2)], axis=1)

    def J(q):
        return abs(np.linalg.det(D(q)))
    Hs = np.zeros((2, 2, 2))
    for i in range(2):
        for j in range(2):
            Hs[:, i, j] = (g(c + e[i] + e[j]) - g(c + e[i] - e[j]) - g(c - e[i] + e[j])
                           + g(c - e[i] - e[j])) / (4 * h * h)
    grad_J = np.array([(J(c + e[k]) - J(c - e[k])) / (2 * h) for k in range(2)])
    return g(c) + 0.5 * np.einsum("kij,ij->k", Hs, Sigma) + D(c) @ Sigma @ grad_J / J(c)


def centroid(u0, v0, cov):
    vv, uu = np.mgrid[v0:v0 + cov.shape[0], u0:u0 + cov.shape[1]]
    return np.array([(cov * uu).sum(), (cov * vv).sum()]) / cov.sum()


def table(t):
    return {k: np.array(v) for k, v in t.to_pydict().items() if k != "corners_px"}


PINHOLE = Camera.from_dict(Sensor(64, 48, 5.0), {"f_mm": 50.0})
# a short lens, a disc of 60 mm at 1 m, tilted 55 deg, off-axis: a large eccentricity
OBLIQUE_NORMAL = [np.sin(np.radians(55)), -np.cos(np.radians(55)), 0.0]
STRONG = {"f_mm": 8.0, "xp_mm": 0.03, "yp_mm": -0.02, "k1": 2.0e-3, "k2": -3e-5,
          "p1": 2e-4, "p2": -1e-4, "a1": 1e-4, "a2": 3e-4}


@pytest.fixture(scope="module")
def paper_small():
    return render.scaled_field(syn.paper_field(seed=0), 0.25)


@pytest.fixture(scope="module")
def wide_small():
    return render.scaled_field(syn.wide_field(seed=0), 0.25)


@pytest.fixture(scope="module")
def wide_image(wide_small):
    return render.render_image(wide_small, 2, seed=3)


@pytest.fixture(scope="module")
def paper_image(paper_small):
    return render.render_image(paper_small, 5, seed=3)


# ------------------------------------------------------------------------------------------
# coverage
# ------------------------------------------------------------------------------------------
def test_fronto_parallel_disc_area_and_centroid_follow_the_pixel_convention():
    rng = np.random.default_rng(11)
    for _ in range(6):
        off = rng.uniform(-0.004, 0.004, 2)       # up to 40 px off the sensor centre
        d_mm = rng.uniform(14.0, 25.0)            # 14-25 px across
        sf = one_target_field(PINHOLE, [off[0], 0.0, off[1]], [0, -1, 0], [0, -10, 0],
                              [0, 0, 0], d_mm)
        r_px = d_mm / 2 / 10_000 * 50.0 / 0.005
        u0, v0, cov = render.coverage_window(sf, 0, 0, supersample=8)
        # area: 8 x 8 regular samples resolve the rim to ~1/64 px; 0.01 px of rim displacement
        assert cov.sum() == pytest.approx(np.pi * r_px ** 2, abs=0.01 * 2 * np.pi * r_px)
        # centroid = projected centre: regular-sampling aliasing stays below 0.006 px at S = 8
        assert np.abs(centroid(u0, v0, cov) - sf.uv_true_px[0]).max() < 0.006


def test_disc_centred_on_a_pixel_corner_is_symmetric_about_it():
    # centre imaged exactly at (24.5, 24.5): the covered pixels are symmetric about that corner
    cam = Camera.from_dict(Sensor(50, 50, 5.0), {"f_mm": 50.0})
    sf = one_target_field(cam, [0.0, 0.0, 0.0], [0, -1, 0], [0, -10, 0], [0, 0, 0], 18.0)
    assert np.allclose(sf.uv_true_px[0], [24.5, 24.5])
    u0, v0, cov = render.coverage_window(sf, 0, 0, supersample=8)
    full = np.zeros((50, 50))
    full[v0:v0 + cov.shape[0], u0:u0 + cov.shape[1]] = cov
    assert full.sum() > 200
    assert np.abs(full - full[::-1, ::-1]).max() < 1e-12
    assert np.abs(full - full.T).max() < 1e-12
    assert full[24, 24] == 1.0 and full[24 - 9, 24] < 0.5 and full[24 + 10, 24] < 0.5


def test_adaptive_sampling_equals_supersampling_every_pixel():
    cam = Camera.from_dict(Sensor(1600, 1200, 5.0), STRONG)
    disc = one_target_field(cam, [0, 0, 0], OBLIQUE_NORMAL, [0, -1.5, 0], [-0.5, 0, -0.4], 60.0)
    marker = one_target_field(cam, [0, 0, 0], OBLIQUE_NORMAL, [0, -1.5, 0], [-0.5, 0, -0.4],
                              60.0, code=123, marker_mm=150.0)
    for sf in (disc, marker):
        a = render.coverage_window(sf, 0, 0, supersample=8, adaptive=True)
        b = render.coverage_window(sf, 0, 0, supersample=8, adaptive=False)
        assert a[:2] == b[:2]
        assert 100 < a[2].sum() and np.abs(a[2] - b[2]).max() == 0.0


def test_grazing_thin_figures_fall_back_to_full_supersampling():
    # a 6 mm disc seen at 84 deg from its normal: 6 px long, 0.6 px wide. Corners alone would
    # miss it entirely (all four corners of every pixel are background), so the adaptive
    # scheme must supersample every pixel: the same numbers as adaptive=False
    cam = Camera.from_dict(Sensor(120, 90, 5.0), {"f_mm": 50.0, "k1": 1e-4})
    n = [np.sin(np.radians(84)), -np.cos(np.radians(84)), 0.0]
    sf = one_target_field(cam, [0, 0, 0], n, [0, -10, 0], [0.0004, 0, 0.0003], 6.0)
    a = render.coverage_window(sf, 0, 0, supersample=8, adaptive=True)
    b = render.coverage_window(sf, 0, 0, supersample=8, adaptive=False)
    assert np.abs(a[2] - b[2]).max() == 0.0
    # area pi r^2 cos(84 deg) = 2.96 px^2; 8 x 8 samples on a 0.6 px wide sliver: 3 %
    assert a[2].sum() == pytest.approx(np.pi * 3.0 ** 2 * np.cos(np.radians(84)), rel=0.03)


def test_oblique_disc_ellipse_centre_is_the_conic_centre_not_the_projected_centre():
    cam = Camera.from_dict(Sensor(1600, 1200, 5.0), {"f_mm": 8.0, "xp_mm": 0.03, "yp_mm": -0.02})
    sf = one_target_field(cam, [0, 0, 0], OBLIQUE_NORMAL, [0, -1.0, 0], [-0.35, 0, -0.25], 60.0)
    c, _, q0 = conic_of_disc(sf, 0.030)
    to_px = lambda q: cam.sensor.mm_to_pixel(q + cam.params[1:3])  # noqa: E731
    centre_px, ellipse_px = to_px(q0), to_px(c)
    assert np.abs(centre_px - sf.uv_true_px[0]).max() < 1e-9    # homography vs camera.project
    ecc = np.linalg.norm(ellipse_px - centre_px)
    assert ecc > 0.5                                             # 0.69 px in this geometry
    u0, v0, cov = render.coverage_window(sf, 0, 0, supersample=8)
    # the rendered disc's centroid is the conic's centre (0.003 px: sampling aliasing)...
    assert np.linalg.norm(centroid(u0, v0, cov) - ellipse_px) < 0.003
    # ...and the truth of render_image says so too (rim polygon centroid, 512 points)
    t = table(render.render_image(sf, 0, noise=False).truth)
    ell = np.array([t["u_ellipse_px"][0], t["v_ellipse_px"][0]])
    assert np.linalg.norm(ell - ellipse_px) < 1e-3
    assert np.hypot(t["u_px"][0] - centre_px[0], t["v_px"][0] - centre_px[1]) < 1e-9


def test_oblique_disc_in_a_distorted_camera_matches_the_second_order_expectation():
    cam = Camera.from_dict(Sensor(1600, 1200, 5.0), STRONG)     # ~28 px distortion at corners
    pinhole = Camera.from_dict(cam.sensor, {k: STRONG[k] for k in ("f_mm", "xp_mm", "yp_mm")})
    for dist in (1.0, 2.0):
        sf = one_target_field(cam, [0, 0, 0], OBLIQUE_NORMAL, [0, -dist, 0],
                              [-0.35 * dist, 0, -0.25 * dist], 60.0)
        sf_ideal = one_target_field(pinhole, [0, 0, 0], OBLIQUE_NORMAL, [0, -dist, 0],
                                    [-0.35 * dist, 0, -0.25 * dist], 60.0)
        c, Sigma, _ = conic_of_disc(sf_ideal, 0.030)
        expected = second_order_centroid(cam, c, Sigma)
        ecc = np.linalg.norm(expected - sf.uv_true_px[0])
        assert ecc > 0.1                                         # 0.67 px at 1 m, 0.17 px at 2 m
        u0, v0, cov = render.coverage_window(sf, 0, 0, supersample=8)
        # 0.004 px: sampling aliasing (S = 8) plus 4th-order terms of the expansion
        assert np.linalg.norm(centroid(u0, v0, cov) - expected) < 0.004
        t = table(render.render_image(sf, 0, noise=False).truth)
        ell = np.array([t["u_ellipse_px"][0], t["v_ellipse_px"][0]])
        assert np.linalg.norm(ell - expected) < 1e-3


def test_eccentricity_is_visible_in_the_wide_scenario(wide_image):
    t = table(wide_image.truth)
    ok = (t["kind"] == "disc") & t["fully_inside"] & (t["visible_fraction"] == 1.0)
    cov = np.stack([t["u_coverage_px"][ok], t["v_coverage_px"][ok]], axis=1)
    ell = np.stack([t["u_ellipse_px"][ok], t["v_ellipse_px"][ok]], axis=1)
    ctr = np.stack([t["u_px"][ok], t["v_px"][ok]], axis=1)
    rms = lambda d: np.sqrt(np.mean(np.sum(d ** 2, axis=1)))   # noqa: E731
    assert ok.sum() > 50
    assert rms(ell - ctr) > 0.02                 # this oblique wide view: 0.03 px RMS
    assert rms(cov - ell) < 0.004                # the rendered discs follow the ellipse centre
    assert rms(cov - ell) < 0.3 * rms(cov - ctr)


# ------------------------------------------------------------------------------------------
# images of the scenarios
# ------------------------------------------------------------------------------------------
def test_truth_centre_is_camera_project_of_the_true_centre(paper_small, paper_image):
    t = table(paper_image.truth)
    X = paper_small.targets_true.xyz_m[t["target_index"]]
    uv = paper_small.camera.project(X, paper_small.R_world_to_camera[5], paper_small.center_m[5])
    assert np.abs(uv - np.stack([t["u_px"], t["v_px"]], axis=1)).max() < 1e-9
    obs = paper_small.data.obs
    k = np.flatnonzero(obs.image == 5)
    row = {ti: r for r, ti in enumerate(t["target_index"])}
    assert all(ti in row for ti in obs.target[k])                  # every observed target drawn
    mine = np.array([[t["u_px"][row[ti]], t["v_px"][row[ti]]] for ti in obs.target[k]])
    assert np.abs(mine - paper_small.uv_true_px[k]).max() < 1e-9
    assert set(t["target_id"]) <= set(paper_small.targets_true.ids)


def test_scaled_fields_have_realistic_target_sizes_in_pixels(paper_small, wide_small,
                                                             paper_image, wide_image):
    paper, wide = syn.paper_field(seed=0), syn.wide_field(seed=0)
    for full, small, img in ((paper, paper_small, paper_image), (wide, wide_small, wide_image)):
        s0, s1 = full.camera.sensor, small.camera.sensor
        assert (s1.width_px, s1.height_px) == (round(s0.width_px / 4), round(s0.height_px / 4))
        # same field of view: the sensor's extent in mm agrees to a pixel
        assert abs(s1.width_px * s1.pixel_mm - s0.width_px * s0.pixel_mm) <= s1.pixel_mm
        assert np.array_equal(small.camera.params, full.camera.params)
        d = table(img.truth)
        d_disc = d["diameter_px"][d["kind"] == "disc"]
        assert 15 <= np.median(d_disc) <= 30
        assert len(small.data.obs) > 0.9 * len(full.data.obs)
    with pytest.raises(InputError, match="would touch"):
        render.scaled_field(wide, 0.05)
    same = render.scaled_field(wide, 1.0, margin_px=15.0)   # scale 1 (wide's margin) is a no-op
    assert same.camera.sensor == wide.camera.sensor and same.marker_size_mm == 120.0
    assert np.array_equal(same.data.obs.target, wide.data.obs.target)
    assert np.abs(same.uv_true_px - wide.uv_true_px).max() < 1e-9
    assert np.abs(same.data.obs.uv_px - wide.data.obs.uv_px).max() < 1e-9


def test_aruco_markers_are_detected_with_their_ids_and_centres(paper_image, wide_image):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_1000),
                                       params)
    n_checked = 0
    for img in (paper_image, wide_image):
        lo, hi = np.percentile(img.pixels, [0.5, 99.5])
        img8 = np.clip((img.pixels - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
        corners, ids, _ = detector.detectMarkers(img8)
        found = {int(i): c.reshape(4, 2).astype(float)
                 for i, c in zip(ids.ravel(), corners, strict=True)}
        t = img.truth.to_pydict()
        for k in range(img.truth.num_rows):
            if not (t["coded"][k] and t["fully_inside"][k] and t["isolated"][k]
                    and t["visible_fraction"][k] == 1.0):
                continue
            code = t["code"][k]
            assert code in found, f"marker {code} not detected"
            c = found[code]
            d1, d2 = c[2] - c[0], c[3] - c[1]
            s = np.linalg.solve(np.stack([d1, -d2], axis=1), c[1] - c[0])[0]
            centre = c[0] + s * d1
            # 0.25 px: OpenCV's sub-pixel corners of blurred outer corners are biased ~0.2 px
            # inwards, symmetrically, so the diagonals' crossing stays within ~0.1 px
            assert np.hypot(centre[0] - t["u_px"][k], centre[1] - t["v_px"][k]) < 0.25
            true_corners = np.array(t["corners_px"][k]).reshape(4, 2)
            assert np.abs(c - true_corners).max() < 0.6              # same order, same corners
            n_checked += 1
    assert n_checked >= 8
    assert set(found) <= {c for c in t["code"] if c is not None}     # no phantom ids


def test_occlusion_hides_the_farther_figure():
    cam = Camera.from_dict(Sensor(200, 150, 5.0), {"f_mm": 50.0})
    tt = TargetField(["near", "far"], [[0.0, -0.5, 0.0], [0.004, 0.0, 0.0]], 5.0, [-1, -1],
                     [[0, -1, 0], [0, -1, 0]])
    R = syn.look_at([0, -10, 0], [0, 0, 0])[None]
    C = np.array([[0.0, -10.0, 0.0]])
    uv = cam.project(tt.xyz_m, R[0], C[0])
    data = FieldData(cam.sensor, tt, [FieldImage("images/a.tif")],
                     FieldObservations([0, 0], [0, 1], uv, 0.1))
    sf = syn.SyntheticField("two", cam, tt, R, C, uv, data, 20.0, 100.0)
    t = table(render.render_image(sf, 0, noise=False).truth)
    vis = dict(zip(t["target_id"], t["visible_fraction"], strict=True))
    assert vis["near"] == pytest.approx(1.0, abs=1e-12)
    assert 0.2 < vis["far"] < 0.9                     # discs ~21 and 20 px, 8 px apart
    assert not t["isolated"].any()


# ------------------------------------------------------------------------------------------
# radiometry
# ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def tiny_wide():
    return render.scaled_field(syn.wide_field(seed=0), 0.1, target_scale=4.0)


@pytest.mark.parametrize("exposure", [0.6, 0.02])
def test_noise_is_shot_plus_read_noise(tiny_wide, exposure):
    img = render.render_image(tiny_wide, 0, targets=[], illumination_gradient=0.0,
                              exposure=exposure, seed=5)
    m = img.meta
    g = m["gain_dn_per_e"]
    electrons = exposure * m["full_well_e"] * m["albedo_background"]
    px = img.pixels.astype(float)
    assert img.pixels.dtype == np.uint16 and img.truth.num_rows == 0
    # 240 000 pixels: the mean to 0.05 DN-level statistics, the variance to ~0.3 % (1 sigma)
    assert px.mean() == pytest.approx(g * electrons, abs=5 * np.sqrt(px.var() / px.size) + 0.01)
    expected_var = g ** 2 * (electrons + m["read_noise_e"] ** 2) + 1.0 / 12.0   # + rounding
    assert px.var() == pytest.approx(expected_var, rel=0.015)
    assert m["read_noise_e"] == 10.0 and m["full_well_e"] == 20_000.0


def test_noise_free_image_is_the_expected_signal_and_saturates_when_asked(tiny_wide):
    img = render.render_image(tiny_wide, 0, targets=[], illumination_gradient=0.0, noise=False)
    m = img.meta
    level = m["gain_dn_per_e"] * m["exposure"] * m["full_well_e"] * m["albedo_background"]
    assert np.all(img.pixels == np.rint(level))
    some = tiny_wide.data.obs.target[tiny_wide.data.obs.image == 0][:12]
    hot = render.render_image(tiny_wide, 0, exposure=1.5, noise=False, illumination_gradient=0.0,
                              targets=some)
    assert (hot.pixels == 65535).mean() > 0.9
    assert hot.truth.num_rows == len(some) and table(hot.truth)["saturated"].all()
    t = table(render.render_image(tiny_wide, 0, noise=False, targets=some).truth)
    assert not t["saturated"].any() and (t["snr"] > 50).all() and (t["contrast"] > 20_000).all()


def test_psf_is_a_gaussian_blur_of_the_sharp_image_and_polarity_flips():
    cam = Camera.from_dict(Sensor(80, 60, 5.0), {"f_mm": 50.0})
    sf = one_target_field(cam, [0.0013, 0.0, -0.0007], [0, -1, 0], [0, -10, 0], [0, 0, 0], 20.0)
    kw = {"noise": False, "illumination_gradient": 0.0}
    sharp = render.render_image(sf, 0, psf_sigma_px=0.0, **kw).pixels.astype(float)
    blurred = render.render_image(sf, 0, psf_sigma_px=1.2, **kw).pixels.astype(float)
    # the same figure blurred: equal up to the rounding of both images to integers
    assert np.abs(ndimage.gaussian_filter(sharp, 1.2, mode="nearest") - blurred).max() <= 1.0
    assert np.abs(sharp - blurred).max() > 5000
    bright = render.render_image(sf, 0, polarity="bright", **kw)
    u, v = np.rint(sf.uv_true_px[0]).astype(int)
    assert bright.pixels[v, u] > 5 * bright.pixels[0, 0]
    assert sharp[v, u] < 0.2 * sharp[0, 0]


def test_bad_arguments_are_rejected_with_a_reason(tiny_wide):
    with pytest.raises(InputError, match="polarity must be"):
        render.render_image(tiny_wide, 0, polarity="grey")
    with pytest.raises(InputError, match="image_index must be an integer in 0..23"):
        render.render_image(tiny_wide, 24)
    with pytest.raises(InputError, match="supersample must be"):
        render.render_image(tiny_wide, 0, supersample=0)
    with pytest.raises(InputError, match="targets: indices"):
        render.render_image(tiny_wide, 0, targets=[10_000])
    with pytest.raises(InputError, match="ArUco code 1000 is outside"):
        render.aruco_cells(1000)


# ------------------------------------------------------------------------------------------
# sessions on disk
# ------------------------------------------------------------------------------------------
def read_csv(path):
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def test_observation_only_session(tmp_path):
    sf = syn.paper_field(seed=0)
    out = session_writer.write_field_session(tmp_path / "s1", sf, images=False, observations_csv=True)
    folder = tmp_path / "s1"
    assert sorted(p.name for p in folder.iterdir()) == ["observations.csv", "session.json",
                                                         "targets.csv"]
    doc = json.loads((folder / "session.json").read_text())
    assert doc == out["session"]
    assert doc["schema"] == "fieldcal.session/1" and doc["method"] == "field"
    assert doc["session_id"] == "s1" and doc["lens"] == {"nominal_focal_mm": 150.0}
    assert doc["sensor"] == {"width_px": 8208, "height_px": 6280, "pixel_size_um": 5.3}
    assert len(doc["images"]) == 72 and doc["images"][0] == {"file": "images/paper_001.tif",
                                                             "station": "G1"}
    assert out["truth"] == {}
    rows = read_csv(folder / "targets.csv")
    assert rows[0] == ["id", "X", "Y", "Z", "sigma_mm", "code"]
    xyz = np.array([[float(x) for x in r[1:4]] for r in rows[1:]])
    assert np.abs(xyz - sf.data.targets.xyz_m).max() < 1e-6        # surveyed, not true
    assert np.abs(xyz - sf.targets_true.xyz_m).max() > 0.01
    codes = [r[5] for r in rows[1:]]
    assert sum(c != "" for c in codes) == (sf.targets_true.codes >= 0).sum()
    obs = read_csv(folder / "observations.csv")
    assert obs[0] == ["image", "target_id", "u", "v", "sigma_px"]
    assert len(obs) - 1 == len(sf.data.obs)
    uv = np.array([[float(r[2]), float(r[3])] for r in obs[1:]])
    assert np.abs(uv - sf.data.obs.uv_px).max() < 1e-6
    assert obs[1][:2] == ["images/paper_001.tif", sf.targets_true.ids[sf.data.obs.target[0]]]
    # and fieldcal's own session reader takes it back
    back = field_data_from_observations(load_session(folder))
    assert np.array_equal(back.targets.ids, sf.data.targets.ids)
    assert np.array_equal(back.targets.codes, sf.data.targets.codes)
    assert np.array_equal(back.obs.image, sf.data.obs.image)
    assert np.array_equal(back.obs.target, sf.data.obs.target)
    assert np.abs(back.obs.uv_px - sf.data.obs.uv_px).max() < 1e-6
    assert back.nominal_focal_mm == 150.0 and back.sensor == sf.camera.sensor


def test_session_with_images_marks_and_the_tiff_mix(tmp_path, tiny_wide):
    folder = tmp_path / "wide-session"
    out = session_writer.write_field_session(folder, tiny_wide, image_indices=[0, 7, 12, 21],
                                     marks_csv=True, seed=4, session_id="w1", camera_id="cam-7")
    doc = json.loads((folder / "session.json").read_text())
    assert doc["session_id"] == "w1" and doc["camera_id"] == "cam-7"
    assert doc["lens"]["nominal_focal_mm"] == 24.0
    assert doc["field"] == {"targets": "targets.csv", "target_diameter_mm": 80.0,
                            "target_polarity": "dark",
                            "coded": {"type": "aruco", "dictionary": "DICT_4X4_1000",
                                      "marker_size_mm": tiny_wide.marker_size_mm}}
    datetime.fromisoformat(doc["acquired"])
    assert [im["file"] for im in doc["images"]] == out["images"]
    layouts = set()
    for k, name in enumerate(out["images"]):
        pix = read_image(folder / name, expect_size=(600, 400))
        assert pix.dtype == np.uint16
        info = probe_image(folder / name)
        layouts.add((info.tiled, info.compression, info.bigtiff))
        if k == 0:     # what was written is what render_image makes with these settings
            again = render.render_image(tiny_wide, 0, seed=4)
            assert np.array_equal(pix, again.pixels)
            for col in again.truth.column_names:       # (str: NaN == NaN)
                assert str(again.truth[col].to_pylist()) == str(out["truth"][name][col].to_pylist())
    assert layouts == {(True, "ZSTD", False), (False, "NONE", False), (True, "ADOBE_DEFLATE", True),
                       (False, "NONE", True)}
    marks = read_csv(folder / "marks.csv")
    assert marks[0] == ["image", "target_id", "u", "v"]
    sess = load_session(folder)                   # valid for fieldcal's own reader
    assert [im.file for im in sess.images] == out["images"] and sess.coded is not None
    targets = read_targets_csv(sess.targets_path)
    assert len(read_marks_csv(sess.marks_path, targets, sess.images)) == 4
    m = out["marks"].to_pydict()
    plain = set(tiny_wide.targets_true.ids[tiny_wide.targets_true.codes < 0])
    err = np.hypot(np.array(m["u"]) - m["u_true"], np.array(m["v"]) - m["v_true"])
    assert 0.25 < np.sqrt(np.mean(err ** 2) / 2) < 0.8                 # ~0.5 px per axis
    for name in out["images"]:
        k = [i for i, im in enumerate(m["image"]) if im == name]
        assert 4 <= len(k) <= 6 and all(m["target_id"][i] in plain for i in k)
        uv = np.array([[m["u_true"][i], m["v_true"][i]] for i in k])
        truth = table(out["truth"][name])
        row = {tid: r for r, tid in enumerate(truth["target_id"])}
        assert all(truth["fully_inside"][row[m["target_id"][i]]] for i in k)
        # well spread: the marks span most of the frame in both directions
        assert np.ptp(uv[:, 0]) > 0.5 * 600 and np.ptp(uv[:, 1]) > 0.4 * 400


def test_uncoded_session_draws_discs_and_writes_no_codes(tmp_path, tiny_wide):
    out = session_writer.write_field_session(tmp_path / "u", tiny_wide, coded=False, image_indices=[3],
                                     compression_mix=False)
    doc = out["session"]
    assert "coded" not in doc["field"]
    assert all(r[5] == "" for r in read_csv(tmp_path / "u" / "targets.csv")[1:])
    t = table(out["truth"]["images/wide_004.tif"])
    coded_targets = set(np.flatnonzero(tiny_wide.targets_true.codes >= 0))
    assert set(t["kind"]) == {"disc"} and coded_targets & set(t["target_index"])
    info = probe_image(tmp_path / "u" / "images" / "wide_004.tif")
    assert (info.tiled, info.compression) == (False, "NONE")
