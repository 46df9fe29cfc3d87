"""What a calibration run shows in Prefect: its name, tags, artifacts and the "camera moved" event.

- **Names**: a calibration run is ``calibrate/<camera>/<session> (<method>)``
  (:func:`calibrate_run_name`, from the session's ``session.json`` when the run is created);
  a fleet run ``fleet/<root>/<UTC time>`` (:func:`fleet_run_name`).
- **Tags** (:func:`label_run`, once the session is validated): ``fieldcal``,
  ``camera:<id>``, ``method:<field|goniometer>``, ``rig:<id>`` for a rig session, so that
  the UI's filters find a camera's runs.
- **Artifacts** (:func:`publish_version`, after the commit; keyed by camera, so the UI keeps
  each camera's history of them): a markdown summary (parameters with sigmas, the verdict,
  images used and left out), the residual statistics per image as a table, and links to
  the certificate and the report, which the run writes into the lake beside the version
  (``LAKE/reports/<camera>/<session>/<version>/``; :func:`reports_wanted`: the certificate
  by default, ``FIELDCAL_REPORTS=all`` the report too, ``off`` neither).
  Nothing of the storage options is ever put into an artifact: only the lake's URL.
- **Event**: when the version's change test against the camera's previous calibration
  (:mod:`fieldcal.products.status`, at the default level and tolerance) flags it, the run
  emits :data:`MOVED_EVENT` with the camera as its resource; a Prefect automation can notify
  someone (``deploy/automation-camera-moved.yaml``).
"""

from __future__ import annotations

import datetime as dt
import json
import math
import os
import re
import tempfile
from pathlib import Path

from prefect import get_run_logger, task
from prefect.artifacts import create_link_artifact, create_markdown_artifact, create_table_artifact
from prefect.cache_policies import NO_CACHE

from fieldcal.errors import InputError, LakeError, one_line
from fieldcal.lake.store import Lake

__all__ = ["calibrate_run_name", "fleet_run_name", "run_tags", "label_run", "publish_version", "MOVED_EVENT",
           "REPORTS_ENV", "reports_folder", "reports_wanted"]

MOVED_EVENT = "fieldcal.camera.moved"
"""The event of a camera whose change test flags it (resource ``fieldcal.camera.<id>``)."""
REPORTS_ENV = "FIELDCAL_REPORTS"
"""What a run writes into the lake besides the version: ``certificate`` (default), ``all``, ``off``."""


# --------------------------------------------------------------------------------------
# names and tags
# --------------------------------------------------------------------------------------
def _identity(folder) -> dict:
    """``camera_id``, ``session_id``, ``method``, ``rig_id`` from ``folder/session.json``
    (what is readable of it; the validation reports what is wrong)."""
    from fieldcal.session.loader import default_session_id

    try:
        manifest = json.loads((Path(folder) / "session.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        manifest = {}
    manifest = manifest if isinstance(manifest, dict) else {}
    rig = manifest.get("rig") if isinstance(manifest.get("rig"), dict) else {}
    sid = manifest.get("session_id")
    return {"camera_id": manifest.get("camera_id") or rig.get("rig_id"),
            "session_id": sid if isinstance(sid, str) else default_session_id({}, folder),
            "method": manifest.get("method"), "rig_id": rig.get("rig_id")}


def _name(camera_id, session_id, method) -> str:
    return f"calibrate/{camera_id or '?'}/{session_id or '?'}" + (f" ({method})" if method else "")


def calibrate_run_name() -> str:
    """The name of a calibration flow run (module docstring), from its ``session`` parameter."""
    from prefect.runtime import flow_run

    ident = _identity(str(flow_run.parameters.get("session", "session")))
    return _name(ident["camera_id"], ident["session_id"], ident["method"])


def fleet_run_name() -> str:
    """``fleet/<root folder name>/<scheduled start, UTC, to the minute>``."""
    from prefect.runtime import flow_run

    params = flow_run.parameters
    root = str(params.get("root") or (str(params.get("lake", "")).rstrip("/") + "/sessions"))
    when = flow_run.scheduled_start_time or dt.datetime.now(dt.UTC)
    return f"fleet/{root.rstrip('/').rsplit('/', 1)[-1]}/{when.astimezone(dt.UTC):%Y-%m-%dT%H:%MZ}"


def run_tags(camera_id: str, method: str, rig_id: str | None = None) -> list[str]:
    """The tags of a calibration run (module docstring)."""
    return ["fieldcal", f"camera:{camera_id}", f"method:{method}"] + ([f"rig:{rig_id}"] if rig_id else [])


def label_run(session) -> None:
    """Give the running flow run its tags and its name from the validated session."""
    from prefect.client.orchestration import get_client
    from prefect.runtime import flow_run

    rig = getattr(session, "rig", None)
    rig_id = getattr(rig, "rig_id", None) or (rig.get("rig_id") if isinstance(rig, dict) else None)
    tags = sorted(set(flow_run.tags or ()) | set(run_tags(session.camera_id, session.method, rig_id)))
    with get_client(sync_client=True) as client:
        client.update_flow_run(flow_run.id, name=_name(session.camera_id, session.session_id, session.method),
                               tags=tags)


# --------------------------------------------------------------------------------------
# after the commit
# --------------------------------------------------------------------------------------
def reports_folder(camera_id: str, session_id: str, version: str) -> str:
    """Lake-relative folder of a version's report and certificate."""
    return f"reports/{camera_id}/{session_id}/{version}"


def _key(text: str) -> str:
    """An artifact key (lowercase letters, digits, dashes)."""
    return re.sub(r"[^a-z0-9-]+", "-", text.lower()).strip("-")[:100] or "calibration"


def reports_wanted() -> tuple[str, ...]:
    """What a run writes into the lake (:data:`REPORTS_ENV`): ``certificate`` (the default;
    ~0.3-0.5 s), ``all`` (the report too: its plots take 2-9 s, up to 28 s on a loaded 2-core
    machine), ``off``."""
    text = os.environ.get(REPORTS_ENV, "").strip().lower() or "certificate"
    if text not in ("certificate", "all", "off"):
        raise InputError(f"{REPORTS_ENV} must be certificate, all or off, got {text!r}", REPORTS_ENV)
    return {"certificate": ("certificate",), "all": ("certificate", "report"), "off": ()}[text]


def _write_reports(lake: Lake, version: str, folder: str, kinds) -> dict:
    """Write the certificate (and the report) into the lake; ``{kind: url}``."""
    from fieldcal.products.certificate import write_certificate
    from fieldcal.products.report import write_report

    out = {}
    with tempfile.TemporaryDirectory(prefix="fieldcal-publish-") as tmp:
        if "certificate" in kinds:
            write_certificate(lake, version, tmp)
        if "report" in kinds:
            write_report(lake, version, tmp)
        for name in sorted(os.listdir(tmp)):
            lake.storage.write(f"{folder}/{name}", Path(tmp, name).read_bytes())
    for kind in kinds:
        url = lake.uri(f"{folder}/{kind}.html")
        out[kind] = Path(url).as_uri() if lake.is_local else url
    return out


def _markdown(result: dict, cal, recorded: dict, verdict: str) -> str:
    from fieldcal.model.camera import PARAM_NAMES

    doc = cal.document
    lines = [f"# {result['camera_id']} / {result['session_id']}: {result['method']} calibration",
             "", f"version `{result['version']}`, lake `{result['lake']}`", "",
             f"**Verdict: {verdict}** (acceptance criteria of the certificate, change since the previous "
             "calibration included)", ""]
    comp = recorded.get("comparison")
    if comp and "error" not in comp:
        from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM, judge

        lines += [f"Change since `{recorded['previous']}`: "
                  f"{judge(comp, DEFAULT_TOLERANCE_UM, DEFAULT_ALPHA)['verdict']}", ""]
    elif recorded.get("previous") is None:
        lines += ["First calibration of this camera in the lake.", ""]
    lines += ["| parameter | value | sigma |", "|---|---:|---:|"]
    for n in PARAM_NAMES:
        s = doc["sigma"].get(n)
        lines.append(f"| {n} | {doc['parameters'][n]:.9g} | {'fixed' if s is None else format(s, '.3g')} |")
    images = result["images"]
    left = result["left_out"]
    lines += ["", f"Images: {images['total'] - len(left)} of {images['total']} used, {len(left)} left out"]
    lines += [f"- left out `{x.get('image')}`: {one_line(x.get('reason'))}" for x in left]
    lines += ["", f"Report: `fieldcal report {result['version']} --lake LAKE --out DIR` (or "
              f"{REPORTS_ENV}=all: every run writes it beside the certificate)"]
    return "\n".join(lines) + "\n"


def _verdict(recorded: dict) -> str:
    from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM, judge

    acc = recorded.get("assessment") or {}
    comp = recorded.get("comparison")
    flagged = bool(comp and "error" not in comp and judge(comp, DEFAULT_TOLERANCE_UM, DEFAULT_ALPHA)["flagged"])
    if "verdict" not in acc:
        return "not assessed" + (" (FLAGGED: the camera moved)" if flagged else "")
    return "FAIL" if acc["verdict"] == "FAIL" or flagged else "PASS"


def _emit_moved(result: dict, recorded: dict) -> bool:
    from prefect.events import emit_event

    from fieldcal.analysis.compare import DEFAULT_ALPHA, DEFAULT_TOLERANCE_UM, judge

    comp = recorded.get("comparison")
    if not comp or "error" in comp:
        return False
    j = judge(comp, DEFAULT_TOLERANCE_UM, DEFAULT_ALPHA)
    if not j["flagged"]:
        return False
    cam = result["camera_id"]
    emit_event(MOVED_EVENT, resource={"prefect.resource.id": f"fieldcal.camera.{cam}", "prefect.resource.name": cam},
               related=[{"prefect.resource.id": f"fieldcal.version.{result['version']}",
                         "prefect.resource.role": "version"}],
               payload={"camera_id": cam, "session_id": result["session_id"], "version": result["version"],
                        "previous_version": recorded["previous"], "max_change_um": comp["max_um"],
                        "changed": j["changed"], "verdict": j["verdict"], "lake": result["lake"]})
    return True


def _finite(row: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


@task(name="publish", cache_policy=NO_CACHE, persist_result=False)
def publish_version(lake_url: str, storage_options: dict | None, result: dict, outcome) -> dict:
    """After a new version's commit: store its change test and acceptance
    (:func:`fieldcal.products.status.record_commit`, with the calibration still in memory),
    write its report and certificate into the lake, publish the artifacts and, when the
    camera moved, the event (module docstring). Never fails the run: a step that fails is
    logged. Returns ``verdict``, ``moved``, ``links``."""
    from fieldcal.analysis.uncertainty import Calibration
    from fieldcal.products.report import residual_statistics
    from fieldcal.products.status import record_commit

    logger = get_run_logger()
    lake = Lake(lake_url, storage_options)
    version = result["version"]
    doc = dict(outcome.document, version=version)
    names = (outcome.array_attrs.get("covariance") or {}).get("names")
    cal = Calibration.from_document(doc, names, outcome.arrays.get("covariance"))
    recorded = record_commit(lake, version, cal, outcome.residuals)
    verdict = _verdict(recorded)
    key = _key(result["camera_id"])
    links = {}
    try:
        kinds = reports_wanted()
        if kinds:
            links = _write_reports(lake, version, reports_folder(result["camera_id"], result["session_id"], version),
                                   kinds)
    except (InputError, LakeError, OSError) as e:
        logger.warning(f"no report or certificate in the lake: {one_line(e)}")
    create_markdown_artifact(_markdown(result, cal, recorded, verdict), key=f"{key}-summary",
                             description=f"{result['camera_id']} / {result['session_id']}: {verdict}")
    create_table_artifact([_finite(r) for r in residual_statistics(outcome.residuals)], key=f"{key}-residuals",
                          description="residual statistics per image [px]")
    for kind, url in links.items():
        create_link_artifact(url, link_text=f"{kind} of {version}", key=f"{key}-{kind}",
                             description=f"{result['camera_id']} / {result['session_id']}: the {kind}")
    moved = _emit_moved(result, recorded)
    if moved:
        logger.warning(f"{result['camera_id']}: the change test flags it against {recorded['previous']} "
                       f"(event {MOVED_EVENT})")
    return {"verdict": verdict, "moved": moved, "links": links}
