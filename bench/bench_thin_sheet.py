"""Monte Carlo of the thin-survey route on the rendered sheet (issue 26 goal 6, the truth analogue).

Each draw: ``fieldcal.synthetic.field.sheet_field(seed=s)`` (new poses' jitter, new image and
clicking noise), rendered, measured and calibrated through the pipeline (``prepare``,
``measure``, ``solve``) with the four control points marked (tests/field/test_thin_survey.py's
session), and again as a free network scaled by two sides. Prints error/sigma of f, xp, yp, k1
per draw, their RMS, and the largest difference free - control in sigmas.

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_thin_sheet.py --draws 6
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.pipeline import measure, prepare, solve  # noqa: E402
from fieldcal.synthetic.field import sheet_field  # noqa: E402
from fieldcal.synthetic.session_writer import write_field_session  # noqa: E402
from tests.field.test_thin_survey import write_sheet_tables  # noqa: E402

PARAMS = ("f_mm", "xp_mm", "yp_mm", "k1")


def draw(seed: int, tmp: Path):
    sf = sheet_field(seed=seed)
    a, b = tmp / f"a{seed}", tmp / f"b{seed}"
    write_field_session(a, sf, coded=False, seed=seed, compression_mix=False)
    write_sheet_tables(a, sf, free=False)
    write_field_session(b, sf, images=False, coded=False, seed=seed)
    (b / "images").mkdir(exist_ok=True)
    for f in (a / "images").iterdir():
        os.link(f, b / "images" / f.name)
    write_sheet_tables(b, sf, free=True)
    pa_, pb = prepare(a), prepare(b)
    meas = {n: measure(pa_, n) for n in pa_.to_measure}
    ra = solve(pa_, meas, fingerprint_="a").result
    rb = solve(pb, meas, fingerprint_="b").result
    truth = sf.camera.params
    z = [(ra.params[INDEX[p]] - truth[INDEX[p]]) / ra.sigma[p] for p in PARAMS]
    d = [(rb.params[INDEX[p]] - ra.params[INDEX[p]]) / ra.sigma[p] for p in PARAMS]
    n_ar = int(sum(t.startswith("AR") for t in ra.data.targets.ids))
    return z, d, n_ar, len(ra.data.images)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--draws", type=int, default=6)
    args = ap.parse_args()
    print("load:", os.getloadavg())
    zs, ds = [], []
    print("| seed | images | referenced | f | xp | yp | k1 | max abs(free - control) [sigma] | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for s in range(args.draws):
            t0 = time.process_time()
            z, d, n_ar, n_img = draw(s, Path(tmp))
            zs.append(z)
            ds.append(d)
            print(f"| {s} | {n_img} | {n_ar} | " + " | ".join(f"{v:+.2f}" for v in z)
                  + f" | {np.max(np.abs(d)):.3f} | {time.process_time() - t0:.1f} |", flush=True)
    zs = np.array(zs)
    print("| RMS | | | " + " | ".join(f"{v:.2f}" for v in np.sqrt(np.mean(zs**2, axis=0))) + " | | |")
    print("load:", os.getloadavg())


if __name__ == "__main__":
    main()
