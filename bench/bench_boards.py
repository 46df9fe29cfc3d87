"""Honest sigmas on planar boards (issue 23, goals 3-4): Monte Carlo of the three board models.

For each board (flat; a dome and a fold of 80 um and of 300 um; a flat board whose corners are
made 30 um worse than their stated 0.01 mm) and each seed, one synthetic session of
:func:`fieldcal.synthetic.field.board_field` (Bouguet's 13 x 12 corner chessboard, a 640 x 480
camera with ~35 px of distortion, 20 poses drawn anew per run, 0.1 px image noise drawn anew),
adjusted with each board model (:mod:`fieldcal.field.board`): ``points`` (every corner adjusted,
weighted by its 0.01 mm, with variance components), ``rigid`` (corners held fixed, their 0.01 mm
propagated) and ``warp`` (held fixed up to the 3-term warp; the default). Reported per board and
model: RMS over the runs of ``|error| / sigma`` of f, xp, yp (goal 0.7-1.3), the mean signed
``error / sigma`` of f (a bias), the median sigma of f [px], the fraction of runs whose 2-sigma
projection-uncertainty region (95.45 % ellipse, :func:`fieldcal.analysis.uncertainty.coverage_fraction`)
holds the true landing error on >= 90 % of a 21 x 15 grid (goal >= 0.9), and for the warp its
fitted bows (mean over the runs, RMS of ``(fit - truth) / sigma``).

Then ``--rendered N`` runs: the same boards (flat, dome and fold of 80 um) as disc boards
(12 mm discs) rendered by :mod:`fieldcal.synthetic.render` (PSF, noise), written as sessions
with ``marks.csv``, measured and identified from the images by the pipeline (eccentricity
corrected with the planar-fit normal), and solved with each board model (``field.board_model``).

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_boards.py [--runs 20] [--rendered 5]

Results: bench/README_uncertainty.md, "Planar boards".
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fieldcal.analysis.uncertainty import Calibration, coverage_fraction  # noqa: E402
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field  # noqa: E402
from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.synthetic.field import board_field  # noqa: E402

CORE = ("f_mm", "xp_mm", "yp_mm")
MODELS = ("points", "rigid", "warp")
BOARDS = [("flat", 0.0, 0.0), ("dome", 0.08, 0.0), ("fold", 0.08, 0.0), ("dome", 0.3, 0.0), ("fold", 0.3, 0.0),
          ("flat", 0.0, 0.03)]
"""(shape, amplitude [mm], corner errors beyond the stated sigma [mm])."""


def _truth_warp(shape, amp):
    """The warp model's coefficients of a rendered dome (``a/2, a/2, 0``); None for a fold (outside the model)."""
    return {"flat": (0.0, 0.0, 0.0), "dome": (amp / 2, amp / 2, 0.0)}.get(shape)


def _one(sf, model):
    res = adjust_field(sf.data, AdjustmentOptions(board_model=model))
    n = len(res.estimate)
    cal = Calibration({}, res.camera, tuple(res.estimate), res.covariance[:n, :n])
    z = np.array([(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in CORE])
    b = res.board
    warp = (np.array(list(b["coefficients_mm"].values())), np.array(list(b["sigma_mm"].values()))) \
        if "coefficients_mm" in b else None
    return z, coverage_fraction(cal, sf.camera), res.sigma["f_mm"] / sf.camera.sensor.pixel_mm, warp


def monte_carlo(runs: int) -> None:
    print("| board | corner errors | model | RMS z f | RMS z xp | RMS z yp | mean z f | median sigma f [px] "
          "| runs covered | fitted bows c_uu, c_vv [um] (truth) | RMS (fit - truth)/sigma |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for shape, amp, extra in BOARDS:
        rows = {m: [] for m in MODELS}
        for seed in range(700, 700 + runs):
            sf = board_field(seed=seed, shape=shape, amplitude_mm=amp, print_noise_mm=extra)
            for m in MODELS:
                rows[m].append(_one(sf, m))
        truth = _truth_warp(shape, amp)
        for m, r in rows.items():
            z = np.array([x[0] for x in r])
            rms = np.sqrt(np.mean(z**2, axis=0))
            covered = np.mean([x[1] >= 0.9 for x in r])
            fit, zfit = "", ""
            if r[0][3] is not None:
                c = np.array([x[3][0] for x in r])
                s = np.array([x[3][1] for x in r])
                fit = f"{1000 * c[:, 0].mean():.0f}, {1000 * c[:, 1].mean():.0f}"
                if truth is not None:
                    fit += f" ({1000 * truth[0]:.0f}, {1000 * truth[1]:.0f})"
                    zfit = ", ".join(f"{v:.2f}" for v in np.sqrt(np.mean(((c - truth) / s) ** 2, axis=0)))
                else:
                    fit += " (a crease: outside the model)"
            name = f"{shape} {1000 * amp:.0f} um" if amp else shape
            print(f"| {name} | {'+' + format(1000 * extra, '.0f') + ' um' if extra else 'as stated'} | {m} | "
                  f"{rms[0]:.2f} | {rms[1]:.2f} | {rms[2]:.2f} | {z[:, 0].mean():+.2f} | "
                  f"{np.median([x[2] for x in r]):.3f} | {covered:.2f} | {fit} | {zfit} |", flush=True)


def _rendered_one(sf, folder, models):
    import json

    from fieldcal import pipeline
    from fieldcal.synthetic.session_writer import write_field_session

    write_field_session(folder, sf, images=True, marks_csv=True, coded=False, compression_mix=False,
                        marks_error_px=0.3, seed=int(sf.settings["seed"]))
    prepared = pipeline.prepare(folder)
    meas = {n: pipeline.measure(prepared, n) for n in prepared.to_measure}
    manifest = json.loads((folder / "session.json").read_text())
    out = {}
    for m in models:
        manifest["field"]["board_model"] = m
        (folder / "session.json").write_text(json.dumps(manifest))
        prepared = pipeline.prepare(folder)
        doc = pipeline.solve(prepared, meas, fingerprint_=pipeline.input_fingerprint(prepared, {})).document
        truth = sf.camera.to_dict()
        z = np.array([(doc["parameters"][p] - truth[p]) / doc["sigma"][p] for p in CORE])
        b = doc["stats"].get("board", {})
        out[m] = (z, b.get("coefficients_mm"), b.get("sigma_mm"), doc["stats"]["eccentricity"].get("max_px"))
    return out


def rendered(runs: int) -> None:
    import tempfile
    from pathlib import Path

    print("\n| rendered board | model | RMS z f | RMS z xp | RMS z yp | mean z f | fitted bows c_uu, c_vv [um] "
          "(truth) | largest eccentricity correction [px] |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for shape, amp in (("flat", 0.0), ("dome", 0.08), ("fold", 0.08)):
            rows = {m: [] for m in MODELS}
            for k, seed in enumerate(range(900, 900 + runs)):
                sf = board_field(seed=seed, shape=shape, amplitude_mm=amp)
                for m, r in _rendered_one(sf, Path(tmp) / f"{shape}{k}", MODELS).items():
                    rows[m].append(r)
            truth = _truth_warp(shape, amp)
            for m, r in rows.items():
                z = np.array([x[0] for x in r])
                rms = np.sqrt(np.mean(z**2, axis=0))
                fit = ""
                if r[0][1]:
                    c = np.array([list(x[1].values()) for x in r])
                    fit = f"{1000 * c[:, 0].mean():.0f}, {1000 * c[:, 1].mean():.0f}"
                    fit += f" ({1000 * truth[0]:.0f}, {1000 * truth[1]:.0f})" if truth else " (a crease)"
                name = f"{shape} {1000 * amp:.0f} um" if amp else shape
                print(f"| {name} | {m} | {rms[0]:.2f} | {rms[1]:.2f} | {rms[2]:.2f} | {z[:, 0].mean():+.2f} | {fit} | "
                      f"{max(x[3] for x in r):.3f} |", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--rendered", type=int, default=0, help="runs per board from rendered images (default 0)")
    args = ap.parse_args()
    t0 = time.perf_counter()
    print(f"load before: {os.getloadavg()[0]:.1f}")
    if args.runs:
        monte_carlo(args.runs)
    if args.rendered:
        rendered(args.rendered)
    print(f"\n{time.perf_counter() - t0:.0f} s; load after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
