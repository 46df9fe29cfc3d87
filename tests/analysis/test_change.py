"""Honest change tests: Monte Carlo of repeat sessions of one camera, both methods.

Repeat sessions of an unchanged camera (new image noise, new survey noise, new attitudes;
for the goniometer a new alignment of the camera on the arm) must be called changed at
about the nominal rate, and a change of a few propagated sigmas in f, in the principal
point or in the distortion at the edge of the field must be found as often as the
test's power says (fieldcal.analysis.change).

Each method: 20 independent pairs of sessions (40 solves, cached for the module). The
field method on observation sessions of the paper's camera (one attitude per station: 6
images, ~1200 points; its sigmas are honest there: RMS |error|/sigma 0.97, 0.89, 1.00 for
f, xp, yp over 30 draws), the goniometer on sessions simulated without images
(tests/goniometer/simulate.py; the rendered sessions are in bench/bench_goniometer.py).

A change is put into B's estimate (its covariance unchanged): the test's power given
honest covariances; whether the covariances are honest is what the false-alarm half
checks on real re-solves.
"""

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from fieldcal.analysis.change import chi_square_test, edge_radius_mm, holm
from fieldcal.analysis.compare import combined_covariance, compare_calibrations
from fieldcal.analysis.uncertainty import Calibration
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.goniometer import calibrate as gonio_calibrate
from fieldcal.model.camera import INDEX, PARAM_NAMES, Camera, params_to_dict
from fieldcal.synthetic.field import paper_field
from tests.goniometer.simulate import simulated_session

N_PAIRS = 20
FIELD_SET = ("f_mm", "xp_mm", "yp_mm", "k1", "k2", "k3", "p1", "p2", "a1", "a2")


def _field_calibration(seed: int) -> Calibration:
    sf = paper_field(seed=seed, n_attitudes=1)
    res = adjust_field(sf.data, AdjustmentOptions(estimate=FIELD_SET))
    doc = {"method": "field", "version": f"field-{seed}", "camera_id": "ixu150", "session_id": f"s{seed}",
           "sensor": sf.camera.sensor.to_dict(), "parameters": params_to_dict(res.params),
           "sigma": dict(res.sigma), "stats": res.stats()}
    return Calibration.from_document(doc, res.covariance_names, res.covariance)


def _gonio_calibration(seed: int) -> Calibration:
    cam, frames, meas = simulated_session("canon5d2", seed=1000 + seed)
    res = gonio_calibrate(cam.sensor, frames, meas)
    doc = dict(res.document_fields(), version=f"gonio-{seed}", camera_id="canon", session_id=f"s{seed}")
    return Calibration.from_document(doc, PARAM_NAMES, res.covariance)


@pytest.fixture(scope="module")
def pairs():
    """Per method: 20 independent pairs of calibrations of one unchanged camera."""
    return {"field": [(_field_calibration(2 * i), _field_calibration(2 * i + 1)) for i in range(N_PAIRS)],
            "goniometer": [(_gonio_calibration(2 * i), _gonio_calibration(2 * i + 1))
                           for i in range(N_PAIRS)]}


# --------------------------------------------------------------------------------------
# the pieces
# --------------------------------------------------------------------------------------
def test_holm_adjusts_as_the_step_down_procedure():
    p = [0.01, 0.04, 0.03, 0.005]
    # sorted 0.005, 0.01, 0.03, 0.04 -> 4x, 3x, 2x, 1x -> 0.02, 0.03, 0.06, 0.06 (monotone)
    np.testing.assert_allclose(holm(p), [0.03, 0.06, 0.06, 0.02])
    assert holm([0.5, 0.9]).tolist() == [1.0, 1.0]


def test_chi_square_test_of_a_vector_against_its_covariance():
    C = np.array([[4.0, 1.0], [1.0, 2.0]])
    d = np.array([1.0, -2.0])
    chi2, r, p = chi_square_test(d, C)
    assert r == 2 and chi2 == pytest.approx(d @ np.linalg.solve(C, d))
    assert p == pytest.approx(stats.chi2.sf(chi2, 2))


def test_edge_radius_is_the_corner_or_the_end_of_the_wider_sweep(pairs):
    field, gonio = pairs["field"][0][0], pairs["goniometer"][0][0]
    assert edge_radius_mm(field) == pytest.approx(field.sensor.half_diagonal_mm)
    # the Canon's x sweep reaches +-34 deg: f tan 34 = 16.4 mm (half diagonal 21.6 mm)
    assert edge_radius_mm(gonio) == pytest.approx(gonio.camera.f_mm * np.tan(np.radians(34.0)))


# --------------------------------------------------------------------------------------
# Monte Carlo: false alarms and detections
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["field", "goniometer"])
def test_repeat_sessions_of_an_unchanged_camera_are_called_changed_at_the_nominal_rate(pairs, method):
    comps = [compare_calibrations(a, b) for a, b in pairs[method]]
    p_family = np.array([c.p_value for c in comps])
    # with 20 pairs a level of 0.01 cannot be told from 0.03 (0 or 1 false alarm); 0.05 and
    # 0.1 can: at most 2 alpha N (2 and 4) false alarms (expected 1 and 2)
    for alpha in (0.05, 0.1):
        assert (p_family < alpha).sum() <= 2 * alpha * N_PAIRS, (alpha, np.sort(p_family)[:5])
    assert (p_family < 0.01).sum() <= 1, np.sort(p_family)[:5]
    # the quantities one by one (before Holm): the sum of their chi-square statistics over
    # the 20 pairs is chi-square with 20 x dof degrees of freedom; within its 0.1 % and
    # 99.9 % points (for one degree of freedom this resolves a variance off by a factor 2.3
    # either way, not less:
    # bench/bench_goniometer.py has 100 pairs)
    keys = [t.key for t in comps[0].tests]
    for k, key in enumerate(keys):
        total = sum(c.tests[k].statistic for c in comps)
        dof = sum(c.tests[k].dof for c in comps)
        lo, hi = stats.chi2.ppf([0.001, 0.999], dof)
        assert lo < total < hi, (method, key, total, dof)
    assert keys == ["f", "principal_point", "edge_distortion", "map"]
    # nothing outside the range the covariances explain
    assert max(c.outside_px for c in comps) < 0.01
    # the sizes of one comparison, in both units, of the same region
    c = comps[0]
    assert c.max_um == pytest.approx(c.max_px * c.pixel_size_um)
    assert c.rms_px <= c.max_px and c.rms_um <= c.max_um
    assert c.region == ("axes" if method == "goniometer" else "sensor")


def _changed(b: Calibration, key: str, size: float, sigma_delta: float, r_e: float) -> Calibration:
    """``b`` with its quantity ``key`` moved by ``size`` standard deviations of the difference."""
    p = b.camera.params.copy()
    if key == "f":
        p[INDEX["f_mm"]] += size * sigma_delta / 1000.0
    elif key == "principal_point":
        p[INDEX["xp_mm"]] += size * sigma_delta / 1000.0
    else:                              # dr(r_e) = k1 r_e^3 + ...: move k1
        p[INDEX["k1"]] += size * sigma_delta / 1000.0 / r_e**3
    return replace(b, camera=Camera(b.sensor, p))


def _power_bonferroni(ncp: float, dof: int, alpha: float, k: int) -> float:
    """Probability that one test of ``dof`` degrees of freedom rejects at ``alpha / k``."""
    return float(stats.ncx2.sf(stats.chi2.isf(alpha / k, dof), dof, ncp))


@pytest.mark.parametrize("method", ["field", "goniometer"])
@pytest.mark.parametrize("key", ["f", "principal_point", "edge_distortion"])
def test_a_change_of_a_few_sigmas_is_found_as_often_as_the_power_says(pairs, method, key):
    alpha = 0.01
    found3, found5, expected3 = [], [], []
    for a, b in pairs[method]:
        base = compare_calibrations(a, b, alpha=alpha)
        t = next(t for t in base.tests if t.key == key)
        col = 0                                      # xp for the principal point
        sigma_delta = t.sigma[col]
        r_e = min(edge_radius_mm(a), edge_radius_mm(b))
        for size, found in ((3.0, found3), (5.0, found5)):
            c = compare_calibrations(a, _changed(b, key, size, sigma_delta, r_e), alpha=alpha)
            found.append(c.significant and key in c.changed)
        # the non-centrality of a 3-sigma move of one component (xp alone: 9 / (1 - rho^2))
        names, cov = combined_covariance(a, b)
        if key == "principal_point":
            i, j = names.index("xp_mm"), names.index("yp_mm")
            C = cov[np.ix_([i, j], [i, j])]
            ncp = 9.0 * C[0, 0] * np.linalg.inv(C)[0, 0]
        else:
            ncp = 9.0
        expected3.append(_power_bonferroni(ncp, len(t.change), alpha, len(base.tests)))
    rate3, rate5, p3 = np.mean(found3), np.mean(found5), np.mean(expected3)
    # Holm is at least as powerful as Bonferroni: at 3 sigma about 50 % (no level-0.01 test
    # can reach the 90 % the issue hoped for: the best, one-sided, reaches 75 %); allow 3
    # binomial sigmas below the Bonferroni power
    assert rate3 >= p3 - 3 * np.sqrt(p3 * (1 - p3) / N_PAIRS), (rate3, p3)
    assert 0.3 < p3 < 0.75
    # at 5 sigma the power is >= 97 %: at least 90 % found
    assert rate5 >= 0.9, rate5


def test_a_goniometer_against_a_field_calibration_compares_only_the_map_and_says_why(pairs):
    gonio, field = pairs["goniometer"][0][0], pairs["field"][0][0]
    # the same camera model on the Canon's sensor, as a field result with a small covariance
    doc = dict(field.document, sensor=gonio.document["sensor"], version="field-on-canon")
    fc = Calibration.from_document(doc, field.names, field.covariance * 1e-4)
    fc = replace(fc, camera=gonio.camera)
    c = compare_calibrations(gonio, fc)
    assert [t.key for t in c.tests] == ["map"] and c.region == "axes"
    text = " ".join(c.left_out)
    assert "optical axis points" in text and "convention" in text and "off the two scanned axes" in text
    assert not c.significant and c.max_px < 1e-9


def test_repeat_goniometer_sessions_scatter_as_their_sigmas_say(pairs):
    """Goal 0 for the goniometer: 40 sessions, each a new alignment on the arm and new noise.

    The error is against the method's value for the true camera (its exact spots on a
    perfectly aligned set-up): the goniometer's f and principal point are those of the
    minimum-sum convention (f absorbs the linear part of the radial distortion: 374 um here).
    """
    import pyarrow as pa

    from fieldcal.goniometer import measurements_table
    from fieldcal.synthetic.goniometer import make_scenario, spot_positions_px

    sc = make_scenario("canon5d2")
    cam = sc.camera()
    aligned = {"zero_px": [0.0, 0.0], "tilt_mrad": 0.0, "cone_mrad": 0.0}
    rows, meas = [], []
    for axis, angles in (("x", sc.x_angles_deg), ("y", sc.y_angles_deg)):
        uv = spot_positions_px(cam, axis, angles, aligned)
        for a, (u, v) in zip(angles, uv, strict=True):
            rows.append({"file": f"{axis}{a:+.1f}", "axis": axis, "angle_deg": a})
            meas.append({"file": f"{axis}{a:+.1f}", "u_px": u, "v_px": v, "flag": "ok"})
    ref = gonio_calibrate(cam.sensor, pa.Table.from_pylist(rows), measurements_table(meas)).parameters[:3]
    cals = [c for pair in pairs["goniometer"] for c in pair]
    est = np.array([c.camera.params[:3] for c in cals])
    sig = np.array([[c.sigma_of(k) for k in ("f_mm", "xp_mm", "yp_mm")] for c in cals])
    rms_z = np.sqrt(np.mean(((est - ref) / sig) ** 2, axis=0))
    # the issue's band; 40 sessions estimate an RMS to +-11 %
    assert np.all((rms_z > 0.7) & (rms_z < 1.3)), rms_z


def test_the_issues_three_synthetic_sessions_of_one_camera_agree(tmp_path):
    """``fieldcal synth --method goniometer`` seeds 1, 2, 3 (the same camera, rendered frames):
    called changed with chi2 464-6425 on 9 dof before; no pair is significant now."""
    from fieldcal.goniometer import measure_session
    from fieldcal.session.frames import read_frames_csv
    from fieldcal.synthetic.goniometer import write_session

    cals = []
    for seed in (1, 2, 3):
        truth = write_session(tmp_path / f"s{seed}", "canon5d2", seed=seed, raster_scale=0.25)
        frames = read_frames_csv(tmp_path / f"s{seed}" / "frames.csv")
        res = gonio_calibrate(truth.sensor, frames, measure_session(tmp_path / f"s{seed}", frames, truth.sensor))
        doc = dict(res.document_fields(), version=f"synth-{seed}", camera_id="canon", session_id=f"s{seed}")
        cals.append(Calibration.from_document(doc, PARAM_NAMES, res.covariance))
    for i, j in ((0, 1), (0, 2), (1, 2)):
        c = compare_calibrations(cals[i], cals[j])
        assert not c.significant, (i, j, c.verdict)
        assert c.region == "axes" and c.max_um == pytest.approx(c.max_px * c.pixel_size_um)
