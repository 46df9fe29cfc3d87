"""Identification of images with fewer than three seeds (fieldcal.field.identify_session, issue 11).

Sessions of the wide-angle scenario (12 images: 4 stations x 3 rolls, 110-200 targets per
image) whose measurement tables come from the truth (fieldcal.synthetic.field.measurements_of:
the exact image points plus 0.1 px of noise, shuffled), so that every identity can be checked.
Three images (of stations S1-S3) keep all their coded targets, or get hand marks; the others
show 0, 1 or 2 markers, and the images of station S4, which has no image with seeds, one
marker with its four corners. Images of another field are mixed in. A periodic grid (every
target kept) is tried, where a pose shifted by whole grid steps explains the dots as well,
except at the field's edges and the relief.
"""

import json

import numpy as np
import pyarrow as pa

from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.field.identify_session import PriorOptions
from fieldcal.session.loader import load_session
from fieldcal.synthetic.field import measurements_of, wide_field
from fieldcal.synthetic.session_writer import write_field_session

IMAGES = list(range(12))        # stations S1..S4, three rolls each
SEEDED = [0, 3, 6]              # the images that keep every code (or get marks)
MARKERS = {1: 0, 2: 1, 4: 2, 5: 0, 7: 1, 8: 2, 9: 1, 10: 1, 11: 1}
"""Markers kept in the other images: 0, 1 or 2 beside a station with seeds, 1 in station S4."""


def _foreign(sf, folder, meas, truth, n: int):
    """``n`` images of another field (other gaps) seen by the same camera, each turned by 20 degrees
    and scaled by 1.15 about the frame's centre (another spacing, a view no pose of this field gives)."""
    other = wide_field(seed=5)
    manifest = json.loads((folder / "session.json").read_text())
    s = sf.camera.sensor
    c = np.array([(s.width_px - 1) / 2, (s.height_px - 1) / 2])
    a = np.radians(20.0)
    M = 1.15 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    for k in range(n):
        name = f"images/foreign_{k}.tif"
        tab, _ = measurements_of(other, 13 + 4 * k, coded=False, seed=k)
        uv = (np.stack([tab["u_px"].to_numpy(), tab["v_px"].to_numpy()], axis=1) - c) @ M.T + c
        inside = (uv > 10).all(axis=1) & (uv[:, 0] < s.width_px - 11) & (uv[:, 1] < s.height_px - 11)
        tab = tab.set_column(tab.schema.get_field_index("u_px"), "u_px", pa.array(uv[:, 0]))
        tab = tab.set_column(tab.schema.get_field_index("v_px"), "v_px", pa.array(uv[:, 1]))
        meas[name], truth[name] = tab.filter(pa.array(inside)), None
        manifest["images"].append({"file": name})
    (folder / "session.json").write_text(json.dumps(manifest))


def _session(tmp_path, *, marks=False, keep_fraction=0.92, foreign=0, images=IMAGES):
    sf = wide_field(seed=1, keep_fraction=keep_fraction)
    folder = tmp_path / "s"
    write_field_session(folder, sf, images=False, coded=not marks, marks_csv=marks, image_indices=images,
                        marks_images=SEEDED if marks else None, seed=3)
    meas, truth = {}, {}
    for i in images:
        tab, t = measurements_of(sf, i, coded=not marks, max_markers=MARKERS.get(i), seed=2, corners=True)
        meas[sf.data.images[i].file], truth[sf.data.images[i].file] = tab, t
    if foreign:
        _foreign(sf, folder, meas, truth, foreign)
    return sf, load_session(folder), meas, truth


def _check(meas, truth, data, report):
    """(wrong identities, identified share of the images showing >= 20 targets)."""
    wrong = 0
    for name, ident in data.meta["identifications"].items():
        if truth[name] is None:
            continue
        found = ident.target >= 0
        wrong += int(np.sum(ident.target[found] != truth[name][found]))
    used = {r["image"] for r in report if r["status"] == "ok"}
    big = [n for n, t in truth.items() if t is not None and meas[n].num_rows >= 20]
    return wrong, sum(n in used for n in big) / len(big)


def test_few_coded_targets_and_foreign_images(tmp_path):
    """0, 1 or 2 markers in 9 of 12 images, two images of another field: every image of the
    field is identified (station, marker corners, pattern), the foreign ones are left out."""
    sf, sess, meas, truth = _session(tmp_path, foreign=2)
    data, result, report = calibrate_from_measurements(sess, meas)
    wrong, rate = _check(meas, truth, data, report)
    summary = data.meta["identification"]
    by = {r["image"]: r for r in report}
    print(f"\n0-2 markers in 9 of 12 images, 2 foreign: {summary}, wrong identities {wrong}")
    assert wrong == 0                                # the issue: no wrong identity
    assert rate >= 0.99                              # the issue: >= 99 % of the images with >= 20 targets
    assert summary["used"] == len(IMAGES)
    assert summary["started_from"]["seeds"] == len(SEEDED)
    assert summary["started_from"].get("marker", 0) >= 1      # station S4: a marker's corners
    for k in range(2):
        r = by[f"images/foreign_{k}.tif"]
        assert r["status"] == "left out" and r["n_measured"] >= 20 and r["reason"]
    assert summary["left_out"] == {"no pose fits": 2}
    assert abs(result.params[0] - sf.camera.f_mm) < 3 * result.sigma["f_mm"]


def test_a_wrong_identification_is_left_out_by_the_adjustment(tmp_path):
    """With the verification switched off, an image of another field is identified (wrongly);
    the adjustment it would spoil leaves it out, and every image of the field stays."""
    images = [0, 1, 2, 3, 4, 5, 6]
    sf, sess, meas, truth = _session(tmp_path, foreign=1, images=images)
    lax = PriorOptions(max_fit_factor=1e9, max_missed=1e9, extra_sigmas=1e9, min_fit_ratio=0.0)
    data, result, report = calibrate_from_measurements(sess, meas, priors=lax)
    wrong, rate = _check(meas, truth, data, report)
    by = {r["image"]: r for r in report}
    print(f"\nverification off, 1 foreign image: {data.meta['identification']}; "
          f"{by['images/foreign_0.tif']['reason']}")
    assert wrong == 0 and rate >= 0.99
    assert data.meta["identification"]["used"] == len(images)
    assert by["images/foreign_0.tif"]["status"] == "left out"
    assert by["images/foreign_0.tif"]["reason"].startswith("does not fit the other images")


def test_marks_in_three_images_of_a_periodic_grid(tmp_path):
    """No codes, marks in 3 of 12 images, every grid target kept: shifted poses explain the dots
    nearly as well; they must be resolved (edges, relief) or left out, never accepted."""
    sf, sess, meas, truth = _session(tmp_path, marks=True, keep_fraction=1.0)
    data, result, report = calibrate_from_measurements(sess, meas)
    wrong, rate = _check(meas, truth, data, report)
    summary = data.meta["identification"]
    print(f"\nperiodic grid, marks in 3 of 12 images: {summary}, wrong identities {wrong}")
    assert wrong == 0
    assert rate >= 0.99
    for r in report:
        if r["status"] != "ok":
            assert r["reason"].startswith(("ambiguous", "not identified")), r["reason"]
    assert abs(result.params[0] - sf.camera.f_mm) < 3 * result.sigma["f_mm"]
