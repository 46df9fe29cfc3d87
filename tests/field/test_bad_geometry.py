"""Geometry that cannot calibrate: a diagnosis (GeometryError), never a silently wrong calibration.

Observation-only field sessions (session.json, targets.csv, observations.csv: what the flow
solves without measuring any image) are written here from an exact synthetic scene: a
wide-angle camera (the ``WIDE_ANGLE`` parameters on a 3000 x 2000 px, 7.8 um sensor), a
10 x 6 grid of targets 0.9 m apart on a wall (flat, or with up to 1 m of relief), and
camera poses chosen per test. Image noise 0.1 px, survey noise 1 mm, seeded.

Each refusal is paired with a control that differs only in what makes the geometry good
(more images, depth, other directions, roll), which calibrates and lands within 3 sigma of
the truth: the refusal is caused by the geometry and by nothing else. The controls give the
method's full parameter set as the session's ``estimate``: the automatic selection used to
hold parameters that were "not significant" at 0 although this lens's are not (k2, a2), which
moved f by up to 3.6 of its sigmas over seeds 0-7 of these scenes (full set: at most 2.7);
issue 16 removed that rule (docs/uncertainty.md), and the controls stay independent of it.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest

from fieldcal import pipeline
from fieldcal.errors import GeometryError
from fieldcal.field import adjustment
from fieldcal.model.camera import FIELD_PARAMS, INDEX, Camera, Sensor
from fieldcal.solver.blocksparse import SingularSystemError
from fieldcal.synthetic.field import WIDE_ANGLE, look_at

SENSOR = Sensor(3000, 2000, 7.8)
CAMERA = Camera.from_dict(SENSOR, WIDE_ANGLE)
FP = "sha256:" + "0" * 64
FULL = FIELD_PARAMS      # the controls estimate the full set: no automatic selection (see below)
AIM = (0.0, 0.0, 2.7)

# convergent stations around the wall, rolled by multiples of 90 degrees: (centre, aim, roll)
CONVERGENT = [((-3, -6, 1.5), AIM, 0), ((3, -6, 2.5), AIM, 90), ((0, -7, 3.5), AIM, 270),
              ((-2, -5, 3.0), AIM, 0), ((2, -5, 1.0), AIM, 90), ((0, -6, 2.0), AIM, 180)]
# the same distance and direction, no roll (a few cm apart): f cannot be told from the distance
SAME_DIRECTION = [((0.01 * i, -6.0, 2.7), (0.01 * i, 0.0, 2.7), 0) for i in range(4)]


def wall(relief_m: float = 0.0, n=(10, 6), spacing_m: float = 0.9, seed: int = 0) -> np.ndarray:
    """Targets (n, 3) [m] on a grid in the plane Y = 0, moved back by up to ``relief_m``."""
    x, z = np.meshgrid((np.arange(n[0]) - (n[0] - 1) / 2) * spacing_m, np.arange(n[1]) * spacing_m + 0.5)
    y = -relief_m * np.random.default_rng(seed).random(x.size)
    return np.stack([x.ravel(), y, z.ravel()], axis=1)


def write_obs_session(folder, X, poses, *, nominal_focal_mm=24.0, estimate=None, seed=1,
                      noise_px=0.1, survey_mm=1.0) -> Path:
    """An observation-only field session of the scene (module docstring); returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    manifest = {"schema": "fieldcal.session/1", "method": "field", "camera_id": "cam-geometry",
                "acquired": "2026-11-20T09:30:00Z", "sensor": SENSOR.to_dict(),
                "field": {"targets": "targets.csv"}, "images": "images/*.tif"}
    if nominal_focal_mm is not None:
        manifest["lens"] = {"nominal_focal_mm": nominal_focal_mm}
    if estimate is not None:
        manifest["estimate"] = list(estimate)
    (folder / "session.json").write_text(json.dumps(manifest))
    surveyed = X + rng.normal(0.0, survey_mm / 1000.0, X.shape)
    rows = ["id,X,Y,Z,sigma_mm,code"] + [f"T{k:03d},{x:.6f},{y:.6f},{z:.6f},{survey_mm},"
                                         for k, (x, y, z) in enumerate(surveyed)]
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    rows = ["image,target_id,u,v,sigma_px"]
    for i, (center, aim, roll_deg) in enumerate(poses):
        uv = CAMERA.project(X, look_at(center, aim, np.radians(roll_deg)), np.asarray(center, float))
        inside = (np.isfinite(uv).all(axis=1) & (uv[:, 0] > 5) & (uv[:, 0] < SENSOR.width_px - 6)
                  & (uv[:, 1] > 5) & (uv[:, 1] < SENSOR.height_px - 6))
        uv = uv + rng.normal(0.0, noise_px, uv.shape)
        rows += [f"images/i{i:02d}.tif,T{k:03d},{uv[k, 0]:.4f},{uv[k, 1]:.4f},{noise_px}"
                 for k in np.flatnonzero(inside)]
    (folder / "observations.csv").write_text("\n".join(rows) + "\n")
    return folder


def solve(folder):
    """What the flow runs for an observation-only session: prepare, then solve."""
    prepared = pipeline.prepare(folder)
    assert prepared.to_measure == []
    return pipeline.solve(prepared, {}, fingerprint_=FP).document


def assert_within_3_sigma(doc):
    for name in ("f_mm", "xp_mm", "yp_mm"):
        z = (doc["parameters"][name] - CAMERA.params[INDEX[name]]) / doc["sigma"][name]
        assert abs(z) < 3.0, f"{name}: {z:.2f} sigma"


def refused(folder, match):
    with pytest.raises(GeometryError, match=match) as info:
        solve(folder)
    assert "\n" not in str(info.value)
    return str(info.value)


# --------------------------------------------------------------------------------------
def test_a_good_network_calibrates_the_camera(tmp_path):
    """The control: the scene's generator and solver are right on a good network."""
    doc = solve(write_obs_session(tmp_path / "good", wall(relief_m=1.0), CONVERGENT, estimate=FULL))
    assert doc["stats"]["n_images"] == 6
    assert_within_3_sigma(doc)


@pytest.mark.parametrize("n_images", [1, 2])
def test_too_few_images_is_a_diagnosis(tmp_path, n_images):
    folder = write_obs_session(tmp_path / "few", wall(relief_m=1.0), CONVERGENT[:n_images])
    names = ", ".join(f"images/i{i:02d}.tif" for i in range(n_images))
    refused(folder, rf"^only {n_images} image\(s\) \({names}\); the field method needs at least 3")


def test_three_images_are_enough_for_a_good_network(tmp_path):
    doc = solve(write_obs_session(tmp_path / "three", wall(relief_m=1.0), CONVERGENT[:3], estimate=FULL))
    assert doc["stats"]["n_images"] == 3
    assert_within_3_sigma(doc)


def test_too_few_targets_is_a_diagnosis_naming_the_image(tmp_path):
    X = wall(relief_m=1.0)
    seen = np.ones(len(X), bool)
    for center, aim, roll_deg in CONVERGENT:
        uv = CAMERA.project(X, look_at(center, aim, np.radians(roll_deg)), np.asarray(center, float))
        seen &= np.isfinite(uv).all(axis=1) & (uv > 10).all(axis=1) & (uv < [2990, 1990]).all(axis=1)
    assert seen.sum() >= 6
    folder = write_obs_session(tmp_path / "five", X[np.flatnonzero(seen)[:5]], CONVERGENT)
    refused(folder, r"^images/i00\.tif: only 5 observed target\(s\); an image needs at least 6")
    # the control: six targets that every image sees are accepted (DLT's minimum per image)
    doc = solve(write_obs_session(tmp_path / "many", X[np.flatnonzero(seen)], CONVERGENT, estimate=FULL))
    assert doc["stats"]["n_targets"] == seen.sum()


@pytest.mark.parametrize("factorisation", ["as it comes", "breaks down"])
@pytest.mark.parametrize("estimate", [None, ("f_mm", "xp_mm", "yp_mm")], ids=["automatic", "session"])
def test_f_that_cannot_be_told_from_the_distance_is_a_diagnosis(tmp_path, monkeypatch, estimate, factorisation):
    """A flat wall photographed from one distance and direction without roll: f vs distance.

    The diagnosis must not depend on where (or whether) the Cholesky factorisation of the
    near-singular normal equations breaks down on a given BLAS: "breaks down" makes every
    factorisation of the check fail, as it may at any leading minor on another machine."""
    if factorisation == "breaks down":
        def broken(S):
            raise SingularSystemError("the reduced Schur complement is not positive definite "
                                      "(23-th leading minor not positive)", "reduced")
        monkeypatch.setattr(adjustment, "equilibrated_cholesky", broken)
    folder = write_obs_session(tmp_path / "same", wall(), SAME_DIRECTION, estimate=estimate)
    text = refused(folder, r"^the data cannot determine the principal distance: ")
    # the diagnosis names the unknown f cannot be told from: a camera's distance to the wall (Y)
    held = " even with every additional parameter held fixed" if estimate is None else ""
    assert re.search(rf"its sigma is [\d.e+]+ % of f{held} \(correlation -1\.0000 with Y_m of "
                     r"images/i0\d\.tif\)", text), text
    assert text.endswith("add images from other positions and distances, rolled by 90 degrees, or targets in depth")


def test_depth_separates_f_from_the_distance(tmp_path):
    """The same poses in front of a wall with 1 m of relief: a correct calibration."""
    doc = solve(write_obs_session(tmp_path / "deep", wall(relief_m=1.0), SAME_DIRECTION, estimate=FULL))
    assert_within_3_sigma(doc)


def test_a_flat_wall_without_nominal_focal_length_needs_views_from_other_directions(tmp_path):
    """Planar field, no lens.nominal_focal_mm: the initial f comes from Zhang's closed form,
    which needs views of the plane from different directions."""
    flat = wall()
    refused(write_obs_session(tmp_path / "two", flat, CONVERGENT[:2], nominal_focal_mm=None),
            r"^only 2 image\(s\)")
    refused(write_obs_session(tmp_path / "parallel", flat, SAME_DIRECTION, nominal_focal_mm=None),
            r"^(session: zhang_focal: no real focal length fits these views|"
            r"the data cannot determine the principal distance)")
    # the control: the same flat wall from convergent, rolled views calibrates without a nominal f
    doc = solve(write_obs_session(tmp_path / "zhang", flat, CONVERGENT, nominal_focal_mm=None, estimate=FULL))
    assert_within_3_sigma(doc)
