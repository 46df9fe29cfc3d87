"""The results of a rig calibration as documents (CONTRACT sections 3 "Rig sessions" and 4).

- One ordinary calibration document (``fieldcal.calibration/1``) per head, a version of that
  head's camera: its interior orientation from the rig adjustment, the sigmas, its residual
  statistics and its images (exterior orientations composed from the rig pose and the head's
  relative orientation, :func:`fieldcal.rig.poses.head_pose`, with their sigmas propagated
  from the covariance), so that a head's history, certificate, exports and drift test work
  unchanged. ``rig`` (an extra key) names the rig and the head's role.
- The rig document (``fieldcal.rig/1``): every head (the reference with the identity and
  zero sigmas) with its calibration's version, ``R_camera_to_rig``, ``t_camera_in_rig_m`` and
  their sigmas, the covariance of the relative-orientation parameters (rotations in arc
  seconds about the rig frame's axes, lever arms in mm), and the statistics.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from fieldcal.contract.schemas import validate_json
from fieldcal.model.rotations import skew
from fieldcal.rig.adjustment import ARCSEC_PER_RAD, RigResult
from fieldcal.rig.poses import head_pose
from fieldcal.session.document import calibration_document, utc_now_iso

__all__ = ["RIG_SCHEMA", "head_document", "head_arrays", "head_residual_table", "rig_document",
           "validate_rig_document", "relative_units", "document_names", "DOCUMENT_COMPONENTS"]

RIG_SCHEMA = "fieldcal.rig/1"


def _head_poses(res: RigResult, h: int):
    """Per image of head ``h``: ``R_world_to_camera``, ``C`` and ``sigma_C`` [m] (NaN where its
    exposure was not used)."""
    st, d = res.state, res.data
    e = d.image_exposure[h]
    R, C = head_pose(st.R_world_to_rig[e], st.C_rig_m[e], st.R_camera_to_rig[h], st.t_camera_in_rig_m[h])
    names = {n: i for i, n in enumerate(res.covariance_names)}
    cid = d.heads[h].camera_id
    sig = np.full((len(e), 3), np.nan)
    for i, ei in enumerate(e):
        ex = d.exposures[ei]
        if f"{ex}:X_m" not in names:
            continue
        cols = [names[f"{ex}:{c}"] for c in ("rig_w_x", "rig_w_y", "rig_w_z", "X_m", "Y_m", "Z_m")]
        G = [st.R_world_to_rig[ei].T @ skew(st.t_camera_in_rig_m[h]), np.eye(3)]
        if h != d.reference:
            cols += [names[f"{cid}:{c}"] for c in ("t_x_m", "t_y_m", "t_z_m")]
            G.append(st.R_world_to_rig[ei].T)
        Gm = np.hstack(G)
        sig[i] = np.sqrt(np.diag(Gm @ res.covariance[np.ix_(cols, cols)] @ Gm.T))
    return R, C, sig


def head_document(res: RigResult, h: int, *, session_id: str, fingerprint: str, acquired: str) -> dict:
    """The calibration document (CONTRACT section 4) of head ``h``, without its version."""
    d, st = res.data, res.state
    hd = d.head_data[h]
    R, C, sig = _head_poses(res, h)
    used, resid = res.obs_used[h], res.residual_px[h]
    images = []
    for i, im in enumerate(hd.images):
        k = used & (hd.obs.image == i)
        images.append({"file": im.file, "station": im.station, "exposure": d.exposures[d.image_exposure[h][i]],
                       "center_m": C[i].tolist(), "rotation_world_to_camera": R[i].tolist(),
                       "sigma_center_m": [None if not np.isfinite(v) else float(v) for v in sig[i]],
                       "n_observations": int(k.sum()),
                       "rmse_px": float(np.sqrt(np.mean(np.sum(resid[k] ** 2, axis=1)))) if k.any() else None})
    du = resid[used]
    stats = {**res.head_stats(h), "n_targets": int(len(np.unique(hd.obs.target[used]))),
             "mean_abs_u_px": float(np.mean(np.abs(du[:, 0]))), "mean_abs_v_px": float(np.mean(np.abs(du[:, 1]))),
             "sigma0": float(res.sigma0), "iterations": int(res.lsq.iterations), "solver": res.options.method,
             "targets_adjusted": bool(res.options.targets_adjusted),
             "fixed_parameters": dict(st.fixed_parameters[h]), "initial_values": "the head calibrated alone",
             **res.unsurveyed_stats(h)}
    role = "reference" if h == d.reference else "head"
    return calibration_document(
        camera_id=d.heads[h].camera_id, session_id=session_id, version="", method="field", sensor=hd.sensor,
        parameters=st.params[h], sigma=res.sigma[h], stats=stats, images=images, fingerprint=fingerprint,
        extra={"acquired": acquired, "rig": {"rig_id": d.rig_id, "role": role,
                                             "reference": d.heads[d.reference].camera_id}})


def head_arrays(res: RigResult, h: int) -> tuple[dict, dict]:
    """``(arrays, attrs)`` for the lake's Zarr group of head ``h``: the covariance of its interior
    parameters and their correlation."""
    names = res.covariance_names
    cid = res.data.heads[h].camera_id
    k = [names.index(f"{cid}:{p}") for p in res.state.estimate[h]]
    cov = res.covariance[np.ix_(k, k)]
    s = np.sqrt(np.diag(cov))
    corr = cov / np.outer(s, s)
    est = list(res.state.estimate[h])
    return ({"covariance": cov, "correlation": corr},
            {"covariance": {"names": est, "units": "a-posteriori, parameter units (the rig adjustment)"},
             "correlation": {"names": est}})


def head_residual_table(res: RigResult, h: int) -> pa.Table:
    """One row per image point of head ``h`` (the lake's residual table)."""
    d = res.data.head_data[h]
    reason = np.where(res.obs_reason[h] == "", None, res.obs_reason[h].astype(object))
    files = np.array([im.file for im in d.images], dtype=object)
    r = res.residual_px[h]
    return pa.table({
        "image": pa.array(files[d.obs.image], pa.string()),
        "target_id": pa.array(d.targets.ids[d.obs.target], pa.string()),
        "u_px": d.obs.uv_px[:, 0], "v_px": d.obs.uv_px[:, 1], "du_px": r[:, 0], "dv_px": r[:, 1],
        "sigma_px": d.obs.sigma_px, "used": pa.array(res.obs_used[h], pa.bool_()),
        "reason": pa.array(reason, pa.string()), "normalized_residual": np.full(len(d.obs), np.nan)})


DOCUMENT_COMPONENTS = {"rot_x": "rot_x_arcsec", "rot_y": "rot_y_arcsec", "rot_z": "rot_z_arcsec",
                       "t_x_m": "t_x_mm", "t_y_m": "t_y_mm", "t_z_m": "t_z_mm"}
"""The adjustment's relative-orientation components [rad, m] -> the rig document's names [arcsec, mm]."""


def relative_units(names) -> np.ndarray:
    """Factors from the adjustment's units (rad, m) to the rig document's (arcsec, mm) of the
    relative-orientation parameters ``names``."""
    return np.array([ARCSEC_PER_RAD if n.split(":")[-1].startswith("rot_") else 1000.0 for n in names])


def document_names(names) -> list[str]:
    """``CAMERA:rot_x`` -> ``CAMERA:rot_x_arcsec``, ``CAMERA:t_x_m`` -> ``CAMERA:t_x_mm``."""
    return [n.rsplit(":", 1)[0] + ":" + DOCUMENT_COMPONENTS[n.rsplit(":", 1)[1]] for n in names]


def rig_document(res: RigResult, *, session_id: str, head_versions: list[str], fingerprint: str,
                 acquired: str, version: str = "", created: str | None = None) -> dict:
    """The rig document (``fieldcal.rig/1``, module docstring)."""
    d, st = res.data, res.state
    heads = []
    for h, hd in enumerate(d.heads):
        heads.append({"camera_id": hd.camera_id, "version": head_versions[h],
                      "R_camera_to_rig": st.R_camera_to_rig[h].tolist(),
                      "t_camera_in_rig_m": st.t_camera_in_rig_m[h].tolist(),
                      "sigma_rotation_arcsec": res.sigma_rotation_arcsec[h].tolist(),
                      "sigma_t_mm": res.sigma_t_mm[h].tolist(),
                      "rmse_px": res.head_stats(h)["rmse_px"]})
    names = res.relative_names()
    u = relative_units(names)
    cov = res.relative_covariance() * np.outer(u, u)
    return {"schema": RIG_SCHEMA, "rig_id": d.rig_id, "session_id": session_id, "version": version,
            "created": created or utc_now_iso(), "acquired": acquired,
            "reference": d.heads[d.reference].camera_id, "heads": heads,
            "covariance": {"names": document_names(names), "units": "arcsec (small rotations about the rig "
                           "frame's axes) and mm", "matrix": cov.tolist()},
            "stats": res.stats(), "inputs": {"fingerprint": fingerprint}}


def validate_rig_document(doc: dict, where: str) -> None:
    """Check a rig document against ``schemas/rig.schema.json`` (InputError naming ``where``)."""
    validate_json(doc, "rig", where)
