"""The focal lengths a certificate states, against exact cameras (fieldcal.products.focal_length)."""

import numpy as np
import pytest
from scipy.optimize import brentq

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.model.camera import INDEX, PARAM_NAMES, Sensor
from fieldcal.products import focal_length as fl

SENSOR = Sensor(6000, 4000, 3.9)


def _cal(params: dict, names=("f_mm", "xp_mm", "yp_mm", "k0", "k1"), sigmas=None) -> Calibration:
    p = dict.fromkeys(PARAM_NAMES, 0.0) | params
    doc = {"version": "v", "method": "goniometer", "camera_id": "c", "sensor": SENSOR.to_dict(),
           "parameters": p, "sigma": dict.fromkeys(PARAM_NAMES)}
    sig = np.asarray(sigmas if sigmas is not None else [1e-3, 1e-3, 1e-3, 1e-4, 1e-7][: len(names)])
    return Calibration.from_document(doc, list(names), np.diag(sig**2))


def test_with_a_scale_term_only_the_effective_focal_length_is_exact_everywhere():
    """k0 alone: a measured radius r corrects to r (1 + k0) = f tan(theta), so r = f_e tan(theta)
    at every angle: relative to f_e there is no distortion, and balancing finds f_e."""
    cal = _cal({"f_mm": 23.936, "k0": -0.0154})
    fe, _ = fl.effective_focal(cal)
    assert fe == pytest.approx(23.936 / (1 - 0.0154), rel=1e-12)
    theta = np.linspace(1.0, 35.0, 12)
    d, rho, _ = fl.distortion_relative(cal, theta, fe)
    np.testing.assert_allclose(rho, fe * np.tan(np.radians(theta))[None, :].repeat(4, 0), rtol=1e-9)
    assert np.abs(d).max() < 1e-6                                   # um
    assert fl.balanced_focal(cal)["c_mm"] == pytest.approx(fe, rel=1e-10)
    d_f, _, _ = fl.distortion_relative(cal, theta, "f")             # relative to f: the 1.5 % scale
    assert d_f[0, -1] == pytest.approx(1000 * (fe - 23.936) * np.tan(np.radians(35.0)), rel=1e-8)


def test_radial_distortion_and_the_balanced_focal_length_against_an_independent_solve():
    f, k1 = 24.0, 3.5e-5
    cal = _cal({"f_mm": f, "k1": k1})
    theta = np.linspace(0.5, 30.0, 25)
    # the measured radius of a ray: r (1 + k1 r^2) = f tan(theta), solved by bracketing
    r = np.array([brentq(lambda x, t=t: x * (1 + k1 * x * x) - f * np.tan(np.radians(t)), 0, 40) for t in theta])
    d, rho, _ = fl.distortion_relative(cal, theta, "f")
    np.testing.assert_allclose(rho[0], r, rtol=1e-10)
    np.testing.assert_allclose(d, 1000 * (r - f * np.tan(np.radians(theta)))[None].repeat(4, 0), atol=1e-6)
    # c minimises the squared distortion over the balance angles (and is below f: barrel)
    bal = fl.balanced_focal(cal, reach_mm=12.0)
    grid = np.linspace(0, bal["theta_max_deg"], fl.BALANCE_ANGLES + 1)[1:]
    t = np.tan(np.radians(grid))
    rr = np.array([brentq(lambda x, tt=tt: x * (1 + k1 * x * x) - f * tt, 0, 40) for tt in t])
    ls = np.linalg.lstsq(t[:, None], rr, rcond=None)[0][0]
    assert bal["c_mm"] == pytest.approx(ls, rel=1e-10) and bal["c_mm"] < f
    assert bal["theta_max_deg"] == pytest.approx(np.degrees(np.arctan(12.0 / f)))
    assert bal["max_um"] < bal["max_f_um"]


def test_the_four_semi_diagonals_differ_by_the_decentering():
    cal = _cal({"f_mm": 24.0, "k1": 3.5e-5, "p1": 2e-5}, names=("f_mm", "k1", "p1"), sigmas=[1e-3, 1e-7, 1e-6])
    rows = fl.semi_diagonal_table(cal, [10.0, 20.0], "f")
    for r in rows:
        # p1's radial component along a direction e is 3 p1 r^2 e_x (to first order): the two
        # right-hand diagonals agree, the two left-hand ones agree, and the sides differ
        ur, ul, ll, lr = r["diagonals_um"]
        assert ur == pytest.approx(lr, abs=1e-6) and ul == pytest.approx(ll, abs=1e-6)
        assert abs(ur - ul) > 1.0
        assert r["mean_um"] == pytest.approx(np.mean(r["diagonals_um"]))
    plain = fl.semi_diagonal_table(_cal({"f_mm": 24.0, "k1": 3.5e-5}), [10.0, 20.0], "f")
    for a, b in zip(rows, plain, strict=True):
        assert a["mean_um"] == pytest.approx(b["mean_um"], abs=0.05)      # decentering averages out


def test_uncertainties_are_the_first_order_propagation():
    f, k0 = 23.936, -0.0154
    cov = np.array([[4e-8, 0, 0, 1e-11], [0, 1e-6, 0, 0], [0, 0, 1e-6, 0], [1e-11, 0, 0, 9e-9]])
    doc = {"version": "v", "method": "goniometer", "camera_id": "c", "sensor": SENSOR.to_dict(),
           "parameters": dict.fromkeys(PARAM_NAMES, 0.0) | {"f_mm": f, "k0": k0}, "sigma": dict.fromkeys(PARAM_NAMES)}
    cal = Calibration.from_document(doc, ["f_mm", "xp_mm", "yp_mm", "k0"], cov)
    g = np.array([1 / (1 + k0), 0, 0, -f / (1 + k0) ** 2])
    _, s = fl.effective_focal(cal)
    assert s == pytest.approx(np.sqrt(g @ cov @ g), rel=1e-6)
    # the balanced focal length of a pure scale is f_e: the same uncertainty
    assert fl.balanced_focal(cal)["sigma_mm"] == pytest.approx(s, rel=1e-5)
    assert INDEX["k0"] == 3
