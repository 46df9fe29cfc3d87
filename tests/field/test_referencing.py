"""Automatic referencing (issue 26 goal 1; fieldcal.field.referencing, from_images step 7).

Truth: the synthetic fields of fieldcal.synthetic (exact targets, poses and image points with
noise); the detector's output per image from ``measurements_of`` (the measurements table the
renderer's images give, without the pixels), with false discs added.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from fieldcal.field.adjustment import AdjustmentOptions
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.field.referencing import ReferencingOptions, reference_discs
from fieldcal.model.camera import INDEX
from fieldcal.session.loader import load_session
from fieldcal.synthetic.field import measurements_of, paper_field, wide_field
from fieldcal.synthetic.render import scaled_field
from fieldcal.synthetic.session_writer import write_field_session

FALSE_DISCS = 10


def test_discs_of_oriented_images_are_matched_into_the_true_targets():
    """Every image's discs (no ids) and 10 false discs each, the true camera and poses: each
    target seen in three or more images is one track of exactly its own points, at its place."""
    sf = wide_field(seed=3)
    d = sf.data
    rng = np.random.default_rng(1)
    uv, truth = [], []
    for i in range(len(d.images)):
        k = np.flatnonzero(d.obs.image == i)
        fake = rng.uniform([0, 0], [d.sensor.width_px, d.sensor.height_px], (FALSE_DISCS, 2))
        uv.append(np.concatenate([d.obs.uv_px[k], fake]))
        truth.append(np.concatenate([d.obs.target[k], np.full(FALSE_DISCS, -1)]))
    tracks = reference_discs(sf.camera, sf.R_world_to_camera, sf.center_m, uv)
    t = np.array([truth[i][p] for i, p in zip(tracks.image, tracks.point, strict=True)])
    of = [t[tracks.track == k] for k in range(len(tracks))]
    assert all(len(set(v)) == 1 and v[0] >= 0 for v in of)           # pure: one true target, no false disc
    target = np.array([v[0] for v in of])
    seen = np.bincount(d.obs.target, minlength=len(d.targets))
    assert len(set(target)) == len(target) == int((seen >= 3).sum())  # complete, each target once
    assert all(len(v) == seen[target[k]] for k, v in enumerate(of))   # every one of its points
    err = np.linalg.norm(tracks.X_m - sf.targets_true.xyz_m[target], axis=1)
    assert np.median(err) < 0.2e-3 and err.max() < 2e-3     # m: intersection of 0.1 px rays at 5-7 m


def test_no_tracks_from_false_discs_alone():
    sf = wide_field(seed=3)
    rng = np.random.default_rng(2)
    s = sf.data.sensor
    uv = [rng.uniform([0, 0], [s.width_px, s.height_px], (40, 2)) for _ in sf.data.images]
    assert len(reference_discs(sf.camera, sf.R_world_to_camera, sf.center_m, uv, ReferencingOptions())) == 0


@pytest.fixture(scope="module")
def referenced(tmp_path_factory):
    """The paper's scenario at scale 0.25, 12 images; targets.csv lists the 78 coded targets and
    a quarter of the plain ones: the other plain discs no survey names."""
    sf = scaled_field(paper_field(), 0.25)
    images = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]
    folder = tmp_path_factory.mktemp("referencing")
    write_field_session(folder, sf, images=False, coded=True, image_indices=images)
    lines = (folder / "targets.csv").read_text().splitlines()
    kept = [line for n, line in enumerate(lines[1:]) if line.split(",")[5].strip() or n % 4 == 0]
    (folder / "targets.csv").write_text("\n".join([lines[0], *kept]) + "\n")
    listed = {line.split(",")[0] for line in kept}
    session = load_session(folder)
    meas = {im.file: measurements_of(sf, i, coded=True, seed=1, extra_blobs=5)[0]
            for i, im in zip(images, session.images, strict=True)}
    lines_out: list[str] = []
    data, res, _ = calibrate_from_measurements(session, meas, AdjustmentOptions(), progress=lines_out.append,
                                               referencing=ReferencingOptions())
    return sf, images, listed, data, res, lines_out


def test_unnamed_discs_of_a_photographed_session_become_unsurveyed_targets(referenced):
    sf, images, listed, data, res, lines = referenced
    ar = np.flatnonzero(np.char.startswith(data.targets.ids.astype(str), "AR"))
    assert data.meta["referenced_targets"] == len(ar) > 100
    assert any("automatic referencing" in line for line in lines)
    # the unlisted plain targets seen in 3+ of the images: (nearly) all found
    obs = sf.data.obs
    sel = np.isin(obs.image, images)
    seen = np.bincount(obs.target[sel], minlength=len(sf.targets_true.ids))
    missing = np.array([tid not in listed for tid in sf.targets_true.ids])
    expected = int(((seen >= 3) & missing).sum())
    assert len(ar) >= 0.9 * expected
    # each is a distinct unlisted target, where the adjustment puts it within 4 sigma
    stats = res.stats()
    rows = {r["id"]: r for r in stats["unsurveyed_targets"]}
    placed = [k for k in ar if data.targets.ids[k] in rows]
    X = np.array([rows[data.targets.ids[k]]["xyz_m"] for k in placed])
    sig = np.array([rows[data.targets.ids[k]]["sigma_mm"] for k in placed]) / 1000.0
    dist, j = cKDTree(sf.targets_true.xyz_m).query(X)
    assert len(set(j)) == len(j) and missing[j].all()
    z = np.abs(X - sf.targets_true.xyz_m[j]) / sig
    assert np.mean(z.max(axis=1) < 4.0) > 0.98
    # interior orientation within its sigmas of the truth
    for name in ("f_mm", "xp_mm", "yp_mm", "k1"):
        assert abs(res.params[INDEX[name]] - sf.camera.params[INDEX[name]]) < 4 * res.sigma[name], name
