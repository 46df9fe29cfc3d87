"""DLT, robust DLT, planar pose and Zhang's focal length against exact synthetic truth, OpenCV."""

import inspect

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from fieldcal.errors import GeometryError, InputError
from fieldcal.field.dlt import dlt, dlt_robust, dlt_robust_many, zhang_focal
from fieldcal.field.geometry import is_collinear, is_coplanar, plane_frame
from fieldcal.field.resection import planar_pose
from fieldcal.model.camera import Camera, Sensor
from fieldcal.model.opencv_frames import ideal_pixels, opencv_camera_matrix, pose_from_opencv, pose_to_opencv
from fieldcal.synthetic.field import IXU150_TABLE1, add_blunders, look_at, wide_field

# Phase One iXU150 as calibrated in METHODS Table 1, and a wide-angle camera with about
# 20 px of radial distortion in the corners.
IXU_SENSOR = Sensor(8208, 6280, 5.3)
IXU = Camera.from_dict(IXU_SENSOR, IXU150_TABLE1)
WIDE_SENSOR = Sensor(6000, 4000, 3.9)
WIDE = Camera.from_dict(WIDE_SENSOR, {"f_mm": 24.0, "k1": 3.5e-5, "k2": -3e-8, "k3": 1e-11})


def pinhole(camera):
    """The same camera without distortion (f, xp, yp kept)."""
    p = camera.params.copy()
    p[3:] = 0.0
    return Camera(camera.sensor, p)


def wall_view(rng, camera, pose, n, relief_m=3.0, width_m=60.0, noise_px=0.0):
    """Points on a wall (world X right, Z up, relief along +Y) seen by `camera`.

    pose = (C, target, roll_deg). Returns R, X (n, 3) inside the image (20 px margin),
    uv (n, 2) exact or with Gaussian noise of `noise_px` per coordinate.
    """
    C, target, roll_deg = pose
    C = np.asarray(C, float)
    R = look_at(C, target, np.radians(roll_deg))
    X = np.column_stack(
        [
            rng.uniform(-width_m / 2, width_m / 2, 40 * n),
            rng.uniform(0, relief_m, 40 * n),
            rng.uniform(-5.0, 35.0, 40 * n),
        ]
    )
    uv = camera.project(X, R, C)
    s = camera.sensor
    inside = np.all((uv > 20) & (uv < [s.width_px - 21, s.height_px - 21]), axis=1)
    X, uv = X[inside][:n], uv[inside][:n]
    assert len(X) == n, "scene too small for the requested number of points"
    return R, X, uv + rng.normal(0.0, noise_px, uv.shape)


# (camera centre, target, roll): the paper's ~60 m, from the ground, from the roof, rolled
POSES = [
    ((3.0, -60.0, 9.0), (0.5, 0.0, 7.0), 0.0),
    ((-20.0, -55.0, 1.5), (-5.0, 0.0, 12.0), 15.0),
    ((15.0, -58.0, 25.0), (8.0, 0.0, 10.0), -90.0),
]


def dlt_sigma(camera, R, C, X, noise_px):
    """First-order standard deviations of (f, xp, yp) [mm] and C [m] of an 11-parameter camera.

    The projection is parametrised as OpenCV's K (alpha, beta, skew, cx, cy), a rotation
    vector (OpenCV frame) and C; the Jacobian by central differences, the covariance
    noise^2 (J^T J)^-1 (the Gauss-Markov bound that a good DLT should reach).
    Independent of fieldcal.field.dlt.
    """
    K = opencv_camera_matrix(camera)
    rvec, _ = pose_to_opencv(R, C)
    theta = np.concatenate([[K[0, 0], K[1, 1], 0.0, K[0, 2], K[1, 2]], rvec, C])

    def proj(t):
        Kt = np.array([[t[0], t[2], t[3]], [0, t[1], t[4]], [0, 0, 1.0]])
        Rcv, _ = cv2.Rodrigues(t[5:8])
        h = (X - t[8:]) @ (Kt @ Rcv).T
        return (h[:, :2] / h[:, 2:]).ravel()

    steps = np.array([1e-3, 1e-3, 1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7, 1e-5, 1e-5, 1e-5])
    J = np.stack(
        [
            (proj(theta + np.eye(11)[j] * h) - proj(theta - np.eye(11)[j] * h)) / (2 * h)
            for j, h in enumerate(steps)
        ],
        axis=1,
    )
    cov = noise_px**2 * np.linalg.inv(J.T @ J)
    d = camera.sensor.pixel_mm
    var_f = 0.25 * d**2 * (cov[0, 0] + cov[1, 1] + 2 * cov[0, 1])
    return np.sqrt(var_f), d * np.sqrt(cov[3, 3]), d * np.sqrt(cov[4, 4]), np.sqrt(np.diag(cov)[8:])


# --------------------------------------------------------------------------------------
# conventions and exact recovery
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("pose", POSES)
def test_dlt_recovers_exact_camera_noise_free(pose):
    rng = np.random.default_rng(10)
    cam = pinhole(IXU)
    C = np.array(pose[0])
    R, X, uv = wall_view(rng, cam, pose, 400)
    r = dlt(X, uv, IXU_SENSOR, where="images/a.tif")
    # near machine precision: the normalised DLT system has a condition number of ~1e5
    assert r.f_mm == pytest.approx(146.39, abs=1e-9)
    assert r.xp_mm == pytest.approx(0.27555, abs=1e-9)
    assert r.yp_mm == pytest.approx(0.040671, abs=1e-9)
    assert r.aspect == pytest.approx(1.0, abs=1e-12) and abs(r.skew) < 1e-12
    assert np.abs(r.R_world_to_camera - R).max() < 1e-12
    assert np.linalg.det(r.R_world_to_camera) == pytest.approx(1.0, abs=1e-12)
    assert np.abs(r.center_m - C).max() < 1e-9
    assert r.rms_px < 1e-8 and r.inliers.all()
    # P reproduces fieldcal's projection of points it was not fitted to, in front of it
    Xn = X[:50] + rng.normal(0, 2.0, (50, 3))
    h = np.c_[Xn, np.ones(50)] @ r.P.T
    assert np.all(h[:, 2] > 0)
    assert np.abs(h[:, :2] / h[:, 2:] - cam.project(Xn, R, C)).max() < 1e-7


def test_dlt_decomposition_agrees_with_opencv():
    rng = np.random.default_rng(11)
    cam = pinhole(IXU)
    R, X, uv = wall_view(rng, cam, POSES[1], 300, noise_px=0.1)
    r = dlt(X, uv, IXU_SENSOR)
    K, R_cv, c_h = cv2.decomposeProjectionMatrix(r.P)[:3]
    K = K / K[2, 2]
    assert np.allclose(K, r.K_px, rtol=1e-9, atol=1e-6)
    assert np.allclose(np.diag([1, -1, -1]) @ R_cv, r.R_world_to_camera, atol=1e-9)
    assert np.allclose(c_h[:3, 0] / c_h[3, 0], r.center_m, atol=1e-7)
    fov_x, fov_y, f_mm, pp_mm, aspect = cv2.calibrationMatrixValues(
        r.K_px, (8208, 6280), 8208 * 0.0053, 6280 * 0.0053
    )
    assert f_mm == pytest.approx(r.K_px[0, 0] * 0.0053, rel=1e-12)  # OpenCV's f is alpha d
    assert aspect == pytest.approx(r.aspect, rel=1e-12)
    assert pp_mm[0] - 8207 / 2 * 0.0053 == pytest.approx(r.xp_mm, abs=1e-9)  # x right in both
    assert -(pp_mm[1] - 6279 / 2 * 0.0053) == pytest.approx(r.yp_mm, abs=1e-9)  # y flips


def test_opencv_interop_projects_like_fieldcal_and_round_trips_poses():
    rng = np.random.default_rng(12)
    R, X, uv = wall_view(rng, IXU, POSES[2], 200)
    rvec, tvec = pose_to_opencv(R, np.array(POSES[2][0]))
    uv_cv, _ = cv2.projectPoints(X, rvec, tvec, opencv_camera_matrix(IXU), None)
    # OpenCV's pinhole projection == fieldcal's projection with the distortion removed
    assert np.abs(uv_cv.reshape(-1, 2) - ideal_pixels(uv, IXU)).max() < 1e-6
    R2, C2 = pose_from_opencv(rvec, tvec)
    assert np.allclose(R2, R, atol=1e-14) and np.allclose(C2, POSES[2][0], atol=1e-12)
    # without distortion the ideal pixels are the measured ones, and OpenCV's pinhole
    # projection with opencv_camera_matrix lands on fieldcal's pixels (xp, yp != 0 here)
    cam = pinhole(IXU)
    uv0 = cam.project(X, R, POSES[2][0])
    assert np.abs(ideal_pixels(uv0, cam) - uv0).max() < 1e-9
    uv_cv, _ = cv2.projectPoints(X, rvec, tvec, opencv_camera_matrix(cam), None)
    assert np.abs(uv_cv.reshape(-1, 2) - uv0).max() < 1e-6


def test_dlt_with_noise_is_within_four_predicted_sigma():
    rng = np.random.default_rng(13)
    cam = pinhole(IXU)
    C = np.array(POSES[0][0])
    R, X, uv = wall_view(rng, cam, POSES[0], 500, noise_px=0.1)
    r = dlt(X, uv, IXU_SENSOR)
    s_f, s_xp, s_yp, s_C = dlt_sigma(cam, R, C, X, 0.1)
    assert 0.0 < s_f < 0.05 and s_C.max() < 0.05  # the geometry does determine the camera
    assert abs(r.f_mm - 146.39) < 4 * s_f
    assert abs(r.xp_mm - 0.27555) < 4 * s_xp
    assert abs(r.yp_mm - 0.040671) < 4 * s_yp
    assert np.all(np.abs(r.center_m - C) < 4 * s_C)
    # the fit leaves the noise: sqrt(2) x 0.1 px per point, minus 11 of 1000 degrees of freedom
    assert r.rms_px == pytest.approx(0.1 * np.sqrt(2), rel=0.1)


def paper_dlt_P(X, uv):
    """The paper's eq. 2 as printed: eigenvector of G^T G, no normalisation (the reference)."""
    Xh = np.c_[X, np.ones(len(X))]
    z = np.zeros_like(Xh)
    G = np.concatenate([np.c_[Xh, z, -uv[:, :1] * Xh], np.c_[z, Xh, -uv[:, 1:] * Xh]])
    _, V = np.linalg.eigh(G.T @ G)
    return V[:, 0].reshape(3, 4)


def f_of_P(P, d):
    K = cv2.decomposeProjectionMatrix(P)[0]
    K = K / K[2, 2]
    return 0.5 * (K[0, 0] + K[1, 1]) * d


def test_hartley_normalisation_is_what_makes_the_dlt_accurate_at_survey_magnitudes():
    rng = np.random.default_rng(14)
    cam = pinhole(IXU)
    R, X, uv = wall_view(rng, cam, POSES[0], 400)
    # tens of metres, noise-free: the un-normalised normal equations lose 9 digits
    f_paper = f_of_P(paper_dlt_P(X, uv), 0.0053)
    assert abs(f_paper - 146.39) > 1e-6
    assert abs(dlt(X, uv, IXU_SENSOR).f_mm - 146.39) < 1e-9
    # a local survey grid with a false origin of (1000, 1000, 100) m and 0.1 px noise
    Xg = X + [1000.0, 1000.0, 100.0]
    uvn = uv + rng.normal(0, 0.1, uv.shape)
    s_f = dlt_sigma(cam, R, np.array(POSES[0][0]), X, 0.1)[0]
    f_paper = f_of_P(paper_dlt_P(Xg, uvn), 0.0053)
    # typically hundreds of sigma off (>= 9.6 sigma over 12 seeds); ours is within 4
    assert abs(f_paper - 146.39) > 5 * s_f
    assert abs(dlt(Xg, uvn, IXU_SENSOR).f_mm - 146.39) < 4 * s_f


# --------------------------------------------------------------------------------------
# refusals
# --------------------------------------------------------------------------------------
def test_dlt_refuses_too_few_coplanar_collinear_and_nan_points():
    rng = np.random.default_rng(15)
    R, X, uv = wall_view(rng, pinhole(IXU), POSES[0], 40)
    name = "images/IMG_0007.tif"
    with pytest.raises(
        GeometryError, match=r"images/IMG_0007\.tif: DLT needs at least 6 points, got 5"
    ):
        dlt(X[:5], uv[:5], IXU_SENSOR, where=name)
    flat = X.copy()
    flat[:, 1] = 0.0
    with pytest.raises(GeometryError, match=r"IMG_0007\.tif: .*coplanar.*planar_pose"):
        dlt(flat, uv, IXU_SENSOR, where=name)
    line = np.outer(np.linspace(0, 10, 40), [1.0, 0.2, 0.5])
    with pytest.raises(GeometryError, match=r"IMG_0007\.tif: .*collinear"):
        dlt(line, uv, IXU_SENSOR, where=name)
    bad = uv.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match=r"IMG_0007\.tif: DLT: 1 point\(s\) with NaN .*rows \[3\]"):
        dlt(X, bad, IXU_SENSOR, where=name)
    Xinf = X.copy()
    Xinf[0, 0] = np.inf
    with pytest.raises(InputError, match="infinite"):
        dlt_robust(Xinf, uv, IXU_SENSOR, where=name)
    with pytest.raises(InputError, match="40 world points but 39 image points"):
        dlt(X, uv[:-1], IXU_SENSOR, where=name)


def test_dlt_refuses_a_mirrored_world_frame():
    rng = np.random.default_rng(16)
    R, X, uv = wall_view(rng, pinhole(IXU), POSES[0], 100)
    with pytest.raises(GeometryError, match="left-handed"):
        dlt(X * [1.0, -1.0, 1.0], uv, IXU_SENSOR, where="a")


def test_coplanarity_and_collinearity_helpers():
    rng = np.random.default_rng(17)
    P = rng.uniform(-10, 10, (50, 3))
    assert not is_coplanar(P) and not is_collinear(P)
    flat = P.copy()
    flat[:, 2] = 1e-4 * rng.normal(size=50)  # 0.1 mm on a 20 m field: coplanar
    R = Rotation.from_rotvec([0.3, -1.0, 0.2]).as_matrix()
    assert is_coplanar(flat @ R.T + 500.0) and not is_collinear(flat @ R.T)
    line = np.outer(rng.uniform(-10, 10, 50), [0.3, 0.4, 1.0]) + 1e-5 * rng.normal(size=(50, 3))
    assert is_collinear(line) and is_coplanar(line)
    origin, B = plane_frame(flat @ R.T + 500.0)
    assert np.allclose(B.T @ B, np.eye(3), atol=1e-12) and np.linalg.det(B) == pytest.approx(1.0)
    assert abs(abs(B[:, 2] @ R[:, 2]) - 1.0) < 1e-9  # the normal is the plane's normal


# --------------------------------------------------------------------------------------
# robust DLT
# --------------------------------------------------------------------------------------
def corrupt(rng, uv, fraction):
    """Blunders: half swapped identifications (pairs exchange pixels), half shifted 20-80 px."""
    n = len(uv)
    idx = rng.choice(n, int(round(fraction * n)), replace=False)
    half = len(idx) // 2 - (len(idx) // 2) % 2
    out = uv.copy()
    sw = idx[:half].reshape(-1, 2)
    out[sw[:, 0]], out[sw[:, 1]] = uv[sw[:, 1]], uv[sw[:, 0]]
    sh = idx[half:]
    ang = rng.uniform(0, 2 * np.pi, len(sh))
    out[sh] += rng.uniform(20, 80, len(sh))[:, None] * np.c_[np.cos(ang), np.sin(ang)]
    bad = np.zeros(n, bool)
    bad[idx] = np.linalg.norm(out[idx] - uv[idx], axis=1) > 10  # a swap of neighbours is no blunder
    return out, bad


def test_robust_dlt_rejects_three_percent_blunders():
    rng = np.random.default_rng(18)
    cam = pinhole(IXU)
    C = np.array(POSES[1][0])
    R, X, uv = wall_view(rng, cam, POSES[1], 600, noise_px=0.1)
    uvb, bad = corrupt(rng, uv, 0.03)
    assert bad.sum() >= 16
    r = dlt_robust(X, uvb, IXU_SENSOR, where="img")
    assert np.array_equal(r.inliers, ~bad)  # 0.1 px noise: every good point is within 2 px
    s_f, s_xp, s_yp, s_C = dlt_sigma(cam, R, C, X[~bad], 0.1)
    assert abs(r.f_mm - 146.39) < 4 * s_f
    assert np.all(np.abs(r.center_m - C) < 4 * s_C)
    assert r.rms_px < 0.2
    # and the blunders would have spoiled the plain DLT (or even mirrored it)
    try:
        spoiled = dlt(X, uvb, IXU_SENSOR).f_mm
    except GeometryError as exc:
        assert "behind the camera" in str(exc)
    else:
        assert abs(spoiled - 146.39) > 10 * s_f


def test_robust_dlt_keeps_distorted_corner_points_of_a_wide_angle_lens():
    rng = np.random.default_rng(19)
    C = np.array([1.0, -12.0, 6.0])
    R, X, uv = wall_view(rng, WIDE, (C, (0.0, 1.5, 6.0), 0.0), 500, noise_px=0.1)
    uvb, bad = corrupt(rng, uv, 0.03)
    r = dlt_robust(X, uvb, WIDE_SENSOR)
    # the uncorrected ~20 px distortion leaves a few px of residual: no good point is lost
    assert np.array_equal(r.inliers, ~bad)
    clean = dlt(X[~bad], uvb[~bad], WIDE_SENSOR)
    assert r.f_mm == pytest.approx(clean.f_mm, abs=1e-9)


def test_robust_dlt_does_not_take_a_least_squares_fit_pulled_by_swapped_ids():
    # images/wide_006.tif of wide_field(0) with 2 % blunders: 8 swapped ids among its 125
    # points pull the least-squares DLT so far (f 13.7 mm, aspect 6, skew 3.5) that the robust
    # scale of its own residuals (1260 px) keeps every point; the fast path took it
    sf = wide_field(seed=0)
    bad, info = add_blunders(sf, fraction=0.02, seed=10)
    d = bad.data
    k = np.flatnonzero(d.obs.image == 5)
    swapped = np.isin(k, info.swapped_observations)
    assert swapped.sum() == 8
    X, uv = d.targets.xyz_m[d.obs.target[k]], d.obs.uv_px[k]
    r = dlt_robust(X, uv, d.sensor, seed=5)
    assert not r.inliers[swapped].any()
    clean = dlt(X[~swapped], uv[~swapped], d.sensor)
    # the DLT has no distortion model: the clean one is 0.4 mm short of 24 mm and 0.1 m off
    assert r.f_mm == pytest.approx(clean.f_mm, abs=0.5)
    assert np.linalg.norm(r.center_m - sf.center_m[5]) < 0.2


# --------------------------------------------------------------------------------------
# flat fields
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("camera", [WIDE, IXU], ids=["wide", "ixu150"])
def test_planar_pose_recovers_the_pose_and_matches_opencv(camera):
    rng = np.random.default_rng(20)
    dist = 12.0 if camera is WIDE else 60.0
    C = np.array([4.0, -dist, 3.0])
    R, X, uv = wall_view(rng, camera, (C, (0.0, 0.0, 8.0), 20.0), 200, relief_m=0.0)
    # an arbitrary plane in 3-D: rotate and shift the whole scene
    Q = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_matrix()
    Xw, Cw, Rw = X @ Q.T + [300.0, -200.0, 50.0], Q @ C + [300.0, -200.0, 50.0], R @ Q.T
    R_est, C_est, rms = planar_pose(Xw, uv, camera, where="img")
    assert np.abs(R_est - Rw).max() < 1e-9 and np.abs(C_est - Cw).max() < 1e-7 and rms < 1e-6
    noisy = uv + rng.normal(0, 0.1, uv.shape)
    R_est, C_est, rms = planar_pose(Xw, noisy, camera)
    assert rms == pytest.approx(0.1 * np.sqrt(2), rel=0.15)
    # same data through OpenCV's iterative solver started from the truth: same optimum.
    # (Centred coordinates: on the raw 300 m offsets OpenCV's LM stops ~1e-5 rad short.)
    K = opencv_camera_matrix(camera)
    m = Xw.mean(axis=0)
    rvec0, tvec0 = pose_to_opencv(Rw, Cw - m)
    ok, rvec, tvec = cv2.solvePnP(
        Xw - m,
        ideal_pixels(noisy, camera),
        K,
        None,
        rvec0.copy(),
        tvec0.copy(),
        useExtrinsicGuess=True,
        flags=cv2.SOLVEPNP_ITERATIVE,
    )
    R_cv, C_cv = pose_from_opencv(rvec, tvec)
    # both stop within ~1e-7 of the minimum's cost: 1e-6 rad, 0.1 mm
    assert np.abs(R_est - R_cv).max() < 1e-6 and np.abs(C_est - (C_cv + m)).max() < 1e-4
    # and within a plausible distance of the truth: 0.1 px at 60 m is a few mm
    assert np.linalg.norm(C_est - Cw) < 0.005 * dist


def test_planar_pose_with_nominal_intrinsics_is_a_usable_initial_value():
    rng = np.random.default_rng(25)
    C = np.array([4.0, -60.0, 3.0])
    R, X, uv = wall_view(rng, IXU, (C, (0.0, 0.0, 8.0), 20.0), 200, relief_m=0.0, noise_px=0.1)
    nominal = Camera.from_dict(IXU_SENSOR, {"f_mm": 150.0})  # no calibration at all
    R_est, C_est, rms = planar_pose(X, uv, nominal)
    # a wrong f scales the distance to the plane (150 / 146.39 = 1.025; the ~40 px of
    # uncorrected distortion take another ~0.4 %), the attitude stays within a few 0.1 deg
    assert -C_est[1] / -C[1] == pytest.approx(150.0 / 146.39, abs=0.01)
    assert np.degrees(Rotation.from_matrix(R_est @ R.T).magnitude()) < 0.5
    assert 1.0 < rms < 20.0  # and the residuals say that the camera is not right


def test_planar_pose_refuses_non_coplanar_and_too_few_points():
    rng = np.random.default_rng(21)
    R, X, uv = wall_view(rng, IXU, POSES[0], 30)
    with pytest.raises(GeometryError, match=r"img7: planar pose: .*not coplanar"):
        planar_pose(X, uv, IXU, where="img7")
    with pytest.raises(GeometryError, match=r"img7: planar pose needs at least 4 points, got 3"):
        planar_pose(X[:3], uv[:3], IXU, where="img7")


def plane_views(rng, camera, n_views, tilt_deg, n=150, noise_px=0.1):
    """Views of a tilted plane (not Z = 0, far from the origin), `tilt_deg` off its normal."""
    normal = np.array([0.2, -1.0, 0.3]) / np.linalg.norm([0.2, -1.0, 0.3])
    e1 = np.cross(normal, [0, 0, 1.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    centre = np.array([250.0, 80.0, 30.0])
    dist = 10.0 if camera.f_mm < 50 else 60.0
    views = []
    for az in np.linspace(0, 2 * np.pi, n_views, endpoint=False) + rng.uniform(0, 1):
        t = np.deg2rad(tilt_deg)
        C = centre + dist * (np.cos(t) * normal + np.sin(t) * (np.cos(az) * e1 + np.sin(az) * e2))
        R = look_at(C, centre, np.radians(rng.uniform(-30, 30)), up=normal)
        half = dist * camera.sensor.half_diagonal_mm / camera.f_mm * 1.5  # beyond the footprint
        ab = rng.uniform(-half, half, (40 * n, 2))
        X = centre + ab[:, :1] * e1 + ab[:, 1:] * e2
        uv = camera.project(X, R, C)
        s = camera.sensor
        inside = np.all((uv > 0) & (uv < [s.width_px - 1, s.height_px - 1]), axis=1)
        views.append((X[inside][:n], uv[inside][:n] + rng.normal(0, noise_px, (n, 2))))
    return views


@pytest.mark.parametrize(
    "camera, n_views, tol",
    [
        # tolerances from the largest error over 10 seeds (measured), with margin:
        (pinhole(WIDE), 3, 0.002),  # 0.1 px noise only: <= 0.008 % at 30 deg
        (WIDE, 4, 0.02),  # 20 px of uncorrected distortion: a bias of <= 0.8 %
        (IXU, 5, 0.03),  # long lens, pp 52 px off centre, 40 px distortion: <= 1.5 %
    ],
    ids=["wide-pinhole", "wide-distorted", "ixu150"],
)
def test_zhang_focal_from_views_of_a_plane(camera, n_views, tol):
    rng = np.random.default_rng(22)
    views = plane_views(rng, camera, n_views, tilt_deg=30.0)
    f = zhang_focal(views, camera.sensor)
    assert f == pytest.approx(camera.f_mm, rel=tol)


def test_zhang_focal_agrees_with_opencv_calibrate_camera():
    rng = np.random.default_rng(23)
    cam = pinhole(WIDE)
    views = plane_views(rng, cam, 4, tilt_deg=35.0)
    f = zhang_focal(views, WIDE_SENSOR)
    obj, img = [], []
    for X, uv in views:
        origin, B = plane_frame(X)
        P = (X - origin) @ B
        obj.append(np.c_[P[:, :2], np.zeros(len(P))].astype(np.float32))
        img.append(uv.astype(np.float32))
    K0 = np.array([[5000.0, 0, 2999.5], [0, 5000.0, 1999.5], [0, 0, 1]])
    flags = (
        cv2.CALIB_USE_INTRINSIC_GUESS
        | cv2.CALIB_FIX_PRINCIPAL_POINT
        | cv2.CALIB_FIX_ASPECT_RATIO
        | cv2.CALIB_ZERO_TANGENT_DIST
        | cv2.CALIB_FIX_K1
        | cv2.CALIB_FIX_K2
        | cv2.CALIB_FIX_K3
    )
    _, K, *_ = cv2.calibrateCamera(obj, img, (6000, 4000), K0, np.zeros(5), flags=flags)
    # OpenCV's maximum-likelihood f and the closed form agree to the noise level (0.1 px)
    assert f == pytest.approx(K[0, 0] * 0.0039, rel=1e-3)
    assert K[0, 0] * 0.0039 == pytest.approx(24.0, rel=1e-3)


def test_zhang_focal_refuses_degenerate_input():
    rng = np.random.default_rng(24)
    views = plane_views(rng, pinhole(WIDE), 3, tilt_deg=0.0, noise_px=0.0)
    with pytest.raises(GeometryError, match=r"session-x: zhang_focal: .*fronto-parallel"):
        zhang_focal(views, WIDE_SENSOR, where="session-x")
    with pytest.raises(GeometryError, match="at least 2 views"):
        zhang_focal(views[:1], WIDE_SENSOR)
    R, X, uv = wall_view(rng, IXU, POSES[0], 30)
    with pytest.raises(GeometryError, match="view 1: needs >= 4 coplanar"):
        zhang_focal([views[0], (X, uv)], WIDE_SENSOR)


# --------------------------------------------------------------------------------------
# many images at once (the batched fast path against the per-image reference)
# --------------------------------------------------------------------------------------
def _views_of(data):
    groups = [np.flatnonzero(data.obs.image == i) for i in range(len(data.images))]
    return [(data.targets.xyz_m[data.obs.target[k]], data.obs.uv_px[k]) for k in groups]


def _assert_same_dlt(r, ref):
    assert np.array_equal(r.inliers, ref.inliers)
    for name in ("f_mm", "xp_mm", "yp_mm", "aspect", "skew", "rms_px"):
        assert getattr(r, name) == pytest.approx(getattr(ref, name), rel=1e-9, abs=1e-9), name
    for name, scale in (("R_world_to_camera", 1.0), ("K_px", np.abs(ref.K_px).max()), ("P", np.abs(ref.P).max()),
                        ("center_m", 1.0), ("residuals_px", 1.0)):
        assert np.allclose(getattr(r, name), getattr(ref, name), rtol=0, atol=1e-9 * scale), name


def test_dlt_robust_many_is_dlt_robust_image_by_image():
    # wide_field(0) with blunders in three images (swapped and shifted points: they leave the
    # fast path), one with 2 % blunders everywhere (swapped ids and moved targets: none takes
    # it), and degenerate images: coplanar, collinear, too few points, a mirrored image
    sf = wide_field(seed=0)
    d = sf.data
    views = _views_of(d)
    rng = np.random.default_rng(3)
    for i in (2, 5, 11):
        X, uv = views[i]
        views[i] = (X, corrupt(rng, uv, 0.05)[0])
    views += _views_of(add_blunders(sf, fraction=0.02, seed=10)[0].data)
    X0, uv0 = views[0]
    flat = X0.copy()
    flat[:, 1] = 0.0
    line = np.outer(np.linspace(0, 1, len(X0)), [1.0, 2.0, 3.0])
    mirrored = uv0.copy()
    mirrored[:, 0] = d.sensor.width_px - 1 - mirrored[:, 0]
    views += [(flat, uv0), (line, uv0), (X0[:5], uv0[:5]), (X0, mirrored),
              (X0[:20], uv0[:20] + rng.normal(0, 0.1, (20, 2)))]   # < 30 points: raw residuals
    wheres = [f"img{i}" for i in range(len(views))]
    seeds = list(range(len(views)))
    many = dlt_robust_many(views, d.sensor, wheres=wheres, seeds=seeds)
    fast = dlt_robust_many(views, d.sensor, wheres=wheres, seeds=seeds, fallback=False)
    n_fast = sum(r is not None for r in fast)
    assert n_fast == len(d.images) - 3             # the batch takes the clean ones, the blunders fall back
    assert all(fast[i] is None for i in (2, 5, 11))
    n_err = 0
    for i, (X, uv) in enumerate(views):
        try:
            ref = dlt_robust(X, uv, d.sensor, where=wheres[i], seed=seeds[i])
        except GeometryError as exc:
            assert isinstance(many[i], GeometryError) and str(many[i]) == str(exc)
            assert fast[i] is None
            n_err += 1
            continue
        _assert_same_dlt(many[i], ref)
        if fast[i] is not None:
            assert ref.inliers.all()
            _assert_same_dlt(fast[i], ref)
        else:
            assert many[i] is not fast[i]
    assert n_err >= 3                              # coplanar, collinear, too few points
    # bad input is refused as by dlt_robust
    with pytest.raises(InputError, match="NaN"):
        dlt_robust_many([views[1], (np.full((10, 3), np.nan), uv0[:10])], d.sensor)


def test_dlt_robust_many_fast_path_on_clean_images_matches_the_reference_closely():
    sf = wide_field(seed=0)
    views = _views_of(sf.data)
    fast = dlt_robust_many(views, sf.data.sensor, fallback=False)
    assert all(r is not None for r in fast)        # clean: every image takes the fast path
    for i, (X, uv) in enumerate(views):
        _assert_same_dlt(fast[i], dlt_robust(X, uv, sf.data.sensor, seed=i))


def test_batched_helpers_against_their_references():
    import scipy.linalg

    from fieldcal.field import dlt as D

    rng = np.random.default_rng(5)
    A = rng.normal(size=(20, 3, 3))
    R, Q = D._rq3(A)
    assert np.allclose(R @ Q, A, atol=1e-13)
    assert np.allclose(np.tril(R, -1), 0.0)
    assert np.allclose(Q @ np.swapaxes(Q, -1, -2), np.eye(3), atol=1e-13)
    for a, r, q in zip(A, R, Q, strict=True):                   # unique once the diagonal is positive
        r_ref, q_ref = scipy.linalg.rq(a)
        s, s_ref = np.sign(np.diag(r)), np.sign(np.diag(r_ref))
        assert np.allclose(r * s, r_ref * s_ref, atol=1e-12)
        assert np.allclose(s[:, None] * q, s_ref[:, None] * q_ref, atol=1e-12)
    counts = np.array([1, 2, 7, 8, 30])
    vals = rng.normal(size=(5, 30))
    valid = np.arange(30) < counts[:, None]
    med = D._batch_median(vals, valid, counts)
    assert np.array_equal(med, [np.median(v[:c]) for v, c in zip(vals, counts, strict=True)])
    Xh = D._homogeneous(rng.normal(size=(4, 25, 3)))
    uv = rng.normal(size=(4, 25, 2))
    G = D._design(Xh, uv)
    assert np.allclose(D._normal_matrix(Xh, uv), np.swapaxes(G, -1, -2) @ G, rtol=1e-13, atol=1e-12)
    uvn = rng.normal(size=(25, 2))
    assert np.allclose(D._monomials(uvn, 3), D._detrend_basis(uvn, 3), rtol=1e-14, atol=0)
    Xp = rng.normal(size=(3, 25, 2)) * 100
    w = np.arange(25) < np.array([25, 10, 7])[:, None]
    T = D._batch_normaliser(Xp, w, w.sum(axis=1))
    for t, x, m in zip(T, Xp, w, strict=True):
        assert np.allclose(t, D._normaliser(x[m]), rtol=1e-13)


def test_dlt_robust_many_takes_dlt_robusts_options_with_the_same_defaults():
    """The batched function repeats :func:`dlt_robust`'s keyword options (it passes them on to
    it for the images it does not take): the same names and the same defaults."""
    one, many = inspect.signature(dlt_robust).parameters, inspect.signature(dlt_robust_many).parameters
    shared = set(one) - {"X_world_m", "uv_px", "sensor", "where", "seed"}
    assert shared <= set(many)
    assert {n: many[n].default for n in shared} == {n: one[n].default for n in shared}
