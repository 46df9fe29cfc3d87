"""Unsurveyed targets and free networks (issue 26): honesty by Monte Carlo, and cost.

1. Monte Carlo on the wide-angle synthetic field (``wide_field``, 326 targets, 24 images,
   0.1 px noise, 5 mm surveys), ``--draws`` seeds: every target surveyed (today's case),
   4 control points with the other targets unsurveyed, and the free network with one scale
   bar between two of those points. Per parameter: the RMS of ``error / sigma`` over the
   draws (1 is honest) and the median sigma.
2. Cost: the paper field (``paper_field``, ~2000 targets, 72 images) all surveyed against the
   same field with 1000 of its targets unsurveyed; time and peak memory of ``adjust_field``,
   each in a fresh process: the second call's time (the first loads kernels), the peak of
   ``tracemalloc`` over a third (NumPy's arrays included) and the process's max RSS.

Usage::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_unsurveyed.py [--draws 20]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np

PARAMS = ("f_mm", "xp_mm", "yp_mm", "k1", "k2", "p1", "p2", "a1", "a2")


def four_control(sf):
    X = sf.data.targets.xyz_m
    spots = [(-1.5, 1.0), (1.5, 1.0), (-1.5, 3.0), (1.5, 3.0)]
    control = [int(np.argmin(np.hypot(X[:, 0] - a, X[:, 2] - b))) for a, b in spots]
    xyz = np.full_like(X, np.nan)
    xyz[control] = X[control]
    return replace(sf.data, targets=replace(sf.data.targets, xyz_m=xyz)), control


def monte_carlo(draws: int) -> dict:
    from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
    from fieldcal.model.camera import INDEX
    from fieldcal.session.data import ScaleBars
    from fieldcal.synthetic.field import wide_field

    cases = ("surveyed", "4 control", "free + 1 bar")
    z = {c: {p: [] for p in PARAMS} for c in cases}
    sig = {c: {p: [] for p in PARAMS} for c in cases}
    seconds = {c: 0.0 for c in cases}
    for seed in range(draws):
        sf = wide_field(seed=100 + seed)
        data, control = four_control(sf)
        Xt = sf.targets_true.xyz_m
        a, b = control[0], control[1]
        bar = ScaleBars([a], [b], [np.linalg.norm(Xt[b] - Xt[a]) * 1e3], [0.02])
        runs = {"surveyed": (sf.data, AdjustmentOptions()), "4 control": (data, AdjustmentOptions()),
                "free + 1 bar": (replace(data, scale_bars=bar), AdjustmentOptions(datum="free"))}
        for c, (d, o) in runs.items():
            t0 = time.process_time()
            res = adjust_field(d, o)
            seconds[c] += time.process_time() - t0
            for p in PARAMS:
                if p in res.sigma:
                    z[c][p].append((res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p])
                    sig[c][p].append(res.sigma[p])
    return {c: {"rms_z": {p: float(np.sqrt(np.mean(np.square(z[c][p])))) for p in PARAMS if z[c][p]},
                "median_sigma": {p: float(np.median(sig[c][p])) for p in PARAMS if sig[c][p]},
                "cpu_s_per_run": seconds[c] / draws} for c in cases}


def cost_child(kind: str) -> None:
    import resource
    import tracemalloc

    from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
    from fieldcal.session.data import ScaleBars
    from fieldcal.synthetic.field import paper_field

    sf = paper_field(seed=1)
    data = sf.data
    options = AdjustmentOptions()
    if kind in ("unsurveyed", "bars"):
        rng = np.random.default_rng(0)
        pick = rng.choice(len(data.targets), 1000, replace=False)
        xyz = data.targets.xyz_m.copy()
        xyz[pick] = np.nan
        data = replace(data, targets=replace(data.targets, xyz_m=xyz))
    if kind == "bars":            # a free network, 4 bars (0.02 mm) between the busiest targets
        busy = np.argsort(-np.bincount(data.obs.target, minlength=len(data.targets)), kind="stable")[:8]
        a, b = busy[0::2], busy[1::2]
        Xt = sf.targets_true.xyz_m
        data = replace(data, scale_bars=ScaleBars(a, b, np.linalg.norm(Xt[b] - Xt[a], axis=1) * 1e3,
                                                  np.full(4, 0.02)))
        options = AdjustmentOptions(datum="free")
    adjust_field(data, options)                       # warm: the kernels loaded, the first call's imports done
    t0, c0 = time.perf_counter(), time.process_time()
    res = adjust_field(data, options)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    tracemalloc.start()
    adjust_field(data, options)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    out = {"wall_s": wall, "cpu_s": cpu, "peak_traced_mib": peak / 2**20,
           "max_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
           "n_targets": res.stats()["n_targets"], "n_unsurveyed": res.stats().get("n_unsurveyed_targets", 0),
           "f_mm": float(res.params[0]), "sigma_f_mm": res.sigma["f_mm"]}
    print(json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--child", choices=("surveyed", "unsurveyed", "bars"))
    args = ap.parse_args()
    if args.child:
        cost_child(args.child)
        return
    print("load:", os.getloadavg())
    mc = monte_carlo(args.draws)
    print(f"Monte Carlo, {args.draws} draws of the wide field")
    print("| case | " + " | ".join(PARAMS) + " | CPU s/run |")
    print("|---|" + "---|" * (len(PARAMS) + 1))
    for c, r in mc.items():
        print(f"| {c} rms(err/sigma) | " + " | ".join(f"{r['rms_z'].get(p, float('nan')):.2f}" for p in PARAMS)
              + f" | {r['cpu_s_per_run']:.2f} |")
        print(f"| {c} median sigma | " + " | ".join(f"{r['median_sigma'].get(p, float('nan')):.3g}" for p in PARAMS)
              + " | |")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    for kind in ("surveyed", "unsurveyed", "bars", "surveyed", "unsurveyed", "bars"):
        out = subprocess.run([sys.executable, __file__, "--child", kind], capture_output=True, text=True,
                             env=env, check=True).stdout.strip().splitlines()[-1]
        print(kind, out)
    print("load:", os.getloadavg())


if __name__ == "__main__":
    main()
