"""Prefect-native runs, against a real Prefect server through its API (issue 29, goal 1).

Two observation-only field sessions of one camera, the second made with a camera whose
principal distance grew by 50 um: both runs get their names and tags, publish their
artifacts (summary, residual statistics, links to the report and certificate, which exist in
the lake), and the second emits the camera-moved event. A storage option planted in the run
reaches none of its artifacts or logs.
"""

import dataclasses
import re
import time
from pathlib import Path
from urllib.parse import urlparse

import httpx
import pytest

from fieldcal.model.camera import INDEX, Camera, Sensor
from fieldcal.synthetic.field import WIDE_ANGLE, wide_field
from fieldcal.synthetic.session_writer import write_field_session
from flows.calibrate import calibrate_session
from flows.publish import MOVED_EVENT

pytestmark = [pytest.mark.slow]
PLANT = "planted-s3cr3t-4a1f"


@pytest.fixture(scope="module")
def runs(prefect_server, tmp_path_factory):
    """Both sessions calibrated into one lake: ``(api_url, lake, [result, result])``."""
    tmp = tmp_path_factory.mktemp("native")
    mp = pytest.MonkeyPatch()
    mp.setenv("FIELDCAL_REPORTS", "all")
    mp.setenv("FIELDCAL_HASH_CACHE", "off")
    truth = Camera.from_dict(Sensor(6000, 4000, 3.9), WIDE_ANGLE)
    moved = truth.params.copy()
    moved[INDEX["f_mm"]] += 0.050
    results = []
    for name, cam, acquired in (("2026-01-10-wall", truth, "2026-01-10"),
                                ("2026-06-10-wall", dataclasses.replace(truth, params=moved), "2026-06-10")):
        write_field_session(tmp / name, wide_field(seed=7, camera=cam), images=False, observations_csv=True,
                            camera_id="ixu-pn1", acquired=acquired)
        results.append(calibrate_session(str(tmp / name), str(tmp / "lake"), storage_options={"secret": PLANT}))
    mp.undo()
    return prefect_server, tmp / "lake", results


def _api(url, path, body):
    r = httpx.post(f"{url}{path}", json=body, timeout=30)
    r.raise_for_status()
    return r.json()


def test_runs_have_names_tags_and_artifacts_with_links_that_resolve(runs):
    url, lake, results = runs
    for result in results:
        name = f"calibrate/ixu-pn1/{result['session_id']} (field)"
        (run,) = _api(url, "/flow_runs/filter", {"flow_runs": {"name": {"any_": [name]}}})
        assert {"fieldcal", "camera:ixu-pn1", "method:field"} <= set(run["tags"])
        arts = _api(url, "/artifacts/filter", {"artifacts": {"flow_run_id": {"any_": [run["id"]]}}})
        by_key = {a["key"]: a for a in arts}
        assert set(by_key) == {"ixu-pn1-summary", "ixu-pn1-residuals", "ixu-pn1-report", "ixu-pn1-certificate"}
        summary = by_key["ixu-pn1-summary"]["data"]
        assert result["version"] in summary and "| f_mm |" in summary and "Verdict:" in summary
        images = result["images"]["total"]
        assert f"Images: {images - len(result['left_out'])} of {images} used" in summary
        table = by_key["ixu-pn1-residuals"]["data"]
        assert "rmse_px" in table and "n_used" in table
        for kind in ("report", "certificate"):
            link = re.fullmatch(r"\[.*\]\((.*)\)", by_key[f"ixu-pn1-{kind}"]["data"]).group(1)  # markdown
            path = Path(urlparse(link).path)
            assert path.is_file() and path.parent.name == result["version"] and lake in path.parents
        logs = _api(url, "/logs/filter", {"logs": {"flow_run_id": {"any_": [run["id"]]}}, "limit": 200})
        assert PLANT not in str(arts) and PLANT not in str(logs) and logs


def test_the_moved_camera_emits_an_event_and_the_first_run_does_not(runs):
    url, _, (first, second) = runs
    assert first["published"]["moved"] is False and second["published"]["moved"] is True
    assert second["published"]["verdict"] == "FAIL"
    deadline = time.monotonic() + 60
    while True:                      # events are written by the server's persister, in the background
        page = _api(url, "/events/filter", {"filter": {"event": {"name": [MOVED_EVENT]},
                                                       "occurred": {"since": "2020-01-01T00:00:00Z"}}, "limit": 50})
        events = [e for e in page["events"] if e["payload"].get("version") in (first["version"], second["version"])]
        if events or time.monotonic() > deadline:
            break
        time.sleep(1)
    (event,) = events
    assert event["resource"]["prefect.resource.id"] == "fieldcal.camera.ixu-pn1"
    assert event["payload"]["previous_version"] == first["version"] and event["payload"]["max_change_um"] > 2
    assert "f" in event["payload"]["changed"] and PLANT not in str(event)


def test_the_documented_automation_is_one_the_server_accepts(runs):
    import uuid

    import yaml
    from prefect import get_client
    from prefect.events.schemas.automations import AutomationCore

    root = Path(__file__).resolve().parents[2]
    (spec,) = yaml.safe_load((root / "deploy" / "automation-camera-moved.yaml").read_text())["automations"]
    spec["actions"][0]["block_document_id"] = str(uuid.uuid4())
    automation = AutomationCore.model_validate(spec)
    assert automation.trigger.expect == {MOVED_EVENT}
    with get_client(sync_client=True) as client:
        made = client.create_automation(automation)
        assert client.read_automation(made).name == "fieldcal camera moved"
