"""The synthetic goniometer sessions: geometry against the camera model, files against the contract."""

import json

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
import tifffile

from fieldcal.errors import InputError
from fieldcal.goniometer import method as gon
from fieldcal.model.camera import Camera, project
from fieldcal.session.frames import read_frames_csv
from fieldcal.session.loader import load_session
from fieldcal.synthetic.goniometer import (
    FAULTS,
    SCENARIOS,
    make_scenario,
    render_frame,
    spot_positions_px,
    sweep_directions,
    write_session,
)

PERFECT = {"zero_px": [0.0, 0.0], "tilt_mrad": 0.0, "cone_mrad": 0.0}


def test_perfect_set_up_gives_the_contract_directions():
    w = np.radians([-30.0, -5.0, 0.0, 12.0, 33.0])
    r0 = np.array([0.0, 0.0, -1.0])
    dx = sweep_directions("x", w, r0)
    dy = sweep_directions("y", w, r0)
    # CONTRACT/brief: x sweep (sin W, 0, -cos W), y sweep (0, sin W, -cos W)
    assert np.allclose(dx, np.column_stack([np.sin(w), 0 * w, -np.cos(w)]), atol=1e-15)
    assert np.allclose(dy, np.column_stack([0 * w, np.sin(w), -np.cos(w)]), atol=1e-15)


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_positions_agree_with_camera_project_and_the_frames_csv_sign(name):
    cam = SCENARIOS[name].camera()
    mis = {"zero_px": [0.4, -0.3], "tilt_mrad": 2.0, "cone_mrad": -1.0}
    angles = np.array([-10.0, 0.0, 10.0, 20.0])
    for axis in ("x", "y"):
        uv = spot_positions_px(cam, axis, angles, mis)
        # the same directions through fieldcal.model.camera.project: a point 1 km away, R = I, C = 0
        centre = np.array([(cam.sensor.width_px - 1) / 2, (cam.sensor.height_px - 1) / 2])
        from fieldcal.model.camera import unproject
        r0 = unproject(centre + mis["zero_px"], cam)
        d = sweep_directions(axis, np.radians(angles), r0, tilt_rad=2e-3, cone_rad=-1e-3)
        ref = project(1000.0 * d, np.eye(3), np.zeros(3), cam)
        assert np.allclose(uv, ref, atol=1e-6)
        # the zero lands where the alignment put it; +W moves towards +x (u up) / +y (v down)
        assert np.allclose(uv[1], centre + mis["zero_px"], atol=1e-6)
        along = uv[:, 0] if axis == "x" else -uv[:, 1]
        assert np.all(np.diff(along) > 0)


def test_misalignments_incline_and_bow_the_track():
    cam = SCENARIOS["canon5d2"].camera()
    a = np.array([-30.0, 0.0, 30.0])
    flat = spot_positions_px(cam, "x", a, PERFECT)
    tilted = spot_positions_px(cam, "x", a, dict(PERFECT, tilt_mrad=2.0))
    cone = spot_positions_px(cam, "x", a, dict(PERFECT, cone_mrad=2.0))
    dv_t, dv_c = tilted[:, 1] - flat[:, 1], cone[:, 1] - flat[:, 1]
    assert abs(dv_t[0] + dv_t[2]) < 0.2 * abs(dv_t[0]) and abs(dv_t[0]) > 3     # inclined: odd
    assert abs(dv_c[0] - dv_c[2]) < 0.2 * abs(dv_c[0]) and abs(dv_c[0] - dv_c[1]) > 0.5  # bowed: even


def test_rendered_spot_integrates_to_its_flux_and_centre():
    sc = make_scenario("h3d", raster_scale=0.1, black_dn=0.0, background_e=0.0, gain_dn_per_e=0.001)
    u, v = 200.3, 150.8
    img = render_frame(sc, [{"u_px": u, "v_px": v, "flux_e": 4e8, "sigma_u_px": 1.1,
                             "sigma_v_px": 0.9}], np.random.default_rng(0), noise=False,
                       window_px=30).astype(float)
    vv, uu = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    total = img.sum()
    # exact pixel integrals, rounded to DN (peak ~50000 DN, below the clip): centre and flux
    # to the precision of the rounding
    assert img.max() < 65535
    assert total == pytest.approx(4e5, rel=2e-3)
    assert (img * uu).sum() / total == pytest.approx(u, abs=2e-3)
    assert (img * vv).sum() / total == pytest.approx(v, abs=2e-3)


def test_raster_scale_keeps_the_millimetre_geometry():
    full, small = make_scenario("canon5d2"), make_scenario("canon5d2", raster_scale=0.25)
    assert (small.width_px, small.height_px) == (1404, 936)
    assert small.pixel_size_um == pytest.approx(25.6)
    a = np.array(full.x_angles_deg)
    mm_full = full.sensor().pixel_to_mm(spot_positions_px(full.camera(), "x", a, PERFECT))
    mm_small = small.sensor().pixel_to_mm(spot_positions_px(small.camera(), "x", a, PERFECT))
    assert np.allclose(mm_full, mm_small, atol=1e-9)


@pytest.mark.parametrize("name, max_px", [("canon5d2", (15, 25)), ("h3d", (0.3, 1.0))])
def test_scenarios_have_the_papers_distortion_before_the_fit(name, max_px):
    # the paper: ~20 px (Canon, Fig. 4) and under 1 px (H3D, Fig. 6) after the interior orientation
    sc = SCENARIOS[name]
    cam = sc.camera()
    rows, meas = [], []
    for axis, angles in (("x", sc.x_angles_deg), ("y", sc.y_angles_deg)):
        for a, (u, v) in zip(angles, spot_positions_px(cam, axis, angles, PERFECT), strict=True):
            rows.append({"file": f"{axis}{a}", "axis": axis, "angle_deg": a})
            meas.append({"file": f"{axis}{a}", "u_px": u, "v_px": v, "flag": "ok"})
    res = gon.calibrate(cam.sensor, pa.Table.from_pylist(rows), gon.measurements_table(meas))
    assert max_px[0] < res.stats["max_distortion_px"] < max_px[1]
    # every angle of both sweeps lands on the sensor, with a margin
    assert res.stats["n_angles"] == len(sc.x_angles_deg) + len(sc.y_angles_deg)


def test_write_session_files_follow_the_contract(tmp_path):
    truth = write_session(tmp_path / "s1", "h3d", seed=3, raster_scale=0.1, frames_per_angle=2)
    man = json.loads((tmp_path / "s1" / "session.json").read_text())
    assert man["schema"] == "fieldcal.session/1" and man["method"] == "goniometer"
    assert man["frames"] == "frames.csv" and man["images"] == "images/*.tif"
    assert man["session_id"] == "s1" and man["camera_id"] == "h3d-synthetic"
    assert man["sensor"] == {"width_px": 722, "height_px": 541, "pixel_size_um": 68.0}
    assert man["lens"] == {"nominal_focal_mm": 50.0}
    assert "field" not in man
    sess = load_session(tmp_path / "s1")              # the project's manifest validation
    assert sess.method == "goniometer" and len(sess.images) == truth.frames.num_rows
    frames = read_frames_csv(tmp_path / "s1" / "frames.csv")
    assert frames.num_rows == 2 * (45 + 35) == truth.frames.num_rows
    assert frames["problem"].null_count == frames.num_rows
    first = tmp_path / "s1" / frames["file"][0].as_py()
    with tifffile.TiffFile(first) as tif:
        page = tif.pages.first
        assert page.dtype == np.uint16 and page.shape == (541, 722)
        assert page.is_tiled and page.compression.name == "ZSTD"
    # the exact positions are those of the camera model for the set-up drawn
    x = truth.frames.filter(pc.equal(truth.frames["axis"], "x"))
    uv = spot_positions_px(truth.camera, "x", x["angle_deg"].to_numpy(), truth.misalignment["x"])
    assert np.allclose(uv, np.column_stack([x["u_px"].to_numpy(), x["v_px"].to_numpy()]))
    # repeated frames share the exact position and differ by the jitter
    jit = x["u_rendered_px"].to_numpy() - x["u_px"].to_numpy()
    assert 0.02 < jit.std() < 0.12          # 0.06 px jitter (+ 1 arcsec encoder)


def test_faults_are_injected_as_documented(tmp_path):
    truth = write_session(tmp_path / "f", "canon5d2", seed=5, raster_scale=0.1, faults=FAULTS)
    got = {f["fault"]: f for f in truth.faults}
    assert set(got) == set(FAULTS)
    assert not (tmp_path / "f" / got["missing_file"]["file"]).exists()
    assert (tmp_path / "f" / got["no_spot"]["file"]).exists()
    text = (tmp_path / "f" / "frames.csv").read_text()
    assert f"{got['bad_axis']['file']},z," in text
    off = truth.frames.filter(pc.equal(truth.frames["fault"], "off_sensor"))
    assert off.num_rows == 3 and not any(off["on_sensor"].to_pylist())
    assert off["angle_deg"][0].as_py() > max(SCENARIOS["canon5d2"].x_angles_deg)


def test_unknown_names_are_refused(tmp_path):
    with pytest.raises(InputError, match="unknown scenario 'nikon'"):
        write_session(tmp_path, "nikon")
    with pytest.raises(InputError, match="unknown fault"):
        write_session(tmp_path, "h3d", faults=["meteor"])
    with pytest.raises(InputError, match="raster_scale"):
        make_scenario("h3d", raster_scale=2.0)
    with pytest.raises(InputError, match="unknown scenario field"):
        make_scenario("h3d", colour="red")
    assert isinstance(SCENARIOS["h3d"].camera(), Camera)
