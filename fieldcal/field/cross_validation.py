r"""Cross-validation by station: recalibrate without each station, see how far the field moves.

mrcal's "projection diff" compares two calibrations by where they land the same rays; here
the two are the calibration from all images and the one without the images of one
station (docs/uncertainty.md). If the covariance is honest, the move is as large as the
covariance of the *difference* says. For nested least squares with the same weights,
the full estimate is the efficient one and the difference ``theta_s - theta`` has the
covariance ``D = Sigma_s - Sigma`` (the Hausman test's identity: the difference is
uncorrelated with the efficient estimate). Over a grid of the sensor, with the landing
Jacobian ``J`` of :func:`fieldcal.analysis.uncertainty.landing_jacobian` at the full
calibration:

* the move ``d(uv) = uv_s(ray(uv)) - uv`` [px] (:func:`fieldcal.analysis.compare.ray_difference_px`),
  summarised as ``rms_px`` and ``max_px``;
* its prediction ``sigma_rms_px = sqrt(mean tr(J D J^T))`` [px] (the RMS of the 1-sigma
  size over the grid);
* the map test ``chi2 = |S_r^-1 U_r^T d|^2`` with ``J L = U S V^T`` (``L L^T = D``, the
  negative eigenvalues round-off leaves clipped), over the ``r`` directions that move the
  grid by more than ``min_sigma_px`` RMS, and its p-value (chi-square with ``r`` degrees of
  freedom), as the change test does (:mod:`fieldcal.analysis.compare`).

A station whose images are all of one place carries its own lever arm: without it the
others may no longer hold the camera (a :class:`~fieldcal.errors.GeometryError`), which is
reported for that station instead of numbers. Images without a station are their own
group. Each recalibration starts from the full one (warm), estimates the same parameters
(no selection) and withholds the same check points: it costs a few iterations, but
one per station, so it is an explicit option (``Settings.cross_validate``), not part of
every run.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import chdtrc  # chi2.sf(x, k) = chdtrc(k, x), without scipy.stats' import

from fieldcal.analysis.compare import ray_difference_px
from fieldcal.analysis.uncertainty import landing_jacobian, remove_rotation_part
from fieldcal.errors import GeometryError
from fieldcal.field.adjustment import FieldResult, InitialValues, adjust_field
from fieldcal.session.data import FieldData

__all__ = ["StationMove", "CrossValidation", "cross_validate_by_station", "station_groups"]


@dataclass
class StationMove:
    """How far the correction field moves without one station (module docstring)."""

    station: str
    n_images: int
    rms_px: float | None = None
    max_px: float | None = None
    sigma_rms_px: float | None = None
    chi2: float | None = None
    dof: int | None = None
    p_value: float | None = None
    params: np.ndarray | None = field(default=None, repr=False)
    error: str = ""

    def to_dict(self) -> dict:
        return {"station": self.station, "n_images": int(self.n_images), "rms_px": self.rms_px,
                "max_px": self.max_px, "sigma_rms_px": self.sigma_rms_px, "chi2": self.chi2, "dof": self.dof,
                "p_value": self.p_value, "error": self.error}


@dataclass
class CrossValidation:
    """:func:`cross_validate_by_station` for every station."""

    stations: list[StationMove]
    grid: tuple[int, int]
    remove_rotation: bool

    def to_dict(self) -> dict:
        """The document's ``stats.cross_validation``."""
        return {"grid": list(self.grid), "remove_rotation": self.remove_rotation,
                "stations": [s.to_dict() for s in self.stations]}


def station_groups(data: FieldData) -> dict[str, np.ndarray]:
    """``{station: image indices}``; an image without a station is a group of its own (its file)."""
    labels = [im.station or im.file for im in data.images]
    return {s: np.array([i for i, x in enumerate(labels) if x == s]) for s in dict.fromkeys(labels)}


def _without(data: FieldData, images: np.ndarray):
    keep_img = np.setdiff1d(np.arange(len(data.images)), images)
    new_index = np.full(len(data.images), -1)
    new_index[keep_img] = np.arange(len(keep_img))
    k = np.flatnonzero(new_index[data.obs.image] >= 0)
    obs = data.obs.take(k)
    obs = replace(obs, image=new_index[obs.image])
    return replace(data, images=[data.images[i] for i in keep_img], obs=obs), keep_img, k


def _sqrt_psd(D):
    w, V = np.linalg.eigh(0.5 * (D + D.T))
    return V * np.sqrt(np.clip(w, 0.0, None))


def _move(full: FieldResult, sub: FieldResult, J, uv, remove_rotation, min_sigma_px):
    """The move of the field, its predicted size and the map test (module docstring)."""
    n = len(full.estimate)
    D = sub.covariance[:n, :n] - full.covariance[:n, :n]
    _, d = ray_difference_px(sub.camera, full.camera, uv, remove_rotation=remove_rotation)
    M = J.reshape(-1, n) @ _sqrt_psd(D)
    if remove_rotation:
        M = remove_rotation_part(full.camera, uv, M)
    norm = np.hypot(d[:, 0], d[:, 1])
    sig = float(np.sqrt(np.sum(M**2) / len(uv)))
    U, S, _ = np.linalg.svd(M, full_matrices=False)
    keep = S / np.sqrt(M.shape[0]) > min_sigma_px
    z = (U[:, keep].T @ d.ravel()) / S[keep]
    c, r = float(z @ z), int(keep.sum())
    return (float(np.sqrt(np.mean(norm**2))), float(norm.max()), sig, c, r,
            float(chdtrc(r, c)) if r else None)


def cross_validate_by_station(result: FieldResult, *, grid: tuple[int, int] = (21, 15),
                              remove_rotation: bool = False, min_sigma_px: float = 1e-4,
                              progress: Callable[[str], None] | None = None) -> CrossValidation:
    """Recalibrate without each station and compare with the full calibration (module docstring).

    Parameters
    ----------
    result : FieldResult
        The calibration from all images (:func:`fieldcal.field.adjustment.adjust_field`).
    grid : (nx, ny)
        Grid over the sensor the fields are compared on.
    remove_rotation : bool
        Compare the fields without their best common rotation (the shape only).
    min_sigma_px : float
        Directions of the map test that move the grid by less (RMS) are left out [px].
    progress : callable, optional

    Returns
    -------
    CrossValidation
    """
    data = result.data
    names = tuple(result.estimate)
    uv = data.sensor.grid_px(*grid)
    J = landing_jacobian(result.camera, uv, names)
    options = replace(result.options, estimate=names)
    blunder = ~result.obs_used & (result.obs_reason == "blunder")
    moves = []
    for station, images in station_groups(data).items():
        sub_data, keep_img, k = _without(data, images)
        init = InitialValues(result.params.copy(), result.R_world_to_camera[keep_img], result.center_m[keep_img],
                             blunder[k], np.full(len(keep_img), np.nan), "the calibration from all images")
        move = StationMove(str(station), int(len(images)))
        try:
            sub = adjust_field(sub_data, options, initial=init, initial_targets_m=result.targets_m)
        except GeometryError as err:
            move.error = str(err)
        else:
            (move.rms_px, move.max_px, move.sigma_rms_px, move.chi2, move.dof,
             move.p_value) = _move(result, sub, J, uv, remove_rotation, min_sigma_px)
            move.params = sub.params
        if progress:
            progress(f"without {station} ({len(images)} images): " + (move.error or (
                f"field moves {move.rms_px:.3g} px RMS (max {move.max_px:.3g}), predicted "
                f"{move.sigma_rms_px:.3g} px; chi2 {move.chi2:.3g} on {move.dof}")))
        moves.append(move)
    return CrossValidation(moves, tuple(grid), bool(remove_rotation))
