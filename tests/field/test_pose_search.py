"""Pose hypotheses (fieldcal.field.pose_search) against exact synthetic truth and references."""

import numpy as np
from scipy.spatial.transform import Rotation

from fieldcal.field.identify import measured_points
from fieldcal.field.pose_search import (
    Anchor,
    field_neighbours,
    field_symmetries,
    marker_poses,
    p3p_batch,
    poses_from_centre,
    poses_pose_free,
    rotations_from_directions,
)
from fieldcal.synthetic.field import measurements_of, wide_field


def test_rotations_from_directions_is_scipys_alignment():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(5, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    R_true = Rotation.random(random_state=1).as_matrix()
    a = b @ R_true.T + rng.normal(0, 1e-3, b.shape)
    R = rotations_from_directions(a[None], b[None])[0]
    ref, _ = Rotation.align_vectors(a, b)
    np.testing.assert_allclose(R, ref.as_matrix(), atol=1e-12)
    assert np.linalg.det(R) > 0


def test_p3p_gives_the_true_pose_among_its_solutions():
    sf = wide_field(seed=1)
    rng = np.random.default_rng(2)
    k = sf.data.obs.image == 2
    t, uv = sf.data.obs.target[k], sf.uv_true_px[k]
    tri = np.stack([rng.choice(len(t), 3, replace=False) for _ in range(50)])
    X = sf.targets_true.xyz_m[t[tri]]                                  # (50, 3, 3)
    rays = sf.camera.unproject(uv[tri])
    R, C, src = p3p_batch(X, rays)
    for h in range(50):
        err = np.abs(C[src == h] - sf.center_m[2]).max(axis=1)
        assert err.min() < 1e-6                                        # [m] exact rays: round-off only
        j = np.flatnonzero(src == h)[np.argmin(err)]
        assert np.abs(R[j] - sf.R_world_to_camera[2]).max() < 1e-6


def _anchor(sf, i, *, pivot_target=None):
    """The disc nearest the image centre (or the given target's) with its 40 nearest neighbours."""
    tab, truth = measurements_of(sf, i, coded=False, seed=0)
    kind, _, uv, usable = measured_points(tab)
    keep = (kind == "disc") & usable
    uv, truth = uv[keep], truth[keep]
    s = sf.camera.sensor
    p = int(np.argmin(np.linalg.norm(uv - [(s.width_px - 1) / 2, (s.height_px - 1) / 2], axis=1)))
    if pivot_target is not None:
        p = int(np.flatnonzero(truth == pivot_target)[0])
    j = np.argsort(np.linalg.norm(uv - uv[p], axis=1))[1:41]
    return uv, truth, p, j


def test_centre_prior_and_pose_free_search_find_the_true_pose():
    """With the true centre the rotation search, without anything the P3P search, ranks a pose
    near the truth among its best (0.1 px of noise)."""
    sf = wide_field(seed=1)
    X = sf.targets_true.xyz_m
    nbrs = field_neighbours(X, 100)
    i = 7
    uv, truth, p, j = _anchor(sf, i)
    for hyps in (poses_from_centre(sf.camera, sf.center_m[i], X, nbrs, Anchor(uv[p], uv[j], np.arange(len(X)))),
                 poses_pose_free(sf.camera, X, nbrs, Anchor(uv[p], uv[j], np.arange(len(X))))):
        assert hyps
        best = hyps[0][2]
        near = [h for h in hyps if h[2] == best and np.linalg.norm(h[1] - sf.center_m[i]) < 0.2
                and np.degrees(np.arccos(np.clip((np.trace(h[0].T @ sf.R_world_to_camera[i]) - 1) / 2, -1, 1))) < 1.0]
        assert near and all(h[3] == truth[p] for h in near)


def test_field_symmetries_of_a_square_sheet_and_of_a_field_with_gaps():
    """A square 10 x 10 grid repeats under three quarter turns (all of it) and under shifts (part
    of it); with random gaps it repeats only over small parts, by chance."""
    g = np.arange(10) * 0.15
    xx, yy = np.meshgrid(g, g)
    X = np.stack([xx.ravel(), yy.ravel(), np.zeros(100)], axis=1)
    sym = field_symmetries(X)
    full = [s for s in sym if s.overlap == 100]
    assert len(full) == 3                              # 90, 180, 270 degrees
    for s in sym:                                      # each maps its targets onto their images
        k = np.flatnonzero(s.perm >= 0)
        assert np.allclose(X[k] @ s.R.T + s.t, X[s.perm[k]], atol=1e-9)
    assert any(s.overlap == 90 for s in sym)           # one step
    rng = np.random.default_rng(0)
    gaps = X[rng.random(100) < 0.9]
    assert all(s.overlap < 0.55 * len(gaps) for s in field_symmetries(gaps))


def test_marker_poses_give_the_marker_in_the_camera_frame():
    """IPPE on a marker's four projected corners: the marker's centre and axes in the camera frame."""
    sf = wide_field(seed=1)
    i = 4
    tab, t = measurements_of(sf, i, coded=True, seed=0, corners=True)
    rows = np.flatnonzero(tab["kind"].to_numpy(zero_copy_only=False) == "aruco")
    assert len(rows)
    r = rows[0]
    corners = np.asarray(tab["corners_px"][int(r)].as_py()).reshape(4, 2)
    sols = marker_poses(sf.camera, corners, sf.marker_size_mm / 1000.0)
    R, C = sf.R_world_to_camera[i], sf.center_m[i]
    centre = R @ (sf.targets_true.xyz_m[t[r]] - C)
    normal = R @ np.array([0.0, -1.0, 0.0])             # the wall faces -Y
    err = [(np.linalg.norm(c - centre), np.degrees(np.arccos(np.clip(Rm[:, 2] @ normal, -1, 1)))) for Rm, c in sols]
    best = min(err, key=lambda e: e[1])            # IPPE's two solutions: one turned the wrong way
    # 0.1 px corner noise on a 120 mm marker ~5 m away: centre within 3 cm, normal within 5 degrees
    assert best[0] < 0.03 and best[1] < 5.0, err
