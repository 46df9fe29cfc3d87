"""Photographs of coded targets that no survey places (issue 26 goals 3 and 5): Monte Carlo.

Each draw: ``wide_field(seed=k)`` (326 targets, 28 coded, 24 images, 0.1 px), the detector's
output per image from ``measurements_of`` (projected centres plus noise: no eccentricity, so
the sessions carry no target diameter); targets.csv lists the coded targets only, none surveyed,
two scale bars of 0.05 mm between the coded targets seen from the most stations
(``tests/field/test_coded_cloud.py``'s session). The same draw with every target surveyed (5 mm)
is the reference. Printed: error/sigma of f, xp, yp, k1 against truth, RMS over the draws, the
sigma ratio coded-only / surveyed, CPU per solve. ``--render`` adds one run through the pipeline
(``prepare``, ``measure``, ``solve``) on rendered images at scale 0.3 with the target diameter
(perspective eccentricity with normals estimated from the adjusted targets' local planes).

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/bench_coded_cloud.py --draws 20 [--render]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np

CORE = ("f_mm", "xp_mm", "yp_mm", "k1")


def _draw(seed: int, tmp: Path):
    from fieldcal.field.adjustment import AdjustmentOptions
    from fieldcal.field.from_images import calibrate_from_measurements
    from fieldcal.field.referencing import ReferencingOptions
    from fieldcal.model.camera import INDEX
    from fieldcal.session.loader import load_session
    from fieldcal.synthetic.field import wide_field
    from fieldcal.synthetic.session_writer import write_field_session
    from tests.field.test_coded_cloud import _coded_only, _measurements, _no_diameter

    sf = wide_field(seed=seed)
    a, b = tmp / f"coded{seed}", tmp / f"surveyed{seed}"
    _coded_only(a, sf)
    write_field_session(b, sf, images=False, coded=True)
    _no_diameter(b)
    out = {}
    for key, folder, ref in (("coded", a, ReferencingOptions()), ("surveyed", b, None)):
        session = load_session(folder)
        meas, _ = _measurements(sf, session)
        t0 = time.process_time()
        _, res, report = calibrate_from_measurements(session, meas, AdjustmentOptions(), referencing=ref)
        cpu = time.process_time() - t0
        z = [(res.params[INDEX[n]] - sf.camera.params[INDEX[n]]) / res.sigma[n] for n in CORE]
        used = sum(r["status"] == "ok" for r in report)
        out[key] = (np.array(z), np.array([res.sigma[n] for n in CORE]), cpu, used,
                    res.stats().get("n_unsurveyed_targets", 0))
    return out


def _render(tmp: Path, scale: float = 0.3):
    import fieldcal.synthetic.session_writer as writer
    import tests.field.test_coded_cloud as cc
    from fieldcal.model.camera import INDEX
    from fieldcal.pipeline import measure, prepare, solve
    from fieldcal.synthetic.field import wide_field
    from fieldcal.synthetic.render import scaled_field

    sf = scaled_field(wide_field(seed=3), scale)
    folder = tmp / "rendered"
    plain = writer.write_field_session
    cc.write_field_session = lambda f, s, images=False, **kw: plain(f, s, images=True, **kw)
    cc._no_diameter = lambda f: None                     # rendered discs: eccentricity is real
    try:
        cc._coded_only(folder, sf)
    finally:
        cc.write_field_session = plain
    p = prepare(folder)
    meas = {n: measure(p, n) for n in p.to_measure}
    t0 = time.process_time()
    said: list[str] = []
    out = solve(p, meas, fingerprint_="bench", progress=said.append)
    cpu = time.process_time() - t0
    r, st = out.result, out.document["stats"]
    z = [(r.params[INDEX[n]] - sf.camera.params[INDEX[n]]) / r.sigma[n] for n in CORE]
    ecc = next((s for s in said if s.startswith("perspective eccentricity")), "no eccentricity line")
    print(f"rendered (scale {scale}, 1800 x 1200 px): images used {st['identification']['used']} of "
          f"{st['identification']['images']}, {st['n_unsurveyed_targets']} targets ({st.get('referenced_targets')} "
          f"referenced), rmse {st['rmse_px']:.4f} px, datum {st['datum']['type']}, scale {st['datum']['scale']}")
    print("  " + ecc)
    print("  error/sigma " + ", ".join(f"{n} {v:+.2f}" for n, v in zip(CORE, z, strict=True)) +
          f"; sigma f {1000 * r.sigma['f_mm']:.3f} um; solve CPU {cpu:.1f} s")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--render", action="store_true")
    args = ap.parse_args()
    print("load:", os.getloadavg())
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        rows = {"coded": [], "surveyed": []}
        print("| seed | coded only: f | xp | yp | k1 | surveyed: f | xp | yp | k1 | sigma ratio f | targets | CPU s |")
        print("|---|---|---|---|---|---|---|---|---|---|---|---|")
        for k in range(args.draws):
            d = _draw(k, tmp)
            for key in rows:
                rows[key].append(d[key])
            zc, sc, cpu, used, n_t = d["coded"]
            zs, ss, _, _, _ = d["surveyed"]
            print(f"| {k} | " + " | ".join(f"{v:+.2f}" for v in zc) + " | " + " | ".join(f"{v:+.2f}" for v in zs) +
                  f" | {sc[0] / ss[0]:.3f} | {n_t} | {cpu:.1f} |", flush=True)
        for key in rows:
            z = np.array([r[0] for r in rows[key]])
            rms = np.sqrt(np.mean(z**2, axis=0))
            print(f"| RMS {key} | " + " | ".join(f"{v:.2f}" for v in rms) + " |")
        ratio = np.array([c[1] / s[1] for c, s in zip(rows["coded"], rows["surveyed"], strict=True)])
        print("median sigma ratio coded / surveyed (f, xp, yp, k1): " +
              ", ".join(f"{v:.3f}" for v in np.median(ratio, axis=0)))
        if args.render:
            _render(tmp)


if __name__ == "__main__":
    main()
