"""A goniometer calibration: the result of :func:`fieldcal.goniometer.method.calibrate`.

:class:`GoniometerResult` holds the camera (docs/conventions.md sections 2 and 4), its covariance,
the statistics and the per-angle residuals, and gives the parts the lake stores: the
document's method fields, the named arrays (Zarr) and the residual rows
(``schemas/residuals.arrow.json``), and a human summary.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

from fieldcal.goniometer.frames import AXES
from fieldcal.model import camera as cam
from fieldcal.model.camera import PARAM_NAMES, Sensor

__all__ = ["RESIDUAL_SCHEMA", "GoniometerResult"]

RESIDUAL_SCHEMA = pa.schema([
    ("axis", pa.string()), ("angle_deg", pa.float64()), ("n_frames", pa.int32()),
    ("u_px", pa.float64()), ("v_px", pa.float64()),
    ("se_u_px", pa.float64()), ("se_v_px", pa.float64()),
    ("along_mm", pa.float64()), ("cross_mm", pa.float64()),
    ("distortion_px", pa.float64()), ("fit_px", pa.float64()), ("residual_px", pa.float64()),
])
"""Per angle and axis: the mean spot, its standard error, the coordinates of the fit
(``along_mm, cross_mm``), the distortion before the fit, the fitted model and the residual [px]."""


@dataclass
class GoniometerResult:
    """A goniometer calibration (docs/conventions.md sections 2 and 4).

    Attributes
    ----------
    sensor : Sensor
    parameters : (13,) ndarray
        In :data:`fieldcal.model.camera.PARAM_NAMES` order; ``a1 = a2 = 0``.
    sigma : dict
        Name -> a-posteriori sigma, or None for a parameter not estimated.
    covariance : (13, 13) ndarray
        Of the parameters; NaN rows and columns for those not estimated.
    stats : dict
        The contract's keys (``n_frames, n_angles, fx_mm, fy_mm, px_mm, py_mm,
        sigma_axes, sigma_fit_px``) and more; see :func:`fieldcal.goniometer.method.calibrate`.
    images : list of dict
        The frames used: ``file, axis, angle_deg, u_px, v_px``.
    rejected : list of dict
        Frames left out: ``file, axis, angle_deg, flag, reason``.
    residuals : pyarrow.Table
        Per angle and axis (see :func:`fieldcal.goniometer.method.calibrate`).
    """

    sensor: Sensor
    parameters: np.ndarray
    sigma: dict
    covariance: np.ndarray
    stats: dict
    images: list
    rejected: list
    residuals: pa.Table
    method: str = "goniometer"

    def camera(self) -> cam.Camera:
        return cam.Camera(self.sensor, self.parameters)

    def document_fields(self) -> dict:
        """The method's part of the calibration document (docs/conventions.md section 4): ``method,
        sensor, model, parameters, sigma, stats, images``; the caller adds ``schema,
        camera_id, session_id, version, created, inputs``."""
        return {"method": self.method, "sensor": self.sensor.to_dict(), "model": cam.MODEL,
                "parameters": cam.params_to_dict(self.parameters), "sigma": dict(self.sigma),
                "stats": self.stats, "images": list(self.images)}

    def arrays(self, grid: tuple[int, int] = (41, 31)) -> dict:
        """Named arrays for the lake: ``parameters`` (13,), ``sigma`` (13,) NaN where null,
        ``covariance`` and ``correlation`` (13, 13), ``correction_field`` (ny, nx, 2) [px]
        of the correction on a grid of ``grid = (nx, ny)`` pixel centres with ``grid_u_px``
        (nx,) and ``grid_v_px`` (ny,). Off the two scanned axes the field is the fitted
        model's extrapolation: the goniometer observes only the axes."""
        nx, ny = grid
        uv = self.sensor.grid_px(nx, ny)
        field_px = cam.correction(self.sensor.pixel_to_mm(uv), self.parameters) / self.sensor.pixel_mm
        field_px[:, 1] *= -1.0      # image-plane y up -> pixel v down
        sd = np.sqrt(np.diag(self.covariance))
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = self.covariance / np.outer(sd, sd)
        return {"parameters": self.parameters.copy(),
                "sigma": np.array([np.nan if self.sigma[n] is None else self.sigma[n]
                                   for n in PARAM_NAMES]),
                "covariance": self.covariance.copy(), "correlation": corr,
                "correction_field": field_px.reshape(ny, nx, 2),
                "grid_u_px": uv[:nx, 0].copy(), "grid_v_px": uv[::nx, 1].copy()}

    def lake_residuals(self) -> pa.Table:
        """The residuals as rows of ``schemas/residuals.arrow.json`` (fieldcal.residuals/1).

        One row per angle (``image`` null: the mean of its frames) with the fit residual
        as measured minus model along the swept axis (``du_px`` for the ``x`` sweep,
        ``dv_px`` for the ``y`` sweep; the other component is NaN: the method models only
        the along-axis coordinate), ``sigma_px`` the standard error of the mean along the
        axis; then one row per rejected frame (``used`` false, ``reason`` its flag and
        reason, NaN positions).
        """
        from fieldcal.contract.schemas import arrow_schema

        rows = []
        for r in self.residuals.to_pylist():
            along_px = -r["residual_px"]          # measured minus model, image-plane axis
            x_sweep = r["axis"] == "x"
            se = r["se_u_px"] if x_sweep else r["se_v_px"]
            rows.append({"image": None, "target_id": None, "u_px": r["u_px"], "v_px": r["v_px"],
                         "du_px": along_px if x_sweep else math.nan,
                         "dv_px": math.nan if x_sweep else -along_px,    # y up -> v down
                         "sigma_px": se, "used": True, "reason": None,
                         "normalized_residual": (abs(along_px) / se if se and math.isfinite(se)
                                                 and se > 0 else None),
                         "axis": r["axis"], "angle_deg": r["angle_deg"]})
        for r in self.rejected:
            rows.append({"image": r["file"], "target_id": None, "u_px": math.nan,
                         "v_px": math.nan, "du_px": math.nan, "dv_px": math.nan,
                         "sigma_px": math.nan, "used": False,
                         "reason": f"{r['flag']}: {r['reason']}", "normalized_residual": None,
                         "axis": r["axis"] if r["axis"] in AXES else None,
                         "angle_deg": r["angle_deg"] if math.isfinite(r["angle_deg"]) else None})
        return pa.Table.from_pylist(rows, schema=arrow_schema("residuals"))

    def report_lines(self) -> list[str]:
        """A human summary, one line per item."""
        s, p, sg = self.stats, cam.params_to_dict(self.parameters), self.sigma
        um = 1000.0

        def pm(name):
            return f"{p[name]:.5f} ± {sg[name]:.5f}" if sg.get(name) is not None else f"{p[name]:.5f}"
        lines = [
            f"goniometer calibration ({s['solver']}): {s['n_angles']} angles from {s['n_frames']} "
            f"frames, {s['n_rejected']} frame(s) rejected",
            f"  f  = {pm('f_mm')} mm from the {s['f_axis']} sweep (±{s['half_span_deg'][s['f_axis']]:.1f}°); "
            f"fx = {s['fx_mm']:.5f}, fy = {s['fy_mm']:.5f} mm",
            f"  xp = {pm('xp_mm')} mm, yp = {pm('yp_mm')} mm",
            f"  arm zero landed {s['zero_offset_px']['x']:+.2f} px (x sweep) and "
            f"{s['zero_offset_px']['y']:+.2f} px (y sweep) from the sensor centre",
            f"  distortion before the fit: max {s['max_distortion_px']:.2f} px; after: "
            f"sigma_fit {s['sigma_fit_px']:.3g} px (n = {s['n_angles']}, t = {s['n_fitted']}), "
            f"max {s['max_px']:.3g} px",
        ]
        if s.get("sigma0") is not None:
            lines.append(f"  a-posteriori spot accuracy {s['sigma0_px']:.3g} px = {s['sigma0']:.2f} x "
                         f"the frame-to-frame standard error")
        for name, why in s["fixed_parameters"].items():
            lines.append(f"  held at 0: {name} ({why})")
        lin = s["linearisation"]
        lines.append(f"  rigorous minus linearised: df {lin['df_mm'] * um:+.2f} µm, dxp "
                     f"{lin['dxp_mm'] * um:+.2f} µm, dyp {lin['dyp_mm'] * um:+.2f} µm; along the axes "
                     f"{lin['rms_px']:.3g} px RMS, {lin['max_px']:.3g} px max")
        lines.extend(f"  note: {n}" for n in s["notes"])
        lines.extend(f"  rejected {r['file']}: {r['flag']}: {r['reason']}" for r in self.rejected)
        return lines
