# ruff: noqa: E501 - table rows
"""Cross-check of the rig adjustment's relative orientation against OpenCV 5's
``cv2.calibrateMultiview`` on the same observations (results: bench/README_rig.md).

OpenCV's pattern, per frame (an exposure of the synthetic two-head rig, fieldcal.synthetic.rig),
is 60 of the targets both heads saw, in world coordinates and exact (no survey noise: OpenCV
holds the pattern fixed); its intrinsics start from its own calibration of each head alone (as
its tutorial advises). fieldcal's rig adjustment runs on the same image points with the targets
fixed too (``RigOptions(targets_adjusted=False)``). OpenCV's model is its own (k1, k2, p1, p2, k3),
fieldcal's the project's; the relative orientations are compared with the truth.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_rig_opencv.py [--draws 5]
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

import cv2
import numpy as np

from fieldcal.model.opencv_frames import FLIP_YZ
from fieldcal.model.rotations import rotvec_from_R
from fieldcal.rig import RigOptions, adjust_rig
from fieldcal.rig.adjustment import ARCSEC_PER_RAD
from fieldcal.synthetic.rig import two_head_rig


def common_points(data, n_points=60):
    """Per exposure, ``n_points`` of the targets both heads saw, spread over their list (OpenCV's
    pattern has one number of points in every frame; with its partial views, unobserved points at
    (-1, -1), this OpenCV diverged: RMS 5e28 px); the rig data restricted to those points."""
    keys = []
    for h, hd in enumerate(data.head_data):
        keys.append(data.image_exposure[h][hd.obs.image] * len(data.targets) + hd.obs.target)
    both_all = np.intersect1d(keys[0], keys[1])
    exp, tgt = np.divmod(both_all, len(data.targets))
    chosen = []
    for k in range(len(data.exposures)):
        ts = tgt[exp == k]
        if len(ts) >= n_points:
            chosen += list(k * len(data.targets) + ts[np.linspace(0, len(ts) - 1, n_points).round().astype(int)])
    head_data = [hd.with_obs(hd.obs.take(np.isin(key, chosen))) for hd, key in zip(data.head_data, keys, strict=True)]
    return replace(data, head_data=head_data)


def opencv_inputs(data):
    """Per frame (an exposure both heads saw the same targets in), the pattern in world
    coordinates and each head's image points of it, in one order."""
    obj, img = [], [[] for _ in data.heads]
    for k in range(len(data.exposures)):
        per_head = []
        for h, hd in enumerate(data.head_data):
            sel = data.image_exposure[h][hd.obs.image] == k
            order = np.argsort(hd.obs.target[sel])
            per_head.append((hd.obs.target[sel][order], hd.obs.uv_px[sel][order]))
        if len(per_head[0][0]) == 0:
            continue
        obj.append(data.targets.xyz_m[per_head[0][0]].astype(np.float32))
        for h, (_, uv) in enumerate(per_head):
            img[h].append(uv.astype(np.float32))
    return obj, img, np.ones((data.n_heads, len(obj)), np.uint8)


def initial_intrinsics(data, obj, img, mask):
    """Per head, OpenCV's own calibration of that camera alone (its tutorial's advice: per-camera
    calls, then the multiview with the intrinsic guess), from the nominal focal length."""
    Ks, dists = [], []
    for h, hd in enumerate(data.heads):
        s = hd.sensor
        f_px = hd.nominal_focal_mm / s.pixel_mm
        K = np.array([[f_px, 0, (s.width_px - 1) / 2], [0, f_px, (s.height_px - 1) / 2], [0, 0, 1]])
        _, K, d, _, _ = cv2.calibrateCamera(obj, img[h], (s.width_px, s.height_px), K, np.zeros(5),
                                            flags=cv2.CALIB_USE_INTRINSIC_GUESS)
        Ks.append(K)
        dists.append(d.ravel())
    return Ks, dists


def run_opencv(data):
    """OpenCV's relative orientation of head 1 in fieldcal's frames (R_camera_to_rig, t [m])."""
    t0 = time.perf_counter()
    obj, img, mask = opencv_inputs(data)
    Ks, dists = initial_intrinsics(data, obj, img, mask)
    sizes = [(hd.sensor.width_px, hd.sensor.height_px) for hd in data.heads]
    rms, Ks, dists, Rs, Ts = cv2.calibrateMultiview(
        obj, img, sizes, mask, np.full(data.n_heads, cv2.CALIB_MODEL_PINHOLE, np.uint8), Ks, dists, None, None,
        np.full(data.n_heads, cv2.CALIB_USE_INTRINSIC_GUESS, np.int32), cv2.CALIB_USE_INTRINSIC_GUESS)
    dt = time.perf_counter() - t0
    R_i = np.asarray(Rs[1], float)
    if R_i.shape != (3, 3):
        R_i = cv2.Rodrigues(R_i)[0]
    T_i = np.asarray(Ts[1], float).ravel()             # X_cam1 = R_i X_cam0 + T_i (OpenCV frames)
    return FLIP_YZ @ R_i.T @ FLIP_YZ, -FLIP_YZ @ R_i.T @ T_i, dt, rms


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=5)
    a = ap.parse_args()
    print(f"load: {os.getloadavg()[0]:.1f} (1-min), OpenCV {cv2.__version__}")
    rows = []
    for seed in range(a.draws):
        sr = two_head_rig(seed=seed, survey_noise_mm=0.0)     # targets fixed: exact, as OpenCV assumes
        data = common_points(sr.data)
        t0 = time.perf_counter()
        res = adjust_rig(data, RigOptions(targets_adjusted=False))
        t_fc = time.perf_counter() - t0
        R_cv, t_cv, t_ocv, rms = run_opencv(data)
        truth_R, truth_t = sr.R_camera_to_rig[1], sr.t_camera_in_rig_m[1]
        e_fc = rotvec_from_R(res.state.R_camera_to_rig[1] @ truth_R.T) * ARCSEC_PER_RAD
        e_cv = rotvec_from_R(R_cv @ truth_R.T) * ARCSEC_PER_RAD
        rows.append((e_fc, (res.state.t_camera_in_rig_m[1] - truth_t) * 1000, e_cv, (t_cv - truth_t) * 1000,
                     res.sigma_rotation_arcsec[1], res.sigma_t_mm[1], t_fc, t_ocv, rms,
                     sum(u.sum() for u in res.obs_used),
                     rotvec_from_R(res.state.R_camera_to_rig[1] @ R_cv.T) * ARCSEC_PER_RAD,
                     (res.state.t_camera_in_rig_m[1] - t_cv) * 1000))
    rms_ = lambda k: np.sqrt(np.mean([r[k] ** 2 for r in rows], axis=0))  # noqa: E731
    n_obs = int(np.mean([r[9] for r in rows]))
    print(f"\n### OpenCV calibrateMultiview cross-check: two-head rig, {a.draws} draws, targets fixed, "
          f"{n_obs} image points per draw (60 targets both heads saw per exposure), exact targets\n")
    print("| solver | rotation error RMS x, y, z [arcsec] | lever arm error RMS x, y, z [mm] | time per draw [s] |")
    print("|---|---|---|---|")
    print(f"| fieldcal rig adjustment (heads alone + rig) | {', '.join(f'{v:.2f}' for v in rms_(0))} | "
          f"{', '.join(f'{v:.3f}' for v in rms_(1))} | {np.mean([r[6] for r in rows]):.2f} |")
    print(f"| OpenCV calibrateMultiview (k1 k2 p1 p2 k3) | {', '.join(f'{v:.2f}' for v in rms_(2))} | "
          f"{', '.join(f'{v:.3f}' for v in rms_(3))} | {np.mean([r[7] for r in rows]):.2f} |")
    print(f"| fieldcal minus OpenCV, draw by draw | {', '.join(f'{v:.2f}' for v in rms_(10))} | "
          f"{', '.join(f'{v:.3f}' for v in rms_(11))} | |")
    print(f"\nfieldcal's mean sigmas: rotation {', '.join(f'{v:.2f}' for v in np.mean([r[4] for r in rows], axis=0))} arcsec, "
          f"lever arm {', '.join(f'{v:.3f}' for v in np.mean([r[5] for r in rows], axis=0))} mm; OpenCV's RMS "
          f"reprojection error {np.mean([r[8] for r in rows]):.3f} px.")


if __name__ == "__main__":
    main()
