"""The camera model fieldcal-brown/1 against hand-derived values and its own inverses."""

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.model import camera as cam
from fieldcal.model.camera import Camera, Sensor
from fieldcal.model.rotations import R_world_to_camera_from_opk

# A wide-angle camera with about 20 px of barrel distortion in the corners.
SENSOR = Sensor(6000, 4000, 3.9)
WIDE = Camera.from_dict(SENSOR, {"f_mm": 24.0, "xp_mm": 0.05, "yp_mm": -0.03, "k1": 3.5e-5,
                                 "k2": -3e-8, "k3": 1e-11, "p1": 2e-6, "p2": -3e-6,
                                 "a1": 1e-5, "a2": -2e-5, "k0": 1e-4, "b1": 3e-5, "b2": -1e-5})


def test_pixel_mm_convention_matches_contract():
    s = Sensor(8208, 6280, 5.3)
    # the centre of the sensor is between pixels (W-1)/2, (H-1)/2
    assert np.allclose(s.pixel_to_mm([(8207 / 2, 6279 / 2)]), 0.0)
    # top-left pixel centre: x negative (left), y positive (up)
    xy = s.pixel_to_mm([0.0, 0.0])
    assert xy[0] == pytest.approx(-8207 / 2 * 0.0053) and xy[1] == pytest.approx(6279 / 2 * 0.0053)
    uv = np.random.default_rng(1).uniform(-0.5, 8000, (100, 2))
    assert np.allclose(s.mm_to_pixel(s.pixel_to_mm(uv)), uv, atol=1e-9)


def test_correction_matches_contract_formula_term_by_term():
    p = WIDE.params
    x, y = 3.1, -2.2
    xb, yb = x - p[cam.XP], y - p[cam.YP]
    r2 = xb**2 + yb**2
    rad = p[cam.K0] + p[cam.K1] * r2 + p[cam.K2] * r2**2 + p[cam.K3] * r2**3
    dx = xb * rad + p[cam.P1] * (r2 + 2 * xb**2) + 2 * p[cam.P2] * xb * yb + p[cam.B1] * xb + p[cam.B2] * yb
    dy = yb * rad + p[cam.P2] * (r2 + 2 * yb**2) + 2 * p[cam.P1] * xb * yb + p[cam.A1] * xb + p[cam.A2] * yb
    assert np.allclose(cam.correction([x, y], p), [dx, dy], rtol=1e-14, atol=0)
    assert np.allclose(cam.correct([x, y], p), [xb + dx, yb + dy], rtol=1e-14, atol=0)


def test_wide_camera_has_about_20px_of_distortion_in_the_corners():
    corners = np.array([[0, 0], [5999, 0], [0, 3999], [5999, 3999]], float)
    dxy = cam.correction(SENSOR.pixel_to_mm(corners), WIDE.params) / SENSOR.pixel_mm
    assert 15 < np.abs(np.linalg.norm(dxy, axis=1)).max() < 30


def test_distort_inverts_correct_to_1e6_px_over_the_whole_sensor():
    uv = np.concatenate([SENSOR.grid_px(61, 41), [[-0.5, -0.5], [5999.5, 3999.5]]])
    xy = SENSOR.pixel_to_mm(uv)
    back = cam.distort(cam.correct(xy, WIDE.params), WIDE.params)
    err_px = np.abs(back - xy).max() / SENSOR.pixel_mm
    assert err_px < 1e-6  # the contract's convergence requirement


def test_correct_jacobian_matches_central_differences():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-10, 10, (50, 2))
    q, G, Q = cam.correct_jacobian(xy, WIDE.params)
    h = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        num = (cam.correct(xy + e, WIDE.params) - cam.correct(xy - e, WIDE.params)) / (2 * h)
        assert np.allclose(G[:, :, j], num, rtol=1e-7, atol=1e-9)
    # steps that move q by about 1e-4 mm: q is linear in every coefficient but xp, yp
    steps = [1e-6, 1e-6, 1e-6, 1e-5, 1e-7, 1e-9, 1e-11, 1e-7, 1e-7, 1e-5, 1e-5, 1e-5, 1e-5]
    for k, step in enumerate(steps):
        pp, pm = WIDE.params.copy(), WIDE.params.copy()
        pp[k] += step
        pm[k] -= step
        num = (cam.correct(xy, pp) - cam.correct(xy, pm)) / (2 * step)
        assert np.allclose(Q[:, :, k], num, rtol=1e-6, atol=1e-9 * max(1.0, np.abs(num).max())), cam.PARAM_NAMES[k]


def test_project_then_unproject_returns_the_ray():
    rng = np.random.default_rng(7)
    R = R_world_to_camera_from_opk(0.1, -0.2, 0.3)
    C = np.array([1.0, -2.0, 10.0])
    uv = rng.uniform(0, [5999, 3999], (200, 2))
    rays_cam = WIDE.unproject(uv)
    X = C + (R.T @ (rays_cam * rng.uniform(3, 30, (200, 1))).T).T
    assert np.allclose(WIDE.project(X, R, C), uv, atol=1e-7)


def test_project_behind_the_camera_is_nan():
    R = np.eye(3)
    uv = WIDE.project([[0.0, 0.0, 5.0], [0.0, 0.0, -5.0]], R, np.zeros(3))
    assert np.isnan(uv[0]).all() and np.allclose(uv[1], [2999.5 + 0.05 / 0.0039, 1999.5 + 0.03 / 0.0039], atol=0.5)


def test_bad_sensor_and_parameters_are_refused():
    with pytest.raises(InputError, match="pixel_size_um"):
        Sensor(10, 10, -1.0)
    with pytest.raises(InputError, match="unknown camera parameter"):
        cam.params_from_dict({"f": 1.0})


def test_principal_point_in_pixels_and_back_is_the_convention_written_out():
    """docs/conventions.md section 1: u0 = (W-1)/2 + xp/d, v0 = (H-1)/2 - yp/d, bit for bit
    (issue 25, goal 6: one function instead of the formula in each module), and its inverse."""
    s = Sensor(820, 628, 5.3)
    params = np.zeros(13)
    params[[cam.F, cam.XP, cam.YP]] = 24.1, 0.0731, -0.0412
    c = Camera(s, params)
    u0, v0 = c.principal_point_px
    assert u0 == (820 - 1) / 2 + 0.0731 / 5.3e-3 and v0 == (628 - 1) / 2 - (-0.0412) / 5.3e-3
    assert u0 > 409.5 and v0 > 313.5                        # x right / u right; y up / v down
    xp, yp = cam.principal_point_mm(s, u0, v0)
    assert abs(xp - 0.0731) < 1e-15 and abs(yp + 0.0412) < 1e-15
    rng = np.random.default_rng(2)
    uv = rng.uniform(0, 800, (5, 2))
    back = cam.principal_point_px(s, *cam.principal_point_mm(s, uv[:, 0], uv[:, 1]).T)
    np.testing.assert_allclose(back, uv, rtol=0, atol=1e-12)
    from fieldcal.model.opencv_frames import opencv_camera_matrix
    np.testing.assert_array_equal(opencv_camera_matrix(c)[:2, 2], [u0, v0])
