"""Disc recall where the candidate search used to lose discs (issue 23, goal 6).

Two situations of the DBAT sheet's photographs (bench/README_dbat_recall.md), rendered with
exact truth: a disc whose top-hat joins shading at the candidate threshold (the noise of a
JPEG-compressed image is at the estimator's floor, so the threshold is a few DN and a soft
shadow beside the disc lies above it), and the dot of a ringed target (a dark dot inside
partial ring segments, PhotoModeler's coded targets), which joins its segments at the coarse
sampling. Both must be found and measured to their true centres; the segments must not be
reported as discs.
"""

import math

import numpy as np
import pytest
from scipy import ndimage

from fieldcal.measure.discs import METHODS, detect_targets
from tests.measure.test_targets import ellipse_coverage, match

BG8, FIG8 = 200.0, 40.0          # an 8-bit photograph's paper and ink [DN]


def _to_uint8(img, noise_dn, seed):
    rng = np.random.default_rng(seed)
    return np.clip(np.rint(img + rng.normal(0.0, noise_dn, img.shape)), 0, 255).astype(np.uint8)


def _ringed_coverage(shape, centre, A, r_dot, r_in, r_out, segments_deg, supersample=8):
    """Coverage of a ringed target: a dot of radius ``r_dot`` and ring segments
    (``r_in <= rho <= r_out``, angle in one of the ``segments_deg`` intervals) on the sheet,
    imaged by the affine map ``x = centre + A y`` (y on the sheet, x in the image)."""
    H, W = shape
    s = supersample
    off = (np.arange(s) + 0.5) / s - 0.5
    reach = r_out * np.abs(A).sum(axis=1).max() + 3
    u0, v0 = int(centre[0] - reach), int(centre[1] - reach)
    n = int(2 * reach) + 2
    uu = (u0 + np.arange(n))[:, None] + off[None, :]
    vv = (v0 + np.arange(n))[:, None] + off[None, :]
    X = np.stack(np.broadcast_arrays(uu.reshape(1, -1) - centre[0], vv.reshape(-1, 1) - centre[1]), axis=-1)
    Y = X @ np.linalg.inv(A).T
    rho = np.hypot(Y[..., 0], Y[..., 1])
    ang = np.degrees(np.arctan2(Y[..., 1], Y[..., 0])) % 360.0
    in_seg = np.zeros(rho.shape, bool)
    for a0, a1 in segments_deg:
        in_seg |= (ang >= a0) & (ang <= a1)
    ink = (rho <= r_dot) | ((rho >= r_in) & (rho <= r_out) & in_seg)
    cov = ink.reshape(n, s, n, s).mean(axis=(1, 3))
    out = np.zeros(shape)
    out[max(v0, 0):min(v0 + n, H), max(u0, 0):min(u0 + n, W)] = cov[max(0, -v0):n - max(0, v0 + n - H),
                                                                    max(0, -u0):n - max(0, u0 + n - W)]
    return out


@pytest.fixture(scope="module")
def discs_in_shade():
    """Discs of 22-30 px at the edge of a soft shadow band 10 DN deep (28 px FWHM, its middle
    24 px below the discs' centres, as the sheet's curl and the books cast on the DBAT
    photographs), an 8-bit image with 0.3 DN of noise (a JPEG's flat areas)."""
    rng = np.random.default_rng(23)
    H, W = 300, 600
    centres = np.array([[80.0 + 110.0 * k, 150.0] for k in range(5)]) + rng.uniform(-0.5, 0.5, (5, 2))
    radius = rng.uniform(11.0, 15.0, 5)
    cov = np.zeros((H, W))
    for c, r in zip(centres, radius, strict=True):
        cov += ellipse_coverage((H, W), c, r)
    cov = ndimage.gaussian_filter(cov, 1.0)
    vv, uu = np.mgrid[:H, :W].astype(float)
    shade = 10.0 * np.exp(-0.5 * ((vv - 150.0 - 24.0) / 12.0) ** 2)       # a shadow band below the discs
    img = BG8 - shade * (1 - cov) + (FIG8 - BG8) * cov
    return _to_uint8(img, 0.3, 1), centres


@pytest.mark.parametrize("method", METHODS)
def test_discs_joined_to_shading_are_found_at_their_centres(discs_in_shade, method):
    img, truth = discs_in_shade
    t = detect_targets(img, method=method)
    j, uv = match(t, truth, radius=1.0)
    assert (j >= 0).all(), f"found {np.count_nonzero(j >= 0)} of {len(truth)}"
    err = np.hypot(*(uv[j] - truth).T)
    assert err.max() < 0.05                          # [px]: the shadow is smooth across a disc
    assert t.num_rows == len(truth)                  # the shadow itself is no disc


@pytest.fixture(scope="module")
def ringed_targets():
    """Four ringed targets of the DBAT sheet's proportions (dot radius 7, ring segments from 19
    to 29, three code segments each), face-on and seen obliquely (affine, minor/major down to
    0.6), a soft shadow band 10 DN deep across the gap below their dots, 8-bit, 0.5 DN noise."""
    H, W = 260, 700
    rng = np.random.default_rng(7)
    centres = np.array([[90.0 + 170.0 * k, 120.0] for k in range(4)]) + rng.uniform(-0.5, 0.5, (4, 2))
    maps = [np.eye(2), np.array([[1.0, 0.0], [0.1, 0.6]]), np.array([[0.7, -0.3], [0.3, 0.9]]),
            np.array([[0.7, 0.0], [0.0, 1.2]])]
    segs = [[(10, 70), (130, 160), (250, 330)], [(0, 45), (90, 200), (270, 300)],
            [(30, 100), (180, 240), (300, 350)], [(60, 120), (200, 220), (280, 359)]]
    cov = sum(_ringed_coverage((H, W), c, A, 7.0, 19.0, 29.0, s) for c, A, s in zip(centres, maps, segs, strict=True))
    cov = ndimage.gaussian_filter(np.clip(cov, 0, 1), 1.0)
    vv = np.mgrid[:H, :W][0].astype(float)
    shade = 10.0 * np.exp(-0.5 * ((vv - 136.0) / 10.0) ** 2)
    dot_diameter = 14.0 * np.sqrt([abs(np.linalg.det(A)) for A in maps])
    return _to_uint8(BG8 - shade * (1 - cov) + (FIG8 - BG8) * cov, 0.5, 2), centres, dot_diameter


@pytest.mark.parametrize("method", METHODS)
def test_ringed_targets_are_measured_by_their_dots_centre(ringed_targets, method):
    img, truth, dot_diameter = ringed_targets
    t = detect_targets(img, method=method)
    j, uv = match(t, truth, radius=1.0)
    assert (j >= 0).all(), f"found {np.count_nonzero(j >= 0)} of {len(truth)} dots"
    err = np.hypot(*(uv[j] - truth).T)
    assert err.max() < 0.05                          # [px]: the segments do not pull the dot
    assert t.num_rows == len(truth), t.select(["u_px", "v_px", "diameter_px", "roundness"]).to_pylist()
    d = t["diameter_px"].to_numpy()[j]
    assert np.all(np.abs(d - dot_diameter) < 1.0)          # [px] the dot's size, not the ring's


def test_a_plain_disc_costs_no_second_measurement():
    """Splitting only touches components that are no disc: an isolated disc is one candidate."""
    img = _to_uint8(BG8 + (FIG8 - BG8) * ndimage.gaussian_filter(ellipse_coverage((120, 120), (60.2, 59.7), 12.0),
                                                                  1.0), 0.3, 3)
    t = detect_targets(img, return_rejected=True)
    assert t.num_rows == 1 and t["reject"][0].as_py() == ""
    assert math.hypot(t["u_px"][0].as_py() - 60.2, t["v_px"][0].as_py() - 59.7) < 0.02
