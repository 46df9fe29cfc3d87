"""The synthetic field problems: the paper's sizes, exact truth, seeded noise, blunders."""

import numpy as np
import pytest

from fieldcal.synthetic import field as syn


@pytest.fixture(scope="module")
def paper():
    return syn.paper_field(seed=0)


def test_paper_geometry_has_the_papers_sizes(paper):
    d = paper.data
    per_image = np.bincount(d.obs.image)
    assert len(d.images) == 72 and len({im.station for im in d.images}) == 6
    assert 1800 <= len(np.unique(d.obs.target)) <= 2100        # paper: 1990 targets
    assert 100 <= per_image.min() and per_image.max() <= 300    # "each image seeing 100-300"
    assert 11_000 <= len(d.obs) <= 16_000                        # "about 12 000 observations"
    depth = np.ptp(paper.targets_true.xyz_m[:, 1])
    assert 1.0 < depth < 2.5                                    # facade relief: not coplanar
    dist = -paper.center_m[:, 1]
    assert 55 < dist.min() and dist.max() < 62                  # ~60 m away


def test_exact_image_points_are_projections_of_the_true_targets(paper):
    d = paper.data
    for i in (0, 37, 71):
        k = d.obs.image == i
        uv = paper.camera.project(paper.targets_true.xyz_m[d.obs.target[k]],
                                  paper.R_world_to_camera[i], paper.center_m[i])
        assert np.abs(uv - paper.uv_true_px[k]).max() < 1e-9


def test_noise_levels_are_the_ones_asked_for(paper):
    dn = paper.data.obs.uv_px - paper.uv_true_px
    assert np.std(dn) == pytest.approx(0.1, rel=0.03)
    ds = (paper.data.targets.xyz_m - paper.targets_true.xyz_m) * 1000
    assert np.std(ds) == pytest.approx(5.0, rel=0.05)


def test_wide_angle_camera_has_about_20px_of_distortion_and_covers_the_sensor():
    sf = syn.wide_field(seed=1)
    from fieldcal.model.camera import correction
    s = sf.camera.sensor
    corners = s.pixel_to_mm(np.array([[0, 0], [5999, 3999]], float))
    mag = np.linalg.norm(correction(corners, sf.camera.params), axis=1) / s.pixel_mm
    assert 15 < mag.max() < 30
    uv = sf.uv_true_px  # observations reach every corner region of the sensor
    for cu, cv in ((0, 0), (5999, 0), (0, 3999), (5999, 3999)):
        assert (np.hypot(uv[:, 0] - cu, uv[:, 1] - cv) < 600).sum() >= 10


def test_same_seed_same_problem_and_blunders_are_reported(paper):
    again = syn.paper_field(seed=0)
    assert np.array_equal(again.data.obs.uv_px, paper.data.obs.uv_px)
    bad, info = syn.add_blunders(paper, fraction=0.01, seed=3)
    moved = np.linalg.norm(bad.data.targets.xyz_m - paper.data.targets.xyz_m, axis=1)
    assert np.allclose(moved[info.survey_targets], 0.10) and (moved > 0).sum() == len(info.survey_targets)
    changed = np.flatnonzero(bad.data.obs.target != paper.data.obs.target)
    assert np.array_equal(changed, info.swapped_observations) and len(changed) >= 0.009 * len(paper.data.obs)


@pytest.mark.parametrize("scenario, n", [("paper", 3), ("paper", 4), ("paper", 6), ("paper", 12), ("wide", 3)])
def test_a_few_images_share_targets_and_spread_over_the_stations(paper, scenario, n):
    sf = paper if scenario == "paper" else syn.wide_field(seed=0)
    idx = syn.overlapping_images(sf, n)
    assert len(idx) == n == len(set(idx)) and idx == sorted(idx)
    seen = np.zeros((len(sf.data.images), len(sf.data.targets)), bool)
    seen[sf.data.obs.image, sf.data.obs.target] = True
    for i in idx:                                   # every image shares enough with the others
        others = seen[[j for j in idx if j != i]].any(axis=0)
        assert (seen[i] & others).sum() >= syn.MIN_SHARED_TARGETS
    stations = {sf.data.images[i].station for i in idx}
    assert len(stations) == min(n, len({im.station for im in sf.data.images}))
    rolls = syn._roll_class(sf.R_world_to_camera[idx])
    assert len(set(rolls.tolist())) == min(n, 4) or scenario == "wide"    # wide: 3 rolls per station


def test_images_spread_evenly_over_the_list_share_nothing(paper):
    """Why the choice above exists: `synth --n-images 4` took images 0, 24, 47, 71, which share
    no target, and the session could not be calibrated (issue 30)."""
    seen = np.zeros((len(paper.data.images), len(paper.data.targets)), bool)
    seen[paper.data.obs.image, paper.data.obs.target] = True
    even = [0, 24, 47, 71]
    assert all((seen[i] & seen[[j for j in even if j != i]].any(axis=0)).sum() == 0 for i in even)
    assert syn.overlapping_images(paper, 100) == list(range(len(paper.data.images)))
