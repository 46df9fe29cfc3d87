"""The whole solver path a user waits for, against OpenCV and mrcal, in one interleaved run.

Sessions (observation-only, written once into ``--work``): ``paper_field(seed=0)`` (72
images, ~1900 targets, ~14 000 points, 5 mm survey noise) and ``wide_field(seed=0)`` (24
images, ~3 200 points). Candidates, timed round robin in one process tree:

- **fieldcal** (this checkout): :func:`fieldcal.pipeline.prepare` + :func:`fieldcal.pipeline.solve`
  (reading the session, initial values, adjustment, blunder rounds, parameter selection,
  covariance, the document), targets fixed and targets adjusted; and the same from a
  ``FieldData`` already in memory (:func:`fieldcal.field.adjustment.adjust_field`), which
  is what the peers are given.
- **fieldcal before** (``--before DIR``: another checkout, e.g. the ``layout`` commit
  unpacked with ``git archive``), the same calls in a worker process on this venv.
- **OpenCV** ``cv2.calibrateCamera`` (its own per-view initial poses included) from the
  nominal focal length, principal point at the centre, no distortion (what fieldcal is
  given), ``CALIB_USE_INTRINSIC_GUESS`` (needed for a non-planar field), k1, k2, p1, p2,
  k3; criteria ``COUNT + EPS, 100, 1e-10``. Per-view float32 arrays prepared outside.
- **mrcal** 2.2 (Debian's ``python3-mrcal`` on ``/usr/bin/python3``, a persistent worker
  process): per-image ``cv2.solvePnP`` with the nominal camera as the seed (mrcal has no
  initialiser for a surveyed point field) and ``mrcal.optimize`` with ``LENSMODEL_OPENCV8``,
  all points fixed, mrcal's outlier rejection and regularisation on (its defaults); the
  seed is inside the time.

Every worker times itself (``time.perf_counter`` around the call); the rounds alternate
candidates so that the machine's load falls on all alike. Reported: best and median
time, ratio to OpenCV and to mrcal (best/best), and the results (RMS, f, xp, yp, points
rejected, parameters held fixed).

Run::

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/bench_whole_solve.py --repeat 7 \\
        --before /tmp/fieldcal-layout          # git archive layout | tar -x -C /tmp/fieldcal-layout
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

SESSIONS = ("paper", "wide")
FP = "sha256:" + "0" * 64


# ------------------------------------------------------------------------------------------
# workers: each reads one JSON request per line and answers one JSON line
# ------------------------------------------------------------------------------------------
def _fieldcal_run(req, cache):
    """prepare + solve of a session folder, or adjust_field on data already read."""
    from fieldcal import pipeline
    from fieldcal.field.adjustment import AdjustmentOptions, adjust_field
    from fieldcal.session.loader import field_data_from_observations

    folder, adjusted = Path(req["folder"]), bool(req["targets_adjusted"])
    if req["what"] == "pipeline":
        t, c = time.perf_counter(), time.process_time()
        prep = pipeline.prepare(folder, pipeline.Settings(targets_adjusted=adjusted))
        res = pipeline.solve(prep, {}, fingerprint_=FP).result
        dt, dc = time.perf_counter() - t, time.process_time() - c
    else:
        if str(folder) not in cache:
            cache[str(folder)] = field_data_from_observations(pipeline.prepare(folder).session)
        data = cache[str(folder)]
        t, c = time.perf_counter(), time.process_time()
        res = adjust_field(data, AdjustmentOptions(targets_adjusted=adjusted))
        dt, dc = time.perf_counter() - t, time.process_time() - c
    st = res.stats()
    return {"t": dt, "cpu": dc, "rms_px": st["rmse_px"], "f_mm": float(res.params[0]), "xp_mm": float(res.params[1]),
            "yp_mm": float(res.params[2]), "sigma_f_mm": res.sigma.get("f_mm"),
            "n_rejected": st["n_rejected"], "fixed": sorted(res.fixed_parameters),
            "iterations": st.get("iterations_total"), "n_obs": st["n_observations"]}


def _mrcal_run(req, cache):
    """Seed by cv2.solvePnP with the nominal camera, then mrcal.optimize (OPENCV8, points fixed)."""
    import cv2
    import mrcal

    key = req["npz"]
    if key not in cache:
        cache[key] = dict(np.load(key))
    a = cache[key]
    W, H, pix = int(a["size"][0]), int(a["size"][1]), float(a["pixel_mm"])
    f_px = float(a["nominal_f_mm"]) / pix
    t, c = time.perf_counter(), time.process_time()
    K = np.array([[f_px, 0, (W - 1) / 2.0], [0, f_px, (H - 1) / 2.0], [0, 0, 1.0]])
    img, tgt, uv, X = a["image"], a["target"], a["uv"], a["xyz"]
    n_img = int(img.max()) + 1
    rt = np.zeros((n_img, 6))
    for i in range(n_img):
        k = img == i
        ok, rvec, tvec = cv2.solvePnP(X[tgt[k]], uv[k], K, None)
        rt[i, :3], rt[i, 3:] = rvec.ravel(), tvec.ravel()
    intr = np.zeros((1, 12))
    intr[0, :4] = (f_px, f_px, (W - 1) / 2.0, (H - 1) / 2.0)
    obs = np.column_stack([uv, np.ones(len(uv))])
    idx = np.column_stack([tgt, np.zeros(len(tgt)), img]).astype(np.int32)
    points = X.astype(float).copy()
    dist = np.linalg.norm(X[tgt] - X.mean(axis=0), axis=1).max()
    stats = mrcal.optimize(intr, rt, None, points, None, None, obs, idx,
                           lensmodel="LENSMODEL_OPENCV8", imagersizes=np.array([[W, H]], np.int32),
                           Npoints_fixed=len(points), do_optimize_frames=False,
                           point_min_range=0.1, point_max_range=10.0 * (dist + 100.0),
                           do_apply_outlier_rejection=True, verbose=False)
    dt, dc = time.perf_counter() - t, time.process_time() - c
    fx, fy, cx, cy = intr[0, :4]
    # RMS per point (CONTRACT section 4), from mrcal's own projection of the fixed points
    q = mrcal.project(mrcal.transform_point_rt(rt[img], X[tgt]), "LENSMODEL_OPENCV8", intr[0])
    rms = float(np.sqrt(np.mean(np.sum((q - uv) ** 2, axis=1))))
    return {"t": dt, "cpu": dc, "rms_px": rms, "f_mm": fx * pix,
            "xp_mm": (cx - (W - 1) / 2.0) * pix, "yp_mm": -(cy - (H - 1) / 2.0) * pix,
            "n_rejected": int(stats.get("Noutliers", 0)), "fixed": [], "iterations": None,
            "sigma_f_mm": None, "n_obs": int(len(uv))}


def worker(kind: str) -> None:
    run = {"fieldcal": _fieldcal_run, "mrcal": _mrcal_run}[kind]
    cache: dict = {}
    for line in sys.stdin:
        req = json.loads(line)
        try:
            out = run(req, cache)
        except Exception as err:  # noqa: BLE001 - reported in the table
            out = {"t": float("nan"), "cpu": float("nan"), "error": f"{type(err).__name__}: {err}"}
        print(json.dumps(out), flush=True)


class Worker:
    """A persistent worker process (``python bench_whole_solve.py --worker KIND``)."""

    def __init__(self, python: str, kind: str, pythonpath: str | None = None):
        env = dict(os.environ)
        if pythonpath is not None:
            env["PYTHONPATH"] = pythonpath
        self.p = subprocess.Popen([python, __file__, "--worker", kind], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, env=env,
                                  cwd=pythonpath or str(Path(__file__).resolve().parents[1]))

    def __call__(self, req: dict) -> dict:
        self.p.stdin.write(json.dumps(req) + "\n")
        self.p.stdin.flush()
        return json.loads(self.p.stdout.readline())

    def close(self):
        self.p.stdin.close()
        self.p.wait(timeout=60)


# ------------------------------------------------------------------------------------------
# the sessions and OpenCV (in this process)
# ------------------------------------------------------------------------------------------
def write_sessions(work: Path) -> dict:
    from fieldcal.synthetic.field import paper_field, wide_field
    from fieldcal.synthetic.session_writer import write_field_session

    out = {}
    for name, make in (("paper", paper_field), ("wide", wide_field)):
        sf = make(seed=0)
        folder = work / name
        if not (folder / "observations.csv").exists():
            write_field_session(folder, sf, images=False, observations_csv=True)
        d = sf.data
        npz = work / f"{name}.npz"
        np.savez(npz, image=d.obs.image, target=d.obs.target, uv=d.obs.uv_px, xyz=d.targets.xyz_m,
                 size=np.array([d.sensor.width_px, d.sensor.height_px]), pixel_mm=d.sensor.pixel_mm,
                 nominal_f_mm=d.nominal_focal_mm)
        out[name] = {"folder": str(folder), "npz": str(npz), "sf": sf}
    return out


def opencv_case(sf):
    import cv2

    d = sf.data
    s = d.sensor
    views = [np.flatnonzero(d.obs.image == i) for i in range(len(d.images))]
    obj = [d.targets.xyz_m[d.obs.target[k]].astype(np.float32) for k in views]
    img = [d.obs.uv_px[k].astype(np.float32) for k in views]
    f_px = d.nominal_focal_mm / s.pixel_mm
    K0 = np.array([[f_px, 0, (s.width_px - 1) / 2.0], [0, f_px, (s.height_px - 1) / 2.0], [0, 0, 1.0]])
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-10)

    def run(_req):
        t, c = time.perf_counter(), time.process_time()
        rms, K, dist, _, _ = cv2.calibrateCamera(obj, img, (s.width_px, s.height_px), K0.copy(), np.zeros(5),
                                                 flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
        dt, dc = time.perf_counter() - t, time.process_time() - c
        px = s.pixel_mm
        return {"t": dt, "cpu": dc, "rms_px": float(rms), "f_mm": K[0, 0] * px,
                "xp_mm": (K[0, 2] - (s.width_px - 1) / 2.0) * px, "yp_mm": -(K[1, 2] - (s.height_px - 1) / 2.0) * px,
                "n_rejected": 0, "fixed": [], "iterations": None, "sigma_f_mm": None, "n_obs": len(d.obs)}
    return run


# ------------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", choices=("fieldcal", "mrcal"))
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--work", default="/tmp/fieldcal-bench-whole-solve")
    ap.add_argument("--before", default=None, help="another fieldcal checkout to time as 'before'")
    ap.add_argument("--mrcal-python", default="/usr/bin/python3")
    ap.add_argument("--sessions", default=",".join(SESSIONS))
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker)
        return 0
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    sessions = write_sessions(work)
    here = str(Path(__file__).resolve().parents[1])
    cands = {"fieldcal": Worker(sys.executable, "fieldcal", here)}
    if args.before:
        cands["before"] = Worker(sys.executable, "fieldcal", str(Path(args.before).resolve()))
    cands["mrcal"] = Worker(args.mrcal_python, "mrcal")
    cases = []   # (session, label, targets, callable, request)
    for name in args.sessions.split(","):
        s = sessions[name]
        for adjusted in (False, True):
            tg = "adjusted" if adjusted else "fixed"
            for who in [w for w in ("before", "fieldcal") if w in cands]:
                for what in ("pipeline", "adjust_field"):
                    call = "prepare + solve" if what == "pipeline" else "adjust_field"
                    label = f"fieldcal{' before' if who == 'before' else ''} {call}"
                    cases.append((name, label, tg, cands[who], {"folder": s["folder"], "targets_adjusted": adjusted,
                                                                 "what": what}))
        cases.append((name, "OpenCV calibrateCamera", "fixed", opencv_case(s["sf"]), {}))
        cases.append((name, "mrcal 2.2 (PnP seed + optimize, OPENCV8)", "fixed", cands["mrcal"], {"npz": s["npz"]}))
    for c in cases:                      # warm-up: imports, Numba's cache, page faults
        c[3](c[4])
    times = {i: [] for i in range(len(cases))}
    cpus = {i: [] for i in range(len(cases))}
    last = {}
    for _ in range(args.repeat):
        for i, c in enumerate(cases):
            out = c[3](c[4])
            times[i].append(out["t"])
            cpus[i].append(out["cpu"])
            last[i] = out
    for w in cands.values():
        w.close()
    print_table(cases, times, cpus, last, args)
    return 0


def print_table(cases, times, cpus, last, args):
    import platform

    OCV, MR = "OpenCV calibrateCamera", "mrcal 2.2 (PnP seed + optimize, OPENCV8)"
    best = {(c[0], c[1]): float(np.nanmin(times[i])) for i, c in enumerate(cases)}
    bcpu = {(c[0], c[1]): float(np.nanmin(cpus[i])) for i, c in enumerate(cases)}
    print(f"# whole solve, {time.strftime('%Y-%m-%d %H:%M')}, {platform.node()}, "
          f"load {os.getloadavg()[0]:.2f}, repeat {args.repeat}, OPENBLAS_NUM_THREADS="
          f"{os.environ.get('OPENBLAS_NUM_THREADS')}\n")
    print("Ratios are best/best: wall time, and in brackets CPU time of the call (less sensitive "
          "to the load of other jobs).\n")
    print("| session | candidate | targets | wall [s], best (median) | CPU [s], best | / OpenCV | / mrcal | "
          "RMS [px] | f [mm] | xp [mm] | yp [mm] | rejected | held fixed |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for i, (name, label, tg, _, _) in enumerate(cases):
        t, o = np.array(times[i]), last[i]
        if "error" in o:
            print(f"| {name} | {label} | {tg} | error: {o['error'][:80]} | | | | | | | | | |")
            continue
        b, bc = float(np.nanmin(t)), float(np.nanmin(cpus[i]))
        ocv, mr = best[(name, OCV)], best[(name, MR)]
        cocv, cmr = bcpu[(name, OCV)], bcpu[(name, MR)]
        print(f"| {name} | {label} | {tg} | {b:.3f} ({np.nanmedian(t):.3f}) | {bc:.3f} | "
              f"{b / ocv:.2f} ({bc / cocv:.2f}) | {b / mr:.2f} ({bc / cmr:.2f}) | "
              f"{o['rms_px']:.4f} | {o['f_mm']:.4f} | {o['xp_mm']:.4f} | "
              f"{o['yp_mm']:.4f} | {o['n_rejected']} | {', '.join(o['fixed'])} |")


if __name__ == "__main__":
    raise SystemExit(main())
