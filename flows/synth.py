"""Synthetic sessions with their truth, for ``fieldcal synth`` and ``fieldcal demo``.

:func:`write_synthetic` writes a session folder (CONTRACT section 3) made by
:mod:`fieldcal.synthetic` and, beside it, ``truth.json``: the camera it was made with and,
for the goniometer, what the method gives on the exact spot positions of the same set-up.
"""

from __future__ import annotations

import json
from pathlib import Path

from fieldcal.errors import InputError

__all__ = ["write_synthetic", "check_synthetic", "METHODS", "SCENARIOS"]

METHODS = ("goniometer", "field", "rig")
SCENARIOS = {"goniometer": ("canon5d2", "h3d"), "field": ("paper", "wide"), "rig": ("two-head", "oblique")}


def check_synthetic(method: str, scenario: str | None) -> str:
    """The scenario to use (the method's first by default); :class:`InputError` when unknown."""
    if method not in METHODS:
        raise InputError(f"method must be 'goniometer', 'field' or 'rig', got {method!r}")
    scenario = scenario or SCENARIOS[method][0]
    if scenario not in SCENARIOS[method]:
        raise InputError(f"{method} scenario must be " + " or ".join(f"'{s}'" for s in SCENARIOS[method])
                         + f", got {scenario!r}")
    return scenario


def _goniometer(out: Path, scenario: str, seed: int, raster_scale: float, camera_id, session_id):
    from fieldcal.goniometer import method as goniometer
    from fieldcal.model.camera import PARAM_NAMES
    from fieldcal.session.frames import read_frames_csv
    from fieldcal.synthetic.goniometer import write_session

    gt = write_session(out, scenario, seed=seed, raster_scale=raster_scale, camera_id=camera_id,
                       session_id=session_id)
    frames = read_frames_csv(out / "frames.csv")
    ref = goniometer.calibrate(gt.sensor, frames, gt.exact_measurements(),
                               nominal_focal_mm=gt.scenario.nominal_focal_mm)
    return gt.camera, {n: float(v) for n, v in zip(PARAM_NAMES, ref.parameters, strict=True)}


def _field(out: Path, scenario: str, seed: int, images: bool, scale: float, n_images, marks: bool,
           camera_id, session_id, check_points):
    from fieldcal.synthetic.field import check_point_ids, overlapping_images, paper_field, wide_field
    from fieldcal.synthetic.render import scaled_field
    from fieldcal.synthetic.session_writer import write_field_session

    sf = {"paper": paper_field, "wide": wide_field}[scenario](seed=seed)
    if images:
        sf = scaled_field(sf, scale)
    idx = None if n_images is None or not images else overlapping_images(sf, int(n_images))
    ids = None if not check_points else check_point_ids(sf, int(check_points), idx, seed)
    if images:
        write_field_session(out, sf, images=True, marks_csv=marks, coded=not marks, seed=seed,
                            image_indices=idx, camera_id=camera_id, session_id=session_id, check_points=ids)
    else:
        write_field_session(out, sf, images=False, observations_csv=True, seed=seed,
                            camera_id=camera_id, session_id=session_id, check_points=ids)
    return sf.camera


def _rig(out: Path, scenario: str, seed: int, session_id) -> dict:
    """A rig session (observation-only, CONTRACT section 3 "Rig sessions") and its truth."""
    from fieldcal.model.camera import PARAM_NAMES
    from fieldcal.synthetic.rig import oblique_rig, two_head_rig, write_rig_session

    sr = {"two-head": two_head_rig, "oblique": oblique_rig}[scenario](seed=seed)
    write_rig_session(out, sr, session_id=session_id)
    return {"rig_id": sr.data.rig_id, "reference": sr.data.heads[sr.data.reference].camera_id,
            "heads": [{"camera_id": hd.camera_id, "sensor": cam.sensor.to_dict(),
                       "parameters": {n: float(v) for n, v in zip(PARAM_NAMES, cam.params, strict=True)},
                       "R_camera_to_rig": sr.R_camera_to_rig[h].tolist(),
                       "t_camera_in_rig_m": sr.t_camera_in_rig_m[h].tolist()}
                      for h, (hd, cam) in enumerate(zip(sr.data.heads, sr.cameras, strict=True))]}


def write_synthetic(out, method: str = "goniometer", *, scenario: str | None = None, seed: int = 0,
                    raster_scale: float = 0.25, images: bool = False, scale: float = 0.25,
                    n_images: int | None = None, marks: bool = False, camera_id: str | None = None,
                    session_id: str | None = None, check_points: int | None = None) -> dict:
    """Write a synthetic session into ``out`` and its ``truth.json``; returns the truth.

    Goniometer sessions (``canon5d2`` or ``h3d``) are rendered frames at ``raster_scale``;
    field sessions (``paper`` or ``wide``) are observation-only (``observations.csv``) or,
    with ``images``, rendered images at ``scale`` (``n_images`` of them, at least
    :data:`fieldcal.field.adjustment.MIN_IMAGES`, chosen by
    :func:`fieldcal.synthetic.field.overlapping_images` so that they share targets and spread
    over the stations and rolls: the session calibrates; identified from coded targets, or
    from ``marks.csv`` with ``marks``). ``check_points`` (field) names that many plain targets
    seen in two or more images as independent check points in ``session.json``
    (:func:`fieldcal.synthetic.field.check_point_ids`), so that the calibration and its
    certificate assess them. ``truth.json`` holds the true camera (sensor and
    the 13 parameters) and, for the goniometer, what the method gives on the exact spot
    positions of the same set-up (``noise_free``). Rendering reports its progress through
    :mod:`fieldcal.progress`.
    """
    from fieldcal.model.camera import PARAM_NAMES

    scenario = check_synthetic(method, scenario)
    from fieldcal.field.adjustment import MIN_IMAGES

    if n_images is not None and int(n_images) < MIN_IMAGES:
        raise InputError(f"--n-images must be at least {MIN_IMAGES} (the field method calibrates from "
                         f"{MIN_IMAGES} or more images sharing targets), got {n_images}")
    out = Path(out)
    truth: dict = {"method": method, "seed": int(seed), "scenario": scenario}
    if check_points is not None and method != "field":
        raise InputError("--check-points is for the field method (surveyed targets withheld)")
    if method == "rig":
        truth.update(_rig(out, scenario, seed, session_id))
        (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
        return truth
    if method == "goniometer":
        camera, truth["noise_free"] = _goniometer(out, scenario, seed, raster_scale, camera_id, session_id)
    else:
        camera = _field(out, scenario, seed, images, scale, n_images, marks, camera_id, session_id, check_points)
    truth.update(sensor=camera.sensor.to_dict(),
                 parameters={n: float(v) for n, v in zip(PARAM_NAMES, camera.params, strict=True)})
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return truth
