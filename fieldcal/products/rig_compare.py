r"""Has a rig changed? The change test of its heads' relative orientations between two rig
versions (documents ``fieldcal.rig/1``, CONTRACT section 3 "Rig sessions").

For every head but the reference, two quantities, each tested on its own:

- the **rotation**: ``Delta_rot = log(R_B R_A^T)`` [arcsec], the small rotation about the rig
  frame's axes that takes the head's ``R_camera_to_rig`` of A to that of B (the convention of
  ``sigma_rotation_arcsec``), 3 degrees of freedom;
- the **lever arm**: ``Delta_t = t_B - t_A`` [mm], 3 degrees of freedom.

The two calibrations are independent sessions, so the covariance of a change is
``C = C_A + C_B`` (each document's covariance block of that head's rotation or lever arm),
and ``Delta^T C^-1 Delta`` is chi-square with 3 degrees of freedom when nothing changed. The
p-values of all heads' tests are combined by Holm's step-down procedure
(:mod:`fieldcal.analysis.change`), which keeps the family-wise level ``alpha``. As for a
camera, the rig is ``significant`` when some Holm-adjusted p-value is below ``alpha``,
``exceeds_tolerance`` when some head's rotation change (its angle) exceeds
``tolerance_arcsec`` or its lever-arm change (its length) ``tolerance_mm``, and ``flagged``
when both.
"""

from __future__ import annotations

import numpy as np
from scipy.special import chdtrc

from fieldcal.analysis.change import holm
from fieldcal.errors import InputError
from fieldcal.model.rotations import rotvec_from_R

__all__ = ["compare_rigs", "DEFAULT_TOLERANCE_ARCSEC", "DEFAULT_TOLERANCE_MM", "rig_comparison_text"]

DEFAULT_TOLERANCE_ARCSEC = 10.0
"""A relative rotation change below this [arcsec] is not worth flagging (default)."""
DEFAULT_TOLERANCE_MM = 1.0
"""A lever-arm change below this [mm] is not worth flagging (default)."""
ARCSEC_PER_RAD = 180.0 * 3600.0 / np.pi
_ROT, _T = ("rot_x_arcsec", "rot_y_arcsec", "rot_z_arcsec"), ("t_x_mm", "t_y_mm", "t_z_mm")


def _block(doc: dict, camera_id: str, comps) -> np.ndarray:
    names = doc["covariance"]["names"]
    k = [names.index(f"{camera_id}:{c}") for c in comps]
    return np.asarray(doc["covariance"]["matrix"], float)[np.ix_(k, k)]


def _test(delta, cov) -> tuple[float, float]:
    """``(chi-square, p)`` of a change ``delta`` (3,) with covariance ``cov`` (3, 3)."""
    try:
        chi2 = float(delta @ np.linalg.solve(cov, delta))
    except np.linalg.LinAlgError:
        return float("nan"), float("nan")
    return chi2, float(chdtrc(len(delta), chi2))


def _head_change(a: dict, b: dict, ha: dict, hb: dict) -> dict:
    cid = ha["camera_id"]
    d_rot = rotvec_from_R(np.asarray(hb["R_camera_to_rig"]) @ np.asarray(ha["R_camera_to_rig"]).T) * ARCSEC_PER_RAD
    d_t = (np.asarray(hb["t_camera_in_rig_m"]) - np.asarray(ha["t_camera_in_rig_m"])) * 1000.0
    c_rot = _block(a, cid, _ROT) + _block(b, cid, _ROT)
    c_t = _block(a, cid, _T) + _block(b, cid, _T)
    chi_r, p_r = _test(d_rot, c_rot)
    chi_t, p_t = _test(d_t, c_t)
    return {"camera_id": cid, "rotation_change_arcsec": d_rot.tolist(),
            "rotation_change_angle_arcsec": float(np.linalg.norm(d_rot)),
            "sigma_rotation_change_arcsec": np.sqrt(np.diag(c_rot)).tolist(),
            "lever_arm_change_mm": d_t.tolist(), "lever_arm_change_length_mm": float(np.linalg.norm(d_t)),
            "sigma_lever_arm_change_mm": np.sqrt(np.diag(c_t)).tolist(),
            "chi2_rotation": chi_r, "p_rotation": p_r, "chi2_lever_arm": chi_t, "p_lever_arm": p_t}


def compare_rigs(a: dict, b: dict, *, alpha: float = 0.01, tolerance_arcsec: float = DEFAULT_TOLERANCE_ARCSEC,
                 tolerance_mm: float = DEFAULT_TOLERANCE_MM) -> dict:
    """The change test of two rig documents (module docstring); a JSON-ready dict.

    Raises
    ------
    InputError
        The documents are not of one rig with the same heads and reference, or a bad level.
    """
    if not (0.0 < alpha < 1.0) or not (tolerance_arcsec >= 0 and tolerance_mm >= 0):
        raise InputError(f"alpha must lie in (0, 1) and the tolerances be >= 0, got {alpha}, "
                         f"{tolerance_arcsec}, {tolerance_mm}", "compare")
    if a.get("rig_id") != b.get("rig_id") or a.get("reference") != b.get("reference"):
        raise InputError(f"rig versions of different rigs or references: {a.get('rig_id')}/{a.get('reference')} "
                         f"and {b.get('rig_id')}/{b.get('reference')}", "compare")
    heads_a = {h["camera_id"]: h for h in a["heads"]}
    heads_b = {h["camera_id"]: h for h in b["heads"]}
    if set(heads_a) != set(heads_b):
        raise InputError(f"the rig versions have different heads: {sorted(heads_a)} and {sorted(heads_b)}", "compare")
    heads = [_head_change(a, b, heads_a[c], heads_b[c]) for c in heads_a if c != a["reference"]]
    p = np.array([[h["p_rotation"], h["p_lever_arm"]] for h in heads], float).ravel()
    q = holm(np.where(np.isfinite(p), p, 1.0)).reshape(-1, 2)     # NaN: a singular covariance, untested
    for h, (qr, qt) in zip(heads, q, strict=True):
        h["q_rotation"], h["q_lever_arm"] = float(qr), float(qt)
        h["significant"] = bool(min(qr, qt) < alpha)
        h["exceeds_tolerance"] = bool(h["rotation_change_angle_arcsec"] > tolerance_arcsec
                                      or h["lever_arm_change_length_mm"] > tolerance_mm)
    significant = any(h["significant"] for h in heads)
    exceeds = any(h["exceeds_tolerance"] for h in heads)
    flagged = any(h["significant"] and h["exceeds_tolerance"] for h in heads)
    changed = [h["camera_id"] for h in heads if h["significant"]]
    worst = max(heads, key=lambda h: h["rotation_change_angle_arcsec"])
    verdict = (f"significant change of {', '.join(changed)} (Holm, alpha {alpha:g})" if significant
               else f"no significant change (Holm, alpha {alpha:g})")
    verdict += (f"; largest rotation change {worst['rotation_change_angle_arcsec']:.3g} arcsec ({worst['camera_id']}), "
                f"largest lever-arm change {max(h['lever_arm_change_length_mm'] for h in heads):.3g} mm"
                + ("; FLAGGED" if flagged else ""))
    return {"kind": "rig", "rig_id": a["rig_id"], "version_a": a.get("version"), "version_b": b.get("version"),
            "reference": a["reference"], "alpha": alpha, "tolerance_arcsec": tolerance_arcsec,
            "tolerance_mm": tolerance_mm, "heads": heads, "p_value": float(q.min()) if q.size else 1.0,
            "significant": significant, "exceeds_tolerance": exceeds, "flagged": flagged, "changed": changed,
            "verdict": verdict}


def rig_comparison_text(c: dict) -> str:
    """The comparison as lines for a terminal."""
    lines = [f"rig {c['rig_id']}: A {c['version_a']}, B {c['version_b']} (reference {c['reference']})"]
    for h in c["heads"]:
        def three(key, fmt, h=h):
            return ", ".join(format(v, fmt) for v in h[key])

        lines.append(f"  {h['camera_id']}: rotation change {three('rotation_change_arcsec', '+.3g')} arcsec "
                     f"(sigma {three('sigma_rotation_change_arcsec', '.2g')}; q {h['q_rotation']:.2g}), "
                     f"lever arm {three('lever_arm_change_mm', '+.3g')} mm "
                     f"(sigma {three('sigma_lever_arm_change_mm', '.2g')}; q {h['q_lever_arm']:.2g})")
    lines.append(f"verdict: {c['verdict']}")
    return "\n".join(lines) + "\n"
