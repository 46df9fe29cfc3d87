"""Unsurveyed coded targets of an image session (issue 26, from_images step 6b).

Truth: the paper's field at scale 0.25 (fieldcal.synthetic), the detector's output per image
from ``measurements_of`` (the measurements table the renderer's images give, without the
pixels); targets.csv leaves every second coded target without coordinates.
"""

from __future__ import annotations

import numpy as np

from fieldcal.field.adjustment import AdjustmentOptions
from fieldcal.field.from_images import calibrate_from_measurements
from fieldcal.model.camera import INDEX
from fieldcal.session.loader import load_session
from fieldcal.synthetic.field import measurements_of, paper_field
from fieldcal.synthetic.render import scaled_field
from fieldcal.synthetic.session_writer import write_field_session


def test_unsurveyed_coded_targets_join_the_adjustment_by_their_code(tmp_path):
    sf = scaled_field(paper_field(), 0.25)
    images = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]
    write_field_session(tmp_path, sf, images=False, coded=True, image_indices=images)
    lines = (tmp_path / "targets.csv").read_text().splitlines()
    out, blank = [lines[0]], []
    for line in lines[1:]:
        f = line.split(",")
        if f[5].strip() and int(f[5]) % 2:
            blank.append(f[0])
            f[1:5] = ["", "", "", ""]
        out.append(",".join(f))
    (tmp_path / "targets.csv").write_text("\n".join(out) + "\n")
    session = load_session(tmp_path)
    meas = {im.file: measurements_of(sf, i, coded=True, seed=1)[0]
            for i, im in zip(images, session.images, strict=True)}
    said: list[str] = []
    data, res, _ = calibrate_from_measurements(session, meas, AdjustmentOptions(), progress=said.append)
    assert any("unsurveyed coded target(s) of targets.csv intersected" in line for line in said)
    # each is adjusted under its own id and code, within 4 sigma of the truth
    stats, truth = res.stats(), sf.targets_true
    rows = {r["id"]: r for r in stats["unsurveyed_targets"]}
    got = [b for b in blank if b in rows]
    assert data.meta["coded_unsurveyed_targets"] == len(got) >= 8
    assert stats["n_unsurveyed_targets"] == len(got)            # no referencing asked: no others
    index, codes = truth.index(), dict(zip(data.targets.ids, data.targets.codes, strict=True))
    assert all(codes[b] == truth.codes[index[b]] >= 0 for b in got)
    z = np.array([np.abs(np.array(rows[b]["xyz_m"]) - truth.xyz_m[index[b]]) / (np.array(rows[b]["sigma_mm"]) / 1e3)
                  for b in got])
    assert z.max() < 4.0
    for name in ("f_mm", "xp_mm", "yp_mm", "k1"):
        assert abs(res.params[INDEX[name]] - sf.camera.params[INDEX[name]]) < 4 * res.sigma[name], name


def test_scale_bars_of_an_image_session_join_the_adjustment(tmp_path):
    """scale_bars.csv of a session of images (identification route): a bar between two surveyed
    targets and one to an unsurveyed coded target (it joins at step 6b) are observations of the
    final adjustment, their adjusted lengths within 4 sigma of the true ones."""
    sf = scaled_field(paper_field(), 0.25)
    images = [12 * s + a for s in range(6) for a in (s % 4, 4 + (s + 1) % 4)]
    write_field_session(tmp_path, sf, images=False, coded=True, image_indices=images)
    lines = (tmp_path / "targets.csv").read_text().splitlines()
    obs = sf.data.obs
    views = np.bincount(obs.target[np.isin(obs.image, images)], minlength=len(sf.targets_true))
    coded = [str(t) for t in sf.targets_true.ids[(sf.targets_true.codes >= 0) & (views >= 3)]]
    a, b, c = coded[0], coded[len(coded) // 2], coded[-1]          # seen in 3 or more of the images
    out = [lines[0]] + [ln if ln.split(",")[0] != c else f"{c},,,,,{ln.split(',')[5]}" for ln in lines[1:]]
    (tmp_path / "targets.csv").write_text("\n".join(out) + "\n")
    truth = sf.targets_true
    index = truth.index()
    true_mm = {(p, q): 1000.0 * float(np.linalg.norm(truth.xyz_m[index[p]] - truth.xyz_m[index[q]]))
               for p, q in ((a, b), (a, c))}
    (tmp_path / "scale_bars.csv").write_text("from_id,to_id,length_mm,sigma_mm\n" + "".join(
        f"{p},{q},{v:.3f},0.5\n" for (p, q), v in true_mm.items()))
    session = load_session(tmp_path)
    meas = {im.file: measurements_of(sf, i, coded=True, seed=1)[0]
            for i, im in zip(images, session.images, strict=True)}
    _, res, _ = calibrate_from_measurements(session, meas, AdjustmentOptions())
    bars = {(r["from_id"], r["to_id"]): r for r in res.datum["scale_bars"]}
    assert set(bars) == set(true_mm)
    for key, r in bars.items():
        assert abs(r["adjusted_mm"] - true_mm[key]) < 4 * r["sigma_adjusted_mm"], (key, r)
