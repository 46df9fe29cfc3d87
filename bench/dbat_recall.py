"""Image recall on the DBAT calibration-sheet photographs (issue 23, goal 6).

The 21 JPEGs of ``../shared/data/dbat-camcal`` are converted to 8-bit TIFF and run through
fieldcal as ``tests/field/test_dbat_photos.py`` does (PhotoModeler's object points as the
survey, 5 of PhotoModeler's marks per image as marks.csv). Every one of PhotoModeler's 2074
marks (``markpts.txt``, minus 0.5 px: its pixel convention) is then classified by what
became of it:

- ``used``: a point of the final adjustment (a row of the residual table, used);
- ``blunder``: in the residual table, rejected by data snooping (or another reason);
- ``identified, not in the adjustment``: a blob identified as the target whose point did
  not reach the adjustment (e.g. a single-image point);
- ``measured, not identified``: an accepted detection within 1 px of the mark, no identity;
- ``rejected by the detector (<filter>)``: a candidate within 1.5 px of the mark that the
  detector's filters refused (the first one that failed);
- ``no candidate``: the candidate search found nothing there; a local look says why
  (diameter, contrast, the mark's distance to the frame's edge).

Usage::

    OPENBLAS_NUM_THREADS=1 nice -n 10 .venv/bin/python bench/dbat_recall.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fieldcal.field.adjustment import AdjustmentOptions, adjust_field  # noqa: E402
from fieldcal.field.from_images import calibrate_from_measurements  # noqa: E402
from fieldcal.measure.discs import detect_targets  # noqa: E402
from fieldcal.measure.imageio import read_image  # noqa: E402
from fieldcal.model.camera import INDEX  # noqa: E402
from fieldcal.pipeline import measure, prepare  # noqa: E402
from tests.realdata import DBAT, dbat_field_data, dbat_image_names, dbat_marks, dbat_rows, write_dbat_photo_session  # noqa: E402


def write_session(folder: Path) -> tuple[dict, np.ndarray]:
    """The session of tests/field/test_dbat_photos.py in ``folder``; (image id -> name, marks)."""
    write_dbat_photo_session(folder, None, list_plain=False, pm_survey=True)
    return {i: name for i, (_, name) in dbat_image_names().items()}, dbat_marks()


def _local_look(img, u, v, r=14):
    """Diameter (px, from the dark area below half contrast) and contrast [DN] around (u, v)."""
    H, W = img.shape
    y0, y1, x0, x1 = max(0, int(v) - r), min(H, int(v) + r + 1), max(0, int(u) - r), min(W, int(u) + r + 1)
    w = img[y0:y1, x0:x1].astype(float)
    bg = np.median(np.concatenate([w[0], w[-1], w[:, 0], w[:, -1]]))
    yy, xx = np.mgrid[y0:y1, x0:x1]
    near = np.hypot(xx - u, yy - v) < 3
    lo = w[near].min()
    c = bg - lo
    dark = (w < bg - 0.5 * c) & (np.hypot(xx - u, yy - v) < r - 2)
    return 2 * np.sqrt(dark.sum() / np.pi), c


def classify(folder: Path, names: dict, pm: np.ndarray, measurements, data, result):
    """One class per PhotoModeler mark (module docstring); returns (rows, counts)."""
    res_tab = result.residual_table().to_pydict()
    in_adj = {(im, t): (u, r) for im, t, u, r in zip(res_tab["image"], res_tab["target_id"],
                                                      res_tab["used"], res_tab["reason"], strict=True)}
    idents = data.meta["identifications"]
    out = []
    for i, name in names.items():
        table = measurements[name]
        uv = np.stack([table["u_px"].to_numpy(), table["v_px"].to_numpy()], axis=1)
        ident = idents.get(name)
        img = read_image(folder / name)
        rej = detect_targets(img, polarity="dark", return_rejected=True)
        ruv = np.stack([rej["u_px"].to_numpy(), rej["v_px"].to_numpy()], axis=1)
        rreason = np.asarray(rej["reject"].to_pylist())
        for _, tid, x, y, _s in pm[pm[:, 0] == i]:
            tid = str(int(tid))
            p = np.array([x - 0.5, y - 0.5])
            key = (name, tid)
            if key in in_adj:
                used, reason = in_adj[key]
                cls = "used" if used else f"in adjustment, rejected ({reason})"
            else:
                d = np.linalg.norm(uv - p, axis=1) if len(uv) else np.array([np.inf])
                j = int(np.argmin(d))
                if d[j] < 1.0:
                    if ident is not None and ident.target[j] >= 0:
                        got = str(data.targets.ids[ident.target[j]])
                        cls = "identified, not in the adjustment" if got == tid else f"identified as {got}"
                    else:
                        cls = "measured, not identified"
                else:
                    dr = np.linalg.norm(ruv - p, axis=1) if len(ruv) else np.array([np.inf])
                    k = int(np.argmin(dr))
                    if dr[k] < 1.5 and rreason[k]:
                        cls = f"rejected by the detector ({rreason[k]})"
                    else:
                        cls = "no candidate"
            diam, contrast = _local_look(img, *p)
            edge = min(p[0], p[1], img.shape[1] - 1 - p[0], img.shape[0] - 1 - p[1])
            out.append(dict(image=name, target=tid, u=p[0], v=p[1], cls=cls, diameter_px=diam,
                            contrast_dn=contrast, edge_px=edge, control=int(tid) >= 1000))
    return out


def sheet_place(target_xy: dict, tid: str) -> str:
    """``corner``, ``border`` (the sheet's outermost row or column of targets) or ``inner``."""
    xs = np.array([xy[0] for xy in target_xy.values()])
    ys = np.array([xy[1] for xy in target_xy.values()])
    x, y = target_xy[tid]
    on_x = min(abs(x - xs.min()), abs(x - xs.max())) < 0.01
    on_y = min(abs(y - ys.min()), abs(y - ys.max())) < 0.01
    return "corner" if on_x and on_y else "border" if on_x or on_y else "inner"


def rejected_by_place(rows):
    """Rejected points and all marks by their target's place on the sheet, and how many of
    the rejected the adjustment of PhotoModeler's own marks rejects too."""
    xy = {}
    for line in dbat_rows(DBAT / "objpts-pm.txt"):
        t = line.split()
        xy[t[0]] = (float(t[1]), float(t[2]))
    ref = adjust_field(dbat_field_data()).residual_table().to_pydict()
    pm_rejected = {(im, t) for im, t, u in zip(ref["image"], ref["target_id"], ref["used"], strict=True) if not u}
    lines = [f"PhotoModeler's own marks, adjusted by fieldcal (0.1 px): {len(ref['used']) - len(pm_rejected)} used, "
             f"{len(pm_rejected)} rejected",
             "| place on the sheet | marks | rejected (ours) | share | also rejected with PM's marks "
             "| PM's marks rejected |",
             "|---|---|---|---|---|---|"]
    for place in ("inner", "border", "corner"):
        sel = [r for r in rows if sheet_place(xy, r["target"]) == place]
        rej = [r for r in sel if r["cls"].startswith("in adjustment, rejected")]
        both = sum((r["image"], r["target"]) in pm_rejected for r in rej)
        pm_here = sum(sheet_place(xy, t) == place for _, t in pm_rejected)
        lines.append(f"| {place} | {len(sel)} | {len(rej)} | {100 * len(rej) / max(len(sel), 1):.1f} % | {both} "
                     f"| {pm_here} |")
    return lines


def summarise(rows):
    lines = []
    for group, sel in (("plain targets", [r for r in rows if not r["control"]]),
                       ("ringed control targets 1001-1004", [r for r in rows if r["control"]])):
        c = Counter(r["cls"] for r in sel)
        lines.append(f"{group}: {len(sel)} marks")
        for k, n in c.most_common():
            lines.append(f"  {n:5d}  {k}")
    return lines


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", type=Path, help="write the session and the per-mark table here")
    args = ap.parse_args(argv)
    print("load:", os.getloadavg(), time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()))
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        names, pm = write_session(folder)
        t0 = time.process_time()
        prepared = prepare(folder)
        measurements = {n: measure(prepared, n) for n in prepared.to_measure}
        t1 = time.process_time()
        data, result, report = calibrate_from_measurements(prepared.session, measurements, AdjustmentOptions())
        t2 = time.process_time()
        rows = classify(folder, names, pm, measurements, data, result)
        if args.keep:
            import csv
            with open(folder / "recall.csv", "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(rows[0]))
                w.writeheader()
                w.writerows(rows)
    st = result.stats()
    print(f"measure {t1 - t0:.1f} CPU s, calibrate {t2 - t1:.1f} CPU s")
    print(f"points used {st['n_observations']}, "
          f"rejected {st['n_rejected']}, rmse {st['rmse_px']:.3f} px, sigma0 {st['sigma0']:.3f}")
    print("\n".join(summarise(rows)))
    print("\n".join(rejected_by_place(rows)))
    for n in ("f_mm", "xp_mm", "yp_mm", "k1"):
        print(f"{n}: {result.params[INDEX[n]]:.6g} ± {result.sigma.get(n, float('nan')):.2g}")
    per_image = Counter(r["image"] for r in rows if r["cls"] != "used" and not r["control"])
    print("plain marks not used, per image:", dict(sorted(per_image.items())))
    return rows, result


if __name__ == "__main__":
    main()
