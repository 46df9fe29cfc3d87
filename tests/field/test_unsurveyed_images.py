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
