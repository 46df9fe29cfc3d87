"""``fieldcal demo``: synth -> run -> show -> history on small synthetic sessions, next to the truth.

Writes into ``OUT/`` (default ``demo-out/``):

- ``sessions/lab-canon5d2``: a goniometer session (Canon 5D Mark II-like, 24 mm, frames at
  a quarter of the pixel resolution over the same sensor: 180 frames of 1404 x 936 px);
- ``sessions/field-paper``: an observation-only field session (the field paper's geometry:
  72 images, ~2000 targets, 0.1 px image noise, 5 mm survey noise);
- ``sessions/field-images``: a field session of rendered images (coded targets), when the
  identification step (``fieldcal.field.from_images``) is available;
- ``lake/``: the lake the flows commit into.

Sessions already written by an earlier demo are reused, so a second ``make demo`` shows
the reruns being recognised (no image is read, no version is added, and no Prefect server
is needed: the reruns are answered from the lake).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import sys
import time
from pathlib import Path

__all__ = ["run_demo", "SESSIONS"]

SESSIONS = (
    ("lab-canon5d2", dict(method="goniometer", scenario="canon5d2", seed=1, camera_id="canon5d2-demo")),
    ("field-paper", dict(method="field", scenario="paper", seed=2, camera_id="ixu150-demo")),
)
IMAGE_SESSION = ("field-images", dict(method="field", scenario="paper", seed=3, images=True, scale=0.25,
                                      n_images=12, camera_id="ixu150-images-demo"))


def _identification_available() -> bool:
    return importlib.util.find_spec("fieldcal.field.from_images") is not None


def _truth_table(doc: dict, truth: dict) -> list[str]:
    """Calibrated vs true parameters (and the method's noise-free values for the goniometer)."""
    from fieldcal.model.camera import PARAM_NAMES

    ref = truth.get("noise_free")
    head = f"  {'parameter':9s} {'calibrated':>14s} {'sigma':>10s} {'truth':>14s} {'(cal-truth)/sigma':>18s}"
    if ref:
        head += f" {'noise-free':>14s} {'(cal-nf)/sigma':>15s}"
    lines = [head]
    for n in PARAM_NAMES:
        cal, s, tru = doc["parameters"][n], doc["sigma"][n], truth["parameters"][n]
        if s is None and cal == 0.0 and tru == 0.0:
            continue
        z = "" if not s else f"{(cal - tru) / s:+.2f}"
        line = f"  {n:9s} {cal:14.7g} {'' if s is None else format(s, '.2e'):>10s} {tru:14.7g} {z:>18s}"
        if ref:
            zr = "" if not s else f"{(cal - ref[n]) / s:+.2f}"
            line += f" {ref[n]:14.7g} {zr:>15s}"
        lines.append(line)
    return lines


def _synthetic(folder: Path, spec: dict, say) -> dict:
    """Write a demo session (or reuse the one an earlier demo wrote); returns its truth."""
    from flows.synth import write_synthetic

    t = time.perf_counter()
    if (folder / "truth.json").is_file():
        say(f"   {folder.name}: reused ({folder})")
        return json.loads((folder / "truth.json").read_text())
    truth = write_synthetic(folder, **spec)
    say(f"   {folder.name}: written in {time.perf_counter() - t:.1f} s ({folder})")
    return truth


def _unchanged(folder: Path, lake) -> dict | None:
    """The result of a rerun answered from the lake (the inputs are calibrated), else None."""
    from fieldcal import batch, pipeline
    from flows.hashcache import known_hashes

    prepared = pipeline.prepare(folder)
    version = batch.plan_session(prepared, lake, known_hashes(prepared), find_cached=False).unchanged
    if version is None:
        return None
    n = len(prepared.to_measure)
    return {"status": "unchanged", "version": version, "left_out": [],
            "images": {"measured": 0, "cached": n, "bad": 0}}


def _run_all(out: Path, sessions, lake_path: Path, n_workers, dask_address, note_stream, api, say) -> dict:
    """``fieldcal run`` of every demo session: from the lake when unchanged, else the flow."""
    from fieldcal import progress
    from fieldcal.lake.store import Lake
    from flows.cli_common import is_tty, progress_sink

    results, todo = {}, []
    for name, _ in sessions:
        t = time.perf_counter()
        r = _unchanged(out / "sessions" / name, Lake(lake_path))
        if r is None:
            todo.append(name)
        else:
            results[name] = r
            _say_result(say, name, r, time.perf_counter() - t)
    if not todo:
        return results
    note = (lambda s: progress.emit("note", text=s)) if is_tty(note_stream) else None
    with progress.listening(progress_sink(note_stream)), (api(note=note) if api else contextlib.nullcontext()):
        from flows import cluster
        from flows.calibrate import calibrate_session

        for name in todo:
            t = time.perf_counter()
            runner = cluster.task_runner(dask_address, n_workers)
            r = calibrate_session.with_options(task_runner=runner)(str(out / "sessions" / name), str(lake_path))
            results[name] = r
            _say_result(say, name, r, time.perf_counter() - t)
    return results


def _say_result(say, name: str, r: dict, seconds: float) -> None:
    img = r["images"]
    say(f"   {name}: {r['status']} {r['version']} in {seconds:.1f} s "
        f"(images: {img['measured']} measured, {img['cached']} cached, {img['bad']} bad)")
    for item in r["left_out"]:
        say(f"      left out {item.get('image')}: {item.get('reason')}")


def run_demo(out="demo-out", *, n_workers: int = 2, dask_address: str | None = None, with_images: str = "auto",
             stream=None, note_stream=None, api=None) -> int:
    """Run the demo (module docstring); prints to ``stream``, returns the exit status.

    ``api`` is a context manager factory that provides a Prefect API
    (:func:`flows.server.prefect_api`); ``with_images`` is ``"auto"``, ``"yes"`` or ``"no"``.
    """
    from fieldcal import progress
    from fieldcal.lake import history
    from fieldcal.lake.store import Lake
    from flows.cli_common import describe, progress_sink

    stream = stream or sys.stdout
    note_stream = note_stream or sys.stderr
    out = Path(out)
    lake_path = out / "lake"
    t_all = time.perf_counter()

    def say(text=""):
        print(text, file=stream, flush=True)

    sessions = list(SESSIONS)
    if with_images == "yes" or (with_images == "auto" and _identification_available()):
        sessions.append(IMAGE_SESSION)
    elif with_images == "auto":
        say("(no field session of rendered images: fieldcal.field.from_images, the identification step, "
            "is not available yet)")

    say(f"== 1. synthetic sessions in {out / 'sessions'}")
    truths = {}
    with progress.listening(progress_sink(note_stream)):
        for name, spec in sessions:
            truths[name] = _synthetic(out / "sessions" / name, spec, say)

    say(f"== 2. fieldcal run (Prefect flow, Dask: {dask_address or f'local cluster of {n_workers} workers'})")
    results = _run_all(out, sessions, lake_path, n_workers, dask_address, note_stream, api, say)
    lake = Lake(lake_path)
    say("== 3. fieldcal show")
    for name, _ in sessions:
        doc = lake.load_document(results[name]["version"])
        say(f"-- {name}")
        for line in describe(doc):
            say("   " + line)
        say("   calibration next to the truth it was made from:")
        if truths[name].get("noise_free"):
            say("   (goniometer: the minimum-sum-of-squares principal point and distance are conventions of the")
            say("    method, far from the lens design's in sigmas; compare them with the method's own values on")
            say("    noise-free data of the same set-up, the last two columns)")
        for line in _truth_table(doc, truths[name]):
            say("   " + line)

    say("== 4. fieldcal history (latest calibration of every camera)")
    table = history.fleet(lake).select(["camera_id", "session_id", "version", "method", "f_mm", "sigma_f_mm",
                                        "xp_mm", "yp_mm", "rmse_px", "sigma_fit_px"])
    for line in history.to_text(table).splitlines():
        say("   " + line)
    say(f"== done in {time.perf_counter() - t_all:.1f} s; lake: {lake_path} (try: fieldcal history --lake "
        f"{lake_path} --sql 'SELECT camera_id, version, f_mm FROM catalog')")
    return 0
