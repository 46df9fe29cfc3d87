"""Perspective eccentricity on rendered 3-D fields: z of f without the correction, with the
target normals given, and with them estimated (issue 23; ``tests/field/test_normals_images.py``
is one draw of this).

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_normals.py [--scene faceted|wide] [--runs 5]

The scene (``faceted_field``: a folded wall of five panels at five yaws; ``wide_field``: a wall
with pillars and a shelf, every target facing -Y) is rendered once at scale 0.2 (12 of 24 images,
1200 x 800 px) without noise, with a defocused PSF (1.5 px) and a 50 % illumination gradient.
Each run draws new shot and read noise for every frame and a new 5 mm survey of the targets
(targets.csv with the true normals as ``nx,ny,nz``), measures, and calibrates three ways:
``eccentricity=False``; the session's normals; the normals unknown (estimated). It prints
``(error) / sigma`` of f, xp, yp per run and their mean and RMS over the runs.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import tifffile

from fieldcal.field.adjustment import AdjustmentOptions
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.model.camera import INDEX
from fieldcal.pipeline import measure, prepare
from fieldcal.synthetic.field import faceted_field, wide_field
from fieldcal.synthetic.render import FULL_WELL_E, READ_NOISE_E, scaled_field
from fieldcal.synthetic.session_writer import write_field_session

IMAGES = list(range(0, 24, 3)) + [1, 7, 13, 19]
CORE = ("f_mm", "xp_mm", "yp_mm")


def _noisy(dn, rng):
    gain = 65535.0 / FULL_WELL_E
    e = rng.poisson(dn / gain).astype(float) + rng.normal(0.0, READ_NOISE_E, dn.shape)
    return np.clip(np.rint(gain * e), 0, 65535).astype(np.uint16)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", choices=("faceted", "wide"), default="faceted")
    ap.add_argument("--runs", type=int, default=5)
    args = ap.parse_args()
    sf = scaled_field((faceted_field if args.scene == "faceted" else wide_field)(seed=0), 0.2)
    X, N = sf.targets_true.xyz_m, sf.targets_true.normals
    folder = Path(tempfile.mkdtemp(prefix=f"normals-{args.scene}-"))
    info = write_field_session(folder, sf, image_indices=IMAGES, coded=True, psf_sigma_px=1.5,
                               illumination_gradient=0.5, compression_mix=False, noise=False)
    expected = {n: tifffile.imread(folder / n).astype(float) for n in info["images"]}
    z: dict[str, list] = {"off": [], "given": [], "estimated": []}
    for k in range(args.runs):
        rng = np.random.default_rng(1000 + k)
        for n, dn in expected.items():
            tifffile.imwrite(folder / n, _noisy(dn, rng))
        surveyed = X + rng.normal(0.0, 5e-3, X.shape)
        rows = ["id,X,Y,Z,sigma_mm,code,nx,ny,nz"] + [
            f"{t},{x:.6f},{y:.6f},{zz:.6f},5.0,{c if c >= 0 else ''},{n[0]:.6f},{n[1]:.6f},{n[2]:.6f}"
            for t, (x, y, zz), c, n in zip(sf.targets_true.ids, surveyed, sf.targets_true.codes, N, strict=True)]
        (folder / "targets.csv").write_text("\n".join(rows) + "\n")
        prepared = prepare(folder)
        meas = {n: measure(prepared, n) for n in prepared.to_measure}
        for how, kw in (("off", {"eccentricity": False}), ("given", {}),
                        ("estimated", {"target_normals": np.full(X.shape, np.nan)})):
            data, res, _ = calibrate_from_measurements(prepared.session, meas, AdjustmentOptions(), **kw)
            zz = [(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in CORE]
            z[how].append(zz)
            print(f"run {k} {how:9s} z(f, xp, yp) {np.round(zz, 2)}  {data.meta['eccentricity'].get('n_targets')}",
                  flush=True)
    print(f"\n{args.scene}, {args.runs} runs | mean z f, xp, yp | RMS z f, xp, yp")
    for how, v in z.items():
        v = np.asarray(v)
        print(f"{how:9s} | {np.round(v.mean(axis=0), 2)} | {np.round(np.sqrt(np.mean(v ** 2, axis=0)), 2)}")


if __name__ == "__main__":
    main()
