"""Target normals: read from the session, resolved, estimated from the field's local planes, and
the eccentricity bound of a disc whose normal is unknown (fieldcal.field.normals, issue 23)."""

import json

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.field.eccentricity import correction_px
from fieldcal.field.normals import eccentricity_bound_px, estimate_normals, normals_summary, resolve_normals
from fieldcal.model.camera import Camera, Sensor
from fieldcal.session.data import TargetField
from fieldcal.session.loader import load_session
from fieldcal.synthetic.field import WIDE_ANGLE, faceted_field, look_at, wide_field
from fieldcal.synthetic.session_writer import write_field_session


def _angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0.0, 1.0)))


def _grid(origin, u, w, n_u, n_w, spacing):
    a, b = np.meshgrid(np.arange(n_u) * spacing, np.arange(n_w) * spacing)
    return np.asarray(origin) + a.reshape(-1, 1) * np.asarray(u) + b.reshape(-1, 1) * np.asarray(w)


def _box_corner(spacing=0.3, n=7):
    """Three faces of a box meeting at a corner (x = 0, y = 0, z = 0 planes), targets half a
    spacing from the edges; normals +X, +Y, +Z."""
    h = spacing / 2
    faces = [(_grid([0, h, h], [0, 1, 0], [0, 0, 1], n, n, spacing), [1.0, 0, 0]),
             (_grid([h, 0, h], [1, 0, 0], [0, 0, 1], n, n, spacing), [0, 1.0, 0]),
             (_grid([h, h, 0], [1, 0, 0], [0, 1, 0], n, n, spacing), [0, 0, 1.0])]
    X = np.vstack([f for f, _ in faces])
    N = np.vstack([np.tile(nrm, (len(f), 1)) for f, nrm in faces])
    return X, N


@pytest.mark.parametrize("field", ["panels", "box corner"])
def test_local_planes_find_the_normals_of_panels_at_several_tilts_and_of_faces(field):
    if field == "panels":
        t = faceted_field(seed=0).targets_true           # five panels, yaw +30 ... +15 degrees
        X, N = t.xyz_m, t.normals
    else:
        X, N = _box_corner()
    rng = np.random.default_rng(3)
    # 1 mm coordinates (adjusted targets), tolerance three sigmas
    E = estimate_normals(X + rng.normal(0.0, 1e-3, X.shape), tol_m=3e-3)
    ok = np.isfinite(E).all(axis=1)
    assert ok.mean() > 0.95
    ang = _angles_deg(E[ok], N[ok])
    assert ang.max() < 2.0                                      # 1 mm over 0.3 m: ~0.2 degrees typical
    # exact coordinates: exact normals
    E0 = estimate_normals(X, tol_m=1e-4)
    ok0 = np.isfinite(E0).all(axis=1)
    np.testing.assert_allclose(np.abs(np.sum(E0[ok0] * N[ok0], axis=1)), 1.0, atol=1e-9)


def test_steps_of_parallel_faces_keep_the_face_normal_where_a_face_is_wide():
    """A wall with pillars 0.5 m in front (wide_field): the faces are parallel, the steps are
    outliers of each face's plane. Where a face has three or more columns the normal is the
    face's; the pillars two targets wide cannot be told from a plane through two rows at
    different depths (module docstring of fieldcal.field.normals), hence a few wrong ones."""
    t = wide_field(seed=0).targets_true
    E = estimate_normals(t.xyz_m, tol_m=1e-3)
    ok = np.isfinite(E).all(axis=1)
    ang = _angles_deg(E[ok], t.normals[ok])
    assert ok.mean() > 0.9
    assert np.mean(ang < 1.0) > 0.9


def test_a_fold_edge_with_equal_support_is_left_undetermined():
    # two half-planes at 90 degrees meeting on the line x = 0, z axis; a target on the edge
    s = 0.3
    left = _grid([0, 0, 0], [-1, 0, 0], [0, 0, 1], 4, 5, s)
    right = _grid([0, 0, 0], [0, -1, 0], [0, 0, 1], 4, 5, s)
    right = right[right[:, 1] < -1e-12]                              # the edge column once
    X = np.vstack([left, right])
    E = estimate_normals(X, tol_m=1e-4)
    edge = np.flatnonzero(np.abs(X[:, 0]) + np.abs(X[:, 1]) < 1e-12)
    assert len(edge) == 5 and not np.isfinite(E[edge]).any()
    inner = np.flatnonzero(np.abs(X[:, 0]) > 0.5)
    np.testing.assert_allclose(np.abs(E[inner]), np.tile([0.0, 1.0, 0.0], (len(inner), 1)), atol=1e-9)


def test_resolve_normals_given_then_planar_then_estimated_pointing_to_the_cameras():
    X, N = _box_corner()
    given = np.full_like(N, np.nan)
    given[:10] = N[:10] * -1.0                                   # given ones are kept as they are
    t = TargetField(np.arange(len(X)).astype(str), X, 5.0, -1, given)
    towards = X + 5.0 * N                                        # the cameras see each face from outside
    r = resolve_normals(t, xyz_m=X, tol_m=1e-4, towards_m=towards)
    assert list(r.source[:10]) == ["given"] * 10
    np.testing.assert_allclose(r.normals[:10], -N[:10])
    est = r.source == "estimated"
    assert est.sum() > 0.9 * (len(X) - 10)
    np.testing.assert_allclose(r.normals[est], N[est], atol=1e-9)   # signed towards the cameras
    assert set(r.source) <= {"given", "estimated", "none"}
    flat = TargetField(t.ids, X * [1, 1, 0], 5.0, -1, None)       # a planar field: its plane
    rf = resolve_normals(flat)
    assert set(rf.source) == {"planar fit"} and np.allclose(np.abs(rf.normals[:, 2]), 1.0)
    off = resolve_normals(t, estimate=False)
    assert set(off.source[10:]) == {"none"} and not np.isfinite(off.normals[10:]).any()
    s = normals_summary(r.source)
    assert s["normals"].startswith("estimated") and s["n_targets"]["given"] == 10


def test_eccentricity_bound_is_at_least_the_eccentricity_of_any_normal():
    cam = Camera.from_dict(Sensor(1200, 800, 19.5), WIDE_ANGLE)
    C = np.array([1.0, -5.0, 1.5])
    R = look_at(C, [0.0, 0.0, 2.0])
    rng = np.random.default_rng(5)
    X = np.column_stack([rng.uniform(-3, 3, 40), rng.uniform(-0.5, 0.5, 40), rng.uniform(0.5, 3.5, 40)])
    bound = eccentricity_bound_px(cam, R, C, X, 0.05)
    ray = (C - X) / np.linalg.norm(C - X, axis=1, keepdims=True)
    worst = np.zeros(len(X))
    for _ in range(200):                                          # random normals within 70 deg of the ray
        n = rng.normal(size=X.shape)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where((np.sum(n * ray, axis=1) < 0)[:, None], -n, n)
        keep = np.sum(n * ray, axis=1) > np.cos(np.radians(70.0))
        e = np.hypot(*correction_px(cam, R, C, X[keep], n[keep], 0.05).T)
        worst[keep] = np.maximum(worst[keep], e)
    # the lattice and its refinement find the maximum to better than 1 %
    assert np.all(bound >= 0.99 * worst) and np.all(bound < 1.5 * worst)
    assert np.all(bound > 0.0)


def test_session_normals_per_target_take_precedence_over_the_field_normal(tmp_path):
    sf = wide_field(seed=1)
    write_field_session(tmp_path, sf, images=False, observations_csv=True, normals="columns")
    lines = (tmp_path / "targets.csv").read_text().splitlines()
    lines[1] = ",".join(lines[1].split(",")[:-3] + ["0.6", "-0.8", "0"])        # one target turned
    lines[2] = ",".join(lines[2].split(",")[:-3] + ["", "", ""])               # one unknown
    lines[3] = ",".join(lines[3].split(",")[:-3] + ["0.0001", "-1.004", "0"])  # rounded: normalised
    (tmp_path / "targets.csv").write_text("\n".join(lines) + "\n")
    n = load_session(tmp_path).targets().normals
    np.testing.assert_allclose(n[0], [0.6, -0.8, 0.0])
    assert not np.isfinite(n[1]).any()
    assert np.linalg.norm(n[2]) == pytest.approx(1.0)
    manifest = json.loads((tmp_path / "session.json").read_text())
    manifest["field"]["target_normal"] = [0.0, -0.7071, 0.7071]
    (tmp_path / "session.json").write_text(json.dumps(manifest))
    n = load_session(tmp_path).targets().normals
    np.testing.assert_allclose(n[0], [0.6, -0.8, 0.0])                       # per target first
    np.testing.assert_allclose(n[1], [0.0, -np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    with pytest.raises(InputError, match="needs every target to face the same way"):
        write_field_session(tmp_path / "x", faceted_field(seed=0), images=False, normals="session")


def _shape_views(sf, noise, rng, radius_m):
    """Per image of a synthetic field: pose, the targets it sees, their true ellipses' shape
    vectors plus Gaussian noise ``noise`` per component."""
    from fieldcal.field.eccentricity import rim_px
    from fieldcal.field.normals import shape_vectors

    views, obs = [], sf.data.obs
    for i in range(len(sf.data.images)):
        t = obs.target[obs.image == i]
        R, C = sf.R_world_to_camera[i], sf.center_m[i]
        shape = shape_vectors(rim_px(sf.camera, R, C, sf.targets_true.xyz_m[t], sf.targets_true.normals[t], radius_m))
        views.append((R, C, t, shape + rng.normal(0.0, noise, shape.shape)))
    return views


@pytest.mark.parametrize("noise, wrong_max", [(0.004, 0), (0.05, None)])
def test_the_ellipses_choose_between_local_planes_where_the_geometry_cannot(noise, wrong_max):
    """Pillars two targets wide in front of a wall (wide_field): the geometry alone gives ~15
    normals tilted by 55 degrees (a plane through a pillar's column and the wall's); the
    imaged ellipses' shapes (noise 0.004, as measured on rendered 20 px discs) reject them.
    With shapes 12 times noisier (targets too small for their ellipses to say much) they
    switch nothing they cannot justify: never worse than the geometry alone."""
    from fieldcal.field.normals import choose_by_shapes, local_planes

    sf = wide_field(seed=0)
    t = sf.targets_true
    radius_m = sf.target_diameter_mm / 2000.0
    rng = np.random.default_rng(11)
    X = t.xyz_m + rng.normal(0.0, 1e-3, t.xyz_m.shape)
    cand, sup = local_planes(X, tol_m=3e-3)
    geo = estimate_normals(X, tol_m=3e-3)
    views = _shape_views(sf, noise, rng, radius_m)
    towards = np.full(X.shape, np.nan)
    seen = np.unique(sf.data.obs.target)
    towards[seen] = [sf.center_m[sf.data.obs.image[sf.data.obs.target == k]].mean(axis=0) for k in seen]
    est, shape_noise = choose_by_shapes(sf.camera, views, cand, sup, X, radius_m, towards)
    assert shape_noise == pytest.approx(noise, rel=0.5)
    ok_geo, ok = np.isfinite(geo).all(axis=1), np.isfinite(est).all(axis=1)
    wrong_geo = np.sum(_angles_deg(geo[ok_geo], t.normals[ok_geo]) > 10.0)
    wrong = np.sum(_angles_deg(est[ok], t.normals[ok]) > 10.0)
    assert wrong_geo >= 8
    assert ok[seen].mean() > 0.95
    if wrong_max is not None:
        assert wrong <= wrong_max
        assert _angles_deg(est[ok], t.normals[ok]).max() < 3.0
    else:
        assert wrong <= wrong_geo


@pytest.mark.parametrize("targets_adjusted", [True, False])
def test_parameter_sensitivities_predict_the_adjustment_to_a_systematic_error(targets_adjusted):
    """fieldcal.field.sensitivity: the linear move of f, xp, yp for an error pattern of every image
    point (the eccentricity of 50 mm discs, smooth and systematic) against adjusting again with
    the points moved by it; the bound of the move is at least the move."""
    from dataclasses import replace

    from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
    from fieldcal.field.sensitivity import eccentricity_bias_bounds, parameter_bounds, sensitivities

    sf = wide_field(seed=2, image_noise_px=0.02)
    data, obs = sf.data, sf.data.obs
    o = AdjustmentOptions(targets_adjusted=targets_adjusted)
    res = adjust_field(data, o)
    e = np.zeros_like(obs.uv_px)
    for i in range(len(data.images)):
        s = obs.image == i
        t = obs.target[s]
        e[s] = correction_px(sf.camera, sf.R_world_to_camera[i], sf.center_m[i], sf.targets_true.xyz_m[t],
                             sf.targets_true.normals[t], 0.025)
    k, g = sensitivities(res)
    predicted = np.einsum("kjc,kc->j", g, e[k])[:3]
    moved = adjust_field(replace(data, obs=replace(obs, uv_px=obs.uv_px + e)), o)
    actual = moved.params[:3] - res.params[:3]
    # linear in a 0.05 px pattern: 1 % of f's move (5 % of the much smaller xp, yp moves, or 1e-6 mm)
    np.testing.assert_allclose(predicted[0], actual[0], rtol=0.01)
    np.testing.assert_allclose(predicted[1:], actual[1:], rtol=0.05, atol=1e-6)
    assert np.all(parameter_bounds(res, np.hypot(*e.T))[:3] >= np.abs(actual))
    # the points of every 15th target: their own pattern's move, against its per-target bound
    few = np.isin(obs.target, np.arange(0, len(sf.targets_true), 15))
    own = np.einsum("kjc,kc->j", g[few[k]], e[k[few[k]]])[:3]
    assert np.all(eccentricity_bias_bounds(res, few, 0.025)[:3] >= np.abs(own))
