"""Projection uncertainty: landing Jacobians against central differences, propagation against
Monte Carlo, distortion-curve sigmas against closed forms, and the lake's covariances."""

import numpy as np
import pytest

from fieldcal.analysis.uncertainty import (
    Calibration,
    decentering_curve,
    interior_covariance,
    landing_covariance,
    landing_jacobian,
    projection_uncertainty_px,
    radial_curve,
    remove_rotation_part,
    rotation_jacobian,
    summarise_2x2,
    uncertainty_map,
)
from fieldcal.errors import InputError
from fieldcal.model.camera import INDEX, PARAM_NAMES, Camera, Sensor, project, unproject
from fieldcal.model.rotations import R_from_rotvec
from fieldcal.synthetic.field import IXU150_TABLE1, WIDE_ANGLE
from tests.products.test_report import reports_lake

WIDE = Camera.from_dict(Sensor(6000, 4000, 3.9), dict(WIDE_ANGLE, k0=2e-4, b1=1e-4, b2=-5e-5,
                                                      a1=3e-5))
PAPER = Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1)

# a parameter step that moves a corner point by about 0.01 px on these cameras
STEP = {"f_mm": 1e-3, "xp_mm": 1e-4, "yp_mm": 1e-4, "k0": 1e-6, "k1": 1e-9, "k2": 1e-12,
        "k3": 1e-15, "p1": 1e-8, "p2": 1e-8, "a1": 1e-6, "a2": 1e-6, "b1": 1e-6, "b2": 1e-6}


def _land(camera, rays):
    return project(rays, np.eye(3), np.zeros(3), camera)


@pytest.mark.parametrize("camera", [WIDE, PAPER], ids=["wide", "paper"])
def test_landing_jacobian_matches_central_differences(camera):
    uv = camera.sensor.grid_px(7, 5)
    rays = unproject(uv, camera)
    J = landing_jacobian(camera, uv, PARAM_NAMES)
    for j, name in enumerate(PARAM_NAMES):
        h = STEP[name]
        plus, minus = camera.params.copy(), camera.params.copy()
        plus[INDEX[name]] += h
        minus[INDEX[name]] -= h
        num = (_land(Camera(camera.sensor, plus), rays) - _land(Camera(camera.sensor, minus), rays)) / (2 * h)
        # central differences are exact to O(h^2): 1e-6 of the column's size
        scale = np.abs(J[:, :, j]).max()
        assert scale > 0
        np.testing.assert_allclose(J[:, :, j], num, atol=1e-6 * scale, err_msg=name)


def test_rotation_jacobian_matches_central_differences():
    cam = WIDE
    uv = cam.sensor.grid_px(6, 4)
    rays = unproject(uv, cam)
    R = rotation_jacobian(cam, uv)
    h = 1e-6
    for k in range(3):
        w = np.zeros(3)
        w[k] = h
        num = (_land(cam, rays @ R_from_rotvec(w).T) - _land(cam, rays @ R_from_rotvec(-w).T)) / (2 * h)
        # [px/rad]; columns reach ~1e4: 1e-5 relative is the differencing error
        np.testing.assert_allclose(R[:, :, k], num, atol=1e-5 * np.abs(R[:, :, k]).max())


def test_removing_the_rotation_part_kills_a_pure_rotation_and_is_a_projection():
    cam = PAPER
    uv = cam.sensor.grid_px(9, 7)
    R = rotation_jacobian(cam, uv).reshape(-1, 3)
    field = R @ np.array([2e-4, -1e-4, 3e-4])
    assert np.abs(remove_rotation_part(cam, uv, field)).max() < 1e-9 * np.abs(field).max()
    rng = np.random.default_rng(3)
    x = rng.normal(size=(R.shape[0], 2))
    once = remove_rotation_part(cam, uv, x)
    np.testing.assert_allclose(remove_rotation_part(cam, uv, once), once, atol=1e-12)


def test_propagated_landing_covariance_matches_monte_carlo():
    cam = WIDE
    names = ("f_mm", "xp_mm", "yp_mm", "k1", "k2", "p1", "a2")
    rng = np.random.default_rng(42)
    sd = np.array([2e-3, 1.5e-3, 1.5e-3, 2e-8, 5e-11, 5e-7, 2e-6])
    A = rng.normal(size=(len(names), len(names)))
    M = A @ A.T + 3 * np.eye(len(names))
    corr = M / np.sqrt(np.outer(np.diag(M), np.diag(M)))
    cov = corr * np.outer(sd, sd)
    uv = cam.sensor.grid_px(4, 3)
    rays = unproject(uv, cam)
    C = landing_covariance(cam, uv, names, cov)
    n = 2000
    draws = rng.multivariate_normal(np.zeros(len(names)), cov, n)
    idx = [INDEX[m] for m in names]
    out = np.empty((n, len(uv), 2))
    for i, d in enumerate(draws):
        p = cam.params.copy()
        p[idx] += d
        out[i] = _land(Camera(cam.sensor, p), rays)
    emp = np.einsum("kni,knj->nij", out - out.mean(0), out - out.mean(0)) / (n - 1)
    # sampling error of a sigma with 2000 draws is ~1.6 %; 8 % leaves room for
    # the second-order terms at these (deliberately large) sigmas
    np.testing.assert_allclose(np.sqrt(emp[:, [0, 1], [0, 1]]), np.sqrt(C[:, [0, 1], [0, 1]]),
                               rtol=0.08)


def test_summarise_2x2_gives_the_semi_major_axis_and_the_rms():
    C = np.array([[[4.0, 0.0], [0.0, 1.0]], [[2.0, 1.0], [1.0, 2.0]]])
    np.testing.assert_allclose(summarise_2x2(C), [2.0, np.sqrt(3.0)])
    np.testing.assert_allclose(summarise_2x2(C, "rms"), [np.sqrt(5.0), 2.0])
    with pytest.raises(InputError, match="what must be one of"):
        summarise_2x2(C, "mean")


def test_principal_point_sigma_alone_is_a_uniform_map():
    doc = _doc(PAPER, {"xp_mm": 0.003})
    cal = Calibration.from_document(doc)
    _, _, sig = uncertainty_map(cal, (9, 7))
    # a principal-point shift moves every ray by the shift itself (G^-1 of a mild correction:
    # within 1 % of 0.003 mm = 0.566 px over this sensor)
    np.testing.assert_allclose(sig, 0.003 / 0.0053, rtol=0.01)
    # and it is nearly a rotation: removing the common rotation leaves almost nothing
    _, _, sig_r = uncertainty_map(cal, (9, 7), remove_rotation=True)
    assert sig_r.max() < 0.05 * sig.max()


def test_radial_and_decentering_sigmas_match_closed_forms():
    sk1, sp = 3e-8, (4e-8, 3e-8)
    cal = Calibration.from_document(_doc(PAPER, {"k1": sk1, "p1": sp[0], "p2": sp[1]}))
    r = np.linspace(0, 25, 6)
    val, sig = radial_curve(cal, r)
    p = PAPER.params
    np.testing.assert_allclose(val, r * (p[INDEX["k1"]] * r**2 + p[INDEX["k2"]] * r**4
                                         + p[INDEX["k3"]] * r**6), rtol=1e-12)
    np.testing.assert_allclose(sig, sk1 * r**3, rtol=1e-12)
    val, sig = decentering_curve(cal, r)
    p1, p2 = p[INDEX["p1"]], p[INDEX["p2"]]
    np.testing.assert_allclose(val, np.hypot(p1, p2) * r**2, rtol=1e-12)
    u = np.array([p1, p2]) / np.hypot(p1, p2)
    np.testing.assert_allclose(sig, np.sqrt(u[0]**2 * sp[0]**2 + u[1]**2 * sp[1]**2) * r**2,
                               rtol=1e-12)


def _doc(camera, sigma):
    s = camera.sensor
    return {"camera_id": "c", "version": "v", "method": "field", "sensor": s.to_dict(),
            "parameters": camera.to_dict(), "sigma": {n: sigma.get(n) for n in PARAM_NAMES}}


def test_interior_covariance_takes_the_interior_block_in_parameter_order():
    names = ["k1", "f_mm", "img:w_x", "xp_mm"]
    cov = np.arange(16.0).reshape(4, 4)
    cov = cov + cov.T + 40 * np.eye(4)
    keep, block = interior_covariance(names, cov)
    assert keep == ("f_mm", "xp_mm", "k1")
    assert block[0, 2] == cov[1, 0] and block[1, 1] == cov[3, 3]
    nan = np.full((13, 13), np.nan)
    nan[0, 0] = 1.0
    assert interior_covariance(PARAM_NAMES, nan)[0] == ("f_mm",)
    with pytest.raises(InputError, match="does not match its 3 names"):
        interior_covariance(["f_mm", "k1", "k2"], np.eye(2))


def test_calibrations_from_the_lake_carry_their_interior_covariance(tmp_path_factory):
    shared = reports_lake(tmp_path_factory)
    lake = shared["lake_obj"]
    field = Calibration.from_lake(lake, shared["versions"]["f1"])
    gonio = Calibration.from_lake(lake, shared["versions"]["g"])
    for cal in (field, gonio):
        assert cal.covariance_source == "covariance"
        est = tuple(n for n in PARAM_NAMES if cal.document["sigma"][n] is not None)
        assert cal.names == est
        # the stored sigmas are the covariance's diagonal
        np.testing.assert_allclose(np.sqrt(np.diag(cal.covariance)),
                                   [cal.document["sigma"][n] for n in est], rtol=1e-9)
    # the goniometer observes only the two axes: the corners are far less certain
    _, _, sig = uncertainty_map(gonio, (21, 15))
    assert sig[0, 0] > 5 * sig[7, 10]
    assert projection_uncertainty_px(field, [[10.0, 10.0]]).shape == (1,)
