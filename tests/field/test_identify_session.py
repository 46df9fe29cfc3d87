"""Identification of images with fewer than three seeds (fieldcal.field.identify_session, issue 11).

Sessions of the wide-angle scenario (12 images: 4 stations x 3 rolls, ~110-200 targets per
image) whose measurement tables come from the truth (fieldcal.synthetic.field.measurements_of:
the exact image points plus 0.1 px of noise, shuffled), so that every identity can be checked.
Three images keep all their coded targets (or hand marks); the others show 0, 1 or 2 markers.
Images of another field (the same grid with other gaps) are mixed in, and a periodic grid is
tried, where a pose shifted by one grid step fits as well as the right one.
"""

import numpy as np
import pytest

from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.session.loader import load_session
from fieldcal.synthetic.field import measurements_of, wide_field
from fieldcal.synthetic.session_writer import write_field_session

IMAGES = list(range(12))        # stations S1..S4, three rolls each
SEEDED = [0, 3, 6]              # the images that keep every code (or get marks)


def _session(tmp_path, *, max_markers=None, marks=False, keep_fraction=0.92, foreign=0):
    sf = wide_field(seed=1, keep_fraction=keep_fraction)
    folder = tmp_path / "s"
    write_field_session(folder, sf, images=False, coded=not marks, marks_csv=marks, image_indices=IMAGES,
                        marks_images=SEEDED if marks else None, seed=3)
    meas, truth = {}, {}
    for i in IMAGES:
        tab, t = measurements_of(sf, i, coded=not marks, max_markers=None if i in SEEDED else max_markers,
                                 seed=2)
        meas[sf.data.images[i].file], truth[sf.data.images[i].file] = tab, t
    if foreign:
        import json

        import pyarrow as pa

        # another field seen by the same camera: an image's dots scaled by 1.15 and turned by 20
        # degrees about the frame's centre (another grid spacing, another layout of the gaps)
        other = wide_field(seed=5, keep_fraction=keep_fraction)
        manifest = json.loads((folder / "session.json").read_text())
        s = sf.camera.sensor
        c = np.array([(s.width_px - 1) / 2, (s.height_px - 1) / 2])
        a = np.radians(20.0)
        M = 1.15 * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        for k in range(foreign):
            name = f"images/foreign_{k}.tif"
            tab, _ = measurements_of(other, 13 + 4 * k, coded=False, seed=k)
            uv = (np.stack([tab["u_px"].to_numpy(), tab["v_px"].to_numpy()], axis=1) - c) @ M.T + c
            inside = (uv > 10).all(axis=1) & (uv[:, 0] < s.width_px - 11) & (uv[:, 1] < s.height_px - 11)
            tab = tab.set_column(tab.schema.get_field_index("u_px"), "u_px", pa.array(uv[:, 0]))
            tab = tab.set_column(tab.schema.get_field_index("v_px"), "v_px", pa.array(uv[:, 1]))
            meas[name], truth[name] = tab.filter(pa.array(inside)), None
            manifest["images"].append({"file": name})
        (folder / "session.json").write_text(json.dumps(manifest))
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


@pytest.mark.parametrize("max_markers", [0, 1, 2])
def test_images_with_few_coded_targets_are_identified(tmp_path, max_markers):
    sf, sess, meas, truth = _session(tmp_path, max_markers=max_markers)
    lines = []
    data, result, report = calibrate_from_measurements(sess, meas, progress=lines.append)
    wrong, rate = _check(meas, truth, data, report)
    summary = data.meta["identification"]
    print(f"\n<= {max_markers} markers in 9 of 12 images: {summary}, wrong identities {wrong}")
    assert wrong == 0                                # the issue: no wrong identity
    assert rate >= 0.99                              # the issue: >= 99 % of the images with >= 20 targets
    assert summary["used"] == len(IMAGES) and summary["left_out"] == {}
    assert summary["started_from"]["seeds"] == len(SEEDED)
    assert result.stats()["n_images"] == len(IMAGES)


def test_a_field_without_codes_and_marks_in_three_images(tmp_path):
    sf, sess, meas, truth = _session(tmp_path, marks=True)
    data, result, report = calibrate_from_measurements(sess, meas)
    wrong, rate = _check(meas, truth, data, report)
    summary = data.meta["identification"]
    print(f"\nmarks in 3 of 12 images, no codes: {summary}, wrong identities {wrong}, rate {rate:.3f}")
    assert wrong == 0
    assert rate >= 0.99
    # the calibration: f within 3 sigma of the truth
    assert abs(result.params[0] - sf.camera.f_mm) < 3 * result.sigma["f_mm"]


@pytest.mark.xfail(strict=True, raises=Exception, reason=(
    "not met yet: with two foreign images (another grid spacing and layout) mixed in, the final "
    "adjustment becomes singular: a foreign image is not reliably left out"))
def test_images_of_another_field_are_left_out(tmp_path):
    sf, sess, meas, truth = _session(tmp_path, max_markers=1, foreign=2)
    data, result, report = calibrate_from_measurements(sess, meas)
    wrong, rate = _check(meas, truth, data, report)
    by = {r["image"]: r for r in report}
    print(f"\nforeign images: {[(n, by[n]['status'], by[n]['reason']) for n in by if 'foreign' in n]}")
    assert wrong == 0 and rate >= 0.99
    for k in range(2):
        r = by[f"images/foreign_{k}.tif"]
        assert r["status"] == "left out" and r["n_measured"] >= 20
    assert data.meta["identification"]["left_out"] == {"no pose fits": 2}


def test_a_periodic_grid_is_never_identified_wrongly(tmp_path):
    """Every target of the grid kept: a pose shifted by a grid step fits as well, so an image
    without seeds must be left out (ambiguous) or resolved, never given shifted identities."""
    sf, sess, meas, truth = _session(tmp_path, marks=True, keep_fraction=1.0)
    data, result, report = calibrate_from_measurements(sess, meas)
    wrong, rate = _check(meas, truth, data, report)
    summary = data.meta["identification"]
    print(f"\nperiodic grid, marks in 3 of 12 images: {summary}, wrong identities {wrong}")
    assert wrong == 0
    assert summary["used"] >= len(SEEDED)
    for r in report:
        if r["status"] != "ok":
            assert r["reason"].startswith(("ambiguous", "not identified")), r["reason"]
