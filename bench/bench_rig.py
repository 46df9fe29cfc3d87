# ruff: noqa: E501 - table rows
"""Monte Carlo of the rig adjustment on the synthetic rigs (fieldcal.synthetic.rig): relative
orientation errors against truth in units of their sigmas, and each head's accuracy in the rig
against its calibration alone. Results: bench/README_rig.md.

    .venv/bin/python bench/bench_rig.py [--draws 20] [--scenario two|oblique|both|misstated]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import numpy as np

from fieldcal.model.rotations import rotvec_from_R
from fieldcal.rig import adjust_rig
from fieldcal.rig.adjustment import ARCSEC_PER_RAD, RigOptions
from fieldcal.synthetic.rig import oblique_rig, two_head_rig

CORE = ("f_mm", "xp_mm", "yp_mm")


def misstated_two_head_rig(*, seed):
    """The two-head rig with sigmas stated wrong: the right head's points 0.3 px (stated 0.1 px),
    the survey 6 mm (stated 2 mm); what the variance components are for."""
    sr = two_head_rig(seed=seed, survey_noise_mm=6.0)
    rng = np.random.default_rng(1000 + seed)
    t = replace(sr.data.targets, sigma_mm=np.full(len(sr.data.targets), 2.0))
    heads = []
    for h, d in enumerate(sr.data.head_data):
        if h == 1:
            d = d.with_obs(replace(d.obs, uv_px=d.obs.uv_px + rng.normal(0.0, np.sqrt(8.0) * 0.1, d.obs.uv_px.shape)))
        heads.append(replace(d, targets=t))
    return replace(sr, data=replace(sr.data, head_data=heads))


def draw(make, seed, options=None):
    sr = make(seed=seed)
    t0 = time.perf_counter()
    res = adjust_rig(sr.data, options)
    dt = time.perf_counter() - t0
    st, ref = res.state, sr.data.reference
    z_rot, z_t, e_rot, e_t = [], [], [], []
    for h in range(sr.data.n_heads):
        if h == ref:
            continue
        dR = rotvec_from_R(st.R_camera_to_rig[h] @ sr.R_camera_to_rig[h].T) * ARCSEC_PER_RAD
        dt_mm = (st.t_camera_in_rig_m[h] - sr.t_camera_in_rig_m[h]) * 1000.0
        z_rot.append(dR / res.sigma_rotation_arcsec[h])
        z_t.append(dt_mm / res.sigma_t_mm[h])
        e_rot.append(dR)
        e_t.append(dt_mm)
    heads = []
    for h, cam in enumerate(sr.cameras):
        solo = st.solo[h]
        row = {}
        for p, i in zip(CORE, range(3), strict=True):
            row[p] = (st.params[h][i] - cam.params[i], res.sigma[h][p], solo.params[i] - cam.params[i], solo.sigma[p])
        heads.append(row)
    return (np.array(z_rot), np.array(z_t), np.array(e_rot), np.array(e_t), heads, dt, res.sigma_rotation_arcsec,
            res.sigma_t_mm, res.variance_components)


def _print_components(vc, draws):
    image_f = np.array([[h["image_factor"] for h in v["heads"].values()] for v in vc])
    floors = np.array([[h["image_floor_px"] for h in v["heads"].values()] for v in vc])
    survey_f = np.array([v.get("survey_factor_estimate", np.nan) for v in vc])
    print(f"\nVariance components: re-weighted in {sum(v['rounds'] > 0 for v in vc)} of {draws} draws "
          f"({sum(v['rounds'] for v in vc)} rounds in all); image factor per head {image_f.mean():.3f} mean "
          f"({image_f.min():.3f}-{image_f.max():.3f}), image floors up to {floors.max():.3f} px; survey factor "
          f"{np.nanmean(survey_f):.3f} mean ({np.nanmin(survey_f):.3f}-{np.nanmax(survey_f):.3f}; estimated at the "
          "last solve)")


def run(name, make, draws, options=None):
    out = [draw(make, seed, options) for seed in range(draws)]
    z_rot = np.stack([o[0] for o in out])       # (draws, heads-1, 3)
    z_t = np.stack([o[1] for o in out])
    e_rot, e_t = np.stack([o[2] for o in out]), np.stack([o[3] for o in out])
    ids = [hd.camera_id for hd in make(seed=0).data.heads]
    rel = [i for i in range(len(ids)) if i != 0]
    print(f"\n### {name}: {draws} draws, rig solve {np.mean([o[5] for o in out]):.2f} s per draw (incl. heads alone)")
    print("\n| head | rotation error RMS x, y, z [arcsec] | mean sigma [arcsec] | |err|/sigma RMS rot | lever arm error RMS [mm] | mean sigma [mm] | |err|/sigma RMS t |")
    print("|---|---|---|---|---|---|---|")
    for j, h in enumerate(rel):
        s_rot = np.mean([o[6][h] for o in out], axis=0)
        s_t = np.mean([o[7][h] for o in out], axis=0)
        rms = lambda a: np.sqrt(np.mean(a**2, axis=0))  # noqa: E731
        print(f"| {ids[h]} | {', '.join(f'{v:.2f}' for v in rms(e_rot[:, j]))} | {', '.join(f'{v:.2f}' for v in s_rot)} "
              f"| {np.sqrt(np.mean(z_rot[:, j]**2)):.2f} | {', '.join(f'{v:.3f}' for v in rms(e_t[:, j]))} "
              f"| {', '.join(f'{v:.3f}' for v in s_t)} | {np.sqrt(np.mean(z_t[:, j]**2)):.2f} |")
    vc = [o[8] for o in out]
    if all("heads" in v for v in vc):
        _print_components(vc, draws)
    print(f"\nAll relative-orientation components: |error|/sigma RMS {np.sqrt(np.mean(np.concatenate([z_rot.ravel(), z_t.ravel()])**2)):.2f} "
          f"(rotation {np.sqrt(np.mean(z_rot**2)):.2f}, lever arm {np.sqrt(np.mean(z_t**2)):.2f}; "
          f"{z_rot.size + z_t.size} values)")
    print("\n| head | parameter | RMS error in rig | mean sigma in rig | RMS error alone | mean sigma alone | |err|/sigma RMS rig | alone |")
    print("|---|---|---|---|---|---|---|---|")
    for h, cid in enumerate(ids):
        for p in CORE:
            a = np.array([o[4][h][p] for o in out])
            print(f"| {cid} | {p} | {np.sqrt(np.mean(a[:, 0]**2)) * 1000:.2f} µm | {np.mean(a[:, 1]) * 1000:.2f} µm "
                  f"| {np.sqrt(np.mean(a[:, 2]**2)) * 1000:.2f} µm | {np.mean(a[:, 3]) * 1000:.2f} µm "
                  f"| {np.sqrt(np.mean((a[:, 0] / a[:, 1])**2)):.2f} | {np.sqrt(np.mean((a[:, 2] / a[:, 3])**2)):.2f} |")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--scenario", default="both", choices=("two", "oblique", "both", "misstated"))
    a = ap.parse_args()
    print(f"load: {os.getloadavg()[0]:.1f} (1-min), OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}")
    if a.scenario in ("two", "both"):
        run("two-head convergent rig (different sensors and lenses)", two_head_rig, a.draws)
    if a.scenario in ("oblique", "both"):
        run("five-head oblique rig (nadir + 4 at 45 degrees)", oblique_rig, a.draws)
    if a.scenario == "misstated":
        name = "two-head rig, right head's points 3x and survey 3x noisier than stated"
        run(f"{name}, variance components", misstated_two_head_rig, a.draws)
        run(f"{name}, without variance components", misstated_two_head_rig, a.draws,
            RigOptions(variance_components=False))


if __name__ == "__main__":
    main()
