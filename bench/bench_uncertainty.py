"""Honest uncertainty of the field adjustment (issue 16, goal 0): Monte Carlo, before and after.

For each synthetic configuration (scenario, attitudes per station, targets adjusted or
fixed) and each seed, one observation session (new image noise, new survey), adjusted
twice, interleaved: "before" is the adjustment as it was (parameters held when not
significant, ``min_t = 1``; one ``sigma0``, ``variance_components=False``), "after" the
default. Reported per configuration: the RMS of ``|error| / sigma`` of f, xp, yp; the
fraction of runs whose true landing error lies in the 2-sigma region on >= 90 % of a
21 x 15 grid (the ellipse of 95.45 %, and the circle of two semi-major axes); how many
runs held a parameter. Then the cost: the whole ``adjust_field`` with and without the
variance components (a session whose sigmas are right, and one whose sigmas leave out a
0.3 px floor), the check points' evaluation and the cross-validation by station.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_uncertainty.py [--runs 20] [--repeat 5]

Results: bench/README_uncertainty.md.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from fieldcal.analysis.uncertainty import Calibration, coverage_fraction  # noqa: E402
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field  # noqa: E402
from fieldcal.field.cross_validation import cross_validate_by_station  # noqa: E402
from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.synthetic.field import paper_field, wide_field  # noqa: E402

CORE = ("f_mm", "xp_mm", "yp_mm")
CONFIGS = [("paper", 12), ("paper", 4), ("paper", 2), ("wide", None)]
BEFORE = {"min_t": 1.0, "variance_components": False}


def scene(name, attitudes, seed):
    return paper_field(seed=seed, n_attitudes=attitudes) if name == "paper" else wide_field(seed=seed)


def measures(sf, res):
    n = len(res.estimate)
    cal = Calibration({}, res.camera, tuple(res.estimate), res.covariance[:n, :n])
    z = [(res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in CORE]
    return (np.array(z), coverage_fraction(cal, sf.camera), coverage_fraction(cal, sf.camera, what="circle"),
            bool(res.fixed_parameters))


def monte_carlo(runs: int):
    print("| scenario | images | targets | version | RMS z f | RMS z xp | RMS z yp | runs covered (ellipse) "
          "| runs covered (circle) | runs holding a parameter |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, att in CONFIGS:
        for adjusted in (True, False):
            rows = {"before": [], "after": []}
            for seed in range(500, 500 + runs):
                sf = scene(name, att, seed)
                for version, kw in (("before", BEFORE), ("after", {})):
                    res = adjust_field(sf.data, AdjustmentOptions(targets_adjusted=adjusted, **kw))
                    rows[version].append(measures(sf, res))
            for version, r in rows.items():
                z = np.array([x[0] for x in r])
                rms = np.sqrt(np.mean(z**2, axis=0))
                print(f"| {name} | {len(sf.data.images)} | {'adjusted' if adjusted else 'fixed'} | {version} | "
                      f"{rms[0]:.2f} | {rms[1]:.2f} | {rms[2]:.2f} | {np.mean([x[1] >= 0.9 for x in r]):.2f} | "
                      f"{np.mean([x[2] >= 0.9 for x in r]):.2f} | {np.mean([x[3] for x in r]):.2f} |", flush=True)


def floored(sf, floor_px, seed):
    rng = np.random.default_rng(seed)
    obs = sf.data.obs
    sigma = rng.uniform(0.03, 0.15, len(obs))
    err = rng.normal(size=(len(obs), 2)) * np.sqrt(sigma**2 + floor_px**2)[:, None]
    return replace(sf.data, obs=replace(obs, uv_px=sf.uv_true_px + err, sigma_px=sigma))


def _time(fn, repeat):
    out = []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        out.append((time.perf_counter() - t0, time.process_time() - c0))
    return np.array(out)


def cost(repeat: int):
    paper = paper_field(seed=1)
    wide = wide_field(seed=1)
    cases = [("paper, 72 images, right sigmas", paper.data), ("wide, 24 images, right sigmas", wide.data),
             ("wide, sigmas without a 0.3 px floor", floored(wide, 0.3, 1))]
    print("\n| data | without variance components [s] | with [s] | ratio (CPU) | re-weightings |")
    print("|---|---|---|---|---|")
    for label, data in cases:
        adjust_field(data)                                   # compile and warm
        off, on = [], []
        for _ in range(repeat):                              # interleaved
            off.append(_time(lambda d=data: adjust_field(d, AdjustmentOptions(variance_components=False)), 1)[0])
            on.append(_time(lambda d=data: adjust_field(d), 1)[0])
        off, on = np.median(off, axis=0), np.median(on, axis=0)
        rounds = adjust_field(data).variance_components.rounds
        print(f"| {label} | {off[0]:.2f} | {on[0]:.2f} | {on[1] / off[1]:.2f} | {rounds} |", flush=True)
    print("\n| step | wide [s] | paper [s] |")
    print("|---|---|---|")
    t_plain = [np.median(_time(lambda d=d: adjust_field(d), repeat)[:, 0]) for d in (wide.data, paper.data)]
    t_check = [np.median(_time(lambda d=d: adjust_field(d, AdjustmentOptions(check_fraction=0.1)), repeat)[:, 0])
               for d in (wide.data, paper.data)]
    res = [adjust_field(d) for d in (wide.data, paper.data)]
    t_cv = [np.median(_time(lambda r=r: cross_validate_by_station(r), max(1, repeat // 2))[:, 0]) for r in res]
    print(f"| adjust_field | {t_plain[0]:.2f} | {t_plain[1]:.2f} |")
    print(f"| adjust_field with 10 % check points | {t_check[0]:.2f} | {t_check[1]:.2f} |")
    print(f"| cross_validate_by_station (8 / 6 stations) | {t_cv[0]:.2f} | {t_cv[1]:.2f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--skip-monte-carlo", action="store_true")
    a = ap.parse_args()
    if not a.skip_monte_carlo:
        monte_carlo(a.runs)
    cost(a.repeat)


if __name__ == "__main__":
    main()
