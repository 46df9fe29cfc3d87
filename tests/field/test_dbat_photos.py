"""The real photos of DBAT's calibration sheet, from JPEG to calibration (../shared/data/dbat-camcal).

21 JPEGs (2272 x 1704, RGB) of a planar sheet with 96 dark discs and 4 PhotoModeler ring-coded
targets (not ArUco), on a wooden floor with books beside it. They are converted to 8-bit
single-channel TIFF, written as a session (targets from PhotoModeler's bundle, the sheet's
units used as metres, sigma from the file; nominal 7.5 mm; dark targets; no coded block) with
a marks.csv of 5 of PhotoModeler's measured points per image, then measured, identified and
calibrated by fieldcal. PhotoModeler's own marks of the same photos are the reference: for the
centroids (same points) and for the calibration (tests/realdata.py: dbat_field_data()).
"""

from dataclasses import replace

import numpy as np
import pytest

from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.pipeline import measure, prepare
from tests.realdata import dbat_field_data, dbat_image_names, dbat_marks, dbat_rows, require, write_dbat_photo_session

MARKED_IMAGES_FEW = (1, 8, 15)
"""The images that keep their marks in the run with marks in only 3 of the 21 photos."""


@pytest.fixture(scope="module")
def dbat(tmp_path_factory):
    return _dbat_run(tmp_path_factory)


@pytest.fixture(scope="module")
def dbat_few_marks(dbat, tmp_path_factory):
    """The same photos and measurements, with the marks of only 3 of the 21 photos."""
    folder = tmp_path_factory.mktemp("dbat-few")
    rows = dbat_rows(dbat["prepared"].session.marks_path)
    keep = {dbat["names"][i] for i in MARKED_IMAGES_FEW}
    (folder / "marks.csv").write_text("\n".join(["image,target_id,u,v"] + [r for r in rows[1:]
                                                                           if r.split(",")[0] in keep]) + "\n")
    session = replace(dbat["prepared"].session, marks_path=folder / "marks.csv")
    lines = []
    data, result, report = calibrate_from_measurements(session, dbat["measurements"], AdjustmentOptions(),
                                                       progress=lines.append)
    print("\n" + "\n".join(ln for ln in lines if not ln.startswith(("adjustment", "re-adj"))))
    return dict(data=data, result=result, report=report)


def _dbat_run(tmp_path_factory):
    require("dbat-camcal")                          # skips every test of the module without the data
    folder = tmp_path_factory.mktemp("dbat") / "dbat-camcal"
    # marks of 5 spread plain targets per photo; PhotoModeler's adjusted points as the survey
    write_dbat_photo_session(folder, None, list_plain=False, pm_survey=True)
    names = {i: name for i, (_, name) in dbat_image_names().items()}
    pm = dbat_marks()
    prepared = prepare(folder)
    measurements = {name: measure(prepared, name) for name in prepared.to_measure}
    lines = []
    data, result, report = calibrate_from_measurements(prepared.session, measurements, AdjustmentOptions(),
                                                       progress=lines.append)
    print("\n" + "\n".join(ln for ln in lines if not ln.startswith(("adjustment", "re-adj"))))
    reference = dbat_field_data()
    return dict(prepared=prepared, measurements=measurements, data=data, result=result, report=report,
                reference=reference, ref_result=adjust_field(reference), pm=pm, names=names)


def _pm_lookup(ref):
    return {(ref.images[i].file, str(ref.targets.ids[t])): uv
            for i, t, uv in zip(ref.obs.image, ref.obs.target, ref.obs.uv_px, strict=True)}


def test_every_photo_is_identified_without_a_wrong_identity(dbat):
    """Every measured blob we identify is the target PhotoModeler says is there; the ring-coded
    targets, the books and the wood grain give no identity."""
    ref, pm = dbat["reference"], _pm_lookup(dbat["reference"])
    assert all(r["status"] == "ok" for r in dbat["report"]), [r["reason"] for r in dbat["report"]]
    n_same = n_elsewhere = n_pm_measured = n_pm_identified = n_ringed = n_ringed_measured = 0
    res = dbat["result"]
    for name, ident in dbat["data"].meta["identifications"].items():
        table = dbat["measurements"][name]
        uv = np.stack([table["u_px"].to_numpy(), table["v_px"].to_numpy()], axis=1)
        i = [im.file for im in ref.images].index(name)
        k = ref.obs.image == i
        pm_uv, pm_id = ref.obs.uv_px[k], ref.targets.ids[ref.obs.target[k]]
        # the blob nearest each of PhotoModeler's marks (within 1 px: the same blob measured)
        d = np.linalg.norm(uv[:, None] - pm_uv[None], axis=2)
        for row in np.flatnonzero(ident.target >= 0):
            tid = str(dbat["data"].targets.ids[ident.target[row]])
            j = int(np.argmin(d[row]))
            if d[row, j] < 1.0:
                assert pm_id[j] == tid, f"{name}: blob at {uv[row]} is {pm_id[j]}, identified as {tid}"
                n_same += 1
            else:
                # a target PhotoModeler did not mark in this image: it must still be where the
                # calibration puts it, and no PhotoModeler mark may be near it
                assert (name, tid) not in pm
                assert d[row].min() > 20.0
                n = [im.file for im in dbat["data"].images].index(name)
                proj = res.camera.project(res.targets_m[ident.target[row]], res.R_world_to_camera[n],
                                          res.center_m[n])
                assert np.hypot(*(proj - uv[row])) < 1.0      # [px] where the calibration puts it
                n_elsewhere += 1
        measured = d.min(axis=0) < 1.0
        n_pm_measured += int(measured.sum())
        ringed = pm_id.astype(int) >= 1000                # the ringed control targets 1001-1004
        n_ringed += int(ringed.sum())
        n_ringed_measured += int((measured & ringed).sum())
        ids_found = {str(dbat["data"].targets.ids[t]) for t in ident.target[ident.target >= 0]}
        n_pm_identified += int(sum(pid in ids_found for pid in pm_id[measured]))
    print(f"\nidentified {n_same} blobs that PhotoModeler marked (all with its id) and {n_elsewhere} it did "
          f"not mark; of PhotoModeler's {len(ref.obs)} marks our detector measured {n_pm_measured}, "
          f"of which {n_pm_identified} were identified")
    print(f"the ringed control targets: {n_ringed_measured} of their {n_ringed} marks measured (their dots)")
    assert n_pm_identified >= 0.99 * n_pm_measured
    # recall (issue 23): discs joined to the sheet's shading were lost at the candidate stage
    # (1829 of 2074 measured before; bench/README_dbat_recall.md)
    assert n_pm_measured >= 0.99 * len(ref.obs)
    assert n_ringed_measured >= 0.95 * n_ringed
    assert n_elsewhere <= 5
    assert res.stats()["n_images"] == 21


def test_centroids_agree_with_photomodeler(dbat):
    pm = _pm_lookup(dbat["reference"])
    data = dbat["data"]
    d = []
    for k in range(len(data.obs)):
        key = (data.images[data.obs.image[k]].file, str(data.targets.ids[data.obs.target[k]]))
        if key in pm:
            d.append(data.obs.uv_px[k] - pm[key])
    d = np.asarray(d)
    norm = np.hypot(d[:, 0], d[:, 1])
    rms = float(np.sqrt(np.mean(norm**2)))
    print(f"\nour centroids - PhotoModeler's: {len(d)} points, RMS {rms:.3f} px, median {np.median(norm):.3f} px, "
          f"max {norm.max():.3f} px, mean ({d[:, 0].mean():+.3f}, {d[:, 1].mean():+.3f}) px")
    # strongly compressed JPEGs, two different centroid operators: a few tenths of a pixel
    assert rms < 0.3
    assert norm.max() < 1.0
    assert np.all(np.abs(d.mean(axis=0)) < 0.05)    # no convention offset (the 0.5 px is handled)


def test_calibration_agrees_with_the_one_from_photomodelers_marks(dbat):
    ours, ref = dbat["result"], dbat["ref_result"]
    print(f"\n{'':6s} {'from the photos':>24s} {'from PhotoModeler marks':>24s}  diff / combined sigma")
    for j, n in enumerate(("f_mm", "xp_mm", "yp_mm", "k1", "k2")):
        a, b = ours.params[j if j < 3 else j + 1], ref.params[j if j < 3 else j + 1]
        sa, sb = ours.sigma.get(n, np.nan), ref.sigma.get(n, np.nan)
        print(f"{n:6s} {a:14.6g} +- {sa:.2g} {b:14.6g} +- {sb:.2g}  {(a - b) / np.hypot(sa, sb):+.1f}")
    so, sr = ours.stats(), ref.stats()
    print(f"photos: {so['n_observations']} points, rmse {so['rmse_px']:.3f} px, sigma0 {so['sigma0']:.1f} "
          f"(a-priori: the detector's sigma_px); PhotoModeler: {sr['n_observations']} points, rmse "
          f"{sr['rmse_px']:.3f} px, sigma0 {sr['sigma0']:.2f} (a-priori 0.1 px)")
    for j, n in enumerate(("f_mm", "xp_mm", "yp_mm")):
        diff = abs(ours.params[j] - ref.params[j])
        # two measurements of the same photos: within 3 combined (a-posteriori) sigmas
        assert diff <= 3.0 * np.hypot(ours.sigma[n], ref.sigma[n])
    assert abs(ours.params[0] / ref.params[0] - 1.0) < 1e-3       # f to 0.1 %
    assert so["rmse_px"] < 0.2                                    # the JPEGs' centroid noise


def test_marks_in_three_photos_give_the_same_calibration(dbat, dbat_few_marks):
    """Hand marks in only 3 of the 21 photos: the others are identified from the calibrated
    camera (pose-free search, the oriented images' centres; the sheet is a square grid that a
    quarter turn maps onto itself, told apart by the fit), every identity is PhotoModeler's, and
    the calibration stays within the full-marks run's bands."""
    few, full = dbat_few_marks["result"], dbat["result"]
    summary = dbat_few_marks["data"].meta["identification"]
    print(f"\nmarks in 3 photos: {summary}")
    ref = dbat["reference"]
    wrong = same = 0
    for name, ident in dbat_few_marks["data"].meta["identifications"].items():
        table = dbat["measurements"][name]
        uv = np.stack([table["u_px"].to_numpy(), table["v_px"].to_numpy()], axis=1)
        k = ref.obs.image == [im.file for im in ref.images].index(name)
        pm_uv, pm_id = ref.obs.uv_px[k], ref.targets.ids[ref.obs.target[k]]
        for row in np.flatnonzero(ident.target >= 0):
            d = np.linalg.norm(pm_uv - uv[row], axis=1)
            if d.min() < 1.0:                       # a blob PhotoModeler marked: its id
                same += 1
                wrong += int(pm_id[np.argmin(d)] != dbat_few_marks["data"].targets.ids[ident.target[row]])
    print(f"identities checked against PhotoModeler's marks: {same}, wrong {wrong}")
    assert wrong == 0 and same > 1500
    assert summary["used"] == 21                         # every photo (>= 99 % of those with >= 20 targets)
    for j, n in enumerate(("f_mm", "xp_mm", "yp_mm")):
        print(f"{n}: {few.params[j]:.6g} +- {few.sigma[n]:.2g} "
              f"(full marks {full.params[j]:.6g} +- {full.sigma[n]:.2g})")
        # the same bands as the full-marks run against PhotoModeler: 3 combined sigmas
        assert abs(few.params[j] - full.params[j]) <= 3.0 * np.hypot(few.sigma[n], full.sigma[n])
    assert abs(few.params[0] / full.params[0] - 1.0) < 1e-3
    assert few.stats()["rmse_px"] < 0.2
