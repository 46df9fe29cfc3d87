"""The fleet dashboard (issue 29, goal 3): what it says, and the site in headless Chromium.

The lake is the reports' (:func:`tests.products.test_report.reports_lake`): ``cam-d`` moved
(f + 20 um, k1 + 3 %) and fails its acceptance on that change, ``cam-f`` was calibrated twice
without change, ``cam-g`` once. Seen on 2029-06-11, ``cam-f``'s certificate (calibrated
2026-06-10, valid 3 years) has expired and ``cam-d``'s (2026-06-12) has not.
"""

import datetime as dt
import re
import shutil
import subprocess
from urllib.parse import unquote

import pytest

from fieldcal.lake.store import Lake
from fieldcal.products import status
from fieldcal.products.certificate import write_certificate
from fieldcal.products.dashboard import fleet_state, write_dashboard
from flows.publish import reports_folder
from tests.products.test_report import reports_lake

SEEN = dt.date(2029, 6, 11)
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A copy of the reports' lake, filled, with cam-f's latest certificate published, and its site."""
    shared = reports_lake(tmp_path_factory)
    root = tmp_path_factory.mktemp("dashboard")
    shutil.copytree(shared["lake"], root / "lake")
    lake = Lake(root / "lake")
    status.fill(lake)
    v = shared["versions"]["f2"]
    with __import__("tempfile").TemporaryDirectory() as tmp:
        page = write_certificate(lake, v, tmp)
        lake.storage.write(f"{reports_folder('cam-f', 'f-jun', v)}/certificate.html", page.read_bytes())
    got = write_dashboard(lake, root / "site", today=SEEN)
    return {"lake": lake, "versions": shared["versions"], "out": root / "site", "got": got}


def test_the_fleet_state_counts_what_moved_expired_and_failed(site):
    got, v = site["got"], site["versions"]
    assert (got["cameras"], got["moved"], got["expired"], got["failed"]) == (3, 1, 1, 1)
    cams = {c.camera_id: c for c in fleet_state(site["lake"], today=SEEN)}
    d, f, g = cams["cam-d"], cams["cam-f"], cams["cam-g"]
    assert d.moved and d.verdict == "FAIL" and d.change["version_a"] == v["d1"] and not d.expired
    assert not f.moved and f.expired and f.days_left == -1 and f.latest["version"] == v["f2"]
    assert g.change is None and g.days_left > 0
    index = (site["out"] / "index.html").read_text()
    assert index.count("<tr data-") == 3 and 'data-moved="yes"' in index
    assert (site["out"] / "cameras" / "cam-d.html").read_text().count("<svg") == 4


def _chromium(*args, tmp):
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={tmp}",
           "--hide-scrollbars", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=True).stdout


@pytest.mark.slow
def test_the_site_loads_in_chromium_filters_and_its_links_resolve(site, tmp_path):
    if CHROMIUM is None:
        print("skipped: no chromium on PATH (Debian's chromium; .ci/run installs it)")
        pytest.skip("no chromium on PATH")
    out = site["out"]
    index = (out / "index.html").as_uri()
    dom = _chromium("--dump-dom", index + "#moved", tmp=tmp_path / "a")
    assert re.search(r'<span id="shown">1</span>', dom)                 # the filter ran: cam-d only
    assert re.search(r'<span id="n-moved">1</span> moved, <span id="n-expired">1</span> expired', dom)
    hidden = re.findall(r'<tr data-[^>]*?(hidden="")?>', dom)
    assert len(hidden) == 3 and sum(bool(h) for h in hidden) == 2
    dom = _chromium("--dump-dom", index + "#expired,failed", tmp=tmp_path / "b")
    assert '<span id="shown">0</span>' in dom                           # none expired and failed
    pages = [out / "index.html", *sorted((out / "cameras").glob("*.html"))]
    links = 0
    for page in pages:
        for href in re.findall(r'href="([^"#]+)"', page.read_text()):
            assert (page.parent / unquote(href)).resolve().is_file(), (page, href)
            links += 1
    assert links >= 3 + 3 + 2                  # camera pages, their way back, cam-f's certificate twice
    shot = tmp_path / "index.png"
    _chromium("--window-size=1300,400", f"--screenshot={shot}", index, tmp=tmp_path / "c")
    assert shot.stat().st_size > 10_000
