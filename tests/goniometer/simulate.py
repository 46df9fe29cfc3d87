"""Goniometer sessions without images, for Monte Carlo tests and benchmarks.

The geometry and the random set-up errors are those of
:func:`fieldcal.synthetic.goniometer.write_session` (a new alignment per session: where the
arm's zero lands, the track's tilt, the collimator's cone; an encoder error per angle; a
jitter per frame), the exact spot positions come from
:func:`fieldcal.synthetic.goniometer.spot_positions_px`, and instead of rendering and
measuring the frames each frame's centroid gets a Gaussian error of ``centroid_sigma_px``
(the rendered frames' centroid error against the rendered positions is about 0.02 px:
tests/goniometer/test_goniometer.py). A session of 60 angles x 3 frames takes
milliseconds instead of seconds.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from fieldcal.goniometer.frames import measurements_table
from fieldcal.model.camera import Camera
from fieldcal.synthetic.goniometer import make_scenario, spot_positions_px


def random_misalignment(sc, rng) -> dict:
    """Per axis: ``zero_px`` (2,), ``tilt_mrad``, ``cone_mrad`` drawn from the scenario's sigmas."""
    return {a: {"zero_px": [float(x) for x in rng.normal(0.0, sc.align_sigma_px, 2)],
                "tilt_mrad": float(rng.normal(0.0, sc.tilt_sigma_mrad)),
                "cone_mrad": float(rng.normal(0.0, sc.cone_sigma_mrad))} for a in ("x", "y")}


def simulated_session(scenario: str = "canon5d2", *, seed: int, raster_scale: float = 1.0,
                      frames_per_angle: int = 3, centroid_sigma_px: float = 0.02,
                      camera: Camera | None = None, misalignment: dict | None = None):
    """``(camera, frames, measurements)`` of one session of the scenario's camera.

    Parameters
    ----------
    scenario : str
        A name of :data:`fieldcal.synthetic.goniometer.SCENARIOS`.
    seed : int
        Seeds the alignment, the encoder errors, the jitter and the centroid errors.
    raster_scale : float
        As :func:`fieldcal.synthetic.goniometer.make_scenario`.
    camera : Camera, optional
        Another camera on the same sensor (default the scenario's).
    misalignment : dict, optional
        Fixed set-up errors (as :func:`random_misalignment`) instead of random ones.
    """
    sc = make_scenario(scenario, raster_scale=raster_scale)
    cam = camera or sc.camera()
    rng = np.random.default_rng(seed)
    mis = misalignment or random_misalignment(sc, rng)
    arcsec = np.radians(1.0 / 3600.0)
    rows, meas = [], []
    for axis, angles in (("x", sc.x_angles_deg), ("y", sc.y_angles_deg)):
        angles = np.asarray(angles, float)
        enc_deg = np.degrees(rng.normal(0.0, sc.encoder_sigma_arcsec * arcsec, angles.size))
        pos = spot_positions_px(cam, axis, angles + enc_deg, mis[axis])
        k = frames_per_angle
        uv = (np.repeat(pos, k, axis=0) + rng.normal(0.0, sc.jitter_px, (angles.size * k, 2))
              + rng.normal(0.0, centroid_sigma_px, (angles.size * k, 2)))
        names = [f"images/{axis}_{a:+06.2f}_{j}.tif" for a in angles for j in range(k)]
        rows += [{"file": n, "axis": axis, "angle_deg": float(a)}
                 for n, a in zip(names, np.repeat(angles, k), strict=True)]
        meas += [{"file": n, "u_px": float(u), "v_px": float(v), "flag": "ok"}
                 for n, (u, v) in zip(names, uv, strict=True)]
    return cam, pa.Table.from_pylist(rows), measurements_table(meas)
