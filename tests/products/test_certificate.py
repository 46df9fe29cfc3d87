"""The calibration certificate: required content for a field and a goniometer calibration."""

import re

import numpy as np
import pytest

from fieldcal.analysis.uncertainty import Calibration, radial_curve
from fieldcal.errors import InputError
from fieldcal.model.camera import INDEX
from fieldcal.products import content
from fieldcal.products.certificate import DEFAULT_CONFIG, acceptance, load_config, write_certificate
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


REQUIRED = ("1. Identity", "certificate number", "camera make / model / serial", "lens", "focus / aperture",
            "sensor", "method", "facility", "issued by", "date of calibration", "date of issue", "valid until",
            "2. Calibrated interior orientation", "principal distance f", "principal point xp",
            "principal point yp", "principal point u0", "principal point v0", "value [mm]",
            "u [µm]", "U (k = 2) [µm]", "value [px]", "u [px]", "Focal lengths",
            "effective focal length f / (1 + k0)", "calibrated focal length c, distortion balanced to",
            "3. Lens distortion", "Radial distortion per semi-diagonal, relative to the calibrated focal length c",
            "upper right (+x, +y) [µm]", "lower left (-x, -y) [µm]", "field angle [°]", "<svg",
            "radial distortion [µm]", "decentering profile [µm]", "Coefficients",
            "The model (fieldcal-brown/1)", "4. Correlations", "5. Adjustment and coverage",
            "σ0", "redundancy", "6. Check points", "7. Traceability, procedure and conditions",
            "reference of the scale", "procedure", "Environmental conditions during the calibration",
            "temperature", "relative humidity", "coverage factor k = 2", "8. Change since the previous calibration",
            "9. Acceptance", "Verdict:", "calibrated by", "approved by")


@pytest.mark.parametrize("key", ["f2", "g"])
def test_certificate_holds_what_an_acceptance_asks_for(pages, shared, key):
    page = pages[key]
    c = check_html(page)
    assert c.errors == [] and c.doctype
    assert "@page { size: A4" in page and "http" not in page.split("</style>")[1]   # self-contained
    text = _text(page)
    for item in REQUIRED:
        assert item in (page if item == "<svg" else text), item
    assert "No check points" in text                  # neither version withheld any
    assert " um" not in text and "+-" not in text and " deg" not in text     # units as symbols
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"][key])
    # f in mm and in px, with u in um and px and U = 2 u
    f, sf = cal.camera.f_mm, cal.document["sigma"]["f_mm"]
    d = cal.sensor.pixel_mm
    assert f"{f:.6f}" in text and f"{1000 * sf:.2f}" in text and f"{2000 * sf:.2f}" in text
    assert f"{f / d:.3f}" in text
    u0 = (cal.sensor.width_px - 1) / 2 + cal.camera.params[INDEX["xp_mm"]] / d
    assert f"{u0:.3f}" in text
    # the model's radial distortion at the first round radius, -dr in um
    r0 = content.radii_mm(cal)[0]
    dr, _ = radial_curve(cal, np.array([r0]))
    assert f"{-1000 * dr[0]:+.2f}" in text
    k0 = cal.camera.params[INDEX["k0"]]
    assert f"{f / (1 + k0):.6f}" in text
    if key == "g":
        assert "laboratory goniometer" in text and "No previous calibration" in text
        assert "observes the two scanned axes only" in text
        assert f"a scale of {100 * abs(k0):.2f} %" in text
    else:
        assert "field calibration" in text and "Against cam-f/f-jan" in text
        assert "principal distance" in text and "Holm" in text
        assert "k0 held at 0 (field method): f is also the effective focal length" in text


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
    assert rows["σ of f"]["result"] == "FAIL" and strict["verdict"] == "FAIL"
    assert rows["check-point RMS (px)"]["threshold"] == "not set"
    assert load_config(cfg)["certificate"]["facility"] == "Test range, Hall 2"
    assert DEFAULT_CONFIG["acceptance"]["max_sigma_f_um"] == 10.0       # unchanged by loading


def test_check_points_in_the_document_are_shown_and_judged(shared):
    cal = Calibration.from_lake(shared["lake_obj"], shared["versions"]["f2"])
    doc = dict(cal.document, stats=dict(cal.document["stats"],
                                        check_points={"n": 40, "rms_px": 0.8, "rms_mm": 3.2}))
    with_cp = Calibration.from_document(doc, cal.names, cal.covariance)
    rows = {r["criterion"]: r for r in acceptance(with_cp, None, load_config())["rows"]}
    assert rows["check-point RMS (px)"]["result"] == "not assessed"   # off by default: the survey dominates it
    assert rows["check-point RMS (mm)"]["result"] == "PASS"           # 3.2 <= 10 mm
    cfg = load_config()
    cfg["acceptance"]["max_check_rms_px"] = 0.5
    rows = {r["criterion"]: r for r in acceptance(with_cp, None, cfg)["rows"]}
    assert rows["check-point RMS (px)"]["result"] == "FAIL"           # 0.8 > 0.5 px


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


# --------------------------------------------------------------------------------------
# identity, strictness, no overwriting (issue 30)
# --------------------------------------------------------------------------------------
FULL = ('[certificate]\norganisation = "Agency X"\nfacility = "Range B"\ncamera = "Cam 24, sn 42"\n'
        'lens = "24 mm f/2.8, sn 7"\noperator = "A. Operator"\n[traceability]\ninstrument = "TS16, sn 3"\n'
        'date = "2026-05-02"\naccuracy = "5 mm (1 sigma)"\nprocedure = "QP-12 rev. 3"\n'
        '[conditions]\nfocus = "infinity, taped"\naperture = "f/8"\ntemperature_c = 18.5\n')


def test_missing_identity_is_warned_about_and_refused_with_strict(shared, tmp_path, capsys):
    v, lake = shared["versions"]["f2"], shared["lake"]
    assert main(["certificate", v, "--lake", lake, "--out", str(tmp_path / "a")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fieldcal certificate: warning: not stated: [certificate] camera, "
                                               "[certificate] lens, [certificate] facility")
    assert "--strict refuses" in err[0]
    rc = main(["certificate", v, "--lake", lake, "--out", str(tmp_path / "b"), "--strict"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "--strict: not stated: [certificate] camera" in err[0]
    assert not (tmp_path / "b").exists()
    cfg = tmp_path / "full.toml"
    cfg.write_text(FULL)
    assert main(["certificate", v, "--lake", lake, "--out", str(tmp_path / "c"), "--config", str(cfg),
                 "--strict"]) == 0
    assert capsys.readouterr().err == ""
    text = _text((tmp_path / "c" / "certificate.html").read_text())
    for item in ("Agency X", "Range B", "Cam 24, sn 42", "24 mm f/2.8, sn 7", "infinity, taped / f/8",
                 "TS16, sn 3", "2026-05-02", "5 mm (1 sigma)", "QP-12 rev. 3; self-calibrating bundle",
                 "18.5 °C", "A. Operator"):
        assert item in text, item
    assert "not stated" in text                   # humidity and pressure were not given
    cfg.write_text(FULL + "[certificate]\n")     # a duplicate section: TOML refuses it
    with pytest.raises(InputError, match="not valid TOML"):
        load_config(cfg)
    cfg.write_text('[certificate]\nstrict = "yes"\n')
    with pytest.raises(InputError, match="strict must be true or false"):
        load_config(cfg)


def test_an_existing_certificate_is_not_overwritten(shared, tmp_path, capsys):
    v, lake = shared["versions"]["g"], shared["lake"]
    out = tmp_path / "cert"
    assert main(["certificate", v, "--lake", lake, "--out", str(out)]) == 0
    before = (out / "certificate.html").read_bytes()
    capsys.readouterr()
    assert main(["certificate", v, "--lake", lake, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "certificate.html exists there: fieldcal does not overwrite" in err[0]
    assert (out / "certificate.html").read_bytes() == before and sorted(p.name for p in out.iterdir()) == [
        "certificate.html"]


# --------------------------------------------------------------------------------------
# check points from `fieldcal synth --check-points`, and the PDF
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def checked(tmp_path_factory):
    """A wide-angle observation-only session with 20 check points, as `fieldcal synth` writes it."""
    from fieldcal import pipeline
    from fieldcal.lake.store import Lake
    from flows.synth import write_synthetic

    root = tmp_path_factory.mktemp("checked")
    write_synthetic(root / "s", "field", scenario="wide", seed=4, check_points=20)
    p = pipeline.prepare(root / "s")
    out = pipeline.solve(p, {}, fingerprint_=pipeline.input_fingerprint(p, {}))
    lake = Lake(root / "lake")
    return lake, lake.commit(out.document, out.arrays, out.residuals, array_attrs=out.array_attrs), root


def test_synthetic_check_points_are_assessed_in_x_y_z(checked, tmp_path):
    lake, v, root = checked
    import json as _json

    manifest = _json.loads((root / "s" / "session.json").read_text())
    assert len(manifest["check_points"]) == 20
    cp = lake.load_document(v)["stats"]["check_points"]
    assert cp["n_withheld"] == 20 and cp["n"] >= 15
    page = write_certificate(lake, v, tmp_path / "c").read_text()
    text = _text(page)
    for a in "xyz":
        assert f"{a.upper()} {cp[f'rms_{a}_mm']:.2f} {cp[f'mean_{a}_mm']:+.2f} {cp[f'max_{a}_mm']:.2f}" in text
    assert f"3-D {cp['rms_mm']:.2f}" in text and "No check points" not in text
    rows = {r["criterion"]: r for r in acceptance(Calibration.from_lake(lake, v), lake.read_residuals(v),
                                                  load_config())["rows"]}
    assert rows["check-point RMS (mm)"]["result"] == "PASS"       # 5 mm survey noise: about 8.7 mm 3-D
    assert rows["check points within their predicted accuracy (chi-square p)"]["result"] == "PASS"


def _tools():
    import shutil

    from fieldcal.products.pdf import CANDIDATES

    missing = [t for t in ("pdftoppm", "pdftotext", "pdfinfo") if shutil.which(t) is None]
    if not any(shutil.which(c) for c in CANDIDATES):
        missing.append("chromium")
    if missing:
        pytest.skip(f"needs {', '.join(missing)} (Debian: apt-get install chromium poppler-utils; .ci/run does)")


def test_the_pdf_is_a4_numbered_and_keeps_the_verdict_with_the_signatures(checked, tmp_path, capsys):
    import subprocess

    _tools()
    lake, v, _ = checked
    out = tmp_path / "pdf"
    assert main(["certificate", v, "--lake", str(lake.url), "--out", str(out), "--pdf"]) == 0
    assert capsys.readouterr().out.split() == [str(out / "certificate.html"), str(out / "certificate.pdf")]
    pdf = out / "certificate.pdf"
    info = subprocess.run(["pdfinfo", str(pdf)], capture_output=True, text=True, check=True).stdout
    n = int(re.search(r"Pages:\s+(\d+)", info).group(1))
    assert 3 <= n <= 7
    w, h = (float(x) for x in re.search(r"Page size:\s+([\d.]+) x ([\d.]+) pts", info).groups())
    assert (w, h) == pytest.approx((595.3, 841.9), abs=1.0)                       # A4 in points
    pages = []
    for i in range(1, n + 1):
        pages.append(subprocess.run(["pdftotext", "-layout", "-f", str(i), "-l", str(i), str(pdf), "-"],
                                    capture_output=True, text=True, check=True).stdout)
        assert f"Certificate No. {v}" in pages[-1], i                             # on every page
        assert re.search(rf"Page {i} of {n}\b", pages[-1]), i
    assert any(f"Certificate No. {v}" in line and "Camera calibration certificate" not in line
               for line in pages[0].splitlines())                                  # the id whole, on a line
    final = [i for i, p in enumerate(pages) if "9. Acceptance" in p]
    assert final and "Verdict:" in pages[final[0]] and "approved by" in pages[final[0]]
    assert sum("8. Change since the previous calibration" in p for p in pages) == 1
    subprocess.run(["pdftoppm", "-r", "20", "-png", str(pdf), str(tmp_path / "page")], check=True)
    from PIL import Image

    images = sorted(tmp_path.glob("page-*.png"))
    assert len(images) == n
    for im in images:
        with Image.open(im) as page:
            assert page.size[1] / page.size[0] == pytest.approx(297 / 210, rel=0.02)
            assert page.convert("L").getextrema()[0] < 100                        # something printed
    assert main(["certificate", v, "--lake", str(lake.url), "--out", str(out), "--pdf"]) == 2   # no overwriting


def test_numbers_keep_their_significant_digits():
    """Three decimals printed good residuals as 0.000 (issue 30)."""
    assert [content.sig(x) for x in (0.0412345, 0.000123, 1.0, 12.345, 0.1)] == ["0.0412", "0.000123", "1.00",
                                                                                 "12.3", "0.100"]
    assert content.residual_format(0.00573, 0.0213) == "0.00573 px RMS, max 0.0213 px"
    assert content.sig(None) == content.sig(float("nan")) == "—"
