"""Field calibration from rendered images, end to end (fieldcal.field.from_images).

One session of the paper's scenario at scale 0.25 (2052 x 1570 px, discs ~27 px, ArUco
markers as coded targets): 12 images, two per station with different roll angles, rendered
by fieldcal.synthetic.render and measured by the pipeline's measuring step, plus a corrupt image (a
truncated TIFF) and an image that shows only 7 targets. The calibration from the images is
compared with the adjustment of exact observations of the same (image, target) pairs with
noise of the same size (the measurement errors' RMS, per kind of target).
"""

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest
import tifffile
from scipy.spatial import cKDTree

from fieldcal.errors import GeometryError, ImageError, InputError
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.field.from_images import calibrate_from_measurements, target_normals_of
from fieldcal.pipeline import measure, prepare, solve
from fieldcal.synthetic.field import paper_field
from fieldcal.synthetic.render import render_image, scaled_field
from fieldcal.synthetic.session_writer import write_field_session

# two attitudes per station, rolled by different multiples of 90 degrees (image = 12 s + a)
IMAGES = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]
SPARSE = 7            # another attitude, rendered with only 4 markers and 3 discs


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    sf = scaled_field(paper_field(), 0.25)
    folder = tmp_path_factory.mktemp("paper-session")
    info = write_field_session(folder, sf, image_indices=IMAGES, coded=True, seed=4)
    # a truncated copy of a good TIFF, and a sparse image
    good = folder / info["images"][1]
    (folder / "images" / "corrupt.tif").write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    obs = sf.data.obs
    seen = np.unique(obs.target[obs.image == SPARSE])
    coded = seen[sf.targets_true.codes[seen] >= 0][:4]
    plain = seen[sf.targets_true.codes[seen] < 0][::40][:3]
    sparse = render_image(sf, SPARSE, targets=np.concatenate([coded, plain]), seed=4)
    assert sparse.truth.num_rows == 7
    tifffile.imwrite(folder / "images" / "sparse.tif", sparse.pixels)
    manifest = json.loads((folder / "session.json").read_text())
    manifest["images"] += [{"file": "images/corrupt.tif"}, {"file": "images/sparse.tif"}]
    (folder / "session.json").write_text(json.dumps(manifest))

    prepared = prepare(folder)
    measurements, bad = {}, []
    for name in prepared.to_measure:            # what the flow does: a bad image is reported
        try:
            measurements[name] = measure(prepared, name)
        except ImageError as err:
            bad.append({"image": name, "status": "left out", "reason": str(err)})
    lines = []
    data, result, report = calibrate_from_measurements(
        prepared.session, measurements, AdjustmentOptions(), progress=lines.append,
        target_normals=sf.targets_true.normals)
    print("\n" + "\n".join(lines))
    return dict(sf=sf, info=info, prepared=prepared, measurements=measurements, bad=bad, data=data,
                result=result, report=report, lines=lines, folder=folder)


def _truth_of(run, name):
    t = run["info"]["truth"][name].to_pydict()
    return (np.asarray(t["target_index"]), np.stack([t["u_px"], t["v_px"]], axis=1), t)


def test_bad_images_are_reported_not_fatal(run):
    assert [b["image"] for b in run["bad"]] == ["images/corrupt.tif"]
    assert "corrupt.tif" in run["bad"][0]["reason"]
    by = {r["image"]: r for r in run["report"]}
    assert len(by) == len(IMAGES) + 2
    assert by["images/corrupt.tif"]["status"] == "left out"
    assert by["images/corrupt.tif"]["reason"].startswith("not measured")
    assert by["images/sparse.tif"]["status"] == "left out"
    assert by["images/sparse.tif"]["reason"] == "only 7 target(s) identified, at least 8 needed"
    assert by["images/sparse.tif"]["n_coded"] == 4
    ok = [r for r in run["report"] if r["status"] == "ok"]
    assert len(ok) == len(IMAGES) and all(r["reason"] == "" for r in ok)
    assert run["result"].stats()["n_images"] == len(IMAGES)


def test_identities_are_right_and_complete(run):
    """>= 99 % of the visible targets of every image identified, no wrong identity (second pass)."""
    sensor = run["sf"].camera.sensor
    idents = run["data"].meta["identifications"]
    rates, n_wrong = [], 0
    for name in run["info"]["images"]:
        ti, exact, t = _truth_of(run, name)
        meas = run["measurements"][name]
        ident = idents[name]
        assert ident.ok, ident.reason
        uv = np.stack([meas["u_px"].to_numpy(), meas["v_px"].to_numpy()], axis=1)
        ell = np.stack([t["u_ellipse_px"], t["v_ellipse_px"]], axis=1)
        _, j = cKDTree(ell).query(uv)
        found = ident.target >= 0
        n_wrong += int(np.sum(found & (ti[j] != ident.target)))
        d = np.asarray(t["diameter_px"])
        margin = 0.5 * d + 3.5                    # blur: 4 sigma of the 0.8 px PSF + 0.3
        visible = (np.asarray(t["fully_inside"]) & (np.asarray(t["visible_fraction"]) > 0.999)
                   & np.asarray(t["isolated"]) & ~np.asarray(t["saturated"])
                   & (ell[:, 0] > margin) & (ell[:, 1] > margin)
                   & (ell[:, 0] < sensor.width_px - 1 - margin) & (ell[:, 1] < sensor.height_px - 1 - margin))
        got = set(ident.target[found].tolist())
        rates.append(np.mean([k in got for k in ti[visible]]))
    print(f"\nsecond pass: identified fraction of the visible targets per image: min {min(rates):.4f}, "
          f"mean {np.mean(rates):.4f}; wrong identities: {n_wrong}")
    assert n_wrong == 0
    assert min(rates) >= 0.99


def test_calibration_matches_exact_observations_with_the_same_noise(run):
    sf, data, res = run["sf"], run["data"], run["result"]
    idx = np.array([int(im.file[-7:-4]) - 1 for im in data.images])      # images/paper_NNN.tif
    exact = sf.camera.project(sf.targets_true.xyz_m[data.obs.target], sf.R_world_to_camera[idx[data.obs.image]],
                              sf.center_m[idx[data.obs.image]])
    err = data.obs.uv_px - exact
    marker = sf.targets_true.codes[data.obs.target] >= 0
    rms = {k: np.sqrt(np.mean(err[m] ** 2)) for k, m in (("discs", ~marker), ("markers", marker))}
    rng = np.random.default_rng(0)
    noise = rng.normal(0.0, 1.0, err.shape) * np.where(marker, rms["markers"], rms["discs"])[:, None]
    ref = adjust_field(data.with_obs(replace(data.obs, uv_px=exact + noise)), AdjustmentOptions())
    truth = sf.camera.params
    print(f"\nmeasurement errors (RMS per axis): discs {rms['discs']:.4f} px, markers {rms['markers']:.4f} px "
          f"(a-priori sigma: median {np.median(data.obs.sigma_px):.4f} px)")
    print(f"{'':6s} {'truth':>10s} {'images':>22s} {'exact + noise':>22s}")
    for j, n in enumerate(("f_mm", "xp_mm", "yp_mm")):
        a, sa, b, sb = res.params[j], res.sigma[n], ref.params[j], ref.sigma[n]
        print(f"{n:6s} {truth[j]:10.5f} {a:10.5f} +- {sa:.5f} ({(a - truth[j]) / sa:+.1f}) "
              f"{b:10.5f} +- {sb:.5f} ({(b - truth[j]) / sb:+.1f})")
        # the issue: within their sigmas of each other, or both within 3 sigma of the truth
        assert abs(a - b) <= sa + sb or (abs(a - truth[j]) <= 3 * sa and abs(b - truth[j]) <= 3 * sb)
    st = res.stats()
    print(f"images: {st['n_observations']} points, {st['n_rejected']} rejected, rmse {st['rmse_px']:.4f} px, "
          f"sigma0 {st['sigma0']:.3f}; fixed {res.fixed_parameters}")
    assert rms["discs"] < 0.01                        # the detector's accuracy on these images
    assert st["n_rejected"] <= 0.01 * st["n_observations"]


def test_eccentricity_is_removed_and_reported(run):
    assert any("perspective eccentricity removed" in line for line in run["lines"])
    e = [r["eccentricity_max_px"] for r in run["report"] if r["status"] == "ok"]
    # paper geometry at scale 0.25: ~0.008-0.016 px (4 x the full-size figure, bench/README_extract.md)
    assert 0.004 < max(e) < 0.03
    assert run["data"].meta["eccentricity_max_px"] == pytest.approx(max(e))


def test_pipeline_solve_serves_image_sessions(run):
    out = solve(run["prepared"], run["measurements"], fingerprint_="sha256:" + "0" * 64, left_out=run["bad"])
    doc = out.document
    assert doc["stats"]["n_images"] == len(IMAGES)
    # the session gives no target normals: the pipeline estimates them (local planes, the
    # ellipses' shapes), so f agrees with the fixture's (true normals) to a fraction of its sigma
    assert abs(doc["parameters"]["f_mm"] - run["result"].params[0]) < run["result"].sigma["f_mm"]
    # 10 %: each run estimates its own floor of the image sigmas (variance components); here the
    # fixture's residuals ask for 0.0017 px (re-weighted, sigma f +6 %), the pipeline's for less
    assert doc["sigma"]["f_mm"] == pytest.approx(run["result"].sigma["f_mm"], rel=0.10)
    left = {r["image"]: r["reason"] for r in out.left_out}
    assert set(left) == {"images/corrupt.tif", "images/sparse.tif"}
    # (pipeline lists the corrupt image twice: once from the flow's report, once from ours)
    assert set(doc["stats"]["left_out_images"]) == {"images/corrupt.tif", "images/sparse.tif"}


def test_fewer_than_three_images_and_missing_focal_length_are_refused(run):
    sess, meas = run["prepared"].session, run["measurements"]
    two = {k: meas[k] for k in list(meas)[:2]}
    with pytest.raises(GeometryError, match=r"only 2 of 14 images could be identified .*not measured"):
        calibrate_from_measurements(sess, two)
    with pytest.raises(InputError, match="lens.nominal_focal_mm is needed"):
        calibrate_from_measurements(replace(sess, nominal_focal_mm=None), meas)


def test_marks_session_and_planar_normals(run, tmp_path):
    """A session without coded targets needs marks.csv; the marks' images are identified from them."""
    folder = tmp_path / "marks"
    shutil.copytree(run["folder"], folder)
    manifest = json.loads((folder / "session.json").read_text())
    del manifest["field"]["coded"]
    manifest["images"] = manifest["images"][:4]
    (folder / "session.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="need marks.csv"):
        prepare(folder)
    # a planar field's normal comes from its plane; a 3-D field without normals has none
    flat = replace(run["sf"].data.targets, xyz_m=run["sf"].data.targets.xyz_m * [1, 0, 1], normals=None)
    n = target_normals_of(flat)
    assert n.shape == (len(flat), 3) and np.allclose(np.abs(n[:, 1]), 1.0)
    assert target_normals_of(replace(run["sf"].data.targets, normals=None)) is None
