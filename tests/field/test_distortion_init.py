"""Distortion initial values (METHODS eq. 7-8): exact recovery, refusals, and on DLT output."""

import numpy as np
import pytest

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.distortion_init import (
    DISTORTION_NAMES,
    distortion_lsq,
    fold_k0,
    ideal_points_mm,
    initial_camera,
)
from fieldcal.field.dlt import dlt
from fieldcal.model.camera import INDEX, Camera, Sensor, correct, correction, params_from_dict
from fieldcal.synthetic.field import IXU150_TABLE1, look_at

IXU_SENSOR = Sensor(8208, 6280, 5.3)
IXU_TRUTH = IXU150_TABLE1
IXU = Camera.from_dict(IXU_SENSOR, IXU_TRUTH)
WIDE_SENSOR = Sensor(6000, 4000, 3.9)
WIDE_TRUTH = {"f_mm": 24.0, "k1": 3.5e-5, "k2": -3e-8, "k3": 1e-11}
WIDE = Camera.from_dict(WIDE_SENSOR, WIDE_TRUTH)
FIELD = ("k1", "k2", "k3", "p1", "p2", "a1", "a2")


def field_view(rng, cam, C, target, n=500, relief_m=4.0, noise_px=0.1):
    """A wall with relief seen by `cam` from C: R, X (n, 3), measured pixels (n, 2) with noise."""
    C = np.asarray(C, float)
    R = look_at(C, target, np.radians(10.0))
    dist = np.linalg.norm(np.asarray(target) - C)
    half = 1.3 * dist * cam.sensor.half_diagonal_mm / cam.f_mm
    X = np.asarray(target) + np.column_stack(
        [
            rng.uniform(-half, half, 20 * n),
            rng.uniform(-2, relief_m - 2, 20 * n),
            rng.uniform(-half, half, 20 * n),
        ]
    )
    uv = cam.project(X, R, C)
    s = cam.sensor
    inside = np.all((uv > 10) & (uv < [s.width_px - 11, s.height_px - 11]), axis=1)
    X, uv = X[inside][:n], uv[inside][:n]
    assert len(X) == n
    return R, X, uv + rng.normal(0.0, noise_px, uv.shape)


WIDE_VIEW = ((1.0, -12.0, 6.0), (0.0, 2.0, 6.0))
IXU_VIEW = ((3.0, -60.0, 9.0), (0.5, 2.0, 7.0))


# --------------------------------------------------------------------------------------
# the linear fit itself
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "camera, names",
    [
        (IXU, FIELD),  # the field method's set
        (
            Camera.from_dict(
                WIDE_SENSOR,
                {
                    "f_mm": 24.0,
                    "xp_mm": 0.05,
                    "yp_mm": -0.03,
                    "k0": 1e-4,
                    "k1": 3.5e-5,
                    "k2": -3e-8,
                    "k3": 1e-11,
                    "p1": 2e-6,
                    "p2": -3e-6,
                    "b1": 3e-5,
                    "b2": -1e-5,
                },
            ),
            ("k0", "k1", "k2", "k3", "p1", "p2", "b1", "b2"),
        ),  # the goniometer's set
    ],
    ids=["field-set", "goniometer-set"],
)
def test_exact_recovery_from_the_true_model_at_the_true_principal_point(camera, names):
    xy = camera.sensor.pixel_to_mm(camera.sensor.grid_px(21, 15))
    q = correct(xy, camera.params)  # the contract's ideal points, relative to the principal point
    fit = distortion_lsq(xy, q, camera.params[1], camera.params[2], names)
    assert list(fit.coefficients) == list(names)
    for k in names:
        # exact data: only round-off (the scaled system's condition number is ~1e4)
        assert fit.coefficients[k] == pytest.approx(camera.params[INDEX[k]], rel=1e-8), k
    assert fit.rms_mm < 1e-12 and fit.residuals_mm.shape == xy.shape


def test_a_subset_fits_what_it_can_and_reports_the_misfit():
    xy = IXU_SENSOR.pixel_to_mm(IXU_SENSOR.grid_px(21, 15))
    only_k1 = params_from_dict({"xp_mm": 0.27555, "yp_mm": 0.040671, "k1": -1.1177e-5})
    fit = distortion_lsq(xy, correct(xy, only_k1), 0.27555, 0.040671, ("k1",))
    assert fit.coefficients == {"k1": pytest.approx(-1.1177e-5, rel=1e-12)} and fit.rms_mm < 1e-12
    # the full iXU150 correction (~40 px in the corners) fitted with k1 alone: ~0.5 px remain
    fit = distortion_lsq(xy, correct(xy, IXU.params), 0.27555, 0.040671, ("k1",))
    assert 0.2 < fit.rms_mm / 0.0053 < 2.0
    assert np.allclose(
        np.sqrt(np.mean(np.sum(fit.residuals_mm**2, axis=1))), fit.rms_mm, rtol=1e-12
    )


def test_noisy_fit_is_within_four_reported_sigma():
    rng = np.random.default_rng(3)
    xy = IXU_SENSOR.pixel_to_mm(rng.uniform([0, 0], [8207, 6279], (2000, 2)))
    q = correct(xy, IXU.params) + rng.normal(0, 0.1 * 0.0053, xy.shape)  # 0.1 px
    fit = distortion_lsq(xy, q, 0.27555, 0.040671, FIELD)
    assert fit.rms_mm / 0.0053 == pytest.approx(0.1 * np.sqrt(2), rel=0.1)
    for k in FIELD:
        assert 0 < fit.sigma[k] and abs(fit.coefficients[k] - IXU_TRUTH[k]) < 4 * fit.sigma[k], k


def test_ideal_points_follow_the_contract_collinearity():
    rng = np.random.default_rng(4)
    R, X, uv = field_view(rng, IXU, *IXU_VIEW, n=100, noise_px=0.0)
    C = np.array(IXU_VIEW[0])
    q = ideal_points_mm(X, R, C, 146.39)
    # the measured points (fieldcal.model.camera.project) corrected by the contract's model
    assert np.abs(correct(IXU_SENSOR.pixel_to_mm(uv), IXU.params) - q).max() < 1e-9
    behind = ideal_points_mm(2 * C - X[:3], R, C, 146.39)
    assert np.isnan(behind).all()


def test_fold_k0_is_exact():
    rng = np.random.default_rng(5)
    xy = rng.uniform(-15, 15, (200, 2))
    coef = {"k0": 2e-3, "k1": 3e-5, "k2": -2e-8, "p1": 1e-6, "a2": 2e-5}
    f2, folded = fold_k0(24.0, coef)
    assert "k0" not in folded and f2 == pytest.approx(24.0 / 1.002, rel=1e-15)
    p = params_from_dict({**coef, "xp_mm": 0.1, "yp_mm": -0.2})
    p2 = params_from_dict({**folded, "xp_mm": 0.1, "yp_mm": -0.2})
    # same ray direction q / f for every measured point
    assert np.abs(correct(xy, p) / 24.0 - correct(xy, p2) / f2).max() < 1e-15


def test_refusals_name_what_is_wrong():
    xy = IXU_SENSOR.pixel_to_mm(IXU_SENSOR.grid_px(11, 9))
    q = correct(xy, IXU.params)
    with pytest.raises(InputError, match=r"cannot fit \['f_mm'\] linearly"):
        distortion_lsq(xy, q, 0.0, 0.0, ("f_mm", "k1"))
    with pytest.raises(InputError, match=r"cannot fit \['k9'\]"):
        distortion_lsq(xy, q, 0.0, 0.0, ("k9",))
    with pytest.raises(InputError, match="distinct"):
        distortion_lsq(xy, q, 0.0, 0.0, ("k1", "k1"))
    bad = q.copy()
    bad[4, 0] = np.nan
    with pytest.raises(InputError, match=r"img3: distortion_lsq: NaN"):
        distortion_lsq(xy, bad, 0.0, 0.0, where="img3")
    with pytest.raises(InputError, match=r"shape \(n, 2\)"):
        distortion_lsq(xy, q[:-1], 0.0, 0.0)
    with pytest.raises(
        GeometryError, match=r"img3: distortion_lsq: 3 points give 6 equations for 7"
    ):
        distortion_lsq(xy[:3], q[:3], 0.0, 0.0, where="img3")
    # k0's column is b1's plus a2's: not separable
    with pytest.raises(GeometryError, match=r"coefficients \[.*'k0'.*\] cannot be separated"):
        distortion_lsq(xy, q, 0.0, 0.0, ("k0", "k1", "a2", "b1"))
    assert set(DISTORTION_NAMES) == {"k0", "k1", "k2", "k3", "p1", "p2", "a1", "a2", "b1", "b2"}


# --------------------------------------------------------------------------------------
# on DLT output (METHODS steps 1-2 together)
# --------------------------------------------------------------------------------------
def corner_error_px(camera, truth):
    """Largest difference of the correction fields over the sensor [px] (same principal point)."""
    xy = truth.sensor.pixel_to_mm(truth.sensor.grid_px(21, 15))
    return (
        np.abs(correction(xy, camera.params) - correction(xy, truth.params)).max()
        / truth.sensor.pixel_mm
    )


def test_one_shot_fit_on_dlt_output_needs_the_scale_term():
    rng = np.random.default_rng(6)
    R, X, uv = field_view(rng, WIDE, *WIDE_VIEW)
    r = dlt(X, uv, WIDE_SENSOR)
    xy = WIDE_SENSOR.pixel_to_mm(uv)
    q = ideal_points_mm(X, r.R_world_to_camera, r.center_m, r.f_mm)
    # the paper's step 2 as printed: the DLT's f has absorbed part of the radial distortion as
    # a scale that k1..k3 cannot represent, and k1 comes out with the wrong sign (~ -2x truth)
    plain = distortion_lsq(xy, q, r.xp_mm, r.yp_mm, ("k1", "k2", "k3")).coefficients
    assert plain["k1"] < 0 < WIDE_TRUTH["k1"]
    # with k0 fitted and folded into f, k1 is close (<= 13 % over 10 seeds)
    f_mm, coef = fold_k0(
        r.f_mm, distortion_lsq(xy, q, r.xp_mm, r.yp_mm, ("k0", "k1", "k2", "k3")).coefficients
    )
    assert coef["k1"] == pytest.approx(WIDE_TRUTH["k1"], rel=0.25)
    assert f_mm == pytest.approx(24.0, abs=0.08)


def test_initial_camera_recovers_the_wide_angle_lens():
    rng = np.random.default_rng(7)
    R, X, uv = field_view(rng, WIDE, *WIDE_VIEW)
    iv = initial_camera(X, uv, WIDE_SENSOR, names=("k1", "k2", "k3"), where="img")
    est = iv.camera.to_dict()
    # tolerances: about twice the largest error over 10 seeds (0.1 px noise, one image)
    assert est["k1"] == pytest.approx(3.5e-5, rel=0.07)
    assert est["f_mm"] == pytest.approx(24.0, abs=0.003)
    assert abs(est["xp_mm"]) < 0.002 and abs(est["yp_mm"]) < 0.002
    assert np.linalg.norm(iv.center_m - WIDE_VIEW[0]) < 0.002
    assert corner_error_px(iv.camera, WIDE) < 1.0  # of ~20 px of distortion
    assert iv.rms_px < 0.16 and iv.converged and iv.iterations <= 5  # the noise: 0.14 px


def test_initial_camera_on_the_ixu150_and_robustly():
    rng = np.random.default_rng(8)
    R, X, uv = field_view(rng, IXU, *IXU_VIEW)
    bad = rng.choice(len(X), 15, replace=False)
    uv[bad] += rng.uniform(30, 60, (15, 2))
    iv = initial_camera(X, uv, IXU_SENSOR, names=FIELD, robust=True)
    assert np.array_equal(np.flatnonzero(~iv.inliers), np.sort(bad))
    est = iv.camera.to_dict()
    # one image of a long lens: f and k1 come out well (k1 <= 3 %, f <= 0.02 mm over 10 seeds);
    # the principal point trades off against the decentering terms (up to 0.4 mm) and is
    # left to the bundle adjustment
    assert est["k1"] == pytest.approx(-1.1177e-5, rel=0.06)
    assert est["f_mm"] == pytest.approx(146.39, abs=0.05)
    assert iv.rms_px < 0.4
