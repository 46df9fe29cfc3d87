"""The correction field of a camera: the model's correction sampled on a pixel grid.

A lake version stores the correction of CONTRACT section 2 (docs/conventions.md) at the
pixels of a regular grid from sensor corner to corner, in pixels along ``u`` and ``v``:
``(dx / d, -dy / d)`` with ``d`` the pixel pitch [mm] (``y`` points up, ``v`` down). The
solve step computes it (:func:`correction_arrays`) and hands it to the lake with the document.
"""

from __future__ import annotations

import numpy as np

from fieldcal.model.camera import PARAM_NAMES, Sensor, correction

__all__ = ["CORRECTION_GRID", "correction_grid", "correction_arrays"]

CORRECTION_GRID = (41, 31)
"""(n_u, n_v): the grid of a version's ``correction_field`` (sensor corner to corner)."""


def correction_grid(sensor: Sensor, params, grid: tuple[int, int] = CORRECTION_GRID):
    """The model's correction at the pixels of a regular grid over the sensor.

    Parameters
    ----------
    sensor : fieldcal.model.camera.Sensor
    params : (13,) array_like
        The camera parameters in ``fieldcal.model.camera.PARAM_NAMES`` order.
    grid : (int, int)
        ``(n_u, n_v)`` grid points along a row and down a column.

    Returns
    -------
    field_px : (n_v, n_u, 2) ndarray
        ``(du, dv)`` [px]: the correction ``(dx, dy)`` [mm] in pixels along ``u`` and ``v``.
    grid_u_px : (n_u,) ndarray
        Column coordinates of the grid [px], ``0 .. width_px - 1``.
    grid_v_px : (n_v,) ndarray
        Row coordinates of the grid [px], ``0 .. height_px - 1``.
    """
    grid_u = np.linspace(0.0, sensor.width_px - 1.0, grid[0])
    grid_v = np.linspace(0.0, sensor.height_px - 1.0, grid[1])
    uv = np.stack(np.meshgrid(grid_u, grid_v), axis=-1)
    d_mm = correction(sensor.pixel_to_mm(uv), np.asarray(params, dtype=float))
    field = np.stack([d_mm[..., 0], -d_mm[..., 1]], axis=-1) / sensor.pixel_mm
    return field, grid_u, grid_v


def correction_arrays(document) -> dict:
    """The arrays ``correction_field``, ``grid_u_px`` and ``grid_v_px`` of a calibration document.

    What a field or rig head version hands the lake with its document: the lake stores what
    it is given (docs/architecture.md) and computes nothing.

    Parameters
    ----------
    document : mapping
        A calibration document (docs/conventions.md section 4): its ``sensor`` and its
        ``parameters`` by name.

    Returns
    -------
    dict
        ``{"correction_field": (n_v, n_u, 2) [px], "grid_u_px": (n_u,), "grid_v_px": (n_v,)}``
        of :func:`correction_grid` on :data:`CORRECTION_GRID`.
    """
    s = document["sensor"]
    sensor = Sensor(int(s["width_px"]), int(s["height_px"]), float(s["pixel_size_um"]))
    params = np.array([document["parameters"][n] for n in PARAM_NAMES], dtype=float)
    field, grid_u, grid_v = correction_grid(sensor, params)
    return {"correction_field": field, "grid_u_px": grid_u, "grid_v_px": grid_v}
