"""Monte Carlo of the uncertainty from images on 3-D fields, the normals not given (issue 23, goal 4).

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_uncertainty_fields.py \
        --scene faceted --runs 20 --out /tmp/faceted.jsonl
    .venv/bin/python bench/bench_uncertainty_fields.py --table /tmp/faceted.jsonl /tmp/wide.jsonl

Scenes (:mod:`fieldcal.synthetic.field`): ``faceted`` (a folded wall of five panels at five
yaws: mixed normals) and ``wide`` (a facade with pillars and a shelf 0.5 m deep: parallel panels
at different depths). Every run ``k`` draws a new problem and renders it:

- the scene of ``seed=k`` (its camera aims; for ``wide`` also which plain targets are kept),
  every target moved in its own plane by a uniform jitter of +-``--jitter-mm`` along both
  plane axes (a new target placement), scaled to ``--scale`` (12 of the 24 images, 1200 x 800
  px at 0.2) and rendered with a 1.5 px PSF, a 50 % illumination gradient and new shot and
  read noise (``seed=k``);
- a new survey: targets.csv with the true positions plus 5 mm of Gaussian noise per axis and
  ``sigma_mm = 5``, **no normals** (the session a user writes).

It measures every image (:func:`fieldcal.pipeline.measure`) and calibrates as ``fieldcal run``
does (:func:`fieldcal.field.from_images.calibrate_from_measurements`, the normals estimated),
and for contrast with ``estimate_normals=False`` (normals "none": discs uncorrected, the
eccentricity bound in their sigmas) and ``eccentricity=False`` (uncorrected, no bound). Per
calibration it records ``z = (estimate - truth) / sigma`` of f, xp, yp and the coverage of the
2-sigma projection-uncertainty region (:func:`fieldcal.analysis.uncertainty.coverage_fraction`
on a 21 x 15 grid: the fraction of grid points whose true landing error lies in the 95.45 %
ellipse of their landing covariance, and in the circle of two semi-major axes the map draws).
One JSON line per calibration goes to ``--out`` as soon as it is done; ``--table`` prints the
Markdown table of bench/README_uncertainty.md from such files (a later row of the same scene,
run and calibration replaces an earlier one: a rerun).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from fieldcal.analysis.uncertainty import Calibration, coverage_fraction
from fieldcal.errors import FieldcalError
from fieldcal.field.adjustment import AdjustmentOptions
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.model.camera import INDEX
from fieldcal.pipeline import measure, prepare
from fieldcal.session.data import TargetField
from fieldcal.synthetic.field import faceted_field, target_plane_axes, wide_field
from fieldcal.synthetic.render import scaled_field
from fieldcal.synthetic.session_writer import write_field_session

IMAGES = list(range(0, 24, 3)) + [1, 7, 13, 19]
CORE = ("f_mm", "xp_mm", "yp_mm")
SCENES = {"faceted": faceted_field, "wide": wide_field}
HOW = {"estimated": {}, "none": {"estimate_normals": False}, "off": {"eccentricity": False}}
SURVEY_MM = 5.0


def jittered(sf, jitter_m: float, rng):
    """``sf`` with every true target moved in its own plane by U(-jitter, jitter) along both axes."""
    t = sf.targets_true
    _, e1, e2 = target_plane_axes(t.normals)
    a, b = rng.uniform(-jitter_m, jitter_m, (2, len(t), 1))
    moved = TargetField(t.ids, t.xyz_m + a * e1 + b * e2, t.sigma_mm, t.codes, t.normals)
    return replace(sf, targets_true=moved)


def write_survey(folder: Path, sf, rng) -> None:
    """targets.csv: the true positions plus SURVEY_MM of noise, no normals."""
    t = sf.targets_true
    surveyed = t.xyz_m + rng.normal(0.0, SURVEY_MM / 1000.0, t.xyz_m.shape)
    rows = ["id,X,Y,Z,sigma_mm,code"] + [
        f"{i},{x:.6f},{y:.6f},{z:.6f},{SURVEY_MM},{c if c >= 0 else ''}"
        for i, (x, y, z), c in zip(t.ids, surveyed, t.codes, strict=True)]
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")


def measures(sf, res) -> dict:
    n = len(res.estimate)
    cal = Calibration({}, res.camera, tuple(res.estimate), res.covariance[:n, :n])
    z = [(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in CORE]
    return {"z": [float(v) for v in z],
            "error": [float(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) for p in CORE],
            "sigma": [float(res.sigma[p]) for p in CORE],
            "coverage_ellipse": coverage_fraction(cal, sf.camera),
            "coverage_circle": coverage_fraction(cal, sf.camera, what="circle")}


def one_run(scene: str, k: int, args, root: Path):
    rng = np.random.default_rng([k, 23])
    sf = scaled_field(jittered(SCENES[scene](seed=k), args.jitter_mm / 1000.0, rng), args.scale)
    folder = root / f"{scene}-{k:03d}"
    t0 = time.process_time()
    write_field_session(folder, sf, image_indices=IMAGES, coded=True, psf_sigma_px=1.5, seed=1000 + k,
                        illumination_gradient=0.5, compression_mix=False)
    write_survey(folder, sf, rng)
    t_render = time.process_time() - t0
    prepared = prepare(folder)
    meas = {n: measure(prepared, n) for n in prepared.to_measure}
    sess = prepared.session
    options = AdjustmentOptions(targets_adjusted=prepared.settings.targets_adjusted, estimate=sess.estimate,
                                method=prepared.settings.solver, datum=sess.datum)
    t_measure = time.process_time() - t0 - t_render
    for how in args.how:
        t1 = time.process_time()
        try:
            data, res, _ = calibrate_from_measurements(sess, meas, options, **HOW[how])
        except FieldcalError as e:      # counted as a failed run in the table
            yield {"scene": scene, "run": k, "how": how, "failed": str(e).splitlines()[0]}
            continue
        ecc = data.meta.get("eccentricity", {})
        row = {"scene": scene, "run": k, "how": how, **measures(sf, res),
               "normals": ecc.get("normals"), "ecc_max_px": ecc.get("max_px"),
               "ecc_n_targets": ecc.get("n_targets"), "n_obs": int(len(data.obs.image)),
               "cpu_s": {"render": round(t_render, 1), "measure": round(t_measure, 1),
                         "calibrate": round(time.process_time() - t1, 1)}}
        yield row
    for p in folder.rglob("*.tif"):
        p.unlink()


def table(paths) -> None:
    rows = [json.loads(line) for p in paths for line in Path(p).read_text().splitlines() if line.strip()]
    rows = list({(r["scene"], r["run"], r["how"]): r for r in rows}.values())    # a rerun replaces its row
    print("| scene | normals | runs | mean z f, xp, yp | RMS z f, xp, yp | median coverage (ellipse) "
          "| runs covered >= 90 % (ellipse) | runs covered >= 90 % (circle) |")
    print("|---|---|---|---|---|---|---|---|")
    for scene in dict.fromkeys(r["scene"] for r in rows):
        for how in HOW:
            sel = [r for r in rows if r["scene"] == scene and r["how"] == how]
            failed = sum("failed" in r for r in sel)
            sel = [r for r in sel if "failed" not in r]
            if not sel:
                continue
            z = np.array([r["z"] for r in sel])
            ce = np.array([r["coverage_ellipse"] for r in sel])
            cc = np.array([r["coverage_circle"] for r in sel])
            mean = ", ".join(f"{v:+.2f}" for v in z.mean(axis=0))
            rms = ", ".join(f"{v:.2f}" for v in np.sqrt(np.mean(z ** 2, axis=0)))
            runs = f"{len(sel)}" + (f" (+{failed} failed)" if failed else "")
            print(f"| {scene} | {how} | {runs} | {mean} | {rms} | {np.median(ce):.2f} "
                  f"| {np.mean(ce >= 0.9):.2f} | {np.mean(cc >= 0.9):.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scene", choices=tuple(SCENES), default="faceted")
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--first", type=int, default=0, help="seed of the first run")
    ap.add_argument("--scale", type=float, default=0.2)
    ap.add_argument("--jitter-mm", type=float, default=30.0)
    ap.add_argument("--how", nargs="+", choices=tuple(HOW), default=list(HOW))
    ap.add_argument("--out", type=Path)
    ap.add_argument("--table", nargs="+", type=Path, help="print the table of these result files")
    args = ap.parse_args()
    if args.table:
        table(args.table)
        return
    root = Path(tempfile.mkdtemp(prefix=f"mc-{args.scene}-"))
    for k in range(args.first, args.first + args.runs):
        for row in one_run(args.scene, k, args, root):
            if "failed" in row:
                print(f"{row['scene']} run {k} {row['how']:9s} failed: {row['failed']}", flush=True)
            else:
                print(f"{row['scene']} run {k} {row['how']:9s} z {np.round(row['z'], 2)} coverage "
                      f"{row['coverage_ellipse']:.2f}/{row['coverage_circle']:.2f} {row['normals']} "
                      f"max {row['ecc_max_px']} cpu {row['cpu_s']}", flush=True)
            if args.out:
                with args.out.open("a") as fh:
                    fh.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
