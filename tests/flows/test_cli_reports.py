"""The report / compare / export / undistort commands and history --plot / --fleet, through
``flows.cli.main`` on the shared lake of versions made from synthetic sessions."""

import json
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
import tifffile

from fieldcal.analysis.uncertainty import Calibration
from fieldcal.products.export import EXACT_PX, normalised_rays
from fieldcal.products.report import GONIOMETER_FIGURES
from flows.cli import main
from tests.products.test_report import check_html, reports_lake


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return reports_lake(tmp_path_factory)


@pytest.fixture
def lake_env(shared, monkeypatch):
    monkeypatch.setenv("FIELDCAL_LAKE", shared["lake"])
    monkeypatch.delenv("FIELDCAL_STORAGE_OPTIONS", raising=False)
    return shared


def test_report_latest_writes_the_html_and_the_plots(lake_env, tmp_path, capsys):
    out = tmp_path / "rep"
    assert main(["report", "latest", "--camera", "cam-g", "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out / "report.html")
    c = check_html((out / "report.html").read_text())
    assert c.errors == [] and len(c.figures) == len(GONIOMETER_FIGURES)
    assert sorted(p.name for p in out.glob("*.png")) == sorted(f"{n}.png" for n in GONIOMETER_FIGURES)


def test_compare_text_json_and_plot(lake_env, tmp_path, capsys):
    v = lake_env["versions"]
    assert main(["compare", v["d1"], v["d2"], "--plot", str(tmp_path / "c.png")]) == 0
    text = capsys.readouterr().out
    assert "FLAGGED" in text and "Holm" in text
    # one line per quantity tested, each change in one unit with its sigma
    for label in ("principal distance: change", "principal point (xp, yp): change",
                  "radial distortion at the edge of the field", "correction field over the sensor"):
        assert label in text, label
    assert "µm; chi2" in text and "px (1 σ up to" in text and " um" not in text
    assert (tmp_path / "c.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["compare", "previous", "latest", "--camera", "cam-f", "--format", "json",
                 "--out", str(tmp_path / "c.json")]) == 0
    s = json.loads((tmp_path / "c.json").read_text())
    assert (s["version_a"], s["version_b"]) == (v["f1"], v["f2"])
    assert s["flagged"] is False and s["dof"] >= 9
    assert [t["key"] for t in s["tests"]] == ["f", "principal_point", "edge_distortion", "map"]
    assert s["max_um"] == pytest.approx(s["max_px"] * s["pixel_size_um"])
    assert s["rms_um"] <= s["max_um"]


def test_export_json_to_stdout_is_the_document(lake_env, capsys):
    v = lake_env["versions"]["f1"]
    assert main(["export", v, "--format", "json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc == lake_env["lake_obj"].load_document(v)


def test_export_opencv_to_a_file_reports_the_fit_on_stderr(lake_env, tmp_path, capsys):
    out = tmp_path / "cam.yml"
    assert main(["export", "latest", "--camera", "cam-g", "--format", "opencv", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "fit residual" in err and "round trip through cv2.undistortPoints" in err
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    K, dist = fs.getNode("camera_matrix").mat(), fs.getNode("distortion_coefficients").mat()
    fs.release()
    cal = Calibration.from_lake(lake_env["lake_obj"], lake_env["versions"]["g"])
    pts = np.random.default_rng(3).uniform([0, 0], [1803, 1352], (2000, 2))
    n = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, dist).reshape(-1, 2)
    err_px = np.hypot(*((n - normalised_rays(cal.camera, pts)) * K[0, 0]).T)
    assert err_px.max() <= EXACT_PX


def test_export_metashape_and_colmap(lake_env, tmp_path, capsys):
    assert main(["export", "latest", "--camera", "cam-g", "--format", "metashape",
                 "--out", str(tmp_path / "c.xml")]) == 0
    assert ET.parse(tmp_path / "c.xml").getroot().findtext("projection") == "frame"
    assert main(["export", "latest", "--camera", "cam-g", "--format", "colmap"]) == 0
    lines = [x for x in capsys.readouterr().out.splitlines() if x and not x.startswith("#")]
    assert len(lines) == 1 and lines[0].split()[1] in ("OPENCV", "FULL_OPENCV")


def test_export_strict_refuses_an_inexact_export(lake_env, tmp_path, capsys):
    # OpenCV's four-coefficient model cannot hold the paper camera to 0.01 px
    v = lake_env["versions"]["f1"]
    out = tmp_path / "x.txt"
    assert main(["export", v, "--format", "opencv", "--model", "brown4", "--strict",
                 "--out", str(out)]) == 3
    err = capsys.readouterr().err
    assert "cannot be that exact" in err and "refused" in err
    assert not out.exists()


def test_undistort_writes_the_corrected_image(lake_env, tmp_path, capsys):
    img = np.random.default_rng(0).integers(0, 4000, (1353, 1804), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "in.tif", img)
    assert main(["undistort", "latest", "--camera", "cam-g", str(tmp_path / "in.tif"),
                 str(tmp_path / "out.tif")]) == 0
    assert "corrected image 1804 x 1353 px" in capsys.readouterr().out
    out = tifffile.imread(tmp_path / "out.tif")
    assert out.shape == img.shape and out.dtype == img.dtype


def test_history_plot_and_fleet(lake_env, tmp_path, capsys):
    png = tmp_path / "h.png"
    assert main(["history", "--camera", "cam-d", "--plot", str(png), "--param", "k1"]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    capsys.readouterr()
    assert main(["history", "--fleet", "--format", "json", "--plot", str(tmp_path / "f.png")]) == 0
    rows = {r["camera_id"]: r for r in json.loads(capsys.readouterr().out)}
    assert rows["cam-d"]["flagged"] is True and rows["cam-f"]["flagged"] is False
    assert (tmp_path / "f.png").exists()
    # without --plot / --fleet the plain history runs as before
    assert main(["history", "--camera", "cam-f", "--format", "json"]) == 0
    assert len(json.loads(capsys.readouterr().out)) == 2


def test_errors_are_one_line_naming_the_command_once(lake_env, monkeypatch, tmp_path, capsys):
    assert main(["report", "latest"]) == 2
    assert capsys.readouterr().err == "fieldcal report: 'latest' needs --camera ID\n"
    assert main(["export", "latest", "--camera", "nobody", "--format", "json"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fieldcal export: camera 'nobody' has no calibration in ") and "camera(s): cam-" in err
    assert main(["compare", "20990101T000000Z-00000000-0000", "latest", "--camera", "cam-f"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fieldcal compare: no version '20990101T000000Z-00000000-0000' in ")
    assert "fieldcal compare: fieldcal" not in err and err.count("\n") == 1
    no = tmp_path / "no"
    assert main(["export", "latest", "--camera", "cam-f", "--format", "json", "--out", str(no / "x.json")]) == 2
    assert capsys.readouterr().err == f"fieldcal export: --out {no / 'x.json'}: no folder {no}\n"
    monkeypatch.delenv("FIELDCAL_LAKE")
    assert main(["report", "x"]) == 2
    assert capsys.readouterr().err == "fieldcal report: no lake: give --lake LAKE or set FIELDCAL_LAKE\n"


def test_undistort_refuses_to_write_over_its_input(lake_env, tmp_path, capsys):
    img = np.random.default_rng(1).integers(0, 4000, (1353, 1804), dtype=np.uint16)
    raw = tmp_path / "raw.tif"
    tifffile.imwrite(raw, img)
    before = raw.read_bytes()
    (tmp_path / "sub").mkdir()
    (tmp_path / "link.tif").hardlink_to(raw)
    for out in (raw, tmp_path / "sub" / ".." / "raw.tif", tmp_path / "link.tif"):
        assert main(["undistort", "latest", "--camera", "cam-g", str(raw), str(out)]) == 2
        err = capsys.readouterr().err
        assert err == (f"fieldcal undistort: OUT {out} is the input image {raw} (the same file): refusing to "
                       "overwrite the photograph\n")
    assert raw.read_bytes() == before
