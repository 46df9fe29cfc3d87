"""Exports: the target models against their own tools (OpenCV, pycolmap), the fits' honesty,
and the files read back."""

import json
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pycolmap
import pytest

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.errors import InputError
from fieldcal.model.camera import PARAM_NAMES, Camera, Sensor
from fieldcal.products.export import (
    EXACT_PX,
    export_text,
    fit_metashape,
    fit_opencv,
    metashape_project,
    normalised_rays,
    opencv_jacobian,
    opencv_project,
)
from fieldcal.synthetic.field import IXU150_TABLE1, WIDE_ANGLE
from fieldcal.synthetic.goniometer import make_scenario

H3D = make_scenario("h3d", raster_scale=0.25).camera()
WIDE = Camera.from_dict(Sensor(1500, 1000, 15.6), WIDE_ANGLE)      # ~5 px of barrel distortion
PAPER = Camera.from_dict(Sensor(8208, 6280, 5.3), IXU150_TABLE1)


def _doc(camera: Camera, version="20260110T090000Z-00000000-0000"):
    return {"schema": "fieldcal.calibration/1", "camera_id": "cam", "session_id": "s",
            "version": version, "method": "field", "created": "2026-01-10T09:00:00Z",
            "model": "fieldcal-brown/1", "sensor": camera.sensor.to_dict(),
            "parameters": camera.to_dict(), "sigma": dict.fromkeys(PARAM_NAMES)}


def _pixels(camera: Camera, n=3000, seed=99):
    s = camera.sensor
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.5, -0.5], [s.width_px - 0.5, s.height_px - 0.5], (n, 2))


# --------------------------------------------------------------------------------------
# the target models are the tools' models
# --------------------------------------------------------------------------------------
def test_opencv_projection_is_cv2_projectPoints():
    rng = np.random.default_rng(0)
    K = np.array([[2000.0, 0, 960.0], [0, 2010.0, 540.0], [0, 0, 1]])
    dist = np.array([-0.2, 0.05, 1e-3, -2e-3, 0.01, 0.02, -0.01, 0.005, 1e-3, -1e-3, 2e-3, 5e-4])
    n = rng.uniform(-0.4, 0.4, (500, 2))
    ref, _ = cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3), np.zeros(3),
                               K, dist)
    # same formula, two implementations: floating-point agreement
    np.testing.assert_allclose(opencv_project(n, K, dist), ref.reshape(-1, 2), atol=1e-9)
    np.testing.assert_allclose(opencv_project(n, K, dist[:5]),
                               cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3),
                                                 np.zeros(3), K, dist[:5])[0].reshape(-1, 2), atol=1e-9)


def test_metashape_model_is_opencv_with_p1_p2_swapped_and_centre_offsets():
    """Metashape's manual: x' += P1 (r^2 + 2x^2) + 2 P2 x y, i.e. OpenCV's p2, p1."""
    W, H = 1200, 900
    p = {"f": 1500.0, "cx": 3.5, "cy": -2.0, "k1": -0.1, "k2": 0.02, "k3": 0.003,
         "p1": 4e-4, "p2": -7e-4}
    n = np.random.default_rng(1).uniform(-0.3, 0.3, (200, 2))
    K = np.array([[1500.0, 0, (W - 1) / 2 + 3.5], [0, 1500.0, (H - 1) / 2 - 2.0], [0, 0, 1]])
    dist = np.array([-0.1, 0.02, -7e-4, 4e-4, 0.003])          # OpenCV: p1 = P2, p2 = P1
    np.testing.assert_allclose(metashape_project(n, p, W, H), opencv_project(n, K, dist), atol=1e-9)
    # B1 (affinity) scales u by (f + B1); B2 (skew) adds y' B2 to u
    q = dict(p, b1=2.0, b2=0.5)
    d = metashape_project(n, q, W, H) - metashape_project(n, p, W, H)
    xd = (metashape_project(n, p, W, H)[:, 0] - (W / 2 + 3.5 - 0.5)) / 1500.0
    yd = (metashape_project(n, p, W, H)[:, 1] - (H / 2 - 2.0 - 0.5)) / 1500.0
    np.testing.assert_allclose(d[:, 0], 2.0 * xd + 0.5 * yd, atol=1e-9)
    np.testing.assert_allclose(d[:, 1], 0.0, atol=1e-12)


# --------------------------------------------------------------------------------------
# fits: exact where the models allow it, honest where they do not
# --------------------------------------------------------------------------------------
def _roundtrip_px(camera, K, dist, pts):
    n_cv = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    return np.hypot(*((n_cv - normalised_rays(camera, pts)) * [K[0, 0], K[1, 1]]).T)


@pytest.mark.parametrize("camera", [H3D, WIDE], ids=["h3d", "wide"])
def test_opencv_export_round_trips_within_a_hundredth_of_a_pixel(camera):
    fit = fit_opencv(camera)
    assert fit.exact
    pts = _pixels(camera)
    # independent check on other pixels: cv2.undistortPoints against fieldcal's rays, and
    # cv2.projectPoints of fieldcal's rays against the pixels
    assert _roundtrip_px(camera, fit.K, fit.dist, pts).max() <= EXACT_PX
    n = normalised_rays(camera, pts)
    uv, _ = cv2.projectPoints(np.column_stack([n, np.ones(len(n))]), np.zeros(3), np.zeros(3),
                              fit.K, fit.dist)
    assert np.hypot(*(uv.reshape(-1, 2) - pts).T).max() <= EXACT_PX
    assert fit.roundtrip_max_px <= EXACT_PX and fit.fit_max_px <= EXACT_PX


def test_the_paper_camera_fits_opencvs_five_coefficients_and_says_how_well():
    fit = fit_opencv(PAPER, "brown5")
    measured = _roundtrip_px(PAPER, fit.K, fit.dist, _pixels(PAPER, 5000, seed=5)).max()
    # the fit reports what an independent check finds (to the sampling of the extremes)
    assert measured <= fit.roundtrip_max_px + 1e-3
    assert fit.exact == (fit.roundtrip_max_px <= EXACT_PX)
    # 0.0102 px: OpenCV's five coefficients cannot hold the paper's shear a1 and the
    # inverse's higher orders to 0.01 px (bench/README_reports.md)
    assert fit.roundtrip_max_px < 0.02


def test_the_fits_jacobian_is_the_projections_derivative():
    rng = np.random.default_rng(3)
    n = rng.uniform(-0.6, 0.6, (40, 2))
    x = np.concatenate([[900.0, 905.0, 700.0, 460.0], rng.normal(0, 0.05, 12)])

    def project(p):
        return opencv_project(n, np.array([[p[0], 0, p[2]], [0, p[1], p[3]], [0, 0, 1]]), p[4:])
    h = 1e-6 * np.maximum(np.abs(x), 1e-2)
    numeric = np.stack([(project(x + d) - project(x - d)) / (2 * d.sum()) for d in np.diag(h)], axis=-1)
    for m in (4, 5, 8, 12):
        jac = opencv_jacobian(n, np.array([[x[0], 0, x[2]], [0, x[1], x[3]], [0, 0, 1]]), x[4:4 + m])
        assert jac.shape == (40, 2, 4 + m)
        if m == 12:
            np.testing.assert_allclose(jac, numeric, rtol=1e-6, atol=1e-6 * np.abs(numeric).max())


def test_a_goniometer_camera_says_which_model_it_exports():
    """Its scale term k0 and the inverse's higher orders need more than OpenCV's five
    coefficients: the export names the model it chose and what the others reached (issue 30)."""
    # what `fieldcal synth` + `run` give for the canon5d2 scenario (seed 0): f with k0 = -0.0154
    gonio = {"f_mm": 23.93576281, "xp_mm": 0.07125548, "yp_mm": -0.04130444, "k0": -0.01538823,
             "k1": 0.00010914, "k2": -7e-08, "p1": 8.66e-06, "p2": -4.76e-06, "b1": 2.804e-05}
    cam = Camera.from_dict(make_scenario("canon5d2", raster_scale=0.25).camera().sensor, gonio)
    exp = export_text(_doc(cam), "opencv")
    fit = exp.fit
    assert fit.exact and fit.model != "brown5"
    line = fit.report_lines()[0]
    assert line.startswith(f"opencv: exported the {fit.model} model ({len(fit.dist)} distortion coefficients)")
    assert "the simplest whose round trip is within 0.01 px" in line and "brown5 " in line
    assert fit.choice_line() in exp.text and exp.report_lines()[0] == line


def test_a_shear_opencv_cannot_model_is_reported_not_exact():
    sheared = Camera.from_dict(WIDE.sensor, dict(WIDE_ANGLE, a1=2e-4))   # dy = a1 x: 0.15 px at the edge
    fit = fit_opencv(sheared, candidates=("brown4", "brown5"))
    assert not fit.exact
    assert [t["model"] for t in fit.tried] == ["brown4", "brown5"]
    assert fit.roundtrip_max_px == min(t["roundtrip_max_px"] for t in fit.tried)
    assert _roundtrip_px(sheared, fit.K, fit.dist, _pixels(sheared)).max() > EXACT_PX
    assert any("cannot be that exact" in line for line in fit.report_lines())


def test_metashape_fit_round_trips_and_takes_the_affinity():
    cam = Camera.from_dict(WIDE.sensor, dict(WIDE_ANGLE, b1=3e-4))      # x scale: Metashape's B1
    fit = fit_metashape(cam)
    assert fit.exact
    pts = _pixels(cam)
    n = normalised_rays(cam, pts)
    assert np.hypot(*(metashape_project(n, fit.params, 1500, 1000) - pts).T).max() <= EXACT_PX
    # fieldcal's b1 scales the ideal x by (1 + b1), its a2 the ideal y by (1 + a2): the
    # pixel scales differ by (1 - b1) / (1 - a2), which is Metashape's (f + B1) / f
    assert fit.params["b1"] / fit.params["f"] == pytest.approx(-(3e-4 - 5e-5), rel=0.02)


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def test_json_export_is_the_document():
    doc = _doc(H3D)
    exp = export_text(doc, "json")
    assert json.loads(exp.text) == doc and exp.fit is None and exp.exact


def test_opencv_yaml_reads_back_with_filestorage(tmp_path):
    exp = export_text(_doc(H3D), "opencv")
    path = tmp_path / "cam.yml"
    path.write_text(exp.text)
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    K = fs.getNode("camera_matrix").mat()
    dist = fs.getNode("distortion_coefficients").mat().ravel()
    assert int(fs.getNode("image_width").real()) == H3D.sensor.width_px
    assert fs.getNode("fieldcal_version").string() == "20260110T090000Z-00000000-0000"
    fs.release()
    np.testing.assert_allclose(K, exp.fit.K, rtol=1e-15)
    np.testing.assert_allclose(dist, exp.fit.dist, rtol=1e-15)
    assert _roundtrip_px(H3D, K, dist, _pixels(H3D)).max() <= EXACT_PX


def test_colmap_cameras_txt_works_in_pycolmap():
    exp = export_text(_doc(WIDE), "colmap")
    line = [x for x in exp.text.splitlines() if x and not x.startswith("#")]
    assert len(line) == 1
    cid, model, w, h, *params = line[0].split()
    assert (cid, int(w), int(h)) == ("1", 1500, 1000)
    assert model in ("OPENCV", "FULL_OPENCV")
    cam = pycolmap.Camera(model=model, width=int(w), height=int(h), params=[float(p) for p in params])
    pts = _pixels(WIDE)
    # COLMAP's pixel centres are at +0.5 (module docstring of fieldcal.products.export)
    n_col = np.asarray(cam.cam_from_img(pts + 0.5))[:, :2]
    err = np.hypot(*((n_col - normalised_rays(WIDE, pts)) * cam.focal_length_x).T)
    assert err.max() <= max(EXACT_PX, exp.fit.roundtrip_max_px + 1e-3)
    assert exp.fit.exact


def test_metashape_xml_reads_back(tmp_path):
    exp = export_text(_doc(WIDE), "metashape")
    root = ET.fromstring(exp.text)
    assert root.tag == "calibration" and root.findtext("projection") == "frame"
    assert int(root.findtext("width")) == 1500 and int(root.findtext("height")) == 1000
    p = {k: float(root.findtext(k)) for k in ("f", "cx", "cy", "b1", "b2", "k1", "k2", "k3", "k4",
                                               "p1", "p2")}
    pts = _pixels(WIDE)
    uv = metashape_project(normalised_rays(WIDE, pts), p, 1500, 1000)
    assert np.hypot(*(uv - pts).T).max() <= EXACT_PX


def test_export_checks_its_arguments():
    with pytest.raises(InputError, match="format must be one of"):
        export_text(_doc(H3D), "pix4d")
    with pytest.raises(InputError, match="COLMAP model must be"):
        export_text(_doc(H3D), "colmap", model="brown5")
    with pytest.raises(InputError, match="model must be 'auto' or one of"):
        fit_opencv(H3D, "fisheye")


def test_export_of_a_calibration_object_uses_its_camera():
    cal = Calibration.from_document(_doc(H3D))
    exp = export_text(cal, "opencv", model="brown5")
    assert exp.fit.model == "brown5" and exp.exact
    assert "distortion_coefficients" in exp.text
