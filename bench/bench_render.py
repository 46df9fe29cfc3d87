"""Benchmark of the renderer (``fieldcal.synthetic.render``) at full and test sizes, and the size of the
perspective eccentricity in the two synthetic scenarios.

Usage::

    OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 .venv/bin/python bench/bench_render.py [--quick]

Each timing runs in a fresh subprocess, so its peak resident memory (``ru_maxrss``) is that
of the one render (Python + numpy + the libraries included, about 150 MB before any work).
Default settings: PSF sigma 0.8 px, 8 x 8 samples, shot + read noise, markers drawn.

Results on the 2-core shared development machine, under load from other jobs (wall time,
one run each)::

    case                  size          targets (coded)  adaptive  time [s]  peak RSS [MB]
    paper, full size      8208 x 6280   146 (6)          yes       6.9-9.8   287-292
    wide, full size       6000 x 4000   186 (19)         yes       9.8       219
    paper @ 0.25          2052 x 1570   148 (8)          yes       1.5       150
    wide @ 0.25           1500 x 1000   193 (22)         yes       2.9       151
    paper @ 0.25          2052 x 1570   148 (8)          no        4.0       151

At full size the noise (one Poisson and one Gaussian draw per pixel, 51 Mpx) is about two
thirds of the time (4.4 s of 6.9 s in a profile); the output array alone is 103 MB.

Eccentricity (centre of the imaged outline minus the image of the disc's centre, over the
observed targets of every image)::

    scenario         median   RMS     p95     max   [px]
    paper (full)     0.0019   0.0021  0.0030  0.0041
    wide (full)      0.0039   0.0059  0.0120  0.0163
    paper @ 0.25     0.0077   0.0082  0.0120  0.0163   (targets 4x larger in mm)
    wide @ 0.25      0.0157   0.0233  0.0476  0.0653
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")


def _field(scenario: str, scale: float):
    from fieldcal.synthetic import field as syn
    from fieldcal.synthetic import render

    sf = syn.paper_field(seed=0) if scenario == "paper" else syn.wide_field(seed=0)
    return sf if scale == 1.0 else render.scaled_field(sf, scale)


def _child(scenario: str, scale: float, image: int, adaptive: bool) -> dict:
    import resource

    from fieldcal.synthetic import render

    sf = _field(scenario, scale)
    t0 = time.perf_counter()
    r = render.render_image(sf, image, adaptive=adaptive)
    dt = time.perf_counter() - t0
    return {"scenario": scenario, "scale": scale, "image": image, "adaptive": adaptive,
            "size": f"{r.pixels.shape[1]} x {r.pixels.shape[0]}", "targets": r.truth.num_rows,
            "coded": int(sum(r.truth["coded"].to_pylist())), "time_s": dt,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def _run(*args) -> dict:
    cmd = [sys.executable, __file__, "--child", *map(str, args)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def eccentricity(scenario: str, scale: float, step: int = 1) -> dict:
    """Statistics of |ellipse centre - projected centre| [px] over the observed targets."""
    import numpy as np

    from fieldcal.synthetic import render

    sf = _field(scenario, scale)
    e = []
    for i in range(0, len(sf.R_world_to_camera), step):
        tg = render._select_targets(sf, i, None, False, sf.marker_size_mm, 1.0)
        geo = render._geometry(sf.camera, tg, 3)
        seen = sf.data.obs.target[sf.data.obs.image == i]
        k = np.flatnonzero(geo["draw"] & np.isin(tg.index, seen))
        e.append(np.linalg.norm(geo["ellipse"][k] - geo["center"][k], axis=1))
    e = np.concatenate(e)
    return {"n": int(e.size), "median": float(np.median(e)), "rms": float(np.sqrt(np.mean(e ** 2))),
            "p95": float(np.percentile(e, 95)), "max": float(e.max())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--child", nargs=4, metavar=("SCENARIO", "SCALE", "IMAGE", "ADAPTIVE"))
    ap.add_argument("--quick", action="store_true", help="skip the full-size renders")
    args = ap.parse_args()
    if args.child:
        s, scale, image, adaptive = args.child
        print(json.dumps(_child(s, float(scale), int(image), adaptive == "True")))
        return
    cases = [("paper", 0.25, 0, True), ("wide", 0.25, 0, True), ("paper", 0.25, 0, False)]
    if not args.quick:
        cases = [("paper", 1.0, 0, True), ("wide", 1.0, 0, True)] + cases
    print("| case | size | targets (coded) | adaptive | time [s] | peak RSS [MB] |")
    print("|---|---|---|---|---|---|")
    for c in cases:
        r = _run(*c)
        print(f"| {r['scenario']} @ {r['scale']:g}, image {r['image'] + 1} | {r['size']} | "
              f"{r['targets']} ({r['coded']}) | {r['adaptive']} | {r['time_s']:.1f} | "
              f"{r['peak_rss_mb']:.0f} |", flush=True)
    print()
    print("| eccentricity | n | median | RMS | p95 | max [px] |")
    print("|---|---|---|---|---|---|")
    for scenario in ("paper", "wide"):
        for scale in (1.0, 0.25):
            e = eccentricity(scenario, scale)
            print(f"| {scenario} @ {scale:g} | {e['n']} | {e['median']:.4f} | {e['rms']:.4f} | "
                  f"{e['p95']:.4f} | {e['max']:.4f} |", flush=True)


if __name__ == "__main__":
    main()
