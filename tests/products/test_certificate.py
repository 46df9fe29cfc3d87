"""The calibration certificate: required content for a field and a goniometer calibration."""

import re

import numpy as np
import pytest

from fieldcal.errors import InputError
from fieldcal.model.camera import INDEX
from fieldcal.products import content
from fieldcal.products.certificate import DEFAULT_CONFIG, acceptance, load_config, write_certificate
from fieldcal.products.uncertainty import Calibration, radial_curve
from flows.cli import main
from tests.products.test_report import check_html, reports_lake


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return reports_lake(tmp_path_factory)


@pytest.fixture(scope="module")
def pages(shared, tmp_path_factory):
    out = tmp_path_factory.mktemp("certificates")
    lake, v = shared["lake_obj"], shared["versions"]
    return {k: write_certificate(lake, v[k], out / k).read_text() for k in ("f2", "d2", "g")}


def _text(page: str) -> str:
    return " ".join(re.sub(r"<[^>]+>", " ", page).split())


REQUIRED = ("1. Identity", "certificate number", "camera make / model / serial", "lens", "sensor",
            "method", "facility", "date of calibration", "date of issue", "valid until",
            "2. Calibrated interior orientation", "principal distance f", "principal point xp",
            "principal point yp", "principal point u0", "principal point v0", "value [mm]",
            "sigma [um]", "value [px]", "sigma [px]", "3. Lens distortion", "At field angles",
            "At radii", "radial distortion [um]", "decentering profile [um]", "Coefficients",
            "The model (fieldcal-brown/1)", "4. Correlations", "5. Adjustment and coverage",
            "sigma0", "redundancy", "6. Check points", "7. Change since the previous calibration",
            "8. Acceptance", "Verdict:")


@pytest.mark.parametrize("key", ["f2", "g"])
def test_certificate_holds_what_an_acceptance_asks_for(pages, shared, key):
    page = pages[key]
    c = check_html(page)
    assert c.errors == [] and c.doctype
    assert "@page { size: A4" in page and "http" not in page.split("</style>")[1]   # self-contained
    text = _text(page)
    for item in REQUIRED:
        assert item in text, item
    assert "No check points" in text                  # neither version withheld any
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"][key])
    # f in mm and in px, with sigmas in um and px
    f, sf = cal.camera.f_mm, cal.document["sigma"]["f_mm"]
    d = cal.sensor.pixel_mm
    assert f"{f:.6f}" in text and f"{1000 * sf:.2f}" in text
    assert f"{f / d:.3f}" in text and f"{sf / d:.3f}" in text
    u0 = (cal.sensor.width_px - 1) / 2 + cal.camera.params[INDEX["xp_mm"]] / d
    assert f"{u0:.3f}" in text
    # the radial distortion at the first field angle, -dr in um
    ang = content.field_angles_deg(cal)[0]
    dr, _ = radial_curve(cal, np.array([f * np.tan(np.radians(ang))]))
    assert f"{-1000 * dr[0]:+.2f}" in text
    if key == "g":
        assert "laboratory goniometer" in text and "No previous calibration" in text
        assert "observes the two scanned axes only" in text
    else:
        assert "field calibration" in text and "Against cam-f/f-jan" in text
        assert "principal distance" in text and "Holm" in text


def test_the_drifted_camera_fails_acceptance_on_its_change(pages):
    text = _text(pages["d2"])
    assert "significant change in" in text and "FLAGGED" in text
    row = re.search(r"change since the previous certificate .*? (PASS|FAIL)", text)
    assert row and row.group(1) == "FAIL"
    assert "Verdict: FAIL" in text


def test_redundancy_is_equations_minus_unknowns(shared):
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"]["f2"])
    st = cal.document["stats"]
    a = content.adjustment_figures(cal)
    assert a["n_equations"] == 2 * st["n_observations"]
    assert a["n_unknowns"] == 6 * st["n_images"] + 3 * st["n_surveys_rejected"] + len(cal.names)
    assert a["redundancy"] == a["n_equations"] - a["n_unknowns"] > 0
    g = content.adjustment_figures(Calibration.from_lake(shared["lake_obj"], shared["versions"]["g"]))
    gst = Calibration.from_lake(shared["lake_obj"], shared["versions"]["g"]).document["stats"]
    assert g["redundancy"] == gst["n_angles"] - gst["n_fitted"] - 6      # 3 unknowns per sweep


def test_acceptance_thresholds_come_from_the_config(shared, tmp_path):
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"]["f2"])
    res = shared["lake_obj"].read_residuals(shared["versions"]["f2"])
    base = acceptance(cal, res, load_config())
    assert base["verdict"] == "PASS"
    cfg = tmp_path / "strict.toml"
    cfg.write_text('[certificate]\nfacility = "Test range, Hall 2"\nvalidity_years = 2\n\n'
                   "[acceptance]\nmax_sigma_f_um = 1.0\nmax_check_rms_px = false\n")
    strict = acceptance(cal, res, load_config(cfg))
    rows = {r["criterion"]: r for r in strict["rows"]}
    assert rows["sigma of f"]["result"] == "FAIL" and strict["verdict"] == "FAIL"
    assert rows["check-point RMS (px)"]["threshold"] == "not set"
    assert load_config(cfg)["certificate"]["facility"] == "Test range, Hall 2"
    assert DEFAULT_CONFIG["acceptance"]["max_sigma_f_um"] == 10.0       # unchanged by loading


def test_check_points_in_the_document_are_shown_and_judged(shared):
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"]["f2"])
    doc = dict(cal.document, stats=dict(cal.document["stats"],
                                        check_points={"n": 40, "rms_px": 0.8, "rms_mm": 3.2}))
    with_cp = Calibration.from_document(doc, cal.names, cal.covariance)
    rows = {r["criterion"]: r for r in acceptance(with_cp, None, load_config())["rows"]}
    assert rows["check-point RMS (px)"]["result"] == "FAIL"           # 0.8 > 0.5 px
    assert rows["check-point RMS (mm)"]["result"] == "PASS"           # 3.2 <= 10 mm


@pytest.mark.parametrize("text, suffix, match", [
    ("[acceptance]\nmax_sigma_f_um = 'ten'\n", ".toml", "must be a number"),
    ("[acceptance]\nmax_sigma_g = 1\n", ".toml", "unknown key 'max_sigma_g'"),
    ("[nonsense]\n", ".toml", r"unknown section \[nonsense\]"),
    ("{not json", ".json", "not valid JSON"),
    ("max_sigma0 = [", ".toml", "not valid TOML"),
])
def test_a_bad_config_is_named_and_nothing_is_written(shared, tmp_path, capsys, text, suffix, match):
    cfg = tmp_path / f"c{suffix}"
    cfg.write_text(text)
    with pytest.raises(InputError, match=match):
        load_config(cfg)
    out = tmp_path / "out"
    rc = main(["certificate", shared["versions"]["f2"], "--lake", shared["lake"], "--out", str(out),
               "--config", str(cfg)])
    err = capsys.readouterr().err
    assert rc == 2 and str(cfg) in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_certificate_command_writes_the_page(shared, tmp_path, capsys):
    out = tmp_path / "cert"
    assert main(["certificate", "latest", "--camera", "cam-g", "--lake", shared["lake"],
                 "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out / "certificate.html")
    assert "goniometer" in (out / "certificate.html").read_text()
