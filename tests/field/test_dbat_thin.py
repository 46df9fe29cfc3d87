"""The DBAT sheet from its photos with only its four control points marked (issue 26 goal 6).

``marks.csv`` holds PhotoModeler's marks of the control points 1001-1004 in each of the 21
photos (nothing else); targets.csv lists those four (the unit square, 0.001 units) and the other
96 ids without coordinates. Through the pipeline (``fieldcal run``'s ``solve``) every photo is
resected from its marks and the plain discs are found by automatic referencing
(``fieldcal.field.thin_start``); PhotoModeler's marks of all 100 targets with the same four
control points (``bench/dbat_unsurveyed.py``) are the reference. The same photos as a free
network scaled by two sides of the sheet give the same camera. Figures:
bench/README_unsurveyed.md.
"""

from dataclasses import replace

import numpy as np
import pytest

from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.model.camera import INDEX
from fieldcal.pipeline import measure, prepare, solve
from tests.realdata import DBAT, dbat_field_data, dbat_rows, write_dbat_photo_session

CONTROL = {"1001": (0, 1, 0), "1002": (1, 1, 0), "1003": (0, 0, 0), "1004": (1, 0, 0)}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("dbat-thin")
    images = write_dbat_photo_session(root / "control", None, list_plain=True)
    write_dbat_photo_session(root / "free", images, list_plain=False, bars=2)
    control, free = prepare(root / "control"), prepare(root / "free")
    meas = {n: measure(control, n) for n in control.to_measure}
    lines = []
    out = {"control": solve(control, meas, fingerprint_="c", progress=lines.append),
           "free": solve(free, meas, fingerprint_="f", progress=lines.append)}
    print("\n" + "\n".join(ln for ln in lines if ln.startswith(("thin", "referencing"))))
    ref = dbat_field_data()
    xyz = np.full_like(ref.targets.xyz_m, np.nan)
    sigma = ref.targets.sigma_mm.copy()
    for k, tid in enumerate(ref.targets.ids):
        if tid in CONTROL:
            xyz[k], sigma[k] = CONTROL[tid], 1.0
    ref = replace(ref, targets=replace(ref.targets, xyz_m=xyz, sigma_mm=sigma))
    out["marks"] = adjust_field(ref, AdjustmentOptions())
    out["pm"] = np.array([[float(v) for v in ln.split(",")] for ln in dbat_rows(DBAT / "markpts.txt")])
    return out


def test_every_photo_is_resected_and_every_disc_referenced_as_photomodeler_marked_it(runs):
    doc, res = runs["control"].document, runs["control"].result
    st = doc["stats"]
    assert st["identification"]["used"] == 21 and st["referenced_targets"] == 96
    data, pm = res.data, runs["pm"]
    ids_of = {}
    for k in np.flatnonzero(res.obs_used):
        name, tid = data.images[data.obs.image[k]].file, str(data.targets.ids[data.obs.target[k]])
        r = pm[pm[:, 0] == int(name[-6:-4]) - 20]
        d = np.linalg.norm(r[:, 2:4] - 0.5 - data.obs.uv_px[k], axis=1)
        if d.min() < 1.0:                           # the disc PhotoModeler marked there
            ids_of.setdefault(tid, set()).add(str(int(r[np.argmin(d), 1])))
    assert all(len(v) == 1 for v in ids_of.values())                 # a track is one target
    named = [next(iter(v)) for v in ids_of.values()]
    assert len(set(named)) == len(named) == 100                      # and no two tracks share one
    assert all(t == next(iter(ids_of[t])) for t in CONTROL)          # the control points are theirs
    assert int(np.sum(res.obs_used)) > 1800


def test_calibration_agrees_with_photomodelers_marks_of_the_same_network(runs):
    """Two measurements of the same photos (our centroids, PhotoModeler's): xp, yp, k1 within 3
    combined sigmas, f to 0.1 % (it differs by ~4 combined sigmas: the centroid operators
    differ; on the same (image, target) pairs PhotoModeler's marks give the same f as on all
    of them, bench/README_unsurveyed.md)."""
    ours, marks = runs["control"].result, runs["marks"]
    for p in ("f_mm", "xp_mm", "yp_mm", "k1"):
        z = (ours.params[INDEX[p]] - marks.params[INDEX[p]]) / np.hypot(ours.sigma[p], marks.sigma[p])
        print(f"{p}: photos {ours.params[INDEX[p]]:.6g} +- {ours.sigma[p]:.2g}, marks {marks.params[INDEX[p]]:.6g} "
              f"+- {marks.sigma[p]:.2g} ({z:+.1f} combined sigma)")
        if p != "f_mm":
            assert abs(z) < 3.0
    assert abs(ours.params[0] / marks.params[0] - 1.0) < 1e-3
    assert ours.stats()["rmse_px"] < 0.2


def test_free_network_scaled_by_two_sides_gives_the_same_camera(runs):
    a, b = runs["control"].result, runs["free"].result
    assert b.datum["type"] == "free network" and len(b.datum["scale_bars"]) == 2
    for p in ("f_mm", "xp_mm", "yp_mm", "k1"):
        assert abs(b.params[INDEX[p]] - a.params[INDEX[p]]) < 0.1 * a.sigma[p]
        assert abs(b.sigma[p] / a.sigma[p] - 1.0) < 0.01
    lengths = [s["adjusted_mm"] for s in b.datum["scale_bars"]]
    assert all(abs(x - 1000.0) < 0.5 for x in lengths)               # the sides, 1:2000
