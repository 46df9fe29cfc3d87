"""This round's session formats through ``fieldcal run`` on a session folder (CONTRACT section 3):
unsurveyed targets with ``scale_bars.csv`` and a free datum (issue 26), target normals in
``targets.csv`` (issue 23). The library paths are tested against truth in tests/field; here the
command line a user types reads them, calibrates and commits what the document says.
"""

import json

import numpy as np
import pytest
import tifffile
from scipy.spatial import cKDTree

from fieldcal import pipeline
from fieldcal.lake.store import Lake
from fieldcal.model.camera import INDEX
from fieldcal.synthetic.field import faceted_field, paper_field, wide_field
from fieldcal.synthetic.render import scaled_field
from fieldcal.synthetic.session_writer import write_field_session
from tests.flows.test_cli import UNREACHABLE, env_for, fieldcal

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_server")]


def _run(folder, tmp_path, prefect_server):
    lake, out = tmp_path / "lake", tmp_path / "doc.json"
    proc = fieldcal("run", folder, "--lake", lake, "--json", out, env=env_for(prefect_server, tmp_path),
                    cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(out.read_text())
    assert doc == Lake(lake).load_document(proc.stdout.strip())
    return doc


def test_run_calibrates_a_free_network_of_unsurveyed_targets_scaled_by_a_bar(tmp_path, prefect_server):
    sf = wide_field(seed=5)
    folder = tmp_path / "free"
    write_field_session(folder, sf, images=False, observations_csv=True, coded=False, camera_id="cam-free")
    X, t = sf.targets_true.xyz_m, sf.data.targets
    ends = [int(np.argmin(np.hypot(X[:, 0] - a, X[:, 2] - 2.0))) for a in (-1.5, 1.5)]
    rows = [f"{t.ids[j]},,,,," for j in ends]            # listed, unsurveyed; every other id unlisted
    (folder / "targets.csv").write_text("id,X,Y,Z,sigma_mm,code\n" + "\n".join(rows) + "\n")
    length_mm = np.linalg.norm(X[ends[1]] - X[ends[0]]) * 1e3
    (folder / "scale_bars.csv").write_text(
        f"from_id,to_id,length_mm,sigma_mm\n{t.ids[ends[0]]},{t.ids[ends[1]]},{length_mm:.4f},0.02\n")

    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["datum"] = "free"                  # the session's own choice (auto would pick it too)
    (folder / "session.json").write_text(json.dumps(manifest))

    doc = _run(folder, tmp_path, prefect_server)
    stats = doc["stats"]
    assert stats["datum"]["type"] == "free network"
    assert stats["n_unlisted_targets"] > 200
    for name in ("f_mm", "xp_mm", "yp_mm"):
        assert abs(doc["parameters"][name] - sf.camera.to_dict()[name]) < 4 * doc["sigma"][name], name


def test_run_corrects_eccentricity_with_the_normals_targets_csv_gives(tmp_path, prefect_server):
    sf = scaled_field(faceted_field(seed=0), 0.2)
    folder = tmp_path / "faceted"
    info = write_field_session(folder, sf, image_indices=list(range(0, 24, 3)) + [1, 7, 13, 19], coded=True,
                               psf_sigma_px=1.5, illumination_gradient=0.5, noise=True, compression_mix=False,
                               normals="columns", camera_id="cam-facets")
    header = (folder / "targets.csv").read_text().splitlines()[0]
    assert header.endswith(",nx,ny,nz")
    assert all(tifffile.imread(folder / n).size for n in info["images"])

    doc = _run(folder, tmp_path, prefect_server)
    prepared = pipeline.prepare(folder)                     # the same session through the library
    meas = {n: pipeline.measure(prepared, n) for n in prepared.to_measure}
    library = pipeline.solve(prepared, meas, fingerprint_=pipeline.input_fingerprint(prepared, {})).document
    assert doc["parameters"] == library["parameters"] and doc["sigma"] == library["sigma"]
    ecc = doc["stats"]["eccentricity"]
    assert ecc["normals"] == "given" and ecc["max_px"] > 0.0
    z = (doc["parameters"]["f_mm"] - sf.camera.f_mm) / doc["sigma"]["f_mm"]
    assert abs(z) < 1.5, z


def _blank(folder, coded_every: int, plain_every: int):
    """Empty X, Y, Z and sigma of every ``coded_every``-th coded and every ``plain_every``-th
    plain row of targets.csv (unsurveyed, CONTRACT section 3); returns their ids (coded, plain)."""
    lines = (folder / "targets.csv").read_text().splitlines()
    out, blank = [lines[0]], {True: [], False: []}
    count = {True: 0, False: 0}
    for line in lines[1:]:
        f = line.split(",")
        coded = bool(f[5].strip())
        count[coded] += 1
        if count[coded] % (coded_every if coded else plain_every) == 0:
            blank[coded].append(f[0])
            f[1:5] = ["", "", "", ""]
        out.append(",".join(f))
    (folder / "targets.csv").write_text("\n".join(out) + "\n")
    return blank[True], blank[False]


def test_run_on_photographs_adjusts_the_unsurveyed_coded_and_plain_targets_of_targets_csv(tmp_path, prefect_server):
    """Issue 26 from photographs: half the coded targets and a quarter of the plain ones have no
    coordinates in targets.csv. The images are oriented from the surveyed ones; the coded ones
    join by their code, the plain ones' discs by automatic referencing (on because targets.csv
    lists unsurveyed plain targets); all are adjusted, near their truth."""
    sf = scaled_field(paper_field(), 0.25)
    folder = tmp_path / "unsurveyed"
    write_field_session(folder, sf, coded=True, image_indices=[12 * s + a for s in range(6)
                                                              for a in (s % 4, 4 + (s + 1) % 4)],
                        camera_id="cam-unsurveyed")
    coded, plain = _blank(folder, 2, 4)

    doc = _run(folder, tmp_path, prefect_server)
    stats, truth = doc["stats"], sf.targets_true
    rows = {r["id"]: r for r in stats["unsurveyed_targets"]}
    index = truth.index()
    # the coded ones: under their own ids, within 4 sigma of the truth
    got = [c for c in coded if c in rows]
    assert stats["coded_unsurveyed_targets"] == len(got) >= 5
    z = [np.abs(np.array(rows[c]["xyz_m"]) - truth.xyz_m[index[c]]) / (np.array(rows[c]["sigma_mm"]) / 1e3)
         for c in got]
    assert np.max(z) < 4.0
    # the plain ones: found by referencing (AR...), each a distinct unsurveyed plain target of the truth
    ar = [r for k, r in rows.items() if k.startswith("AR")]
    assert stats["referenced_targets"] == len(ar) > 20
    X = np.array([r["xyz_m"] for r in ar])
    _, j = cKDTree(truth.xyz_m).query(X)
    assert len(set(j)) == len(j) and set(truth.ids[j]) <= set(plain)
    z = np.abs(X - truth.xyz_m[j]) / (np.array([r["sigma_mm"] for r in ar]) / 1e3)
    assert np.mean(z.max(axis=1) < 4.0) > 0.95
    # the interior orientation within 4 sigma of the truth
    for name in ("f_mm", "xp_mm", "yp_mm", "k1"):
        assert abs(doc["parameters"][name] - sf.camera.to_dict()[name]) < 4 * doc["sigma"][name], name


def test_a_strict_session_refuses_an_unlisted_id_in_one_line_before_any_server(tmp_path):
    folder = tmp_path / "strict"
    write_field_session(folder, wide_field(seed=6), images=False, observations_csv=True, coded=False)
    lines = (folder / "targets.csv").read_text().splitlines()
    missing = lines.pop(5).split(",")[0]                 # a target the observations still name
    (folder / "targets.csv").write_text("\n".join(lines) + "\n")
    manifest = json.loads((folder / "session.json").read_text())
    manifest["field"]["strict_targets"] = True
    (folder / "session.json").write_text(json.dumps(manifest))
    lake = tmp_path / "lake"
    proc = fieldcal("run", folder, "--lake", lake, env=env_for(UNREACHABLE, tmp_path), cwd=tmp_path)
    assert proc.returncode == 2 and proc.stdout == ""
    assert len(proc.stderr.splitlines()) == 1, proc.stderr
    assert "observations.csv:" in proc.stderr and f"target_id '{missing}' is not in targets.csv" in proc.stderr
    assert not lake.exists()


def test_run_on_the_dbat_photos_with_only_four_marked_control_points(tmp_path, prefect_server):
    """The thin-survey route (issue 26 goal 6) through the command line: marks.csv with the four
    control points per photo, the 96 other discs found by referencing; the document counts them
    and gives the library's camera (tests/field/test_dbat_thin.py checks it against PhotoModeler)."""
    from tests.realdata import write_dbat_photo_session

    folder = tmp_path / "dbat-thin"
    write_dbat_photo_session(folder, None, list_plain=True)
    doc = _run(folder, tmp_path, prefect_server)
    stats = doc["stats"]
    assert stats["referenced_targets"] == 96 and stats["identification"]["used"] == 21
    assert stats["identification"]["started_from"] == {"resection from marks": 21}
    assert stats["datum"]["type"] == "weighted control"
    prepared = pipeline.prepare(folder)
    meas = {n: pipeline.measure(prepared, n) for n in prepared.to_measure}
    lib = pipeline.solve(prepared, meas, fingerprint_="lib").result
    for name in ("f_mm", "xp_mm", "yp_mm", "k1"):
        assert doc["parameters"][name] == pytest.approx(lib.params[INDEX[name]], rel=1e-9), name
