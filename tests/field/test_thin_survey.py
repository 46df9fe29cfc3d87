"""From photographs with only four control points (issue 26 goals 3 and 6, the truth analogue).

A rendered planar sheet like DBAT's (``fieldcal.synthetic.field.sheet_field``: 100 plain discs,
the four corners the control points 1001-1004, 20 convergent photos, a quarter of them rolled a
quarter turn, ~60 px of distortion in the corners). marks.csv holds only the four control points
in each photograph (their true image points plus 0.3 px of clicking noise); targets.csv lists
them with their coordinates and the other 96 ids without (unsurveyed, plain). The pipeline
(``fieldcal run``'s ``solve``) resects every photo from its marks and grows the network by
automatic referencing (``fieldcal.field.thin_start``); the same photos as a free network scaled
by two sides of the sheet (scale_bars.csv) give the same interior orientation.
"""

import json
import os
from dataclasses import replace

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
from fieldcal.model.camera import INDEX
from fieldcal.pipeline import measure, prepare, solve
from fieldcal.session.data import ScaleBars
from fieldcal.session.loader import scale_bars_among
from fieldcal.synthetic.field import SHEET_CONTROL_IDS, sheet_field
from fieldcal.synthetic.session_writer import write_field_session

INTERIOR = ("f_mm", "xp_mm", "yp_mm", "k1")
MARK_NOISE_PX = 0.3


def write_sheet_tables(folder, sf, *, free: bool):
    """targets.csv (the four control points; unless ``free``, the other ids listed without
    coordinates), marks.csv (the control points only) and, ``free``, scale_bars.csv (two sides)
    and ``field.datum`` "free" in session.json (bench/bench_thin_sheet.py uses it too)."""
    ids, X = sf.targets_true.ids, sf.targets_true.xyz_m
    rows = ["id,X,Y,Z,sigma_mm,code"]
    for t, x in zip(ids, X, strict=True):
        if t in SHEET_CONTROL_IDS:
            rows.append(f"{t},{x[0]:.6f},{x[1]:.6f},{x[2]:.6f},1.0,")
        elif not free:
            rows.append(f"{t},,,,,")                 # listed, unsurveyed, plain
    (folder / "targets.csv").write_text("\n".join(rows) + "\n")
    rng = np.random.default_rng(11)
    obs, marks = sf.data.obs, ["image,target_id,u,v"]
    for k in np.flatnonzero(np.isin(ids[obs.target], SHEET_CONTROL_IDS)):
        u, v = sf.uv_true_px[k] + rng.normal(0.0, MARK_NOISE_PX, 2)
        marks.append(f"{sf.data.images[obs.image[k]].file},{ids[obs.target[k]]},{u:.3f},{v:.3f}")
    (folder / "marks.csv").write_text("\n".join(marks) + "\n")
    if free:
        side_mm = 1000.0 * float(np.linalg.norm(X[list(ids).index("1002")] - X[list(ids).index("1001")]))
        (folder / "scale_bars.csv").write_text(f"from_id,to_id,length_mm,sigma_mm\n1001,1002,{side_mm:.4f},0.02\n"
                                               f"1003,1001,{side_mm:.4f},0.02\n")
        manifest = json.loads((folder / "session.json").read_text())
        manifest["field"]["datum"] = "free"
        (folder / "session.json").write_text(json.dumps(manifest, indent=2))


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    sf = sheet_field(seed=3)
    a = tmp_path_factory.mktemp("sheet-control")
    write_field_session(a, sf, coded=False, seed=3, compression_mix=False)
    write_sheet_tables(a, sf, free=False)
    b = tmp_path_factory.mktemp("sheet-free")
    write_field_session(b, sf, images=False, coded=False, seed=3)
    (b / "images").mkdir(exist_ok=True)
    for f in (a / "images").iterdir():              # the same photos (hard links: a link out is refused)
        os.link(f, b / "images" / f.name)
    write_sheet_tables(b, sf, free=True)
    pa_, pb = prepare(a), prepare(b)
    meas = {n: measure(pa_, n) for n in pa_.to_measure}
    lines = []
    out_a = solve(pa_, meas, fingerprint_="a", progress=lines.append)
    out_b = solve(pb, meas, fingerprint_="b", progress=lines.append)
    print("\n" + "\n".join(ln for ln in lines if ln.startswith(("thin", "referencing"))))
    return dict(sf=sf, a=out_a, b=out_b, folder_a=a)


def _z(res, sf):
    return {p: (res.params[INDEX[p]] - sf.camera.params[INDEX[p]]) / res.sigma[p] for p in INTERIOR}


def test_four_marked_control_points_start_the_sheet_and_referencing_finds_every_disc(sheet):
    sf, out = sheet["sf"], sheet["a"]
    res = out.result
    data = res.data
    st = out.document["stats"]
    assert st["n_images"] == 20 and st["identification"]["used"] == 20
    ids = data.targets.ids
    seen = np.unique(data.obs.target[res.obs_used])
    ar = [t for t in ids[seen] if t.startswith("AR")]
    assert len(ar) == 96 and st["referenced_targets"] == 96
    # listed unsurveyed plain ids cannot be matched (no coordinates): their discs get AR ids
    assert not set(ids[seen]) & {t for t in sf.targets_true.ids if t not in SHEET_CONTROL_IDS}
    # every track is one true disc, and no two tracks share one: the true point nearest each
    # observation (in its image, within 1 px) names it
    truth = {}
    for k in np.flatnonzero(res.obs_used):
        i = [im.file for im in sf.data.images].index(data.images[data.obs.image[k]].file)
        m = np.flatnonzero(sf.data.obs.image == i)
        d = np.linalg.norm(sf.uv_true_px[m] - data.obs.uv_px[k], axis=1)
        assert d.min() < 1.0
        truth.setdefault(ids[data.obs.target[k]], set()).add(sf.targets_true.ids[sf.data.obs.target[m[np.argmin(d)]]])
    assert all(len(v) == 1 for v in truth.values())
    assert len({next(iter(v)) for v in truth.values()}) == len(truth) == 100
    z = _z(res, sf)
    print({p: round(v, 2) for p, v in z.items()})
    assert all(abs(v) < 3.0 for v in z.values()), z


def test_free_network_with_two_scale_bars_gives_the_same_interior_orientation(sheet):
    sf, a, b = sheet["sf"], sheet["a"].result, sheet["b"].result
    assert a.datum["type"] == "weighted control" and b.datum["type"] == "free network"
    assert len(b.datum.get("scale_bars", [])) == 2
    for p in INTERIOR:
        d = (b.params[INDEX[p]] - a.params[INDEX[p]]) / a.sigma[p]
        print(f"{p}: control {a.params[INDEX[p]]:.7g} +- {a.sigma[p]:.2g}, free + 2 bars "
              f"{b.params[INDEX[p]]:.7g} +- {b.sigma[p]:.2g} ({d:+.3f} sigma)")
        assert abs(d) < 0.05                                 # the second bar is one redundant length
        assert abs(b.sigma[p] / a.sigma[p] - 1.0) < 0.01
    assert all(abs(v) < 3.0 for v in _z(b, sf).values())


def test_minimal_datums_give_the_interior_orientation_to_round_off(sheet):
    """Datum invariance on the photographs' final observations: the free network without a bar
    and with one (a minimal scale) give one interior orientation and one set of interior sigmas
    (the four weighted control points are 5 constraints more than minimal: their sigmas are
    7e-4 smaller here)."""
    data = sheet["b"].result.data
    index = data.targets.index()
    one = ScaleBars([index["1001"]], [index["1002"]], [900.0], [0.02])
    free = adjust_field(replace(data, scale_bars=None), AdjustmentOptions(datum="free"))
    bar = adjust_field(replace(data, scale_bars=one), AdjustmentOptions(datum="free"))
    for p in INTERIOR:
        # the same optimum within the adjustment's stopping rule (sigma_tol of a sigma; measured
        # 6e-5), the same sigmas to round-off (measured 4e-9)
        assert abs(bar.params[INDEX[p]] - free.params[INDEX[p]]) < AdjustmentOptions().sigma_tol * free.sigma[p]
        assert bar.sigma[p] == pytest.approx(free.sigma[p], rel=1e-6)


def test_scale_bars_join_between_targets_the_photos_hold(sheet, tmp_path):
    """From photographs the adjustment holds the targets found in the images: a bar to a listed
    unsurveyed plain target (which referencing names AR...) is not used, one between control
    points is; a bar naming an id targets.csv does not list is refused before measuring."""
    folder = sheet["folder_a"]
    data = sheet["a"].result.data
    bars = tmp_path / "scale_bars.csv"
    bars.write_text("from_id,to_id,length_mm,sigma_mm\n1001,1002,900.0,0.02\n2,3,100.0,0.02\n")
    session = replace(prepare(folder).session, scale_bars_path=bars)
    got = scale_bars_among(session, data.targets)
    index = data.targets.index()
    assert list(got.from_target) == [index["1001"]] and list(got.to_target) == [index["1002"]]
    (folder / "scale_bars.csv").write_text("from_id,to_id,length_mm,sigma_mm\n1001,X9,900.0,0.02\n")
    try:
        with pytest.raises(InputError, match="to_id 'X9' is not a target"):
            prepare(folder)
    finally:
        (folder / "scale_bars.csv").unlink()
