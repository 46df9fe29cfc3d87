"""The DBAT calibration sheet from its PHOTOGRAPHS with only its four control points (issue 26, goal 6).

The 21 JPEGs of ``../shared/data/dbat-camcal`` are converted to 8-bit TIFF and written as
sessions; ``marks.csv`` holds only the four control points 1001-1004 in each photograph
(PhotoModeler's marks of them minus 0.5 px, its pixel convention); the other 96 targets are
found and matched by automatic referencing. Everything runs through ``fieldcal run``'s
pipeline (``fieldcal.pipeline.prepare``, ``measure``, ``solve``), whose thin-survey route
(``fieldcal.field.thin_start``) resects every photo from its marks and grows the network.

Runs from the photos: (a) targets.csv with the four control points (0.001 units, as
ctrlpts-weighted.txt) and the 96 others listed without coordinates; (b) the same with only the
four listed; (c) a free network (``field.datum`` "free": the four points' coordinates only start
it) scaled by two sides of the sheet (scale_bars.csv, 1 unit +- 0.0001 each); (d) the same with one
side. For comparison: PhotoModeler's marks of all 100 targets with the four control points
(``bench/dbat_unsurveyed.py``'s case), on all its marks and on the (image, target) pairs the photo
run (a) used. The sheet's units are used as metres.

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/dbat_photos_unsurveyed.py
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from dbat_unsurveyed import four_control  # noqa: E402

from fieldcal.field.adjustment import AdjustmentOptions, adjust_field  # noqa: E402
from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.pipeline import measure, prepare, solve  # noqa: E402
from tests.realdata import DBAT, dbat_field_data, dbat_rows, write_dbat_photo_session  # noqa: E402


def _cells(r, st):
    c = [f"{r.params[INDEX[p]]:.5f} ± {r.sigma[p]:.5f}" for p in ("f_mm", "xp_mm", "yp_mm")]
    c.append(f"{r.params[INDEX['k1']]:.4e} ± {r.sigma['k1']:.1e}")
    c.append(f"{int(np.sum(r.obs_used))} / {st['n_targets']}")
    c.append(f"{st['rmse_px']:.3f}")
    return c


def _pm_pairs(res, pm):
    """(image, PhotoModeler id) of every used observation of a photo run (the PhotoModeler mark
    within 1 px names a referenced disc); the number of tracks holding more than one id."""
    pairs, ids_of = set(), {}
    data = res.data
    for k in np.flatnonzero(res.obs_used):
        name, tid = data.images[data.obs.image[k]].file, str(data.targets.ids[data.obs.target[k]])
        r = pm[pm[:, 0] == int(name[-6:-4]) - 20]
        d = np.linalg.norm(r[:, 2:4] - 0.5 - data.obs.uv_px[k], axis=1)
        if d.min() < 1.0:
            pid = str(int(r[np.argmin(d), 1]))
            pairs.add((name, pid))
            ids_of.setdefault(tid, set()).add(pid)
    mixed = sum(len(v) > 1 for v in ids_of.values())
    distinct = len({next(iter(v)) for v in ids_of.values() if len(v) == 1})
    return pairs, mixed, distinct


def main():
    print("load:", os.getloadavg())
    pm = np.array([[float(v) for v in ln.split(",")] for ln in dbat_rows(DBAT / "markpts.txt")])
    header = "| run | f [mm] | xp [mm] | yp [mm] | k1 [mm^-2] | points used / targets | rmse [px] | CPU s |"
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        imgs = write_dbat_photo_session(tmp / "a", None, list_plain=True)
        write_dbat_photo_session(tmp / "b", imgs, list_plain=False)
        write_dbat_photo_session(tmp / "c", imgs, list_plain=False, bars=2)
        write_dbat_photo_session(tmp / "d", imgs, list_plain=False, bars=1)
        write_dbat_photo_session(tmp / "e", imgs, list_plain=False, pm_survey=True)
        prepared = {k: prepare(tmp / k) for k in "abcde"}
        t0 = time.process_time()
        meas = {n: measure(prepared["a"], n) for n in prepared["a"].to_measure}
        print(f"measured 21 photos: {time.process_time() - t0:.1f} s CPU")
        labels = {"a": "photos: 4 control points, 96 listed unsurveyed",
                  "b": "photos: 4 control points only listed",
                  "c": "photos: free network, 2 sides as scale bars",
                  "d": "photos: free network, 1 side as a scale bar",
                  "e": "photos: PhotoModeler's 100 object points as survey (5 plain marks per photo)"}
        results = {}
        for k, label in labels.items():
            say = []
            t0 = time.process_time()
            out = solve(prepared[k], meas, fingerprint_=k, progress=say.append)
            cpu = time.process_time() - t0
            r = results[k] = out.result
            st = out.document["stats"]
            _, mixed, distinct = _pm_pairs(r, pm)
            print(f"{label}: {st.get('referenced_targets', 0)} referenced targets ({distinct} distinct "
                  "PhotoModeler ids, "
                  f"{mixed} tracks with more than one), images used {st['identification']['used']}, "
                  f"datum {r.datum['type']}, sigma0 {st['sigma0']:.3f}")
            for b in r.datum.get("scale_bars", []):
                print(f"   bar {b['from_id']}-{b['to_id']}: {b['adjusted_mm']:.3f} ± {b['sigma_adjusted_mm']:.3f} mm")
            lines.append(f"| {label} | " + " | ".join(_cells(r, st)) + f" | {cpu:.1f} |")
    pairs, _, _ = _pm_pairs(results["a"], pm)
    ref = four_control(dbat_field_data())
    same = np.array([(ref.images[i].file, str(ref.targets.ids[t])) in pairs
                     for i, t in zip(ref.obs.image, ref.obs.target, strict=True)])
    for label, d in (("PhotoModeler's marks, 4 control points (all 2074 marks)", ref),
                     ("PhotoModeler's marks, 4 control points, the pairs the photos used",
                      replace(ref, obs=ref.obs.take(same)))):
        t0 = time.process_time()
        r = adjust_field(d, AdjustmentOptions())
        lines.append(f"| {label} | " + " | ".join(_cells(r, r.stats())) + f" | {time.process_time() - t0:.1f} |")
    r = adjust_field(dbat_field_data(), AdjustmentOptions())
    lines.append("| PhotoModeler's marks, its 100 object points as survey | " + " | ".join(_cells(r, r.stats()))
                 + " | |")
    a, m = results["a"], adjust_field(ref, AdjustmentOptions())
    print("\n".join(lines))
    print("photos (a) - marks (all): " + ", ".join(
        f"{p} {(a.params[INDEX[p]] - m.params[INDEX[p]]) / np.hypot(a.sigma[p], m.sigma[p]):+.1f} combined sigma"
        for p in ("f_mm", "xp_mm", "yp_mm", "k1")))
    print("load:", os.getloadavg())


if __name__ == "__main__":
    main()
